# observer_ros.core.analysis: observability, detectability and their duals.
"""
Observability and controllability analysis: ranks, PBH test, decompositions, reports.

Every function takes plain matrices (no ROS, no Plant required).

**The decision** (:mod:`observer_ros.core.pbh`, stated there once; the reports, the PBH
lines, the decompositions, the pole count of a design and the sensor advisor all read
it): a mode is unobservable when the PBH matrix of the plant scaled to itself loses rank
at its eigenvalue, to within the rounding of that eigenvalue. The decompositions split an
orthogonal basis along the unobservable subspace the decision finds.
The textbook rank of ``obsv(A, C)`` is still available as :func:`obsv` and
:func:`numerical_rank`.

An unobservable mode's stability is its eigenvalue's verdict by the stability rule of
:mod:`observer_ros.core.verify`; detectable means every unobservable mode is stable.

"""

from dataclasses import dataclass, field
from typing import Tuple

import numpy as np
import scipy.linalg

from ._lazy import control
from .errors import DimensionError
from .model import as_matrix
from .pbh import (hidden_eigenvalues, pbh_decision, pbh_test, pbh_test_controllability,
                  PBH_TOL_FACTOR, PBHResult)
from .verify import EIG_BOUND_FACTOR

__all__ = ['obsv', 'ctrb', 'numerical_rank', 'rank_tolerance', 'PBHResult', 'pbh_test',
           'pbh_test_controllability', 'observable_decomposition', 'controllable_decomposition',
           'unobservable_eigenvalues', 'uncontrollable_eigenvalues', 'Mode',
           'ObservabilityReport', 'observability_report', 'ControllabilityReport',
           'controllability_report', 'is_observable', 'is_detectable', 'is_controllable',
           'is_stabilizable', 'is_stable_eigenvalue', 'stability_margin', 'format_complex',
           'PBH_TOL_FACTOR']

_EPS = np.finfo(float).eps

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


def _decompose(A, C, tol, discrete=False):
    """Q^T A Q = [[Ao, 0], [A21, Aobar]], C Q = [Co, 0]; the rank; the decision."""
    s = pbh_decision(A, C, discrete, tol)
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
    return hidden_eigenvalues(pbh_decision(A, C, False, tol))


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
    return hidden_eigenvalues(pbh_decision(A.T, B.T, False, tol))


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
    ueigs = hidden_eigenvalues(s)
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
