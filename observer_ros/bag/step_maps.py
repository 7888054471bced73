# observer_ros.bag.step_maps: the affine maps of many step lengths at once.
"""
The affine maps of the steps of a bulk stretch, computed for all step lengths at once.

With jittered stamps every step of a stretch has its own length, so its own map
``x_k = F x_{k-1} + G y_k + H u``. Measuring each map on the estimator
(``replay._probe``, n + q + m + 1 calls) costs about 1.5 ms a step; here the maps of a
continuous plant's open-loop and full-order (poles) estimators are built with numpy
from the same ingredients the estimator uses:

- the step key ``est.cache.key(h)`` (the step rounded to ``dt_digits``);
- ``Ad``, ``Bd`` of each key: ``expm([[A, B], [0, 0]] key)``, factored as
  ``expm(M base) expm(M d)`` on a base step of :data:`BASE_DIGITS` digits with the
  Taylor series of the small rest summed for all keys at once (the estimator's
  ``StepCache`` does the same one key at a time); a key whose rest is not small goes
  through ``scipy.linalg.expm``;
- the gain of each key, interpolated between the gains of its grid steps
  (``est.gain_steps``, ``est.correction_gain`` on the grid steps only), as the
  estimator interpolates it.

The current form ``x- = Ad x + Bd u``, ``x+ = x- + M (y - D u - C x-)`` then gives
``F = (I - M C) Ad``, ``G = M``, ``H = (I - M C) Bd - M D`` and the residual
``r = y - D u - C x-``; the open loop is the same with M = 0. The replay checks these
maps against the estimator's own calls (``replay._probe`` on a sample of step classes,
and its usual step and window checks).

"""

import numpy as np
import scipy.linalg

__all__ = ['bulk_maps', 'zoh_stack']

BASE_DIGITS = 3          # significant digits of the base step of the factored exponential
FACTOR_NORM_MAX = 0.02   # |rest| * |aug|_1 up to which the Taylor factor is used
TAYLOR_TERMS = 12        # most terms of the Taylor factor (its terms fall below 1e-17)
CHUNK = 1 << 14          # keys whose matrices are built together


def zoh_stack(A, B, keys):
    """
    Return ``Ad = expm(A h)`` and ``Bd = int_0^h expm(A s) ds B`` for every step h.

    Parameters
    ----------
    A : (n, n) array_like
        Continuous state matrix.
    B : (n, m) array_like
        Continuous input matrix.
    keys : (K,) array_like of float
        Step lengths in seconds, > 0.

    Returns
    -------
    Ad : (K, n, n) ndarray
    Bd : (K, n, m) ndarray
        Equal to ``scipy.linalg.expm`` of ``[[A, B], [0, 0]] h`` to round-off.

    """
    A = np.asarray(A, dtype=float)
    B = np.asarray(B, dtype=float).reshape(A.shape[0], -1)
    n, m = B.shape
    aug = np.zeros((n + m, n + m))
    aug[:n, :n] = A
    aug[:n, n:] = B
    norm = float(np.abs(aug).sum(axis=0).max())
    keys = np.asarray(keys, dtype=float).reshape(-1)
    E = np.empty((keys.size, n + m, n + m))
    bases = np.array([float(format(k, f'.{BASE_DIGITS - 1}e')) for k in keys.tolist()])
    rest = keys - bases
    small = np.abs(rest) * norm <= FACTOR_NORM_MAX
    for i in np.flatnonzero(~small):
        E[i] = scipy.linalg.expm(aug * keys[i])
    sel = np.flatnonzero(small)
    ubase, inv = np.unique(bases[sel], return_inverse=True)
    E0 = np.stack([scipy.linalg.expm(aug * b) for b in ubase]) if ubase.size else None
    eye = np.eye(n + m)
    for lo in range(0, sel.size, CHUNK):
        part = sel[lo:lo + CHUNK]
        Md = aug[None] * rest[part][:, None, None]
        T = eye + Md
        term = Md
        for k in range(2, TAYLOR_TERMS):
            term = np.matmul(term, Md) * (1.0 / k)
            T += term
            if np.abs(term).max() <= 1e-17:
                break
        E[part] = np.matmul(E0[inv.reshape(-1)[lo:lo + CHUNK]], T)
    return E[:, :n, :n], E[:, :n, n:]


def _gains(est, keys, rows):
    """Return the correction gain M of every key for the rows, as the estimator has it."""
    brackets = [est.gain_steps(key) for key in keys.tolist()]
    grid = {}
    for g0, g1, _ in brackets:
        for g in (g0, g1):
            if g is not None and g not in grid:
                grid[g] = est.correction_gain(g, rows)
    g0 = [grid[b[0]] for b in brackets]
    g1 = [grid[b[0] if b[1] is None else b[1]] for b in brackets]
    w = np.array([b[2] for b in brackets])[:, None, None]
    out = np.stack(g0)
    inter = np.array([b[1] is not None for b in brackets])
    # (1 - w) M(g0) + w M(g1), as the estimator interpolates; a grid step is M(g0)
    out[inter] = (1.0 - w[inter]) * out[inter] + w[inter] * np.stack(g1)[inter]
    return out


def bulk_maps(est, steps, sensors, rows):
    """
    Return the affine map of each step class, or None when not built in bulk.

    Parameters
    ----------
    est : Estimator
        The replay's estimator (read only: no call changes its state).
    steps : (C,) array_like of float
        The step length of each class, in seconds (a float difference of stamps).
    sensors : (C,) array_like of int
        The sensor of each class (index into rows).
    rows : sequence of tuple of int
        The output rows of each sensor.

    Returns
    -------
    maps : tuple of ndarray or None
        ``(F, G, H, Rx, Ry, Ru)``, each stacked over the classes, as ``replay._probe``
        measures them one class at a time; None for an estimator this module does not
        model (reduced order, Kalman, a gain given, a discrete plant) or sensors with
        different numbers of rows: the caller measures its maps.

    """
    plant = est.plant
    kind = getattr(est, 'kind', '')
    if plant.is_discrete or not (kind == 'open_loop' or (kind == 'full'
                                                         and est.poles is not None)):
        return None
    steps = np.asarray(steps, dtype=float)
    sensors = np.asarray(sensors, dtype=np.intp)
    keys = np.array([est.cache.key(h) for h in steps.tolist()])
    Ad, Bd = zoh_stack(plant.A, plant.B, keys)
    n = plant.n
    q = len(rows[0]) if rows else 0
    if any(len(rk) != q or tuple(sorted(rk)) != tuple(rk) for rk in rows):
        return None
    C_all = plant.C
    F, H = Ad.copy(), Bd.copy()
    G = np.zeros((steps.size, n, q))
    Rx = np.empty((steps.size, q, n))
    Ru = np.empty((steps.size, q, plant.m))
    for k, rk in enumerate(rows):
        sel = np.flatnonzero(sensors == k)
        if not sel.size:
            continue
        idx = list(rk)
        C, D = C_all[idx], plant.D[idx]
        CA = np.matmul(C, Ad[sel])
        CB = np.matmul(C, Bd[sel]) + D
        if kind == 'full':
            M = _gains(est, keys[sel], tuple(rk))
            G[sel] = M
            F[sel] -= np.matmul(M, CA)
            H[sel] -= np.matmul(M, CB)
        Rx[sel] = -CA
        Ru[sel] = -CB
    Ry = np.broadcast_to(np.eye(q), (steps.size, q, q))
    return F, G, H, Rx, Ry, Ru
