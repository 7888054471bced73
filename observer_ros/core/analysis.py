# observer_ros.core.analysis: observability, detectability and their duals.
"""
Observability and controllability analysis: ranks, PBH test, Gramians, decompositions.

Every function takes plain matrices (no ROS, no Plant required). The structural
decisions (rank, observable, detectable) come from an orthogonal staircase
reduction, which is far better conditioned than the rank of the observability
matrix ``[C; CA; ...; CA^(n-1)]``; that matrix is still available as :func:`obsv`
and :func:`numerical_rank` for the textbook test.

"""

from dataclasses import dataclass, field
import math
from typing import Tuple

import numpy as np
import scipy.linalg

from ._lazy import control
from .errors import DimensionError, ObserverError
from .model import as_matrix
from .verify import EIG_BOUND_FACTOR, eigenvalue_bounds, stability_status, unstable_eigenvalues

__all__ = ['obsv', 'ctrb', 'numerical_rank', 'rank_tolerance', 'PBHResult', 'pbh_test',
           'pbh_test_controllability', 'observability_gramian', 'controllability_gramian',
           'observable_decomposition', 'controllable_decomposition',
           'unobservable_eigenvalues', 'uncontrollable_eigenvalues', 'Mode',
           'ObservabilityReport', 'observability_report', 'ControllabilityReport',
           'controllability_report', 'is_observable', 'is_detectable', 'is_controllable',
           'is_stabilizable', 'is_stable_eigenvalue', 'stability_margin', 'format_complex']

_EPS = np.finfo(float).eps

#: Widening of the LAPACK/MATLAB rank tolerance n*eps*||M|| used for structural
#: decisions, to absorb the rounding already present in model data (matrices
#: typed with 4 digits, or built by a similarity transformation).
STRUCTURAL_TOL_FACTOR = 1e3

#: A state is named in a mode description when its weight in the mode's
#: eigenvector(s) is at least this fraction of the largest weight.
MODE_WEIGHT_THRESHOLD = 0.1


# ---------------------------------------------------------------- ranks


def obsv(A, C):
    """
    Return the observability matrix ``[C; C A; ...; C A^(n-1)]`` (python-control's ``obsv``).

    Parameters
    ----------
    A : (n, n) array_like
        State matrix.
    C : (p, n) array_like
        Output matrix.

    Returns
    -------
    O : (n p, n) ndarray

    """
    A = as_matrix(A, 'A', square=True)
    C = as_matrix(C, 'C', cols=A.shape[0])
    return np.asarray(control.obsv(A, C))


def ctrb(A, B):
    """
    Return the controllability matrix ``[B, A B, ..., A^(n-1) B]`` (python-control's ``ctrb``).

    Parameters
    ----------
    A : (n, n) array_like
        State matrix.
    B : (n, m) array_like
        Input matrix.

    Returns
    -------
    P : (n, n m) ndarray

    """
    A = as_matrix(A, 'A', square=True)
    B = as_matrix(B, 'B', rows=A.shape[0])
    return np.asarray(control.ctrb(A, B))


def rank_tolerance(M):
    """
    Return the default tolerance of :func:`numerical_rank`, ``max(M.shape) eps sigma_max(M)``.

    This is the LAPACK, MATLAB ``rank`` and ``numpy.linalg.matrix_rank``
    convention: singular values below the rounding error of an SVD of M are zero.

    Parameters
    ----------
    M : array_like
        A 2-D matrix.

    Returns
    -------
    tol : float

    """
    M = as_matrix(M, 'M')
    if M.size == 0:
        return 0.0
    return max(M.shape) * _EPS * float(np.linalg.norm(M, 2))


def numerical_rank(M, tol=None):
    """
    Return the rank of M by SVD: the number of singular values above ``tol``.

    Parameters
    ----------
    M : array_like
        A 2-D matrix.
    tol : float, optional
        Threshold on the singular values; default :func:`rank_tolerance`,
        ``max(M.shape) * eps * sigma_max``, relative to the largest singular
        value and the matrix size.

    Returns
    -------
    r : int

    """
    M = as_matrix(M, 'M')
    if M.size == 0:
        return 0
    s = scipy.linalg.svd(M, compute_uv=False)
    if tol is None:
        tol = max(M.shape) * _EPS * s[0]
    return int(np.sum(s > tol))


# ---------------------------------------------------------------- stability helpers


def stability_margin(A):
    """
    Return the rounding bound of a perfectly conditioned eigenvalue of A.

    ``EIG_BOUND_FACTOR n eps ||A||_2``: the stability rule of
    :mod:`observer_ros.core.verify` with kappa = 1. Verdicts on the eigenvalues of a
    matrix use :func:`~observer_ros.core.verify.eigenvalue_bounds` (each eigenvalue's
    own condition number); this scalar is for an eigenvalue known without its matrix.

    Parameters
    ----------
    A : (n, n) array_like
        State matrix.

    Returns
    -------
    margin : float

    """
    A = np.asarray(A, dtype=float)
    if not A.size:
        return EIG_BOUND_FACTOR * _EPS
    return EIG_BOUND_FACTOR * A.shape[0] * _EPS * max(float(np.linalg.norm(A, 2)), _EPS)


def is_stable_eigenvalue(lam, discrete=False, margin=1e-9):
    """
    Return True when lam is strictly stable by more than ``margin``.

    Parameters
    ----------
    lam : complex
        Eigenvalue.
    discrete : bool
        z-plane (``|z| < 1 - margin``) instead of s-plane (``Re s < -margin``).
    margin : float
        Stability margin.

    Returns
    -------
    bool

    """
    lam = complex(lam)
    if discrete:
        return abs(lam) < 1.0 - margin
    return lam.real < -margin


def _block_eigenvalues(Au, A):
    """
    Eigenvalues of a trailing staircase block Au of A and their stability bounds.

    The staircase drops couplings below its structural tolerance (about
    ``STRUCTURAL_TOL_FACTOR n eps ||A||``), so the block's eigenvalues are known to that
    perturbation times their condition number: the bound is the stability rule's with
    ``||A||`` widened by that factor. It scales with ||A|| only through eps.

    """
    return eigenvalue_bounds(Au, STRUCTURAL_TOL_FACTOR * float(np.linalg.norm(A, 1)))


def format_complex(z, digits=6):
    """
    Format a number for messages: ``5``, ``-0.6``, ``-1+2j``.

    Parameters
    ----------
    z : complex
        Number, or the observer state.
    digits : int
        Significant digits.

    Returns
    -------
    str

    """
    z = complex(z)
    scale = max(abs(z.real), abs(z.imag), 1e-300)
    re = 0.0 if abs(z.real) < 1e-12 * scale else z.real
    im = 0.0 if abs(z.imag) < 1e-12 * scale else z.imag
    if im == 0.0:
        return f'{re:.{digits}g}'
    if re == 0.0:
        return f'{im:.{digits}g}j'
    return f'{re:.{digits}g}{im:+.{digits}g}j'


def _format_pair(z, digits=6):
    z = complex(z)
    if abs(z.imag) <= 1e-12 * max(1.0, abs(z)):
        return format_complex(z.real, digits)
    return f'{format_complex(z.real, digits)}±{abs(z.imag):.{digits}g}j'


# ---------------------------------------------------------------- decompositions


def _structural_tol(A, B):
    n = A.shape[0]
    scale = max(np.linalg.norm(A, 1), np.linalg.norm(B, 1)) if B.size else np.linalg.norm(A, 1)
    return STRUCTURAL_TOL_FACTOR * max(n, B.shape[1], 1) * _EPS * float(scale)


def _staircase(A, B, tol):
    """Orthogonal controllability staircase: Q^T A Q = [[Ac, *], [0, Au]], Q^T B = [Bc; 0]."""
    n = A.shape[0]
    Q = np.eye(n)
    At = A.copy()
    k = 0
    Bk = B.copy()
    while k < n and Bk.size:
        U, s, _ = scipy.linalg.svd(Bk, full_matrices=True)
        r = int(np.sum(s > tol))
        if r == 0:
            break
        W = np.eye(n)
        W[k:, k:] = U
        At = W.T @ At @ W
        Q = Q @ W
        if k + r >= n:
            k = n
            break
        Bk = At[k + r:, k:k + r]
        k += r
    return Q, k


def controllable_decomposition(A, B, C=None, tol=None):
    """
    Kalman controllable decomposition by an orthogonal staircase (MATLAB ``ctrbf``-like).

    Parameters
    ----------
    A : (n, n) array_like
        State matrix.
    B : (n, m) array_like
        Input matrix.
    C : (p, n) array_like, optional
        Output matrix, transformed too (default: an empty 0 x n matrix).
    tol : float, optional
        Rank tolerance of each staircase step; default
        ``1e3 * max(n, m) * eps * max(||A||_1, ||B||_1)``: the LAPACK/MATLAB
        ``ctrbf`` tolerance widened by ``STRUCTURAL_TOL_FACTOR`` for rounding in
        the model data.

    Returns
    -------
    Abar, Bbar, Cbar : ndarray
        ``Abar = T^-1 A T = [[Ac, A12], [0, Auc]]``, ``Bbar = T^-1 B = [Bc; 0]``,
        ``Cbar = C T``; blocks that are zero within the tolerance are set to zero.
    T : (n, n) ndarray
        Orthogonal (``T^-1 = T^T``); its first r columns span the controllable subspace.
    r : int
        Dimension of the controllable subspace (the rank of ``ctrb(A, B)``).

    """
    A = as_matrix(A, 'A', square=True)
    n = A.shape[0]
    B = as_matrix(B, 'B', rows=n)
    C = np.zeros((0, n)) if C is None else as_matrix(C, 'C', cols=n)
    if tol is None:
        tol = _structural_tol(A, B)
    T, r = _staircase(A, B, tol)
    Abar = T.T @ A @ T
    Bbar = T.T @ B
    Abar[r:, :r] = 0.0
    Bbar[r:, :] = 0.0
    return Abar, Bbar, C @ T, T, r


def observable_decomposition(A, B=None, C=None, tol=None):
    """
    Observable decomposition in the form of seed 003 (by duality with the staircase).

    Parameters
    ----------
    A : (n, n) array_like
        State matrix.
    B : (n, m) array_like, optional
        Input matrix, transformed too (default: an empty n x 0 matrix).
    C : (p, n) array_like
        Output matrix (required).
    tol : float, optional
        Rank tolerance of each staircase step; default
        ``1e3 * max(n, p) * eps * max(||A||_inf, ||C||_inf)``: the LAPACK rank
        tolerance widened by ``STRUCTURAL_TOL_FACTOR`` (the staircase of the dual).

    Returns
    -------
    Abar, Bbar, Cbar : ndarray
        ``Abar = T^-1 A T = [[Ao, 0], [A21, Aobar]]``, ``Bbar = T^-1 B = [Bo; Bobar]``,
        ``Cbar = C T = [Co, 0]``, with (Ao, Co) observable.
    T : (n, n) ndarray
        Orthogonal; its last n - m columns span the unobservable subspace (the
        null space of ``obsv(A, C)``), the first m its orthogonal complement.
    m : int
        Rank of the observability matrix.

    """
    A = as_matrix(A, 'A', square=True)
    n = A.shape[0]
    if C is None:
        raise DimensionError('C is required for the observable decomposition')
    C = as_matrix(C, 'C', cols=n)
    B = np.zeros((n, 0)) if B is None else as_matrix(B, 'B', rows=n)
    if tol is None:
        tol = _structural_tol(A.T, C.T)
    T, m = _staircase(A.T, C.T, tol)
    Abar = T.T @ A @ T
    Cbar = C @ T
    Abar[:m, m:] = 0.0
    Cbar[:, m:] = 0.0
    return Abar, T.T @ B, Cbar, T, m


def unobservable_eigenvalues(A, C, tol=None):
    """
    Return the eigenvalues of the unobservable block Aobar of :func:`observable_decomposition`.

    Parameters
    ----------
    A : (n, n) array_like
        State matrix.
    C : (p, n) array_like
        Output matrix.
    tol : float, optional
        Staircase tolerance.

    Returns
    -------
    ndarray of complex
        Empty when (A, C) is observable.

    """
    Abar, _, _, _, m = observable_decomposition(A, None, C, tol)
    return np.linalg.eigvals(Abar[m:, m:]) if m < Abar.shape[0] else np.zeros(0, complex)


def uncontrollable_eigenvalues(A, B, tol=None):
    """
    Return the eigenvalues of the uncontrollable block Auc of :func:`controllable_decomposition`.

    Parameters
    ----------
    A : (n, n) array_like
        State matrix.
    B : (n, m) array_like
        Input matrix.
    tol : float, optional
        Staircase tolerance.

    Returns
    -------
    ndarray of complex
        Empty when (A, B) is controllable.

    """
    Abar, _, _, _, r = controllable_decomposition(A, B, None, tol)
    return np.linalg.eigvals(Abar[r:, r:]) if r < Abar.shape[0] else np.zeros(0, complex)


# ---------------------------------------------------------------- PBH


@dataclass(frozen=True)
class PBHResult:
    """
    One distinct eigenvalue of A and its PBH (Popov-Belevitch-Hautus) rank test.

    ``rank`` is the numerical rank of ``[A - lambda I; C]`` (observability) or
    ``[A - lambda I, B]`` (controllability); the mode passes when it equals n.

    """

    eigenvalue: complex
    multiplicity: int
    rank: int
    n: int
    passed: bool
    stable: bool
    min_singular_value: float
    tol: float


def _clusters(eigs, tol_rel=1e-5):
    """Group eigenvalues closer than tol_rel * max(1, |lambda|) (numerical multiplicity)."""
    groups = []
    for i, lam in enumerate(eigs):
        for g in groups:
            centre = np.mean(eigs[g])
            if abs(lam - centre) <= tol_rel * max(1.0, abs(centre)):
                g.append(i)
                break
        else:
            groups.append([i])
    return groups


def _pbh(A, X, stack, discrete, tol):
    n = A.shape[0]
    if n == 0:
        return []
    lam, vl, vr = scipy.linalg.eig(A, left=True, right=True)
    scale = max(float(np.linalg.norm(A, 2)), float(np.linalg.norm(X, 2)) if X.size else 0.0,
                _EPS)
    results = []
    for g in _clusters(lam):
        centre = complex(np.mean(lam[g]))   # the mean of a cluster is well conditioned
        if abs(centre.imag) <= 1e-12 * max(1.0, abs(centre)):
            centre = complex(centre.real, 0.0)
        elif centre.imag < 0:
            continue   # report each conjugate pair once, by its member with Im > 0
        kappa = max(1.0 / max(abs(np.vdot(vl[:, i], vr[:, i])), _EPS) for i in g)
        kappa = min(kappa, 1.0 / np.sqrt(_EPS))
        M = A - centre * np.eye(n)
        M = np.vstack([M, X]) if stack == 'rows' else np.hstack([M, X])
        s = scipy.linalg.svd(M, compute_uv=False)
        t = tol if tol is not None else 10.0 * max(M.shape) * _EPS * scale * kappa
        rank = int(np.sum(s > t))
        bound = EIG_BOUND_FACTOR * n * _EPS * float(np.linalg.norm(A, 2)) * kappa
        results.append(PBHResult(centre, len(g), rank, n, rank == n,
                                 stability_status(centre, bound, discrete) == 'stable',
                                 float(s[min(n, len(s)) - 1]), float(t)))
    return results


def pbh_test(A, C, discrete=False, tol=None):
    """
    PBH observability test: for each distinct eigenvalue, the rank of ``[A - lambda I; C]``.

    Parameters
    ----------
    A : (n, n) array_like
        State matrix.
    C : (p, n) array_like
        Output matrix.
    discrete : bool
        Classify stability in the z-plane.
    tol : float, optional
        Rank threshold; default ``10 (n + p) eps max(||A||, ||C||) kappa(lambda)``,
        the rounding error of the eigenvalue (kappa is its condition number,
        from the left and right eigenvectors; at most 1/sqrt(eps)).

    Returns
    -------
    list of PBHResult
        One per distinct eigenvalue (a complex pair appears once, with Im > 0);
        eigenvalues closer than 1e-5 relative are one eigenvalue of higher
        multiplicity, tested at their mean.

    """
    A = as_matrix(A, 'A', square=True)
    C = as_matrix(C, 'C', cols=A.shape[0])
    return _pbh(A, C, 'rows', discrete, tol)


def pbh_test_controllability(A, B, discrete=False, tol=None):
    """
    PBH controllability test: for each distinct eigenvalue, the rank of ``[A - lambda I, B]``.

    Parameters
    ----------
    A : (n, n) array_like
        State matrix.
    B : (n, m) array_like
        Input matrix.
    discrete : bool
        Classify stability in the z-plane.
    tol : float, optional
        Rank threshold (see :func:`pbh_test`).

    Returns
    -------
    list of PBHResult

    """
    A = as_matrix(A, 'A', square=True)
    B = as_matrix(B, 'B', rows=A.shape[0])
    return _pbh(A, B, 'cols', discrete, tol)


# ---------------------------------------------------------------- Gramians


def observability_gramian(A, C, horizon=None, discrete=False):
    """
    Return the observability Gramian of (A, C), finite or infinite horizon.

    Parameters
    ----------
    A : (n, n) array_like
        State matrix.
    C : (p, n) array_like
        Output matrix.
    horizon : float or int, optional
        Continuous time: the length t > 0 of ``W(t) = int_0^t e^{A^T s} C^T C e^{A s} ds``,
        computed by Van Loan's (1978) matrix exponential over a step h with
        ||A|| h <= 1 and doubling to t (stable for long horizons). Discrete time: the
        number of steps N >= 1 of ``W = sum_{k<N} (A^T)^k C^T C A^k``.
        None: the infinite-horizon Gramian, from the Lyapunov equation
        ``A^T W + W A = -C^T C`` (or ``A^T W A - W = -C^T C``), which exists only
        for a stable A.
    discrete : bool
        Discrete-time system.

    Returns
    -------
    W : (n, n) ndarray
        Symmetric positive semi-definite; nonsingular exactly when (A, C) is observable.

    """
    A = as_matrix(A, 'A', square=True)
    n = A.shape[0]
    C = as_matrix(C, 'C', cols=n)
    Q = C.T @ C
    if horizon is None:
        bad = unstable_eigenvalues(A, discrete)
        if bad:
            raise ObserverError(
                f'the infinite-horizon Gramian needs a stable A; A has the eigenvalue '
                f'{format_complex(bad[0][0])} ({bad[0][1]}); give a finite horizon')
        if discrete:
            W = scipy.linalg.solve_discrete_lyapunov(A.T, Q)
        else:
            W = scipy.linalg.solve_continuous_lyapunov(A.T, -Q)
        return (W + W.T) / 2.0
    if discrete:
        steps = int(horizon)
        if steps != horizon or steps < 1:
            raise ObserverError(
                f'horizon must be a whole number of steps >= 1 for a discrete system; '
                f'got {horizon!r}')
        W = np.zeros((n, n))
        Ak = np.eye(n)
        for _ in range(steps):
            W += Ak.T @ Q @ Ak
            Ak = A @ Ak
        return (W + W.T) / 2.0
    t = float(horizon)
    if not (t > 0.0 and np.isfinite(t)):
        raise ObserverError(f'horizon must be positive and finite; got {horizon!r}')
    # Van Loan on a short step h (||A|| h <= 1, where e^{-A^T h} cannot swamp the
    # result), then doubling W(2h) = W(h) + e^{A^T h} W(h) e^{A h}: sums of PSD terms.
    norm = float(np.linalg.norm(A, 1)) * t
    k = max(0, int(math.ceil(math.log2(norm)))) if norm > 1.0 else 0
    h = t / 2.0 ** k
    M = np.zeros((2 * n, 2 * n))
    M[:n, :n] = -A.T
    M[:n, n:] = Q
    M[n:, n:] = A
    E = scipy.linalg.expm(M * h)
    Phi = E[n:, n:]
    W = Phi.T @ E[:n, n:]
    for _ in range(k):
        W = W + Phi.T @ W @ Phi
        Phi = Phi @ Phi
    return (W + W.T) / 2.0


def controllability_gramian(A, B, horizon=None, discrete=False):
    """
    Return the controllability Gramian of (A, B): the observability Gramian of (A^T, B^T).

    Parameters
    ----------
    A : (n, n) array_like
        State matrix.
    B : (n, m) array_like
        Input matrix.
    horizon : float or int, optional
        See :func:`observability_gramian`.
    discrete : bool
        Discrete-time system.

    Returns
    -------
    W : (n, n) ndarray
        ``int_0^t e^{A s} B B^T e^{A^T s} ds`` (or its sum / infinite-horizon limit).

    """
    A = as_matrix(A, 'A', square=True)
    B = as_matrix(B, 'B', rows=A.shape[0])
    return observability_gramian(A.T, B.T, horizon, discrete)


# ---------------------------------------------------------------- reports


@dataclass(frozen=True)
class Mode:
    """
    An unobservable (or uncontrollable) mode and the states it lives on.

    ``eigenvalue`` is real or the member with Im > 0 of a conjugate pair;
    ``weights`` are the normalised row norms of an orthonormal basis of the
    mode's generalised eigenspace (for an uncontrollable mode: of the left one,
    i.e. the combinations of states the input cannot move) and ``states`` the
    names with weight >= ``MODE_WEIGHT_THRESHOLD`` (0.1).

    """

    eigenvalue: complex
    multiplicity: int
    status: str                       # stable | unstable | marginally stable
    states: Tuple[str, ...]
    weights: Tuple[float, ...]

    @property
    def stable(self):
        """Return True when the mode decays."""
        return self.status == 'stable'

    def describe(self):
        """Return e.g. ``"eigenvalue 5 (unstable): x3"``."""
        complex_pair = abs(complex(self.eigenvalue).imag) > 0.0
        word = 'eigenvalues' if complex_pair else 'eigenvalue'
        mult = f'multiplicity {self.multiplicity}, ' if self.multiplicity > 1 else ''
        return (f'{word} {_format_pair(self.eigenvalue)} ({mult}{self.status}): '
                f'{", ".join(self.states)}')


def _names(state_names, n):
    if state_names is None or len(state_names) == 0:
        return tuple(f'x{i + 1}' for i in range(n))
    names = tuple(state_names)
    if len(names) != n:
        raise DimensionError(f'state_names has {len(names)} names; expected {n}')
    return names


def _modes(Abar, T, m, names, discrete, A):
    """Describe the eigenvalues of the trailing block Abar[m:, m:] (basis T[:, m:])."""
    n = Abar.shape[0]
    if m >= n:
        return []
    Au = Abar[m:, m:]
    T2 = T[:, m:]
    lam, bound = _block_eigenvalues(Au, A)
    modes = []
    for g in _clusters(lam):
        centre = complex(np.mean(lam[g]))
        if abs(centre.imag) <= 1e-12 * max(1.0, abs(centre)):
            centre = complex(centre.real, 0.0)
        elif centre.imag < 0:
            continue
        # generalised eigenspace: null space of (Au - lambda I)^k, k the multiplicity
        k = len(g)
        M = np.linalg.matrix_power(Au - centre * np.eye(n - m), k)
        _, _, vh = scipy.linalg.svd(M)
        basis = vh[-k:].conj().T
        V = T2 @ basis
        w = np.sqrt(np.sum(np.abs(V) ** 2, axis=1))
        w = w / max(float(np.max(w)), _EPS)
        states = tuple(nm for nm, wi in zip(names, w) if wi >= MODE_WEIGHT_THRESHOLD)
        status = stability_status(centre, float(np.max(bound[g])), discrete)
        modes.append(Mode(centre, len(g), status, states, tuple(float(x) for x in w)))
    return modes


@dataclass(frozen=True)
class ObservabilityReport:
    """
    Observability and detectability of (A, C), with the unobservable modes named.

    ``rank`` is the dimension of the observable subspace (the rank of the
    observability matrix, from the orthogonal staircase); ``pbh`` the per-eigenvalue
    PBH test; ``unobservable_modes`` human-readable lines such as
    ``"eigenvalue 5 (unstable): x3"``.

    """

    n: int
    rank: int
    observable: bool
    detectable: bool
    discrete: bool
    state_names: Tuple[str, ...]
    unobservable_eigenvalues: np.ndarray
    pbh: Tuple[PBHResult, ...]
    modes: Tuple[Mode, ...]
    unobservable_modes: Tuple[str, ...] = field(default=())

    def summary(self):
        """One line: observable / detectable / undetectable."""
        if self.observable:
            return f'observable (rank {self.rank} of {self.n})'
        verdict = 'detectable' if self.detectable else 'NOT detectable'
        return (f'unobservable (rank {self.rank} of {self.n}), {verdict}; '
                + '; '.join(self.unobservable_modes))


def observability_report(A, C, state_names=None, discrete=False, tol=None):
    """
    Report the observability, detectability and named unobservable modes of (A, C).

    Parameters
    ----------
    A : (n, n) array_like
        State matrix.
    C : (p, n) array_like
        Output matrix.
    state_names : sequence of str, optional
        Names used in the mode descriptions (default x1..xn).
    discrete : bool
        Stability in the z-plane (``|z| < 1``) instead of ``Re s < 0``.
    tol : float, optional
        Staircase rank tolerance (see :func:`observable_decomposition`).

    Returns
    -------
    ObservabilityReport
        Detectable means every unobservable eigenvalue is stable by the stability
        rule of :mod:`observer_ros.core.verify` (its bound widened to the staircase's
        structural tolerance).

    """
    A = as_matrix(A, 'A', square=True)
    n = A.shape[0]
    C = as_matrix(C, 'C', cols=n)
    names = _names(state_names, n)
    Abar, _, _, T, m = observable_decomposition(A, None, C, tol)
    modes = _modes(Abar, T, m, names, discrete, A)
    ueigs, ubound = _block_eigenvalues(Abar[m:, m:], A) if m < n else \
        (np.zeros(0, complex), np.zeros(0))
    detectable = all(stability_status(lam, b, discrete) == 'stable'
                     for lam, b in zip(ueigs, ubound))
    return ObservabilityReport(n, m, m == n, detectable, bool(discrete), names, ueigs,
                               tuple(pbh_test(A, C, discrete)), tuple(modes),
                               tuple(md.describe() for md in modes))


@dataclass(frozen=True)
class ControllabilityReport:
    """
    Controllability and stabilizability of (A, B), with the uncontrollable modes named.

    An uncontrollable mode is named by the states in its left eigenvector: the
    combination of states that evolves as ``e^{lambda t}`` whatever the input.

    """

    n: int
    rank: int
    controllable: bool
    stabilizable: bool
    discrete: bool
    state_names: Tuple[str, ...]
    uncontrollable_eigenvalues: np.ndarray
    pbh: Tuple[PBHResult, ...]
    modes: Tuple[Mode, ...]
    uncontrollable_modes: Tuple[str, ...] = field(default=())

    def summary(self):
        """One line: controllable / stabilizable / not stabilizable."""
        if self.controllable:
            return f'controllable (rank {self.rank} of {self.n})'
        verdict = 'stabilizable' if self.stabilizable else 'NOT stabilizable'
        return (f'uncontrollable (rank {self.rank} of {self.n}), {verdict}; '
                + '; '.join(self.uncontrollable_modes))


def controllability_report(A, B, state_names=None, discrete=False, tol=None):
    """
    Report the controllability, stabilizability and named uncontrollable modes of (A, B).

    Computed as the observability report of the dual pair (A^T, B^T).

    Parameters
    ----------
    A : (n, n) array_like
        State matrix.
    B : (n, m) array_like
        Input matrix.
    state_names : sequence of str, optional
        State names for messages (default x1..xn).
    discrete : bool
        Discrete time: z-plane instead of s-plane.
    tol : float, optional
        Staircase rank tolerance.

    Returns
    -------
    ControllabilityReport

    """
    A = as_matrix(A, 'A', square=True)
    n = A.shape[0]
    B = as_matrix(B, 'B', rows=n)
    dual = observability_report(A.T, B.T, state_names, discrete, tol)
    pbh = tuple(pbh_test_controllability(A, B, discrete))
    return ControllabilityReport(n, dual.rank, dual.observable, dual.detectable,
                                 bool(discrete), dual.state_names,
                                 dual.unobservable_eigenvalues, pbh, dual.modes,
                                 dual.unobservable_modes)


def is_observable(A, C):
    """Return True when (A, C) is observable (staircase rank n)."""
    return observable_decomposition(A, None, C)[4] == as_matrix(A, 'A', square=True).shape[0]


def is_controllable(A, B):
    """Return True when (A, B) is controllable (staircase rank n)."""
    return controllable_decomposition(A, B)[4] == as_matrix(A, 'A', square=True).shape[0]


def is_detectable(A, C, discrete=False):
    """Return True when every unobservable eigenvalue of (A, C) is strictly stable."""
    return observability_report(A, C, discrete=discrete).detectable


def is_stabilizable(A, B, discrete=False):
    """Return True when every uncontrollable eigenvalue of (A, B) is strictly stable."""
    A = as_matrix(A, 'A', square=True)
    B = as_matrix(B, 'B', rows=A.shape[0])
    return observability_report(A.T, B.T, discrete=discrete).detectable
