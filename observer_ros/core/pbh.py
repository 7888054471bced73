# observer_ros.core.pbh: the observability decision, by the PBH test on the scaled plant.
"""
The decision of observability (controllability by duality) per eigenvalue.

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

An unobservable mode's stability is its eigenvalue's verdict by the stability rule of
:mod:`observer_ros.core.verify`. :mod:`observer_ros.core.analysis` builds the
decompositions and the reports on :func:`pbh_decision`.

"""

from dataclasses import dataclass
import math
from typing import Tuple

import numpy as np
import scipy.linalg

from .model import as_matrix
from .verify import EIG_BOUND_FACTOR, eigenvalue_bounds, stability_status

__all__ = ['PBHResult', 'PBHDecision', 'pbh_decision', 'pbh_test', 'pbh_test_controllability',
           'hidden_eigenvalues', 'PBH_TOL_FACTOR', 'CLUSTER_LIMIT']

_EPS = np.finfo(float).eps

#: Constant of the decision's threshold ``PBH_TOL_FACTOR (n + p) eps kappa`` on the scaled
#: PBH matrix (the rounding error of an eigenvalue, as in ``core/verify.py``).
PBH_TOL_FACTOR = 10.0

#: Eigenvalues closer than this fraction of ``||A||`` are never told apart when their
#: rounding disks overlap (a defective eigenvalue splits by ``eps^(1/k) ||A||``).
CLUSTER_LIMIT = 1e-3

_KAPPA_CAP = 1.0 / math.sqrt(_EPS)


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
class PBHDecision:
    """The decision for (A, C): see :func:`pbh_decision`."""

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


def pbh_decision(A, C, discrete=False, tol=None):
    """
    Return the decision of this module for (A, C); see its docstring.

    Parameters
    ----------
    A : (n, n) ndarray
        State matrix.
    C : (p, n) ndarray
        Output matrix.
    discrete : bool
        Stability in the z-plane.
    tol : float, optional
        Threshold on the scaled PBH matrix (default the module's).

    Returns
    -------
    PBHDecision
        Per distinct eigenvalue its PBHResult (``pbh``); the failing ones (``failing``,
        indices into ``pbh``) with their unobservable parts (``bases``, original
        coordinates); ``V``, an orthonormal basis of the unobservable subspace, and
        ``Q = [complement, V]``, orthogonal.

    """
    n = A.shape[0]
    if n == 0:
        return PBHDecision((), (), (), np.zeros((0, 0)), np.eye(0))
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
    return PBHDecision(tuple(results), tuple(bases), tuple(failing), Q[:, n - k:], Q)


def _orth_complex(B):
    """Orthonormal (complex) basis of the columns of B, in the original coordinates."""
    U, s, _ = scipy.linalg.svd(B, full_matrices=False)
    return U[:, :max(1, int(np.sum(s > 1e-8 * s[0])))]


def hidden_eigenvalues(structure):
    """
    Return each failing eigenvalue once per dimension of its hidden part (pairs both ways).

    Parameters
    ----------
    structure : PBHDecision
        From :func:`pbh_decision`.

    Returns
    -------
    ndarray of complex

    """
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
    return list(pbh_decision(A, C, discrete, tol).pbh)


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
    return list(pbh_decision(A.T, B.T, discrete, tol).pbh)
