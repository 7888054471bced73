# observer_ros.bag.replay_events: the recorded messages in the order the node took them.
"""
The recording's measurements and commands merged into the observer node's order.

:class:`_Events` gives bag order for a free-running node and stamp order within each
epoch (:func:`epochs_of`) for a lockstep one; :class:`_Rows` reads its columns as Python
ints a block at a time for the replay's main loop.

"""

import numpy as np

__all__ = ['epochs_of', 'CLOCK_JUMP_TOLERANCE']

CLOCK_JUMP_TOLERANCE = 0.5     # s, as the observer node's clock_jump_tolerance


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
        sources = []                            # (kind, stream, selected indices)
        for k, stream in enumerate(streams):
            ok = stream.valid.copy()
            if stream.has_header:
                zero = stream.stamp_ns == 0
                counts['zero_stamps'] += int((zero & ok).sum())
                ok &= ~zero
            counts['bad_messages'] += int((~stream.valid).sum())
            sources.append((k, stream, np.flatnonzero(ok)))
        cmd = recording.command
        self.command = cmd
        if cmd is not None and plant.m:
            counts['bad_commands'] += int((~cmd.valid).sum())
            sources.append((-1, cmd, np.flatnonzero(cmd.valid)))
        if lockstep:
            self._lockstep(sources, clock_jump_tolerance)
        else:
            self._bag_order(sources)

    def _bag_order(self, sources):
        """Merge into bag order: each event put at its bag position (seq), no sort."""
        size = max((int(st.seq[sel].max()) + 1 for _, st, sel in sources if sel.size),
                   default=0)
        kind = np.full(size, -2, dtype=np.int8)     # -2: no event at this position
        idx = np.empty(size, dtype=_index_type(size))
        for k, stream, sel in sources:
            at = stream.seq[sel]
            kind[at] = k
            idx[at] = sel
        self.seq = np.flatnonzero(kind != -2)
        self.kind = kind[self.seq]
        del kind
        self.idx = idx[self.seq]

    def _lockstep(self, sources, clock_jump_tolerance):
        """
        Merge into the node's order: stamps sorted within each epoch of bag order.

        From bag order, each epoch's events are sorted stably by (stamp, command after
        measurement): at equal keys bag order stays, as a sort by (epoch, stamp,
        command, seq) gives. One int64 key per event (``2 stamp + command``).

        """
        self._bag_order(sources)
        kind = self.kind
        stamp = np.empty(kind.size, dtype=np.int64)
        for k, stream, _ in sources:
            sel = np.flatnonzero(kind == k)
            stamp[sel] = stream.stamp_ns[self.idx[sel]]
        cuts = np.flatnonzero(np.diff(epochs_of(stamp, clock_jump_tolerance))) + 1
        order = np.empty(kind.size, dtype=np.int64)
        for e0, e1 in zip([0, *cuts.tolist()], [*cuts.tolist(), kind.size]):
            st = stamp[e0:e1]
            if st.size and -(1 << 62) <= int(st.min()) and int(st.max()) < (1 << 62):
                key = st * 2 + (kind[e0:e1] < 0)
                order[e0:e1] = np.argsort(key, kind='stable') + e0
            else:                               # a stamp too large for the one key
                order[e0:e1] = np.lexsort((kind[e0:e1] < 0, st)) + e0
        del stamp
        if np.any(order != np.arange(order.size)):
            self.seq = self.seq[order]
            self.kind = kind[order]
            self.idx = self.idx[order]

    def __len__(self):
        return int(self.kind.size)


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
