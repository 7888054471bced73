# test/replay/test_bag_bulk_kalman.py: the Kalman filter replayed in bulk equals its own calls.
"""
A Kalman filter replayed in bulk (observer_ros/replay/bulk_kalman.py) equals its calls.

The bulk replay against the filter called message by message (``exact=True``):
time-varying gains while P converges, then the steady-state gain of each step class;
jittered stamps stay time-varying.

"""

from pathlib import Path

from bag_cases import jittered
from bag_synth import CONFIG, simulate, write_bag
import numpy as np
from numpy.testing import assert_allclose, assert_array_equal
from observer_ros.bag.reader import read_recording
from observer_ros.replay import bulk_kalman, bulk_runs
from observer_ros.replay.replay import replay
from observer_ros.vehicle import load_vehicle
import pytest

SAMPLES = Path(__file__).resolve().parents[2] / 'bags' / 'samples'

KALMAN = {
    'submarine': ['observer.type:=kalman',
                  'observer.Qd:=[1.0e-6,0.0,0.0, 0.0,1.0e-4,0.0, 0.0,0.0,1.0e-4]'],
    'cart_pendulum': ['observer.type:=kalman',
                      'observer.Qd:=[1.0e-6,0.0,0.0,0.0, 0.0,1.0e-4,0.0,0.0, '
                      '0.0,0.0,1.0e-6,0.0, 0.0,0.0,0.0,1.0e-4]'],
    'submarine_reduced': ['observer.type:=kalman',
                          'observer.Qd:=[1.0e-6,0.0,0.0, 0.0,1.0e-4,0.0, 0.0,0.0,1.0e-4]'],
}


def _same(bulk, exact):
    """Assert that the bulk replay's rows equal the calls' to round-off (whitened too)."""
    assert not bulk.warnings
    assert_array_equal(bulk.stamp_ns, exact.stamp_ns)
    assert_array_equal(bulk.seq, exact.seq)
    scale = np.max(np.abs(exact.x_hat), axis=0)
    assert np.max(np.abs(bulk.x_hat - exact.x_hat) / scale) < 1e-10
    assert_allclose(bulk.residual, exact.residual, rtol=1e-9, atol=1e-12)
    assert_array_equal(np.isnan(bulk.whitened), np.isnan(exact.whitened))
    assert_allclose(bulk.whitened, exact.whitened, rtol=1e-8, atol=1e-9)


@pytest.fixture
def spy(monkeypatch):
    """Record the step where each bulk Kalman stretch turns steady (and its length)."""
    seen = []
    real = bulk_kalman.kalman_maps

    def recording(*args):
        out = real(*args)
        if out is not None:
            seen.append((out[3].steady_from, out[1].size))
        return out
    monkeypatch.setattr('observer_ros.replay.bulk_replay.kalman_maps', recording)
    return seen


@pytest.mark.parametrize('name', sorted(KALMAN))
def test_sample_bags_kalman_in_bulk_equals_the_filters_calls(name, spy):
    vehicle = load_vehicle(CONFIG / f'{name}.yaml', overrides=KALMAN[name])
    rec = read_recording(SAMPLES / name, vehicle)
    exact = replay(rec, vehicle, exact=True)
    bulk = replay(rec, vehicle)
    assert bulk.bulk_steps >= len(bulk) - 1 and exact.bulk_steps == 0
    _same(bulk, exact)
    # P converged to its steady state inside the bag: the rest took the steady gains
    assert spy and all(steady < steps for steady, steps in spy), spy


def test_jittered_stamps_stay_time_varying_and_equal_the_calls(tmp_path, spy):
    vehicle = load_vehicle(CONFIG / 'submarine.yaml', overrides=KALMAN['submarine'])
    run = simulate(vehicle, steps=400, noise=True)
    rec = read_recording(write_bag(tmp_path / 'jit', jittered(run['messages'])), vehicle)
    bulk = replay(rec, vehicle)
    assert bulk.bulk_steps > 300
    _same(bulk, replay(rec, vehicle, exact=True))
    assert all(steady == steps for steady, steps in spy), spy      # never steady


def test_no_process_noise_equals_the_calls(tmp_path):
    vehicle = load_vehicle(CONFIG / 'submarine.yaml', overrides=[
        'observer.type:=kalman', 'observer.Qd:=[0.0,0.0,0.0, 0.0,0.0,0.0, 0.0,0.0,0.0]'])
    run = simulate(load_vehicle(CONFIG / 'submarine.yaml'), steps=500, noise=True)
    rec = read_recording(write_bag(tmp_path / 'q0', run['messages']), vehicle)
    bulk = replay(rec, vehicle)
    assert bulk.bulk_steps > 400
    _same(bulk, replay(rec, vehicle, exact=True))


def test_pieces_carry_the_covariance_from_one_to_the_next(tmp_path, monkeypatch, spy):
    vehicle = load_vehicle(CONFIG / 'submarine.yaml', overrides=KALMAN['submarine'])
    run = simulate(vehicle, steps=700, noise=True)
    rec = read_recording(write_bag(tmp_path / 'long', run['messages']), vehicle)
    exact = replay(rec, vehicle, exact=True)
    monkeypatch.setattr(bulk_runs, 'MAX_RUN', 100)
    bulk = replay(rec, vehicle)
    assert bulk.bulk_steps > 600 and len(spy) >= 6
    _same(bulk, exact)
    # the later pieces start from a converged P: steady from their first step
    assert spy[-1][0] == 0, spy
