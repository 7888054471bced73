# observer_ros.core.estimators.kalman: the time-varying discrete Kalman filter.
"""
Time-varying discrete Kalman filter on the exactly sampled plant.

The process noise of a step is the exact (Van Loan) one of that step.

"""

import numpy as np
import scipy.linalg

from .base import Estimator
from .steps import CACHE_SIZE, discrete_noise, DT_DIGITS, GAIN_DIGITS, process_noise_covariance
from ..errors import DesignError
from ..model import as_matrix

__all__ = ['KalmanEstimator', 'kalman_correction']


class KalmanEstimator(Estimator):
    """
    Time-varying discrete Kalman filter on the exactly sampled plant.

    Propagation over dt: ``x- = Ad x + Bd u``, ``P- = Ad P Ad^T + Qk(dt)``. For a
    continuous plant Qd is the intensity of continuous white process noise w in
    ``x' = A x + B u + Bd w`` and ``Qk(dt)`` its exact discretisation (Van Loan,
    :func:`process_noise_covariance`) for dt rounded to ``gain_digits``
    significant digits (Ad is that of dt itself); for a discrete plant Qd is the covariance
    of w per sample (``Qk = sum_{i<k} A^i Bd Qd Bd^T A^iT`` over k samples).
    Rd is the covariance of the measurement noise of each sample.

    Correction with the rows r of a message: ``S = C_r P C_r^T + R_rr``,
    ``K = P C_r^T S^-1``, ``x+ = x- + K (y - D_r u - C_r x-)`` and the Joseph form
    ``P+ = (I - K C_r) P (I - K C_r)^T + K R_rr K^T``. Messages are processed one
    after the other (sequential update); with a diagonal Rd this equals a joint
    update of all rows of one time stamp (correlations of Rd between rows of
    different messages are ignored).

    P0 default: the steady-state filter covariance (from
    scipy.linalg.solve_discrete_are) of the step between the initial estimate
    and the first correction after it, for the rows of that correction
    (identity if the Riccati equation has no solution). Until that step is
    known (a measurement at the very time of the initial estimate) there is no
    correction.

    Parameters
    ----------
    plant : Plant
        The model.
    Qd : (k, k) array_like
        Process-noise intensity (continuous plant) or per-sample covariance.
    Rd : (p, p) array_like
        Measurement-noise covariance, for all plant outputs.
    Bd : (n, k) array_like, optional
        Process-noise input matrix; default the identity (k = n).
    P0 : (n, n) array_like, optional
        Covariance of x0.
    x0, t0, measured_rows, dt_digits, cache_size, gain_digits
        See :class:`Estimator`.

    """

    kind = 'kalman'
    _STATE = Estimator._STATE + ('_P', '_S', '_gain_used')
    _superposable = True            # P and K do not depend on u

    def __init__(self, plant, Qd, Rd, Bd=None, P0=None, x0=None, t0=None,
                 measured_rows=None, dt_digits=DT_DIGITS, cache_size=CACHE_SIZE,
                 gain_digits=GAIN_DIGITS):
        super().__init__(plant, x0, t0, measured_rows, dt_digits, cache_size, gain_digits)
        n, p = plant.n, plant.p
        G = np.eye(n) if Bd is None else as_matrix(Bd, 'Bd', rows=n)
        k = G.shape[1]
        Q = _as_covariance(Qd, 'Qd', k)
        R = _as_covariance(Rd, 'Rd', p)
        Rm = R[np.ix_(self._measured, self._measured)]
        if np.min(np.linalg.eigvalsh(Rm)) <= 0.0:
            raise DesignError('Rd is not positive definite on the measured outputs '
                              f'{[plant.output_names[r] for r in self._measured]}')
        self._G, self._Q, self._R = G, Q, R
        self._GQG = G @ Q @ G.T
        self._P0 = None if P0 is None else _as_covariance(P0, 'P0', n)
        self._P = None
        self._I = np.eye(n)
        self._rows_R = {}
        self._S = None
        self._gain_used = None          # K of the last correction (superposition)
        self.reset(t0=self._t0)

    @property
    def P(self):
        """Covariance of x_hat (copy), or None before it is known (see P0)."""
        return None if self._P is None else self._P.copy()

    @property
    def innovation_covariance(self):
        """Return ``S = C P- C^T + R`` of the last correction's rows (a copy), or None."""
        return None if self._S is None else self._S.copy()

    def last_residual(self):
        """Return the residual of the last correction and its S, not copied (see the base)."""
        return self._residual, self._S

    def _reset_state(self):
        self._P = None if self._P0 is None else self._P0.copy()
        self._S = None

    def _noise(self, step):
        """Qk of a step (interpolated between grid steps, see :data:`GAIN_DIGITS`)."""
        return self._gain_value(step.key, 'Q', self._noise_at)

    def _noise_at(self, step):
        if step.k is None:
            return process_noise_covariance(self._plant.A, self._Q, step.h, self._G)
        return discrete_noise(self._plant.A, self._GQG, step.k)

    def _propagate(self, step):
        self._propagate_model(step)
        if self._P is not None:
            self._P = self.prior_covariance(step, self._P)

    def prior_covariance(self, step, P):
        """Return ``Ad P Ad^T + Qk`` of a step entry (``cache.step(dt)``): the prior of P."""
        Ad = step.Ad
        P = Ad @ P @ Ad.T
        P += self._noise(step)
        return P

    def first_prior(self, step, rows):
        """
        Return the prior P of a first correction after a step entry, P not known yet.

        The steady-state covariance of that step for those rows (see P0), as the
        filter's first correction after its initial estimate takes it.

        """
        info = self._rows_info(rows, 'rows')
        return self._steady_prior(step, info, self._R_rows(info))

    def rows_model(self, rows):
        """Return the output rows' ``(C_r, D_r, R_rr)`` (rows: a tuple of measured rows)."""
        info = self._rows_info(rows, 'rows')
        return info.C, info.D, self._R_rows(info)

    def _R_rows(self, info):
        R = self._rows_R.get(info.rows)
        if R is None:
            R = self._R[np.ix_(info.idx, info.idx)]
            self._rows_R[info.rows] = R
        return R

    def _steady_prior(self, step, info, R):
        Qk = self._noise(step)
        try:
            P = scipy.linalg.solve_discrete_are(step.Ad.T, info.C.T, Qk, R)
        except (ValueError, np.linalg.LinAlgError):
            return self._I.copy()
        if not np.all(np.isfinite(P)):
            return self._I.copy()
        return 0.5 * (P + P.T)

    def _correct(self, y, info):
        ybar = y - info.D @ self._u
        innov = ybar - info.C @ self._x
        self._residual = innov
        R = self._R_rows(info)
        self._S = None
        self._gain_used = None
        if self._P is None:
            h = self._t - self._t_anchor
            if h <= 0.0:
                return
            self._P = self._steady_prior(self._cache.step(h), info, R)
        self._S, K, self._P = kalman_correction(self._P, info.C, R, self._I)
        self._gain_used = K
        self._x = self._x + K @ innov
        self._t_anchor = self._t

    def _shift_correction(self, state, new, dx, dyb, info, t, carry):
        """Move a saved state by a late input change: ``dx + K (dybar - C dx)``, K as used."""
        slots = self._slots
        dres = -(info.C @ dx) if dyb is None else dyb - info.C @ dx
        K = state[slots['_gain_used']]
        if K is not None:
            dx = dx + K @ dres
        return (dx,) + self._shifted(state, new, dx, dres) + (state[slots['_S']],)


def kalman_correction(P, C, R, eye):
    """
    Return ``(S, K, P+)`` of a correction of the prior covariance P by rows (C, R).

    ``S = C P C^T + R``, ``K = P C^T S^-1`` and the Joseph form
    ``P+ = (I - K C) P (I - K C)^T + K R K^T``, symmetrised (``eye``: the identity of
    P's size). The filter's own arithmetic, shared by the bulk replay.

    """
    PCt = P @ C.T
    S = C @ PCt + R
    K = np.linalg.solve(S, PCt.T).T
    IKC = eye - K @ C
    P = IKC @ P @ IKC.T + K @ R @ K.T
    return S, K, 0.5 * (P + P.T)


def _as_covariance(X, name, size):
    M = as_matrix(X, name, rows=size, cols=size)
    scale = max(1.0, float(np.max(np.abs(M))))
    if np.max(np.abs(M - M.T)) > 1e-9 * scale:
        raise DesignError(f'{name} is not symmetric')
    M = 0.5 * (M + M.T)
    if size and np.min(np.linalg.eigvalsh(M)) < -1e-9 * scale:
        raise DesignError(f'{name} is not positive semidefinite')
    return M
