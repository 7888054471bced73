# observer_ros.core.step_matrices: the exact discretisation of many steps of different lengths.
"""
Matrix exponentials ``expm(M t_k)`` for many step lengths t_k at once.

For a bag's jittered stamps: each step's zero-order-hold matrices and process noise.

Each t_k is split as ``c_k h + d_k`` with c_k = round(t_k / h), h the nominal step, so
``|d_k| <= h / 2``; ``expm(M c h)`` is computed once per distinct c (scipy), ``expm(M
d_k)`` for every step at once by a Taylor series of 12 terms after scaling ``M d_k`` to a
norm of at most 1/4 (then squared back), whose truncation is below 1e-15 relatively
(``0.25^13 / 13!``). A step's matrices are the exact ones of its own length, to
round-off: no resampling.

No ROS here: numpy and scipy only.

"""

import math

import numpy as np
import scipy.linalg

__all__ = ['expm_steps', 'zoh_steps', 'noise_steps', 'discrete_steps']

_TERMS = 12
_NORM = 0.25


def expm_steps(M, t, h):
    """
    Return ``expm(M t_k)`` for every step length t_k.

    Parameters
    ----------
    M : (d, d) array_like
        The matrix.
    t : (K,) array_like
        Step lengths (any real values).
    h : float
        The nominal step (> 0): lengths near its multiples are the cheapest.

    Returns
    -------
    E : (K, d, d) ndarray

    """
    M = np.asarray(M, dtype=float)
    t = np.asarray(t, dtype=float).reshape(-1)
    d = M.shape[0]
    out = np.empty((t.size, d, d))
    if not t.size:
        return out
    c = np.rint(t / h).astype(np.int64)
    delta = t - c * h
    small = _expm_small(M, delta)
    for cv in np.unique(c):
        sel = np.flatnonzero(c == cv)
        if cv == 0:
            out[sel] = small[sel]
        else:
            out[sel] = scipy.linalg.expm(M * (cv * h)) @ small[sel]
    return out


def _expm_small(M, delta):
    """Return expm(M d_k) for small d_k (scaled Taylor series, batched)."""
    d = M.shape[0]
    norm = float(np.max(np.sum(np.abs(M), axis=0))) * float(np.max(np.abs(delta)))
    s = max(0, int(math.ceil(math.log2(norm / _NORM)))) if norm > _NORM else 0
    X = M[None] * (delta / 2.0 ** s)[:, None, None]
    eye = np.eye(d)
    T = eye + X / _TERMS
    for i in range(_TERMS - 1, 0, -1):
        T = eye + (X @ T) / i
    for _ in range(s):
        T = T @ T
    return T


def zoh_steps(A, B, t, h):
    """
    Return the zero-order-hold matrices (Ad, Bd) of every step length t_k.

    ``[[Ad, Bd], [0, I]] = expm([[A, B], [0, 0]] t_k)``.

    Returns
    -------
    Ad : (K, n, n) ndarray
    Bd : (K, n, m) ndarray

    """
    A = np.asarray(A, dtype=float)
    n = A.shape[0]
    B = np.asarray(B, dtype=float).reshape(n, -1)
    m = B.shape[1]
    aug = np.zeros((n + m, n + m))
    aug[:n, :n] = A
    aug[:n, n:] = B
    E = expm_steps(aug, t, h)
    return E[:, :n, :n], E[:, :n, n:]


def noise_steps(A, S, t, h):
    """
    Return the process noise of every step length t_k for white noise of intensity S.

    ``Qd(t) = int_0^t expm(A s) S expm(A^T s) ds`` (Van Loan: with ``E = expm([[-A, S],
    [0, A^T]] t)``, ``Qd = E22^T E12``), as
    :func:`observer_ros.core.estimators.process_noise_covariance` for one step.

    Parameters
    ----------
    A : (n, n) array_like
        The continuous state matrix.
    S : (n, n) array_like
        ``G Q G^T``, symmetric.
    t : (K,) array_like
        Step lengths.
    h : float
        The nominal step.

    Returns
    -------
    Qd : (K, n, n) ndarray

    """
    A = np.asarray(A, dtype=float)
    n = A.shape[0]
    V = np.zeros((2 * n, 2 * n))
    V[:n, :n] = -A
    V[:n, n:] = np.asarray(S, dtype=float)
    V[n:, n:] = A.T
    E = expm_steps(V, t, h)
    Q = np.swapaxes(E[:, n:, n:], 1, 2) @ E[:, :n, n:]
    return 0.5 * (Q + np.swapaxes(Q, 1, 2))


def discrete_steps(Ad, samples, S=None):
    """
    Return a discrete plant's transition over each step of ``samples`` samples.

    Parameters
    ----------
    Ad : (n, n) array_like
        The transition of one sample.
    samples : (K,) array_like of int
        Samples per step (>= 1).
    S : (n, n) array_like, optional
        The process noise covariance per sample: also return each step's
        ``sum_(i < c) Ad^i S Ad^iT``.

    Returns
    -------
    Phi : (K, n, n) ndarray
        ``Ad^c``.
    Qd : (K, n, n) ndarray
        Only with ``S``.

    """
    Ad = np.asarray(Ad, dtype=float)
    n = Ad.shape[0]
    c = np.asarray(samples, dtype=np.int64).reshape(-1)
    Phi = np.empty((c.size, n, n))
    Q = np.empty((c.size, n, n)) if S is not None else None
    for cv in np.unique(c):
        sel = c == cv
        Phi[sel] = np.linalg.matrix_power(Ad, int(cv))
        if S is not None:
            acc = np.zeros((n, n))
            P = np.eye(n)
            for _ in range(int(cv)):
                acc += P @ S @ P.T
                P = Ad @ P
            Q[sel] = acc
    return (Phi, Q) if S is not None else Phi
