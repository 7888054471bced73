# observer_ros.core.closed_loop: plant + observer + state feedback, as matrices.
"""
The closed loop of a compensator (state feedback on an estimate): matrices, separation, D(s).

The control law is seed 002's Eq. 5.109, ``u = K (x_d - x_hat) - Kd x_d``; with
``x_d = 0`` it is seed 000's ``u = -K x_hat``, and the compensator transfer
function is defined by ``u(s) = -D(s) y(s)``.

"""

import numpy as np
import scipy.linalg

from ._lazy import control
from .design import pole_placement_error, ReducedOrderDesign
from .errors import DesignError, DimensionError
from .model import as_matrix, as_vector
from .verify import match_eigenvalues

__all__ = ['closed_loop_matrix', 'closed_loop_matrices', 'error_dynamics_matrix',
           'reduced_closed_loop_matrix', 'reduced_closed_loop_matrices',
           'spectrum_match', 'separation_check', 'compensator_matrices', 'compensator_ss',
           'compensator_tf', 'compensator_poles', 'reference_input_matrix', 'tracking_residual',
           'tracking_ok', 'plant_matrices', 'separation_details', 'SEPARATION_TOL']

#: Default relative tolerance of :func:`separation_check`.
SEPARATION_TOL = 1e-6


# ---------------------------------------------------------------- argument checking


def plant_matrices(A, B, C, D=None):
    """
    Return A, B, C, D checked against each other (D zeros when None).

    Parameters
    ----------
    A, B, C : array_like
        Plant: state, input and output matrices.
    D : array_like, optional
        Feedthrough; default zeros.

    Returns
    -------
    A, B, C, D : ndarray

    Raises
    ------
    DimensionError
        A matrix of the wrong shape, named.

    """
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
    A, B, C, D = plant_matrices(A, B, C, D)
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
    A, B, C, _ = plant_matrices(A, B, C)
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
    order = match_eigenvalues(lam, want)
    matched, allowed = lam[order], bound[order]
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
    ok, cl, expected, _, _ = separation_details(A, B, C, K, L, tol, D)
    return ok, cl, expected


def separation_details(A, B, C, K, L, tol=SEPARATION_TOL, D=None):
    """
    :func:`separation_check`, also returning the largest ``|eig - expected|`` and its allowance.

    Returns
    -------
    ok, closed_loop_poles, expected
        As :func:`separation_check`.
    error : float
        The largest distance of a closed-loop eigenvalue from its expected pole.
    allowed : float
        What tol and rounding allow at that pole.

    """
    A, B, C, D = plant_matrices(A, B, C, D)
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
    A, B, C, D = plant_matrices(A, B, C, D)
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
