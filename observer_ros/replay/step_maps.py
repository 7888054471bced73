# observer_ros.replay.step_maps: the affine maps of many step lengths at once.
"""
The affine maps of the steps of a bulk stretch, computed for all step lengths at once.

With jittered stamps every step of a stretch has its own length, so its own map
``x_k = F x_{k-1} + G y_k + H u``. Measuring each map on the estimator
(``bulk_replay._probe``, n + q + m + 1 calls) costs about 1.5 ms a step; here the maps of a
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
maps against the estimator's own calls (``bulk_replay._probe`` on a sample of step classes,
and its usual step and window checks).

"""

import numpy as np
import scipy.linalg

__all__ = ['bulk_maps', 'zoh_stack']

BASE_DIGITS = 3          # significant digits of the base step of the factored exponential
FACTOR_NORM_MAX = 0.02   # |rest| * |aug|_1 up to which the Taylor factor is used
TAYLOR_TERMS = 12        # most terms of the Taylor factor (its terms fall below 1e-17)
CHUNK = 1 << 14          # keys whose matrices are built together
MAX_GRID = 1 << 12       # most gain-grid steps walked over the keys of a run


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
    scale = 10.0 ** (BASE_DIGITS - 1 - np.floor(np.log10(keys)))
    bases = np.round(keys * scale) / scale          # about BASE_DIGITS significant digits
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


def _grid(est, lo, hi):
    """
    Return the sorted gain-grid steps from the one at or below lo to the one above hi.

    Walked with ``est.gain_steps`` (the step just above a grid step brackets it with the
    next one); None when there are more than :data:`MAX_GRID` of them.

    """
    g0, g1, _ = est.gain_steps(lo)
    grid = [g0]
    while grid[-1] <= hi:
        if len(grid) > MAX_GRID:
            return None
        g = grid[-1]
        nxt = est.gain_steps(g * (1.0 + 1e-9))[1]
        if nxt is None or not nxt > g:
            return None
        grid.append(nxt)
    return np.array(grid)


def _brackets(est, keys):
    """
    Return ``est.gain_steps`` of every key as arrays (i0, i1, w, grid); None if not found.

    ``grid[i0] <= key < grid[i1]`` with ``w = (key - g0) / (g1 - g0)``, or i1 = -1 for a
    key on the grid (within 1e-12 of itself), as ``gain_steps`` says; tested equal to
    it key by key.

    """
    if est.gain_cache is est.cache or not keys.size:
        return None
    grid = _grid(est, float(keys.min()), float(keys.max()))
    if grid is None:
        return None
    i = np.clip(np.searchsorted(grid, keys, side='right') - 1, 0, grid.size - 2)
    lo, hi = grid[i], grid[i + 1]
    tol = 1e-12 * keys
    on_lo = np.abs(keys - lo) <= tol
    on_hi = ~on_lo & (np.abs(hi - keys) <= tol)
    i0 = np.where(on_hi, i + 1, i)
    i1 = np.where(on_lo | on_hi, -1, i + 1)
    w = np.where(i1 < 0, 0.0, (keys - lo) / (hi - lo))
    return i0, i1, w, grid


def _gains(est, keys, rows):
    """Return the correction gain M of every key for the rows, as the estimator has it."""
    found = _brackets(est, keys)
    if found is None:
        return np.stack([est.correction_gain(k, rows) for k in keys.tolist()])
    i0, i1, w, grid = found
    used = np.unique(np.concatenate([i0, i1[i1 >= 0]]))
    Mg = np.zeros((grid.size,) + est.correction_gain(float(grid[used[0]]), rows).shape)
    for g in used.tolist():
        Mg[g] = est.correction_gain(float(grid[g]), rows)
    out = Mg[i0]
    inter = np.flatnonzero(i1 >= 0)
    wi = w[inter][:, None, None]
    # (1 - w) M(g0) + w M(g1), as the estimator interpolates; a grid step is M(g0)
    out[inter] = (1.0 - wi) * out[inter] + wi * Mg[i1[inter]]
    return out


def bulk_maps(est, keys, sensors, rows):
    """
    Return the affine map of each step class, or None when not built in bulk.

    Parameters
    ----------
    est : Estimator
        The replay's estimator (read only: no call changes its state).
    keys : (C,) array_like of float
        The step key of each class (``est.cache.key`` of its step length).
    sensors : (C,) array_like of int
        The sensor of each class (index into rows).
    rows : sequence of tuple of int
        The output rows of each sensor.

    Returns
    -------
    maps : tuple of ndarray or None
        ``(F, G, H, Rx, Ry, Ru)``, each stacked over the classes, as ``bulk_replay._probe``
        measures them one class at a time; None for an estimator this module does not
        model (reduced order, Kalman, a gain given, a discrete plant) or sensors with
        different numbers of rows: the caller measures its maps.

    """
    plant = est.plant
    kind = getattr(est, 'kind', '')
    if plant.is_discrete or not (kind == 'open_loop' or (kind == 'full'
                                                         and est.poles is not None)):
        return None
    keys = np.asarray(keys, dtype=float)
    sensors = np.asarray(sensors, dtype=np.intp)
    Ad, Bd = zoh_stack(plant.A, plant.B, keys)
    n = plant.n
    q = len(rows[0]) if rows else 0
    if any(len(rk) != q or tuple(sorted(rk)) != tuple(rk) for rk in rows):
        return None
    C_all = plant.C
    F, H = Ad.copy(), Bd.copy()
    G = np.zeros((keys.size, n, q))
    Rx = np.empty((keys.size, q, n))
    Ru = np.empty((keys.size, q, plant.m))
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
    Ry = np.broadcast_to(np.eye(q), (keys.size, q, q))
    return F, G, H, Rx, Ry, Ru
