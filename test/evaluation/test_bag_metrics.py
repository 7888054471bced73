# test/evaluation/test_bag_metrics.py: scores of a replay computed block by block.
"""
``metrics.StateError`` gives the error rows on demand and ``score_variant`` scores from it.

Any rows asked for equal those of the whole ``x_hat - truth_at(...)`` array, the scores
equal the whole-array formulas exactly, and scoring holds far less than whole-array
copies of the error, the matched error and the squares would (about 100 bytes per estimate).

"""

import tracemalloc
from types import SimpleNamespace

from bag_synth import CONFIG
import numpy as np
from numpy.testing import assert_array_equal
from observer_ros.evaluation import metrics
from observer_ros.evaluation.metrics import score_variant, StateError, truth_at
from observer_ros.evaluation.results import VariantResult
from observer_ros.evaluation.running_metrics import blocked_state_metrics
from observer_ros.replay.replay import epochs_of, Replay
from observer_ros.vehicle import load_vehicle
import pytest

STATES = ('theta', 'w', 'q')


def _case(rows, seed=0):
    """Return a synthetic (result, replay): two epochs, rows outside the truth, a NaN."""
    rng = np.random.default_rng(seed)
    vehicle = load_vehicle(CONFIG / 'submarine.yaml')
    half = rows // 2
    stamp = np.concatenate([np.arange(half), np.arange(rows - half)]) * 10_000_000 + 10**9
    stamp[5] += 3_000_000                       # between two truth stamps: interpolated
    epoch = epochs_of(stamp)
    t_ns = np.arange(20, half - 20, 10) * 10_000_000 + 10**9     # a tenth of the rate
    t_ns = np.concatenate([t_ns, t_ns])         # the truth of both epochs (none at the ends)
    values = rng.normal(size=(t_ns.size, 3))
    truth = (t_ns, values, epochs_of(t_ns))
    x_hat = rng.normal(size=(rows, 3))
    x_hat[7, 1] = np.nan
    residual = rng.normal(size=(rows, 1))
    rep = Replay(name='design', vehicle=vehicle, stamp_ns=stamp, x_hat=x_hat,
                 residual=residual, epoch=epoch, seq=np.arange(rows),
                 sensor=np.zeros(rows, dtype=np.int64), whitened=residual / 0.01)
    result = SimpleNamespace(vehicle=vehicle, truth=truth,
                             tolerance=dict.fromkeys(STATES, 0.05))
    return result, rep


def test_state_error_rows_equal_the_whole_array():
    result, rep = _case(3000)
    whole = rep.x_hat - truth_at(result.truth, rep.stamp_ns, rep.epoch, block=1 << 30)
    err = StateError(rep, result.truth)
    assert err.shape == whole.shape and len(err) == whole.shape[0]
    assert np.isnan(whole[:20]).all() and np.isfinite(whole[30:60]).all()
    assert_array_equal(np.asarray(err), whole)
    for rows in (slice(0, 7), slice(1490, 1530), slice(2999, 5000),
                 np.array([2999, 0, 5, 1500, 7]), np.isfinite(whole).all(axis=1)):
        assert_array_equal(err[rows], whole[rows])


def test_scores_equal_the_whole_array_formulas():
    result, rep = _case(5000, seed=1)
    vr = VariantResult('design', 'full', (), rep)
    score_variant(result, vr)
    error = rep.x_hat - truth_at(result.truth, rep.stamp_ns, rep.epoch)
    ok = np.all(np.isfinite(error), axis=1)
    assert_array_equal(vr.matched, ok)
    assert vr.summary['matched'] == int(ok.sum())
    assert vr.summary['error_rms'] == float(np.sqrt(np.mean(np.sum(error[ok] ** 2, axis=1))))
    tol = np.full(3, 0.05)
    whole = blocked_state_metrics(rep.t, error, rep.epoch, tol, 0.2)
    assert [vr.states[s] for s in STATES] == whole


def _scoring_peak(rows, monkeypatch):
    result, rep = _case(rows, seed=2)
    vr = VariantResult('design', 'full', (), rep)
    # the errors and the residuals' whiteness only: the innovation health (per sensor,
    # core.innovation) is measured on its own
    monkeypatch.setattr(metrics, 'innovation_health', lambda rep, spill=None: {})
    tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        base = tracemalloc.get_traced_memory()[0]
        score_variant(result, vr)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    return peak - base


@pytest.mark.parametrize('rows', [300_000])
def test_scoring_holds_no_whole_error_copies(rows, monkeypatch):
    per_row = _scoring_peak(rows, monkeypatch) / rows
    # the whole-array code held x_true, the error, the matched error and its squares
    # (4 x 24 bytes per estimate of 3 states); what is left is the residual's whiteness
    # (a float per estimate and output), the matched flags and norms, and each epoch's
    # truth sorted once (at a tenth of the rate)
    assert per_row < 48, per_row
