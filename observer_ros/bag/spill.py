# observer_ros.bag.spill: columns of rows in temporary files, read a block at a time.
"""
Columns of rows kept in unnamed temporary files, so that a long bag is not held in memory.

A :class:`SpilledColumn` is appended to a block at a time and indexed like a read-only
numpy array (slices, index and boolean arrays, a column key): the rows asked for are read
back a block at a time, with the very values written, so every figure computed from
them is the in-memory one bit for bit. The bag tools keep in them what grows with the
bag: the decoded recording (:func:`observer_ros.bag.reader.read_recording` with
``spill``), the replay's events and rows, the truth and the scores' per-row figures.

The helpers work on a numpy array or a spilled column alike: :class:`Sink` (rows
appended in order, in memory or spilled), :func:`blocks`, :func:`count_true`,
:func:`pairwise_sum` (numpy's own sum of a column, bit for bit, read a block at a
time), :class:`SortedColumn` (``searchsorted`` on a non-decreasing column) and
:func:`decimated_rows`.

"""

import math
import tempfile

import numpy as np

from .errors import BagToolError

__all__ = ['SpilledColumn', 'Sink', 'SortedColumn', 'is_spilled', 'spill_folder', 'blocks',
           'count_true', 'pairwise_sum', 'decimated_rows', 'READ_BLOCK']

READ_BLOCK = 1 << 16             # rows: a spilled column is read this many at a time
CACHE_ROWS = 1 << 12             # rows: one row asked for reads (and keeps) this many
PAIRWISE_BLOCK = 1 << 16         # values: the largest subtree of a sum left to numpy
#: numpy before 2.3 reduces an array a buffer (np.getbufsize() values) at a time, adding the
#: buffers' pairwise sums in order; 2.3 on sums a float64 array pairwise as a whole (the
#: same arrays summed with numpy 1.26.4, 2.0.2, 2.1.3, 2.2.6, 2.3.5 and 2.4.6)
NUMPY_SUMS_IN_BUFFERS = np.lib.NumpyVersion(np.__version__) < '2.3.0'
SEARCH_STRIDE = 1 << 10          # rows: a sorted column keeps every this many in memory


def _disk_error(folder, err, extra=''):
    where = folder or tempfile.gettempdir()
    return BagToolError(f'cannot write the temporary files in {where}: {err.strerror or err}'
                        f' ({extra}set TMPDIR to a folder with room, or keep them in memory: '
                        '--in-memory)')


def spill_folder(spill):
    """Return the folder of a ``spill`` argument (True: the system's temporary folder)."""
    return None if spill is True else spill


def is_spilled(column):
    """Tell whether a column is a :class:`SpilledColumn`."""
    return isinstance(column, SpilledColumn)


class SpilledColumn:
    """
    A column of rows in a temporary file, indexed like a read-only numpy array.

    ``column[rows]`` and ``column[rows, cols]`` read the rows asked for, a block of
    :data:`READ_BLOCK` rows at a time; ``np.asarray(column)`` reads them all. One row
    (``column[i]``) is served from a cached block of :data:`CACHE_ROWS` rows, so rows
    taken one after the other cost one read per block.

    """

    def __init__(self, dtype, row_shape=(), directory=None):
        self.dtype = np.dtype(dtype)
        self.row_shape = tuple(row_shape)
        self.row_bytes = self.dtype.itemsize * int(np.prod(self.row_shape, dtype=np.int64))
        self.directory = directory
        try:
            self.file = tempfile.TemporaryFile(prefix='observer_eval_', dir=directory)
        except OSError as err:
            raise _disk_error(directory, err) from None
        self.rows = 0
        self._cache_lo = 0
        self._cache = None

    @property
    def shape(self):
        """Return ``(rows, *row_shape)``."""
        return (self.rows, *self.row_shape)

    @property
    def ndim(self):
        """Return the number of dimensions."""
        return 1 + len(self.row_shape)

    @property
    def size(self):
        """Return the number of elements."""
        return self.rows * int(np.prod(self.row_shape, dtype=np.int64))

    def __len__(self):
        """Return the number of rows."""
        return self.rows

    def append(self, rows):
        """Write rows after the last one."""
        rows = np.ascontiguousarray(rows, dtype=self.dtype)
        if not rows.size:
            return
        self._write(self.rows, rows)
        self.rows += rows.shape[0]

    def write_row(self, i, row):
        """Overwrite row i (a revised estimate)."""
        self._write(i, np.ascontiguousarray(row, dtype=self.dtype))

    def _write(self, i, rows):
        self._cache = None
        try:
            self.file.seek(i * self.row_bytes)
            self.file.write(rows.data.cast('B'))
        except OSError as err:      # a full disk: said, not a traceback
            raise _disk_error(self.directory, err,
                              f'about {self.row_bytes} bytes per row per column; ') from None

    def read(self, lo, hi):
        """Return rows lo..hi-1 (up to the last row) as a new array."""
        hi = max(lo, min(hi, self.rows))
        out = np.empty((hi - lo, *self.row_shape), dtype=self.dtype)
        if out.size:
            self.file.seek(lo * self.row_bytes)
            if self.file.readinto(out.data.cast('B')) != out.nbytes:
                raise OSError(f'{self.file.name}: rows {lo}..{hi - 1} could not be read back')
        return out

    def __array__(self, dtype=None, copy=None):
        whole = self.read(0, self.rows)
        return whole if dtype is None else whole.astype(dtype)

    def astype(self, dtype):
        """Return every row converted to ``dtype`` (a new array)."""
        return np.asarray(self).astype(dtype)

    def min(self):  # noqa: A003 (numpy's name)
        """Return the smallest element (read a block at a time)."""
        return self._reduce(np.min)

    def max(self):  # noqa: A003 (numpy's name)
        """Return the largest element (read a block at a time)."""
        return self._reduce(np.max)

    def sum(self, axis=None, dtype=None, out=None):  # noqa: A003 (numpy's name)
        """Return ``np.sum`` of a 1-D float column, bit for bit (:func:`pairwise_sum`)."""
        self._whole_float(axis, dtype, out, 'sum')
        return pairwise_sum(self)

    def mean(self, axis=None, dtype=None, out=None):
        """Return ``np.mean`` of a 1-D float column, bit for bit (read a block at a time)."""
        self._whole_float(axis, dtype, out, 'mean')
        return pairwise_sum(self) / self.rows if self.rows else np.float64(math.nan)

    def _whole_float(self, axis, dtype, out, name):
        if axis is not None or dtype is not None or out is not None or self.ndim != 1 or \
                self.dtype != np.float64:
            raise NotImplementedError(f'{name} of a spilled column: float64 rows, whole only')

    def _reduce(self, func):
        if not self.size:
            raise ValueError('zero-size column has no minimum or maximum')
        return func([func(self.read(lo, lo + READ_BLOCK))
                     for lo in range(0, self.rows, READ_BLOCK)])

    def _row(self, i):
        if self._cache is None or not 0 <= i - self._cache_lo < self._cache.shape[0]:
            self._cache_lo = i - i % CACHE_ROWS
            self._cache = self.read(self._cache_lo, self._cache_lo + CACHE_ROWS)
        return self._cache[i - self._cache_lo]

    def __getitem__(self, key):
        """Return the rows (and columns) asked for, as numpy indexing gives them."""
        rest = ()
        if isinstance(key, tuple):
            key, rest = key[0], key[1:]
        if isinstance(key, (int, np.integer)):
            i = int(key) + (self.rows if key < 0 else 0)
            if not 0 <= i < self.rows:
                raise IndexError(f'row {int(key)} of {self.rows}')
            row = self._row(i)
            out = row[rest] if rest else row
            return out.copy() if isinstance(out, np.ndarray) else out
        if isinstance(key, slice):
            start, stop, step = key.indices(self.rows)
            if step == 1:
                return self._gather_range(start, stop, rest)
            idx = np.arange(start, stop, step)
        else:
            idx = np.asarray(key)
            if idx.dtype == bool:
                if idx.shape != (self.rows,):
                    raise IndexError(f'boolean index of {idx.shape} for {self.rows} rows')
                idx = np.flatnonzero(idx)
            else:
                idx = np.where(idx < 0, idx + self.rows, idx).astype(np.intp).reshape(-1)
                if idx.size and (idx.min() < 0 or idx.max() >= self.rows):
                    raise IndexError(f'row index out of range for {self.rows} rows')
        return self._gather(idx, rest)

    def _gather_range(self, start, stop, rest):
        if not rest:
            return self.read(start, stop)
        parts = [self.read(lo, min(stop, lo + READ_BLOCK))[(slice(None), *rest)]
                 for lo in range(start, stop, READ_BLOCK)]
        return np.concatenate(parts) if parts else \
            self.read(0, 0)[(slice(None), *rest)]

    def _gather(self, idx, rest):
        order = None
        if idx.size > 1 and np.any(idx[1:] < idx[:-1]):
            order = np.argsort(idx, kind='stable')
            idx = idx[order]
        parts = []
        at = 0
        while at < idx.size:
            lo = int(idx[at])
            hi = min(self.rows, lo + READ_BLOCK)
            end = at + int(np.searchsorted(idx[at:], hi))
            parts.append(self.read(lo, hi)[(idx[at:end] - lo, *rest)])
            at = end
        out = np.concatenate(parts) if parts else self.read(0, 0)[(slice(None), *rest)]
        if order is not None:
            unsorted = np.empty_like(out)
            unsorted[order] = out
            out = unsorted
        return out


class Sink:
    """
    Rows appended in order: a numpy array, or a :class:`SpilledColumn` with ``spill``.

    ``rows`` (in memory): the expected number of rows, allocated at once (grown if more
    come). :meth:`result` returns the array of the rows appended, or the column.

    """

    def __init__(self, dtype, row_shape=(), rows=0, spill=None):
        self.spilled = spill is not None
        if self.spilled:
            self.column = SpilledColumn(dtype, row_shape, spill_folder(spill))
        else:
            self.column = np.empty((int(rows), *row_shape), dtype=dtype)
        self.rows = 0

    def append(self, part):
        """Append rows."""
        n = len(part)
        if self.spilled:
            self.column.append(part)
        else:
            if self.rows + n > self.column.shape[0]:
                grown = np.empty((max(2 * self.column.shape[0], self.rows + n),
                                  *self.column.shape[1:]), dtype=self.column.dtype)
                grown[:self.rows] = self.column[:self.rows]
                self.column = grown
            self.column[self.rows:self.rows + n] = part
        self.rows += n

    def result(self):
        """Return the rows appended (an array, or the spilled column)."""
        if self.spilled or self.rows == self.column.shape[0]:
            return self.column
        return self.column[:self.rows]


def blocks(column, block=READ_BLOCK, lo=0, hi=None):
    """Yield ``(start, rows)`` of a column (array or spilled) a block of rows at a time."""
    hi = len(column) if hi is None else hi
    for start in range(lo, hi, block):
        yield start, column[start:min(hi, start + block)]


def count_true(mask):
    """Return the number of true rows of a boolean column (array or spilled)."""
    if not is_spilled(mask):
        return int(np.count_nonzero(mask))
    return sum(int(np.count_nonzero(part)) for _, part in blocks(mask))


def pairwise_sum(values, lo=0, hi=None, block=PAIRWISE_BLOCK, square=False):
    """
    Return ``np.sum(values[lo:hi])`` of a 1-D float64 column, bit for bit, a block at a time.

    numpy sums a float64 array by pairwise summation: a run of n values is split at
    ``n2 = n // 2`` rounded down to a multiple of 8, and each half summed alike down to 128
    values. numpy before 2.3 (Ubuntu 24.04's is 1.26) does so for each run of its buffer
    size (``np.getbufsize()``, 8192 values) and adds the runs' sums in order; 2.3 and later
    over the whole array (:data:`NUMPY_SUMS_IN_BUFFERS`). The same splits are made here;
    every part of at most ``block`` values is read and summed by numpy itself, so the
    result is numpy's sum of the whole array, with memory bounded by the block.
    ``square``: the sum of the squares (``np.sum(v * v)``).

    """
    hi = len(values) if hi is None else hi
    size = np.getbufsize()
    if not NUMPY_SUMS_IN_BUFFERS or hi - lo <= size:
        return _pairwise(values, lo, hi, block, square)
    total = _pairwise(values, lo, lo + size, block, square)
    for start in range(lo + size, hi, size):
        total = total + _pairwise(values, start, min(hi, start + size), block, square)
    return total


def _pairwise(values, lo, hi, block, square):
    """Return numpy's pairwise sum of values[lo:hi] (one run), parts of at most block values."""
    n = hi - lo
    if n <= block:
        part = np.asarray(values[lo:hi], dtype=np.float64)
        return np.add.reduce(part * part if square else part)
    n2 = n // 2
    n2 -= n2 % 8
    return _pairwise(values, lo, lo + n2, block, square) + \
        _pairwise(values, lo + n2, hi, block, square)


class SortedColumn:
    """
    ``searchsorted`` on rows lo..hi-1 of a non-decreasing column (array or spilled).

    Every :data:`SEARCH_STRIDE`-th value is kept in memory; a search reads only the
    windows between two of them that hold its answers.

    """

    def __init__(self, column, lo=0, hi=None, stride=SEARCH_STRIDE):
        self.column, self.lo = column, lo
        self.hi = len(column) if hi is None else hi
        self.stride = stride
        self.coarse = np.asarray(column[lo:self.hi:stride]) if self.hi > lo else \
            np.zeros(0, dtype=getattr(column, 'dtype', np.int64))

    def __len__(self):
        """Return the number of rows searched."""
        return self.hi - self.lo

    def searchsorted(self, values, window=READ_BLOCK):
        """
        Return where each value goes in rows lo..hi-1 (numpy's search, side left), plus lo.

        Values in any order; the windows read hold at most ``window`` rows (more only
        for one stride).

        """
        values = np.asarray(values)
        out = np.full(values.shape, self.lo, dtype=np.int64)
        if not values.size or self.hi <= self.lo:
            return out
        S = self.stride
        b = np.searchsorted(self.coarse, values)        # coarse[b-1] < v <= coarse[b]
        # the answer of a value in bucket b >= 1 is in rows (b-1)*S+1 .. b*S (local)
        todo = np.flatnonzero(b > 0)
        if not todo.size:
            return out
        order = todo[np.argsort(b[todo], kind='stable')]
        bs = b[order]
        cuts = np.flatnonzero(np.diff(bs)) + 1
        starts = np.concatenate([[0], cuts])
        ends = np.concatenate([cuts, [bs.size]])
        i = 0
        n = self.hi - self.lo
        while i < starts.size:
            j = i           # buckets i..j-1 read together while the window stays small
            while j < starts.size and (bs[starts[j]] - bs[starts[i]] + 1) * S <= \
                    max(window, S):
                j += 1
            first, last = int(bs[starts[i]]), int(bs[starts[j - 1]])
            w0 = (first - 1) * S
            w1 = min(n, last * S + 1)
            rows = np.asarray(self.column[self.lo + w0:self.lo + w1])
            sel = order[starts[i]:ends[j - 1]]
            out[sel] = self.lo + w0 + np.searchsorted(rows, values[sel])
            i = j
        return out


def decimated_rows(n, limit, mask=None, block=READ_BLOCK):
    """
    Return the rows kept when the rows of ``mask`` are decimated to about ``limit``.

    Without ``mask``: the slice of :func:`observer_ros.evaluation.plots.decimate` over ``n``
    rows. With a boolean column ``mask`` (array or spilled), or a function
    ``mask(lo, hi)`` giving its rows lo..hi-1: the indices of the true rows, every
    ``ceil(count / limit)``-th of them from the first (``np.flatnonzero(mask)``
    decimated), found a block at a time.

    """
    if mask is None:
        return slice(None) if n <= limit else slice(None, None, int(math.ceil(n / limit)))
    part = mask if callable(mask) else (lambda lo, hi: mask[lo:hi])
    count = sum(int(np.count_nonzero(part(lo, min(n, lo + block))))
                for lo in range(0, n, block))
    step = 1 if count <= limit else int(math.ceil(count / limit))
    kept, seen = [], 0
    for lo in range(0, n, block):
        rows = np.flatnonzero(part(lo, min(n, lo + block)))
        first = (-seen) % step                  # the first true row here kept
        kept.append(rows[first::step] + lo)
        seen += rows.size
    return np.concatenate(kept) if kept else np.zeros(0, dtype=np.int64)
