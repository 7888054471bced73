# observer_ros.core.analysis: observability, detectability and their duals.
"""
Observability and controllability analysis: ranks, PBH test, decompositions, reports.

Every function takes plain matrices (no ROS, no Plant required).

**The decision** (stated here once; the reports, the PBH lines, the decompositions, the
pole count of a design and the sensor advisor all read it). A mode of A is unobservable
through C when the PBH matrix ``[A - lambda I; C]`` loses rank at its eigenvalue. The test
is made on the plant *scaled to itself*: A balanced by a diagonal similarity (states in
any units), divided by its norm, and each row of C divided by its own norm (sensors in any
units); then ``sigma_min([A_s - lambda I; C_s]) <= PBH_TOL_FACTOR (n + p) eps kappa``,
``kappa`` being the eigenvalue's condition number (at most ``1 / sqrt(eps)``): the mode is
unobservable to within the rounding with which its eigenvalue is known. Eigenvalues whose
rounding disks overlap form one (numerically multiple) eigenvalue. For a multiple
eigenvalue the unobservable part of its generalized eigenspace is followed along its
Jordan chains (``v`` with ``C v = 0`` and ``(A - lambda I) v`` in the part found so far),
each step the same scaled test. The unobservable subspace is the span of those parts; the
observable decomposition is an orthogonal basis split along it. A staircase (Krylov)
reduction is not used: its steps mix the time scales of a stiff plant (eigenvalues from
1e-3 to 1e5), where a coupling of 1e-5 it cannot drop says nothing about observability.
The textbook rank of ``obsv(A, C)`` is still available as :func:`obsv` and
:func:`numerical_rank`.

An unobservable mode's stability is its eigenvalue's verdict by the stability rule of
:mod:`observer_ros.core.verify`; detectable means every unobservable mode is stable.

"""

from dataclasses import dataclass, field
import math
from typing import Tuple

import numpy as np
import scipy.linalg

from ._lazy import control
from .errors import DimensionError
from .model import as_matrix
from .verify import EIG_BOUND_FACTOR, eigenvalue_bounds, stability_status

__all__ = ['obsv', 'ctrb', 'numerical_rank', 'rank_tolerance', 'PBHResult', 'pbh_test',
           'pbh_test_controllability', 'observable_decomposition', 'controllable_decomposition',
           'unobservable_eigenvalues', 'uncontrollable_eigenvalues', 'Mode',
           'ObservabilityReport', 'observability_report', 'ControllabilityReport',
           'controllability_report', 'is_observable', 'is_detectable', 'is_controllable',
           'is_stabilizable', 'is_stable_eigenvalue', 'stability_margin', 'format_complex',
           'PBH_TOL_FACTOR']

_EPS = np.finfo(float).eps

#: Constant of the decision's threshold ``PBH_TOL_FACTOR (n + p) eps kappa`` on the scaled
#: PBH matrix (the rounding error of an eigenvalue, as in ``core/verify.py``).
PBH_TOL_FACTOR = 10.0

#: Eigenvalues closer than this fraction of ``||A||`` are never told apart when their
#: rounding disks overlap (a defective eigenvalue splits by ``eps^(1/k) ||A||``).
CLUSTER_LIMIT = 1e-3

#: A state is named in a mode description when its weight in the mode's
#: eigenvector(s) is at least this fraction of the largest weight.
MODE_WEIGHT_THRESHOLD = 0.1

_KAPPA_CAP = 1.0 / math.sqrt(_EPS)


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

# ---------------------------------------------------------------- the decision


@dataclass(frozen=True)
class PBHResult:
    """
    One distinct eigenvalue of A and its PBH (Popov-Belevitch-Hautus) rank test.

    ``rank`` is the numerical rank of ``[A - lambda I; C]`` (observability) or
    ``[A - lambda I, B]`` (controllability) on the scaled plant (see the module's
    decision); the mode passes when it equals n. ``min_singular_value`` and ``tol`` are
    relative (on the scaled matrix). ``unobserved`` is the dimension of the mode's
    unobservable (uncontrollable) part, its Jordan chains included; ``stable`` its
    eigenvalue's verdict by the stability rule.

    """

    eigenvalue: complex
    multiplicity: int
    rank: int
    n: int
    passed: bool
    stable: bool
    min_singular_value: float
    tol: float
    unobserved: int = 0
    status: str = 'stable'


@dataclass(frozen=True)
class _Structure:
    """The decision for (A, C): per distinct eigenvalue, and the unobservable subspace."""

    pbh: Tuple[PBHResult, ...]
    bases: Tuple[np.ndarray, ...]       # per failing eigenvalue: its unobservable part
    failing: Tuple[int, ...]            # indices into pbh of the failing eigenvalues
    V: np.ndarray                       # orthonormal basis of the unobservable subspace
    Q: np.ndarray                       # orthogonal: [complement, V]


def _scaled(A, C):
    """Return A balanced and normalised, C in its coordinates with unit rows, the scaling."""
    n = A.shape[0]
    if n and np.any(A):
        _, (d, _) = scipy.linalg.matrix_balance(A, permute=False, separate=True)
    else:
        d = np.ones(n)
    As = A * (1.0 / d)[:, None] * d[None, :]
    a = float(np.linalg.norm(As, 2)) if n else 0.0
    a = a if a > 0.0 else 1.0
    Cs = C * d[None, :]
    rows = np.linalg.norm(Cs, axis=1) if Cs.size else np.zeros(C.shape[0])
    Cs = Cs[rows > 0.0] / rows[rows > 0.0, None]
    return As / a, Cs, d, a


def _clusters(lam, radius):
    """Group eigenvalues whose rounding disks overlap (at most CLUSTER_LIMIT apart)."""
    N = lam.size
    parent = list(range(N))

    def root(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for i in range(N):
        for j in range(i + 1, N):
            gap = abs(lam[i] - lam[j])
            if gap == 0.0 or gap <= min(radius[i] + radius[j], CLUSTER_LIMIT):
                parent[root(i)] = root(j)
    groups = {}
    for i in range(N):
        groups.setdefault(root(i), []).append(i)
    return sorted(groups.values(), key=lambda g: g[0])


def _null(M, tol, limit):
    """Smallest right singular vectors of M with singular value <= tol (at most limit)."""
    _, s, vh = scipy.linalg.svd(M)
    s = np.concatenate([s, np.zeros(max(0, M.shape[1] - s.size))])
    rank = int(np.sum(s > tol))
    keep = min(M.shape[1] - rank, limit)
    return rank, float(s[M.shape[1] - 1]), vh[M.shape[1] - keep:].conj().T


def _orth(V):
    """Orthonormal basis of the columns of V (real)."""
    if V.shape[1] == 0:
        return V
    U, s, _ = scipy.linalg.svd(V, full_matrices=False)
    return U[:, :int(np.sum(s > 1e-8 * s[0]))]


def _structure(A, C, discrete, tol=None):
    """Return the decision of this module for (A, C); see its docstring."""
    n = A.shape[0]
    if n == 0:
        return _Structure((), (), (), np.zeros((0, 0)), np.eye(0))
    As, Cs, d, a = _scaled(A, C)
    p = Cs.shape[0]
    lam, vl, vr = scipy.linalg.eig(As, left=True, right=True)
    dots = np.abs(np.sum(vl.conj() * vr, axis=0))
    kappa = 1.0 / np.maximum(dots, _EPS)
    radius = EIG_BOUND_FACTOR * n * _EPS * kappa
    _, bound = eigenvalue_bounds(A)
    results, bases, failing = [], [], []
    eye = np.eye(n)
    for g in _clusters(lam, radius):
        centre = complex(np.mean(lam[g]))
        if abs(centre.imag) <= max(float(np.max(radius[g])), 1e-14 * abs(centre)):
            centre = complex(centre.real, 0.0)
        elif centre.imag < 0:
            continue   # each conjugate pair once, by its member with Im > 0
        k = len(g)
        t = tol if tol is not None else \
            PBH_TOL_FACTOR * (n + p) * _EPS * min(float(np.max(kappa[g])), _KAPPA_CAP)
        M = As - centre * eye if centre.imag else As - centre.real * eye
        rank, smin, basis = _null(np.vstack([M, Cs]), t, k)
        while 0 < basis.shape[1] < k:
            P = eye - basis @ basis.conj().T
            _, _, wider = _null(np.vstack([P @ M, Cs]), t, k)
            if wider.shape[1] <= basis.shape[1]:
                break
            basis = wider
        value = centre * a
        status = stability_status(value, float(np.max(bound[g])), discrete)
        if basis.shape[1]:
            failing.append(len(results))
            bases.append(_orth_complex(basis * d[:, None]))
        results.append(PBHResult(value, k, rank, n, basis.shape[1] == 0, status == 'stable',
                                 smin, float(t), basis.shape[1], status))
    parts = [np.hstack([b.real, b.imag]) if np.any(b.imag) else b.real for b in bases]
    V = _orth(np.hstack(parts)) if parts else np.zeros((n, 0))
    Qfull, _ = scipy.linalg.qr(V, mode='full') if V.shape[1] else (eye, None)
    k = V.shape[1]
    Q = np.hstack([Qfull[:, k:], Qfull[:, :k]])
    return _Structure(tuple(results), tuple(bases), tuple(failing), Q[:, n - k:], Q)


def _orth_complex(B):
    """Orthonormal (complex) basis of the columns of B, in the original coordinates."""
    U, s, _ = scipy.linalg.svd(B, full_matrices=False)
    return U[:, :max(1, int(np.sum(s > 1e-8 * s[0])))]


# ---------------------------------------------------------------- decompositions


def _decompose(A, C, tol, discrete=False):
    """Q^T A Q = [[Ao, 0], [A21, Aobar]], C Q = [Co, 0]; the rank; the decision."""
    s = _structure(A, C, discrete, tol)
    Q = s.Q
    m = A.shape[0] - s.V.shape[1]
    Abar = Q.T @ A @ Q
    Cbar = C @ Q
    Abar[:m, m:] = 0.0
    Cbar[:, m:] = 0.0
    return Abar, Cbar, Q, m, s


def controllable_decomposition(A, B, C=None, tol=None):
    """
    Kalman controllable decomposition by an orthogonal transformation (MATLAB ``ctrbf``-like).

    Parameters
    ----------
    A : (n, n) array_like
        State matrix.
    B : (n, m) array_like
        Input matrix.
    C : (p, n) array_like, optional
        Output matrix, transformed too (default: an empty 0 x n matrix).
    tol : float, optional
        Threshold of the decision on the scaled PBH matrix (see the module's docstring);
        default ``PBH_TOL_FACTOR (n + m) eps kappa``.

    Returns
    -------
    Abar, Bbar, Cbar : ndarray
        ``Abar = T^-1 A T = [[Ac, A12], [0, Auc]]``, ``Bbar = T^-1 B = [Bc; 0]``,
        ``Cbar = C T``; blocks that are zero by the decision are set to zero.
    T : (n, n) ndarray
        Orthogonal (``T^-1 = T^T``); its first r columns span the controllable subspace.
    r : int
        Dimension of the controllable subspace (the rank of ``ctrb(A, B)``).

    """
    A = as_matrix(A, 'A', square=True)
    n = A.shape[0]
    B = as_matrix(B, 'B', rows=n)
    C = np.zeros((0, n)) if C is None else as_matrix(C, 'C', cols=n)
    AbarT, BbarT, T, r, _ = _decompose(A.T, B.T, tol)
    return AbarT.T, BbarT.T, C @ T, T, r


def observable_decomposition(A, B=None, C=None, tol=None):
    """
    Observable decomposition in the form of seed 003, along the module's decision.

    Parameters
    ----------
    A : (n, n) array_like
        State matrix.
    B : (n, m) array_like, optional
        Input matrix, transformed too (default: an empty n x 0 matrix).
    C : (p, n) array_like
        Output matrix (required).
    tol : float, optional
        Threshold of the decision on the scaled PBH matrix (see the module's docstring).

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
    Abar, Cbar, T, m, _ = _decompose(A, C, tol)
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
        Threshold of the decision (see :func:`observable_decomposition`).

    Returns
    -------
    ndarray of complex
        Each unobservable eigenvalue of A once per dimension of its unobservable part
        (the eigenvalues of Aobar, computed from A itself); empty when (A, C) is
        observable.

    """
    A = as_matrix(A, 'A', square=True)
    C = as_matrix(C, 'C', cols=A.shape[0])
    return _hidden_eigenvalues(_structure(A, C, False, tol))


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
        Threshold of the decision.

    Returns
    -------
    ndarray of complex
        Empty when (A, B) is controllable.

    """
    A = as_matrix(A, 'A', square=True)
    B = as_matrix(B, 'B', rows=A.shape[0])
    return _hidden_eigenvalues(_structure(A.T, B.T, False, tol))


def _hidden_eigenvalues(structure):
    """Each failing eigenvalue once per dimension of its hidden part (pairs both ways)."""
    out = []
    for i in structure.failing:
        res = structure.pbh[i]
        z = complex(res.eigenvalue)
        out += [z] * res.unobserved
        if z.imag:
            out += [z.conjugate()] * res.unobserved
    return np.array(out, dtype=complex)


# ---------------------------------------------------------------- PBH


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
        Threshold on the scaled matrix; default the module's decision,
        ``PBH_TOL_FACTOR (n + p) eps kappa(lambda)``.

    Returns
    -------
    list of PBHResult
        One per distinct eigenvalue (a complex pair appears once, with Im > 0);
        eigenvalues within each other's rounding are one eigenvalue of higher
        multiplicity, tested at their mean.

    """
    A = as_matrix(A, 'A', square=True)
    C = as_matrix(C, 'C', cols=A.shape[0])
    return list(_structure(A, C, discrete, tol).pbh)


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
        Threshold (see :func:`pbh_test`).

    Returns
    -------
    list of PBHResult

    """
    A = as_matrix(A, 'A', square=True)
    B = as_matrix(B, 'B', rows=A.shape[0])
    return list(_structure(A.T, B.T, discrete, tol).pbh)


# ---------------------------------------------------------------- reports


@dataclass(frozen=True)
class Mode:
    """
    An unobservable (or uncontrollable) mode and the states it lives on.

    ``eigenvalue`` is real or the member with Im > 0 of a conjugate pair;
    ``multiplicity`` the dimension of its unobservable part; ``weights`` are the
    normalised row norms of an orthonormal basis of that part (for an uncontrollable
    mode: of the left one, i.e. the combinations of states the input cannot move) and
    ``states`` the names with weight >= ``MODE_WEIGHT_THRESHOLD`` (0.1).

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


def _modes(structure, names):
    """Describe the failing eigenvalues of a decision (their unobservable parts)."""
    modes = []
    for i, basis in zip(structure.failing, structure.bases):
        res = structure.pbh[i]
        w = np.sqrt(np.sum(np.abs(basis) ** 2, axis=1))
        w = w / max(float(np.max(w)), _EPS)
        states = tuple(nm for nm, wi in zip(names, w) if wi >= MODE_WEIGHT_THRESHOLD)
        modes.append(Mode(res.eigenvalue, res.unobserved, res.status, states,
                          tuple(float(x) for x in w)))
    return modes


@dataclass(frozen=True)
class ObservabilityReport:
    """
    Observability and detectability of (A, C), with the unobservable modes named.

    ``rank`` is the dimension of the observable subspace (the rank of the
    observability matrix, by the module's decision); ``pbh`` the per-eigenvalue
    PBH test, the same decision; ``unobservable_modes`` human-readable lines such as
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
        Threshold of the decision (see :func:`observable_decomposition`).

    Returns
    -------
    ObservabilityReport
        Detectable means every unobservable mode is stable by the stability rule of
        :mod:`observer_ros.core.verify` (its eigenvalue of A). The PBH lines, the rank
        and the modes are one decision: a failing PBH line is exactly an unobservable
        mode.

    """
    A = as_matrix(A, 'A', square=True)
    n = A.shape[0]
    C = as_matrix(C, 'C', cols=n)
    names = _names(state_names, n)
    _, _, _, m, s = _decompose(A, C, tol, discrete)
    modes = _modes(s, names)
    ueigs = _hidden_eigenvalues(s)
    detectable = all(md.stable for md in modes)
    return ObservabilityReport(n, m, m == n, detectable, bool(discrete), names, ueigs,
                               s.pbh, tuple(modes), tuple(md.describe() for md in modes))


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
        Threshold of the decision.

    Returns
    -------
    ControllabilityReport

    """
    A = as_matrix(A, 'A', square=True)
    n = A.shape[0]
    B = as_matrix(B, 'B', rows=n)
    dual = observability_report(A.T, B.T, state_names, discrete, tol)
    return ControllabilityReport(n, dual.rank, dual.observable, dual.detectable,
                                 bool(discrete), dual.state_names,
                                 dual.unobservable_eigenvalues, dual.pbh, dual.modes,
                                 dual.unobservable_modes)


def is_observable(A, C):
    """Return True when (A, C) is observable (the module's decision)."""
    return observable_decomposition(A, None, C)[4] == as_matrix(A, 'A', square=True).shape[0]


def is_controllable(A, B):
    """Return True when (A, B) is controllable (the module's decision)."""
    return controllable_decomposition(A, B)[4] == as_matrix(A, 'A', square=True).shape[0]


def is_detectable(A, C, discrete=False):
    """Return True when every unobservable eigenvalue of (A, C) is strictly stable."""
    return observability_report(A, C, discrete=discrete).detectable


def is_stabilizable(A, B, discrete=False):
    """Return True when every uncontrollable eigenvalue of (A, B) is strictly stable."""
    A = as_matrix(A, 'A', square=True)
    B = as_matrix(B, 'B', rows=A.shape[0])
    return observability_report(A.T, B.T, discrete=discrete).detectable
