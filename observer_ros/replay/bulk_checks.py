# observer_ros.replay.bulk_checks: a bulk stretch checked against the estimator's own calls.
"""
Checks of a bulk-replayed stretch against the estimator, before its estimates are used.

Every step against its affine map with the held input found again from the events
(:func:`check_steps`), and windows of the estimator's own calls over the recorded
events (:func:`check_windows`, placed by :func:`_windows`); a difference beyond
:data:`CHECK_RTOL` of the size of the steps' terms (:func:`term_scale`) fails it.

"""

import copy

import numpy as np

CHECK_STEPS = 16               # steps of each checked window of a bulk stretch
CHECK_WINDOWS = 8              # windows spread over a stretch (first and last included)
CHECK_IRREGULAR = 16           # most windows at irregular places of a stretch
IRREGULAR_STEPS = 3            # steps of each of those
CHECK_RTOL = 1e-10             # bulk vs call, relative to the terms of the steps so far


def twin(est):
    """
    Return a copy of an estimator with its own state and the same caches.

    The step and gain caches hold values that depend on the step length only
    (``StepCache``), so sharing them changes no result; it saves designing the gains of
    every new step again in each copy (jittered stamps: a new step each message).

    """
    memo = {id(est.cache): est.cache, id(est.gain_cache): est.gain_cache}
    return copy.deepcopy(est, memo)


def spread(items, count):
    """Return up to ``count`` of ``items`` spread evenly, the first and the last included."""
    if len(items) <= count:
        return list(items)
    return [items[i] for i in np.linspace(0, len(items) - 1, count).round().astype(int)]


def class_matvec(M, classes, V, chunk=1 << 16):
    """
    Return ``out[k] = M[classes[k]] @ V[k]`` for every step k.

    In chunks of steps, so that the per-step matrices ``M[classes]`` never exist for a
    whole run at once (a run of 10^6 steps would hold one n x n matrix per step).

    """
    K = V.shape[0]
    out = np.empty((K, M.shape[1]))
    for lo in range(0, K, chunk):
        hi = min(K, lo + chunk)
        np.einsum('kij,kj->ki', M[classes[lo:hi]], V[lo:hi], out=out[lo:hi])
    return out


def _call_events(check, run, streams, cmd, rows, e0, e1):
    """
    Handle the events e0..e1-1 with the estimator ``check`` as the main loop does.

    Inside a bulk stretch every event passes the node's checks, so a command is
    ``set_input`` at its stamp (at the estimate's time if before it) and a
    measurement is ``correct``. Returns the estimates after the measurements.

    """
    kind, idx = run['kind'], run['idx']
    xs = []
    for e in range(e0, e1):
        k, j = int(kind[e]), int(idx[e])
        if k < 0:
            t = float(cmd.stamp_ns[j]) * 1e-9        # cmd.t[j], without the whole array
            last = check.t
            check.set_input(last if last is not None and t < last else t, cmd.values[j])
        else:
            t = float(streams[k].stamp_ns[j]) * 1e-9  # streams[k].t[j]
            xs.append(check.correct(t, streams[k].values[j], rows[k]))
    return np.array(xs).reshape(-1, check.n)


def _windows(run, K):
    """
    Return the stretches (s0, s1) of steps of a bulk run checked call by call.

    Steps s0..s1-1 (step s is measurement a+1+s): the first and the last
    :data:`CHECK_STEPS`, :data:`CHECK_WINDOWS` in all spread evenly, and up to
    :data:`CHECK_IRREGULAR` short ones (spread over them) where the events are not
    the plain pattern: a gap with other than one command, events whose bag order is
    not the replay order, a change of step class.

    """
    a = run['a']
    w = min(CHECK_STEPS, K)
    starts = np.unique(np.linspace(0, K - w, max(2, CHECK_WINDOWS)).round().astype(np.int64))
    wins = [(int(s), int(s) + w) for s in starts]
    mev = run['mev']
    e0, e1 = int(mev[a]), int(mev[a + K])
    seq = run['seq'][e0:e1 + 1]
    odd = np.zeros(K, dtype=bool)                    # step s is irregular
    odd |= run['gap_cmds'][a:a + K] != 1             # commands in the gap before step s
    back = np.flatnonzero(np.diff(seq) < 0)          # bag order is not the replay order
    if back.size:
        odd[np.clip(np.searchsorted(mev[a + 1:a + K + 1] - e0, back + 1), 0, K - 1)] = True
    cls = run['step_class'][a:a + K]
    odd[1:] |= cls[1:] != cls[:-1]
    spots = np.flatnonzero(odd)
    if spots.size > CHECK_IRREGULAR:
        spots = spots[np.linspace(0, spots.size - 1, CHECK_IRREGULAR).round().astype(int)]
    for s in spots.tolist():
        s0 = max(0, s - 1)
        wins.append((s0, min(K, s0 + IRREGULAR_STEPS)))
    wins.sort()
    merged = []
    for s0, s1 in wins:
        if merged and s0 <= merged[-1][1]:
            merged[-1] = (merged[-1][0], max(merged[-1][1], s1))
        else:
            merged.append((s0, s1))
    return merged


def check_windows(est, run, streams, cmd, rows, X, U, scale, setup=None):
    """
    Compare the bulk estimates X with the estimator's calls over the checked windows.

    Each window starts from the bulk estimate before it (the estimator itself for
    the first one; ``setup(check, s0)`` puts in what else the estimator carries, a
    Kalman filter's covariance) and handles the recorded events as the main loop does, commands
    included, so it checks which input each step holds as well as the arithmetic.
    Returns None, or a message naming the first difference beyond round-off.

    """
    a, K = run['a'], X.shape[0]
    mev, tm = run['mev'], run['tm']
    for s0, s1 in _windows(run, K):
        check = twin(est)
        if s0:
            t0 = float(tm[a + s0])
            check.reset(X[s0 - 1], t0)
            check.set_input(t0, U[s0 - 1])
            if setup is not None:               # what else the estimator carries (P)
                setup(check, s0)
        xs = _call_events(check, run, streams, cmd, rows, int(mev[a + s0]) + 1,
                          int(mev[a + s1]) + 1)
        err = np.max(np.abs(xs - X[s0:s1]), axis=1)
        bad = np.flatnonzero(err > CHECK_RTOL * scale[s0:s1])
        if bad.size:
            s = s0 + int(bad[0])
            return (f'{err[bad[0]]:.3g} at step {s} of {K}, t = {float(tm[a + 1 + s]):.9g} s '
                    f'(|x_hat| up to {scale[s]:.3g})')
    return None


def term_scale(maps, cls, sens, Y, Xprev, X, U):
    """Return the running maximum over steps of ``max(|F| |x_prev| + |G| |y| + |H| |u|, |x|)``."""
    absF, absG, absH = (np.abs(M) for M in maps[:3])
    terms = class_matvec(absF, cls, np.abs(Xprev)) + class_matvec(absH, cls, np.abs(U))
    for k, y in enumerate(Y):
        if y is not None:
            sel = np.flatnonzero(sens == k)
            terms[sel] += class_matvec(absG, cls[sel], np.abs(y))
    scale = np.maximum(np.max(terms, axis=1), np.max(np.abs(X), axis=1))
    return np.maximum.accumulate(scale) + np.finfo(float).tiny


def check_steps(run, cmd, maps, cls, sens, Y, X, x0, u0, scale):
    """
    Check every step of a bulk run against its own affine map; None or a message.

    ``x_k = F x_{k-1} + G y_k + H u_k`` with the maps measured on the estimator and
    the held input u_k found again from the events, through the commands of each gap
    (not the way :func:`_held_inputs` finds it), so a step given the wrong input or
    mangled by the scan is caught wherever it is in the run.

    """
    a, b, K = run['a'], run['b'], X.shape[0]
    mev, kind, idx = run['mev'], run['kind'], run['idx']
    e0, e1 = int(mev[a]), int(mev[b])
    pos = np.flatnonzero(kind[e0:e1] < 0) + e0          # the commands inside the run
    gap = np.searchsorted(mev[a:b + 1], pos, side='right') - 1
    last = np.full(K, -1, dtype=np.int64)
    np.maximum.at(last, gap, pos)                      # the last command of each gap
    last = np.maximum.accumulate(last)                 # held until the next one
    U = np.empty((K, u0.size))
    U[:] = u0
    held = last >= 0
    if held.any():
        U[held] = cmd.values[idx[last[held]]]
    F, G, H = maps[:3]
    Xprev = np.vstack([x0[None, :], X[:-1]])
    pred = class_matvec(F, cls, Xprev) + class_matvec(H, cls, U)
    for k, y in enumerate(Y):
        if y is not None:
            sel = np.flatnonzero(sens == k)
            pred[sel] += class_matvec(G, cls[sel], y)
    err = np.max(np.abs(pred - X), axis=1)
    bad = np.flatnonzero(err > CHECK_RTOL * scale)
    if bad.size:
        s = int(bad[0])
        return f'{err[s]:.3g} at step {s} of {K} (its affine map; {bad.size} steps)'
    return None
