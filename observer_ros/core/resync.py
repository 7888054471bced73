# observer_ros.core.resync: when the compensator follows the estimates again after an outage.
"""
After an outage (the estimates stale), when the loop follows the observer's estimates again.

- **Lock-step.** The simulator waits for each step's answer. While an estimate publisher
  is matched, the compensator sends no safe command (:meth:`Resync.plant_waits`): the
  simulator would wait it out, while the observer would take it for the input of the step
  it waits on. So the plant does not move and the observer misses no measurement (held
  off the CPU, its messages queue). When no estimate publisher matched since the
  estimates went stale (the DDS match count, :attr:`Resync.matches`, is unchanged), its
  estimates are followed again at once: the run stays the run it would have been without
  the outage. A publisher that matched meanwhile (an observer restarted) resyncs as
  below. Once no estimate publisher is left, safe commands go out, and the simulator
  applies them.
- **With a standby observer** (realtime): the standby keeps closing the loop until
  :data:`RESYNC_AGREE` estimates in a row agree with the standby's (within
  :data:`RESYNC_TOL` of each state's scale: the command does not jump).
- **Otherwise**: the prediction keeps closing the loop until the observer's estimates
  follow the model step by step again (:class:`~.health.SettleCheck`), at most
  :data:`RESYNC_SETTLINGS` observer settling times.

No ROS here.
"""

from .estimate_stream import within

__all__ = ['RESYNC_AGREE', 'RESYNC_SETTLINGS', 'RESYNC_TOL', 'Resync']

# After an outage, wait at most this many observer settling times for it to settle again.
RESYNC_SETTLINGS = 10.0
# Estimates in a row that agree with the standby's (within RESYNC_TOL of each state's
# scale: the command does not jump) before the loop follows them again.
RESYNC_AGREE = 10
RESYNC_TOL = 0.02


class Resync:
    """
    What an outage leaves to judge the estimates that come back (the module says how).

    Parameters
    ----------
    lockstep : bool
        The simulator runs in lock-step (``simulator.mode``).

    Attributes
    ----------
    matches, publishers : int
        Estimate publishers matched so far in all, and matched now (the node sets them
        from its subscription's match events: ``total_count``, ``current_count``).
    agreeing : int
        With a standby: estimates in a row that agree with the standby's.

    """

    def __init__(self, lockstep=False):
        self.lockstep = bool(lockstep)
        self.matches = 0
        self.publishers = 0
        self.agreeing = 0
        self._matches_at_stale = None

    def matched(self, current, total):
        """Take a match event of the estimate topic: publishers matched now, and in all."""
        self.publishers, self.matches = int(current), int(total)

    def went_stale(self):
        """Note that the estimates went stale (the publishers matched until then)."""
        self._matches_at_stale = self.matches

    def plant_waits(self):
        """
        Return True in lock-step while an estimate publisher is matched.

        The simulator waits out a safe command then (marked: it answers no estimate),
        while the observer would take it for the input of the step it waits on.
        """
        return self.lockstep and self.publishers > 0

    def same_observer(self):
        """Return True in lock-step when no estimate publisher matched since they went stale."""
        return self.lockstep and self.matches == self._matches_at_stale

    def agrees(self, x, ref, scale):
        """
        Count an estimate x against the standby's ref (None: none); True once enough agree.

        ``RESYNC_AGREE`` in a row within ``RESYNC_TOL`` of each state's scale.
        """
        ok = ref is not None and within(x, ref, scale, RESYNC_TOL)
        self.agreeing = self.agreeing + 1 if ok else 0
        return self.agreeing >= RESYNC_AGREE
