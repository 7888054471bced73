# observer_ros.core.estimators.admission: what a message's stamp means, decided once.
"""
Admission: the one decision of what each measurement or command stamp means.

The observer node and the bag replay both ask an :class:`Admission` about every message
before it reaches the estimator's :class:`~observer_ros.core.estimators.History`, so the
replay of a recording judges each message as the node judged it live. The answer is a
:class:`Verdict`: whether the message is used, how, and the diagnostics counter it bumps
(the admission bumps it in the counts it was given).

A measurement stamped t, with the estimate at time ``head`` and ``newest`` the newest
stamp any sensor has given since the last reset:

- ``t`` after ``head`` (or no estimate yet): used in order (:data:`IN_ORDER`); after a
  gap longer than ``max_gap`` the estimator restarts at it (:data:`LONG_GAP`,
  ``long_gap_resets``: predicting across the gap would amplify the error);
- ``t`` before ``head`` but inside the history: used at its stamp (:data:`LATE`,
  ``late_measurements``); older than the history: skipped (:data:`OUT_OF_ORDER`,
  ``out_of_order``);
- ``t`` more than ``clock_jump_tolerance`` before ``newest``: a stamp far back
  (:data:`FAR_BACK`, ``far_back_stamps``), skipped, the estimate untouched, unless it is
  the ``clock_jump_agreement``-th such message in a row: then the clock jumped back and
  the estimator restarts at it (:data:`CLOCK_JUMP`, ``clock_jumps``). The rule is
  :class:`~observer_ros.core.clock_jump.ClockJump`'s, the one every component that
  resets on a clock jump asks; a message older than the history but not far back breaks
  the streak as one in order does;
- the stamp this sensor gave last, again: skipped (:data:`DUPLICATE`, ``duplicates``);
- more than ``future_tolerance`` ahead of the clock: skipped (:data:`FUTURE`,
  ``future_stamps``).

A command stamped t is never a time source and never resets the estimator: ahead of the
clock by more than ``future_tolerance``, or of the estimate by more than
``clock_jump_tolerance``, it is skipped (:data:`FUTURE_COMMAND`,
:data:`AHEAD_COMMAND`, ``future_stamps``); inside the history or newer it applies from
its stamp (:data:`COMMAND`); older than the history it is held from the estimate's time
(:data:`HELD_COMMAND`, ``late_commands_held_from_now``; more than
``clock_jump_tolerance`` back, :data:`STALE_COMMAND`, ``late_commands``): the plant holds
the newest command it was sent, whatever its stamp says.

A malformed stamp (``nanosec`` >= 10^9, negative ``sec``, the first second of the clock:
:func:`check_stamp`, :func:`malformed_ns`) is refused before any of this
(:data:`BAD_STAMP`, ``bad_stamps``). The callers count what comes after the verdict
(``measurements``, ``rejected_updates``, ...).

"The clock" is what the caller's ``clock`` callable reads (the node's ROS clock), or the
``now`` it passes (the replay: the receive time the recorder wrote). A message without a
header carries the time it was received, which is never ahead.

"""

import math
from typing import NamedTuple, Optional

import numpy as np

from ..clock_jump import CLOCK_JUMP as JUMPED, CLOCK_JUMP_AGREEMENT, CLOCK_JUMP_TOLERANCE, \
    ClockJump
from ..errors import ObserverError
from ...timeutil import ns_to_sec

__all__ = ['Admission', 'Verdict', 'check_stamp', 'stamp_ns', 'malformed_ns', 'restart_at',
           'restart_state',
           'CLOCK_JUMP_TOLERANCE', 'FUTURE_TOLERANCE', 'CLOCK_JUMP_AGREEMENT',
           'FIRST_VALID_NS', 'MALFORMED_NS', 'IN_ORDER', 'LATE', 'LONG_GAP', 'CLOCK_JUMP',
           'FAR_BACK', 'OUT_OF_ORDER', 'DUPLICATE', 'FUTURE', 'BAD_STAMP', 'COMMAND',
           'HELD_COMMAND', 'STALE_COMMAND', 'FUTURE_COMMAND', 'AHEAD_COMMAND']

#: s: a stamp this far ahead of the clock is refused
FUTURE_TOLERANCE = 10.0
#: the first stamp that is not malformed, in ns (1 s: a zero stamp reads as unset)
FIRST_VALID_NS = 1_000_000_000
#: what :func:`stamp_ns` gives for a malformed stamp (below :data:`FIRST_VALID_NS`)
MALFORMED_NS = -1
# s of the caller's wall clock during which a clock reading bounds the stamps not ahead
_BOUND_LIFETIME = 1.0


class Verdict(NamedTuple):
    """
    What a message's stamp means.

    Attributes
    ----------
    name : str
        A short name (``in_order``, ``far_back``, ...).
    counter : str or None
        The diagnostics counter the admission bumped for it (None: none).
    use : bool
        The message goes to the estimator.
    restart : bool
        Restart the estimator at the message before using it (a clock jump, a long
        gap: :func:`restart_state`).

    """

    name: str
    counter: Optional[str]
    use: bool
    restart: bool = False


IN_ORDER = Verdict('in_order', None, True)
LATE = Verdict('late', 'late_measurements', True)
LONG_GAP = Verdict('long_gap', 'long_gap_resets', True, True)
CLOCK_JUMP = Verdict('clock_jump', 'clock_jumps', True, True)
FAR_BACK = Verdict('far_back', 'far_back_stamps', False)
OUT_OF_ORDER = Verdict('out_of_order', 'out_of_order', False)
DUPLICATE = Verdict('duplicate', 'duplicates', False)
FUTURE = Verdict('future', 'future_stamps', False)
BAD_STAMP = Verdict('bad_stamp', 'bad_stamps', False)
COMMAND = Verdict('command', None, True)
HELD_COMMAND = Verdict('held_command', 'late_commands_held_from_now', True)
STALE_COMMAND = Verdict('stale_command', 'late_commands', True)
FUTURE_COMMAND = Verdict('future_command', 'future_stamps', False)
AHEAD_COMMAND = Verdict('ahead_command', 'future_stamps', False)


def check_stamp(sec, nanosec, topic):
    """
    Return the seconds of a stamp given as ``sec`` and ``nanosec``; refuse a malformed one.

    Raises
    ------
    ObserverError
        Naming the topic, when ``nanosec`` is not below 10^9, ``sec`` is negative, or the
        stamp lies in the first second of its clock (``sec`` 0: an unset header).

    """
    sec, nanosec = int(sec), int(nanosec)
    if not 0 <= nanosec < 1_000_000_000:
        raise ObserverError(f'{topic}: header.stamp.nanosec {nanosec} is not below 10^9')
    if sec < 0:
        raise ObserverError(f'{topic}: header.stamp.sec {sec} is negative')
    if sec == 0:
        raise ObserverError(f'{topic}: header.stamp {sec} s {nanosec} ns is in the first '
                            'second (an unset stamp)')
    return ns_to_sec(sec * 1_000_000_000 + nanosec)


def stamp_ns(sec, nanosec):
    """
    Return a stamp's nanoseconds, :data:`MALFORMED_NS` when ``nanosec`` is not below 10^9.

    Works on numbers and on numpy arrays alike. The result is below
    :data:`FIRST_VALID_NS` exactly when :func:`check_stamp` refuses the stamp.
    """
    ns = sec * 1_000_000_000 + nanosec
    if isinstance(ns, np.ndarray):
        return np.where((nanosec >= 0) & (nanosec < 1_000_000_000), ns, MALFORMED_NS)
    return ns if 0 <= nanosec < 1_000_000_000 else MALFORMED_NS


def malformed_ns(ns):
    """Tell which stamps (ns, from :func:`stamp_ns`) :func:`check_stamp` refuses (arrays too)."""
    return ns < FIRST_VALID_NS


def restart_state(estimator, rows, y):
    """
    Return the estimate to restart at (a clock jump, a long gap): x_hat(0) agreeing with y.

    The one nearest the estimator's initial estimate that gives the measurement (least
    squares on C's rows, u taken as zero): restarting from x_hat(0) itself would leave
    the whole distance to the plant as an estimation error (a plant that went on while
    the clock restarted: the cart's fast observer turned 1 m of it into a theta_dot of
    1.1e3 rad/s).

    Parameters
    ----------
    estimator : Estimator
        Reset (its :attr:`x_hat` is its initial estimate).
    rows : sequence of int
        The measurement's output rows.
    y : array_like
        The measured values.

    """
    x0 = estimator.x_hat
    C = estimator.plant.C[list(rows)]
    return x0 + np.linalg.pinv(C) @ (np.asarray(y, dtype=float) - C @ x0)


def restart_at(history, estimator, rows, y):
    """
    Start a history over at a measurement (the verdict's ``restart``): a clock jump, a gap.

    The history is cleared, so that the estimator holds its initial estimate, then set to
    :func:`restart_state` at no time (the measurement, corrected with next, gives it). The
    observer node, the replay and the compensator's standby all restart so.
    """
    history.reset(None, None)
    history.reset(restart_state(estimator, rows, y), None)


class Admission:
    """
    Judge each message's stamp against the estimate, the clock and the stamps before it.

    Parameters
    ----------
    history : History
        The estimator's history (its time and window); replace :attr:`history` when the
        caller builds a new one.
    clock_jump_tolerance : float
        s, > 0.
    future_tolerance : float or None
        s, > 0; None: no stamp is too far ahead.
    clock_jump_agreement : int
        Far-back measurements in a row that make a clock jump, >= 1.
    max_gap : float
        s: a measurement this long after the estimate restarts it (inf: never).
    clock : callable, optional
        ``clock()`` -> the time now on the stamps' clock, in s (<= 0: no clock yet). Read
        at most once per ``_BOUND_LIFETIME`` of the caller's wall time while stamps stay
        below the last reading plus ``future_tolerance``. Without it the caller passes
        ``now`` to each call.
    counts : dict, optional
        The counters to bump (a new dict by default): :attr:`counts`.

    Attributes
    ----------
    previous : float or None
        After :meth:`measurement`: the newest stamp the sensor had given before, or None.

    """

    def __init__(self, history, clock_jump_tolerance=CLOCK_JUMP_TOLERANCE,
                 future_tolerance=FUTURE_TOLERANCE, clock_jump_agreement=CLOCK_JUMP_AGREEMENT,
                 max_gap=math.inf, clock=None, counts=None):
        self.history = history
        self.counts = {} if counts is None else counts
        self.jumps = ClockJump(clock_jump_tolerance, clock_jump_agreement, self._bump)
        self._jump = self.jumps.tolerance
        self.future_tolerance = future_tolerance
        self.max_gap = max_gap
        self._clock = clock
        self.previous = None
        self._clear()

    @property
    def clock_jump_tolerance(self):
        """s: a measurement this far before the newest stamp is far back."""
        return self._jump

    @clock_jump_tolerance.setter
    def clock_jump_tolerance(self, value):
        self.jumps.tolerance = value
        self._jump = self.jumps.tolerance

    @property
    def future_tolerance(self):
        """s: a stamp this far ahead of the clock is refused (None: never)."""
        return self._future

    @future_tolerance.setter
    def future_tolerance(self, value):
        if value is not None:
            value = float(value)
            if not value > 0.0:
                raise ValueError(f'future_tolerance must be > 0; got {value!r}')
        self._future = value
        self._bound = -math.inf

    @property
    def clock_jump_agreement(self):
        """Far-back measurements in a row that make a clock jump."""
        return self.jumps.agreement

    @clock_jump_agreement.setter
    def clock_jump_agreement(self, value):
        self.jumps.agreement = value

    def _clear(self):
        """Forget the stamps seen: a new time base."""
        self._newest = {}           # sensor key -> its newest stamp used
        self._top = None            # the newest of them
        self.jumps.clear()          # no far-back measurements in a row
        self._bound = -math.inf     # stamps up to here are not ahead of the clock ...
        self._until = -math.inf     # ... until this wall time

    def reset(self):
        """Forget every stamp seen (the caller reset its estimator for another reason)."""
        self._clear()

    @property
    def newest(self):
        """Return the newest measurement stamp used since the last clock jump, or None."""
        return self._top

    def _count(self, verdict):
        counts = self.counts
        counts[verdict.counter] = counts.get(verdict.counter, 0) + 1
        return verdict

    def _bump(self, counter):
        counts = self.counts
        counts[counter] = counts.get(counter, 0) + 1

    def _ahead(self, t, wall, now):
        """Tell whether t is more than future_tolerance ahead of the clock."""
        tol = self._future
        if tol is None:
            return False
        if now is None:
            now = self._clock()
            if now > 0.0:
                # the clock only moves forward between two readings (a jump back is a
                # clock jump, which clears this bound)
                self._bound, self._until = now + tol, wall + _BOUND_LIFETIME
        return now > 0.0 and t - now > tol

    def measurement(self, key, t, wall=0.0, now=None):
        """
        Judge a measurement stamped t (s) of the sensor ``key``; bump its counter.

        Parameters
        ----------
        key : hashable
            The sensor (its name, or an index).
        t : float
            The stamp in s (well formed).
        wall : float
            The caller's wall clock (s), for how long a clock reading is trusted.
        now : float, optional
            The time now on the stamps' clock (the replay: the receive time); default:
            read from ``clock`` when needed.

        Returns
        -------
        Verdict

        """
        history = self.history
        head = history.t
        newest = self._newest
        previous = self.previous = newest.get(key)
        verdict = IN_ORDER
        if head is not None and t < head:
            top = self._top
            if (head if top is None else top) - t > self._jump:
                return self._far_back(key, t)
            if not history.accepts(t):
                self.jumps.interrupt()
                return self._count(OUT_OF_ORDER)
            verdict = LATE
        jumps = self.jumps
        if jumps.streak:
            jumps.interrupt()
        if previous == t:
            return self._count(DUPLICATE)
        if (t > self._bound or wall >= self._until) and self._ahead(t, wall, now):
            return self._count(FUTURE)
        if verdict is IN_ORDER and head is not None and t - head > self.max_gap:
            verdict = LONG_GAP
        if previous is None or t > previous:
            newest[key] = t
            top = self._top
            if top is None or t > top:
                self._top = t
        if verdict.counter is not None:
            self._count(verdict)
        return verdict

    def _far_back(self, key, t):
        """Judge a measurement far before the newest stamp: an outlier, or one more agreeing."""
        if self.jumps.stamp_far_back(t) is not JUMPED:
            return FAR_BACK                 # counted by the agreement
        self._clear()
        self._newest[key] = self._top = t
        return CLOCK_JUMP

    def used(self, key, t):
        """Note a measurement the caller used in order without asking (replay in bulk)."""
        newest = self._newest
        if key not in newest or t > newest[key]:
            newest[key] = t
        if self._top is None or t > self._top:
            self._top = t
        self.jumps.interrupt()

    def command(self, t, wall=0.0, now=None):
        """
        Judge a command stamped t (s); bump its counter.

        Parameters are those of :meth:`measurement` (without the sensor).

        Returns
        -------
        Verdict
            :data:`COMMAND`, :data:`HELD_COMMAND` or :data:`STALE_COMMAND` (to
            ``History.set_input``, which holds the last two from the estimate's time), or
            :data:`FUTURE_COMMAND` or :data:`AHEAD_COMMAND` (skipped).

        """
        if (t > self._bound or wall >= self._until) and self._ahead(t, wall, now):
            return self._count(FUTURE_COMMAND)
        history = self.history
        head = history.t
        if head is None:
            return COMMAND
        if t > head:
            if t - head > self._jump:
                return self._count(AHEAD_COMMAND)
            return COMMAND
        if t < head and not history.accepts(t):
            return self._count(STALE_COMMAND if head - t > self._jump else HELD_COMMAND)
        return COMMAND
