# observer_ros.replay.events: the recorded messages in the order the node took them.
"""
The recording's measurements and commands merged into the observer node's order.

:class:`Events` gives bag order for a free-running node and stamp order within each
epoch (:func:`epochs_of`) for a lockstep one; :class:`Rows` reads its columns as Python
ints a block at a time for the replay's main loop.

"""

import numpy as np

from ..bag.spill import Sink
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


def epochs_from_cuts(cuts, size, spill=None, block=None):
    """Return the epoch of each of ``size`` rows whose epochs start at ``cuts`` (int64)."""
    block = block or EVENT_BLOCK
    epoch = Sink(np.int64, (), size, spill)
    for lo in range(0, size, block):
        epoch.append(np.searchsorted(cuts, np.arange(lo, min(size, lo + block)),
                                     side='right'))
    return epoch.result()


def index_type(size):
    """Return int32 for indices below ``size`` when they fit (half the memory), else int64."""
    return np.int32 if size < (1 << 31) else np.int64


def epoch_cuts(stamp_ns, tolerance, block=None):
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


def _in_order(stamp, kind, e0, e1, block=None):
    """
    Tell whether events e0..e1-1 are sorted by (stamp, command after measurement).

    A block at a time (the columns may be spilled).

    """
    block = block or EVENT_BLOCK
    for lo in range(e0, max(e1 - 1, e0), block):
        hi = min(e1, lo + block + 1)
        a = stamp[lo:hi]
        c = kind[lo:hi] < 0
        if np.any((a[1:] < a[:-1]) | ((a[1:] == a[:-1]) & (c[1:] < c[:-1]))):
            return False
    return True


class _Source:
    """
    The messages of one stream that reach the admission, read a block at a time.

    ``kind``: the sensor's index, -1 for the commands. A message reaches it unless its
    stamp is malformed (``bad_stamps``) or it does not give the values (counted under
    ``bad_values``): the admission's order.

    """

    def __init__(self, kind, stream, counts, bad_values):
        self.kind, self.stream = kind, stream
        self.used = 0
        self.last_seq = -1                      # the bag position of the last one used
        for lo in range(0, len(stream), EVENT_BLOCK):
            ok, bad = self._usable(lo, lo + EVENT_BLOCK)
            if stream.has_header:
                counts['bad_stamps'] = counts.get('bad_stamps', 0) + bad
            counts[bad_values] = counts.get(bad_values, 0) + \
                int(ok.size - np.count_nonzero(ok)) - bad
            used = np.flatnonzero(ok)
            self.used += used.size
            if used.size:
                self.last_seq = int(stream.seq[lo + int(used[-1])])
        self.next = 0                           # the next message not yet buffered
        self.buf_seq = self.buf_idx = np.zeros(0, dtype=np.int64)

    def _usable(self, lo, hi):
        """Return which messages lo..hi-1 are used, and how many have a malformed stamp."""
        ok = np.array(self.stream.valid[lo:hi], dtype=bool)
        if not self.stream.has_header:
            return ok, 0
        bad = malformed_ns(self.stream.stamp_ns[lo:hi])
        ok &= ~bad
        return ok, int(np.count_nonzero(bad))

    def fill(self):
        """Buffer the next used messages if none is buffered; False when none is left."""
        while not self.buf_seq.size and self.next < len(self.stream):
            lo = self.next
            self.next = min(len(self.stream), lo + EVENT_BLOCK)
            used = np.flatnonzero(self._usable(lo, self.next)[0])
            self.buf_idx = used + lo
            self.buf_seq = np.asarray(self.stream.seq[lo:self.next], dtype=np.int64)[used]
        return bool(self.buf_seq.size)

    def exhausted(self):
        """Tell whether every message is buffered."""
        return self.next >= len(self.stream)

    def take(self, horizon):
        """Return (bag positions, indices) of the buffered messages up to ``horizon``."""
        k = int(np.searchsorted(self.buf_seq, horizon, side='right'))
        out = self.buf_seq[:k], self.buf_idx[:k]
        self.buf_seq, self.buf_idx = self.buf_seq[k:], self.buf_idx[k:]
        return out


class Events:
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

    The columns ``seq`` (bag position), ``kind`` (sensor index, -1 a command) and
    ``idx`` (index in its stream) are built a block at a time, in memory or, with
    ``spill``, in temporary files (:class:`~observer_ros.bag.spill.SpilledColumn`).
    ``measurements`` counts the measurements, ``seq_max`` is the largest bag position.

    """

    def __init__(self, recording, sensors, plant, counts, lockstep=False,
                 clock_jump_tolerance=CLOCK_JUMP_TOLERANCE, spill=None):
        streams = [recording.sensors[s.name] for s in sensors]
        self.streams = streams
        self.spill = spill
        sources = []
        # the admission's order: a malformed stamp first (bad_stamps), then the values
        for k, stream in enumerate(streams):
            sources.append(_Source(k, stream, counts, 'bad_messages'))
        cmd = recording.command
        self.command = cmd
        if cmd is not None and plant.m:
            sources.append(_Source(-1, cmd, counts, 'bad_commands'))
        self.measurements = sum(s.used for s in sources if s.kind >= 0)
        self._bag_order(sources)
        if lockstep:
            self._lockstep(sources, clock_jump_tolerance)

    def _sinks(self, count, size):
        return (Sink(index_type(size), (), count, self.spill), Sink(np.int8, (), count,
                                                                    self.spill),
                Sink(index_type(size), (), count, self.spill))

    def _bag_order(self, sources):
        """
        Merge into bag order, a block of :data:`EVENT_BLOCK` messages at a time.

        The streams' bag positions increase, so their used messages are merged block by
        block: up to the smallest last position buffered of the streams not yet read to
        their end, every buffered message is in order.

        """
        count = sum(s.used for s in sources)
        size = max([s.last_seq + 1 for s in sources], default=0)
        self.seq_max = size - 1 if count else -1
        seq, kind, idx = self._sinks(count, size)
        while True:
            live = [s for s in sources if s.fill()]
            if not live:
                break
            ends = [int(s.buf_seq[-1]) for s in live if not s.exhausted()]
            horizon = min(ends) if ends else size
            parts = [(s.kind, *s.take(horizon)) for s in live]
            at = np.concatenate([p[1] for p in parts])
            order = np.argsort(at, kind='stable')
            seq.append(at[order])
            kind.append(np.concatenate([np.full(p[1].size, p[0], dtype=np.int8)
                                        for p in parts])[order])
            idx.append(np.concatenate([p[2] for p in parts])[order])
        self.seq, self.kind, self.idx = seq.result(), kind.result(), idx.result()

    def _lockstep(self, sources, clock_jump_tolerance):
        """
        Put the events in the node's order: stamps sorted within each epoch of bag order.

        Each epoch's events are sorted stably by (stamp, command after measurement): at
        equal keys bag order stays, as a sort by (epoch, stamp, command, seq) gives. One
        int64 key per event (``2 stamp + command``). An epoch already in that order (a
        recorder that received every command before the next measurement) is found so a
        block at a time and not sorted; an epoch that is not is sorted in memory (16
        bytes per event of that epoch).

        """
        size = len(self)
        stamp = Sink(np.int64, (), size, self.spill)
        for lo in range(0, size, EVENT_BLOCK):
            kb, ib = self.kind[lo:lo + EVENT_BLOCK], self.idx[lo:lo + EVENT_BLOCK]
            sb = np.empty(kb.size, dtype=np.int64)
            for s in sources:
                sel = kb == s.kind
                sb[sel] = s.stream.stamp_ns[ib[sel]]
            stamp.append(sb)
        stamp = stamp.result()
        cuts = epoch_cuts(stamp, clock_jump_tolerance)
        epochs = list(zip([0, *cuts], [*cuts, size]))
        todo = [not _in_order(stamp, self.kind, e0, e1) for e0, e1 in epochs]
        if not any(todo):
            return
        seq, kind, idx = self._sinks(size, self.seq_max + 1)
        for (e0, e1), sort in zip(epochs, todo):
            if not sort:                    # the stable sort would change nothing
                for lo in range(e0, e1, EVENT_BLOCK):
                    hi = min(e1, lo + EVENT_BLOCK)
                    for sink, col in zip((seq, kind, idx), (self.seq, self.kind, self.idx)):
                        sink.append(col[lo:hi])
                continue
            st = np.asarray(stamp[e0:e1])
            kd = np.asarray(self.kind[e0:e1])
            if -(1 << 62) <= int(st.min()) and int(st.max()) < (1 << 62):
                order = np.argsort(st * 2 + (kd < 0), kind='stable')
            else:                               # a stamp too large for the one key
                order = np.lexsort((kd < 0, st))
            del st
            kind.append(kd[order])
            del kd
            for sink, col in ((seq, self.seq), (idx, self.idx)):
                sink.append(np.asarray(col[e0:e1])[order])
        self.seq, self.kind, self.idx = seq.result(), kind.result(), idx.result()

    def __len__(self):
        return int(self.kind.size)


class Rows:
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
