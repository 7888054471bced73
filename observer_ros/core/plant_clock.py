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

A plant's rate is not the wall clock's either: a realtime simulator on a busy host skips
timer ticks and steps slower than ``simulator.realtime_factor`` says (at about 40 % of it
beside two CPU hogs on two cores). Taking the nominal rate would then put the plant's time
ahead of the plant by as much as the window's wall time times the shortfall (0.3 s at 40 %),
and every command would be stamped that much ahead: a horizon of open-loop prediction
the unstable cart's loop does not keep.

:class:`PlantClock` keeps the offset between the wall clock (times the plant's rate) and
the stamps of the measurements taken; the smallest offset over the last ``window`` s of
wall time is that of a measurement taken as it came, so the plant's time now is the wall
clock less it. The rate is measured: each ``window`` of wall time gives its measurement
taken most as it came, and the plant's time between the last three of them over the wall
time between is its rate (the larger of the two, so one window whose measurements all
queued does not slow it; at most the nominal rate, at least ``MIN_RATE`` of it, and the
nominal rate until three windows are seen). A plant that falls behind the wall clock (a
simulator paused) makes the plant's time too late by as much times the rate for at most
``window``: the commands are then stamped further ahead than needed, which the plant and
the observers agree on (the plant holds the command in force until the new one's stamp,
as the model predicts).

A host short of CPU delays the commands on their way to the plant as it delays the
measurements on their way here: a command that reaches the plant after its stamp is
applied from when it arrives, not from its stamp as the observers take it. How long a
measurement waited (how far the plant was past its stamp when it was taken) is kept over
``WAIT_WINDOW`` s, and :meth:`PlantClock.extra_steps` lengthens the commands' lead by as
much (at most ``LEAD_MOST``).

"""

import collections
import math

__all__ = ['PlantClock']

# The rate measured is at least this fraction of the nominal rate (a plant that stands).
MIN_RATE = 0.01
# Wall seconds over which the longest wait of a measurement is kept (:meth:`waited`).
WAIT_WINDOW = 2.0
# s: the most added to a command's lead while measurements wait (:meth:`extra_steps`).
LEAD_MOST = 0.1


class PlantClock:
    """
    The plant's time now, from the stamps of the measurements and when they were taken.

    Parameters
    ----------
    rate : float
        Seconds of plant time per second of wall time at most (``simulator.realtime_factor``).
    window : float
        Wall seconds over which the smallest offset is kept, and over which the rate is
        measured.

    Attributes
    ----------
    rate : float
        The plant's rate measured (``nominal`` before three windows are seen).
    nominal : float
        The ``rate`` given.

    """

    def __init__(self, rate=1.0, window=0.5):
        if not rate > 0.0:
            raise ValueError(f'PlantClock: rate must be > 0, not {rate!r}')
        if not window > 0.0:
            raise ValueError(f'PlantClock: window must be > 0, not {window!r}')
        self.nominal, self.window = float(rate), float(window)
        self.rate = self.nominal
        self._offsets = collections.deque()     # (wall, offset), offsets increasing
        self._seen = collections.deque()        # (wall, t) of the last window
        self._anchors = collections.deque(maxlen=3)     # (wall, t): each window's best
        self._block = None                      # [start, wall, t] of the window filling
        self._waits = collections.deque()       # (wall, wait), waits decreasing

    def reset(self):
        """Forget the measurements seen and the rate measured (a clock that started over)."""
        self._offsets.clear()
        self._seen.clear()
        self._anchors.clear()
        self._block = None
        self._waits.clear()
        self.rate = self.nominal

    def seen(self, t, now):
        """Note a measurement stamped t (plant time, s) taken at wall time now (s)."""
        block = self._block
        if block is None:
            self._block = [now, now, t]
        elif now - block[0] >= self.window:
            self._anchors.append((block[1], block[2]))
            self._block = [now, now, t]
            self._measure_rate()
        elif t - self.rate * now > block[2] - self.rate * block[1]:
            block[1], block[2] = now, t
        seen = self._seen
        seen.append((now, t))
        while seen[0][0] < now - self.window:
            seen.popleft()
        self._push(now, now * self.rate - t)
        wait, q = self.behind(t, now), self._waits
        while q and q[-1][1] <= wait:
            q.pop()
        q.append((now, wait))

    def waited(self, now):
        """
        Return the longest wait of a measurement over the last ``WAIT_WINDOW`` s (plant s).

        How far the plant was past a measurement's stamp when it was taken: the time it
        waited for this process (and the transport) on a busy host. 0 before any.
        """
        q = self._waits
        while q and q[0][0] < now - WAIT_WINDOW:
            q.popleft()
        return q[0][1] if q else 0.0

    def extra_steps(self, now, dt):
        """
        Return the steps of dt to add to the commands' lead: :meth:`waited`, rounded up.

        At most ``LEAD_MOST``.
        """
        return math.ceil(min(self.waited(now), LEAD_MOST) / dt - 1e-9)

    def _push(self, now, offset):
        q = self._offsets
        while q and q[-1][1] >= offset:
            q.pop()
        q.append((now, offset))
        while q[0][0] < now - self.window:
            q.popleft()

    def _measure_rate(self):
        """Measure the rate from the last three windows' best measurements (the module)."""
        a = self._anchors
        if len(a) < 3:
            return
        rates = [(t1 - t0) / (w1 - w0) for (w0, t0), (w1, t1) in ((a[0], a[1]), (a[1], a[2]))
                 if w1 > w0]
        if not rates:
            return
        rate = min(max(max(rates), MIN_RATE * self.nominal), self.nominal)
        if rate != self.rate:
            self.rate = rate
            self._offsets.clear()
            for w, t in self._seen:
                self._push(w, w * rate - t)

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
