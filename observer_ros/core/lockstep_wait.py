# observer_ros.core.lockstep_wait: the lock-step observer's wait for its command.
"""
The lock-step observer's wait for the command that answers its estimate.

In a lock-step run the simulator publishes the measurements of step k+1 only once the
command of step k has reached it; the observer must take that command u(k) before it
corrects with y(k+1), or its estimate is not the run's. Each estimate it publishes is
answered by one command stamped as the estimate; until that command comes, measurements
wait in the node's queue.

A watchdog (a timer, :data:`WATCH_PERIOD`) re-sends the estimate after
:data:`RESEND_AFTER` s without an answer (DDS matching can lag at the start) and gives
up after the simulator's ``command_timeout``. A check that comes more than
:data:`WATCH_GAP` s after the one before (the process was held off the CPU:
core.health.HeldOff) judges nothing, and the wait starts again from it: the command may be
in the process's queue, still to be taken, and the time the process did not run is not a
time it waited.
"""

from .health import HeldOff

__all__ = ['CommandWait', 'WATCH_PERIOD', 'WATCH_GAP', 'RESEND_AFTER', 'DEFERRED', 'GAVE_UP',
           'RESEND']

# s: the watchdog's period, and the gap between two of its checks beyond which the later
# one judges nothing
WATCH_PERIOD = 0.1
WATCH_GAP = 0.5
# s without an answer after which the estimate is sent again
RESEND_AFTER = 0.2

# what a check asks of the node (None: nothing)
DEFERRED = 'watchdog_deferred'      # held off the CPU: nothing judged, the wait restarts
GAVE_UP = 'command_wait_timeouts'   # no command within the timeout: take the queue
RESEND = 'resent_estimates'         # send the last estimate again


class CommandWait:
    """
    Count the estimates whose command has not come back, and judge the wait.

    The verdicts of :meth:`check` are also the names of the counters the node keeps.
    """

    def __init__(self):
        self.pending = 0            # estimates whose command is not back
        self.since = None           # monotonic time of the newest of them (once pending)
        self.stamp = None           # its stamp: the command that answers it has this one
        self._held_off = HeldOff()

    def published(self, t, now):
        """Note an estimate stamped ``t`` published at ``now`` (monotonic seconds)."""
        self.pending += 1
        self.since = now
        self.stamp = t

    def answered(self, t):
        """
        Take a command stamped ``t``; return True when it ends the wait.

        Only a command stamped as the newest estimate answers it (an older one, e.g. the
        answer to an estimate sent again, does not).
        """
        if self.pending > 0 and t == self.stamp:
            self.pending -= 1
            return self.pending == 0
        return False

    def check(self, now, timeout):
        """
        Judge the wait at ``now``: DEFERRED, GAVE_UP, RESEND, or None.

        GAVE_UP ends the wait (the node takes its queued measurements). ``timeout``: the
        seconds to wait for a command (the simulator's ``command_timeout``).
        """
        held_off = self._held_off.check(now, WATCH_GAP)
        if not self.pending:
            return None
        if held_off:
            self.since = now
            return DEFERRED
        waited = now - self.since
        if waited > timeout:
            self.pending = 0
            return GAVE_UP
        if waited > RESEND_AFTER:
            return RESEND
        return None
