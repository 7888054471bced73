# observer_ros.replay.bulk_replay: stretches of measurements replayed as one affine recursion.
"""
Replay a stretch of measurements in bulk, as an affine recursion evaluated with numpy.

Long single-sensor stretches at a constant step are replayed in bulk for the
current-form estimators (full and reduced order with poles, open loop): one step of
such an estimator is the affine map ``x_k = F x_{k-1} + G y_k + H u_{k-1}``, whose
matrices are measured by calling the estimator itself on unit vectors; the recursion is
then evaluated in blocks with numpy. The input held at each step is that of the last
command before it in the replay order (the order above, which the main loop walks; in
lockstep it is not the bag order). Every stretch is checked before it is used:

- every step against its affine map, with the held input found again from the events
  (:func:`check_steps`);
- windows of the estimator's own calls, the recorded events handled as the main loop
  handles them (:func:`check_windows`): the first and last steps, a spread across the
  stretch, and its irregular places (a gap with other than one command, events whose bag
  order is not the replay order, a change of step length or sensor);
- one step of each step class from its bulk prior.

A stretch that differs anywhere by more than round-off (:data:`CHECK_RTOL` of the size
of the terms of its steps so far) is replayed call by call instead, with a warning.
An unstable estimator (the open loop of an unstable plant) is replayed call by call when
its growth to the end of the bag exceeds :data:`MAX_GROWTH`, since it would amplify the
bulk's different round-off as much. ``exact=True`` turns bulk replay off.

"""

import numpy as np

from .bulk_checks import (CHECK_RTOL, check_steps, check_windows, class_matvec, spread, term_scale,
                          twin)
from .bulk_kalman import kalman_maps
from .step_maps import bulk_maps

__all__ = ['affine_scan']

MAX_GROWTH = 1e3               # unstable step maps: most growth to the end of the bag
CHECK_CLASSES = 32             # step classes checked call by call (jittered: one per step)


def affine_scan(F, W, x0, steps=None, chunk=1 << 16):
    """
    Evaluate ``x_k = F[c_k] x_{k-1} + W[k-1]`` for k = 1..K, in blocks.

    Parameters
    ----------
    F : (n, n) or (C, n, n) ndarray
        One transition matrix, or one per class.
    W : (K, n) ndarray
        The forcing of each step.
    x0 : (n,) ndarray
        The state before the first step.
    steps : (K,) int array, optional
        The class c_k of each step (index into F); all 0 when None.
    chunk : int
        Steps evaluated together (memory is ``chunk * n**2`` floats).

    Returns
    -------
    X : (K, n) ndarray
        ``X[k-1] = x_k``, equal to the step-by-step recursion up to round-off.

    Notes
    -----
    A chunk of K steps is cut into blocks of about sqrt(K) steps. The products of
    the transitions inside each block and the response of each block from zero are
    accumulated for all blocks at once (one batched product per position in the
    block), then the state is carried from block to block, then every step is
    ``Phi x_block_start + z``. That is O(K n^3) work in numpy with O(sqrt(K)) Python
    iterations.

    """
    W = np.asarray(W, dtype=float)
    K, n = W.shape
    F = np.asarray(F, dtype=float)
    if F.ndim == 2:
        F = F[None]
    cls = np.zeros(K, dtype=np.intp) if steps is None else np.asarray(steps, dtype=np.intp)
    Fx = np.concatenate([F, np.eye(n)[None]])        # the last class pads: identity
    pad_class = F.shape[0]
    X = np.empty((K, n))
    x = np.asarray(x0, dtype=float).copy()
    for lo in range(0, K, chunk):
        hi = min(K, lo + chunk)
        L = hi - lo
        B = max(1, int(np.sqrt(L)))
        nb = -(-L // B)
        c = np.full(nb * B, pad_class, dtype=np.intp)
        c[:L] = cls[lo:hi]
        c = c.reshape(nb, B)
        Wb = np.zeros((nb * B, n))
        Wb[:L] = W[lo:hi]
        Wb = Wb.reshape(nb, B, n)
        Phi = np.empty((nb, B, n, n))
        Z = np.empty((nb, B, n))
        P = np.broadcast_to(np.eye(n), (nb, n, n)).copy()
        z = np.zeros((nb, n))
        for j in range(B):
            Fj = Fx[c[:, j]]
            P = np.matmul(Fj, P)
            z = np.einsum('bij,bj->bi', Fj, z) + Wb[:, j]
            Phi[:, j] = P
            Z[:, j] = z
        S = np.empty((nb, n))
        for blk in range(nb):
            S[blk] = x
            x = Phi[blk, -1] @ x + Z[blk, -1]
        Xc = np.einsum('bjkl,bl->bjk', Phi, S) + Z
        X[lo:hi] = Xc.reshape(nb * B, n)[:L]
        x = X[hi - 1].copy()
    return X


def _probe(probe, t0, t1, rows):
    """Measure the affine map of one step t0 -> t1 (correction with rows) on a twin."""
    plant = probe.plant
    n, m, q = plant.n, plant.m, len(rows)

    def run(x0, u, y):
        probe.reset(x0, t0)
        probe.set_input(t0, u)
        x = probe.correct(t1, y, rows)
        return x, probe.residual

    F, G, H = np.zeros((n, n)), np.zeros((n, q)), np.zeros((n, m))
    Rx, Ry, Ru = np.zeros((q, n)), np.zeros((q, q)), np.zeros((q, m))
    zx, zu, zy = np.zeros(n), np.zeros(m), np.zeros(q)
    x, r = run(zx, zu, zy)
    if np.any(x != 0) or r is None or np.any(r != 0):
        return None
    for i in range(n):
        F[:, i], Rx[:, i] = run(np.eye(n)[i], zu, zy)
    for i in range(q):
        G[:, i], Ry[:, i] = run(zx, zu, np.eye(q)[i])
    for i in range(m):
        H[:, i], Ru[:, i] = run(zx, np.eye(m)[i], zy)
    return F, G, H, Rx, Ry, Ru


def _step_maps(est, run, first, sens, rows, warnings):
    """
    Return the affine maps of the step classes of a run (first step of class c: first[c]).

    As ``(F, G, H, Rx, Ry, Ru)``, each stacked over the classes (see :func:`_probe`).

    Built in bulk (:func:`~observer_ros.replay.step_maps.bulk_maps`) when there are more
    than :data:`CHECK_CLASSES` classes (jittered stamps) and the estimator is one it
    models, then checked against :func:`_probe` on :data:`CHECK_CLASSES` classes spread
    over the run; else measured by :func:`_probe` class by class. None: not linear.

    """
    probe = twin(est)
    a, tm = run['a'], run['tm']
    first = np.asarray(first)
    t0, t1 = tm[a + first], tm[a + first + 1]
    ks = sens[first]
    maps = None
    if len(first) > CHECK_CLASSES:
        keys = run['keys'][run['step_class'][a + first] // len(rows)]
        maps = bulk_maps(est, keys, ks, rows)
    todo = range(len(first)) if maps is None else spread(range(len(first)), CHECK_CLASSES)
    probed = {}
    for c in todo:
        mp = _probe(probe, float(t0[c]), float(t1[c]), rows[ks[c]])
        if mp is None:
            warnings.append('bulk replay disabled: an estimator step is not linear')
            return None
        probed[c] = mp
    if maps is None:
        return _stacked([probed[c] for c in range(len(first))])
    for c, mp in probed.items():
        for bulk, measured in zip((M[c] for M in maps), mp):
            if np.max(np.abs(bulk - measured)) > CHECK_RTOL * (1.0 + np.max(np.abs(measured))):
                warnings.append("bulk step maps differ from the estimator's at t = "
                                f'{float(t1[c]):.9g} s; measuring every step')
                maps = [_probe(probe, float(t0[i]), float(t1[i]), rows[ks[i]])
                        for i in range(len(first))]
                return None if any(mp is None for mp in maps) else _stacked(maps)
    return maps


def _spectral_radius(F, h):
    """
    Return the largest spectral radius of the step maps F (step lengths h).

    At most :data:`CHECK_CLASSES` * 8 maps are decomposed: spread over the classes, and
    the shortest and longest steps (a map's poles move monotonically with its length,
    ``exp(s h)``); jittered stamps give one class per step.

    """
    if F.shape[0] > 8 * CHECK_CLASSES:
        pick = spread(range(F.shape[0]), 8 * CHECK_CLASSES)
        pick += [int(np.argmin(h)), int(np.argmax(h))]
        F = F[pick]
    return float(np.max(np.abs(np.linalg.eigvals(F))))


def _stacked(maps):
    """Return the maps (F, G, H, Rx, Ry, Ru) of the classes as six stacked arrays."""
    return tuple(np.stack(part) for part in zip(*maps))


def _held_inputs(run, cmd, u0, a, b):
    """
    Return the input held at each correction a+1..b: that of the last command before it.

    The last command before measurement j in the replay order, if it comes after
    measurement a; else ``u0``, the input the estimator held at a.

    """
    mev = run['mev']
    e0, e1 = int(mev[a]), int(mev[b]) + 1       # the events from measurement a to b
    # the last command at or before each of these events, from a on (-1: none)
    last = np.maximum.accumulate(np.where(run['kind'][e0:e1] == -1, np.arange(e0, e1), -1))
    last = last[mev[a + 1:b + 1] - e0]
    U = np.empty((b - a, u0.size))
    U[:] = u0
    after_a = last > e0
    if after_a.any():
        U[after_a] = cmd.values[run['idx'][last[after_a]]]
    return U


def bulk_run(est, run, streams, cmd, rows, rows_idx, out, m, warnings):
    """
    Replay measurements a+1..b of a run in bulk; hand the state back to est.

    Returns (steps, event of the last measurement, last stamp per sensor); None when a
    check fails (the caller replays the rest call by call); False when the run cannot
    start here (a Kalman filter whose P is not known at its first step).

    """
    a, b = run['a'], run['b']
    tm = run['tm']
    K = b - a
    t_a = float(tm[a])
    if est.t != t_a:
        return None
    plant = est.plant
    n, p = plant.n, plant.p
    ev = run['mev'][a + 1:b + 1]             # the events of measurements a+1..b
    sens = run['kind'][ev]
    idx = run['idx'][ev]
    U = _held_inputs(run, cmd, est.u, a, b)
    # classes of this run, and their maps measured on the estimator
    cls_all = run['step_class'][a:b]
    classes, first, cls = np.unique(cls_all, return_index=True, return_inverse=True)
    cls = cls.reshape(-1)
    W = np.zeros((K, n))
    Y = [None] * len(streams)
    cov = setup = None
    if getattr(est, 'kind', '') == 'kalman':     # maps from its covariance recursion
        built = kalman_maps(est, run, first, cls, sens, rows)
        if built is None:                        # not from here: call by call to the next
            return False
        maps, cls, first, cov = built
        setup = cov.set_on                       # a check starts from the step's P
    else:
        maps = _step_maps(est, run, first, sens, rows, warnings)
        if maps is None:
            return None
    Fs = maps[0]
    # an unstable estimator (the open loop of an unstable plant) amplifies every
    # difference in round-off until the end of the bag: call by call, as the node
    rho = _spectral_radius(Fs, tm[a + first + 1] - tm[a + first])
    if rho > 1.0 and run['rest'] * np.log(rho) > np.log(MAX_GROWTH):
        return None
    for k in range(len(streams)):
        sel = sens == k
        if not sel.any():
            continue
        Y[k] = streams[k].values[idx[sel]]
        Gk, Hk = maps[1], maps[2]
        ck = cls[sel]
        W[sel] = class_matvec(Gk, ck, Y[k]) + class_matvec(Hk, ck, U[sel])
    x0 = est.x_hat
    X = affine_scan(Fs, W, x0, cls)
    if not np.all(np.isfinite(X)):
        return None
    Xprev = np.vstack([x0[None, :], X[:-1]])
    R = np.full((K, p), np.nan)
    E = None if cov is None else np.full((K, p), np.nan)
    for k in range(len(streams)):
        sel = np.flatnonzero(sens == k)
        if not sel.size:
            continue
        ck = cls[sel]
        Rx, Ry, Ru = maps[3:]
        r = (class_matvec(Rx, ck, Xprev[sel]) + class_matvec(Ry, ck, Y[k])
             + class_matvec(Ru, ck, U[sel]))
        R[np.ix_(sel, rows_idx[k])] = r
        if E is not None:                        # whitened by the step's S
            E[np.ix_(sel, rows_idx[k])] = class_matvec(cov.whiten, ck, r)
    # round-off is relative to the size of the terms of a step, |F| |x| + |G| |y| +
    # |H| |u| (the map of a reduced-order observer in x coordinates has large entries
    # that cancel), and to the largest of them so far: the estimate may shrink to zero
    # by cancellation or grow without bound on an unstable open loop
    scale = term_scale(maps, cls, sens, Y, Xprev, X, U)
    # check: every step against its map, windows of real calls over the recorded
    # events, and one step of each class from its bulk prior
    problem = check_steps(run, cmd, maps, cls, sens, Y, X, x0, est.u, scale)
    if problem is None:
        problem = check_windows(est, run, streams, cmd, rows, X, U, scale, setup)
    check = twin(est)
    for f in spread(first, CHECK_CLASSES) if problem is None else ():
        k = int(sens[f])
        check.reset(Xprev[f], float(tm[a + f]))
        check.set_input(float(tm[a + f]), U[f])
        if setup is not None:
            setup(check, f)
        x = check.correct(float(tm[a + f + 1]), streams[k].values[idx[f]], rows[k])
        err = float(np.max(np.abs(x - X[f])))
        if err > CHECK_RTOL * scale[f]:
            problem = f'{err:.3g} at step {f} of {K} (one step of its class)'
            break
    if problem is not None:
        warnings.append("bulk replay disabled: it differs from the estimator's calls by "
                        f'{problem}; replaying call by call')
        return None
    out_ns, out_x, out_r, out_seq, out_sensor, out_e = out
    for k in range(len(streams)):
        sel = sens == k
        out_ns[m:m + K][sel] = streams[k].stamp_ns[idx[sel]]
    out_x[m:m + K] = X
    out_r[m:m + K] = R
    if E is not None:
        out_e[m:m + K] = E
    out_seq[m:m + K] = run['seq'][ev]
    out_sensor[m:m + K] = sens
    t_b = float(tm[b])
    # hand over: the estimator is at x_b, t_b, holding the input it held at b
    est.reset(X[-1], t_b)
    est.set_input(t_b, U[-1])
    if cov is not None:                          # and the covariance of its last step
        c = cls[-1]
        est._P, est._S, est._gain_used = cov.post[c].copy(), cov.S[c].copy(), \
            cov.gain[c].copy()
    last = {int(k): float(tm[a + 1 + int(np.flatnonzero(sens == k)[-1])])
            for k in np.unique(sens)}
    return K, run['last_event'], last
