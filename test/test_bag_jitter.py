# test/test_bag_jitter.py: replay of a bag whose stamps jitter (a new step length each message).
"""
Jittered stamps and long stretches: the bulk replay gives the estimator's own answers.

The replay's copies of the estimator share its step and gain caches, so the gains of a
step are designed once, not once per copy.

"""

import copy

from bag_synth import CONFIG, simulate, write_bag
import numpy as np
from numpy.testing import assert_allclose
from observer_ros.bag.reader import read_recording
from observer_ros.bag.replay import _twin, replay
from observer_ros.core.estimators import make_estimator
from observer_ros.vehicle import load_vehicle

JITTER_NS = 300_000


def _jittered(messages, seed=3):
    """Move every step's messages (stamp and receive time) by one jitter of +-0.3 ms."""
    rng = np.random.default_rng(seed)
    shift = {}
    out = []
    for topic, msgtype, ns, msg in messages:
        if ns not in shift:
            shift[ns] = int(rng.integers(-JITTER_NS, JITTER_NS + 1))
        t = ns + shift[ns]
        msg = copy.deepcopy(msg)
        stamp = msg.header.stamp if hasattr(msg, 'header') else msg.clock
        stamp.sec, stamp.nanosec = t // 1_000_000_000, t % 1_000_000_000
        out.append((topic, msgtype, t, msg))
    return out


def test_jittered_bulk_replay_equals_the_estimators_calls(tmp_path):
    vehicle = load_vehicle(CONFIG / 'submarine.yaml')
    run = simulate(vehicle, steps=400, noise=True)
    bag = write_bag(tmp_path / 'jit', _jittered(run['messages']))
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
    twin = _twin(est)
    assert twin.cache is est.cache and twin.gain_cache is est.gain_cache
    x = est.x_hat.copy()
    twin.reset(np.ones(vehicle.plant.n), 2.0)
    assert_allclose(est.x_hat, x)
    assert est.t == 1.0


def test_long_stretches_are_replayed_in_pieces_with_the_same_estimates(tmp_path,
                                                                       monkeypatch):
    from observer_ros.bag import replay as replay_module
    vehicle = load_vehicle(CONFIG / 'submarine.yaml')
    run = simulate(vehicle, steps=600, noise=True)
    bag = write_bag(tmp_path / 'long', run['messages'])
    rec = read_recording(bag, vehicle)
    whole = replay(rec, vehicle)
    exact = replay(rec, vehicle, exact=True)
    assert whole.bulk_steps > 500
    monkeypatch.setattr(replay_module, 'MAX_RUN', 100)
    pieces = replay(rec, vehicle)
    assert pieces.bulk_steps == whole.bulk_steps and not pieces.warnings
    assert pieces.counts == whole.counts
    assert_allclose(pieces.x_hat, exact.x_hat, rtol=1e-9, atol=1e-10)
    np.testing.assert_array_equal(pieces.stamp_ns, exact.stamp_ns)
    np.testing.assert_array_equal(pieces.seq, exact.seq)
