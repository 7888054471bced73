# observer_ros.core.design: observer and controller gains (python-control does the work).
"""Gain design: observer poles, Kalman gains, controller gains, reduced-order observer."""

from dataclasses import dataclass
from typing import Tuple

import numpy as np
import scipy.linalg

from ._lazy import control
from .analysis import controllable_decomposition, observability_report
from .errors import DesignError, DimensionError, NotControllableError, NotDetectableError
from .model import as_matrix, as_poles
from .pole_placement import (ACKER_DIGITS_LOST, place_gain, PLACEMENT_WARN_TOL,
                             pole_placement_error)

__all__ = ['observer_gain', 'controller_gain', 'lqr_gain', 'kalman_gain',
           'kalman_update_gain', 'pole_placement_error', 'reduced_coordinates',
           'ReducedOrderDesign', 'reduced_order_observer', 'PLACEMENT_WARN_TOL',
           'ACKER_DIGITS_LOST']

_METHODS = ('auto', 'place', 'acker')


# ---------------------------------------------------------------- pole placement


def _design(A, B, poles, method, discrete, state_names, role):
    """
    Pole placement for (A, B) in controller form, keeping stable uncontrollable modes.

    For the observer, A and B are A^T and C^T of the plant; the naming report is
    the observability report of (A^T, B^T) in both cases.

    """
    if method not in _METHODS:
        raise DesignError(f'method is {method!r}; expected one of {list(_METHODS)}')
    n = A.shape[0]
    p = as_poles(poles, 'poles', require_stable=False)
    Abar, Bbar, _, T, r = controllable_decomposition(A, B)
    if r == n:
        if p.size != n:
            raise DimensionError(
                f'poles has {p.size} poles; expected {n} (one per state)')
        return place_gain(A, B, p, method, role)
    report = observability_report(A.T, B.T, state_names, discrete)
    pair = '(A, C)' if role == 'observer' else '(A, B)'
    lost = 'unobservable' if role == 'observer' else 'uncontrollable'
    bad = [md for md in report.modes if not md.stable]
    if bad:
        modes = '; '.join(md.describe() for md in bad)
        if role == 'observer':
            raise NotDetectableError(
                f'{pair} is not detectable: the {lost} {modes} cannot be estimated and '
                'does not decay; measure one of those states')
        raise NotControllableError(
            f'{pair} is not stabilizable: the {lost} {modes} cannot be moved by the '
            'input and does not decay')
    kept = '; '.join(md.describe() for md in report.modes)
    if p.size != r:
        msg = (f'poles has {p.size} poles; expected {r}: {pair} is {lost} with rank {r} '
               f'of {n} and its {lost} modes are kept as they are ({kept}); give poles '
               f'only for the {r} {"observable" if role == "observer" else "controllable"} '
               'modes')
        raise DimensionError(msg)
    Kc = place_gain(Abar[:r, :r], Bbar[:r], p, method, role)
    Kbar = np.zeros((B.shape[1], n))
    Kbar[:, :r] = Kc
    return Kbar @ T.T


def observer_gain(A, C, poles, method='auto', discrete=False, state_names=None):
    """
    Observer gain L placing eig(A - L C) at the given poles.

    Parameters
    ----------
    A : (n, n) array_like
        State matrix.
    C : (p, n) array_like
        Output matrix.
    poles : array_like of complex
        n poles, in conjugate pairs (z-plane poles for a discrete plant). For a
        detectable but unobservable plant give one pole per observable mode (the
        rank of ``obsv(A, C)``): the unobservable eigenvalues are kept.
    method : {'auto', 'place', 'acker'}
        ``place`` is python-control's place on the dual (A^T, C^T);
        ``acker`` is Ackermann's formula (one output only);
        ``auto`` takes the best of the candidates of
        :mod:`observer_ros.core.pole_placement` (place, place run to convergence,
        acker; for a pole repeated more often than there are outputs, a rank-one
        gain ``L = l w^T`` or a cyclic design).
    discrete : bool
        Stability of unobservable modes is judged in the z-plane.
    state_names : sequence of str, optional
        Used to name the states of unobservable modes in errors.

    Returns
    -------
    L : (n, p) ndarray
        ``eig(A - L C)`` = poles (plus the kept unobservable eigenvalues).

    Raises
    ------
    DimensionError
        Wrong shapes, or wrong number of poles (the message gives n, or the rank).
    NotDetectableError
        An unobservable eigenvalue is not stable; the message names it and its states.
    DesignError
        A method that does not apply (``place`` with a pole repeated more often than
        there are independent outputs, ``acker`` with several outputs).

    Warns
    -----
    ObserverDesignWarning
        The placed poles are off by more than ``PLACEMENT_WARN_TOL``, or
        ``method='acker'`` loses digits relative to place.

    """
    A = as_matrix(A, 'A', square=True)
    n = A.shape[0]
    C = as_matrix(C, 'C', cols=n)
    return _design(A.T, C.T, poles, method, discrete, state_names, 'observer').T


def controller_gain(A, B, poles, method='auto', discrete=False, state_names=None):
    """
    State-feedback gain K placing eig(A - B K) at the given poles (dual of observer_gain).

    Parameters
    ----------
    A : (n, n) array_like
        State matrix.
    B : (n, m) array_like
        Input matrix.
    poles : array_like of complex
        n poles in conjugate pairs; for a stabilizable but uncontrollable plant
        one per controllable mode (the uncontrollable eigenvalues are kept).
    method : {'auto', 'place', 'acker'}
        Pole placement method (see observer_gain).
    discrete : bool
        Discrete time: z-plane instead of s-plane.
    state_names : sequence of str, optional
        State names for messages (default x1..xn).

    Returns
    -------
    K : (m, n) ndarray

    Raises
    ------
    NotControllableError
        (A, B) is not stabilizable.
    DimensionError
        Wrong shapes or number of poles (the message gives n, or the controllable
        rank: the same rule as observer_gain's).

    """
    A = as_matrix(A, 'A', square=True)
    B = as_matrix(B, 'B', rows=A.shape[0])
    return _design(A, B, poles, method, discrete, state_names, 'controller')


# ---------------------------------------------------------------- optimal gains


def _check_cov(M, name, definite):
    """Return M symmetrised when it is symmetric to round-off; refuse it otherwise."""
    if not np.allclose(M, M.T, rtol=1e-10, atol=1e-12 * max(1.0, float(np.max(np.abs(M))))):
        raise DesignError(f'{name} is not symmetric')
    w = np.linalg.eigvalsh((M + M.T) / 2.0)
    tol = 1e-12 * max(1.0, float(np.max(np.abs(w)))) if w.size else 0.0
    if definite and (w.size and w[0] <= tol):
        raise DesignError(f'{name} must be positive definite; its smallest eigenvalue is '
                          f'{w[0]:.3g}')
    if not definite and (w.size and w[0] < -tol):
        raise DesignError(f'{name} must be positive semi-definite; its smallest eigenvalue '
                          f'is {w[0]:.3g}')
    return (M + M.T) / 2.0


def lqr_gain(A, B, Q, R, discrete=False):
    """
    Linear-quadratic regulator gain (python-control ``lqr`` / ``dlqr``).

    Parameters
    ----------
    A : (n, n) array_like
        State matrix.
    B : (n, m) array_like
        Input matrix.
    Q : (n, n) array_like
        State weight, symmetric positive semi-definite.
    R : (m, m) array_like
        Input weight, symmetric positive definite.
    discrete : bool
        Discrete-time plant (``dlqr``).

    Returns
    -------
    K : (m, n) ndarray
        Optimal gain, u = -K x.
    S : (n, n) ndarray
        Solution of the Riccati equation.
    E : ndarray of complex
        Closed-loop eigenvalues eig(A - B K).

    """
    A = as_matrix(A, 'A', square=True)
    n = A.shape[0]
    B = as_matrix(B, 'B', rows=n)
    Q = as_matrix(Q, 'Q', rows=n, cols=n)
    R = as_matrix(R, 'R', rows=B.shape[1], cols=B.shape[1])
    Q = _check_cov(Q, 'Q', definite=False)
    R = _check_cov(R, 'R', definite=True)
    try:
        K, S, E = (control.dlqr if discrete else control.lqr)(A, B, Q, R)
    except (ValueError, np.linalg.LinAlgError) as err:
        report = observability_report(A.T, B.T, None, discrete)
        if not report.detectable:
            raise NotControllableError(
                '(A, B) is not stabilizable: ' + '; '.join(report.unobservable_modes)) from None
        raise DesignError(f'LQR design failed: {err}') from None
    return np.asarray(K, dtype=float), np.asarray(S, dtype=float), np.asarray(E)


def kalman_gain(A, C, Qd, Rd, Bd=None, discrete=False, state_names=None):
    """
    Steady-state Kalman(-Bucy) gain (python-control ``lqe`` / ``dlqe``).

    Parameters
    ----------
    A : (n, n) array_like
        State matrix.
    C : (p, n) array_like
        Output matrix.
    Qd : (k, k) array_like
        Process noise covariance (intensity for a continuous plant), symmetric
        positive semi-definite.
    Rd : (p, p) array_like
        Measurement noise covariance, symmetric positive definite.
    Bd : (n, k) array_like, optional
        Process noise input matrix; default the identity (k = n).
    discrete : bool
        Discrete-time plant.
    state_names : sequence of str, optional
        Names for the error message of an undetectable plant.

    Returns
    -------
    L : (n, p) ndarray
        Continuous: ``L = P C^T Rd^-1`` with P solving
        ``A P + P A^T + Bd Qd Bd^T - P C^T Rd^-1 C P = 0`` (seed 004).
        Discrete: python-control's ``dlqe`` convention, the *predictor* gain
        ``L = A P C^T (C P C^T + Rd)^-1`` of
        ``x[k+1|k] = A x[k|k-1] + B u + L (y - C x[k|k-1] - D u)``, P being the
        a-priori (predicted) covariance; the filter (measurement-update) gain is
        :func:`kalman_update_gain`, with ``L = A M``.
    P : (n, n) ndarray
        Steady-state error covariance (a priori in discrete time).
    E : ndarray of complex
        Estimator poles eig(A - L C).

    """
    A = as_matrix(A, 'A', square=True)
    n = A.shape[0]
    C = as_matrix(C, 'C', cols=n)
    p = C.shape[0]
    Bd = np.eye(n) if Bd is None else as_matrix(Bd, 'Bd', rows=n)
    k = Bd.shape[1]
    Qd = as_matrix(Qd, 'Qd', rows=k, cols=k)
    Rd = as_matrix(Rd, 'Rd', rows=p, cols=p)
    Qd = _check_cov(Qd, 'Qd', definite=False)
    Rd = _check_cov(Rd, 'Rd', definite=True)
    # python-control demands Bd Qd Bd^T symmetric to the last bit: form it here,
    # symmetrised, and give the Riccati solver the noise input I (same L, P, E)
    Qn = Bd @ Qd @ Bd.T
    Qn = (Qn + Qn.T) / 2.0
    report = observability_report(A, C, state_names, discrete)
    if not report.detectable:
        raise NotDetectableError(
            '(A, C) is not detectable, no Kalman filter converges: '
            + '; '.join(md.describe() for md in report.modes if not md.stable))
    try:
        L, P, E = (control.dlqe if discrete else control.lqe)(A, np.eye(n), C, Qn, Rd)
    except (ValueError, np.linalg.LinAlgError) as err:
        raise DesignError(f'Kalman design failed (no stabilizing Riccati solution; is every '
                          f'marginal mode excited by Bd Qd?): {err}') from None
    return np.asarray(L, dtype=float), np.asarray(P, dtype=float), np.asarray(E)


def kalman_update_gain(P, C, Rd):
    """
    Discrete Kalman measurement-update (filter) gain ``M = P C^T (C P C^T + Rd)^-1``.

    Parameters
    ----------
    P : (n, n) array_like
        A-priori covariance (the P of :func:`kalman_gain` with ``discrete=True``).
    C : (p, n) array_like
        Output matrix.
    Rd : (p, p) array_like
        Measurement noise covariance.

    Returns
    -------
    M : (n, p) ndarray
        ``x[k|k] = x[k|k-1] + M (y - C x[k|k-1] - D u)``; the predictor gain is ``A M``.

    """
    P = as_matrix(P, 'P', square=True)
    C = as_matrix(C, 'C', cols=P.shape[0])
    Rd = as_matrix(Rd, 'Rd', rows=C.shape[0], cols=C.shape[0])
    S = C @ P @ C.T + Rd
    return scipy.linalg.solve(S.T, C @ P.T, assume_a='sym').T


# ---------------------------------------------------------------- reduced order


def reduced_coordinates(C):
    """
    Change of coordinates x_bar = T x with x_bar[:p] = C x and x_bar[p:] = x[rest].

    The p measured coordinates are y itself; the others are the states that C
    depends on least (pivoted QR picks the p columns that make C's square part
    best conditioned), kept in their original order. For C = [0 1 0 0] the
    estimated coordinates are states 0, 2, 3, as in the seed's Example 5.19.

    Parameters
    ----------
    C : (p, n) array_like of full row rank
        Output matrix.

    Returns
    -------
    T, Tinv : (n, n) ndarray
        ``T = [C; E]`` with E rows of the identity, so ``C Tinv = [I 0]``.
    rest : list of int
        The state indices estimated by the reduced-order observer.

    """
    C = as_matrix(C, 'C')
    p, n = C.shape
    if p >= n:
        raise DesignError(f'C has {p} rows for {n} states: nothing left to estimate')
    if np.linalg.matrix_rank(C) < p:
        raise DesignError(f'C must have full row rank ({p}); a reduced-order observer needs '
                          'independent measurements')
    _, _, piv = scipy.linalg.qr(C, pivoting=True)
    rest = sorted(int(i) for i in piv[p:])
    T = np.vstack([C, np.eye(n)[rest]])
    return T, np.linalg.inv(T), rest


@dataclass(frozen=True)
class ReducedOrderDesign:
    """
    A reduced-order observer (seed 000 section 3.5, seed 002 Eq. 5.129-5.132).

    In the coordinates ``x_bar = T x`` (``x_bar[:p] = C x``, ``x_bar[p:] = x[rest]``)
    with ``y_t = y - D u``::

        x_hat2 = L y_t + z
        z' = F z + G y_t + H u        (z[k+1] = ... for a discrete plant)
        x_hat = Tinv [y_t; x_hat2]

    and the error ``e2 = x_bar[p:] - x_hat2`` obeys ``e2' = F e2`` because
    ``F = A22 - L A12``, ``H = B2 - L B1`` and ``G = F L + A21 - L A11``.

    """

    F: np.ndarray
    G: np.ndarray
    H: np.ndarray
    L: np.ndarray
    T: np.ndarray
    Tinv: np.ndarray
    rest: Tuple[int, ...]
    p: int
    D: np.ndarray
    A11: np.ndarray
    A12: np.ndarray
    A21: np.ndarray
    A22: np.ndarray
    B1: np.ndarray
    B2: np.ndarray
    discrete: bool = False

    @property
    def n(self):
        """Return the number of plant states."""
        return self.T.shape[0]

    @property
    def order(self):
        """Return the number of observer states, n - p."""
        return self.F.shape[0]

    @property
    def poles(self):
        """Observer poles eig(F)."""
        return np.linalg.eigvals(self.F)

    def _y_t(self, y, u):
        y = np.asarray(y, dtype=float).reshape(-1)
        if y.size != self.p:
            raise DimensionError(f'y has {y.size} elements; expected {self.p}')
        if u is None:
            return y
        u = np.asarray(u, dtype=float).reshape(-1)
        if u.size != self.D.shape[1]:
            raise DimensionError(f'u has {u.size} elements; expected {self.D.shape[1]}')
        return y - self.D @ u

    def state_estimate(self, y, z, u=None):
        """
        Return x_hat in the original state order.

        Parameters
        ----------
        y : (p,) array_like
            Measurement.
        z : (n - p,) array_like
            Observer state.
        u : (m,) array_like, optional
            Input (needed when D is not zero).

        Returns
        -------
        x_hat : (n,) ndarray
            ``Tinv [y - D u; L (y - D u) + z]``.

        """
        yt = self._y_t(y, u)
        z = np.asarray(z, dtype=float).reshape(-1)
        if z.size != self.order:
            raise DimensionError(f'z has {z.size} elements; expected {self.order}')
        return self.Tinv @ np.concatenate([yt, self.L @ yt + z])

    def z_rate(self, z, y, u=None):
        """
        Return ``F z + G (y - D u) + H u``: dz/dt, or z[k+1] for a discrete plant.

        Parameters
        ----------
        z : (n - p,) array_like
            Observer state.
        y : (p,) array_like
            Measurement.
        u : (m,) array_like, optional
            Input (needed when D or H is not zero).

        Returns
        -------
        ndarray

        """
        yt = self._y_t(y, u)
        z = np.asarray(z, dtype=float).reshape(-1)
        out = self.F @ z + self.G @ yt
        if u is not None:
            out = out + self.H @ np.asarray(u, dtype=float).reshape(-1)
        return out

    def z_from_estimate(self, x_hat, y=None, u=None):
        """
        Observer state z for a full estimate x_hat: ``z = (T x_hat)[p:] - L y_t``.

        Parameters
        ----------
        x_hat : (n,) array_like
            Full state estimate.
        y : (p,) array_like, optional
            Measurement; default ``C x_hat`` (then ``y_t = C x_hat``).
        u : (m,) array_like, optional
            Input (needed when D is not zero).

        Returns
        -------
        z : (n - p,) ndarray

        """
        xb = self.T @ np.asarray(x_hat, dtype=float).reshape(-1)
        yt = xb[:self.p] if y is None else self._y_t(y, u)
        return xb[self.p:] - self.L @ yt


def reduced_order_observer(A, B, C, D=None, poles=None, gain=None, method='auto',
                           discrete=False, state_names=None):
    """
    Design a reduced-order observer estimating the n - p states C does not give.

    Parameters
    ----------
    A : (n, n) array_like
        State matrix.
    B : (n, m) array_like
        Input matrix.
    C : (p, n) array_like
        Output matrix, full row rank.
    D : (p, m) array_like, optional
        Feedthrough; the observer uses ``y - D u``.
    poles : array_like of complex, optional
        The n - p poles of F (fewer for a detectable unobservable plant, see
        :func:`observer_gain`). Exactly one of ``poles`` and ``gain``.
    gain : ((n - p), p) array_like, optional
        L given directly.
    method : {'auto', 'place', 'acker'}
        Pole placement method (see observer_gain).
    discrete : bool
        Discrete time: z-plane instead of s-plane.
    state_names : sequence of str, optional
        State names for messages (default x1..xn).

    Returns
    -------
    ReducedOrderDesign
        With ``L = observer_gain(A22, A12, poles)`` (``place(A22', A12')'`` as in
        the seeds), ``F = A22 - L A12``, ``H = B2 - L B1``, ``G = F L + A21 - L A11``.

    """
    A = as_matrix(A, 'A', square=True)
    n = A.shape[0]
    B = as_matrix(B, 'B', rows=n)
    C = as_matrix(C, 'C', cols=n)
    p, m = C.shape[0], B.shape[1]
    D = np.zeros((p, m)) if D is None else as_matrix(D, 'D', rows=p, cols=m)
    if (poles is None) == (gain is None):
        raise DesignError('give exactly one of poles and gain for the reduced-order observer')
    T, Tinv, rest = reduced_coordinates(C)
    Ab = T @ A @ Tinv
    Bb = T @ B
    A11, A12, A21, A22 = Ab[:p, :p], Ab[:p, p:], Ab[p:, :p], Ab[p:, p:]
    B1, B2 = Bb[:p], Bb[p:]
    if gain is None:
        names = None if state_names is None else [tuple(state_names)[i] for i in rest]
        try:
            L = observer_gain(A22, A12, poles, method, discrete, names)
        except DimensionError as err:
            if 'poles has' not in str(err):
                raise
            raise DimensionError(f'reduced-order observer: {err} (n - p = {n} - {p})') from None
    else:
        L = as_matrix(gain, 'gain', rows=n - p, cols=p)
    F = A22 - L @ A12
    H = B2 - L @ B1
    G = F @ L + A21 - L @ A11
    return ReducedOrderDesign(F, G, H, L, T, Tinv, tuple(rest), p, D, A11, A12, A21, A22,
                              B1, B2, bool(discrete))
