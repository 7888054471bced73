# observer_ros.nodes.clock_follower: where a simulator's steps fall on another one's /clock.
"""
One time base per ROS graph: the steps of a simulator that follows /clock.

A second vehicle's simulator (``simulator.publish_clock: false``) takes its time from the
/clock another vehicle publishes: it starts at /clock's time and takes a step only when
/clock has reached it. :class:`ClockFollower` holds that decision (no ROS here; the
simulator node feeds it each /clock it hears and asks it before each step).

A /clock more than :data:`CLOCK_RESYNC` before the newest one heard is a clock jump only
once :data:`~observer_ros.core.clock_jump.CLOCK_JUMP_AGREEMENT` of them come in a row
(:class:`~observer_ros.core.clock_jump.ClockJump`, the rule of the observer and the
compensator): a single one is skipped, counted (``far_back_stamps``), and the time base
stays; the agreed one is counted as ``clock_jumps``.

"""

from ..core.clock_jump import CLOCK_JUMP, CLOCK_JUMP_AGREEMENT, ClockJump, FAR_BACK

__all__ = ['ClockFollower', 'CLOCK_RESYNC', 'CLOCK_CATCH_UP']

#: s: a /clock this far behind the step taken restarts the follower's time base from it
#: (its owner restarted); a realtime follower this far behind /clock catches up
CLOCK_RESYNC = 0.5
#: s: a follower this far behind /clock starts again from it
CLOCK_CATCH_UP = 10.0


class ClockFollower:
    """
    Place a simulator's steps on the /clock it hears.

    Parameters
    ----------
    dt : float
        The simulator's step (s).
    first_wait : float
        Wall seconds to wait for the first /clock before running on the simulator's own
        time.
    count : callable, optional
        ``count(name)``: bumps ``far_back_stamps`` or ``clock_jumps`` (of /clock).

    Attributes
    ----------
    clock : float or None
        The last /clock taken (s), None before the first.
    newest : float or None
        The newest /clock of the time base (s), far-back ones are judged against it.
    synced : bool
        The time base is placed (on /clock's time, or on the simulator's own after
        ``first_wait``).

    """

    def __init__(self, dt, first_wait, count=None):
        self.dt = float(dt)
        self.first_wait = float(first_wait)
        self.clock = None
        self.synced = False
        self.jumps = ClockJump(CLOCK_RESYNC, CLOCK_JUMP_AGREEMENT, count)
        self.newest = None          # the newest /clock of the time base

    def heard(self, sec, nanosec):
        """Take a /clock message's time; return False when it is skipped (far back)."""
        clock = (int(sec) * 1_000_000_000 + int(nanosec)) * 1e-9
        verdict = self.jumps.judge(clock, self.newest)
        if verdict == FAR_BACK:
            return False
        if verdict == CLOCK_JUMP or self.newest is None or clock > self.newest:
            self.newest = clock
        self.clock = clock
        return True

    def start(self, k, waited):
        """
        Return where step k starts: a t0 (step k at /clock), None (own time), or False.

        False: no /clock yet, keep waiting (``waited`` wall s so far, less than
        ``first_wait``). Called until it returns something other than False.
        """
        if self.clock is None:
            if waited <= self.first_wait:
                return False
            self.synced = True
            return None
        self.synced = True
        return self.t0_at(k)

    def t0_at(self, k):
        """Return the t0 that puts step k at the newest /clock (None without one)."""
        return None if self.clock is None else self.clock - k * self.dt

    def steps_due(self, t, k):
        """
        Return the steps /clock has reached after the step at t, and a new t0 or None.

        ``(n, None)``: n steps are due (0: wait). ``(1, t0)``: /clock went back more than
        :data:`CLOCK_RESYNC` (its owner restarted) or is more than
        :data:`CLOCK_CATCH_UP` ahead: the next step (k + 1) is put at /clock's time.
        Without a /clock (or before the time base is placed): ``(1, None)``.
        """
        clock = self.clock
        if clock is None or not self.synced:
            return 1, None
        if clock < t - CLOCK_RESYNC or clock > t + CLOCK_CATCH_UP:
            return 1, clock - (k + 1) * self.dt
        return max(0, int((clock - t) / self.dt + 1e-9)), None
