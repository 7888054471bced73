# observer_ros.core.compensator: controller + observer, closed loop and vehicle design.
"""
Compensators (state feedback on an estimate): closed loop, separation, D(s), vehicle design.

The control law is seed 002's Eq. 5.109, ``u = K (x_d - x_hat) - Kd x_d``; with
``x_d = 0`` it is seed 000's ``u = -K x_hat``, and the compensator transfer
function is defined by ``u(s) = -D(s) y(s)``.

"""

from dataclasses import dataclass, field
import math
from typing import Optional, Tuple
import warnings

import numpy as np
import scipy.linalg
import scipy.optimize

from ._lazy import control
from .analysis import (controllability_report, ControllabilityReport, format_complex,
                       observability_report, ObservabilityReport, stability_margin,
                       unobservable_eigenvalues)
from .delay_compensation import loop_delay_margin
from .design import (controller_gain, kalman_gain, lqr_gain, observer_gain,
                     pole_placement_error, reduced_order_observer, ReducedOrderDesign)
from .errors import (DesignError, DimensionError, NotDetectableError, ObserverDesignWarning,
                     ObserverError)
from .estimators.sampled import check_sampled_observer, SampledCheck
from .model import as_matrix, as_poles, as_vector
from .verify import (PlacementCheck, stability_status, unstable_eigenvalues, verify_placement,
                     verify_stable)

__all__ = ['closed_loop_matrix', 'closed_loop_matrices', 'error_dynamics_matrix',
           'reduced_closed_loop_matrix', 'reduced_closed_loop_matrices',
           'spectrum_match', 'separation_check', 'compensator_matrices', 'compensator_ss',
           'compensator_tf', 'compensator_poles', 'reference_input_matrix', 'tracking_residual',
           'tracking_ok', 'observer_noise_gain', 'design_warnings', 'VehicleDesign',
           'design_vehicle', 'to_json_dict', 'format_report', 'SPEED_RATIO',
           'NOISE_GAIN_LIMIT', 'SEPARATION_TOL']

#: Seed 000's rule of thumb: observer poles "twice as negative" as the controller's.
SPEED_RATIO = 2.0

#: An observer whose estimate of a measured output is noisier than the sensor
#: itself (ratio > 1) amplifies measurement noise.
NOISE_GAIN_LIMIT = 1.0

#: Default relative tolerance of :func:`separation_check`.
SEPARATION_TOL = 1e-6


# ---------------------------------------------------------------- argument checking


def _plant(A, B, C, D=None):
    A = as_matrix(A, 'A', square=True)
    n = A.shape[0]
    B = as_matrix(B, 'B', rows=n)
    C = as_matrix(C, 'C', cols=n)
    D = np.zeros((C.shape[0], B.shape[1])) if D is None else \
        as_matrix(D, 'D', rows=C.shape[0], cols=B.shape[1])
    return A, B, C, D


def _gain_K(K, m, n):
    return as_matrix(K, 'K', rows=m, cols=n)


def _gain_L(L, n, p):
    return as_matrix(L, 'L', rows=n, cols=p)


def _check_design(design, n, m, p):
    if design.n != n:
        raise DimensionError(f'reduced design has {design.n} states; expected {n}')
    if design.p != p:
        raise DimensionError(f'reduced design has {design.p} outputs; expected {p}')
    if design.H.shape[1] != m:
        raise DimensionError(f'reduced design has {design.H.shape[1]} inputs; expected {m}')


# ---------------------------------------------------------------- closed loop, full order


def closed_loop_matrix(A, B, C, K, L, D=None):
    """
    Return the closed loop of plant and full-order compensator, state ``[x; x_hat]``.

    Seed 002 Eq. 5.113.

    Parameters
    ----------
    A, B, C : array_like
        Plant (n states, m inputs, p outputs).
    K : (m, n) array_like
        State feedback, ``u = -K x_hat`` (plus reference terms).
    L : (n, p) array_like
        Observer gain.
    D : (p, m) array_like, optional
        Feedthrough. The observer uses the residual ``y - C x_hat - D u``, so D
        cancels and the matrix does not depend on it (it is checked only).

    Returns
    -------
    Acl : (2n, 2n) ndarray
        ``[[A, -B K], [L C, A - L C - B K]]``.

    """
    A, B, C, D = _plant(A, B, C, D)
    n, m, p = A.shape[0], B.shape[1], C.shape[0]
    K = _gain_K(K, m, n)
    L = _gain_L(L, n, p)
    return np.block([[A, -B @ K], [L @ C, A - L @ C - B @ K]])


def reference_input_matrix(B, K, Kd=None):
    """
    Plant input matrix of the reference: ``B (K - Kd)`` (Eq. 5.112).

    Parameters
    ----------
    B : (n, m) array_like
        Input matrix.
    K : (m, n) array_like
        State-feedback gain (u = -K x_hat).
    Kd : (m, n) array_like, optional
        Feedforward gain (default zeros).

    Returns
    -------
    (n, n) ndarray

    """
    B = as_matrix(B, 'B')
    n, m = B.shape
    K = _gain_K(K, m, n)
    Kd = np.zeros((m, n)) if Kd is None else as_matrix(Kd, 'Kd', rows=m, cols=n)
    return B @ (K - Kd)


def closed_loop_matrices(A, B, C, K, L, D=None, Kd=None):
    """
    Closed-loop tracking system of Eq. 5.113: ``[x; x_hat]' = Acl [x; x_hat] + Bcl x_d``.

    Parameters
    ----------
    A, B, C, K, L, D : array_like
        See :func:`closed_loop_matrix`.
    Kd : (m, n) array_like, optional
        Feedforward gain of ``u = K (x_d - x_hat) - Kd x_d`` (default zeros).

    Returns
    -------
    Acl : (2n, 2n) ndarray
    Bcl : (2n, n) ndarray
        ``[B (K - Kd); B (K - Kd)]``.

    """
    Acl = closed_loop_matrix(A, B, C, K, L, D)
    Bx = reference_input_matrix(B, K, Kd)
    return Acl, np.vstack([Bx, Bx])


def error_dynamics_matrix(A, B, C, K, L):
    """
    Tracking-error form of Eq. 5.117, state ``[e; e_o]`` with ``e = x_d - x``, ``e_o = x - x_hat``.

    Parameters
    ----------
    A, B, C, K, L : array_like
        Plant matrices, state-feedback gain and observer gain.

    Returns
    -------
    (2n, 2n) ndarray
        ``[[A - B K, -B K], [0, A - L C]]``.

    """
    A, B, C, _ = _plant(A, B, C)
    n, m, p = A.shape[0], B.shape[1], C.shape[0]
    K = _gain_K(K, m, n)
    L = _gain_L(L, n, p)
    return np.block([[A - B @ K, -B @ K], [np.zeros((n, n)), A - L @ C]])


# ---------------------------------------------------------------- closed loop, reduced order


def _estimate_maps(design):
    """x_hat = M y_t + N z with M = Tinv[:, :p] + Tinv[:, p:] L and N = Tinv[:, p:]."""
    p = design.p
    N = design.Tinv[:, p:]
    M = design.Tinv[:, :p] + N @ design.L
    return M, N


def reduced_closed_loop_matrix(A, B, K, design, coordinates='error'):
    """
    Return the closed loop of plant and reduced-order compensator.

    Parameters
    ----------
    A, B : array_like
        Plant.
    K : (m, n) array_like
        State feedback on ``x_hat = Tinv [y - D u; L (y - D u) + z]``.
    design : ReducedOrderDesign
        The design.
    coordinates : {'error', 'state'}
        ``'error'``: Example 5.20's ``[e; e2]`` with ``e = x_d - x`` and
        ``e2 = x_bar[p:] - x_hat2``, matrix ``[[A - B K, -B K2], [0, F]]`` where
        ``K2 = K Tinv[:, p:]`` is K acting on the estimated coordinates (for a C
        made of rows of the identity, the columns of K of the estimated states).
        ``'state'``: ``[x; z]``, the matrix that is simulated.

    Returns
    -------
    (2n - p, 2n - p) ndarray

    """
    A = as_matrix(A, 'A', square=True)
    n = A.shape[0]
    B = as_matrix(B, 'B', rows=n)
    m = B.shape[1]
    K = _gain_K(K, m, n)
    if not isinstance(design, ReducedOrderDesign):
        raise DesignError('design must be a ReducedOrderDesign')
    _check_design(design, n, m, design.p)
    M, N = _estimate_maps(design)
    r = design.order
    if coordinates == 'error':
        return np.block([[A - B @ K, -B @ K @ N], [np.zeros((r, n)), design.F]])
    if coordinates == 'state':
        C = design.T[:design.p]
        KM = K @ M @ C
        return np.block([[A - B @ KM, -B @ K @ N],
                         [design.G @ C - design.H @ KM, design.F - design.H @ K @ N]])
    raise DesignError(f"coordinates is {coordinates!r}; expected 'error' or 'state'")


def reduced_closed_loop_matrices(A, B, K, design, Kd=None):
    """
    Reduced-order tracking loop in ``[x; z]``: ``Acl``, and ``Bcl`` for x_d.

    Parameters
    ----------
    A, B, K : array_like
        Plant matrices and the state-feedback gain on x_hat.
    design : ReducedOrderDesign
        The design.
    Kd : (m, n) array_like, optional
        Feedforward gain; default zeros.

    Returns
    -------
    Acl : (2n - p, 2n - p) ndarray
    Bcl : (2n - p, n) ndarray
        ``[B (K - Kd); H (K - Kd)]``.

    """
    Acl = reduced_closed_loop_matrix(A, B, K, design, 'state')
    B = as_matrix(B, 'B')
    Kx = _gain_K(K, B.shape[1], B.shape[0])
    Kd = np.zeros_like(Kx) if Kd is None else \
        as_matrix(Kd, 'Kd', rows=Kx.shape[0], cols=Kx.shape[1])
    return Acl, np.vstack([B @ (Kx - Kd), design.H @ (Kx - Kd)])


# ---------------------------------------------------------------- separation principle


def _eig_bounds(M):
    """Eigenvalues of M and first-order rounding bounds 10 N eps ||Mb|| kappa_i (Mb balanced)."""
    N = M.shape[0]
    if N == 0:
        return np.zeros(0, complex), np.zeros(0)
    Mb, _ = scipy.linalg.matrix_balance(M)
    lam, vl, vr = scipy.linalg.eig(Mb, left=True, right=True)
    dots = np.abs(np.sum(vl.conj() * vr, axis=0))
    with np.errstate(divide='ignore'):
        kappa = np.where(dots > 0, 1.0 / np.maximum(dots, 1e-300), np.inf)
    return lam, 10.0 * N * _EPS * float(np.linalg.norm(Mb, 2)) * kappa


_EPS = np.finfo(float).eps


def spectrum_match(M, expected, tol=SEPARATION_TOL, expected_bounds=None):
    """
    Check that eig(M) is the expected set of eigenvalues, up to tol or rounding.

    Parameters
    ----------
    M : (N, N) array_like
        Square matrix.
    expected : (N,) array_like of complex
        Expected eigenvalues.
    tol : float
        Relative tolerance: eigenvalue lambda matched to p passes when
        ``|lambda - p| <= max(tol max(1, |p|), b)``, b being the first-order
        rounding bound ``10 N eps ||Mb|| kappa(lambda)`` of the eigenvalue (Mb is M
        balanced, kappa the eigenvalue condition number from the left and right
        eigenvectors) plus ``expected_bounds`` of p. Repeated eigenvalues, whose
        kappa is unbounded, also pass when
        :func:`~observer_ros.core.design.pole_placement_error` is within tol.
    expected_bounds : (N,) array_like, optional
        Rounding bounds of the expected values (when they are computed too).

    Returns
    -------
    ok : bool
    eigenvalues : ndarray of complex
        eig(M), matched to ``expected`` (same order).

    """
    ok, matched, _, _ = _spectrum_compare(M, expected, tol, expected_bounds)
    return ok, matched


def _spectrum_compare(M, expected, tol, expected_bounds):
    """spectrum_match, also returning ``|matched - expected|`` and what is allowed of it."""
    M = as_matrix(M, 'M', square=True)
    want = np.asarray(expected, dtype=complex).reshape(-1)
    if want.size != M.shape[0]:
        raise DimensionError(f'expected has {want.size} eigenvalues; expected {M.shape[0]}')
    lam, bound = _eig_bounds(M)
    if want.size == 0:
        return True, lam, np.zeros(0), np.zeros(0)
    eb = np.zeros(want.size) if expected_bounds is None else \
        np.asarray(expected_bounds, dtype=float).reshape(-1)
    scale = np.maximum(1.0, np.abs(want))
    cost = np.abs(lam[:, None] - want[None, :]) / scale[None, :]
    rows, cols = scipy.optimize.linear_sum_assignment(cost)
    matched = np.empty_like(want)
    matched[cols] = lam[rows]
    allowed = np.empty(want.size)
    allowed[cols] = bound[rows]
    allowed = np.maximum(tol * scale, allowed + eb)
    off = np.abs(matched - want)
    ok = bool(np.all(off <= allowed))
    if not ok:
        ok = pole_placement_error(M, want) <= tol
    return ok, matched, off, allowed


def separation_check(A, B, C, K, L, tol=SEPARATION_TOL, D=None):
    """
    Check the separation principle: eig(closed loop) = eig(A - B K) and the observer poles.

    Parameters
    ----------
    A, B, C : array_like
        Plant: state, input and output matrices.
    K : (m, n) array_like
        State-feedback gain (u = -K x_hat).
    L : (n, p) array_like or ReducedOrderDesign
        Full-order gain L (expected ``eig(A - L C)``) or a reduced design
        (expected ``eig(F)``); the closed loop is the one that runs
        (``[x; x_hat]`` or ``[x; z]``).
    tol : float
        Relative tolerance of :func:`spectrum_match`: every closed-loop
        eigenvalue is within ``tol max(1, |p|)`` of its expected pole p, or within
        what rounding allows for the eigenvalues of these matrices (first-order
        bound from the eigenvalue condition numbers of the balanced matrices,
        which matters for gains of 1e4 and more). 1e-6 is far below any real
        design difference.
    D : (p, m) array_like, optional
        Feedthrough matrix; default zeros.

    Returns
    -------
    ok : bool
    closed_loop_poles : ndarray of complex
        Matched to ``expected``, element by element.
    expected : ndarray of complex
        ``eig(A - B K)`` followed by the observer poles.

    """
    ok, cl, expected, _, _ = _separation(A, B, C, K, L, tol, D)
    return ok, cl, expected


def _separation(A, B, C, K, L, tol=SEPARATION_TOL, D=None):
    """separation_check, also returning the largest ``|eig - expected|`` and its allowance."""
    A, B, C, D = _plant(A, B, C, D)
    n, m = A.shape[0], B.shape[1]
    K = _gain_K(K, m, n)
    if isinstance(L, ReducedOrderDesign):
        Acl = reduced_closed_loop_matrix(A, B, K, L, 'state')
        obs, obs_b = _eig_bounds(L.F)     # L is the reduced design here
    else:
        L = _gain_L(L, n, C.shape[0])
        Acl = closed_loop_matrix(A, B, C, K, L, D)
        obs, obs_b = _eig_bounds(A - L @ C)
    ctrl, ctrl_b = _eig_bounds(A - B @ K)
    expected = np.concatenate([ctrl, obs])
    ok, cl, off, allowed = _spectrum_compare(Acl, expected, tol,
                                             np.concatenate([ctrl_b, obs_b]))
    if not off.size:
        return ok, cl, expected, 0.0, 0.0
    i = int(np.argmax(off / np.maximum(allowed, 1e-300)))
    return ok, cl, expected, float(off[i]), float(allowed[i])


# ---------------------------------------------------------------- compensator D(s)


def compensator_matrices(A, B, C, K, L, D=None):
    """
    State-space matrices (Ac, Bc, Cc, Dc) of the compensator, ``u = -D(s) y``.

    Parameters
    ----------
    A, B, C : array_like
        Plant: state, input and output matrices.
    K : (m, n) array_like
        State-feedback gain (u = -K x_hat).
    L : (n, p) array_like or ReducedOrderDesign
        Observer gain L or reduced design.
    D : (p, m) array_like, optional
        Feedthrough matrix; default zeros.

    Returns
    -------
    Ac, Bc, Cc, Dc : ndarray
        Full order (seed 000, with seed 002 Eq. 5.110 for D): ``Ac = A - B K - L C
        + L D K``, ``Bc = L``, ``Cc = K``, ``Dc = 0``, so that
        ``D(s) = K (sI - A + B K + L C - L D K)^-1 L``. Reduced order: the
        controller state is z, ``x_hat = M y_t + N z``, and the algebraic loop
        through D is solved with ``X = (I - K M D)^-1``: ``Cc = X K N``,
        ``Dc = X K M``, ``Ac = F - (H - G D) Cc``, ``Bc = G - (H - G D) Dc``.

    """
    A, B, C, D = _plant(A, B, C, D)
    n, m, p = A.shape[0], B.shape[1], C.shape[0]
    K = _gain_K(K, m, n)
    if isinstance(L, ReducedOrderDesign):
        red = L
        _check_design(red, n, m, p)
        M, N = _estimate_maps(red)
        W = np.eye(m) - K @ M @ D
        try:
            X = np.linalg.inv(W)
        except np.linalg.LinAlgError:
            raise DesignError('the reduced-order compensator has a singular algebraic loop '
                              'I - K M D through the feedthrough D') from None
        Cc = X @ K @ N
        Dc = X @ K @ M
        Hy = red.H - red.G @ D
        return red.F - Hy @ Cc, red.G - Hy @ Dc, Cc, Dc
    L = _gain_L(L, n, p)
    return A - B @ K - L @ C + L @ D @ K, L, K, np.zeros((m, p))


def compensator_ss(A, B, C, K, L, D=None, dt=None):
    """
    Return the compensator D(s) (``u = -D(s) y``) as a python-control StateSpace.

    Parameters
    ----------
    A, B, C, K, L, D
        See :func:`compensator_matrices`.
    dt : float, optional
        Sample time of a discrete plant (D(z)); None for continuous time.

    Returns
    -------
    control.StateSpace

    """
    Ac, Bc, Cc, Dc = compensator_matrices(A, B, C, K, L, D)
    return control.ss(Ac, Bc, Cc, Dc, 0 if dt is None else dt)


def compensator_tf(A, B, C, K, L, D=None, dt=None):
    """
    Return the compensator transfer function ``D(s) = K (sI - A + B K + L C - L D K)^-1 L``.

    Parameters
    ----------
    A, B, C, K, L, D, dt
        See :func:`compensator_ss`.

    Returns
    -------
    control.TransferFunction
        m x p (python-control converts MIMO systems too).

    """
    return control.ss2tf(compensator_ss(A, B, C, K, L, D, dt))


def compensator_poles(A, B, C, K, L, D=None):
    """
    Compensator poles, the eigenvalues of its state matrix (seed 000).

    Parameters
    ----------
    A, B, C, K, L, D
        See :func:`compensator_matrices`.

    Returns
    -------
    ndarray of complex
        Unstable ones mean an "unstable compensator": the loop is only
        conditionally stable (seed 000).

    """
    Ac = compensator_matrices(A, B, C, K, L, D)[0]
    return np.linalg.eigvals(Ac) if Ac.size else np.zeros(0, complex)


# ---------------------------------------------------------------- reference tracking


def tracking_residual(A, B, x_d, Kd=None, A_d=None, discrete=False):
    """
    Steady-state tracking condition of Eq. 5.117: ``(A_d - A + B Kd) x_d``.

    Parameters
    ----------
    A, B : array_like
        Plant: state and input matrices.
    x_d : (n,) array_like
        Desired state.
    Kd : (m, n) array_like, optional
        Feedforward gain (default zeros).
    A_d : (n, n) array_like, optional
        Reference dynamics ``x_d' = A_d x_d``; default a constant reference:
        zeros in continuous time, the identity in discrete time
        (``x_d[k+1] = x_d[k]``).
    discrete : bool
        Discrete time: z-plane instead of s-plane.

    Returns
    -------
    r : (n,) ndarray
        Zero when the tracking error goes to zero for this x_d.

    """
    A = as_matrix(A, 'A', square=True)
    n = A.shape[0]
    B = as_matrix(B, 'B', rows=n)
    m = B.shape[1]
    x_d = as_vector(x_d, 'x_d', n)
    Kd = np.zeros((m, n)) if Kd is None else as_matrix(Kd, 'Kd', rows=m, cols=n)
    if A_d is None:
        A_d = np.eye(n) if discrete else np.zeros((n, n))
    A_d = as_matrix(A_d, 'A_d', rows=n, cols=n)
    return (A_d - A + B @ Kd) @ x_d


def tracking_ok(A, B, x_d, Kd=None, A_d=None, discrete=False, rtol=1e-9):
    """
    Return True when :func:`tracking_residual` is zero relative to ``(|A| + |B Kd|) |x_d|``.

    Parameters
    ----------
    A, B, x_d, Kd, A_d, discrete
        See :func:`tracking_residual`.
    rtol : float
        Relative tolerance.

    Returns
    -------
    bool

    """
    r = tracking_residual(A, B, x_d, Kd, A_d, discrete)
    A = as_matrix(A, 'A')
    scale = (np.linalg.norm(A, 2) + 1.0) * np.linalg.norm(as_vector(x_d, 'x_d'))
    if Kd is not None:
        scale += np.linalg.norm(as_matrix(B, 'B') @ as_matrix(Kd, 'Kd'), 2) * \
            np.linalg.norm(as_vector(x_d, 'x_d'))
    return bool(np.linalg.norm(r) <= rtol * max(scale, 1e-300))


# ---------------------------------------------------------------- warnings


def _decay_rate(lam, discrete):
    lam = complex(lam)
    if discrete:
        return math.inf if abs(lam) == 0.0 else -math.log(abs(lam))
    return -lam.real


def observer_noise_gain(A, C, L, noise_std, sample_time=None, discrete=False):
    """
    Noise gain of a full-order observer: std of its estimate of each output / sensor std.

    Parameters
    ----------
    A, C : array_like
        Plant: state and output matrices.
    L : (n, p) array_like
        Observer gain.
    noise_std : (p,) array_like
        Measurement noise standard deviation per output.
    sample_time : float or (p,) array_like, optional
        Sample time of each sensor; required in continuous time, where sampled
        noise of variance sigma^2 every dt is white noise of intensity
        ``sigma^2 dt``.
    discrete : bool
        Discrete plant: the noise enters every step with variance sigma^2.

    Returns
    -------
    ratio : (p,) ndarray
        ``sqrt(diag(C P C^T)) / sigma`` where P is the steady-state covariance of
        the estimation error driven by the measurement noise alone:
        ``(A - L C) P + P (A - L C)^T + L R L^T = 0`` (continuous,
        scipy ``solve_continuous_lyapunov``) or ``P = Phi P Phi^T + L R L^T``
        (discrete). A ratio above 1 means the observer's estimate of a
        measured quantity is noisier than the measurement: the gain is too large
        (poles too fast) for the sensor. NaN for outputs with sigma = 0, inf if
        the observer is unstable.
    P : (n, n) ndarray
        The covariance (per-state noise std is ``sqrt(diag(P))``).

    """
    A = as_matrix(A, 'A', square=True)
    n = A.shape[0]
    C = as_matrix(C, 'C', cols=n)
    p = C.shape[0]
    L = _gain_L(L, n, p)
    sigma = as_vector(noise_std, 'noise_std', p)
    if discrete:
        R = np.diag(sigma ** 2)
    else:
        if sample_time is None:
            raise ObserverError('sample_time is needed for the noise gain of a continuous '
                                'observer')
        dt = np.broadcast_to(np.asarray(sample_time, dtype=float), (p,))
        R = np.diag(sigma ** 2 * dt)
    Phi = A - L @ C
    if unstable_eigenvalues(Phi, discrete):
        return np.full(p, np.inf), np.full((n, n), np.inf)
    Q = L @ R @ L.T
    if discrete:
        P = scipy.linalg.solve_discrete_lyapunov(Phi, Q)
    else:
        P = scipy.linalg.solve_continuous_lyapunov(Phi, -Q)
    P = (P + P.T) / 2.0
    out_std = np.sqrt(np.maximum(np.diag(C @ P @ C.T), 0.0))
    with np.errstate(divide='ignore', invalid='ignore'):
        ratio = np.where(sigma > 0, out_std / np.where(sigma > 0, sigma, 1.0), np.nan)
    return ratio, P


def design_warnings(A, B, C, K, L, D=None, discrete=False, noise_std=None,
                    sample_time=None, output_names=None, speed_ratio=SPEED_RATIO,
                    noise_gain_limit=NOISE_GAIN_LIMIT):
    """
    Rule-of-thumb checks of a compensator design; a list of human-readable warnings.

    Parameters
    ----------
    A, B, C : array_like
        Plant: state, input and output matrices.
    K : (m, n) array_like or None
        Controller gain (None: observer only, rules 1 and 2 are skipped).
    L : (n, p) array_like or ReducedOrderDesign
        Observer gain L or reduced design.
    D : (p, m) array_like, optional
        Feedthrough matrix; default zeros.
    discrete : bool
        Discrete time: z-plane instead of s-plane.
    noise_std : (p,) array_like, optional
        Sensor noise std per output, for rule 4.
    sample_time : float or (p,) array_like, optional
        Sensor sample times (continuous plant), for rule 4.
    output_names : sequence of str, optional
        Output names for messages.
    speed_ratio : float
        Rule 1 factor (2: seed 000's "twice as negative").
    noise_gain_limit : float
        Rule 4 threshold.

    Returns
    -------
    list of str
        The rules:

        1. Observer too slow (seed 000, seed 004): the slowest observer pole must
           decay at least ``speed_ratio`` times as fast as the slowest controller
           pole, decay rate ``-Re(s)`` (or ``-ln|z|`` per step).
        2. Unstable compensator (seed 000): an eigenvalue of the compensator's state
           matrix in the closed right half plane (on/outside the unit circle):
           the loop is only conditionally stable and not robust.
        3. Unstable observer: the estimation error does not decay (an open-loop
           observer of an unstable plant drifts, seed 004).
        4. Noise amplification (seed 000, seed 004; full-order observers): the
           :func:`observer_noise_gain` of an output exceeds ``noise_gain_limit``.

    """
    A, B, C, D = _plant(A, B, C, D)
    n, m, p = A.shape[0], B.shape[1], C.shape[0]
    out_names = list(output_names) if output_names else [f'y{i + 1}' for i in range(p)]
    observer = L
    reduced = isinstance(observer, ReducedOrderDesign)
    if reduced:
        obs_poles = observer.poles
        L = None
    else:
        L = _gain_L(observer, n, p)
        obs_poles = np.linalg.eigvals(A - L @ C)
    out = []
    unstable_obs = [lam for lam, _ in unstable_eigenvalues(
        observer.F if reduced else A - L @ C, discrete)]
    if unstable_obs:
        what = 'the open-loop observer drifts (L = 0 and A is not stable)' \
            if L is not None and not np.any(L) else 'the estimation error does not decay'
        out.append(f'observer is not stable: poles '
                   f'{", ".join(format_complex(x, 4) for x in unstable_obs)}; {what}')
    if K is not None:
        K = _gain_K(K, m, n)
        ctrl_poles = np.linalg.eigvals(A - B @ K)
        ctrl_rate = min(_decay_rate(x, discrete) for x in ctrl_poles) if n else math.inf
        obs_rate = min(_decay_rate(x, discrete) for x in obs_poles) if len(obs_poles) else \
            math.inf
        if 0.0 < ctrl_rate < math.inf and obs_rate < speed_ratio * ctrl_rate * (1 - 1e-6):
            slow_o = min(obs_poles, key=lambda x: _decay_rate(x, discrete))
            slow_c = min(ctrl_poles, key=lambda x: _decay_rate(x, discrete))
            out.append(
                f'observer is slow: its slowest pole {format_complex(slow_o, 4)} is not '
                f'{speed_ratio:g}x as fast as the slowest controller pole '
                f'{format_complex(slow_c, 4)}; the estimate lags and the loop responds '
                'like the observer (seed 000: make observer poles twice as negative)')
        comp = compensator_poles(A, B, C, K, observer, D)
        cm = stability_margin(A - B @ K)
        bad = [lam for lam in comp if stability_status(lam, cm, discrete) == 'unstable']
        if bad:
            out.append(
                f'unstable compensator: D(s) has the pole(s) '
                f'{", ".join(format_complex(x, 4) for x in bad)}; the closed loop is only '
                'conditionally stable and may not be robust to model errors (seed 000)')
    if noise_std is not None and not reduced and not unstable_obs:
        sigma = as_vector(noise_std, 'noise_std', p)
        if discrete or sample_time is not None:
            ratio, _ = observer_noise_gain(A, C, L, sigma, sample_time, discrete)
            for i in range(p):
                if np.isfinite(ratio[i]) and ratio[i] > noise_gain_limit:
                    out.append(
                        f'observer amplifies the noise of {out_names[i]}: its estimate of '
                        f'{out_names[i]} has {ratio[i]:.3g}x the sensor noise std; the '
                        'observer poles are too fast (gains too large) for this sensor')
    return out


# ---------------------------------------------------------------- vehicle design


@dataclass(frozen=True)
class VehicleDesign:
    """
    Everything designed for a vehicle: reports, gains, poles, compensator, warnings.

    ``L`` is the gain in use: (n, p) for 'full', 'kalman' and 'open_loop' (zeros),
    (n - p, p) for 'reduced' (whose full design is ``reduced``). ``K`` is None
    when the vehicle has no controller. Poles are s-plane for a continuous plant
    and z-plane for a discrete one.

    """

    kind: str
    discrete: bool
    sample_time: Optional[float]
    state_names: Tuple[str, ...]
    input_names: Tuple[str, ...]
    output_names: Tuple[str, ...]
    observability: ObservabilityReport
    controllability: ControllabilityReport
    L: np.ndarray
    K: Optional[np.ndarray]
    observer_poles: np.ndarray
    controller_poles: np.ndarray
    closed_loop_poles: np.ndarray
    expected_poles: np.ndarray
    separation_ok: Optional[bool]
    compensator: Optional['control.StateSpace']
    compensator_poles: np.ndarray
    reduced: Optional[ReducedOrderDesign] = None
    P: Optional[np.ndarray] = None
    Kd: Optional[np.ndarray] = None
    reference: Optional[np.ndarray] = None
    tracking_residual: Optional[np.ndarray] = None
    noise_gain: Optional[np.ndarray] = None
    warnings: Tuple[str, ...] = field(default=())
    observer_placement: Optional[PlacementCheck] = None
    controller_placement: Optional[PlacementCheck] = None
    separation_error: Optional[float] = None
    separation_allowed: Optional[float] = None
    sampled: Optional[SampledCheck] = None

    @property
    def observer(self):
        """Return what the closed-loop helpers take: L (full order) or the ReducedOrderDesign."""
        return self.reduced if self.reduced is not None else self.L


def _poles_from_spec(poles, name, discrete):
    if poles is None:
        return None
    try:
        return as_poles(poles, name, None, discrete=discrete, require_stable=True)
    except DimensionError:
        raise
    except ObserverError as err:
        raise DesignError(str(err)) from None


def _prefixed(name, fn, *args, **kwargs):
    """Call fn; prefix the vehicle-file field name to a DimensionError about poles."""
    try:
        return fn(*args, **kwargs)
    except DimensionError as err:
        if str(err).startswith('poles'):
            raise DimensionError(f'{name}: {err}') from None
        raise


def _noise_per_output(vehicle):
    plant = vehicle.plant
    p = plant.p
    sigma = np.full(p, np.nan)
    dt = np.full(p, np.nan)
    base = vehicle.sample_time
    for s in vehicle.sensors:
        stds = np.asarray(s.noise_std, dtype=float).reshape(-1)
        for j, out in enumerate(s.outputs):
            if out in plant.output_names and j < stds.size:
                i = plant.output_names.index(out)
                sigma[i] = stds[j]
                dt[i] = base * max(1, int(s.rate_divider))
    return sigma, dt


def design_vehicle(vehicle):
    """
    Design the observer and controller a vehicle file asks for, and check them.

    Parameters
    ----------
    vehicle : observer_ros.core.spec.Vehicle
        The vehicle.

    Returns
    -------
    VehicleDesign

    Raises
    ------
    NotDetectableError
        The observer ('full', 'reduced', 'kalman') cannot converge: an
        unobservable mode is not stable (seed 002 Example 5.15).
    NotControllableError
        Controller poles asked of a plant that is not stabilizable (or n poles
        of an uncontrollable one).
    DesignError
        Unusable specs: unstable or unpaired poles, a given K or L that does not
        stabilize, a failed LQR/Kalman design, ...
    DimensionError
        Wrong number of poles or wrong gain shapes (named by their field).

    """
    plant = vehicle.plant
    A, B, C, D = plant.A, plant.B, plant.C, plant.D
    n, m, p = plant.n, plant.m, plant.p
    discrete = plant.is_discrete
    names = plant.state_names
    obs_spec = vehicle.observer
    ctrl_spec = vehicle.controller
    kind = obs_spec.kind
    messages = []
    obs_check = None

    obs_report = observability_report(A, C, names, discrete)
    ctrb_report = controllability_report(A, B, names, discrete)

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter('always', ObserverDesignWarning)
        reduced = None
        P = None
        if kind in ('full', 'reduced', 'kalman') and not obs_report.detectable:
            bad = '; '.join(md.describe() for md in obs_report.modes if not md.stable)
            raise NotDetectableError(
                f'the plant is not detectable with outputs {list(plant.output_names)}: '
                f'the unobservable {bad} cannot be estimated and does not decay; no '
                f'{kind!r} observer converges (add a sensor on those states)')
        if kind == 'full':
            if (obs_spec.poles is None) == (obs_spec.gain is None):
                raise DesignError('observer: give exactly one of observer.poles and '
                                  'observer.gain')
            if obs_spec.gain is not None:
                L = as_matrix(obs_spec.gain, 'observer.gain', rows=n, cols=p)
            else:
                poles = _poles_from_spec(obs_spec.poles, 'observer.poles', discrete)
                L = _prefixed('observer.poles', observer_gain, A, C, poles, obs_spec.method,
                              discrete, names)
                obs_check = verify_placement(
                    A - L @ C, np.concatenate([poles, obs_report.unobservable_eigenvalues]),
                    'observer.poles', _norm(A) + _norm(L) * _norm(C), discrete)
            observer_poles = np.linalg.eigvals(A - L @ C)
        elif kind == 'reduced':
            if (obs_spec.poles is None) == (obs_spec.gain is None):
                raise DesignError('observer: give exactly one of observer.poles and '
                                  'observer.gain')
            poles = _poles_from_spec(obs_spec.poles, 'observer.poles', discrete)
            gain = None if obs_spec.gain is None else \
                as_matrix(obs_spec.gain, 'observer.gain', rows=n - p, cols=p)
            reduced = _prefixed('observer.poles', reduced_order_observer, A, B, C, D,
                                poles=poles, gain=gain, method=obs_spec.method,
                                discrete=discrete, state_names=names)
            L = reduced.L
            observer_poles = reduced.poles
            if poles is not None:
                obs_check = verify_placement(
                    reduced.F, np.concatenate([poles, unobservable_eigenvalues(reduced.A22,
                                                                               reduced.A12)]),
                    'observer.poles', _norm(reduced.A22) + _norm(L) * _norm(reduced.A12),
                    discrete)
        elif kind == 'open_loop':
            L = np.zeros((n, p))
            observer_poles = np.linalg.eigvals(A)
        elif kind == 'kalman':
            if obs_spec.Qd is None or obs_spec.Rd is None:
                raise DesignError('observer: a kalman observer needs observer.Qd and '
                                  'observer.Rd')
            L, P, observer_poles = kalman_gain(A, C, obs_spec.Qd, obs_spec.Rd, obs_spec.Bd,
                                               discrete, names)
            verify_stable(A - L @ C, 'the Kalman gain of observer.Qd and observer.Rd',
                          'eig(A - L C)', discrete)
        else:
            raise DesignError(f'observer.type is {kind!r}; expected full, reduced, '
                              'open_loop or kalman')
        if kind in ('full', 'reduced') and obs_spec.gain is not None:
            verify_stable(A - L @ C if reduced is None else reduced.F, 'observer.gain',
                          'eig(A - L C)' if reduced is None else 'eig(F)', discrete)

        # the gains the loop runs: per sampled step and set of outputs, at the sensors' rates
        sampled, sampled_messages = check_sampled_observer(vehicle)
        messages.extend(sampled_messages)
        K, ctrl_check = _controller(ctrl_spec, A, B, n, m, discrete, names,
                                    ctrb_report.uncontrollable_eigenvalues)
    messages.extend(str(w.message) for w in caught
                    if issubclass(w.category, ObserverDesignWarning))
    for w in caught:   # re-emit anything that is not ours
        if not issubclass(w.category, ObserverDesignWarning):
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)

    observer = reduced if reduced is not None else L
    full_L = None if reduced is not None else L
    sigma, dt = _noise_per_output(vehicle)
    noise_gain = None
    if full_L is not None and np.any(np.isfinite(sigma)):
        try:
            noise_gain, _ = observer_noise_gain(A, C, full_L, np.nan_to_num(sigma),
                                                np.nan_to_num(dt, nan=vehicle.sample_time),
                                                discrete)
            noise_gain = np.where(np.isfinite(sigma), noise_gain, np.nan)
        except (ObserverError, np.linalg.LinAlgError, ValueError):
            noise_gain = None
    warn_sigma = np.where(np.isfinite(sigma), sigma, 0.0) if np.any(np.isfinite(sigma)) \
        else None
    messages.extend(design_warnings(A, B, C, K, observer, D, discrete, warn_sigma,
                                    None if discrete else np.nan_to_num(
                                        dt, nan=vehicle.sample_time),
                                    plant.output_names))
    if kind == 'kalman' and obs_spec.poles is not None:
        messages.append('observer.poles is ignored by a kalman observer')

    controller_poles = np.linalg.eigvals(A - B @ K) if K is not None else np.zeros(0, complex)
    Kd = reference = residual = None
    if K is not None:
        # the closed-loop poles are the union of the verified blocks (exact in error
        # coordinates, where the matrix is block triangular); the full 2n matrix's
        # eigenvalues are only compared with them
        ok, _, expected, sep_err, sep_allowed = _separation(A, B, C, K, observer, D=D)
        cl = expected
        comp = compensator_ss(A, B, C, K, observer, D, plant.dt)
        comp_poles = compensator_poles(A, B, C, K, observer, D)
        Kd = np.zeros((m, n)) if ctrl_spec.Kd is None else \
            as_matrix(ctrl_spec.Kd, 'controller.Kd', rows=m, cols=n)
        reference = np.zeros(n) if ctrl_spec.reference is None else \
            as_vector(ctrl_spec.reference, 'controller.reference', n)
        residual = tracking_residual(A, B, reference, Kd, discrete=discrete)
        if np.any(reference) and not tracking_ok(A, B, reference, Kd, discrete=discrete):
            messages.append(
                'the reference is not tracked without steady-state error: '
                f'(A_d - A + B Kd) x_d = {np.array2string(residual, precision=4)} is not '
                'zero (seed 002 Eq. 5.117); choose Kd or a reachable x_d')
        if not ok:
            messages.append(f'separation check failed: the eigenvalues of the closed-loop '
                            f'matrix differ from eig(A - BK) and the observer poles by '
                            f'{sep_err:.2g}, more than rounding explains ({sep_allowed:.2g})')
    else:
        ok = None
        sep_err = sep_allowed = None
        cl = expected = comp_poles = np.zeros(0, complex)
        comp = None
    return VehicleDesign(
        kind=kind, discrete=discrete, sample_time=plant.dt, state_names=names,
        input_names=plant.input_names, output_names=plant.output_names,
        observability=obs_report, controllability=ctrb_report, L=L, K=K,
        observer_poles=observer_poles, controller_poles=controller_poles,
        closed_loop_poles=cl, expected_poles=expected, separation_ok=ok, compensator=comp,
        compensator_poles=comp_poles, reduced=reduced, P=P, Kd=Kd, reference=reference,
        tracking_residual=residual, noise_gain=noise_gain, warnings=tuple(messages),
        observer_placement=obs_check, controller_placement=ctrl_check,
        separation_error=sep_err, separation_allowed=sep_allowed, sampled=sampled)


def _norm(M):
    return float(np.linalg.norm(M, 2)) if np.size(M) else 0.0


def _controller(spec, A, B, n, m, discrete, names, kept):
    """Return (K or None, PlacementCheck or None); every K returned is verified stable."""
    given = [k for k, v in (('controller.poles', spec.poles), ('controller.K', spec.K),
                            ('controller.lqr_Q', spec.lqr_Q)) if v is not None]
    if len(given) > 1:
        raise DesignError(f'controller: give only one of {", ".join(given)}')
    if spec.poles is not None:
        poles = _poles_from_spec(spec.poles, 'controller.poles', discrete)
        K = _prefixed('controller.poles', controller_gain, A, B, poles, 'auto', discrete,
                      names)
        return K, verify_placement(A - B @ K, np.concatenate([poles, kept]),
                                   'controller.poles', _norm(A) + _norm(B) * _norm(K),
                                   discrete)
    if spec.K is not None:
        K = as_matrix(spec.K, 'controller.K', rows=m, cols=n)
        verify_stable(A - B @ K, 'controller.K', 'eig(A - B K)', discrete)
        return K, None
    if spec.lqr_Q is not None or spec.lqr_R is not None:
        if spec.lqr_Q is None or spec.lqr_R is None:
            raise DesignError('controller: an LQR design needs both controller.lqr_Q and '
                              'controller.lqr_R')
        Q = as_matrix(spec.lqr_Q, 'controller.lqr_Q', rows=n, cols=n)
        R = as_matrix(spec.lqr_R, 'controller.lqr_R', rows=m, cols=m)
        K = lqr_gain(A, B, Q, R, discrete)[0]
        verify_stable(A - B @ K, 'the LQR gain of controller.lqr_Q and controller.lqr_R',
                      'eig(A - B K)', discrete)
        return K, None
    return None, None


# ---------------------------------------------------------------- output


def _matrix(M):
    return None if M is None else [[float(x) for x in row] for row in np.atleast_2d(M)]


def _cvec(v):
    return [[float(np.real(x)), float(np.imag(x))] for x in np.asarray(v).reshape(-1)]


def to_json_dict(design):
    """
    Summarise a VehicleDesign as a JSON-serialisable dict.

    Parameters
    ----------
    design : VehicleDesign
        The design.

    Returns
    -------
    dict
        Matrices are lists of rows; poles (real ones too) are ``[re, im]`` pairs.
        Keys: kind, discrete, sample_time, state_names, input_names, output_names,
        observable, detectable, observability_rank, unobservable_modes,
        controllable, stabilizable, uncontrollable_modes, L, K, observer_poles,
        controller_poles, closed_loop_poles (the union of eig(A - B K) and the observer
        poles), separation_ok, separation_error (largest distance of an eigenvalue of the
        full closed-loop matrix from that union) and separation_allowed (what rounding
        allows there), compensator_poles,
        placement {observer, controller} (each None, or the achieved-versus-requested
        summary of :class:`~observer_ros.core.verify.PlacementCheck`), warnings, and
        when they apply reduced {F, G, H, L, rest}, P, Kd, reference,
        tracking_residual, noise_gain.

    """
    d = {
        'kind': design.kind,
        'discrete': design.discrete,
        'sample_time': design.sample_time,
        'state_names': list(design.state_names),
        'input_names': list(design.input_names),
        'output_names': list(design.output_names),
        'observable': bool(design.observability.observable),
        'detectable': bool(design.observability.detectable),
        'observability_rank': int(design.observability.rank),
        'unobservable_modes': list(design.observability.unobservable_modes),
        'controllable': bool(design.controllability.controllable),
        'stabilizable': bool(design.controllability.stabilizable),
        'uncontrollable_modes': list(design.controllability.uncontrollable_modes),
        'L': _matrix(design.L),
        'K': _matrix(design.K),
        'observer_poles': _cvec(design.observer_poles),
        'controller_poles': _cvec(design.controller_poles),
        'closed_loop_poles': _cvec(design.closed_loop_poles),
        'separation_ok': design.separation_ok,
        'separation_error': design.separation_error,
        'separation_allowed': design.separation_allowed,
        'compensator_poles': _cvec(design.compensator_poles),
        'placement': {
            'observer': None if design.observer_placement is None else
            design.observer_placement.to_json(),
            'controller': None if design.controller_placement is None else
            design.controller_placement.to_json(),
            'sampled': None if design.sampled is None else design.sampled.to_json()},
        'warnings': list(design.warnings),
    }
    if design.reduced is not None:
        r = design.reduced
        d['reduced'] = {'F': _matrix(r.F), 'G': _matrix(r.G), 'H': _matrix(r.H),
                        'L': _matrix(r.L), 'rest': [design.state_names[i] for i in r.rest]}
    if design.P is not None:
        d['P'] = _matrix(design.P)
    if design.Kd is not None:
        d['Kd'] = _matrix(design.Kd)
        d['reference'] = [float(x) for x in design.reference]
        d['tracking_residual'] = [float(x) for x in design.tracking_residual]
    if design.noise_gain is not None:
        d['noise_gain'] = [None if not np.isfinite(x) else float(x) for x in design.noise_gain]
    return d


def _table(M, row_names, col_names, digits=6):
    M = np.atleast_2d(M)
    cells = [[f'{x:.{digits}g}' for x in row] for row in M]
    w0 = max([len(r) for r in row_names] + [1])
    w = max([len(c) for c in col_names] + [len(c) for row in cells for c in row] + [1])
    lines = ['  ' + ' ' * w0 + '  ' + '  '.join(c.rjust(w) for c in col_names)]
    for name, row in zip(row_names, cells):
        lines.append('  ' + name.ljust(w0) + '  ' + '  '.join(c.rjust(w) for c in row))
    return lines


def _poles_line(poles):
    if len(poles) == 0:
        return 'none'
    order = sorted(np.asarray(poles).reshape(-1), key=lambda z: (z.real, -abs(z.imag)))
    return ', '.join(format_complex(z, 6) for z in order)


def _placement_lines(check):
    if check is None or not check.requested.size:
        return []
    w = check.worst
    return [f' placement ({check.field}): achieved poles within {check.max_error:.2g} of '
            f'those asked (relative {check.relative_error:.2g}); at the worst pole '
            f'{format_complex(check.requested[w])} the conditioning allows '
            f'{check.bound[w]:.2g}']


def _delay_margin_lines(design, vehicle):
    """Return the report's lines on the delay margin at the plant input (SISO, continuous)."""
    plant = None if vehicle is None else vehicle.plant
    if plant is None or design.discrete or design.compensator is None or \
            plant.m != 1 or plant.p != 1:
        return []
    try:
        tau, wc = loop_delay_margin(control.ss(plant.A, plant.B, plant.C, plant.D),
                                    design.compensator, points=20001)
    except Exception:   # noqa: BLE001 - the report must not fail on the printout
        return []
    if not np.isfinite(tau):
        return ['Delay margin at the plant input: no gain crossover (none needed)']
    lines = [f'Delay margin at the plant input: {tau * 1e3:.3g} ms (at {wc:.3g} rad/s)']
    dt = vehicle.sample_time
    if tau < dt:
        lines.append(f'  less than one sample ({dt * 1e3:g} ms): a realtime loop needs '
                     'controller.delay_compensation (a command that misses its step '
                     'destabilises it)')
    return lines


def format_report(design, vehicle=None):
    """
    Console report of a VehicleDesign (what ``observer-design`` prints).

    Parameters
    ----------
    design : VehicleDesign
        The design.
    vehicle : observer_ros.core.spec.Vehicle, optional
        Adds the vehicle's name, description and source.

    Returns
    -------
    str

    """
    lines = []
    if vehicle is not None:
        lines.append(f'Vehicle: {vehicle.name}' + (f' - {vehicle.description}'
                                                   if vehicle.description else ''))
        if vehicle.source:
            lines.append(f'Source: {vehicle.source}')
    plane = 'z-plane' if design.discrete else 's-plane'
    time = f'discrete, dt = {design.sample_time:g} s' if design.discrete else 'continuous'
    lines.append(f'Plant ({time}): states {list(design.state_names)}, inputs '
                 f'{list(design.input_names)}, outputs {list(design.output_names)}')
    lines.append('')
    lines.append(f'Observability: {design.observability.summary()}')
    for res in design.observability.pbh:
        lines.append(f'  PBH eigenvalue {format_complex(res.eigenvalue)}: rank {res.rank}/'
                     f'{res.n} ({"observable" if res.passed else "UNOBSERVABLE"}, '
                     f'{"stable" if res.stable else "not stable"})')
    lines.append(f'Controllability: {design.controllability.summary()}')
    lines.append('')
    lines.append(f'Observer ({design.kind}), poles ({plane}): '
                 f'{_poles_line(design.observer_poles)}')
    lines.extend(_placement_lines(design.observer_placement))
    if design.sampled is not None:
        sc = design.sampled
        lines.append(f' sampled gains (sensors {list(sc.sensors)}, period {sc.period:.6g} s, '
                     f'{len(sc.corrections)} corrections): verified; error map over one period '
                     f'has spectral radius {sc.spectral_radius:.4g} (decay {sc.decay_rate:.3g}/s, '
                     f'designed {sc.designed_rate:.3g}/s)')
    if design.reduced is not None:
        r = design.reduced
        est = [design.state_names[i] for i in r.rest]
        lines.append(f'  estimates {est} from {list(design.output_names)}; x_hat2 = L y + z, '
                     "z' = F z + G y + H u")
        for label, M, cols in (('L', r.L, design.output_names), ('F', r.F, est),
                               ('G', r.G, design.output_names), ('H', r.H, design.input_names)):
            lines.append(f' {label}:')
            lines.extend(_table(M, est, list(cols)))
    else:
        lines.append(' L:')
        lines.extend(_table(design.L, list(design.state_names), list(design.output_names)))
    if design.P is not None:
        lines.append(' P (steady-state error covariance):')
        lines.extend(_table(design.P, list(design.state_names), list(design.state_names)))
    if design.noise_gain is not None:
        parts = [f'{nm} {g:.3g}' for nm, g in zip(design.output_names, design.noise_gain)
                 if np.isfinite(g)]
        if parts:
            lines.append(' noise gain (estimate std / sensor std): ' + ', '.join(parts))
    lines.append('')
    if design.K is None:
        lines.append('Controller: none')
    else:
        lines.append(f'Controller u = K (x_d - x_hat) - Kd x_d, poles ({plane}): '
                     f'{_poles_line(design.controller_poles)}')
        lines.extend(_placement_lines(design.controller_placement))
        lines.append(' K:')
        lines.extend(_table(design.K, list(design.input_names), list(design.state_names)))
        if design.reference is not None and np.any(design.reference):
            lines.append(f' reference x_d: {np.array2string(design.reference, precision=4)}')
        lines.append('')
        lines.append(f'Closed loop poles: {_poles_line(design.closed_loop_poles)}')
        lines.append('Separation principle (eig = eig(A - BK) + observer poles): '
                     + ('ok' if design.separation_ok else 'FAILED')
                     + f' (closed-loop matrix off by {design.separation_error:.2g}; '
                     f'rounding allows {design.separation_allowed:.2g})')
        lines.append(f'Compensator poles: {_poles_line(design.compensator_poles)}')
        lines.extend(_delay_margin_lines(design, vehicle))
        lines.append('Compensator D(s), u = -D(s) y:' if not design.discrete else
                     'Compensator D(z), u = -D(z) y:')
        try:
            tf = control.ss2tf(design.compensator)
            text = str(tf).split('\n')
            lines.extend('  ' + t for t in text if t.strip() and not t.startswith(
                ('<', 'Inputs', 'Outputs')))
        except Exception:   # noqa: BLE001 - the report must not fail on the printout
            lines.append('  (transfer function not available)')
    lines.append('')
    if design.warnings:
        lines.append('Warnings:')
        lines.extend(f'  - {w}' for w in design.warnings)
    else:
        lines.append('Warnings: none')
    return '\n'.join(lines)
