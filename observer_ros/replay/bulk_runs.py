# observer_ros.replay.bulk_runs: where the replay can take measurements in bulk.
"""
Find the stretches of measurements the replay can evaluate in bulk.

A step between two accepted measurements is one affine map of the current-form
estimators when its stamp increases, every check of the node passes and every command
in the gap is stamped at the earlier measurement (:func:`_steps`). :class:`_Runs` finds
the stretches of such steps a block of :data:`RUN_BLOCK` steps at a time and cuts them
into pieces of at most :data:`MAX_RUN` steps; :func:`has_late` tells whether any message
would be late (then nothing is replayed in bulk). :mod:`observer_ros.replay.bulk_replay`
evaluates the pieces.

"""

import math

import numpy as np

from .events import index_type
from ..bag.spill import Sink
from ..core.errors import ObserverError

MIN_RUN = 64                   # steps: shorter stretches are replayed call by call
MAX_RUN = 1 << 17              # steps: longer stretches are replayed in pieces this long
RUN_BLOCK = 1 << 17           # steps: the bulk stretches are found this many at a time


def has_late(events, streams, cmd, length, block=1 << 16):
    """Tell whether a message comes, in replay order, up to ``length`` s after a newer one."""
    if length <= 0.0 or not len(events):
        return False
    top = -np.inf                               # the newest stamp so far
    for e0 in range(0, len(events), block):     # a block of events at a time
        kind, idx = events.kind[e0:e0 + block], events.idx[e0:e0 + block]
        t = np.empty(kind.size)
        for k, stream in enumerate(streams):
            sel = kind == k
            t[sel] = stream.stamp_ns[idx[sel]].astype(np.float64) * 1e-9    # Stream.t
        if cmd is not None:
            sel = kind < 0
            t[sel] = cmd.stamp_ns[idx[sel]].astype(np.float64) * 1e-9
        back = np.maximum.accumulate(np.concatenate([[top], t]))[1:] - t
        if np.any((back > 0.0) & (back <= length)):
            return True
        top = max(top, float(t.max()))
    return False


def _key_ids(key_of, steps):
    """
    Return the key id of each step length (-1: no valid key) and the keys by id.

    ``key_of`` is the estimator's ``cache.key``; ids number the distinct keys.

    """
    try:
        keys = np.array([key_of(v) for v in steps.tolist()], dtype=float)
    except (ObserverError, ValueError):
        keys = None                              # some step has no key: one at a time
    if keys is not None:
        ukeys, ids = np.unique(keys, return_inverse=True)
        return ids.reshape(-1).astype(np.int64), ukeys
    key_index = {}
    ids = np.empty(steps.size, dtype=np.int64)
    for i, v in enumerate(steps.tolist()):
        try:
            key = key_of(v)
        except (ObserverError, ValueError):
            ids[i] = -1
            continue
        ids[i] = key_index.setdefault(key, len(key_index))
    return ids, np.array(list(key_index), dtype=float)


def _steps(events, streams, cmd, est, jump, future_tolerance, mev, s0, s1, keyed=True,
           max_gap=math.inf):
    """
    Return the steps s0..s1-1 between measurements s0..s1 (indices into ``mev``).

    As ``(tm, key_id, keys, step_ok, gap_cmds)``: the measurements' stamps in seconds,
    each step's key id among ``keys`` (the distinct step keys of these steps, sorted;
    -1: no valid key), whether the step can be replayed in bulk, and the number of
    commands in the gap after each measurement s0..s1-1. Everything is local to the
    steps asked for: a block of a long bag, or one piece of a run. ``keyed=False``
    (only ``step_ok`` wanted): a continuous plant's every positive step has a key (its
    rounded length), so the keys are not computed (one call per distinct step length).

    """
    ev = mev[s0:s1 + 1]
    msens = events.kind[ev]
    midx = events.idx[ev]
    tm = np.empty(ev.size)
    ok = np.ones(ev.size, dtype=bool)
    for k, stream in enumerate(streams):
        sel = msens == k
        if not sel.any():
            continue
        tm[sel] = stream.stamp_ns[midx[sel]].astype(np.float64) * 1e-9     # as Stream.t
        if future_tolerance is not None:
            log = stream.log_ns[midx[sel]].astype(np.float64) * 1e-9
            ok[sel] = ~(tm[sel] - log > future_tolerance)
    h = np.diff(tm)
    key_id = np.full(h.size, -1, dtype=np.int64)
    pos = h > 0
    if not keyed and not est.plant.is_discrete:
        key_id[pos], keys = 0, None
    else:
        uniq, inv = np.unique(h[pos], return_inverse=True)
        ids, keys = _key_ids(est.cache.key, uniq)
        if ids.size:
            key_id[pos] = ids[inv.reshape(-1)]
    # a longer gap restarts the estimator (the admission's LONG_GAP): not a step
    step_ok = (key_id >= 0) & ok[1:] & (h <= max_gap)
    gap_cmds = np.zeros(h.size, dtype=np.int64)
    e0 = int(ev[0])
    cev = np.flatnonzero(events.kind[e0:int(ev[-1])] == -1) + e0   # commands in between
    if cev.size:
        ct = cmd.stamp_ns[events.idx[cev]].astype(np.float64) * 1e-9
        g = np.searchsorted(ev, cev) - 1        # the measurement before each command
        # at the earlier measurement's stamp: the admission's COMMAND (one held from
        # the estimate's time would be counted as such, call by call)
        good = ct == tm[g]
        step_ok[g[~good]] = False
        np.add.at(gap_cmds, g, 1)
    return tm, key_id, keys, step_ok, gap_cmds


class _Runs:
    """
    The pieces of the bulk stretches, by the event index of their first measurement.

    Found a block of :data:`RUN_BLOCK` steps at a time, keeping the stretches' ends; the
    arrays a piece needs (stamps, step classes, commands per gap) are built when the
    replay reaches it, over the piece's own steps (:meth:`get`), so they never exist
    for the whole bag. The stretches, their pieces and every piece's numbers are those
    of the whole-bag computation: a step's flag depends only on its two measurements
    and the events between them, and a piece's class ids keep the order of its keys.

    """

    def __init__(self, events, streams, cmd, est, jump, future_tolerance, block=None,
                 max_gap=math.inf):
        self.args = (events, streams, cmd, est, jump, future_tolerance)
        self.max_gap = max_gap
        self.pieces = {}
        block = block or RUN_BLOCK
        spill = getattr(events, 'spill', None)      # events in temporary files: these too
        mev = self.mev = _measurement_events(events.kind, block, spill)
        M = mev.size
        if M < MIN_RUN + 1:
            return
        starts, ends = [], []                       # of the stretches of good steps
        prev = np.zeros(1, dtype=np.int8)           # the flag of the step before a block
        for s0 in range(0, M - 1, block):
            s1 = min(M - 1, s0 + block)
            flags = self._steps(s0, s1, keyed=False)[3].astype(np.int8)
            d = np.diff(np.concatenate([prev, flags]))
            starts.append(np.flatnonzero(d == 1) + s0)
            ends.append(np.flatnonzero(d == -1) + s0)
            prev = flags[-1:]
        ends.append(np.full(int(prev[0]), M - 1, dtype=np.int64))
        for s0, s1 in zip(np.concatenate(starts), np.concatenate(ends)):
            a, b = int(s0), int(s1)                 # steps a..b-1: measurements a+1..b
            if b + 1 < M and self._t(b + 1) == self._t(b):
                b -= 1                              # the next one fuses with b: b by call
            if b - a < MIN_RUN:
                continue
            # pieces of at most MAX_RUN steps, replayed one after the other: the memory
            # of a bulk stretch (a dozen arrays of its steps) stays bounded on a long bag
            cuts = list(range(a, b, MAX_RUN)) + [b]
            if len(cuts) > 2 and cuts[-1] - cuts[-2] < MIN_RUN:
                del cuts[-2]                        # no short last piece
            for p0, p1 in zip(cuts, cuts[1:]):
                self.pieces[int(mev[p0])] = (p0, p1)

    def _steps(self, s0, s1, keyed=True):
        return _steps(*self.args, self.mev, s0, s1, keyed, self.max_gap)

    def _t(self, i):
        events, streams = self.args[:2]
        e = self.mev[i]
        return float(streams[events.kind[e]].stamp_ns[events.idx[e]]) * 1e-9

    def __bool__(self):
        return bool(self.pieces)

    def get(self, i):
        """Return the piece starting at event i as a run (None: none starts there)."""
        piece = self.pieces.get(i)
        if piece is None:
            return None
        p0, p1 = piece
        events, streams = self.args[:2]
        tm, key_id, keys, _, gap_cmds = self._steps(p0, p1)
        mev = self.mev[p0:p1 + 1]
        msens = events.kind[mev[1:]]
        return {'tm': tm, 'mev': mev, 'kind': events.kind, 'idx': events.idx,
                'seq': events.seq, 'gap_cmds': gap_cmds,
                'step_class': key_id * len(streams) + msens, 'keys': keys,
                'a': 0, 'b': p1 - p0, 'rest': self.mev.size - p0,
                'commands': int(gap_cmds.sum()), 'last_event': int(mev[-1])}


def _measurement_events(kind, block, spill=None):
    """
    Return the event indices of the measurements (kind >= 0), found a block at a time.

    In memory, or with ``spill`` in a temporary file.

    """
    blocks = range(0, kind.size, block)
    count = sum(int(np.count_nonzero(kind[e0:e0 + block] >= 0)) for e0 in blocks)
    mev = Sink(index_type(kind.size), (), count, spill)
    for e0 in blocks:
        mev.append(np.flatnonzero(kind[e0:e0 + block] >= 0) + e0)
    return mev.result()


def find_runs(events, streams, cmd, est, jump, future_tolerance, block=None,
              max_gap=math.inf):
    """
    Stretches of measurements each of whose steps is an affine map of the previous x.

    A step goes from one accepted measurement to the next; it is one affine map
    ``x_k = F x_{k-1} + G y_k + H u`` of the current-form estimators when the stamp
    increases (no fused correction at one stamp) by at most ``max_gap`` (a longer gap
    restarts the estimator), every check of the node passes, and every command in
    between is stamped at the earlier measurement. Its class is (step key, sensor): F,
    G, H depend only on those. "In between" is in the replay order (``events``), which in lockstep
    is not the bag order: positions in ``events``, never ``seq``, place the commands.

    Returns a :class:`_Runs`: ``get(event index of measurement a)`` gives the run of
    measurements a+1..b (a piece of at most :data:`MAX_RUN` steps), indices local to
    the piece (``a`` is 0).

    """
    return _Runs(events, streams, cmd, est, jump, future_tolerance, block, max_gap)
