# test/core/test_core_autocovariance.py: running lagged sums against the whole-array formulas.
"""
Sample autocovariances from blocks (core.autocovariance, core.als).

:class:`LaggedSums` given the rows in blocks of any size must give the whole-array
:func:`sample_autocovariances` (pooled sequences included) to 1e-12 relative; the blocked
predictor
the same innovations and final prediction as one call; and the memory of summing does
not grow with the number of rows.

"""

import tracemalloc

import numpy as np
from numpy.testing import assert_allclose
from observer_ros.core.als import (ALSError, predictor_blocks, predictor_innovations,
                                   sample_autocovariances)
from observer_ros.core.autocovariance import LaggedSums
from observer_ros.core.errors import ObserverError
import pytest


def _coloured(seed, N, p=2, mean=0.3):
    """Rows of an AR(1) sequence with correlated columns and a non-zero mean."""
    rng = np.random.default_rng(seed)
    w = rng.standard_normal((N, p)) @ np.array([[1.0, 0.4], [0.0, 0.7]])[:p, :p]
    out = np.empty((N, p))
    x = np.zeros(p)
    for k in range(N):
        x = 0.8 * x + w[k]
        out[k] = x
    return out + mean


def _summed(seqs, lags, block):
    sums = LaggedSums(seqs[0].shape[1], lags)
    for s in seqs:
        sums.new_sequence()
        for a in range(0, s.shape[0], block):
            sums.add(s[a:a + block])
    return sums


@pytest.mark.parametrize('block', [1, 7, 64, 1000, 10 ** 6])
def test_blocked_autocovariances_equal_the_whole_array_ones(block):
    seqs = [_coloured(1, 3001), _coloured(2, 1234), _coloured(3, 40)]
    lags = 15
    whole = sample_autocovariances(seqs, lags)
    sums = _summed(seqs, lags, block)
    got = sums.autocovariances()
    assert sums.samples == 3001 + 1234 + 40 and sums.lengths == [3001, 1234, 40]
    assert_allclose(got, whole, rtol=1e-12, atol=1e-12 * np.max(np.abs(whole)))
    assert_allclose(sums.autocovariances(4), whole[:4], rtol=1e-12)
    # one sequence: the plain average of products, as the whole-array function
    one = _summed(seqs[:1], lags, block).autocovariances()
    assert_allclose(one, sample_autocovariances(seqs[0], lags), rtol=1e-12)
    # an off-diagonal lag is not symmetric: the orientation is e[k+j] e[k]^T
    e = seqs[0]
    assert one[3, 0, 1] == pytest.approx(float(e[3:, 0] @ e[:-3, 1]) / (e.shape[0] - 3),
                                         rel=1e-12)
    assert abs(one[3, 0, 1] - one[3, 1, 0]) > 1e-3 * abs(one[3, 0, 1])


def test_too_few_rows_are_refused():
    sums = _summed([_coloured(6, 10)], 15, 4)
    with pytest.raises(ALSError, match='10 innovations are too few for 15 lags'):
        sums.autocovariances()
    with pytest.raises(ObserverError, match='lags must be at least 1'):
        LaggedSums(2, 0)


def test_blocked_predictor_gives_the_same_innovations_and_prediction():
    rng = np.random.default_rng(8)
    Ad = np.array([[0.9, 0.1], [0.0, 0.8]])
    Bd = np.array([[0.0], [0.1]])
    C = np.array([[1.0, 0.0]])
    D = np.array([[0.05]])
    Lp = np.array([[0.5], [0.2]])
    y, u, um = rng.standard_normal((500, 1)), rng.standard_normal((500, 1)), \
        rng.standard_normal((500, 1))
    x0 = np.array([0.3, -0.1])
    e, x = predictor_innovations(Ad, Bd, C, D, Lp, y, u, um, x0=x0, final=True)

    class Keep:
        def __init__(self):
            self.parts = []

        def add(self, block):
            self.parts.append(block)
    keep = Keep()
    got = predictor_blocks(Ad, Bd, C, D, Lp, y, u, um, x0=x0, sinks=[keep], block=37)
    assert len(keep.parts) == 14
    # each block starts from the last one's real prediction: equal up to rounding
    np.testing.assert_allclose(np.vstack(keep.parts), e, rtol=0, atol=1e-12)
    np.testing.assert_allclose(got, x, rtol=0, atol=1e-12)
    # no rows: the start itself (zeros when not given)
    np.testing.assert_array_equal(predictor_blocks(Ad, Bd, C, D, Lp, y[:0], u[:0]),
                                  np.zeros(2))


def _stepwise(Ad, Bd, C, Lp, y, u, x0):
    """Return the innovations and last prediction of the recursion, one step at a time."""
    x, out = np.array(x0, float), []
    for k in range(y.shape[0]):
        out.append(y[k] - C @ x)
        x = (Ad - Lp @ C) @ x + Bd @ u[k] + Lp @ y[k]
    return np.array(out), x


@pytest.mark.parametrize('Ad', [
    np.array([[0.9, 0.3, 0.0], [-0.3, 0.9, 0.01], [0.0, 0.0, 0.995]]),   # a complex pair
    np.array([[1.0, 0.01, 0.0], [0.0, 0.99, 0.01], [0.0, 0.0, 0.995]]),  # real modes
    np.array([[0.5, 1.0, 0.0], [0.0, 0.5, 1.0], [0.0, 0.0, 0.5]]),       # one Jordan block
])
def test_predictor_run_mode_by_mode_equals_the_recursion(Ad):
    rng = np.random.default_rng(3)
    Bd, C = rng.standard_normal((3, 1)), np.array([[1.0, 0.0, 1.0]])
    Lp = np.array([[0.02], [0.1], [0.3]])
    y, u = rng.standard_normal((3000, 1)), rng.standard_normal((3000, 1))
    x0 = np.array([1.0, -2.0, 0.5])
    e, x = predictor_innovations(Ad, Bd, C, None, Lp, y, u, x0=x0, final=True)
    want_e, want_x = _stepwise(Ad, Bd, C, Lp, y, u, x0)
    scale = np.max(np.abs(want_e))
    np.testing.assert_allclose(e, want_e, rtol=0, atol=1e-12 * scale)
    np.testing.assert_allclose(x, want_x, rtol=0, atol=1e-12 * np.max(np.abs(want_x)))


def test_summing_a_longer_sequence_needs_no_more_memory():
    def peak(N):
        rng = np.random.default_rng(9)
        Ad, C = np.array([[0.9, 0.1], [0.0, 0.8]]), np.array([[1.0, 0.0]])
        Lp, Bd = np.array([[0.5], [0.2]]), np.zeros((2, 1))
        y, u = rng.standard_normal((N, 1)), np.zeros((N, 1))
        sums = LaggedSums(1, 15)
        tracemalloc.start()
        predictor_blocks(Ad, Bd, C, None, Lp, y, u, sinks=[sums], block=512)
        _, top = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        return top
    small, large = peak(5_000), peak(20_000)
    # the whole innovations would add 8 bytes a row (120 kB more for the longer one)
    assert large < 1.2 * small + 10_000, (small, large)
