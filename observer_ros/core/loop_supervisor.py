# observer_ros.core.loop_supervisor: which command the compensator sends, and why.
"""
The compensator's decisions, without ROS: one estimate in, one command (or none) out.

:class:`LoopSupervisor` is a small state machine. Its modes:

``waiting``
    No estimate yet.
``closed``
    The loop closes on the estimates it follows: u = K (x_d - x_hat) - Kd x_d.
``stale``
    No usable estimate for ``controller.stale_timeout`` (wall clock), or, in realtime
    with a warm standby, none within ``LAG_LIMIT`` s of the plant's time. With a
    standby observer (:mod:`.standby`; a plant that cannot be held open loop, realtime)
    the loop closes on the standby's estimate, one command per measurement; without one,
    the safe command (:mod:`.safe_command`: predict-and-hold from the last estimate that
    passed, then ``controller.safe_command``) every sample time (in lock-step none while an
    estimate publisher is matched: :mod:`.resync`).
``resync``
    Estimates are back after an outage (:mod:`.resync`: in lock-step from the same observer
    they are followed at once). Until they are trusted again, the standby (one not yet
    warm is no reference: the loop closes on the estimates at once) or the prediction
    keeps closing the loop.
``recover``
    Without a standby, after a resync: the loop closes on the estimates again, reported
    as ERROR ``recovering`` for an observer settling time.

Every estimate and every command passes gates first:

- an estimate stamped at or before the last one answered is not answered again (a
  repeat, or a second publisher answering the same measurements);
- an estimate outside the vehicle's envelope (:class:`~.health.Envelope`: 100 times what
  the file and the first seconds make plausible) is refused the first time: the safe
  command instead, ERROR ``implausible``; ``ENVELOPE_PERSIST`` in a row are ``diverging``;
- with two publishers or a warm standby, an estimate that fits neither the model's
  prediction from the last one followed nor the standby's is another stream's: ignored
  (``other_stream_estimates``, said on /diagnostics); a standby that disagrees with the
  stream followed takes no hand-over (:mod:`.estimate_stream` says how), and a standby
  beyond the envelope is no reference at all;
- a command must be finite, inside ``controller.u_min``/``u_max``, and without limits
  inside the command envelope (100 times ``|K|`` applied to the file's state scale, the
  bound ``observer-design`` prints), or the safe command is sent instead; the safe
  command itself predicts only from the last estimate that passed, and its prediction
  stops (the fallback) where it would leave the envelope.

A clock jump is the observer's (:class:`~.clock_jump.ClockJump`): ``jump_agreement`` sensor
stamps in a row far back (``clock_jumps``) restart the plant's time, standby and safe command;
one is skipped (``far_back_stamps``). Estimates: ``far_back_estimates``, then a resync.

The node turns messages into numbers, calls these methods, and publishes the
:class:`Command` they return; counters and log lines go through the callables it gives.

"""

import math

import numpy as np

from .clock_jump import CLOCK_JUMP, CLOCK_JUMP_AGREEMENT, ClockJump, FAR_BACK, \
    far_back_text, IN_BASE
from .control_law import ControlLaw
from .delay_compensation import DelayCompensation
from .estimate_stream import CONSISTENCY_TOL, EstimateStream
from .health import divergence_envelopes, ENVELOPE_PERSIST, HeldOff, SettleCheck, settling_time
from .loop_command import Command, command_refusal
from .loop_status import ERROR, OK, status_message, WARN
from .plant_clock import PlantClock
from .resync import Resync, RESYNC_AGREE, RESYNC_SETTLINGS
from .safe_command import SafeCommand
from .standby import StandbyObserver, unstable_plant
from ..timeutil import stamp_sec

__all__ = ['Command', 'LoopSupervisor', 'OK', 'WARN', 'ERROR', 'CONSISTENCY_TOL',
           'RESYNC_AGREE', 'RESYNC_SETTLINGS']

# Longest gap, in steps, across which an estimate is compared with the model's prediction.
CONSISTENCY_STEPS = 50
# Realtime with a standby: the observer is silent once its newest estimate followed is
# LAG_LIMIT s (at least LAG_STEPS sample times) behind the newest measurement's stamp.
# Estimates a few sample times late (a loaded host) stay followed, the plant holding the
# last command meanwhile: the standby is for a silence, not for each delay.
LAG_LIMIT = 0.1
LAG_STEPS = 3


def _nothing(*args, **kwargs):
    return None


class LoopSupervisor:
    """
    Decide each command of the compensator.

    Parameters
    ----------
    vehicle : Vehicle
        The vehicle file.
    design : VehicleDesign
        Its design (``K``, the observer poles).
    lead_steps : int
        ``command_lead_steps``: steps a delay-compensated command is stamped ahead.
    jump_tolerance, jump_agreement : float, int
        ``clock_jump_tolerance`` (s), ``clock_jump_agreement``: :attr:`sensor_jumps`,
        :attr:`estimate_jumps` (:class:`ClockJump`; change them there).
    standby : bool or None
        Keep a standby observer: None (default) for a plant that cannot be held open
        loop in realtime; False never.
    count : callable, optional
        ``count(key)``: a diagnostics counter.
    log : callable, optional
        ``log(level, text)``: a log line (``WARN`` or ``ERROR``), said once per change.
    clock : callable, optional
        ``clock()``: the time on the estimates' clock (ROS time, s), for a safe command
        before any estimate gave a stamp.
    clock_bound : callable, optional
        ``clock_bound()``: /clock's time when the node follows /clock, else None; a safe
        command is never stamped past it (plus the lead), however long the wall clock ran.

    """

    def __init__(self, vehicle, design, lead_steps=3, jump_tolerance=0.5, standby=None,
                 count=None, log=None, clock=None, clock_bound=None,
                 jump_agreement=CLOCK_JUMP_AGREEMENT):
        self._count = count or _nothing
        self._log = log or _nothing
        self._clock = clock or (lambda: 0.0)
        self._clock_bound = clock_bound or _nothing
        self.sensor_jumps = ClockJump(jump_tolerance, jump_agreement, self._count)
        self.estimate_jumps = ClockJump(jump_tolerance, jump_agreement, self._count,
                                        ('far_back_estimates', 'estimate_clock_jumps'))
        self.lead_steps = int(lead_steps)
        self.mode = 'waiting'
        self.safe = None
        self.standby = None
        self.resync = Resync()          # what an outage leaves to judge what comes back
        self.apply(vehicle, design, standby)
        self._last_wall = None          # wall time of the last estimate followed
        self._held_off = HeldOff()      # the watchdog's checks
        self._last_stamp = None         # its stamp: the estimates' time base
        self._answered = None           # the newest estimate's stamp answered
        self._answer = None             # the command that answered it
        self._followed = None           # (t, x) of the last estimate followed (floats)
        self._refusals = 0              # envelope refusals in a row
        self._problem = None            # the last refusal (a report), until one passes
        self._refused_command = None    # why the last command was not sent (per report)
        self._too_late = 0              # estimates too late to predict, since the report
        self._max_steps = 0             # steps predicted (delay compensation), since then
        self._recover_since = None      # recover: stamp since when closed again
        self._standby_wall = None       # wall time of the standby's last command
        self.stream = EstimateStream(self._count, self._log)    # the writer followed
        self.publishers = 1             # known publishers of the estimate topic
        self.safe_mode = None           # how the last safe command was decided
        self.plant_time = None          # realtime: the newest sensor stamp
        self._plant_start = None        # the first sensor stamp: the plant's step 0
        self.plant_stepping = False     # a later stamp came: the plant steps
        self._stepping_wall = None      # wall time it was seen to step first

    # ------------------------------------------------------------ set-up

    def apply(self, vehicle, design, standby=None):
        """Take a (re)designed vehicle: the law, the envelopes, the safe command."""
        plant, c = vehicle.plant, vehicle.controller
        n, m = plant.n, plant.m
        self.vehicle, self.design = vehicle, design
        self.K = np.asarray(design.K, dtype=float).reshape(m, n)
        self.x_d = np.zeros(n) if c.reference is None else np.asarray(c.reference, float)
        self.Kd = np.zeros((m, n)) if c.Kd is None else np.asarray(c.Kd, float).reshape(m, n)
        self.u_min, self.u_max = c.u_min, c.u_max
        self.law = ControlLaw(self.K, self.x_d, self.Kd, self.u_min, self.u_max)
        self.x_envelope, self.u_envelope = divergence_envelopes(vehicle, self.K, self.x_d,
                                                                self.Kd, persist=1)
        self._scale = self.x_envelope.file_scale
        last = self.safe
        self.safe = SafeCommand(plant, self._safe_law, vehicle.sample_time, c.safe_command,
                                c.predict_timeout)
        if last is not None:
            self.safe.sent(last.last_command)
        self.dt = self.safe.dt
        self.settle = settling_time(design.observer_poles, vehicle.sample_time,
                                    plant.is_discrete)
        self.settle_check = SettleCheck(self.safe.Ad, self.safe.Bd, self.dt, self._scale)
        realtime = vehicle.simulator.mode == 'realtime'
        self.resync.lockstep = vehicle.simulator.mode == 'lockstep'
        self.time_rate = vehicle.simulator.realtime_factor if realtime else 1.0
        self.delay = DelayCompensation(
            self.safe.Ad, self.safe.Bd, self.dt, vehicle.observer.history_length,
            self.lead_steps) if c.delay_compensation and realtime else None
        # the plant's time from the wall clock: measurements taken late (a stall of this
        # process) do not make the commands answering them late
        self.plant_clock = None if self.delay is None else PlantClock(self.time_rate)
        wanted = realtime and unstable_plant(plant) if standby is None else \
            bool(standby) and realtime
        if wanted and self.standby is None:
            self.standby = StandbyObserver(vehicle, warm_after=self.settle)
        elif not wanted:
            self.standby = None
        # realtime with a standby: no estimate this far behind the plant's time is silence
        self.lag_limit = max(LAG_STEPS * self.dt, LAG_LIMIT)

    def set_lead_steps(self, steps):
        """Change ``command_lead_steps``."""
        self.lead_steps = int(steps)
        if self.delay is not None:
            self.delay.lead = self.lead_steps

    @property
    def stale(self):
        """Return True while no usable estimate comes: the safe command or the standby."""
        return self.mode == 'stale'

    @property
    def wants_sensors(self):
        """Tell whether the node should pass its sensor messages (plant time, standby)."""
        return self.delay is not None or self.standby is not None

    @property
    def wants_values(self):
        """Tell whether the sensor messages' values are needed (a standby), not only stamps."""
        return self.standby is not None

    def _safe_law(self, x):
        """Return the law on the safe command's prediction; NaN where it leaves the envelope."""
        if not self.x_envelope.inside(x):
            return [math.nan] * self.law.m
        u = self.law(x.tolist())
        return u if self.u_envelope.inside(u) or self.law.limited else [math.nan] * len(u)

    # ------------------------------------------------------------ inputs

    def estimate(self, t, x_hat, now):
        """
        Answer an estimate stamped t, its values x_hat (finite), received at wall time now.

        Returns
        -------
        Command or None
            None when the estimate is not answered (a repeat, another stream, or while
            the standby closes the loop).

        """
        last = self._last_stamp
        jump = self.estimate_jumps.judge(t, last)
        if jump is CLOCK_JUMP:
            self._clock_restarted(t, last, now)
        elif jump is FAR_BACK:
            # an outlier, or the first of a restarted clock's: ignored until agreed
            self._log(WARN, far_back_text('state/estimate', t, last,
                                          self.estimate_jumps.agreement))
            return None
        elif self._answered is not None and t <= self._answered:
            # a repeat (the observer answers a repeated measurement so; a simulator
            # re-sends step 0 until a command answers it) gets the same command again,
            # unchanged; an older one, or one from another publisher, none
            self._count('repeated_estimates')
            if self.publishers > 1:
                self.stream.other += 1
            elif t == self._answered and self._answer is not None:
                return self._answer
            return None
        steps = self._steps_late(t, now)
        if steps is None:
            # too late to predict from: the safe command (or the standby), ERROR
            self._count('too_late_estimates')
            self._too_late += 1
            return None if self.standby is not None else \
                self._safe_command(self._estimate_clock(now))
        x_list = x_hat.tolist() if isinstance(x_hat, np.ndarray) else list(x_hat)
        problem = self.x_envelope.check(t, x_list)
        if problem is not None:
            return self._refuse(t, problem, now)
        if not self._consistent(t, x_list):
            return self.stream.ignore('state/estimate: an estimate that does not follow the '
                                      "stream followed (the standby observer's estimate, or "
                                      'the model from the last one): ignored')
        self._last_wall, self._last_stamp = now, t
        mode = self.mode
        if mode != 'closed' and mode != 'recover':
            command = self._back(t, x_list, now)
            if command is not False:
                return command
        if mode == 'recover' and t - self._recover_since >= self.settle:
            self.mode = 'closed'
        return self._close(t, x_list, 'observer', steps)

    def bad_estimate(self, now, t=None):
        """Take an estimate that cannot be used (a malformed stamp: t None; bad values)."""
        if self.standby is not None and self.mode == 'stale':
            return None         # the standby answers the measurements
        if t is None:
            return self._safe_command(self._estimate_clock(now))
        return self._safe_command(t, answers=True)

    def measurement(self, sensor, t, y, now):
        """
        Take a sensor's stamp t (and its values y, for the standby) at wall time now.

        Returns
        -------
        Command or None
            The standby's command answering this measurement while the observer is
            silent (realtime, with a standby); else None.

        """
        jump = self.sensor_jumps.judge(t, self.plant_time)
        if jump is not IN_BASE:
            if jump is FAR_BACK:
                self._log(WARN, far_back_text(sensor, t, self.plant_time,
                                              self.sensor_jumps.agreement))
                return None
            self._plant_restarted(sensor, t)
        if self._plant_start is None:
            self._plant_start = t
        elif not self.plant_stepping and t > self._plant_start:
            # a realtime plant waits at its step 0 until a command reaches it: that wait
            # is no lag of this process (the plant's clock starts here)
            self.plant_stepping, self._stepping_wall = True, now
            if self.plant_clock is not None:
                self.plant_clock.reset()
        if self.plant_clock is not None:
            self.plant_clock.seen(t, now)
            # a busy host delays the commands as the measurements: a longer lead meanwhile
            self.delay.lead = self.lead_steps + (
                self.plant_clock.extra_steps(now, self.dt) if self.plant_stepping else 0)
        if self.plant_time is None or t > self.plant_time:
            self.plant_time = t
        standby = self.standby
        if standby is None or y is None:
            return None
        x = standby.measurement(sensor, t, y)
        if standby.restarted is not None:   # so does the observer (one admission)
            self.x_envelope.reset()         # its new initial transient learned again
            self.u_envelope.reset()
            self._count('standby_restarts')
            self._log(WARN, f'standby observer: {sensor} {standby.restarted:.2f} s after its '
                      'estimate, longer than the model can be predicted over; restarted at '
                      'the measurement (warm after its settling time; envelopes learn again)')
        if x is None or t < self.plant_time:
            return None
        if standby.warm and self.mode in ('closed', 'recover', 'waiting') and \
                self.stream.standby_agrees and self._last_stamp is not None and \
                t - self._last_stamp > self.lag_limit:
            self._go_stale(f"no estimate within {self.lag_limit:g} s of the plant's time")
        if self.mode not in ('stale', 'resync'):
            return None
        return self._standby_command(t, x, now)

    def watchdog(self, now):
        """
        Check the estimate's age on the wall clock; return True when it just went stale.

        A check that comes more than ``controller.stale_timeout`` after the one before
        judges nothing (``watchdog_deferred``, core.health.HeldOff): the estimates that
        reached the compensator meanwhile wait in its queue, taken after this check. The
        next check, a watchdog period later, judges. Once the sensors are heard (realtime),
        nothing is judged before the plant steps (a sensor stamp later than its first): a
        realtime simulator waits at its step 0 until a command reaches it, and no estimate
        is due meanwhile.
        """
        held_off = self._held_off.check(now, self.vehicle.controller.stale_timeout)
        if self._last_wall is None or self.mode == 'stale':
            return False
        if self._plant_start is not None and not self.plant_stepping:
            # the plant still waits at its step 0 (its measurements say so): no estimate
            # is due before it steps
            return False
        if held_off:
            self._count('watchdog_deferred')
            return False
        age = now - self._last_wall
        if self._stepping_wall is not None and now - self._stepping_wall < age:
            # the estimate of the plant's step 0 came before it stepped: the next one is
            # due from the plant's first step on
            if now - self._stepping_wall <= self.vehicle.controller.stale_timeout:
                return False
        elif age <= self.vehicle.controller.stale_timeout:
            return False
        c = self.vehicle.controller
        how = 'the standby observer closes the loop' if self.standby is not None else \
            'waiting for its estimates (lock-step: the plant waits for them)' \
            if self.resync.plant_waits() else \
            f'safe command (predict {c.predict_timeout:g} s, then {c.safe_command})'
        self._go_stale(f'estimate stale ({age:.2f} s); {how}')
        return True

    def safe_tick(self, now):
        """
        Return the safe command of a sample time while stale (None when none is due).

        With a standby that answered a measurement within the last two sample times (at
        the plant's rate measured, :attr:`.PlantClock.rate`), none: it closes the loop.
        """
        if self.mode != 'stale' or self.resync.plant_waits():
            return None
        period = self.dt / (self.time_rate if self.plant_clock is None else self.plant_clock.rate)
        if self._standby_wall is not None and now - self._standby_wall < 2.0 * period:
            return None
        return self._safe_command(self._estimate_clock(now), marked=True)

    def stop_command(self, now):
        """
        Return the command of a compensator that stops: ``controller.safe_command``.

        Zero, or the last command held, clipped into the limits, stamped on the estimates'
        time base and marked (it answers no estimate).
        """
        fallback = self.vehicle.controller.safe_command
        u = self.safe.last_command if fallback == 'hold' else np.zeros(self.vehicle.plant.m)
        u = self.law.clip(np.asarray(u, dtype=float).tolist())
        t = self._estimate_clock(now)
        self._send(u, t)
        return Command(u, t, marked=True, source='safe')

    # ------------------------------------------------------------ decisions

    def _close(self, t, x_list, source, steps):
        """Return the law's command for an estimate that passed its gates (or the safe one)."""
        t_apply, x_apply = t, x_list
        if steps:
            self._count('delay_compensated_commands')
            self._max_steps = max(self._max_steps, steps)
            t_apply = t + steps * self.dt
            with np.errstate(all='ignore'):
                x_apply = self.delay.predict(x_list, t, steps).tolist()
        u_law = self.law.unclipped(x_list)
        problem = self.u_envelope.check(t, u_law) if all(map(math.isfinite, u_law)) \
            else None
        if problem is not None:
            return self._refuse(t, problem, None)
        if x_apply is x_list:
            u = self.law.clip(u_law)
            # u is u_law inside the limits: the envelope's check above was its own
            reason = self.law.problem(u)
        else:
            u = self.law(x_apply)
            reason = command_refusal(self.law, self.u_envelope, u)
        if reason is not None:
            self._count('refused_commands')
            self._refused_command = f'command {reason}: safe command sent instead'
            self._log(ERROR, self._refused_command)
            return self._safe_command(t_apply, answers=not steps)
        if self._problem is not None:
            self._problem, self._refusals = None, 0
        answered = self._answered
        self._answered = t
        self._followed = (t, x_list)
        self._send(u, t_apply)
        self.safe.trusted(t_apply, x_apply, u)
        self._count('commands')
        command = Command(u, t_apply, answers=not steps, source=source)
        if source == 'standby':
            self._count('standby_commands')
            self._answered = answered
        else:
            self._answer = command
        return command

    def _refuse(self, t, problem, now):
        """Refuse an implausible estimate or command: the safe command, ERROR, once a change."""
        self._refusals += 1
        word = 'diverging' if self._refusals >= ENVELOPE_PERSIST else 'implausible'
        text = f'{word}: {problem}'
        if self._problem is None or word != self._problem.split(':', 1)[0]:
            self._log(ERROR, f'{text}; refused, safe command')
        self._problem = text
        self._count('implausible_estimates')
        if self._reference() or (self.standby is not None and self.mode == 'stale'):
            # the stream followed (or the standby) answers: this one is ignored
            return None
        self._count('divergence_safe_commands')
        if now is not None and self.standby is None:
            # answered (by the safe command): no staleness on top of it
            self._last_wall, self._last_stamp, self._answered = now, t, t
            self._answer = self._safe_command(t, answers=True)
            return self._answer
        return self._safe_command(t, answers=True)

    def _reference(self):
        """Whether estimates are checked against a reference (a warm standby, a stream)."""
        return (self.standby is not None and self.standby.warm) or \
            (self.publishers > 1 and self._followed is not None)

    def _consistent(self, t, x_list):
        """
        Whether an estimate belongs to the stream followed (:mod:`.estimate_stream`).

        With a warm standby whatever the publishers known: a second publisher's first
        estimates can come before its match is known.
        """
        warm = self.standby is not None and self.standby.warm
        if self.publishers <= 1 and not warm:
            return True
        ref = self.standby.at(t) if warm else None
        if ref is not None and not self.x_envelope.inside(ref):
            ref = None          # a standby beyond the envelope (diverged) is no reference
        return self.stream.belongs(x_list, ref, lambda: self._predicted(t), self._scale)

    def _predicted(self, t):
        """Return the model's prediction at t from the last estimate followed, or None."""
        if self._followed is None:
            return None
        t0, x0 = self._followed
        steps = int(round((t - t0) / self.dt))
        return self.safe.predict_from(x0, steps) if 0 < steps <= CONSISTENCY_STEPS else None

    def _back(self, t, x_list, now):
        """Estimates after an outage: resync; return a command, None, or False (close)."""
        if self.mode == 'waiting':
            self.mode = 'closed'
            return False
        if self.mode == 'stale' and self.resync.same_observer():
            self.mode = 'closed'
            self._log(WARN, 'estimates back from the same observer (lock-step: the plant '
                      'waited for them): closing the loop on them')
            return False
        if self.standby is not None and not self.standby.warm:
            # nothing to compare them with yet (its first settling time): the observer's
            # estimates are the best there is; the prediction ran open loop meanwhile
            self.mode = 'closed'
            return False
        if self.standby is not None:
            if self.mode == 'stale':
                self.mode, self.resync.agreeing = 'resync', 0
            if not self.resync.agrees(x_list, self.standby.at(t), self._scale):
                self._count('resync_estimates')
                return None         # the standby answers the measurements meanwhile
            self.mode = 'closed'
            self._log(WARN, f'estimates agree with the standby observer again ({RESYNC_AGREE}'
                      ' in a row): closing the loop on them')
            return False
        if not np.isfinite(self.settle):
            self.mode = 'closed'
            return False
        if self.mode == 'stale':
            # the observer restarts or catches up; until it has settled (its estimates
            # follow the model again; at most RESYNC_SETTLINGS of its settling times) the
            # prediction keeps closing the loop
            self.mode = 'resync'
            self.settle_check.start(self._estimate_clock(now) + RESYNC_SETTLINGS * self.settle)
        self._count('resync_commands')
        command = self._safe_command(t, answers=True)
        if self.settle_check.settled(t, np.asarray(x_list), self.safe.last_command):
            self.mode, self._recover_since = 'recover', t
        return command

    def _standby_command(self, t, x, now):
        """Return the standby's command for its estimate at a measurement's stamp t."""
        self._standby_wall = now
        if not self.standby.warm:       # not converged yet: the safe command
            return self._safe_command(t)
        x_list = x.tolist()
        problem = self.x_envelope.check(t, x_list)
        if problem is not None:
            self._refuse(t, f'standby observer: {problem}', None)
            return self._safe_command(t)
        # stamped as the observer's would be: at the plant's time plus the lead, never
        # before a command already sent (the plant would ignore it; the observers not)
        steps = self._steps_late(t, now)
        if steps is None:
            return None
        return self._close(t, x_list, 'standby', steps)

    def _go_stale(self, why):
        self.mode = 'stale'
        self.resync.went_stale()
        self._log(ERROR, why)

    def _safe_command(self, t, marked=False, answers=False):
        """
        Send the safe command for time t (SafeCommand), clipped into the limits.

        With delay compensation it takes effect where the law's commands do (the plant's
        time plus the lead), never before one already sent: the plant would ignore it.
        """
        if self.delay is not None and self.plant_time is not None:
            steps = self.delay.steps_late(self.plant_time, t)
            ahead = self.plant_time + self.delay.lead * self.dt if steps is None else \
                t + steps * self.dt
            if ahead > t:
                t, answers = ahead, False
        u, self.safe_mode = self.safe.command(t)
        u = self.law.clip(u.tolist())
        self._send(u, t)
        self._count('safe_commands')
        self._count(f'safe_commands_{self.safe_mode}')
        return Command(u, t, answers=answers, marked=marked, source='safe')

    def _send(self, u, t):
        """Note a command about to be sent: hold, delay compensation, standby."""
        t = stamp_sec(t)    # as the plant and the observer read it: t + k dt is off by ulps
        self.safe.sent(u)
        if self.delay is not None:
            self.delay.sent(t, u)
        if self.standby is not None:
            self.standby.command(t, u)

    def _plant_restarted(self, sensor, t):
        """Sensor stamps agree the plant's clock started over: forget the old run's plant."""
        self._log(WARN, f'clock jumped back: {sensor} {self.plant_time - t:.3f} s '
                  f'({self.sensor_jumps.agreement} in a row; a restarted simulator?); plant '
                  'time, standby observer and safe command reset')
        self.plant_time = None
        self._plant_start, self.plant_stepping = None, False
        if self.plant_clock is not None:
            self.plant_clock.reset()
        if self.standby is not None:
            self.standby.reset()
        self.safe.reset()
        if self.delay is not None:
            self.delay.reset()

    def _clock_restarted(self, t, last, now):
        """Estimates agree their clock started over: forget the old run's loop; resync."""
        # the plant's side is the sensors' to restart: kept when they jumped first
        plant = self.plant_time is None or self.sensor_jumps.far_back(t, self.plant_time)
        self._log(WARN, f'clock jumped back: state/estimate {last - t:.3f} s '
                  f'({self.sensor_jumps.agreement} in a row; a restarted simulator?); '
                  f'{"safe command and " if plant else ""}limits reset')
        self.mode = 'resync' if self.standby and self.standby.warm else 'closed'
        self.resync.agreeing = 0
        self._last_wall, self._last_stamp = now, t      # the new time base
        self._answered = self._followed = self._answer = None
        self._problem, self._refusals = None, 0
        if plant:
            self.safe.reset()
            self._plant_start, self.plant_stepping = None, False
            if self.delay is not None:
                self.delay.reset()
        self.x_envelope.reset()
        self.u_envelope.reset()

    def _steps_late(self, t, now=None):
        """
        Return the steps the estimate stamped t is late (0 uncompensated; None: too late).

        Too late by the stamps: later than ``observer.history_length`` behind the newest
        sensor stamp. The steps are counted to the plant's time at wall time now
        (:meth:`_plant_now`, or from t, a measurement's stamp, when newer and the plant is
        past it; without ``now``, the newest sensor stamp).
        """
        if self.delay is None:
            return 0
        steps = self.delay.steps_late(self.plant_time, t)
        plant = self._plant_now(now)
        if plant is not None and t > plant and (newer := self._plant_now(now, t)) > t:
            plant = newer       # the plant is past t by the wall clock
        if steps is None or plant == self.plant_time:
            return steps
        return self.delay.steps_late(min(plant, t + self.delay.max_delay), t)

    def _plant_now(self, now, newest=None):
        """Return the plant's time at wall time now from the newest stamp (plant_time)."""
        newest = self.plant_time if newest is None else newest
        if self.plant_clock is None or not self.plant_stepping:
            return newest           # (a plant at its step 0 waits: it is where it says)
        return self.plant_clock.plant_now(newest, now, self.dt, self.delay.max_delay)

    def _estimate_clock(self, now):
        """
        Now on the estimates' time base (their last stamp plus the time since).

        With delay compensation: the plant's time (:meth:`_plant_now`) plus the lead,
        when the command takes effect (a simulator slower than the wall clock would
        otherwise get safe commands stamped ahead of it).
        """
        lead = 0.0 if self.delay is None else self.delay.lead * self.dt
        if self.delay is not None and self.plant_time is not None:
            t = self._plant_now(now) + lead
        elif self._last_stamp is None:
            return self._clock()
        else:
            t = self._last_stamp + (now - self._last_wall) * self.time_rate
        bound = self._clock_bound()
        return t if bound is None else min(t, bound + lead)

    # ------------------------------------------------------------ report

    def status(self, duplicates=()):
        """
        Return ``(level, message, values)`` for /diagnostics, and start a new report.

        Parameters
        ----------
        duplicates : sequence of str
            ``"topic (N publishers)"`` for the node's topics with more than one.

        """
        values = {'u': np.array2string(np.asarray(self.safe.last_command, dtype=float)),
                  'max_steps_predicted': self._max_steps, 'mode': self.mode}
        if self.plant_time is not None:
            values['plant_time'] = f'{self.plant_time:.6f}'
        self._max_steps = 0
        too_late, self._too_late = self._too_late, 0
        other = self.stream.report()
        refused, self._refused_command = self._refused_command, None
        level, message = status_message(
            self.mode, duplicates=duplicates, other=other, refused=refused,
            too_late=too_late, problem=self._problem, standby=self.standby is not None,
            safe_mode=self.safe_mode, history=self.vehicle.observer.history_length,
            settle=self.settle)
        return level, message, values
