# observer_ros.replay.rows: the replay's rows, in memory or spilled a block at a time.
"""
The rows a replay writes (stamp, estimate, residual, ...), kept in memory or on disk.

:class:`ReplayOutputs` holds the output columns of :func:`observer_ros.replay.replay.replay`.
With ``spill`` it keeps only a buffer of about :data:`SPILL_BLOCK` rows plus the longest
bulk piece in memory and appends each full block to a temporary file per column, so a
bag of 10^7 messages does not hold its ~50 bytes per estimate in memory. The columns of
the finished replay are then :class:`SpilledColumn` objects: read-only arrays whose rows
are read from the file when indexed (slices, index or boolean arrays, a column key), a
block at a time, with the very values that were written (no conversion, so every figure
computed from them is the in-memory one bit for bit).

A late measurement revises earlier rows (written in place, on disk if spilled) and puts
the rows in stamp order at the end: a spilled replay with late measurements is read
back whole for that sort (the in-memory path's peak).

"""

import tempfile

import numpy as np

from ..bag.errors import BagToolError

__all__ = ['ReplayOutputs', 'SpilledColumn', 'SPILL_BLOCK']

SPILL_BLOCK = 1 << 16            # rows: a spilled replay appends this many at a time
READ_BLOCK = 1 << 16             # rows: a spilled column is read this many at a time


class SpilledColumn:
    """
    A column of rows in a temporary file, indexed like a read-only numpy array.

    ``column[rows]`` and ``column[rows, cols]`` read the rows asked for, a block of
    :data:`READ_BLOCK` rows at a time; ``np.asarray(column)`` reads them all.

    """

    def __init__(self, dtype, row_shape=(), directory=None):
        self.dtype = np.dtype(dtype)
        self.row_shape = tuple(row_shape)
        self.row_bytes = self.dtype.itemsize * int(np.prod(self.row_shape, dtype=np.int64))
        self.directory = directory
        try:
            self.file = tempfile.TemporaryFile(prefix='observer_eval_', dir=directory)
        except OSError as err:
            where = directory or tempfile.gettempdir()
            raise BagToolError(f"cannot write the replay's temporary files in {where}: "
                               f'{err.strerror or err} (set TMPDIR to a writable folder, or '
                               'keep them in memory: --in-memory)') from None
        self.rows = 0

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
        try:
            self.file.seek(i * self.row_bytes)
            self.file.write(rows.data.cast('B'))
        except OSError as err:      # a full disk: said, not a traceback
            raise BagToolError(f"cannot write the replay's temporary files in "
                               f'{self.directory or tempfile.gettempdir()}: '
                               f'{err.strerror or err} (about {self.row_bytes} bytes per '
                               'estimate per column; set TMPDIR to a folder with room, or '
                               'keep them in memory: --in-memory)') from None

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

    def _reduce(self, func):
        if not self.size:
            raise ValueError('zero-size column has no minimum or maximum')
        return func([func(self.read(lo, lo + READ_BLOCK))
                     for lo in range(0, self.rows, READ_BLOCK)])

    def __getitem__(self, key):
        """Return the rows (and columns) asked for, as numpy indexing gives them."""
        rest = ()
        if isinstance(key, tuple):
            key, rest = key[0], key[1:]
        if isinstance(key, (int, np.integer)):
            i = int(key) + (self.rows if key < 0 else 0)
            if not 0 <= i < self.rows:
                raise IndexError(f'row {int(key)} of {self.rows}')
            return self.read(i, i + 1)[(0, *rest)]
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


class ReplayOutputs:
    """
    The output columns of a replay: rows written at global row numbers.

    ``local(m)`` returns the buffer index of row m, appending the full blocks before it
    to the spill files first (with ``spill``); rows m.. up to ``ahead`` further must be
    written through that index before the next call. ``cols`` are the buffers:
    ``ns, x, r, e, epoch, seq, sensor`` (``e``: Kalman whitened residuals, else None).

    """

    NAMES = ('ns', 'x', 'r', 'e', 'epoch', 'seq', 'sensor')

    def __init__(self, rows, n, p, kalman, epoch_type, seq_type, sensor_type, spill=None,
                 ahead=0):
        self.spill = spill
        self.base = 0
        cap = rows if spill is None else min(rows, SPILL_BLOCK + ahead + 1)
        self.ns = np.zeros(cap, dtype=np.int64)
        self.x = np.zeros((cap, n))
        self.r = np.full((cap, p), np.nan)
        self.e = np.full((cap, p), np.nan) if kalman else None
        self.epoch = np.zeros(cap, dtype=epoch_type)
        self.seq = np.zeros(cap, dtype=seq_type)
        self.sensor = np.zeros(cap, dtype=sensor_type)
        self.files = None
        if spill is not None:
            directory = None if spill is True else spill
            self.files = {name: SpilledColumn(getattr(self, name).dtype,
                                              getattr(self, name).shape[1:], directory)
                          for name in self.NAMES if getattr(self, name) is not None}

    def local(self, m):
        """Return the buffer index of row m, spilling the rows before it when due."""
        if self.files is not None and m - self.base >= SPILL_BLOCK:
            self._flush(m)
        return m - self.base

    def _flush(self, m):
        k = m - self.base
        for name, column in self.files.items():
            buf = getattr(self, name)
            column.append(buf[:k])
            buf[:k] = np.nan if buf.dtype.kind == 'f' else 0
        self.base = m

    def sensor_of(self, r):
        """Return the sensor of row r (written before)."""
        if r >= self.base:
            return int(self.sensor[r - self.base])
        return int(self.files['sensor'][r])

    def revise(self, r, x, cols, residual, whitened):
        """Overwrite row r's estimate and its residual's columns (a late measurement)."""
        if r >= self.base:
            i = r - self.base
            self.x[i] = x
            self.r[i, cols] = residual
            if whitened is not None:
                self.e[i, cols] = whitened
            return
        files = self.files
        files['x'].write_row(r, x)
        row = files['r'][r]
        row[cols] = residual
        files['r'].write_row(r, row)
        if whitened is not None:
            row = files['e'][r]
            row[cols] = whitened
            files['e'].write_row(r, row)

    def finish(self, m, sort=False):
        """
        Return the columns of rows 0..m-1 (a dict by :data:`NAMES`).

        In memory: arrays; spilled: :class:`SpilledColumn` objects. With ``sort`` (late
        measurements) the rows are put in stamp order within each epoch (a stable sort),
        and spilled columns are read back whole for it.

        """
        if self.files is not None:
            self._flush(m)
            cols = {name: self.files.get(name) for name in self.NAMES}
            if not sort:
                return cols
            cols = {name: None if c is None else np.asarray(c) for name, c in cols.items()}
        else:
            cols = {name: None if getattr(self, name) is None else getattr(self, name)[:m]
                    for name in self.NAMES}
        if sort:
            order = np.lexsort((cols['ns'], cols['epoch']))
            cols = {name: None if c is None else c[order] for name, c in cols.items()}
        return cols
