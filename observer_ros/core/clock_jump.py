# observer_ros.core.clock_jump: when stamps far back mean that a clock started over.
"""
The one rule for a clock that jumped back: stamps in a row that agree.

A stamp more than ``tolerance`` before the newest stamp of its time base is far back.
One such stamp is an outlier (a glitched header, a message from a dead run still in
flight): it is skipped and counted (``far_back_stamps``), and nothing resets. A clock
that started over (a restarted simulator, a looping bag, the owner of /clock restarted)
sends every following message in its new time base: the ``agreement``-th far-back stamp
in a row is a clock jump (``clock_jumps``), and the caller starts its time base over at
it. Stamps agree when no stamp of the old time base comes between them and none is more
than ``tolerance`` before the newest of them (a repeat agrees: a restarted realtime
simulator sends its step 0 again until a command answers it).

The observer node and the replay (through
:class:`~observer_ros.core.estimators.admission.Admission`), the compensator's loop
supervisor (its sensor stamps and its estimates) and a simulator following /clock all
ask a :class:`ClockJump`, so each of them resets on the same evidence and counts it under
the same names.

"""

import math

__all__ = ['ClockJump', 'far_back_text', 'IN_BASE', 'FAR_BACK', 'CLOCK_JUMP',
           'CLOCK_JUMP_TOLERANCE', 'CLOCK_JUMP_AGREEMENT']

#: s: a stamp this far before the newest one is far back (a clock jump if agreed)
CLOCK_JUMP_TOLERANCE = 0.5
#: far-back stamps in a row that make a clock jump (1: every one is a jump)
CLOCK_JUMP_AGREEMENT = 3

#: the stamp belongs to the time base (not far back): the streak, if any, is broken
IN_BASE = 'in_base'
#: far back, not (yet) agreed: skip it, reset nothing (``far_back_stamps``)
FAR_BACK = 'far_back'
#: the agreed far-back stamp: the clock started over here (``clock_jumps``)
CLOCK_JUMP = 'clock_jump'


def _nothing(key):
    return None


def far_back_text(topic, t, newest, agreement):
    """Return the log line of a far-back stamp t (s) skipped, ``newest`` the newest stamp."""
    return (f'{topic}: stamp {t:.6f} is {newest - t:.3f} s before the newest '
            f'({newest:.6f}); skipped (a clock jump needs {agreement} such messages in a row)')


class ClockJump:
    """
    Judge stamps against the newest of their time base; agree on a clock jump.

    Parameters
    ----------
    tolerance : float
        s, > 0 and finite: a stamp this far before the newest is far back.
    agreement : int
        Far-back stamps in a row that make a clock jump, >= 1.
    count : callable, optional
        ``count(name)``: bumps a counter, one of ``counters``.
    counters : (str, str)
        The names of the far-back and the clock-jump counters (default
        ``far_back_stamps``, ``clock_jumps``: the sensor stamps' names in every node).

    Attributes
    ----------
    streak : int
        Far-back stamps in a row so far (0: none).

    """

    def __init__(self, tolerance=CLOCK_JUMP_TOLERANCE, agreement=CLOCK_JUMP_AGREEMENT,
                 count=None, counters=('far_back_stamps', 'clock_jumps')):
        self.tolerance = tolerance
        self.agreement = agreement
        self.count = count or _nothing
        self._far_counter, self._jump_counter = counters
        self.streak = 0
        self._streak_top = None     # the newest far-back stamp of the streak

    @property
    def tolerance(self):
        """s: a stamp this far before the newest is far back."""
        return self._tolerance

    @tolerance.setter
    def tolerance(self, value):
        value = float(value)
        if not (value > 0.0 and math.isfinite(value)):
            raise ValueError(f'clock_jump_tolerance must be > 0 and finite; got {value!r}')
        self._tolerance = value

    @property
    def agreement(self):
        """Far-back stamps in a row that make a clock jump."""
        return self._agreement

    @agreement.setter
    def agreement(self, value):
        if isinstance(value, bool) or int(value) != value or value < 1:
            raise ValueError(f'clock_jump_agreement must be an integer >= 1; got {value!r}')
        self._agreement = int(value)

    def far_back(self, t, newest):
        """Tell whether stamp t is far back of ``newest`` (None: no time base yet)."""
        return newest is not None and newest - t > self._tolerance

    def judge(self, t, newest):
        """
        Judge stamp t (s) against ``newest``, the newest stamp of its time base (or None).

        Returns
        -------
        str
            :data:`IN_BASE` (the streak is broken), :data:`FAR_BACK` (counted
            ``far_back_stamps``) or :data:`CLOCK_JUMP` (counted ``clock_jumps``; the
            streak starts over: the caller's time base is the jump's, newest t). The
            counters are those named by ``counters``.

        """
        if newest is None or newest - t <= self._tolerance:
            if self.streak:
                self.streak = 0
            return IN_BASE
        return self.stamp_far_back(t)

    def stamp_far_back(self, t):
        """Take stamp t that the caller found far back; return FAR_BACK or CLOCK_JUMP."""
        if self.streak and t >= self._streak_top - self._tolerance:
            self.streak += 1
            if t > self._streak_top:
                self._streak_top = t
        else:
            self.streak, self._streak_top = 1, t
        if self.streak < self._agreement:
            self.count(self._far_counter)
            return FAR_BACK
        self.streak, self._streak_top = 0, None
        self.count(self._jump_counter)
        return CLOCK_JUMP

    def interrupt(self):
        """Break the streak: a message of the old time base came (the caller judged it)."""
        self.streak = 0

    def clear(self):
        """Forget the streak (a new time base for another reason)."""
        self.streak, self._streak_top = 0, None
