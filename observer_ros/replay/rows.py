# observer_ros.replay.rows: the replay's rows, in memory or spilled a block at a time.
"""
The rows a replay writes (stamp, estimate, residual, ...), kept in memory or on disk.

:class:`ReplayOutputs` holds the output columns of :func:`observer_ros.replay.replay.replay`.
With ``spill`` it keeps only a buffer of about :data:`SPILL_BLOCK` rows plus the longest
bulk piece in memory and appends each full block to a temporary file per column, so a
bag of 10^7 messages does not hold its ~50 bytes per estimate in memory. The columns of
the finished replay are then :class:`~observer_ros.bag.spill.SpilledColumn` objects:
read-only arrays whose rows are read from the file when indexed (slices, index or
boolean arrays, a column key), a block at a time, with the very values that were
written (no conversion, so every figure computed from them is the in-memory one bit for
bit).

A late measurement revises earlier rows (written in place, on disk if spilled) and puts
the rows in stamp order at the end: a spilled replay with late measurements is read
back whole for that sort (the in-memory path's peak).

"""

import numpy as np

from ..bag.spill import spill_folder, SpilledColumn

__all__ = ['ReplayOutputs', 'SpilledColumn', 'SPILL_BLOCK']

SPILL_BLOCK = 1 << 16            # rows: a spilled replay appends this many at a time


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
            self.files = {name: SpilledColumn(getattr(self, name).dtype,
                                              getattr(self, name).shape[1:],
                                              spill_folder(spill))
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
