# observer_ros.core.safe_command: the command sent when the estimate cannot be used.
"""
The safe-command policy: predict-and-hold for a bounded time, then the fallback.

On an unstable plant a zero command is not safe: the cart's pendulum falls within a
second. While the estimate is stale (or not trusted) the compensator keeps the loop closed
on the model's prediction from the last trusted estimate (one that passed every gate),
for ``predict_timeout`` seconds; then it sends the fallback (``zero``, or ``hold`` the
last command sent). A plant that cannot be held open loop for seconds has a standby
observer in its compensator instead (:mod:`.standby`).

"""

import numpy as np

from .errors import ObserverError
from .model import zoh_matrices

__all__ = ['SAFE_FALLBACKS', 'SafeCommand']

SAFE_FALLBACKS = ('zero', 'hold')


class SafeCommand:
    """
    Decide the safe command: predict-and-hold, then the fallback.

    Parameters
    ----------
    plant : Plant
        The model (continuous: discretised with a zero-order hold on ``dt``).
    law : callable
        ``law(x_hat) -> u``: the control law (with its limits) the prediction is closed by;
        a u that is not finite ends the prediction (the compensator's law returns NaN
        where the prediction leaves the vehicle's envelope): the fallback from then on.
    dt : float
        Prediction step, s (the sample time; a discrete plant's own).
    fallback : str
        ``zero`` or ``hold`` (the last command sent).
    predict_timeout : float
        Seconds after the last trusted estimate during which the prediction is used;
        0 sends the fallback at once.

    """

    def __init__(self, plant, law, dt, fallback='zero', predict_timeout=0.0):
        if fallback not in SAFE_FALLBACKS:
            raise ObserverError(f'safe command {fallback!r}: expected one of '
                                f'{list(SAFE_FALLBACKS)}')
        if not (np.isfinite(predict_timeout) and predict_timeout >= 0.0):
            raise ObserverError(f'predict_timeout {predict_timeout}: must be finite and >= 0')
        if not (np.isfinite(dt) and dt > 0.0):
            raise ObserverError(f'dt {dt}: must be finite and > 0')
        if plant.is_discrete:
            self.Ad, self.Bd = plant.A, plant.B
        else:
            self.Ad, self.Bd = zoh_matrices(plant.A, plant.B, dt)
        self.law = law
        self.dt = float(dt)
        self.fallback = fallback
        self.predict_timeout = float(predict_timeout)
        self._m = plant.m
        self._last_u = np.zeros(plant.m)
        self._trusted_t = None      # time of the last trusted estimate
        self._t = None              # time of the prediction
        self._x = None              # the prediction at _t
        self._u = None              # the command held from _t on

    @property
    def last_command(self):
        """Return the last command sent (a copy; zeros before the first)."""
        return np.array(self._last_u, dtype=float)

    def reset(self):
        """Forget the estimate and the commands (a clock that starts over)."""
        self._last_u = np.zeros(self._m)
        self._trusted_t = self._t = self._x = self._u = None

    def sent(self, u):
        """
        Remember the last command sent: the one ``hold`` repeats.

        ``u`` (m floats: a list or an ndarray) is kept as it is, not copied (once per
        command): the caller does not change it afterwards.
        """
        self._last_u = u

    def trusted(self, t, x_hat, u):
        """
        Note a trusted estimate at t and the command u sent in answer (held from t).

        Kept as they are, not copied, like :meth:`sent`'s ``u``.
        """
        self._trusted_t = self._t = float(t)
        self._x = x_hat
        self._u = self._last_u = u

    def predict_from(self, x, steps):
        """
        Return x predicted ``steps`` sample times ahead, the last command sent held.

        The model's prediction that tells whether an estimate continues the one before
        it (the compensator's check of one estimate stream).
        """
        x = np.asarray(x, dtype=float)
        held = np.asarray(self._last_u, dtype=float)
        for _ in range(int(steps)):
            x = self.Ad @ x + self.Bd @ held
        return x

    def command(self, t):
        """
        Return the safe command at time t and how it was decided.

        Parameters
        ----------
        t : float
            Time on the estimates' time base, s.

        Returns
        -------
        u : ndarray
            The command (m); also noted as sent.
        mode : str
            ``predict`` (the control law on the model's prediction, within
            ``predict_timeout`` of the last trusted estimate), ``zero`` or ``hold``.

        """
        if self._x is not None and t - self._trusted_t <= self.predict_timeout:
            # the plant held self._u since self._t: propagate on whole steps
            steps = int(np.floor((t - self._t) / self.dt + 1e-9))
            self._x = np.asarray(self._x, dtype=float)
            held = np.asarray(self._u, dtype=float)
            for _ in range(max(steps, 0)):
                self._x = self.Ad @ self._x + self.Bd @ held
            self._t += max(steps, 0) * self.dt
            u = np.asarray(self.law(self._x), dtype=float)
            if np.isfinite(u).all():
                self._u = u
                self.sent(u)
                return u.copy(), 'predict'
            self._x = None      # a prediction gone non-finite is not used again
        u = self.last_command if self.fallback == 'hold' else np.zeros(self._m)
        self.sent(u)
        return u.copy(), self.fallback
