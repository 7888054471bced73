#!/usr/bin/env python3
# benchmarks/tune_bars.py: observer-tune on bags of an independent writer, over seeds.
"""
Noise identification on closed-loop bags with lost messages and jittered stamps.

The bags come from ``test/irregular_bags.py`` (numpy, scipy and rosbags only: nothing of
observer_ros), 5 % of each sensor's messages lost and stamps jittered by +-20 % of the
step, known noise. For each system and seed: ``observer-tune`` (identification only),
then ``observer-eval`` of the tuned vehicle file beside the Kalman filter of the true
covariances. Printed per system: Rd / true, the fraction of Qd entries within their
stated +-2 sigma, the RMSE of the tuned filter / the true-covariance one (median and
worst; and the steady-state ratio that one run's scatters around), and how often
``observer-eval`` called the true-covariance filter WARN against the level it states.
With ``--fresh K`` each seed's tuned filter is also scored on K more runs of the writer
(seeds ``1000 * seed + 1..K``, the same system) beside the true-covariance filter: the
mean of those ratios is the filter's own loss, apart from the scatter of one run.

Run: ``.venv/bin/python benchmarks/tune_bars.py [--seeds 10] [--steps 10000]
[--systems chain,submarine,submarine_input,chain3,spring] [--fresh K] [--out DIR]``.
``chain3`` is three masses in a row (``three_mass_chain`` of test/irregular_bags.py),
``spring`` a mass on a spring with one position sensor and noise on both states
(``mass_spring``): systems no other file describes.

"""

import argparse
import json
from pathlib import Path
import shutil
import sys
import tempfile
import time

import numpy as np
import scipy.linalg

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / 'test'))

import irregular_bags as ib  # noqa: E402,I100
from observer_ros.evaluation.evaluator import evaluate_bag  # noqa: E402
from observer_ros.tuning.tune import tune  # noqa: E402


def _floats(values):
    return '[' + ', '.join(repr(float(x)) for x in np.ravel(values)) + ']'


def steady_rms(sysm, Qc, R, Qc_true, R_true):
    """
    Return the steady-state RMS error of the Kalman filter of (Qc, R) under the true noise.

    At the nominal step with every measurement present: the filter's gain from the
    discrete Riccati equation of (Qc, R), its error covariance under (Qc_true, R_true)
    from a Lyapunov equation (the expected figure that one run's RMSE scatters around).

    """
    n = sysm.A.shape[0]

    def discrete(q):
        M = np.zeros((2 * n, 2 * n))
        M[:n, :n], M[n:, n:] = -sysm.A, sysm.A.T
        M[:n, n:] = sysm.Gw @ np.diag(q) @ sysm.Gw.T
        F = scipy.linalg.expm(M * sysm.h)
        Ad = F[n:, n:].T
        Qd = Ad @ F[:n, n:]
        return Ad, 0.5 * (Qd + Qd.T)
    Ad, Qd = discrete(Qc)
    C = sysm.C
    P = scipy.linalg.solve_discrete_are(Ad.T, C.T, Qd, np.diag(R))
    K = P @ C.T @ np.linalg.inv(C @ P @ C.T + np.diag(R))
    _, Qd_true = discrete(Qc_true)
    J = np.eye(n) - K @ C
    W = J @ Qd_true @ J.T + K @ np.diag(R_true) @ K.T
    return float(np.sqrt(np.trace(scipy.linalg.solve_discrete_lyapunov(J @ Ad, W))))


def system(name, root):
    """Return (System, vehicle file, tune keywords, true Qc diagonal, true R diagonal)."""
    if name == 'chain3':
        Qc = [0.001, 0.002, 0.004]
        s = ib.three_mass_chain(Qc)
        return (s, ib.vehicle_file(s, 'three_mass_chain', root / 'three_mass_chain.yaml'),
                {'states': ['v1', 'v2', 'v3']}, Qc, [0.002 ** 2, 0.004 ** 2])
    if name == 'spring':
        Qc = [2e-6, 4e-2]
        s = ib.mass_spring(Qc)
        return (s, ib.vehicle_file(s, 'mass_spring', root / 'mass_spring.yaml'),
                {'states': ['x', 'v']}, Qc, [1e-6])
    if name == 'chain':
        Qc = [0.0016, 0.0036]
        return (ib.spring_chain(Qc), ib.chain_vehicle(root / 'spring_chain.yaml'),
                {'states': ['v1', 'v2']}, Qc, [0.002 ** 2, 0.003 ** 2])
    if name == 'submarine':
        Qc = [1e-5, 4e-4]
        return (ib.submarine(Qc), ROOT / 'config' / 'submarine.yaml',
                {'states': ['theta', 'w']}, Qc, [1e-6])
    if name == 'submarine_input':
        Qc = [4e-4]
        s = ib.submarine(Qc)
        s.Gw = s.B.copy()
        return s, ROOT / 'config' / 'submarine.yaml', {'input_noise': True}, Qc, [1e-6]
    raise SystemExit(f'unknown system {name!r}')


def rmse_ratio(bag, vehicle, true, tuned):
    """Return the RMSE of the tuned file's filter over that of the true covariances."""
    ev = evaluate_bag(bag, vehicle, {'truekf': true}, compare={'tuned': tuned},
                      include_live=False, include_design=False)
    return ev, ev.variants['tuned'].summary['error_rms'] / \
        ev.variants['truekf'].summary['error_rms']


def one(name, seed, steps, root, passes=None, fresh=0):
    """Return the figures of one system and seed."""
    sysm, vehicle, kw, Qc, R = system(name, root)
    bag = root / f'{name}_{seed}'
    if not bag.exists():
        ib.write(bag, sysm, ib.simulate(sysm, steps, seed))
    out = root / f'{name}_{seed}_tune'
    shutil.rmtree(out, ignore_errors=True)
    start = time.perf_counter()
    if passes:
        kw['passes'] = passes
    res = tune([bag], vehicle, out, search='none', plots=False, **kw)
    seconds = time.perf_counter() - start
    ident = res.identification
    entries = ident.result.entries()
    q = [(v, s, t) for (k, _, v, s), t in zip([e for e in entries if e[0] == 'Q'], Qc)]
    r = [v / t for (k, _, v, s), t in zip([e for e in entries if e[0] == 'R'], R)]
    true = ['observer.type:=kalman', f'observer.Qd:={_floats(np.diag(Qc))}',
            f'observer.Rd:={_floats(np.diag(R))}', f'observer.Bd:={_floats(sysm.Gw)}']
    ev, ratio = rmse_ratio(bag, vehicle, true, res.vehicle_file)
    others = []
    for j in range(1, fresh + 1):
        other = root / f'{name}_{seed}_fresh_{j}'
        if not other.exists():
            ib.write(other, sysm, ib.simulate(sysm, steps, 1000 * seed + j))
        others.append(rmse_ratio(other, vehicle, true, res.vehicle_file)[1])
    written = np.diag(ident.file_Q)                 # the tuned file's Qd
    expected = steady_rms(sysm, written, np.diag(ident.result.R), Qc, R) / \
        steady_rms(sysm, Qc, R, Qc, R)
    health = ev.variants['truekf'].sensors
    return {'seed': seed, 'seconds': seconds, 'lags': [p.lags for p in ident.passes],
            'Rd_ratio': r,
            'Qd': [{'value': v, 'std': s, 'true': t, 'inside': abs(v - t) <= 2 * s}
                   for v, s, t in q],
            'rmse_ratio': ratio, 'fresh_ratios': others,
            'expected_rmse_ratio': expected,
            'states_ratio': {st: ev.variants['tuned'].states[st]['rmse'] /
                             ev.variants['truekf'].states[st]['rmse']
                             for st in ev.variants['truekf'].states},
            'truekf_warn': [not h['consistent'] for h in health.values()],
            'truekf_level': [h['false_alarm'] for h in health.values()],
            'warnings': ident.warnings}


def main(argv=None):
    """Run the systems over the seeds; print the summary."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    ap.add_argument('--seeds', type=int, default=10)
    ap.add_argument('--first-seed', type=int, default=1)
    ap.add_argument('--steps', type=int, default=10_000)
    ap.add_argument('--systems', default='chain,submarine,submarine_input')
    ap.add_argument('--passes', type=int, help='observer-tune --passes (default its own)')
    ap.add_argument('--fresh', type=int, default=0, metavar='K',
                    help="each seed's tuned filter also on K more runs of the writer")
    ap.add_argument('--out', help='keep the bags here (default: a temporary folder)')
    ap.add_argument('--json', help='write every figure to this file')
    args = ap.parse_args(argv)
    root = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix='tune_bars_'))
    root.mkdir(parents=True, exist_ok=True)
    figures = {}
    for name in args.systems.split(','):
        rows = [one(name, seed, args.steps, root, args.passes, args.fresh)
                for seed in range(args.first_seed, args.first_seed + args.seeds)]
        figures[name] = rows
        rd = [x for row in rows for x in row['Rd_ratio']]
        inside = [e['inside'] for row in rows for e in row['Qd']]
        ratio = [row['rmse_ratio'] for row in rows]
        warn = [w for row in rows for w in row['truekf_warn']]
        level = [v for row in rows for v in row['truekf_level']]
        print(f'{name}: {len(rows)} seeds of {args.steps} samples')
        print(f'  Rd / true: {min(rd):.3f} .. {max(rd):.3f}')
        print(f'  Qd entries within +-2 sigma: {sum(inside)} of {len(inside)} '
              f'({sum(inside) / len(inside):.0%})')
        print(f'  RMSE tuned / true covariances: median {np.median(ratio):.4f}, '
              f'{min(ratio):.4f} .. {max(ratio):.4f}')
        expected = [row['expected_rmse_ratio'] for row in rows]
        print(f'  steady-state RMS error tuned / true covariances (Lyapunov, nominal step): '
              f'{min(expected):.4f} .. {max(expected):.4f}')
        if args.fresh:
            means = [float(np.mean(row['fresh_ratios'])) for row in rows]
            every = [x for row in rows for x in row['fresh_ratios']]
            print(f'  each tuned filter on {args.fresh} more runs: mean ratio '
                  f'{min(means):.4f} .. {max(means):.4f} over the seeds (one run '
                  f'{min(every):.4f} .. {max(every):.4f})')
        print(f'  true-covariance filter WARN: {sum(warn)} of {len(warn)} sensor verdicts '
              f'(stated false-alarm probability {np.mean(level):.3g} each)')
        print(f'  identification seconds: median {np.median([r["seconds"] for r in rows]):.1f}')
        sys.stdout.flush()
    if args.json:
        Path(args.json).write_text(json.dumps(figures, indent=1, default=float))
    if not args.out:
        shutil.rmtree(root, ignore_errors=True)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
