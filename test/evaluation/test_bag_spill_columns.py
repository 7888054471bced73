# test/test_bag_spill_columns.py: the helpers that read a spilled column a block at a time.
"""
What the evaluation computes from a column in a temporary file equals numpy's figure.

``pairwise_sum`` is numpy's sum bit for bit (parts of any block of at least 128 values);
``SortedColumn.searchsorted`` is ``np.searchsorted``; ``decimated_rows`` keeps the rows
the whole-array decimation kept; ``epochs_from_cuts`` gives ``epochs_of``'s epochs;
``column_whiteness`` is ``whiteness`` up to its block and, beyond, the same figures
spilled or in memory (and numpy's to round-off). Each on an array and on a
:class:`SpilledColumn` alike, with small blocks so that a short column is many blocks.

"""

import numpy as np
from numpy.testing import assert_allclose, assert_array_equal
from observer_ros.bag import spill
from observer_ros.bag.spill import (count_true, decimated_rows, pairwise_sum, Sink,
                                    SortedColumn, SpilledColumn)
from observer_ros.evaluation import metrics
from observer_ros.evaluation.plots import decimate
from observer_ros.replay.events import epoch_cuts, epochs_from_cuts, epochs_of
import pytest


def _both(values, tmp_path):
    """Return the values as an array and as a spilled column (appended in 3 parts)."""
    col = SpilledColumn(values.dtype, values.shape[1:], tmp_path)
    for part in np.array_split(values, 3):
        col.append(part)
    return values, col


@pytest.mark.parametrize('n', [1, 7, 8, 9, 127, 128, 129, 1000, 1025, 4097, 20_011, 100_003])
def test_pairwise_sum_is_numpys_sum_bit_for_bit(n, tmp_path):
    rng = np.random.default_rng(n)
    # magnitudes over 16 decades: any other order of the additions changes the last digits
    values = rng.normal(size=n) * 10.0 ** rng.integers(-8, 8, size=n)
    for column in _both(values, tmp_path):
        for block in (128, 136, 1000):
            assert pairwise_sum(column, block=block) == np.sum(values)
            assert pairwise_sum(column, block=block, square=True) == np.sum(values * values)
    col = _both(values, tmp_path)[1]
    assert col.sum() == np.sum(values) and col.mean() == np.mean(values)
    assert col.min() == values.min() and col.max() == values.max()


@pytest.mark.parametrize('in_buffers', [False, True])
def test_pairwise_sum_follows_numpys_reduction_of_either_kind(in_buffers, monkeypatch):
    # numpy before 2.3 adds the pairwise sums of each buffer (np.getbufsize() values) in
    # order, 2.3 on sums the whole array pairwise: a sum of buffers of 8192 or fewer values
    # is the same in both, so each kind's figure is known whatever numpy runs the test
    installed = spill.NUMPY_SUMS_IN_BUFFERS
    rng = np.random.default_rng(5)
    values = rng.normal(size=100_003) * 10.0 ** rng.integers(-8, 8, size=100_003)
    size = np.getbufsize()
    buffered = np.sum(values[:size])
    for lo in range(size, values.size, size):
        buffered = buffered + np.sum(values[lo:lo + size])
    monkeypatch.setattr(spill, 'NUMPY_SUMS_IN_BUFFERS', False)
    whole = pairwise_sum(values, block=128)
    assert buffered != whole                            # the two kinds differ here
    monkeypatch.setattr(spill, 'NUMPY_SUMS_IN_BUFFERS', in_buffers)
    expected = buffered if in_buffers else whole
    for block in (128, 1000, spill.PAIRWISE_BLOCK):
        assert pairwise_sum(values, block=block) == expected
    assert pairwise_sum(values[:size]) == np.sum(values[:size])
    if in_buffers == installed:                         # the kind of the numpy installed
        assert expected == np.sum(values)


def test_pairwise_sum_differs_from_a_plain_sum_of_blocks():
    # the check above could not fail by luck: summing the blocks' sums in turn differs
    rng = np.random.default_rng(3)
    values = rng.normal(size=20_011) * 10.0 ** rng.integers(-8, 8, size=20_011)
    plain = sum(np.sum(values[lo:lo + 1000]) for lo in range(0, values.size, 1000))
    assert plain != np.sum(values)
    assert pairwise_sum(values, block=1000) == np.sum(values)


def test_sorted_column_searches_as_numpy(tmp_path):
    rng = np.random.default_rng(4)
    column = np.sort(rng.integers(0, 3000, size=5000))      # repeated values too
    values = np.concatenate([rng.integers(-10, 3010, size=700), column[::97], [-5, 4000]])
    rng.shuffle(values)
    for col in _both(column, tmp_path):
        for lo, hi in ((0, None), (123, 4321), (50, 51), (7, 7)):
            found = SortedColumn(col, lo, hi, stride=16)
            want = lo + np.searchsorted(column[lo:hi], values)
            for window in (1, 40, 1 << 16):
                assert_array_equal(found.searchsorted(values, window=window), want)


def test_decimated_rows_are_the_whole_arrays_decimation(tmp_path):
    rng = np.random.default_rng(5)
    for n, limit in ((1000, 2000), (1000, 1000), (1000, 999), (5003, 37), (5003, 1)):
        assert decimated_rows(n, limit) == decimate(n, limit)
        mask = rng.random(n) < 0.6
        ok = np.flatnonzero(mask)
        want = ok[decimate(ok.size, limit)]
        for col in _both(mask, tmp_path):
            assert count_true(col) == ok.size
            for block in (7, 100, 1 << 16):
                assert_array_equal(decimated_rows(n, limit, col, block=block), want)
        got = decimated_rows(n, limit, lambda lo, hi: mask[lo:hi], block=64)
        assert_array_equal(got, want)


def test_epochs_from_cuts_are_epochs_of(tmp_path):
    rng = np.random.default_rng(6)
    stamp = np.cumsum(rng.integers(1, 10**7, size=3000))
    for at in (400, 401, 2500):
        stamp[at:] -= 10**10                            # a clock that jumps back
    want = epochs_of(stamp, 0.5)
    assert want[-1] == 3
    for col in _both(stamp, tmp_path):
        cuts = epoch_cuts(col, 0.5, block=64)
        for spilled in (None, tmp_path):
            got = epochs_from_cuts(cuts, len(col), spilled, block=100)
            assert isinstance(got, SpilledColumn) == (spilled is not None)
            assert_array_equal(np.asarray(got), want)


def test_sink_grows_in_memory_and_spills_the_same_rows(tmp_path):
    rng = np.random.default_rng(7)
    parts = [rng.normal(size=(k, 2)) for k in (3, 0, 10, 1, 25)]
    sinks = [Sink(np.float64, (2,), 4), Sink(np.float64, (2,), 0, tmp_path),
             Sink(np.float64, (2,), 100)]
    for sink in sinks:
        for part in parts:
            sink.append(part)
    for sink in sinks:
        assert_array_equal(np.asarray(sink.result()), np.concatenate(parts))
    assert isinstance(sinks[1].result(), SpilledColumn)


def _residuals(n, seed=8):
    rng = np.random.default_rng(seed)
    e = rng.normal(size=n)
    r = np.convolve(e, [1.0, 0.3], mode='same')          # coloured: rho_1 about 0.28
    values = np.stack([r, -r], axis=1)
    values[rng.random(n) < 0.05, 0] = np.nan              # rows without this output
    return values


def test_column_whiteness_is_whiteness_up_to_its_block(tmp_path):
    values = _residuals(3000)
    want = metrics.whiteness(values[:, 0])
    for col in _both(values, tmp_path):
        assert metrics.column_whiteness(col, 0, spill=tmp_path) == want


def test_column_whiteness_beyond_its_block_is_the_same_spilled_or_not(tmp_path, monkeypatch):
    monkeypatch.setattr(spill, 'READ_BLOCK', 256)
    values = _residuals(20_000)
    whole = metrics.whiteness(values[:, 0])
    got = [metrics.column_whiteness(col, 0, spill=where, block=1000)
           for col in _both(values, tmp_path) for where in (None, tmp_path)]
    for other in got[1:]:
        assert other == got[0]
    out = got[0]
    assert out['samples'] == whole['samples'] > 18_000
    assert out['residual_rms'] == whole['residual_rms']       # numpy's pairwise sums
    assert out['lags'] == whole['lags'] == metrics.WHITENESS_LAGS
    assert_allclose(out['acf'], whole['acf'], rtol=1e-9, atol=1e-13)
    assert out['acf'][0] > 0.2
    assert_allclose(out['ljung_box_q'], whole['ljung_box_q'], rtol=1e-9)
    assert_allclose(out['ljung_box_p'], whole['ljung_box_p'], rtol=1e-6)
    assert out['acf_outside'] == whole['acf_outside']
