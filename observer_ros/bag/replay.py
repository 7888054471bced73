# observer_ros.bag.replay: run an estimator over recorded measurements as the node does.
"""
Replay recorded measurements and commands through an estimator, as the observer node.

The events (every sensor message and every ``control/u`` message of a
:class:`~observer_ros.bag.reader.Recording`) are taken in the order the node took them:
bag order, the order the recorder received them (ties in receive time keep the order in
the file); for a vehicle whose ``simulator.mode`` is ``lockstep``, stamp order within
each epoch of the bag (a measurement before a command at one stamp), since the recorder
may receive a command after the next measurement (:class:`_Events`). Each one is handled
as ``observer_ros.nodes.observer_node`` handles it:

- a measurement at stamp t (``stamp_to_sec``; the receive time for a message without a
  header): a zero stamp or a message that does not give the outputs is skipped; a stamp
  more than ``clock_jump_tolerance`` before the estimate's time is a clock jump (looping
  bag): the estimator is reset; a smaller step back is skipped (out of order), as is a
  repeated stamp of the same sensor and a stamp more than ``future_tolerance`` ahead of
  the receive time. Otherwise ``x_hat = est.correct(t, y, plant.output_rows(outputs))``;
  a non-finite estimate resets the estimator at t.
- a command at stamp t: ``est.set_input(t, u)``; a stamp before the estimate's time is
  held from the estimate's time on, or resets the estimator if it is a clock jump.
- a measurement or command stamped before the estimate's time but inside the vehicle's
  ``observer.history_length`` is used at its own stamp, through the same
  :class:`~observer_ros.core.estimators.History` as the node (``out_of_order`` counts
  only those older than the history). The estimates it revises are recorded as revised
  (each row is the estimate at its stamp once every message of the history is in), and
  the rows are then in stamp order within each epoch: a bag in receive order gives the
  estimates of the same bag in stamp order.

So replaying a noise-free recorded run through the vehicle's own design reproduces the
live estimate to round-off.

Long single-sensor stretches at a constant step are replayed in bulk for the
current-form estimators (full and reduced order with poles, open loop): one step of
such an estimator is the affine map ``x_k = F x_{k-1} + G y_k + H u_{k-1}``, whose
matrices are measured by calling the estimator itself on unit vectors; the recursion is
then evaluated in blocks with numpy. The input held at each step is that of the last
command before it in the replay order (the order above, which the main loop walks; in
lockstep it is not the bag order). Every stretch is checked before it is used:

- every step against its affine map, with the held input found again from the events
  (:func:`_check_steps`);
- windows of the estimator's own calls, the recorded events handled as the main loop
  handles them (:func:`_check_windows`): the first and last steps, a spread across the
  stretch, and its irregular places (a gap with other than one command, events whose bag
  order is not the replay order, a change of step length or sensor);
- one step of each step class from its bulk prior.

A stretch that differs anywhere by more than round-off (:data:`CHECK_RTOL` of the size
of the terms of its steps so far) is replayed call by call instead, with a warning.
An unstable estimator (the open loop of an unstable plant) is replayed call by call when
its growth to the end of the bag exceeds :data:`MAX_GROWTH`, since it would amplify the
bulk's different round-off as much. ``exact=True`` turns bulk replay off.

"""

import copy
from dataclasses import dataclass, field
from typing import Dict, Optional, Tuple

import numpy as np

from .errors import BagToolError
from .step_maps import bulk_maps
from ..core.compensator import design_vehicle
from ..core.errors import ObserverError
from ..core.estimators import History, make_estimator
from ..core.innovation import sequence_health_blocks, transient_time, whiten

__all__ = ['Replay', 'replay', 'live_replay', 'epochs_of', 'affine_scan', 'innovation_health',
           'CLOCK_JUMP_TOLERANCE', 'FUTURE_TOLERANCE']

CLOCK_JUMP_TOLERANCE = 0.5     # s, as the observer node's clock_jump_tolerance
FUTURE_TOLERANCE = 10.0        # s, as the observer node's future_tolerance
MIN_RUN = 64                   # steps: shorter stretches are replayed call by call
MAX_RUN = 1 << 17              # steps: longer stretches are replayed in pieces this long
CHECK_STEPS = 16               # steps of each checked window of a bulk stretch
CHECK_WINDOWS = 8              # windows spread over a stretch (first and last included)
CHECK_IRREGULAR = 16           # most windows at irregular places of a stretch
IRREGULAR_STEPS = 3            # steps of each of those
MAX_GROWTH = 1e3               # unstable step maps: most growth to the end of the bag
CHECK_RTOL = 1e-10             # bulk vs call, relative to the terms of the steps so far
CHECK_CLASSES = 32             # step classes checked call by call (jittered: one per step)
RUN_BLOCK = 1 << 17           # steps: the bulk stretches are found this many at a time
HEALTH_BLOCK = 1 << 16        # estimates: the innovation health takes this many at a time
_PROGRESS_EVERY = 1 << 15


@dataclass
class Replay:
    """
    The estimates of one observer configuration over a recording.

    One row per accepted measurement, in bag order: ``x_hat[i]`` is the estimate
    published after the measurement stamped ``stamp_ns[i]``, ``residual[i]`` its
    residual (NaN for the outputs that message does not carry), ``epoch[i]`` the number
    of clock-jump resets before it.

    """

    name: str
    vehicle: object
    stamp_ns: np.ndarray
    x_hat: np.ndarray
    residual: np.ndarray
    epoch: np.ndarray
    seq: np.ndarray
    sensor: np.ndarray                      # index into the vehicle's sensors; -1 live
    counts: Dict[str, int] = field(default_factory=dict)
    overrides: Tuple[str, ...] = ()
    bulk_steps: int = 0
    warnings: list = field(default_factory=list)
    # residuals whitened by their covariance (Kalman: C P C^T + R), as residual; None
    # for the live estimate and for the other observers, whose whitened residual is
    # residual / noise_std (per output, NaN where 0): :meth:`whitened_rows`
    whitened: Optional[np.ndarray] = None
    kalman: bool = False
    noise_std: Optional[np.ndarray] = None

    @property
    def t(self):
        """Stamps in seconds (``ns * 1e-9``)."""
        return self.stamp_ns.astype(np.float64) * 1e-9

    def __len__(self):
        """Return the number of estimates."""
        return int(self.stamp_ns.size)

    def whitened_rows(self, start=0, stop=None):
        """Return the whitened residuals of rows ``start:stop`` (None: the live estimate)."""
        if self.whitened is not None:
            return self.whitened[start:stop]
        if self.noise_std is not None:
            return self.residual[start:stop] / self.noise_std
        return None


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


def affine_scan(F, W, x0, steps=None, chunk=1 << 16):
    """
    Evaluate ``x_k = F[c_k] x_{k-1} + W[k-1]`` for k = 1..K, in blocks.

    Parameters
    ----------
    F : (n, n) or (C, n, n) ndarray
        One transition matrix, or one per class.
    W : (K, n) ndarray
        The forcing of each step.
    x0 : (n,) ndarray
        The state before the first step.
    steps : (K,) int array, optional
        The class c_k of each step (index into F); all 0 when None.
    chunk : int
        Steps evaluated together (memory is ``chunk * n**2`` floats).

    Returns
    -------
    X : (K, n) ndarray
        ``X[k-1] = x_k``, equal to the step-by-step recursion up to round-off.

    Notes
    -----
    A chunk of K steps is cut into blocks of about sqrt(K) steps. The products of
    the transitions inside each block and the response of each block from zero are
    accumulated for all blocks at once (one batched product per position in the
    block), then the state is carried from block to block, then every step is
    ``Phi x_block_start + z``. That is O(K n^3) work in numpy with O(sqrt(K)) Python
    iterations.

    """
    W = np.asarray(W, dtype=float)
    K, n = W.shape
    F = np.asarray(F, dtype=float)
    if F.ndim == 2:
        F = F[None]
    cls = np.zeros(K, dtype=np.intp) if steps is None else np.asarray(steps, dtype=np.intp)
    Fx = np.concatenate([F, np.eye(n)[None]])        # the last class pads: identity
    pad_class = F.shape[0]
    X = np.empty((K, n))
    x = np.asarray(x0, dtype=float).copy()
    for lo in range(0, K, chunk):
        hi = min(K, lo + chunk)
        L = hi - lo
        B = max(1, int(np.sqrt(L)))
        nb = -(-L // B)
        c = np.full(nb * B, pad_class, dtype=np.intp)
        c[:L] = cls[lo:hi]
        c = c.reshape(nb, B)
        Wb = np.zeros((nb * B, n))
        Wb[:L] = W[lo:hi]
        Wb = Wb.reshape(nb, B, n)
        Phi = np.empty((nb, B, n, n))
        Z = np.empty((nb, B, n))
        P = np.broadcast_to(np.eye(n), (nb, n, n)).copy()
        z = np.zeros((nb, n))
        for j in range(B):
            Fj = Fx[c[:, j]]
            P = np.matmul(Fj, P)
            z = np.einsum('bij,bj->bi', Fj, z) + Wb[:, j]
            Phi[:, j] = P
            Z[:, j] = z
        S = np.empty((nb, n))
        for blk in range(nb):
            S[blk] = x
            x = Phi[blk, -1] @ x + Z[blk, -1]
        Xc = np.einsum('bjkl,bl->bjk', Phi, S) + Z
        X[lo:hi] = Xc.reshape(nb * B, n)[:L]
        x = X[hi - 1].copy()
    return X


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


def _variant_sensors(vehicle, recording):
    sensors = []
    for s in vehicle.sensors:
        if s.name not in recording.sensors:
            raise BagToolError(
                f'sensor {s.name!r} of this configuration is not among the recorded sensors '
                f'{list(recording.sensors)}')
        rec = recording.sensors[s.name]
        if tuple(rec.names) != tuple(s.outputs):
            raise BagToolError(
                f'sensor {s.name!r} gives outputs {list(s.outputs)} in this configuration '
                f'but {list(rec.names)} in the vehicle the bag was read with')
        sensors.append(s)
    return sensors


def _bulk_capable(est):
    kind = getattr(est, 'kind', '')
    if kind == 'open_loop':
        return True
    return kind in ('full', 'reduced') and getattr(est, 'gain', None) is None


def replay(recording, vehicle, name='design', overrides=(), exact=False,
           clock_jump_tolerance=CLOCK_JUMP_TOLERANCE, future_tolerance=FUTURE_TOLERANCE,
           progress=None):
    """
    Replay a recording through the estimator of a vehicle configuration.

    Parameters
    ----------
    recording : Recording
        From :func:`observer_ros.bag.reader.read_recording`.
    vehicle : Vehicle
        The configuration: its plant and observer build the estimator
        (``make_estimator``); its sensors say which recorded sensors it uses (all of
        them must be in the recording, with the same outputs).
    name : str
        Name of the configuration (``design``, ``slow``, ...).
    overrides : sequence of str
        The overrides that made this configuration (kept for the report).
    exact : bool
        Call the estimator for every event (no bulk replay).
    clock_jump_tolerance, future_tolerance : float
        As the observer node's parameters; ``future_tolerance=None`` disables that check.
    progress : callable, optional
        ``progress(done, total)`` over the events.

    Returns
    -------
    result : Replay

    Raises
    ------
    BagToolError
        The configuration's sensors do not match the recording.
    ObserverError
        The estimator cannot be built (bad design).

    """
    plant = vehicle.plant
    sensors = _variant_sensors(vehicle, recording)
    counts = dict.fromkeys(('measurements', 'commands', 'bad_messages', 'bad_commands',
                            'zero_stamps', 'out_of_order', 'duplicates', 'future_stamps',
                            'rejected_updates', 'numerical_resets', 'clock_jumps',
                            'late_measurements'), 0)
    events = _Events(recording, sensors, plant, counts,
                     lockstep=vehicle.simulator.mode == 'lockstep',
                     clock_jump_tolerance=clock_jump_tolerance)
    est = make_estimator(plant, vehicle.observer)
    history = History(est, vehicle.observer.history_length)
    rows = [tuple(plant.output_rows(s.outputs)) for s in sensors]
    rows_idx = [np.array(r, dtype=np.intp) for r in rows]
    streams = events.streams
    # seconds of one stamp as Stream.t gives them (ns * 1e-9), taken per event: no
    # whole-bag float copies of the stamps and receive times
    times = [s.stamp_ns for s in streams]
    values = [s.values for s in streams]
    logs = [s.log_ns for s in streams]
    cmd = events.command
    if cmd is not None and plant.m:
        cmd_t = cmd.stamp_ns
        cmd_u = cmd.values
    n_meas = int(sum(int((events.kind == k).sum()) for k in range(len(streams))))
    out_ns = np.zeros(n_meas, dtype=np.int64)
    out_x = np.zeros((n_meas, plant.n))
    out_r = np.full((n_meas, plant.p), np.nan)
    kalman = est.kind == 'kalman'
    out_e = np.full((n_meas, plant.p), np.nan) if kalman else None
    # the narrowest exact types: epochs and bag positions fit the events' index type
    out_epoch = np.zeros(n_meas, dtype=_index_type(len(events)))
    out_seq = np.zeros(n_meas, dtype=_index_type(int(events.seq.max()) + 1 if len(events) else 0))
    out_sensor = np.zeros(n_meas, dtype=np.int8 if len(sensors) < 128 else np.int16)
    runs = {}
    warnings = []
    if not exact and _bulk_capable(est) and not _has_late(events, streams, cmd, history.length):
        runs = _find_runs(events, streams, cmd, est, clock_jump_tolerance, future_tolerance)
    stamps = [s.stamp_ns for s in streams]
    jump = clock_jump_tolerance
    last_stamp = {}
    epoch = 0
    m = 0
    bulk_steps = 0
    event = _Rows(events.kind, events.idx, events.seq)
    total = len(events)
    next_report = _PROGRESS_EVERY
    i = 0
    while i < total:
        if progress is not None and i >= next_report:
            next_report = i + _PROGRESS_EVERY
            progress(i, total)
        k, j, sq = event(i)
        if k < 0:
            t = float(cmd_t[j]) * 1e-9
            u = cmd_u[j]
            last = est.t
            try:
                if last is not None and last - t > jump:
                    history.reset(None, None)
                    counts['clock_jumps'] += 1
                    epoch += 1
                history.set_input(t, u)     # older than the history: from the estimate's t
                counts['commands'] += 1
            except (ObserverError, ValueError):
                counts['bad_commands'] += 1
            i += 1
            continue
        t = float(times[k][j]) * 1e-9
        last = est.t
        if last is not None and t < last:
            if last - t > jump:
                history.reset(None, None)
                last_stamp.clear()
                counts['clock_jumps'] += 1
                epoch += 1
            elif not history.accepts(t):
                counts['out_of_order'] += 1
                i += 1
                continue
        if last_stamp.get(k) == t:
            counts['duplicates'] += 1
            i += 1
            continue
        if future_tolerance is not None and t - float(logs[k][j]) * 1e-9 > future_tolerance:
            counts['future_stamps'] += 1
            i += 1
            continue
        try:
            head = history.correct(t, values[k][j], rows[k], tag=m)
        except (ObserverError, ValueError):
            counts['rejected_updates'] += 1
            i += 1
            continue
        if not np.all(np.isfinite(head)):
            history.reset(None, t)
            counts['numerical_resets'] += 1
            i += 1
            continue
        if last is not None and t < last:
            counts['late_measurements'] += 1
            for r, x_r, res_r, S_r in history.revised:     # estimates the late one changed
                out_x[r] = x_r
                out_r[r, rows_idx[out_sensor[r]]] = res_r
                if kalman:
                    _put_whitened(out_e, r, rows_idx[out_sensor[r]], res_r, S_r)
        last_stamp[k] = max(t, last_stamp.get(k, t))
        counts['measurements'] += 1
        out_ns[m] = stamps[k][j]
        out_x[m] = history.x_at_stamp
        res = history.residual
        if res is not None:
            out_r[m, rows_idx[k]] = res
            if kalman:
                _put_whitened(out_e, m, rows_idx[k], res, history.innovation_covariance)
        out_epoch[m] = epoch
        out_seq[m] = sq
        out_sensor[m] = k
        m += 1
        run = runs.get(i)
        while run is not None:
            done = _bulk_run(est, run, streams, cmd, rows, rows_idx,
                             (out_ns, out_x, out_r, out_seq, out_sensor), m, warnings)
            if done is None:             # check failed: replay everything call by call
                runs = {}
                break
            steps, i, last = done        # i: the event of the last measurement done
            out_epoch[m:m + steps] = epoch
            m += steps
            bulk_steps += steps
            counts['measurements'] += steps
            counts['commands'] += run['commands']
            last_stamp.update(last)
            history.forget()             # the bulk stretch drove the estimator itself
            run = runs.get(i)
        i += 1
    if progress is not None:
        progress(total, total)
    # late measurements were used at their stamps: the rows in stamp order (per epoch)
    order = np.lexsort((out_ns[:m], out_epoch[:m])) if counts['late_measurements'] else \
        slice(None)
    std = None
    if not kalman:      # whitened by the sensors' noise_std (NaN where it is 0), on demand
        std = np.full(plant.p, np.nan)
        for s, r in zip(sensors, rows_idx):
            std[r] = np.where(np.asarray(s.noise_std) > 0.0, s.noise_std, np.nan)
    return Replay(name=name, vehicle=vehicle, stamp_ns=out_ns[:m][order],
                  x_hat=out_x[:m][order], residual=out_r[:m][order],
                  epoch=out_epoch[:m][order], seq=out_seq[:m][order],
                  sensor=out_sensor[:m][order], counts=counts, overrides=tuple(overrides),
                  bulk_steps=bulk_steps, warnings=warnings,
                  whitened=out_e[:m][order] if kalman else None, kalman=kalman, noise_std=std)


def _put_whitened(out_e, m, cols, residual, S):
    if S is None:           # a Kalman filter before its first covariance: not counted
        return
    try:
        out_e[m, cols] = whiten(residual, S)
    except (ValueError, np.linalg.LinAlgError):
        pass


def innovation_health(rep):
    """
    Return the innovation health of each sensor of a replay, as the node judges it.

    Parameters
    ----------
    rep : Replay
        From :func:`replay` (None figures for the live estimate).

    Returns
    -------
    health : dict
        Sensor name -> :func:`observer_ros.core.innovation.sequence_health` figures.

    """
    if rep.whitened is None and rep.noise_std is None:
        return {}
    veh = rep.vehicle
    plant = veh.plant
    # the initial transient of each epoch (the estimator restarts) is not judged
    transient = transient_time(design_vehicle(veh).observer_poles, veh.sample_time,
                               plant.is_discrete, rep.kalman)
    starts, t0 = _epoch_starts(rep) if transient > 0.0 else (None, None)
    counts = np.zeros(len(veh.sensors), dtype=np.int64)
    for b0 in range(0, len(rep), HEALTH_BLOCK):
        sens = rep.sensor[b0:b0 + HEALTH_BLOCK]
        counts += np.bincount(sens[sens >= 0], minlength=len(counts))[:len(counts)]
    out = {}
    for k, s in enumerate(veh.sensors):
        cols = list(plant.output_rows(s.outputs))
        out[s.name] = sequence_health_blocks(s.name, _health_blocks(rep, k, cols, starts, t0),
                                             rep.kalman, transient=transient,
                                             rows=int(counts[k]))
    return out


def _epoch_starts(rep):
    """Return the epochs of a replay and the stamp (s) of each one's first row."""
    first = {}
    for b0 in range(0, len(rep), HEALTH_BLOCK):
        ep, at = np.unique(rep.epoch[b0:b0 + HEALTH_BLOCK], return_index=True)
        for e, i in zip(ep.tolist(), at.tolist()):
            first.setdefault(e, b0 + i)
    starts = np.array(sorted(first), dtype=rep.epoch.dtype)
    idx = np.array([first[e] for e in starts.tolist()], dtype=np.int64)
    return starts, rep.stamp_ns[idx].astype(np.float64) * 1e-9


def _health_blocks(rep, k, cols, starts, t0):
    """Yield sensor k's whitened residuals and their seconds since the epoch's start."""
    for b0 in range(0, max(len(rep), 1), HEALTH_BLOCK):
        b1 = b0 + HEALTH_BLOCK
        mine = rep.sensor[b0:b1] == k
        E = rep.whitened_rows(b0, b1)[mine][:, cols]
        since = None
        if starts is not None:
            t = rep.stamp_ns[b0:b1][mine].astype(np.float64) * 1e-9
            since = t - t0[np.searchsorted(starts, rep.epoch[b0:b1][mine])]
        yield E, since


def _has_late(events, streams, cmd, length, block=1 << 16):
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


# ---------------------------------------------------------------------------------------
# Bulk replay of stretches of measurements at distinct, increasing stamps
# ---------------------------------------------------------------------------------------

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


def _steps(events, streams, cmd, est, jump, future_tolerance, mev, s0, s1, keyed=True):
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
    step_ok = (key_id >= 0) & ok[1:]
    gap_cmds = np.zeros(h.size, dtype=np.int64)
    e0 = int(ev[0])
    cev = np.flatnonzero(events.kind[e0:int(ev[-1])] == -1) + e0   # commands in between
    if cev.size:
        ct = cmd.stamp_ns[events.idx[cev]].astype(np.float64) * 1e-9
        g = np.searchsorted(ev, cev) - 1        # the measurement before each command
        good = (ct <= tm[g]) & (tm[g] - ct <= jump)
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

    def __init__(self, events, streams, cmd, est, jump, future_tolerance, block=None):
        self.args = (events, streams, cmd, est, jump, future_tolerance)
        self.pieces = {}
        block = block or RUN_BLOCK
        mev = self.mev = _measurement_events(events.kind, block)
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
        return _steps(*self.args, self.mev, s0, s1, keyed)

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


def _measurement_events(kind, block):
    """Return the event indices of the measurements (kind >= 0), found a block at a time."""
    blocks = range(0, kind.size, block)
    count = sum(int(np.count_nonzero(kind[e0:e0 + block] >= 0)) for e0 in blocks)
    mev = np.empty(count, dtype=_index_type(kind.size))
    done = 0
    for e0 in blocks:
        found = np.flatnonzero(kind[e0:e0 + block] >= 0)
        mev[done:done + found.size] = found + e0
        done += found.size
    return mev


def _find_runs(events, streams, cmd, est, jump, future_tolerance, block=None):
    """
    Stretches of measurements each of whose steps is an affine map of the previous x.

    A step goes from one accepted measurement to the next; it is one affine map
    ``x_k = F x_{k-1} + G y_k + H u`` of the current-form estimators when the stamp
    increases (no fused correction at one stamp), every check of the node passes,
    and every command in between is stamped at (or, within the jump tolerance,
    before) the earlier measurement. Its class is (step key, sensor): F, G, H depend
    only on those. "In between" is in the replay order (``events``), which in lockstep
    is not the bag order: positions in ``events``, never ``seq``, place the commands.

    Returns a :class:`_Runs`: ``get(event index of measurement a)`` gives the run of
    measurements a+1..b (a piece of at most :data:`MAX_RUN` steps), indices local to
    the piece (``a`` is 0).

    """
    return _Runs(events, streams, cmd, est, jump, future_tolerance, block)


def _twin(est):
    """
    Return a copy of an estimator with its own state and the same caches.

    The step and gain caches hold values that depend on the step length only
    (``StepCache``), so sharing them changes no result; it saves designing the gains of
    every new step again in each copy (jittered stamps: a new step each message).

    """
    memo = {id(est.cache): est.cache, id(est.gain_cache): est.gain_cache}
    return copy.deepcopy(est, memo)


def _probe(probe, t0, t1, rows):
    """Measure the affine map of one step t0 -> t1 (correction with rows) on a twin."""
    plant = probe.plant
    n, m, q = plant.n, plant.m, len(rows)

    def run(x0, u, y):
        probe.reset(x0, t0)
        probe.set_input(t0, u)
        x = probe.correct(t1, y, rows)
        return x, probe.residual

    F, G, H = np.zeros((n, n)), np.zeros((n, q)), np.zeros((n, m))
    Rx, Ry, Ru = np.zeros((q, n)), np.zeros((q, q)), np.zeros((q, m))
    zx, zu, zy = np.zeros(n), np.zeros(m), np.zeros(q)
    x, r = run(zx, zu, zy)
    if np.any(x != 0) or r is None or np.any(r != 0):
        return None
    for i in range(n):
        F[:, i], Rx[:, i] = run(np.eye(n)[i], zu, zy)
    for i in range(q):
        G[:, i], Ry[:, i] = run(zx, zu, np.eye(q)[i])
    for i in range(m):
        H[:, i], Ru[:, i] = run(zx, np.eye(m)[i], zy)
    return F, G, H, Rx, Ry, Ru


def _spread(items, count):
    """Return up to ``count`` of ``items`` spread evenly, the first and the last included."""
    if len(items) <= count:
        return list(items)
    return [items[i] for i in np.linspace(0, len(items) - 1, count).round().astype(int)]


def _step_maps(est, run, first, sens, rows, warnings):
    """
    Return the affine maps of the step classes of a run (first step of class c: first[c]).

    As ``(F, G, H, Rx, Ry, Ru)``, each stacked over the classes (see :func:`_probe`).

    Built in bulk (:func:`~observer_ros.bag.step_maps.bulk_maps`) when there are more
    than :data:`CHECK_CLASSES` classes (jittered stamps) and the estimator is one it
    models, then checked against :func:`_probe` on :data:`CHECK_CLASSES` classes spread
    over the run; else measured by :func:`_probe` class by class. None: not linear.

    """
    probe = _twin(est)
    a, tm = run['a'], run['tm']
    first = np.asarray(first)
    t0, t1 = tm[a + first], tm[a + first + 1]
    ks = sens[first]
    maps = None
    if len(first) > CHECK_CLASSES:
        keys = run['keys'][run['step_class'][a + first] // len(rows)]
        maps = bulk_maps(est, keys, ks, rows)
    todo = range(len(first)) if maps is None else _spread(range(len(first)), CHECK_CLASSES)
    probed = {}
    for c in todo:
        mp = _probe(probe, float(t0[c]), float(t1[c]), rows[ks[c]])
        if mp is None:
            warnings.append('bulk replay disabled: an estimator step is not linear')
            return None
        probed[c] = mp
    if maps is None:
        return _stacked([probed[c] for c in range(len(first))])
    for c, mp in probed.items():
        for bulk, measured in zip((M[c] for M in maps), mp):
            if np.max(np.abs(bulk - measured)) > CHECK_RTOL * (1.0 + np.max(np.abs(measured))):
                warnings.append("bulk step maps differ from the estimator's at t = "
                                f'{float(t1[c]):.9g} s; measuring every step')
                maps = [_probe(probe, float(t0[i]), float(t1[i]), rows[ks[i]])
                        for i in range(len(first))]
                return None if any(mp is None for mp in maps) else _stacked(maps)
    return maps


def _spectral_radius(F, h):
    """
    Return the largest spectral radius of the step maps F (step lengths h).

    At most :data:`CHECK_CLASSES` * 8 maps are decomposed: spread over the classes, and
    the shortest and longest steps (a map's poles move monotonically with its length,
    ``exp(s h)``); jittered stamps give one class per step.

    """
    if F.shape[0] > 8 * CHECK_CLASSES:
        pick = _spread(range(F.shape[0]), 8 * CHECK_CLASSES)
        pick += [int(np.argmin(h)), int(np.argmax(h))]
        F = F[pick]
    return float(np.max(np.abs(np.linalg.eigvals(F))))


def _stacked(maps):
    """Return the maps (F, G, H, Rx, Ry, Ru) of the classes as six stacked arrays."""
    return tuple(np.stack(part) for part in zip(*maps))


def _held_inputs(run, cmd, u0, a, b):
    """
    Return the input held at each correction a+1..b: that of the last command before it.

    The last command before measurement j in the replay order, if it comes after
    measurement a; else ``u0``, the input the estimator held at a.

    """
    mev = run['mev']
    e0, e1 = int(mev[a]), int(mev[b]) + 1       # the events from measurement a to b
    # the last command at or before each of these events, from a on (-1: none)
    last = np.maximum.accumulate(np.where(run['kind'][e0:e1] == -1, np.arange(e0, e1), -1))
    last = last[mev[a + 1:b + 1] - e0]
    U = np.empty((b - a, u0.size))
    U[:] = u0
    after_a = last > e0
    if after_a.any():
        U[after_a] = cmd.values[run['idx'][last[after_a]]]
    return U


def _call_events(check, run, streams, cmd, rows, e0, e1):
    """
    Handle the events e0..e1-1 with the estimator ``check`` as the main loop does.

    Inside a bulk stretch every event passes the node's checks, so a command is
    ``set_input`` at its stamp (at the estimate's time if before it) and a
    measurement is ``correct``. Returns the estimates after the measurements.

    """
    kind, idx = run['kind'], run['idx']
    xs = []
    for e in range(e0, e1):
        k, j = int(kind[e]), int(idx[e])
        if k < 0:
            t = float(cmd.stamp_ns[j]) * 1e-9        # cmd.t[j], without the whole array
            last = check.t
            check.set_input(last if last is not None and t < last else t, cmd.values[j])
        else:
            t = float(streams[k].stamp_ns[j]) * 1e-9  # streams[k].t[j]
            xs.append(check.correct(t, streams[k].values[j], rows[k]))
    return np.array(xs).reshape(-1, check.n)


def _windows(run, K):
    """
    Return the stretches (s0, s1) of steps of a bulk run checked call by call.

    Steps s0..s1-1 (step s is measurement a+1+s): the first and the last
    :data:`CHECK_STEPS`, :data:`CHECK_WINDOWS` in all spread evenly, and up to
    :data:`CHECK_IRREGULAR` short ones (spread over them) where the events are not
    the plain pattern: a gap with other than one command, events whose bag order is
    not the replay order, a change of step class.

    """
    a = run['a']
    w = min(CHECK_STEPS, K)
    starts = np.unique(np.linspace(0, K - w, max(2, CHECK_WINDOWS)).round().astype(np.int64))
    wins = [(int(s), int(s) + w) for s in starts]
    mev = run['mev']
    e0, e1 = int(mev[a]), int(mev[a + K])
    seq = run['seq'][e0:e1 + 1]
    odd = np.zeros(K, dtype=bool)                    # step s is irregular
    odd |= run['gap_cmds'][a:a + K] != 1             # commands in the gap before step s
    back = np.flatnonzero(np.diff(seq) < 0)          # bag order is not the replay order
    if back.size:
        odd[np.clip(np.searchsorted(mev[a + 1:a + K + 1] - e0, back + 1), 0, K - 1)] = True
    cls = run['step_class'][a:a + K]
    odd[1:] |= cls[1:] != cls[:-1]
    spots = np.flatnonzero(odd)
    if spots.size > CHECK_IRREGULAR:
        spots = spots[np.linspace(0, spots.size - 1, CHECK_IRREGULAR).round().astype(int)]
    for s in spots.tolist():
        s0 = max(0, s - 1)
        wins.append((s0, min(K, s0 + IRREGULAR_STEPS)))
    wins.sort()
    merged = []
    for s0, s1 in wins:
        if merged and s0 <= merged[-1][1]:
            merged[-1] = (merged[-1][0], max(merged[-1][1], s1))
        else:
            merged.append((s0, s1))
    return merged


def _check_windows(est, run, streams, cmd, rows, X, U, scale):
    """
    Compare the bulk estimates X with the estimator's calls over the checked windows.

    Each window starts from the bulk estimate before it (the estimator itself for
    the first one) and handles the recorded events as the main loop does, commands
    included, so it checks which input each step holds as well as the arithmetic.
    Returns None, or a message naming the first difference beyond round-off.

    """
    a, K = run['a'], X.shape[0]
    mev, tm = run['mev'], run['tm']
    for s0, s1 in _windows(run, K):
        check = _twin(est)
        if s0:
            t0 = float(tm[a + s0])
            check.reset(X[s0 - 1], t0)
            check.set_input(t0, U[s0 - 1])
        xs = _call_events(check, run, streams, cmd, rows, int(mev[a + s0]) + 1,
                          int(mev[a + s1]) + 1)
        err = np.max(np.abs(xs - X[s0:s1]), axis=1)
        bad = np.flatnonzero(err > CHECK_RTOL * scale[s0:s1])
        if bad.size:
            s = s0 + int(bad[0])
            return (f'{err[bad[0]]:.3g} at step {s} of {K}, t = {float(tm[a + 1 + s]):.9g} s '
                    f'(|x_hat| up to {scale[s]:.3g})')
    return None


def _class_matvec(M, classes, V, chunk=1 << 16):
    """
    Return ``out[k] = M[classes[k]] @ V[k]`` for every step k.

    In chunks of steps, so that the per-step matrices ``M[classes]`` never exist for a
    whole run at once (a run of 10^6 steps would hold one n x n matrix per step).

    """
    K = V.shape[0]
    out = np.empty((K, M.shape[1]))
    for lo in range(0, K, chunk):
        hi = min(K, lo + chunk)
        np.einsum('kij,kj->ki', M[classes[lo:hi]], V[lo:hi], out=out[lo:hi])
    return out


def _term_scale(maps, cls, sens, Y, Xprev, X, U):
    """Return the running maximum over steps of ``max(|F| |x_prev| + |G| |y| + |H| |u|, |x|)``."""
    absF, absG, absH = (np.abs(M) for M in maps[:3])
    terms = _class_matvec(absF, cls, np.abs(Xprev)) + _class_matvec(absH, cls, np.abs(U))
    for k, y in enumerate(Y):
        if y is not None:
            sel = np.flatnonzero(sens == k)
            terms[sel] += _class_matvec(absG, cls[sel], np.abs(y))
    scale = np.maximum(np.max(terms, axis=1), np.max(np.abs(X), axis=1))
    return np.maximum.accumulate(scale) + np.finfo(float).tiny


def _check_steps(run, cmd, maps, cls, sens, Y, X, x0, u0, scale):
    """
    Check every step of a bulk run against its own affine map; None or a message.

    ``x_k = F x_{k-1} + G y_k + H u_k`` with the maps measured on the estimator and
    the held input u_k found again from the events, through the commands of each gap
    (not the way :func:`_held_inputs` finds it), so a step given the wrong input or
    mangled by the scan is caught wherever it is in the run.

    """
    a, b, K = run['a'], run['b'], X.shape[0]
    mev, kind, idx = run['mev'], run['kind'], run['idx']
    e0, e1 = int(mev[a]), int(mev[b])
    pos = np.flatnonzero(kind[e0:e1] < 0) + e0          # the commands inside the run
    gap = np.searchsorted(mev[a:b + 1], pos, side='right') - 1
    last = np.full(K, -1, dtype=np.int64)
    np.maximum.at(last, gap, pos)                      # the last command of each gap
    last = np.maximum.accumulate(last)                 # held until the next one
    U = np.empty((K, u0.size))
    U[:] = u0
    held = last >= 0
    if held.any():
        U[held] = cmd.values[idx[last[held]]]
    F, G, H = maps[:3]
    Xprev = np.vstack([x0[None, :], X[:-1]])
    pred = _class_matvec(F, cls, Xprev) + _class_matvec(H, cls, U)
    for k, y in enumerate(Y):
        if y is not None:
            sel = np.flatnonzero(sens == k)
            pred[sel] += _class_matvec(G, cls[sel], y)
    err = np.max(np.abs(pred - X), axis=1)
    bad = np.flatnonzero(err > CHECK_RTOL * scale)
    if bad.size:
        s = int(bad[0])
        return f'{err[s]:.3g} at step {s} of {K} (its affine map; {bad.size} steps)'
    return None


def _bulk_run(est, run, streams, cmd, rows, rows_idx, out, m, warnings):
    """Replay measurements a+1..b of a run in bulk; hand the state back to est."""
    a, b = run['a'], run['b']
    tm = run['tm']
    K = b - a
    t_a = float(tm[a])
    if est.t != t_a:
        return None
    plant = est.plant
    n, p = plant.n, plant.p
    ev = run['mev'][a + 1:b + 1]             # the events of measurements a+1..b
    sens = run['kind'][ev]
    idx = run['idx'][ev]
    U = _held_inputs(run, cmd, est.u, a, b)
    # classes of this run, and their maps measured on the estimator
    cls_all = run['step_class'][a:b]
    classes, first, cls = np.unique(cls_all, return_index=True, return_inverse=True)
    cls = cls.reshape(-1)
    W = np.zeros((K, n))
    Y = [None] * len(streams)
    maps = _step_maps(est, run, first, sens, rows, warnings)
    if maps is None:
        return None
    Fs = maps[0]
    # an unstable estimator (the open loop of an unstable plant) amplifies every
    # difference in round-off until the end of the bag: call by call, as the node
    rho = _spectral_radius(Fs, tm[a + first + 1] - tm[a + first])
    if rho > 1.0 and run['rest'] * np.log(rho) > np.log(MAX_GROWTH):
        return None
    for k in range(len(streams)):
        sel = sens == k
        if not sel.any():
            continue
        Y[k] = streams[k].values[idx[sel]]
        Gk, Hk = maps[1], maps[2]
        ck = cls[sel]
        W[sel] = _class_matvec(Gk, ck, Y[k]) + _class_matvec(Hk, ck, U[sel])
    x0 = est.x_hat
    X = affine_scan(Fs, W, x0, cls)
    if not np.all(np.isfinite(X)):
        return None
    Xprev = np.vstack([x0[None, :], X[:-1]])
    R = np.full((K, p), np.nan)
    for k in range(len(streams)):
        sel = np.flatnonzero(sens == k)
        if not sel.size:
            continue
        ck = cls[sel]
        Rx, Ry, Ru = maps[3:]
        r = (_class_matvec(Rx, ck, Xprev[sel]) + _class_matvec(Ry, ck, Y[k])
             + _class_matvec(Ru, ck, U[sel]))
        R[np.ix_(sel, rows_idx[k])] = r
    # round-off is relative to the size of the terms of a step, |F| |x| + |G| |y| +
    # |H| |u| (the map of a reduced-order observer in x coordinates has large entries
    # that cancel), and to the largest of them so far: the estimate may shrink to zero
    # by cancellation or grow without bound on an unstable open loop
    scale = _term_scale(maps, cls, sens, Y, Xprev, X, U)
    # check: every step against its map, windows of real calls over the recorded
    # events, and one step of each class from its bulk prior
    problem = _check_steps(run, cmd, maps, cls, sens, Y, X, x0, est.u, scale)
    if problem is None:
        problem = _check_windows(est, run, streams, cmd, rows, X, U, scale)
    check = _twin(est)
    for f in _spread(first, CHECK_CLASSES) if problem is None else ():
        k = int(sens[f])
        check.reset(Xprev[f], float(tm[a + f]))
        check.set_input(float(tm[a + f]), U[f])
        x = check.correct(float(tm[a + f + 1]), streams[k].values[idx[f]], rows[k])
        err = float(np.max(np.abs(x - X[f])))
        if err > CHECK_RTOL * scale[f]:
            problem = f'{err:.3g} at step {f} of {K} (one step of its class)'
            break
    if problem is not None:
        warnings.append("bulk replay disabled: it differs from the estimator's calls by "
                        f'{problem}; replaying call by call')
        return None
    out_ns, out_x, out_r, out_seq, out_sensor = out
    for k in range(len(streams)):
        sel = sens == k
        out_ns[m:m + K][sel] = streams[k].stamp_ns[idx[sel]]
    out_x[m:m + K] = X
    out_r[m:m + K] = R
    out_seq[m:m + K] = run['seq'][ev]
    out_sensor[m:m + K] = sens
    t_b = float(tm[b])
    # hand over: the estimator is at x_b, t_b, holding the input it held at b
    est.reset(X[-1], t_b)
    est.set_input(t_b, U[-1])
    last = {int(k): float(tm[a + 1 + int(np.flatnonzero(sens == k)[-1])])
            for k in np.unique(sens)}
    return K, run['last_event'], last


def live_replay(recording, vehicle, clock_jump_tolerance=CLOCK_JUMP_TOLERANCE):
    """
    Return the live estimate recorded on ``state/estimate`` as a :class:`Replay`.

    Parameters
    ----------
    recording : Recording
        From :func:`observer_ros.bag.reader.read_recording`.
    vehicle : Vehicle
        The vehicle the bag was recorded with (its plant).
    clock_jump_tolerance : float
        A step back of the estimate's stamp by more than this many seconds is a clock
        jump (a new epoch, see :func:`epochs_of`).

    Returns
    -------
    result : Replay or None
        None when the bag has no ``state/estimate``.

    """
    est = recording.estimate
    if est is None or not est.valid.any():
        return None
    plant = vehicle.plant
    sel = np.flatnonzero(est.valid)
    stamp = est.stamp_ns[sel]
    residual = np.full((sel.size, plant.p), np.nan)
    res = recording.residual
    if res is not None and res.valid.any():
        # the residual published right after each estimate, matched by stamp and order
        rsel = np.flatnonzero(res.valid)
        pos = np.searchsorted(res.seq[rsel], est.seq[sel])
        pos = np.clip(pos, 0, rsel.size - 1)
        same = res.stamp_ns[rsel][pos] == stamp
        residual[same] = res.values[rsel][pos[same]]
    counts = {'measurements': int(sel.size), 'bad_messages': int((~est.valid).sum())}
    epoch = epochs_of(stamp, clock_jump_tolerance)
    counts['clock_jumps'] = int(epoch[-1]) if epoch.size else 0
    return Replay(name='live', vehicle=vehicle, stamp_ns=stamp, x_hat=est.values[sel],
                  residual=residual, epoch=epoch, seq=est.seq[sel],
                  sensor=np.full(sel.size, -1, dtype=np.int64), counts=counts)
