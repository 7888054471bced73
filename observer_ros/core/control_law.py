# observer_ros.core.control_law: the compensator's law and command gate on plain floats.
"""
The control law u = K (x_d - x_hat) - Kd x_d, its limits and the command gate.

The compensator evaluates these once per estimate on a handful of numbers (n states, m
inputs), where numpy's per-call overhead is most of the cost: here they are plain Python
floats, the gains and the constant part ``K x_d - Kd x_d`` prepared once. Overflow gives
inf or NaN as numpy does (no exception), which the command gate then refuses.

"""

import math
from operator import le

import numpy as np

__all__ = ['command_problem', 'control_law', 'ControlLaw']


def command_problem(u, m, u_min=None, u_max=None):
    """
    Return why a command must not be sent, or None when it may.

    A command is sent only when it has ``m`` values, all finite and inside
    ``[u_min, u_max]`` (None: no limit on that side).

    Returns
    -------
    str or None

    """
    u = np.asarray(u, dtype=float)
    if u.shape != (m,):
        return f'{u.size} values for {m} inputs'
    if not np.isfinite(u).all():
        return f'not finite: {u.tolist()}'
    low = -np.inf if u_min is None else np.asarray(u_min, dtype=float)
    high = np.inf if u_max is None else np.asarray(u_max, dtype=float)
    if np.any(u < low) or np.any(u > high):
        return f'{u.tolist()} outside the limits [{u_min}, {u_max}]'
    return None


def control_law(K, x_hat, x_d, Kd, u_min=None, u_max=None):
    """
    Return u = K (x_d - x_hat) - Kd x_d, clipped to [u_min, u_max].

    Parameters
    ----------
    K, Kd : (m, n) ndarray
        Feedback gain and desired-state gain.
    x_hat, x_d : (n,) ndarray
        State estimate and desired state.
    u_min, u_max : (m,) ndarray, optional
        Input limits (None: no limit on that side).

    Returns
    -------
    u : (m,) ndarray

    """
    u = K @ (x_d - x_hat) - Kd @ x_d
    if u_min is not None or u_max is not None:
        u = np.clip(u, u_min, u_max)
    return u


class ControlLaw:
    """
    The tracking law u = K (x_d - x_hat) - Kd x_d on plain floats, with its limits.

    Equal to :func:`control_law` (numpy, the reference) to rounding; a few times faster on
    the compensator's few elements.

    Parameters
    ----------
    K, Kd : (m, n) array_like
        Feedback gain and desired-state gain.
    x_d : (n,) array_like
        Desired state.
    u_min, u_max : (m,) array_like, optional
        Input limits (None: no limit on that side; infinite entries allowed).

    """

    def __init__(self, K, x_d, Kd, u_min=None, u_max=None):
        K = np.asarray(K, dtype=float)
        x_d = np.asarray(x_d, dtype=float)
        m = K.shape[0]
        self.m = m
        self.u_min, self.u_max = u_min, u_max
        self._rows = [tuple(row) for row in (-K).tolist()]
        # the part that does not depend on x_hat
        self._offset = (K @ x_d - np.asarray(Kd, dtype=float) @ x_d).tolist()
        self._low = [-math.inf] * m if u_min is None else \
            np.asarray(u_min, dtype=float).tolist()
        self._high = [math.inf] * m if u_max is None else \
            np.asarray(u_max, dtype=float).tolist()
        self.limited = u_min is not None or u_max is not None

    def unclipped(self, x_hat):
        """
        Return the law's u before the limits, a list of m floats.

        Parameters
        ----------
        x_hat : sequence of float
            The estimate (n values: a list, or an ndarray's ``tolist()``).

        """
        return [c + sum(map(float.__mul__, row, x_hat))
                for c, row in zip(self._offset, self._rows)]

    def clip(self, u):
        """Return u clipped into the limits, a list (NaN stays NaN, as np.clip does)."""
        if not self.limited:
            return list(u)
        return [lo if v < lo else hi if v > hi else v
                for v, lo, hi in zip(u, self._low, self._high)]

    def __call__(self, x_hat):
        """Return the law's u clipped into the limits, a list of m floats."""
        return self.clip(self.unclipped(x_hat))

    def problem(self, u):
        """
        Return why the command u (m floats) must not be sent, or None when it may.

        The gate of :func:`command_problem` (which words the refusal), on floats.
        """
        if len(u) == self.m and all(map(math.isfinite, u)) and \
                all(map(le, self._low, u)) and all(map(le, u, self._high)):
            return None
        return command_problem(u, self.m, self.u_min, self.u_max)
