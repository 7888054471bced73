# observer_ros.core.delay_compensation: predict a late estimate to when its command applies.
"""
Delay compensation: the command is computed for the time it takes effect.

The cart-pendulum's compensator (observer plus K; D(s) has a pole at +95.75) keeps the
loop stable only with less than about 0.6 ms of delay at the plant input (its Nyquist
plot passes within 0.65 degrees of -1 at 19.7 rad/s). In a realtime ROS loop an estimate
is sometimes tens of milliseconds late (a busy core): answered as if it were on time, its
command applies steps after its stamp, the plant holds the old command meanwhile, and the
observer, which takes the stamp at its word, estimates with an input the plant did not
get. A few such steps and the loop diverges.

:class:`DelayCompensation` takes how late each estimate is from the plant's time when it
arrives (the simulator's ``/clock``; a robot's clock) and predicts it with the model over
the steps it missed, through the commands already sent for them (the plant holds each
from its stamp). The command answering it is stamped with the time it takes effect, never
before one already sent, so the simulator (or a driver honouring stamps) applies it there
and the observer takes it from there: model, plant and observer agree again. Only an
estimate later than ``max_delay`` is not predicted (the compensator's stale path takes
over). Lateness is not guessed from arrival times: a simulator that falls behind the wall
clock (a missed tick) would make every later estimate look late.

"""

import collections

import numpy as np

__all__ = ['DelayCompensation', 'loop_delay_margin']


class DelayCompensation:
    """
    How late an estimate is, and the estimate predicted to when its command applies.

    Parameters
    ----------
    Ad, Bd : ndarray
        The model over one step (n x n, n x m).
    dt : float
        The step, s: commands take effect on its grid.
    max_delay : float
        Seconds: a later estimate is not predicted (None from :meth:`steps_late`).
    lead : int
        Steps added to the lateness: the command's own way to the plant (computing it,
        the transport, the plant's next step). With 0 a command computed just before the
        plant steps comes late; with 1 it has a whole step.

    """

    def __init__(self, Ad, Bd, dt, max_delay=0.25, lead=1):
        self.Ad, self.Bd = np.asarray(Ad, float), np.asarray(Bd, float)
        self.dt, self.max_delay, self.lead = float(dt), float(max_delay), int(lead)
        self._sent = collections.deque()        # (stamp, u), stamps increasing
        self._max_late_steps = int(np.floor(self.max_delay / self.dt + 0.5))
        # commands kept: enough for the longest prediction, two commands a step
        self._keep = 2 * int(np.ceil(max_delay / self.dt)) + 64

    def reset(self):
        """Forget the commands sent (a clock that started over)."""
        self._sent.clear()

    def steps_late(self, now, t):
        """
        Return the steps to predict the estimate stamped t: to the plant's time plus ``lead``.

        Parameters
        ----------
        now : float or None
            The plant's time when the estimate arrived, on the stamps' time base (None:
            not known: from t).
        t : float
            The estimate's stamp, s (after the plant's time when the observer predicted it
            through a command already stamped ahead: then fewer steps, never below 0).

        Returns
        -------
        int or None
            Steps to ``now + lead`` steps, to the nearest step, and at least enough that
            the command is not stamped before the newest one sent (the plant would not
            apply it). ``now`` on another time base (more than 100 ``max_delay`` away)
            counts as unknown. None when the estimate is later than ``max_delay``, or
            when a command already sent would put its answer more than ``max_delay``
            plus the lead and a step after it (a horizon the commands kept, and the
            unstable model's prediction, are not meant for; the plant holds the
            commands already sent, computed for those times).

        """
        late = 0.0 if now is None else now - t
        if abs(late) > 100.0 * self.max_delay:
            late = 0.0                          # another time base: nothing to compare
        if late > self.max_delay + 1e-9:       # (a lateness capped at it is not past it)
            return None
        steps = int(np.floor(late / self.dt + 0.5)) + self.lead
        if self._sent:
            newest = self._sent[-1][0]
            steps = max(steps, int(np.ceil((newest - t) / self.dt - 0.25)))
            if steps > self._max_late_steps + self.lead + 1:
                return None
        return max(steps, 0)

    def sent(self, t, u):
        """Note the command u sent, in force from its stamp t on."""
        q = self._sent
        while q and q[-1][0] >= t - 0.25 * self.dt:    # a newer stamp replaces it
            q.pop()
        q.append((float(t), np.array(u, dtype=float)))
        while len(q) > self._keep:
            q.popleft()

    def in_force(self, t):
        """Return the command the plant holds at t (the newest stamped at or before it)."""
        for stamp, u in reversed(self._sent):
            if stamp <= t + 0.25 * self.dt:
                return u
        return np.zeros(self.Bd.shape[1])

    def predict(self, x, t, steps):
        """
        Return x predicted from t over ``steps`` steps, with the commands in force then.

        Parameters
        ----------
        x : (n,) ndarray
            The estimate at t.
        t : float
            Its stamp, s.
        steps : int
            Steps to predict (0: x itself).

        Returns
        -------
        (n,) ndarray

        """
        x = np.asarray(x, dtype=float)
        for k in range(steps):
            x = self.Ad @ x + self.Bd @ self.in_force(t + k * self.dt)
        return x


def loop_delay_margin(plant, compensator, w_min=1e-3, w_max=1e5, points=200001):
    """
    Return the delay at the plant input that makes the loop lose stability, and where.

    The loop is broken at the plant input, L(s) = D(s) P(s) with ``u = -D(s) y``
    (continuous time). At each gain crossover (|L(jw)| = 1) a delay tau lags L(jw) by
    w tau; the smallest delay that brings one of them onto -1 is the margin (a closed-loop
    pole then reaches the imaginary axis). Unlike a single phase margin this holds for a
    conditionally stable loop with several crossovers.

    Parameters
    ----------
    plant, compensator : control.StateSpace
        P(s) (y from u) and D(s) (u = -D y), single input and output, continuous.
    w_min, w_max : float
        The frequency range searched, rad/s.
    points : int
        How many log-spaced frequencies are evaluated.

    Returns
    -------
    tau : float
        Seconds (inf when |L| never crosses 1).
    w : float
        The crossover frequency where it applies, rad/s (nan with tau inf).

    """
    w = np.logspace(np.log10(w_min), np.log10(w_max), points)
    loop = (compensator * plant)(1j * w)
    response = np.asarray(loop).reshape(-1)
    mag = np.abs(response) - 1.0
    best, where = np.inf, np.nan
    for i in np.nonzero(np.sign(mag[:-1]) != np.sign(mag[1:]))[0]:
        # the crossover between w[i] and w[i+1], interpolated in log |L|
        f = mag[i] / (mag[i] - mag[i + 1])
        wc = w[i] * (w[i + 1] / w[i]) ** f
        lag = (np.angle(complex((compensator * plant)(1j * wc))) + np.pi) % (2 * np.pi)
        if lag / wc < best:
            best, where = lag / wc, wc
    return float(best), float(where)
