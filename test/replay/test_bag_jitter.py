# test_bag_jitter.py: replay of a bag whose stamps jitter (a new step length each message).
"""
Jittered stamps and long stretches: the bulk replay gives the estimator's own answers.

The replay's copies of the estimator share its step and gain caches, so the gains of a
step are designed once, not once per copy.

"""

import copy

from bag_cases import jittered
from bag_synth import CONFIG, simulate, write_bag
import numpy as np
from numpy.testing import assert_allclose
from observer_ros.bag.reader import read_recording
from observer_ros.core.estimators import make_estimator
from observer_ros.replay.bulk_checks import twin
from observer_ros.replay.replay import replay
from observer_ros.vehicle import load_vehicle


def test_jittered_bulk_replay_equals_the_estimators_calls(tmp_path):
    vehicle = load_vehicle(CONFIG / 'submarine.yaml')
    run = simulate(vehicle, steps=400, noise=True)
    bag = write_bag(tmp_path / 'jit', jittered(run['messages']))
    rec = read_recording(bag, vehicle)
    steps = np.diff(rec.sensors['gyro'].stamp_ns)
    assert np.unique(steps).size > 300            # a new step length nearly every message
    exact = replay(rec, vehicle, exact=True)
    bulk = replay(rec, vehicle)
    assert bulk.bulk_steps > 300 and not bulk.warnings
    assert_allclose(bulk.x_hat, exact.x_hat, rtol=1e-9, atol=1e-10)


def test_a_twin_has_its_own_state_and_the_same_caches():
    vehicle = load_vehicle(CONFIG / 'submarine.yaml')
    est = make_estimator(vehicle.plant, vehicle.observer)
    est.correct(1.0, [0.1], vehicle.plant.output_rows(vehicle.sensors[0].outputs))
    copy = twin(est)
    assert copy.cache is est.cache and copy.gain_cache is est.gain_cache
    x = est.x_hat.copy()
    copy.reset(np.ones(vehicle.plant.n), 2.0)
    assert_allclose(est.x_hat, x)
    assert est.t == 1.0


def test_long_stretches_are_replayed_in_pieces_with_the_same_estimates(tmp_path,
                                                                       monkeypatch):
    from observer_ros.replay import bulk_runs
    vehicle = load_vehicle(CONFIG / 'submarine.yaml')
    run = simulate(vehicle, steps=600, noise=True)
    bag = write_bag(tmp_path / 'long', run['messages'])
    rec = read_recording(bag, vehicle)
    whole = replay(rec, vehicle)
    exact = replay(rec, vehicle, exact=True)
    assert whole.bulk_steps > 500
    monkeypatch.setattr(bulk_runs, 'MAX_RUN', 100)
    pieces = replay(rec, vehicle)
    assert pieces.bulk_steps == whole.bulk_steps and not pieces.warnings
    assert pieces.counts == whole.counts
    assert_allclose(pieces.x_hat, exact.x_hat, rtol=1e-9, atol=1e-10)
    np.testing.assert_array_equal(pieces.stamp_ns, exact.stamp_ns)
    np.testing.assert_array_equal(pieces.seq, exact.seq)


def test_jittered_maps_are_built_in_bulk_with_few_probes(tmp_path, monkeypatch):
    from observer_ros.replay import bulk_replay
    vehicle = load_vehicle(CONFIG / 'submarine.yaml')
    run = simulate(vehicle, steps=400, noise=True)
    rec = read_recording(write_bag(tmp_path / 'jit', jittered(run['messages'])), vehicle)
    calls = []
    probe = bulk_replay._probe

    def counted(*args):
        calls.append(args[1])
        return probe(*args)

    monkeypatch.setattr(bulk_replay, '_probe', counted)
    bulk = replay(rec, vehicle)
    exact = replay(rec, vehicle, exact=True)
    assert bulk.bulk_steps > 300 and not bulk.warnings
    assert len(calls) <= bulk_replay.CHECK_CLASSES       # one probe per step before
    assert_allclose(bulk.x_hat, exact.x_hat, rtol=1e-9, atol=1e-10)
    assert_allclose(bulk.residual, exact.residual, rtol=1e-9, atol=1e-10)


def test_zoh_stack_equals_scipy_expm():
    import scipy.linalg
    from observer_ros.replay.step_maps import zoh_stack
    vehicle = load_vehicle(CONFIG / 'submarine.yaml')
    A, B = vehicle.plant.A, vehicle.plant.B
    n, m = B.shape
    rng = np.random.default_rng(1)
    keys = np.concatenate([0.05 + rng.uniform(-3e-4, 3e-4, 200), [0.05, 2.5, 1e-6]])
    Ad, Bd = zoh_stack(A, B, keys)
    aug = np.zeros((n + m, n + m))
    aug[:n, :n], aug[:n, n:] = A, B
    for h, Ad_h, Bd_h in zip(keys, Ad, Bd):
        E = scipy.linalg.expm(aug * h)
        assert_allclose(Ad_h, E[:n, :n], rtol=1e-13, atol=1e-15)
        assert_allclose(Bd_h, E[:n, n:], rtol=1e-13, atol=1e-15)


def test_bulk_maps_equal_the_probed_maps_of_every_step():
    from observer_ros.replay.bulk_replay import _probe
    from observer_ros.replay.step_maps import bulk_maps
    vehicle = load_vehicle(CONFIG / 'submarine.yaml')
    rows = [tuple(vehicle.plant.output_rows(vehicle.sensors[0].outputs))]
    steps = 0.05 + np.random.default_rng(2).uniform(-3e-4, 3e-4, 50)
    for kind in ('full', 'open_loop'):
        obs = copy.deepcopy(vehicle.observer)
        if kind == 'open_loop':
            object.__setattr__(obs, 'kind', 'open_loop')
        est = make_estimator(vehicle.plant, obs)
        assert est.kind == kind
        keys = np.array([est.cache.key(h) for h in steps])
        maps = bulk_maps(est, keys, np.zeros(steps.size, dtype=int), rows)
        for c, h in enumerate(keys):
            probed = _probe(twin(est), 10.0, 10.0 + h, rows[0])
            for bulk, measured in zip((M[c] for M in maps), probed):
                assert_allclose(bulk, measured, rtol=1e-10, atol=1e-12)


def test_gain_brackets_equal_the_estimators_key_by_key():
    from observer_ros.replay.step_maps import _brackets
    vehicle = load_vehicle(CONFIG / 'submarine.yaml')
    est = make_estimator(vehicle.plant, vehicle.observer)
    rng = np.random.default_rng(4)
    keys = [est.cache.key(h) for h in
            np.concatenate([0.05 + rng.uniform(-3e-3, 3e-3, 300), [0.05, 0.049, 0.0999]])]
    keys = np.array(keys + [0.05 * (1 + 5e-13), 0.051 * (1 - 5e-13)])
    i0, i1, w, grid = _brackets(est, keys)
    for key, a, b, wk in zip(keys.tolist(), i0, i1, w):
        g0, g1, w_est = est.gain_steps(key)
        assert grid[a] == g0 and w_est == wk
        assert (g1 is None) == (b < 0) and (g1 is None or grid[b] == g1)


def test_key_ids_number_the_keys_and_mark_steps_without_one():
    from observer_ros.replay.bulk_runs import _key_ids
    from observer_ros.core.errors import ObserverError

    def key_of(h):
        if h > 1.0:
            raise ObserverError('not a whole number of samples')
        return round(h, 1)

    ids, keys = _key_ids(key_of, np.array([0.11, 0.12, 0.2, 1.5]))
    assert ids[0] == ids[1] != ids[2] and ids[3] == -1
    assert keys[ids[0]] == 0.1 and keys[ids[2]] == 0.2
    ids, keys = _key_ids(key_of, np.array([0.11, 0.2, 0.12]))
    assert ids[0] == ids[2] != ids[1] and keys.tolist() == [0.1, 0.2]
