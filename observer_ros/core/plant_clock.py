# observer_ros.core.plant_clock: where a realtime plant is now, when its messages queue up.
"""
The plant's time now, for a compensator whose process did not run for a while.

A realtime plant steps on the wall clock. The newest measurement's stamp is its time only
if that measurement was taken as it came: when the compensator's process did not run for
a while (a busy host) and then takes the measurements that queued meanwhile one after
the other, the first of them is tens of milliseconds behind the plant. A command answering
it, stamped its stamp plus the lead, reaches the plant after its step; the plant applies it
from when it arrives, while the observers take it from its stamp, and the loop runs on
inputs the plant did not get (the cart's loop tolerates 0.58 ms of unmodelled delay).

:class:`PlantClock` keeps the offset between the wall clock (times the plant's rate) and
the stamps of the measurements taken; the smallest offset over the last ``window`` s of
wall time is that of a measurement taken as it came, so the plant's time now is the wall
clock less it. A plant that falls behind the wall clock (a timer that skips ticks, a
simulator paused) makes it too late by as much for at most ``window``: the commands are then
stamped further ahead than needed, which the plant and the observers agree on (the plant
holds the command in force until the new one's stamp, as the model predicts).

"""

import collections

__all__ = ['PlantClock']


class PlantClock:
    """
    The plant's time now, from the stamps of the measurements and when they were taken.

    Parameters
    ----------
    rate : float
        Seconds of plant time per second of wall time (``simulator.realtime_factor``).
    window : float
        Wall seconds over which the smallest offset is kept.

    """

    def __init__(self, rate=1.0, window=0.5):
        if not rate > 0.0:
            raise ValueError(f'PlantClock: rate must be > 0, not {rate!r}')
        if not window > 0.0:
            raise ValueError(f'PlantClock: window must be > 0, not {window!r}')
        self.rate, self.window = float(rate), float(window)
        self._offsets = collections.deque()     # (wall, offset), offsets increasing

    def reset(self):
        """Forget the measurements seen (a clock that started over)."""
        self._offsets.clear()

    def seen(self, t, now):
        """Note a measurement stamped t (plant time, s) taken at wall time now (s)."""
        offset = now * self.rate - t
        q = self._offsets
        while q and q[-1][1] >= offset:
            q.pop()
        q.append((now, offset))
        while q[0][0] < now - self.window:
            q.popleft()

    def at(self, now):
        """Return the plant's time at wall time now (s), or None before a measurement."""
        q = self._offsets
        while len(q) > 1 and q[0][0] < now - self.window:
            q.popleft()
        if not q:
            return None
        return now * self.rate - q[0][1]

    def behind(self, t, now):
        """
        Return how far the plant is past stamp t at wall time now (s, at least 0).

        0 before any measurement.
        """
        plant = self.at(now)
        return 0.0 if plant is None else max(plant - t, 0.0)

    def plant_now(self, plant, now, dt, most):
        """
        Return the plant's time at wall time now, ``plant`` the newest sensor stamp.

        That stamp; later by the wall clock when the measurements queued for this process
        (it did not run for a while) by more than a step ``dt``, so that a command
        answering one still reaches the plant before its stamp; at most ``most`` s later.
        None without a stamp; ``plant`` without ``now``.
        """
        if plant is None or now is None:
            return plant
        behind = self.behind(plant, now) - dt
        return plant if behind <= 0.0 else plant + min(behind, most)
