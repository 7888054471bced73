#!/usr/bin/env python3
# benchmarks/whiteness_calibration.py: false-alarm rates of the whiteness verdicts.
"""
How often each whiteness verdict calls truly white residuals not white, against its level.

White residuals: independent standard normal values (a consistent Kalman filter's
whitened innovations). Each seed is one run; the verdicts measured:

- ``node``: the node's per-window verdict (``InnovationMonitor.health`` of each window of
  50 residuals, NIS and whiteness; level ``ALPHA`` = 1e-3), one and two outputs;
- ``eval``: ``observer-eval``'s verdict on a run (``sequence_health``, windows of 50,
  ``run_rule``: the level it states, ``false_alarm``);
- ``tune``: ``observer-tune``'s verdict on a run (``WindowWhiteness``, whiteness only,
  the same rule).

Printed per verdict: runs (or windows), false alarms, the measured rate with its 95 %
(Clopper-Pearson) interval, the stated level and the two-sided binomial test of the
count against it; ``consistent`` when that test's p-value is at least 1e-3.

Run: ``.venv/bin/python benchmarks/whiteness_calibration.py [--seeds 5000]
[--node-seeds 200] [--samples 10000] [--only node|runs]`` (about an hour of CPU).

"""

import argparse
import sys

import numpy as np
from observer_ros.core.innovation import ALPHA, InnovationMonitor, sequence_health, WINDOW
from observer_ros.core.whiteness import WindowWhiteness
from scipy.stats import binomtest


def _line(name, trials, alarms, level):
    test = binomtest(int(alarms), int(trials), level)
    ci = test.proportion_ci(0.95)
    inside = test.pvalue >= 1e-3
    print(f'{name}: {alarms} false alarms in {trials}: rate {alarms / trials:.3g} '
          f'[95 % {ci.low:.3g} .. {ci.high:.3g}], stated level {level:.3g} (binomial test '
          f'p {test.pvalue:.2g}): {"consistent" if inside else "NOT consistent"}')
    sys.stdout.flush()
    return inside


def main(argv=None):
    """Measure each verdict's false-alarm rate over the seeds."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    ap.add_argument('--seeds', type=int, default=20_000,
                    help='runs per run verdict (default 20000: a level near 0.006 gives '
                    'about 120 false alarms)')
    ap.add_argument('--only', choices=['node', 'runs'], help='one part only')
    ap.add_argument('--node-seeds', type=int, default=200, help='runs of the node monitor')
    ap.add_argument('--samples', type=int, default=10_000, help='residuals per run')
    ap.add_argument('--node-windows', type=int, default=250,
                    help='windows per seed judged by the node monitor')
    args = ap.parse_args(argv)
    ok = True
    for p in (1, 2) if args.only != 'runs' else ():
        alarms = trials = 0
        for seed in range(args.node_seeds):
            rng = np.random.default_rng(seed)
            mon = InnovationMonitor([('s', [1.0] * p)], kalman=True)
            E = rng.standard_normal((args.node_windows * WINDOW, p))
            S = np.eye(p)
            for w in range(args.node_windows):
                mon.restart()
                for row in E[w * WINDOW:(w + 1) * WINDOW]:
                    mon.add('s', row, S)
                alarms += not mon.health('s').consistent
                trials += 1
        ok &= _line(f'node window verdict, {p} output(s)', trials, alarms, ALPHA)
    if args.only == 'node':
        return 0 if ok else 1
    for p in (1, 2):
        alarms = 0
        levels = []
        for seed in range(args.seeds):
            E = np.random.default_rng(10_000 + seed).standard_normal((args.samples, p))
            h = sequence_health('s', E, True)
            alarms += not h['consistent']
            levels.append(h['false_alarm'])
        ok &= _line(f'observer-eval run verdict, {p} output(s), {args.samples} residuals',
                    args.seeds, alarms, float(np.mean(levels)))
    alarms = 0
    levels = []
    for seed in range(args.seeds):
        E = np.random.default_rng(20_000 + seed).standard_normal((args.samples, 1))
        white = WindowWhiteness(1, WINDOW, ALPHA)
        white.add(E)
        v = white.verdicts()[0]
        alarms += not v['white']
        levels.append(v['level'])
    ok &= _line(f'observer-tune run verdict, {args.samples} innovations', args.seeds, alarms,
                float(np.mean(levels)))
    return 0 if ok else 1


if __name__ == '__main__':
    raise SystemExit(main())
