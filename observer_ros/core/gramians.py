# observer_ros.core.gramians: observability and controllability Gramians.
"""Observability and controllability Gramians, finite or infinite horizon (seed 003)."""

import math

import numpy as np
import scipy.linalg

from .analysis import format_complex
from .errors import ObserverError
from .model import as_matrix
from .verify import unstable_eigenvalues

__all__ = ['observability_gramian', 'controllability_gramian']


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
