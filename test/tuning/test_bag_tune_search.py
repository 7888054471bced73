# test/tuning/test_bag_tune_search.py: observer-tune's gain searches over several different bags.
"""
The per-pole search, and the searches over two different bags (serially and on Dask).

The bags are test_bag_tune's closed loops with known noise, 3000 samples each, two per
vehicle that differ in seed, measurement noise (the second twice the sensor's) and
initial state (the second starts away from rest, where the observer starts).

"""

from pathlib import Path
from types import SimpleNamespace

from bag_cases import simulate_noisy, true_noise
from bag_synth import CONFIG, write_bag
import numpy as np
from numpy.testing import assert_allclose
from observer_ros.bag.errors import BagToolError
from observer_ros.evaluation.evaluator import evaluate_bag
from observer_ros.tuning.gain_search import gain_search
from observer_ros.tuning.pole_search import MARGIN, pole_set
from observer_ros.tuning.tune import main, tune
from observer_ros.vehicle import load_vehicle
import pytest
import yaml

STEPS = 3000


@pytest.fixture(scope='module')
def two_bags(tmp_path_factory):
    """Two different bags of the cart-pendulum and of the submarine (and without truth)."""
    root = tmp_path_factory.mktemp('tune_search')
    out = {}
    for name in ('cart_pendulum', 'submarine'):
        v, q, _ = true_noise(name)
        runs = [simulate_noisy(v, q, 31, steps=STEPS),
                simulate_noisy(v, q, 32, steps=STEPS, x0=0.01 * np.ones(v.plant.n),
                               noise_scale=2.0)]
        out[name] = [write_bag(root / f'{name}_{i}', m) for i, m in enumerate(runs)]
        out[f'{name}_no_truth'] = [write_bag(root / f'{name}_{i}_nt', m, skip=('state/true',))
                                   for i, m in enumerate(runs)]
    return out


def _sorted(poles):
    return np.sort_complex(np.asarray(poles, dtype=complex))


def test_per_pole_search_beats_the_common_scale_and_writes_the_poles(two_bags, tmp_path):
    bags = two_bags['cart_pendulum']
    vehicle = CONFIG / 'cart_pendulum.yaml'
    res = tune(bags, vehicle, tmp_path / 'out', als=False, search='each-pole',
               scales=[0.5, 1.0, 2.0], evaluations=12)
    sr = res.search
    grid_best = min(sr.grid.mean)
    # the start is the vehicle's poles times the best common scale, and it is evaluation 0
    assert sr.start_scale == sr.grid.best
    assert sr.mean[0] == pytest.approx(grid_best, rel=1e-12)
    assert sr.best_metric <= grid_best and len(sr.mean) <= 12
    assert len(sr.mean) >= 8                           # the optimizer did move the poles
    # the metric is the mean over the two bags of each bag's error RMS; the per-bag
    # figures are observer-eval's of the written file
    assert len(sr.per_bag) == 2
    a, b = (v[sr.best] for v in sr.per_bag.values())
    assert sr.best_metric == pytest.approx((a + b) / 2, rel=1e-12) and a != b
    text = Path(res.vehicle_file).read_text()
    tuned = load_vehicle(res.vehicle_file)
    assert tuned.observer.kind == 'full'
    assert_allclose(_sorted(tuned.observer.poles), _sorted(sr.best_poles), rtol=1e-12)
    for bag, want in zip(bags, (a, b)):
        ev = evaluate_bag(bag, res.vehicle_file, include_live=False)
        assert ev.variants['design'].summary['error_rms'] == pytest.approx(want, rel=1e-9)
    assert '# observer-tune per-pole search (scipy.optimize Nelder-Mead' in text
    assert text.count('# observer-tune per-pole search') == 2      # poles and poles_imag
    # conjugate pairs stay pairs, every pole left of the margin
    p = np.asarray(tuned.observer.poles, dtype=complex)
    assert_allclose(_sorted(p), _sorted(p.conj()), rtol=1e-12)
    assert np.all(p.real < -MARGIN * 0.5 * 10.0 + 1e-9)     # slowest start: -5 (scale 0.5)
    # the report: per evaluation, per bag, the summary; the plot per evaluation
    rows = (tmp_path / 'out' / 'pole_search.csv').read_text().splitlines()
    assert rows[0].split(',')[:2] == ['evaluation', 'mean'] and len(rows) == len(sr.mean) + 1
    report = (tmp_path / 'out' / 'tune.txt').read_text()
    assert 'per-pole search' in report and 'summary per bag:' in report
    assert f'best: evaluation {sr.best}' in report
    assert {'pole_search.png', 'search.png', 'search.csv'} <= \
        {f.name for f in (tmp_path / 'out').iterdir()}


def test_search_over_two_different_bags_is_the_mean_of_each(two_bags):
    bags = two_bags['submarine']
    vehicle = CONFIG / 'submarine.yaml'
    both = gain_search(bags, vehicle, 'poles', [0.25, 0.5, 1.0])
    alone = [gain_search([b], vehicle, 'poles', [0.25, 0.5, 1.0]) for b in bags]
    assert list(both.per_bag) == [str(b) for b in bags]
    for one, values in zip(alone, both.per_bag.values()):
        assert list(one.per_bag.values())[0] == values
    first, second = both.per_bag.values()
    assert all(x != y for x, y in zip(first, second))         # different data
    assert both.mean == [(x + y) / 2 for x, y in zip(first, second)]
    assert both.metric.startswith('error_rms')


@pytest.mark.ros
def test_search_on_dask_gives_the_serial_numbers(two_bags, tmp_path, capsys):
    # without state/true: the residual metric, relative to the scale nearest 1
    bags = two_bags['submarine_no_truth']
    vehicle = CONFIG / 'submarine.yaml'
    serial = gain_search(bags, vehicle, 'poles', [0.25, 0.5, 1.0])
    assert serial.metric.startswith('residual RMS')
    out = tmp_path / 'dask'
    argv = [str(b) for b in bags] + ['--vehicle', str(vehicle), '--out', str(out), '--no-als',
                                     '--search', 'poles', '--grid', '0.25,0.5,1', '--no-plots',
                                     '--workers', '2']
    assert main(argv) == 0
    assert 'summary per bag:' in capsys.readouterr().out
    rows = [r.split(',') for r in (out / 'search.csv').read_text().splitlines()]
    assert rows[0] == ['scale', 'mean'] + [str(b) for b in bags]
    got = np.array(rows[1:], dtype=float)
    want = np.column_stack([serial.scales, serial.mean] + list(serial.per_bag.values()))
    np.testing.assert_array_equal(got, want)


def _vehicle_file(tmp_path, name, **observer):
    doc = yaml.safe_load((CONFIG / 'submarine.yaml').read_text())
    params = doc['/**']['ros__parameters']
    for key, value in observer.items():
        section, field = key.split('__')
        params[section][field] = value
    path = tmp_path / f'{name}.yaml'
    path.write_text(yaml.safe_dump(doc))
    return str(path)


def test_per_pole_search_refusals(two_bags, tmp_path, capsys):
    bag = str(two_bags['submarine'][0])
    cases = [
        # theta and w are not seen by the gyro once the model is decoupled
        (_vehicle_file(tmp_path, 'unobservable', model__A=[
            -1.0, 0.0, 0.0, 0.0, -2.0, 0.0, 0.0, 0.0, -3.0]), [],
         'is not observable from its outputs'),
        (_vehicle_file(tmp_path, 'unpaired', observer__poles_imag=[1.0, 0.0, 0.0]), [],
         'observer.poles: pole -0.6+1j has no complex-conjugate partner'),
        (_vehicle_file(tmp_path, 'kalman', observer__type='kalman', observer__Qd=[1e-4],
                       observer__Rd=[1e-6], observer__Bd=[0.0, 0.0322, -0.0857]), [],
         'has no poles'),
        (str(CONFIG / 'submarine.yaml'), ['--evaluations', '0'], '--evaluations 0'),
        (str(CONFIG / 'submarine.yaml'), ['--workers', '0'], '--workers 0'),
    ]
    for i, (vehicle, extra, match) in enumerate(cases):
        code = main([bag, '--vehicle', vehicle, '--no-als', '--search', 'each-pole',
                     '--out', str(tmp_path / f'o{i}')] + extra)
        err = capsys.readouterr().err
        assert code == 2 and err.startswith('error: ') and match in err, err
        assert err.count('\n') == 1 and not (tmp_path / f'o{i}').exists()
    # the pairing is checked by the search itself too (a vehicle built in code)
    plant = load_vehicle(CONFIG / 'submarine.yaml').plant
    fake = SimpleNamespace(name='fake', plant=plant, observer=SimpleNamespace(
        kind='full', poles=[-1 + 1j, -1 + 2j, -3]))
    with pytest.raises(BagToolError, match=r'observer.poles_imag: the pole .* no conjugate'):
        pole_set(fake)
    fake.observer.poles = [-1.0, 0.5, -2.0]
    with pytest.raises(BagToolError, match='observer.poles: 0.5.* is not stable'):
        pole_set(fake)
    # a discrete vehicle's z-plane poles are searched through s = log(z) / dt: the start
    # gives them back, and any parameters give poles inside the unit circle
    disc = load_vehicle(CONFIG / 'submarine_discrete.yaml')
    space = pole_set(disc)
    assert_allclose(_sorted(space.poles(space.start)), _sorted(disc.observer.poles),
                    rtol=1e-12)
    assert np.all(np.abs(space.poles(space.start + 5.0)) < 1.0)
    assert np.all(np.abs(space.poles(space.start - 30.0)) < 1.0)


def test_the_same_filter_is_replayed_once(monkeypatch):
    """A Qd of zeros times every scale is one filter: one replay, one score for all."""
    from observer_ros.tuning import gain_search as gs
    from observer_ros.evaluation import evaluator as evaluate
    calls = []
    real = evaluate.replay

    def counting(recording, vehicle, name='design', overrides=(), **kw):
        calls.append(tuple(overrides))
        return real(recording, vehicle, name, overrides, **kw)
    monkeypatch.setattr(evaluate, 'replay', counting)
    bag = Path(__file__).resolve().parents[2] / 'bags' / 'samples' / 'submarine'
    zero = ['observer.type:=kalman', 'observer.Qd:=[0.0,0.0,0.0, 0.0,0.0,0.0, 0.0,0.0,0.0]']
    other = ['observer.type:=kalman',
             'observer.Qd:=[1.0e-6,0.0,0.0, 0.0,1.0e-4,0.0, 0.0,0.0,1.0e-4]']
    per_bag, truth = gs.score_variants([bag], CONFIG / 'submarine.yaml',
                                       [zero, other, zero, zero], 1)
    assert truth and len(calls) == 2
    values = next(iter(per_bag.values()))
    assert values[0] == values[2] == values[3] != values[1]
    alone = evaluate_bag(bag, CONFIG / 'submarine.yaml', {'z': zero}, include_live=False,
                         include_design=False)
    assert values[0] == alone.variants['z'].summary['error_rms']
    assert alone.variants['z'].sensors            # observer-eval still judges the health
    assert set(alone.variants['z'].states) == {'theta', 'q', 'w'}   # and scores each state
    bare = evaluate_bag(bag, CONFIG / 'submarine.yaml', {'z': zero}, include_live=False,
                        include_design=False, states=False)      # as the search asks
    assert bare.variants['z'].states == {} and 'settling_time' not in bare.variants['z'].summary
    assert bare.variants['z'].summary['error_rms'] == values[0]


def test_model_errors_are_least_at_the_true_covariances_and_match_a_simulation():
    """The model's predicted RMS error: least at scale 1, and what a long run measures."""
    from observer_ros.tuning.gain_search import model_errors
    from observer_ros.tuning.sampled import sampled_model
    from observer_ros.core.estimators import process_noise_covariance
    v, q, r = true_noise('submarine')
    Ad, _ = sampled_model(v, v.sample_time)
    C = v.plant.C
    Qk = process_noise_covariance(v.plant.A, [[q]], v.sample_time, v.plant.B)
    R = np.array([[r]])
    scales = [0.25, 0.5, 1.0, 2.0, 4.0]
    rms = model_errors(Ad, C, Qk, R, scales)
    assert int(np.argmin(rms)) == 2 and rms[0] > rms[2] < rms[4]
    # a long simulation of the steady-state filter of scale 2 on that model
    import scipy.linalg
    P = scipy.linalg.solve_discrete_are(Ad.T, C.T, 2.0 * Qk, R)
    K = np.linalg.solve(C @ P @ C.T + R, C @ P).T
    rng = np.random.default_rng(5)
    w = rng.multivariate_normal(np.zeros(v.plant.n), Qk, size=200_000)
    e = np.zeros(v.plant.n)
    sq = 0.0
    for k in range(w.shape[0]):
        e = Ad @ e + w[k]                                       # prior error
        e = e - K @ (C @ e + np.sqrt(r) * rng.standard_normal(1))   # after the correction
        if k >= 1000:
            sq += e @ e
    assert np.sqrt(sq / (w.shape[0] - 1000)) == pytest.approx(rms[3], rel=0.03)


def test_the_kalman_search_replays_the_scales_around_the_models_best(two_bags, tmp_path,
                                                                     monkeypatch):
    from observer_ros.tuning import gain_search as gs
    from observer_ros.tuning.identify import identify
    from observer_ros.tuning.tuned_vehicle import write_tuned_vehicle
    bags = two_bags['submarine'][:1]
    ident = identify(bags, CONFIG / 'submarine.yaml', input_noise=True)
    r = ident.result
    identified = tmp_path / 'identified.yaml'
    write_tuned_vehicle(CONFIG / 'submarine.yaml', identified, {
        'observer.type': 'kalman', 'observer.Qd': list(np.ravel(r.Q)),
        'observer.Rd': list(np.ravel(r.R)), 'observer.Bd': list(np.ravel(ident.G))},
        {}, ['test'])
    replayed = []
    real = gs.score_variants

    def counting(bags, vehicle, overrides, *args, **kw):
        replayed.extend(map(tuple, overrides))
        return real(bags, vehicle, overrides, *args, **kw)
    monkeypatch.setattr(gs, 'score_variants', counting)
    first = gs.gain_search(bags, identified, 'kalman', model=ident)
    assert first.model is not None and int(np.nanargmin(first.model)) == \
        first.scales.index(1.0)
    done = [i for i, m in enumerate(first.mean) if np.isfinite(m)]
    assert 3 <= len(done) < len(first.scales)
    assert len(set(replayed)) == len(done)               # each scale replayed once
    best = int(np.nanargmin(first.mean))
    # a minimum bracketed by replayed scales (or the grid's end)
    assert all(j in done for j in (best - 1, best + 1) if 0 <= j < len(first.scales))
    # the bags identification read are replayed as they are: not read again, same numbers
    from observer_ros.evaluation import evaluator
    shared, reads = {}, []
    identify(bags, CONFIG / 'submarine.yaml', input_noise=True, recordings=shared)
    assert set(shared) == {str(b) for b in bags}
    monkeypatch.setattr(evaluator, 'read_recording', lambda *a, **k: reads.append(a))
    again = gs.gain_search(bags, identified, 'kalman', model=ident, recordings=shared)
    assert not reads
    assert_allclose(again.mean, first.mean, rtol=0, atol=0)        # NaN where not replayed
    monkeypatch.undo()
    monkeypatch.setattr(gs, 'score_variants', counting)
    replayed.clear()
    full = gs.gain_search(bags, identified, 'kalman')     # every scale, the same numbers
    assert full.model is None and len(set(replayed)) == len(full.scales)
    for i in done:
        assert first.mean[i] == full.mean[i]
    # a noise identified as zero goes into the tuned file at its standard error: the
    # search on that file is still scored on the identified model first (a filter of the
    # file's Qd on the identified noise), and replays the scales around the model's best
    import copy
    import dataclasses
    from observer_ros.tuning.identify import FILE_FLOOR, filter_Q
    zero = copy.copy(r)
    zero.Q, zero.Qk = np.zeros_like(r.Q), np.zeros_like(r.Qk)
    ident0 = dataclasses.replace(ident, passes=ident.passes[:-1] + [zero])
    written = tmp_path / 'written.yaml'
    write_tuned_vehicle(CONFIG / 'submarine.yaml', written, {
        'observer.type': 'kalman', 'observer.Qd': list(np.ravel(filter_Q(zero, FILE_FLOOR))),
        'observer.Rd': list(np.ravel(r.R)), 'observer.Bd': list(np.ravel(ident.G))},
        {}, ['test'])
    replayed.clear()
    floored = gs.gain_search(bags, written, 'kalman', model=ident0)
    assert floored.model is not None and int(np.nanargmin(floored.model)) == 0
    done = [i for i, m in enumerate(floored.mean) if np.isfinite(m)]
    assert 2 <= len(done) < len(floored.scales) and len(set(replayed)) == len(done)


def test_the_default_mode_reads_each_bag_once(two_bags, tmp_path, monkeypatch):
    """Identification's reading of a bag is what the Kalman search replays."""
    from observer_ros.evaluation import evaluator
    from observer_ros.tuning import identify as ident_module
    reads = []
    real = ident_module.read_recording

    def counting(path, *args, **kw):
        reads.append(str(path))
        return real(path, *args, **kw)
    monkeypatch.setattr(ident_module, 'read_recording', counting)
    monkeypatch.setattr(evaluator, 'read_recording', counting)
    bags = two_bags['submarine']
    res = tune(bags, CONFIG / 'submarine.yaml', tmp_path / 'out', input_noise=True,
               plots=False)
    assert sorted(reads) == sorted(map(str, bags))
    assert res.search is not None and np.isfinite(res.search.mean).sum() >= 3
