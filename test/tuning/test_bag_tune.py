# test/tuning/test_bag_tune.py: observer-tune (ALS noise identification, gain search, tuned file).
"""
Noise identification and tuning from bags with known noise.

The bags are closed-loop runs simulated here with measurement noise of the vehicle's
``noise_std`` and white process noise on the input (G = B) of a known intensity, 10^4
samples each: the plant sampled exactly (ZOH plus the exact noise covariance of a step),
the compensator's law on the true state, and only the topics the tuner reads
(``state/true``, the sensor, ``control/u``) written with test/bag_synth.py's messages.
The core ALS is checked against python-control's Kalman filter first (its innovations
are white), then on arrays, then through the bags.

"""

import json
import math
from pathlib import Path

from bag_cases import INPUT_NOISE, simulate_noisy, STEPS, true_noise
from bag_synth import CONFIG, write_bag
import numpy as np
from numpy.testing import assert_allclose
from observer_ros.bag.errors import BagToolError
from observer_ros.core.als import (ALSError, identify_noise, model_autocovariances,
                                   predictor_innovations, process_noise_map,
                                   sample_autocovariances)
from observer_ros.core.design import kalman_gain, observer_gain
from observer_ros.core.estimators import process_noise_covariance
from observer_ros.core.model import map_poles_to_discrete, zoh_matrices
from observer_ros.evaluation.evaluate import main as eval_main
from observer_ros.evaluation.evaluator import evaluate_bag
from observer_ros.tuning.tune import identify, main, tune
from observer_ros.vehicle import load_vehicle
import pytest
import yaml


def _floats(values):
    return '[' + ', '.join(repr(float(x)) for x in np.ravel(values)) + ']'


@pytest.fixture(scope='module')
def noisy_bags(tmp_path_factory):
    """Bags of 10^4 samples of the submarine and the cart with known noise."""
    root = tmp_path_factory.mktemp('tune')
    out = {}
    for seed, name in enumerate(INPUT_NOISE):
        v, q, _ = true_noise(name)
        messages = simulate_noisy(v, q, 10 + seed)
        out[name] = write_bag(root / name, messages)
        if name == 'submarine':
            out['submarine_no_truth'] = write_bag(root / 'no_truth', messages[:3 * 2001],
                                                  skip=('state/true',))
    return out


# ------------------------------------------------------------------------------ core

def _sampled(name):
    v, q, r = true_noise(name)
    pl, dt = v.plant, v.sample_time
    Ad, Bd = zoh_matrices(pl.A, pl.B, dt)
    F = process_noise_map(pl.A, pl.B, dt)
    return v, Ad, Bd, F, q, r


def test_als_model_autocovariances_of_the_kalman_predictor_are_white():
    # python-control's dlqe predictor gain gives white innovations of covariance
    # C P C^T + R: the model autocovariances must say so
    v, Ad, Bd, F, q, r = _sampled('submarine')
    C = np.asarray(v.plant.C, float)
    Qk = F(np.array([[q]]))
    L, P, _ = kalman_gain(Ad, C, Qk, [[r]], discrete=True)
    c = model_autocovariances(Ad, C, L, Qk, np.array([[r]]), 10)
    assert_allclose(c[0], C @ P @ C.T + r, rtol=1e-8)
    assert np.max(np.abs(c[1:])) < 1e-9 * c[0, 0, 0]
    # and a non-optimal gain's are not
    Lp = observer_gain(Ad, C, map_poles_to_discrete(v.observer.poles, v.sample_time),
                       discrete=True)
    c = model_autocovariances(Ad, C, Lp, Qk, np.array([[r]]), 10)
    assert c[1, 0, 0] > 0.2 * c[0, 0, 0]
    # the map of a continuous intensity is the Van Loan integral
    assert_allclose(F(np.array([[q]])),
                    process_noise_covariance(v.plant.A, [[q]], v.sample_time, v.plant.B))


def _simulate_arrays(name, seed, N=STEPS):
    v, Ad, Bd, F, q, r = _sampled(name)
    C = np.asarray(v.plant.C, float)
    w, V = np.linalg.eigh(F(np.array([[q]])))
    S = V * np.sqrt(np.maximum(w, 0.0))
    rng = np.random.default_rng(seed)
    x = np.zeros(v.plant.n)
    y = np.empty((N, 1))
    for k in range(N):
        y[k] = C @ x + math.sqrt(r) * rng.standard_normal(1)
        x = Ad @ x + S @ rng.standard_normal(v.plant.n)
    u = np.zeros((N, v.plant.m))
    return v, Ad, Bd, C, F, q, r, y, u


def test_als_on_arrays_recovers_the_noise_and_refuses_what_it_cannot_identify():
    v, Ad, Bd, C, F, q, r, y, u = _simulate_arrays('submarine', 0)   # stable open loop
    Lp = observer_gain(Ad, C, map_poles_to_discrete(v.observer.poles, v.sample_time),
                       discrete=True)
    e = predictor_innovations(Ad, Bd, C, v.plant.D, Lp, y, u)[200:]
    res = identify_noise(e, Ad, C, Lp, F, 1, lags=15)
    assert abs(res.Q[0, 0] / q - 1) < 0.25 and abs(res.R[0, 0] / r - 1) < 0.10
    assert res.rank == res.unknowns == 2 and 1.0 <= res.condition < 100
    assert res.empirical.shape == res.fitted.shape == (15, 1, 1)
    # the empirical autocovariances are within the +-2 sigma bands at most lags
    inside = np.abs(res.empirical[:, 0, 0] - res.fitted[:, 0, 0]) <= 2 * res.sigma[:, 0]
    assert inside.mean() >= 0.8
    # the sample autocovariance is the plain average of products
    assert sample_autocovariances(e, 3)[2, 0, 0] == pytest.approx(
        float(e[2:, 0] @ e[:-2, 0]) / (e.shape[0] - 2), rel=1e-12)
    # full: symmetric and positive semidefinite
    full = identify_noise(e, Ad, C, Lp, F, 1, lags=15, full=True)
    assert np.min(np.linalg.eigvalsh(full.R)) >= 0 and full.full
    # two noise inputs with the same effect cannot be told apart
    G2 = np.column_stack([v.plant.B, 2.0 * np.asarray(v.plant.B)])
    F2 = process_noise_map(v.plant.A, G2, v.sample_time)
    with pytest.raises(ALSError, match='not identifiable: the ALS matrix has rank 2 for 3'):
        identify_noise(e, Ad, C, Lp, F2, 2, lags=15)
    with pytest.raises(ALSError, match='not stable'):
        identify_noise(e, Ad, C, observer_gain(Ad, C, [1.05, 0.9, 0.8], discrete=True), F, 1)


def test_als_discrete_vehicle_and_pooled_sequences():
    # a discrete model: Q is the covariance per sample on G's columns (G Q G^T), the
    # reference is the vehicle's z-plane poles; two halves pooled give the same Q, R
    from observer_ros.tuning.sampled import reference_gain
    v = load_vehicle(CONFIG / 'submarine_discrete.yaml')
    A, B, C = (np.asarray(m, float) for m in (v.plant.A, v.plant.B, v.plant.C))
    q, r = 8e-3, 1e-6          # per sample: about the continuous tests' 0.02^2 / dt
    F = process_noise_map(A, B, discrete=True)
    assert_allclose(F(np.array([[q]])), q * B @ B.T)
    rng = np.random.default_rng(4)
    N = STEPS
    x = np.zeros(3)
    y = np.empty((N, 1))
    for k in range(N):
        y[k] = C @ x + math.sqrt(r) * rng.standard_normal()
        x = A @ x + B[:, 0] * math.sqrt(q) * rng.standard_normal()
    Lp, what = reference_gain(v, A, v.sample_time, B)
    assert 'observer poles' in what
    assert_allclose(np.sort(np.abs(np.linalg.eigvals(A - Lp @ C))),
                    np.sort(np.abs(v.observer.poles)), rtol=1e-9)
    e = predictor_innovations(A, B, C, None, Lp, y, np.zeros((N, 1)))[500:]
    one = identify_noise(e, A, C, Lp, F, 1)
    assert abs(one.Q[0, 0] / q - 1) < 0.25 and abs(one.R[0, 0] / r - 1) < 0.10
    halves = [e[:e.shape[0] // 2], e[e.shape[0] // 2:]]
    pooled = sample_autocovariances(halves, 4)
    j = 3
    products = sum(float(h[j:, 0] @ h[:-j, 0]) for h in halves)
    assert pooled[j, 0, 0] == pytest.approx(products / (e.shape[0] - 2 * j), rel=1e-12)
    two = identify_noise(halves, A, C, Lp, F, 1)
    assert two.samples == e.shape[0]
    assert_allclose([two.Q[0, 0], two.R[0, 0]], [one.Q[0, 0], one.R[0, 0]], rtol=0.02)


# ------------------------------------------------------------------------------ bags

@pytest.mark.parametrize('name', list(INPUT_NOISE))
def test_tune_identifies_the_noise_and_the_kalman_filter_matches_the_true_one(
        noisy_bags, tmp_path, name):
    v, q, r = true_noise(name)
    bag = noisy_bags[name]
    res = tune([bag], CONFIG / f'{name}.yaml', tmp_path / 'tune', input_noise=True,
               search='none', plots=False)
    ident = res.identification
    assert sum(ident.samples.values()) == STEPS + 1
    Q, R = ident.result.Q[0, 0], ident.result.R[0, 0]
    assert abs(R / r - 1) < 0.10, (R, r)
    assert abs(Q / q - 1) < 0.25, (Q, q)
    # the reference observer's innovations are coloured, the tuned filter's white
    assert ident.whiteness_before[v.plant.output_names[0]]['white'] is False
    assert ident.whiteness_after[v.plant.output_names[0]]['white'] is True
    # each entry with its standard error, the truth within 3 of them
    (_, _, qv, qs), (_, _, rv, rs) = ident.result.entries()
    assert 0 < qs < 0.2 * qv and 0 < rs < 0.05 * rv
    assert abs(qv - q) < 3 * qs and abs(rv - r) < 3 * rs
    # the tuned file: the project's loader, ROS's parser rules, sources as comments
    text = Path(res.vehicle_file).read_text()
    tuned = load_vehicle(res.vehicle_file)
    assert tuned.observer.kind == 'kalman'
    assert_allclose(tuned.observer.Rd, [[R]])
    assert_allclose(np.ravel(tuned.observer.Bd), np.ravel(v.plant.B))
    doc = yaml.safe_load(text)
    assert list(doc) == ['/**'] and '&' not in text
    obs = doc['/**']['ros__parameters']['observer']
    for key in ('Qd', 'Rd', 'Bd'):
        assert all(type(x) is float for x in obs[key]), key
    assert '# intensity of the process noise' in text and 'autocovariance least' in text
    assert f'# standard errors (1 sigma): {ident.noise_names[0]} {Q:.4g} +- ' in text
    # the tuned Kalman filter's RMSE is within 5 % of the one of the true covariances
    ev = evaluate_bag(bag, CONFIG / f'{name}.yaml', {'truekf': [
        'observer.type:=kalman', f'observer.Qd:=[{q!r}]', f'observer.Rd:=[{r!r}]',
        f'observer.Bd:={_floats(v.plant.B)}']}, compare={'tuned': res.vehicle_file},
        include_live=False, include_design=False)
    tuned_rms = ev.variants['tuned'].summary['error_rms']
    true_rms = ev.variants['truekf'].summary['error_rms']
    assert abs(tuned_rms / true_rms - 1) < 0.05, (tuned_rms, true_rms)
    # never overwritten
    with pytest.raises(BagToolError, match='never overwritten'):
        tune([bag], CONFIG / f'{name}.yaml', tmp_path / 'tune2', output=res.vehicle_file,
             input_noise=True, search='none', plots=False)


def test_identify_pools_bags(noisy_bags):
    bag = noisy_bags['submarine']
    one = identify([bag], CONFIG / 'submarine.yaml', input_noise=True, passes=1)
    two = identify([bag, bag], CONFIG / 'submarine.yaml', input_noise=True, passes=1)
    assert two.samples == {str(bag): STEPS + 1} and two.result.samples == \
        2 * one.result.samples
    assert_allclose(two.result.empirical, one.result.empirical, rtol=1e-12)
    assert_allclose([two.result.Q, two.result.R], [one.result.Q, one.result.R], rtol=1e-9)


def test_observer_tune_command_search_report_and_compare(noisy_bags, tmp_path, capsys):
    bag = noisy_bags['cart_pendulum']
    out = tmp_path / 'cart_tune'
    code = main([str(bag), '--vehicle', str(CONFIG / 'cart_pendulum.yaml'), '--out',
                 str(out), '--input-noise', '--grid', '0.5,1,2'])
    text = capsys.readouterr().out
    assert code == 0, text
    assert 'gain search: kalman scale' in text and 'whiteness of the innovations' in text
    assert 'std_err' in text and 'chosen from the plant' in text
    names = {p.name for p in out.iterdir()}
    assert {'tune.txt', 'tune.json', 'search.csv', 'autocovariance.png', 'search.png',
            'cart_pendulum_tuned.yaml'} <= names
    rows = (out / 'search.csv').read_text().splitlines()
    assert rows[0].startswith('scale,mean') and len(rows) == 4
    metric = [float(r.split(',')[1]) for r in rows[1:]]
    assert all(m > 0 for m in metric)
    # the identified filter is near the best of the grid (RMSE against state/true)
    assert metric[1] <= 1.05 * min(metric)
    # observer-eval compares the tuned file with the original at once
    code = eval_main([str(bag), '--vehicle', str(CONFIG / 'cart_pendulum.yaml'), '--compare',
                      str(out / 'cart_pendulum_tuned.yaml'), '--out', str(tmp_path / 'ev'),
                      '--no-plots', '--no-bag'])
    text = capsys.readouterr().out
    assert code == 0 and 'cart_pendulum_tuned' in text
    # again into the same folder: refused, one error line
    assert main([str(bag), '--vehicle', str(CONFIG / 'cart_pendulum.yaml'), '--out',
                 str(out), '--input-noise']) == 2
    err = capsys.readouterr().err
    assert err.startswith('error: ') and 'exists' in err and err.count('\n') == 1


def test_observer_tune_pole_search_without_identification(noisy_bags, tmp_path, capsys):
    bag = noisy_bags['submarine']
    out = tmp_path / 'sub_tune'
    assert main([str(bag), '--vehicle', str(CONFIG / 'submarine.yaml'), '--out', str(out),
                 '--no-als', '--search', 'poles', '--grid', '0.125,0.25,0.5,1', '--refine',
                 '4', '--no-plots']) == 0
    assert 'gain search: poles scale' in capsys.readouterr().out
    search = json.loads((out / 'tune.json').read_text())['search']
    grid = {0.125: None, 0.25: None, 0.5: None, 1.0: None}
    metric = dict(zip(search['scales'], search['mean']))
    for s in grid:
        grid[s] = metric.pop(s)
    # the design's poles are too fast for this noise: the best grid scale is inside, and
    # minimize_scalar's points (between its neighbours) join the table
    assert min(grid, key=grid.get) == 0.25
    assert 1 <= len(metric) <= 4 and all(0.125 < s < 0.5 for s in metric)
    best = search['best']
    assert min(metric.values()) <= min(grid.values())
    tuned = load_vehicle(out / 'submarine_tuned.yaml')
    v = load_vehicle(CONFIG / 'submarine.yaml')
    assert tuned.observer.kind == 'full'
    assert_allclose(np.sort_complex(tuned.observer.poles),
                    np.sort_complex(best * v.observer.poles), rtol=1e-12)
    assert '# observer-tune gain search (poles scale' in (out / 'submarine_tuned.yaml').read_text()


def test_gain_search_without_truth_scores_residuals(noisy_bags):
    from observer_ros.tuning.gain_search import gain_search
    res = gain_search([noisy_bags['submarine_no_truth']], CONFIG / 'submarine.yaml', 'poles',
                      [0.25, 1.0, 4.0])
    assert res.metric.startswith('residual RMS')
    # relative to the scale 1 itself: 1 + its fraction of lags outside the band
    assert 1.0 <= res.mean[1] <= 2.0
    assert all(math.isfinite(m) and m > 0 for m in res.mean)
    assert res.best in res.scales


def test_observer_tune_errors(noisy_bags, tmp_path, capsys):
    bag = str(noisy_bags['submarine'])
    vehicle = str(CONFIG / 'submarine.yaml')
    cases = [
        ([bag, '--vehicle', vehicle, '--states', 'theta,nope'], "'nope' is not a state"),
        ([bag, '--vehicle', vehicle, '--lags', '0'], '--lags 0'),
        ([str(tmp_path / 'none'), '--vehicle', vehicle], 'no such file'),
        # one lag: C0 alone cannot separate process from measurement noise
        ([bag, '--vehicle', vehicle, '--input-noise', '--lags', '1'],
         'not identifiable: the ALS matrix has rank 1 for 2 unknowns'),
        ([bag, '--vehicle', vehicle, '--no-als', '--search', 'kalman'], 'nothing to tune'),
    ]
    # observer-eval --compare: a file of another vehicle, a missing file, a reserved name
    for compare, match in ((str(CONFIG / 'cart_pendulum.yaml'), 'state names differ'),
                           (str(tmp_path / 'no.yaml'), 'no such file'),
                           (f'live={vehicle}', "'live' must be")):
        assert eval_main([bag, '--vehicle', vehicle, '--compare', compare, '--out',
                          str(tmp_path / 'ev')]) == 2
        err = capsys.readouterr().err
        assert err.startswith('error: ') and match in err, err
    for i, (argv, match) in enumerate(cases):
        assert main(argv + ['--out', str(tmp_path / f'o{i}')]) == 2, match
        err = capsys.readouterr().err
        assert err.startswith('error: ') and match in err, err
        assert 'Traceback' not in err


def test_observer_tune_entry_points_and_help(capsys):
    root = Path(__file__).resolve().parents[2]
    # one console script (ros2 run's name); the dash name is the venv's alias (Makefile)
    assert "'observer_tune = observer_ros.tuning.tune:main'" in (root / 'setup.py').read_text()
    assert 'observer_tune' in (root / 'Makefile').read_text()
    with pytest.raises(SystemExit) as done:
        main(['--help'])
    out = capsys.readouterr().out
    assert done.value.code == 0 and 'autocovariance least squares' in out
    assert '--compare' in out and '--input-noise' in out and '--refine' in out
    assert 'each-pole' in out and '--evaluations' in out and '--workers' in out


def test_sampled_data_steps_are_the_stamps_of_measurements_and_command_changes():
    # the steps are the measurement stamps and, inside them, the command stamps (the
    # command is held between steps); y is NaN at a step without a measurement; the
    # commands are looked up a block at a time: any block gives the same arrays
    from types import SimpleNamespace
    from observer_ros.bag.reader import Stream
    from observer_ros.tuning.sampled import sampled_data
    v = load_vehicle(CONFIG / 'submarine.yaml')
    rng = np.random.default_rng(3)
    N = 1001
    ns = 10**9 + np.arange(N) * 50_000_000 + rng.integers(-300_000, 300_000, N)
    valid = np.ones(N, dtype=bool)
    valid[[0, 17, N - 1]] = False                  # a lost message inside: a longer step
    q = rng.standard_normal((N, 1))
    c_ns = ns[::10] + np.where(np.arange(len(ns[::10])) % 2, 0, 1000)   # some equal stamps
    c_val = rng.standard_normal((c_ns.size, 1))

    def stream(stamps, values, ok):
        n = stamps.size
        return Stream('t', 'x', ('q',), np.arange(n), stamps, stamps, values, ok)

    def rec(stamps):
        return SimpleNamespace(sensors={'gyro': stream(stamps, q, valid)},
                               command=stream(c_ns, c_val, np.ones(c_ns.size, dtype=bool)))
    whole = sampled_data(rec(ns), v, block=10**6)
    meas = ns[valid]
    inside = c_ns[(c_ns > meas[0]) & (c_ns < meas[-1])]
    assert np.array_equal(whole.stamp_ns, np.union1d(meas, inside))
    assert whole.dt == float(np.median(np.diff(meas).astype(np.float64) * 1e-9))
    at = np.searchsorted(whole.stamp_ns, meas)
    assert np.array_equal(whole.y[at, 0], q[valid, 0])
    assert np.isnan(np.delete(whole.y[:, 0], at)).all() and whole.measured == meas.size
    held = np.searchsorted(c_ns, whole.stamp_ns, side='right') - 1
    assert np.array_equal(whole.u[held >= 0, 0], c_val[held[held >= 0], 0])
    assert np.any(whole.u != whole.u_meas)          # a command stamped at its sample
    assert not whole.regular and whole.steps[1] > 1.9 and whole.missing == {'q': 0.0}
    for block in (1, 7, 64):
        part = sampled_data(rec(ns), v, block=block)
        for key in ('stamp_ns', 'y', 'u', 'u_meas'):
            assert np.array_equal(getattr(part, key), getattr(whole, key), equal_nan=True), key
    # a clock jump (two runs in one bag) is refused; a message out of order is sorted
    swapped = ns.copy()
    swapped[[40, 41]] = swapped[[41, 40]]
    assert np.array_equal(sampled_data(rec(swapped), v).stamp_ns, whole.stamp_ns)
    jump = ns.copy()
    jump[700:] -= 20 * 10**9
    with pytest.raises(BagToolError, match='a clock jump'):
        sampled_data(rec(jump), v)
