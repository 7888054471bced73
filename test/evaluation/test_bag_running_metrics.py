# test_bag_running_metrics.py: block-by-block error metrics equal the whole-series ones.
"""Per-state metrics fed block by block (running_metrics) against the whole-series code."""

import math
from pathlib import Path
import tracemalloc

import numpy as np
from numpy.testing import assert_array_equal
from observer_ros.evaluation.evaluator import evaluate_bag
from observer_ros.evaluation.metrics import STEADY_FRACTION, truth_at
from observer_ros.evaluation.running_metrics import blocked_state_metrics
import pytest

ROOT = Path(__file__).resolve().parents[2]
SAMPLES = ROOT / 'bags' / 'samples'


def whole_series_metrics(t, error, epoch, tolerance, steady_fraction=STEADY_FRACTION):
    """Return the metrics as observer-eval computed them on whole arrays (the reference)."""
    ok = np.all(np.isfinite(error), axis=1)
    t, error, epoch = t[ok], error[ok], epoch[ok]
    n = error.shape[1]
    if not t.size:
        return [dict.fromkeys(('rmse', 'max_abs_error', 'settling_time', 'ss_std',
                               'ss_mean'), math.nan) | {'samples': 0} for _ in range(n)]
    settle = np.zeros(n)
    steady = np.zeros(t.size, dtype=bool)
    for e in np.unique(epoch):
        sel = np.flatnonzero(epoch == e)
        tau = t[sel] - t[sel[0]]
        steady[sel[tau >= (1.0 - steady_fraction) * tau[-1]]] = True
        outside = np.abs(error[sel]) > tolerance[None, :]
        for i in range(n):
            bad = np.flatnonzero(outside[:, i])
            if not bad.size:
                continue
            if bad[-1] == sel.size - 1 or tau[bad[-1] + 1] > (1.0 - steady_fraction) * tau[-1]:
                settle[i] = math.inf        # outside at the end, or in the steady state
            else:
                settle[i] = max(settle[i], tau[bad[-1] + 1])
    ss = error[steady]
    out = []
    for i in range(n):
        e = error[:, i]
        out.append({
            'samples': int(e.size),
            'rmse': float(np.sqrt(np.mean(e * e))),
            'max_abs_error': float(np.max(np.abs(e))),
            'settling_time': float(settle[i]),
            'ss_std': float(np.std(ss[:, i])) if ss.shape[0] > 1 else math.nan,
            'ss_mean': float(np.mean(ss[:, i])) if ss.shape[0] else math.nan,
        })
    return out


def assert_same(got, want):
    assert len(got) == len(want)
    for g, w in zip(got, want):
        assert set(g) == set(w)
        assert g['samples'] == w['samples']
        for key in w:
            a, b = g[key], w[key]
            if math.isnan(b) or math.isinf(b):
                assert a == b or (math.isnan(a) and math.isnan(b)), (key, a, b)
            else:
                assert a == pytest.approx(b, rel=1e-12, abs=1e-300), (key, a, b)


def _synthetic(rng, size, n=3):
    """Errors decaying into a band, three epochs, NaN rows, and a state outside at the end."""
    t = np.concatenate([np.arange(size // 3) * 0.01, 5.0 + np.arange(size // 3) * 0.02,
                        np.arange(size - 2 * (size // 3)) * 0.005])
    epoch = np.repeat([0, 1, 2], [size // 3, size // 3, size - 2 * (size // 3)])
    within = np.concatenate([np.arange(c) for c in np.bincount(epoch)])
    decay = np.exp(-within / (size / 30.0))
    error = (decay[:, None] * rng.normal(size=(size, n)) + 0.001 * rng.normal(size=(size, n)))
    error[rng.random(size) < 0.05, rng.integers(n)] = np.nan
    error[size // 3 - 1, n - 1] = 10.0              # epoch 0 ends outside the band: inf
    return t, error, epoch


@pytest.mark.parametrize('block', [1, 7, 64, 1000, 1 << 16])
def test_blocked_metrics_equal_whole_series_on_synthetic_errors(block):
    rng = np.random.default_rng(3)
    t, error, epoch = _synthetic(rng, 3001)
    tol = np.array([0.01, 0.02, 0.05])
    want = whole_series_metrics(t, error, epoch, tol)
    assert math.isinf(want[2]['settling_time']) and 0 < want[0]['settling_time'] < math.inf
    assert_same(blocked_state_metrics(t, error, epoch, tol, STEADY_FRACTION, block), want)


def test_blocked_metrics_with_no_matched_row_or_one_row():
    tol = np.ones(2)
    nan = np.full((5, 2), np.nan)
    t, epoch = np.arange(5.0), np.zeros(5, dtype=np.int64)
    assert_same(blocked_state_metrics(t, nan, epoch, tol, STEADY_FRACTION, 2),
                whole_series_metrics(t, nan, epoch, tol))
    one = nan.copy()
    one[3] = [0.5, 2.0]
    assert_same(blocked_state_metrics(t, one, epoch, tol, STEADY_FRACTION, 2),
                whole_series_metrics(t, one, epoch, tol))


@pytest.mark.parametrize('sample', ['submarine', 'cart_pendulum', 'submarine_reduced'])
def test_blocked_metrics_equal_whole_series_on_sample_bags(sample):
    bag = SAMPLES / sample
    vehicle = ROOT / 'config' / f'{sample}.yaml'
    result = evaluate_bag(bag, vehicle, include_live=True)
    assert result.truth is not None
    tol = np.array([result.tolerance[s] for s in result.vehicle.plant.state_names])
    checked = 0
    for vr in result.variants.values():
        rep = vr.replay
        error = rep.x_hat - truth_at(result.truth, rep.stamp_ns, rep.epoch, block=1 << 30)
        for block in (7, 1000):         # the truth at the stamps, block by block
            assert_array_equal(rep.x_hat - truth_at(result.truth, rep.stamp_ns, rep.epoch,
                                                    block=block), error)
        want = whole_series_metrics(rep.t, error, rep.epoch, tol)
        for block in (5, 113):
            assert_same(blocked_state_metrics(rep.t, error, rep.epoch, tol,
                                              STEADY_FRACTION, block), want)
        assert_same(list(vr.states.values()), want)      # what observer-eval reports
        checked += want[0]['samples'] > 0
    assert checked


def test_truth_at_block_by_block_interpolates_each_epoch_alone():
    """Two epochs, stamps between, on and outside the truth's: any block, the same rows."""
    t_ns = np.array([10, 20, 30, 5, 15], dtype=np.int64) * 10**9
    values = np.arange(10.0).reshape(5, 2) ** 2
    truth = (t_ns, values, np.array([0, 0, 0, 1, 1]))
    stamp = np.array([10, 12, 20, 29, 31, 4, 5, 9, 15, 16], dtype=np.int64) * 10**9
    epoch = np.array([0, 0, 0, 0, 0, 1, 1, 1, 1, 1])
    whole = truth_at(truth, stamp, epoch, block=1 << 30)
    assert_array_equal(whole[0], values[0])
    assert_array_equal(whole[6], values[3])
    assert whole[1, 0] == pytest.approx(0.0 + 0.2 * 4.0) and np.isnan(whole[4]).all()
    assert np.isnan(whole[5]).all() and np.isnan(whole[9]).all()
    for block in (1, 2, 3, 7):
        assert_array_equal(truth_at(truth, stamp, epoch, block=block), whole)


def _peak(size):
    rng = np.random.default_rng(5)
    t, error, epoch = _synthetic(rng, size)
    tol = np.array([0.01, 0.02, 0.05])
    tracemalloc.start()
    try:
        blocked_state_metrics(t, error, epoch, tol, STEADY_FRACTION, 1 << 12)
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def test_blocked_metrics_memory_does_not_grow_with_the_series():
    small, large = _peak(1 << 17), _peak(1 << 18)
    # whole-series code copies the matched rows (~56 bytes a row): 2x the rows, ~2x the peak
    assert large < 1.3 * small, (small, large)
