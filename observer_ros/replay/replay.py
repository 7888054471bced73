# observer_ros.replay.replay: run an estimator over recorded measurements as the node does.
"""
Replay recorded measurements and commands through an estimator, as the observer node.

The events (every sensor message and every ``control/u`` message of a
:class:`~observer_ros.bag.reader.Recording`) are taken in the order the node took them:
bag order, the order the recorder received them (ties in receive time keep the order in
the file); for a vehicle whose ``simulator.mode`` is ``lockstep``, stamp order within
each epoch of the bag (a measurement before a command at one stamp), since the recorder
may receive a command after the next measurement (:class:`Events`). Each one is handled
as ``observer_ros.nodes.observer_node`` handles it:

- every message is judged by the node's own
  :class:`~observer_ros.core.estimators.admission.Admission` (the receive time as the
  node's clock), after a malformed stamp (``bad_stamps``) or a message that does not
  give the outputs (``bad_messages``, ``bad_commands``) is skipped: what it skips, the
  replay skips, and counts under the same name; a clock jump (``clock_jump_agreement``
  measurements in a row stamped more than ``clock_jump_tolerance`` before the newest)
  resets the estimator and starts a new epoch, a long gap restarts it at the
  measurement, as in the node. A measurement it takes gives
  ``x_hat = est.correct(t, y, plant.output_rows(outputs))``; a non-finite estimate resets
  the estimator at t. A command applies from its stamp (inside the history; the rows of
  the measurements after it are revised as for a late measurement) or is held from the
  estimate's time (older); it never resets the estimator.
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
current-form estimators (:mod:`observer_ros.replay.bulk_replay`, checked as described
there); ``exact=True`` turns bulk replay off. The events come in the node's order
(:mod:`observer_ros.replay.events`); the innovation health of a replay is
:mod:`observer_ros.replay.health`'s.

"""

from dataclasses import dataclass, field
from typing import Dict, Optional, Tuple

import numpy as np

from . import bulk_runs
from .bulk_replay import affine_scan, bulk_run
from .bulk_runs import find_runs, has_late
from .events import epoch_cuts, epochs_from_cuts, epochs_of, Events, index_type, Rows
from .health import innovation_health
from .rows import ReplayOutputs
from ..bag.errors import BagToolError
from ..bag.spill import blocks, count_true, Sink, SortedColumn
from ..core.errors import ObserverError
from ..core.estimators import History, make_estimator
from ..core.estimators.admission import (Admission, CLOCK_JUMP, CLOCK_JUMP_AGREEMENT,
                                         CLOCK_JUMP_TOLERANCE, DUPLICATE, FAR_BACK,
                                         FUTURE_TOLERANCE, LATE, restart_at)
from ..core.health import max_prediction_gap
from ..core.innovation import whiten
from ..timeutil import ns_to_secs

__all__ = ['Replay', 'replay', 'live_replay', 'epochs_of', 'affine_scan', 'innovation_health',
           'CLOCK_JUMP_TOLERANCE', 'FUTURE_TOLERANCE', 'CLOCK_JUMP_AGREEMENT', 'COUNTERS',
           'SKIPPED']

#: The counters of a replay (:attr:`Replay.counts`), named as the observer node's.
COUNTERS = ('measurements', 'commands', 'bad_messages', 'bad_commands', 'bad_stamps',
            'out_of_order', 'duplicates', 'future_stamps', 'far_back_stamps', 'clock_jumps',
            'long_gap_resets', 'rejected_updates', 'numerical_resets', 'estimator_resets',
            'late_measurements', 'late_commands', 'late_commands_held_from_now')
#: Those of messages the replay skipped, as the node did.
SKIPPED = ('bad_messages', 'bad_commands', 'bad_stamps', 'out_of_order', 'duplicates',
           'future_stamps', 'far_back_stamps', 'rejected_updates')
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
    # replay(answers=True): each estimate a free-running node publishes, in its order
    # (a late measurement is answered with the revised estimate at the newest stamp, a
    # repeated stamp with the estimate again); stamps in ns and the estimates
    answer_ns: Optional[np.ndarray] = None
    answer_x: Optional[np.ndarray] = None

    @property
    def t(self):
        """Stamps in seconds (``ns * 1e-9``)."""
        return ns_to_secs(self.stamp_ns)

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
    if kind in ('open_loop', 'kalman'):
        return True
    return kind in ('full', 'reduced') and getattr(est, 'gain', None) is None


def replay(recording, vehicle, name='design', overrides=(), exact=False,
           clock_jump_tolerance=CLOCK_JUMP_TOLERANCE, future_tolerance=FUTURE_TOLERANCE,
           progress=None, spill=None, clock_jump_agreement=CLOCK_JUMP_AGREEMENT,
           answers=False):
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
    clock_jump_tolerance, future_tolerance, clock_jump_agreement : float, float, int
        As the observer node's parameters; ``future_tolerance=None`` disables that check.
    progress : callable, optional
        ``progress(done, total)`` over the events.
    spill : True or path, optional
        Keep the output rows in temporary files (in this folder; True: the system's
        temporary folder) a block at a time instead of in memory: the result's columns
        are then :class:`~observer_ros.replay.rows.SpilledColumn` objects, read
        on demand with the same values (:mod:`observer_ros.replay.rows`).
    answers : bool
        Also give the estimates a free-running node publishes, in its order
        (:attr:`Replay.answer_ns`, :attr:`Replay.answer_x`); the events are then replayed
        call by call.

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
    counts = dict.fromkeys(COUNTERS, 0)
    events = Events(recording, sensors, plant, counts,
                    lockstep=vehicle.simulator.mode == 'lockstep',
                    clock_jump_tolerance=clock_jump_tolerance, spill=spill)
    est = make_estimator(plant, vehicle.observer)
    history = History(est, vehicle.observer.history_length)
    max_gap = max_prediction_gap(plant.A, vehicle.sample_time, plant.is_discrete)
    # what each stamp means: the node's own decision (receive times as its clock)
    admission = Admission(history, clock_jump_tolerance, future_tolerance,
                          clock_jump_agreement, max_gap, counts=counts)
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
        cmd_log = cmd.log_ns
    n_meas = events.measurements
    kalman = est.kind == 'kalman'
    # the narrowest exact types: epochs and bag positions fit the events' index type
    out = ReplayOutputs(n_meas, plant.n, plant.p, kalman, index_type(len(events)),
                        index_type(events.seq_max + 1),
                        np.int8 if len(sensors) < 128 else np.int16, spill=spill,
                        ahead=bulk_runs.MAX_RUN + bulk_runs.MIN_RUN)
    runs = {}
    warnings = []
    answered = _Answers(plant.n) if answers else None
    if not exact and answered is None and _bulk_capable(est) and \
            not has_late(events, streams, cmd, history.length):
        runs = find_runs(events, streams, cmd, est, clock_jump_tolerance, future_tolerance,
                         max_gap=max_gap)
    stamps = [s.stamp_ns for s in streams]
    lockstep = vehicle.simulator.mode == 'lockstep'
    head_ns = None                  # the stamp (ns) of the estimate's time
    epoch = 0
    m = 0
    bulk_steps = 0
    event = Rows(events.kind, events.idx, events.seq)
    total = len(events)
    next_report = _PROGRESS_EVERY
    i = 0
    while i < total:
        if progress is not None and i >= next_report:
            next_report = i + _PROGRESS_EVERY
            progress(i, total)
        k, j, sq = event(i)
        i += 1
        if k < 0:
            t = float(cmd_t[j]) * 1e-9
            if not admission.command(t, now=float(cmd_log[j]) * 1e-9).use:
                continue
            last = est.t
            try:
                history.set_input(t, cmd_u[j])  # inside the history: from its stamp
                if history.revised:             # a late one: the estimates after its stamp
                    _revise(out, history.revised, rows_idx, kalman)
                counts['commands'] += 1
            except (ObserverError, ValueError):
                counts['bad_commands'] += 1
            if est.t != last:
                head_ns = int(cmd_t[j])
            continue
        t = float(times[k][j]) * 1e-9
        last = est.t
        verdict = admission.measurement(k, t, now=float(logs[k][j]) * 1e-9)
        if not verdict.use:
            if answered is not None and (verdict is DUPLICATE and last == t or
                                         verdict is FAR_BACK and lockstep):
                answered.add(stamps[k][j], est.x_hat)       # the node answers these
            continue
        if verdict.restart:                 # a clock jump, a long gap: at the measurement
            restart_at(history, est, rows[k], values[k][j])
            counts['estimator_resets'] += 1
            if verdict is CLOCK_JUMP:
                epoch += 1
            last = None
        try:
            head = history.correct(t, values[k][j], rows[k], tag=m)
        except (ObserverError, ValueError):
            counts['rejected_updates'] += 1
            continue
        if not np.all(np.isfinite(head)):
            history.reset(None, t)
            counts['numerical_resets'] += 1
            counts['estimator_resets'] += 1
            head_ns = int(stamps[k][j])
            continue
        if verdict is LATE:
            _revise(out, history.revised, rows_idx, kalman)   # estimates the late one changed
        else:
            head_ns = int(stamps[k][j])
        if answered is not None:
            answered.add(head_ns, head)
        counts['measurements'] += 1
        b = out.local(m)
        out.ns[b] = stamps[k][j]
        out.x[b] = history.x_at_stamp
        res = history.residual
        if res is not None:
            out.r[b, rows_idx[k]] = res
            if kalman:
                w = _whitened(res, history.innovation_covariance)
                if w is not None:
                    out.e[b, rows_idx[k]] = w
        out.epoch[b] = epoch
        out.seq[b] = sq
        out.sensor[b] = k
        m += 1
        run = runs.get(i - 1)
        while run is not None:
            b = out.local(m)
            done = bulk_run(est, run, streams, cmd, rows, rows_idx,
                            (out.ns, out.x, out.r, out.seq, out.sensor, out.e), b,
                            warnings)
            if done is None:             # check failed: replay everything call by call
                runs = {}
                break
            if done is False:            # this piece cannot start here (Kalman: P unknown)
                break
            steps, i, newest = done      # i: the event of the last measurement done
            out.epoch[b:b + steps] = epoch
            m += steps
            bulk_steps += steps
            counts['measurements'] += steps
            counts['commands'] += run['commands']
            for key, t_key in newest.items():
                admission.used(key, t_key)
            history.forget()             # the bulk stretch drove the estimator itself
            run = runs.get(i)
            i += 1
    if progress is not None:
        progress(total, total)
    # late measurements were used at their stamps: the rows in stamp order (per epoch)
    cols = out.finish(m, sort=bool(counts['late_measurements']))
    std = None
    if not kalman:      # whitened by the sensors' noise_std (NaN where it is 0), on demand
        std = np.full(plant.p, np.nan)
        for s, r in zip(sensors, rows_idx):
            std[r] = np.where(np.asarray(s.noise_std) > 0.0, s.noise_std, np.nan)
    return Replay(name=name, vehicle=vehicle, stamp_ns=cols['ns'], x_hat=cols['x'],
                  residual=cols['r'], epoch=cols['epoch'], seq=cols['seq'],
                  sensor=cols['sensor'], counts=counts, overrides=tuple(overrides),
                  bulk_steps=bulk_steps, warnings=warnings, whitened=cols['e'],
                  kalman=kalman, noise_std=std,
                  answer_ns=None if answered is None else answered.stamps(),
                  answer_x=None if answered is None else answered.estimates())


class _Answers:
    """The estimates a free-running node publishes, collected in its order."""

    def __init__(self, n):
        self.n = n
        self.ns = []
        self.x = []

    def add(self, ns, x):
        self.ns.append(int(ns))
        self.x.extend(x.tolist())

    def stamps(self):
        return np.array(self.ns, dtype=np.int64)

    def estimates(self):
        return np.array(self.x, dtype=float).reshape(-1, self.n)


def _revise(out, revised, rows_idx, kalman):
    """Overwrite the rows of the estimates a late message changed (``History.revised``)."""
    for r, x_r, res_r, S_r in revised:
        out.revise(r, x_r, rows_idx[out.sensor_of(r)], res_r,
                   _whitened(res_r, S_r) if kalman else None)


def _whitened(residual, S):
    """Return a Kalman residual whitened by its covariance S (None: none to count)."""
    if S is None:           # a Kalman filter before its first covariance: not counted
        return None
    try:
        return whiten(residual, S)
    except (ValueError, np.linalg.LinAlgError):
        return None


def live_replay(recording, vehicle, clock_jump_tolerance=CLOCK_JUMP_TOLERANCE, spill=None):
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
    spill : True or path, optional
        Keep the rows in temporary files (as :func:`replay`'s ``spill``).

    Returns
    -------
    result : Replay or None
        None when the bag has no ``state/estimate``.

    """
    est = recording.estimate
    if est is None:
        return None
    count = count_true(est.valid)
    if not count:
        return None
    plant = vehicle.plant
    res = recording.residual
    matched = None          # the residual published right after each estimate (by seq)
    if res is not None and count_true(res.valid):
        rows = Sink(np.int64, (), 0, spill)         # the valid residuals' rows, their seq
        seqs = Sink(res.seq.dtype, (), 0, spill)
        for lo, ok in blocks(res.valid):
            sel = np.flatnonzero(ok) + lo
            rows.append(sel)
            seqs.append(res.seq[sel])
        matched = rows.result(), SortedColumn(seqs.result())
    cols = {'ns': Sink(np.int64, (), count, spill),
            'x': Sink(np.float64, (plant.n,), count, spill),
            'r': Sink(np.float64, (plant.p,), count, spill),
            'seq': Sink(est.seq.dtype, (), count, spill)}
    for lo, ok in blocks(est.valid):
        sel = np.flatnonzero(ok) + lo
        stamp = est.stamp_ns[sel]
        residual = np.full((sel.size, plant.p), np.nan)
        if matched is not None:
            rows, found = matched
            pos = np.clip(found.searchsorted(est.seq[sel]), 0, len(found) - 1)
            at = rows[pos]
            same = res.stamp_ns[at] == stamp
            residual[same] = res.values[at[same]]
        for name, part in (('ns', stamp), ('x', est.values[sel]), ('r', residual),
                           ('seq', est.seq[sel])):
            cols[name].append(part)
    stamp = cols['ns'].result()
    cuts = epoch_cuts(stamp, clock_jump_tolerance)
    epoch = epochs_from_cuts(cuts, count, spill)
    sensor = Sink(np.int64, (), count, spill)
    for lo in range(0, count, 1 << 16):
        sensor.append(np.full(min(count, lo + (1 << 16)) - lo, -1, dtype=np.int64))
    counts = {'measurements': count, 'bad_messages': len(est) - count,
              'clock_jumps': len(cuts)}
    return Replay(name='live', vehicle=vehicle, stamp_ns=stamp, x_hat=cols['x'].result(),
                  residual=cols['r'].result(), epoch=epoch,
                  seq=cols['seq'].result(), sensor=sensor.result(), counts=counts)
