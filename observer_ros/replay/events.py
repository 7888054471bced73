# observer_ros.replay.events: the recorded messages in the order the node took them.
"""
The recording's measurements and commands merged into the observer node's order.

:class:`_Events` gives bag order for a free-running node and stamp order within each
epoch (:func:`epochs_of`) for a lockstep one; :class:`_Rows` reads its columns as Python
ints a block at a time for the replay's main loop.

"""

import numpy as np

from ..core.estimators.admission import CLOCK_JUMP_TOLERANCE, malformed_ns

__all__ = ['epochs_of', 'CLOCK_JUMP_TOLERANCE']

EVENT_BLOCK = 1 << 16          # messages: the events are merged this many at a time


def epochs_of(stamp_ns, tolerance=CLOCK_JUMP_TOLERANCE):
    """
    Return the epoch of each stamp: the runs of a sequence split where it jumps back.

    Parameters
    ----------
    stamp_ns : (N,) int array
        Stamps in bag order.
    tolerance : float
        A step back of more than this many seconds starts a new epoch.

    Returns
    -------
    epoch : (N,) int64 ndarray
        0 for the first run, 1 after the first jump back, ...

    """
    stamp_ns = np.asarray(stamp_ns, dtype=np.int64)
    epoch = np.zeros(stamp_ns.size, dtype=np.int64)
    if stamp_ns.size < 2:
        return epoch
    tol = int(round(tolerance * 1e9))
    # a jump is measured against the latest stamp of the current epoch: a running
    # maximum that restarts at each jump, in a loop over the (few) jumps.
    start, e = 0, 0
    while True:
        seg = stamp_ns[start:]
        running = np.maximum.accumulate(seg)
        back = np.flatnonzero(seg[1:] < running[:-1] - tol)
        if not back.size:
            epoch[start:] = e
            return epoch
        stop = start + int(back[0]) + 1
        epoch[start:stop] = e
        start, e = stop, e + 1


def _index_type(size):
    """Return int32 for indices below ``size`` when they fit (half the memory), else int64."""
    return np.int32 if size < (1 << 31) else np.int64


def _epoch_cuts(stamp_ns, tolerance, block=None):
    """
    Return where the epochs of a sequence of stamps start (after the first), as a list.

    The positions where :func:`epochs_of` increases, found a block at a time (no
    whole-sequence temporaries): the running maximum of the current epoch is carried
    from block to block and restarts at each jump back.

    """
    block = block or EVENT_BLOCK
    tol = int(round(tolerance * 1e9))
    cuts = []
    lo, top = 0, None                           # top: the current epoch's latest stamp
    while lo < stamp_ns.size:
        seg = stamp_ns[lo:lo + block]
        if top is None:
            top = int(seg[0])
        running = np.maximum.accumulate(np.concatenate([[top], seg]))
        back = np.flatnonzero(seg < running[:-1] - tol)
        if back.size:
            lo += int(back[0])
            cuts.append(lo)
            top = None
            continue
        top = int(running[-1])
        lo += seg.size
    return cuts


def _in_order(stamp, kind, block=None):
    """Tell whether events are sorted by (stamp, command after measurement), a block at a time."""
    block = block or EVENT_BLOCK
    for lo in range(0, max(stamp.size - 1, 0), block):
        a = stamp[lo:lo + block + 1]
        c = kind[lo:lo + block + 1] < 0
        if np.any((a[1:] < a[:-1]) | ((a[1:] == a[:-1]) & (c[1:] < c[:-1]))):
            return False
    return True


class _Events:
    """
    The recording's measurements and commands merged into the order the node used.

    A free-running (``realtime``) node handles messages as they arrive: bag order, the
    recorder's receive order. A ``lockstep`` observer waits, after each estimate, for the
    command that answers it before it takes the next measurement, so its order is the
    stamps' order with, at one stamp, the measurement before the command; the recorder may
    receive u[k] after y[k+1] (they come from different processes), so bag order is not
    the node's order there. The stamps are sorted within each epoch of the bag order
    (:func:`epochs_of`): a bag that loops, or a recording of several runs, keeps its
    clock jumps where they were received.

    """

    def __init__(self, recording, sensors, plant, counts, lockstep=False,
                 clock_jump_tolerance=CLOCK_JUMP_TOLERANCE):
        streams = [recording.sensors[s.name] for s in sensors]
        self.streams = streams
        sources = []                            # (kind, stream, messages used: bool)
        # the admission's order: a malformed stamp first (bad_stamps), then the values
        for k, stream in enumerate(streams):
            sources.append((k, stream, _usable(stream, counts, 'bad_messages')))
        cmd = recording.command
        self.command = cmd
        if cmd is not None and plant.m:
            sources.append((-1, cmd, _usable(cmd, counts, 'bad_commands')))
        if lockstep:
            self._lockstep(sources, clock_jump_tolerance)
        else:
            self._bag_order(sources)

    def _bag_order(self, sources):
        """
        Merge into bag order: each event put at its bag position (seq), no sort.

        A block of :data:`EVENT_BLOCK` messages or positions at a time: the whole-bag
        arrays are the bag positions' kind and index and the three columns kept.

        """
        size = 0
        for _, stream, ok in sources:
            for lo in range(0, ok.size, EVENT_BLOCK):
                at = stream.seq[lo:lo + EVENT_BLOCK][ok[lo:lo + EVENT_BLOCK]]
                size = max(size, int(at.max()) + 1 if at.size else 0)
        kind = np.full(size, -2, dtype=np.int8)     # -2: no event at this position
        idx = np.empty(size, dtype=_index_type(size))
        for k, stream, ok in sources:
            for lo in range(0, ok.size, EVENT_BLOCK):
                sel = np.flatnonzero(ok[lo:lo + EVENT_BLOCK]) + lo
                at = stream.seq[sel]
                kind[at] = k
                idx[at] = sel
        blocks = range(0, size, EVENT_BLOCK)
        count = sum(int(np.count_nonzero(kind[lo:lo + EVENT_BLOCK] != -2)) for lo in blocks)
        self.seq = np.empty(count, dtype=_index_type(size))
        self.kind = np.empty(count, dtype=np.int8)
        self.idx = np.empty(count, dtype=idx.dtype)
        done = 0
        for lo in blocks:
            at = np.flatnonzero(kind[lo:lo + EVENT_BLOCK] != -2)
            self.seq[done:done + at.size] = at + lo
            self.kind[done:done + at.size] = kind[lo:lo + EVENT_BLOCK][at]
            self.idx[done:done + at.size] = idx[lo:lo + EVENT_BLOCK][at]
            done += at.size

    def _lockstep(self, sources, clock_jump_tolerance):
        """
        Merge into the node's order: stamps sorted within each epoch of bag order.

        From bag order, each epoch's events are sorted stably by (stamp, command after
        measurement): at equal keys bag order stays, as a sort by (epoch, stamp,
        command, seq) gives. One int64 key per event (``2 stamp + command``). An epoch
        already in that order (a recorder that received every command before the next
        measurement) is found so a block at a time and not sorted.

        """
        self._bag_order(sources)
        kind, idx = self.kind, self.idx
        stamp = np.empty(kind.size, dtype=np.int64)
        for lo in range(0, kind.size, EVENT_BLOCK):
            kb, ib, sb = (a[lo:lo + EVENT_BLOCK] for a in (kind, idx, stamp))
            for k, stream, _ in sources:
                sel = kb == k
                sb[sel] = stream.stamp_ns[ib[sel]]
        cuts = _epoch_cuts(stamp, clock_jump_tolerance)
        order = None
        for e0, e1 in zip([0, *cuts], [*cuts, kind.size]):
            st = stamp[e0:e1]
            if _in_order(st, kind[e0:e1]):
                continue                        # the stable sort would change nothing
            if order is None:
                order = np.arange(kind.size)
            if -(1 << 62) <= int(st.min()) and int(st.max()) < (1 << 62):
                key = st * 2 + (kind[e0:e1] < 0)
                order[e0:e1] = np.argsort(key, kind='stable') + e0
            else:                               # a stamp too large for the one key
                order[e0:e1] = np.lexsort((kind[e0:e1] < 0, st)) + e0
        del stamp
        if order is not None:
            self.seq = self.seq[order]
            self.kind = kind[order]
            self.idx = self.idx[order]

    def __len__(self):
        return int(self.kind.size)


def _usable(stream, counts, bad_values):
    """Return which messages of a stream reach the admission; count the others."""
    ok = stream.valid.copy()
    if stream.has_header:
        bad = malformed_ns(stream.stamp_ns)
        counts['bad_stamps'] = counts.get('bad_stamps', 0) + int(bad.sum())
        ok &= ~bad
        counts[bad_values] = counts.get(bad_values, 0) + int((~stream.valid & ~bad).sum())
    else:
        counts[bad_values] = counts.get(bad_values, 0) + int((~stream.valid).sum())
    return ok


class _Rows:
    """
    Rows of integer columns as tuples of Python ints, converted a block at a time.

    The main loop reads every event it does not skip in bulk; lists of the whole columns
    would hold three Python ints per event of the bag at once (about 100 bytes each).

    """

    def __init__(self, *columns, block=1 << 16):
        self.columns = columns
        self.size = int(columns[0].size)
        self.block = block
        self.lo = self.hi = 0
        self.rows = []

    def __call__(self, i):
        if not self.lo <= i < self.hi:
            self.lo, self.hi = i, min(self.size, i + self.block)
            self.rows = list(zip(*(c[self.lo:self.hi].tolist() for c in self.columns)))
        return self.rows[i - self.lo]
