# observer_ros.replay.bulk_kalman: the affine maps of a Kalman filter's steps in a bulk stretch.
"""
The step maps of a Kalman filter over a bulk stretch: time-varying, then steady.

A step of the Kalman filter is the affine map ``x_k = F x_{k-1} + G y_k + H u`` of the
other current-form estimators, with the gain ``K_k`` of its covariance: ``F = (I - K C)
Ad``, ``G = K``, ``H = (I - K C) Bd - K D``, and the residual ``r = y - D u - C x-``.
The gain depends on P, which the filter carries from step to step, so the maps are built
here instead of measured on the estimator (``bulk_replay._probe``):

- while P converges, the covariance recursion runs step by step with the filter's own
  arithmetic (:meth:`~observer_ros.core.estimators.KalmanEstimator.prior_covariance`
  and :func:`~observer_ros.core.estimators.kalman.kalman_correction`: the same P, bit
  for bit, as the filter's calls), and each step gets its own map;
- once the prior P of a step is within :data:`STEADY_RTOL` of the steady-state prior of
  its step class (``scipy.linalg.solve_discrete_are`` of that step length and sensor,
  one per distinct step, cached on the estimator's step entry), every later step takes
  the steady-state gain of its class: one map per class, as for a pole-placement design.

Stretches with more than :data:`MAX_STEADY_CLASSES` classes (jittered stamps: one step
length each) stay time-varying throughout, and so does a filter whose P does not reach
its steady state within the stretch. The replay
checks the result against the filter's own calls as for the other estimators
(``bulk_checks``), each check starting from the covariance of its step.

"""

import numpy as np
import scipy.linalg

from ..core.estimators.kalman import kalman_correction

__all__ = ['kalman_maps', 'KalmanCovariances', 'STEADY_RTOL', 'MAX_STEADY_CLASSES']

#: A step's prior covariance within this (relative to the largest entry of the class's
#: steady-state prior) of its class's steady state: from there on the steady gains.
STEADY_RTOL = 1e-12
#: Most step classes of a stretch whose steady states are solved for.
MAX_STEADY_CLASSES = 64
#: The steady state is the filter's own fixed point: its recursion from the Riccati
#: solution until a prior repeats the one before to this (relative to its largest entry),
#: at most FIXED_STEPS steps.
FIXED_RTOL = 1e-14
FIXED_STEPS = 4000


class KalmanCovariances:
    """
    The covariances of the map classes of a Kalman stretch.

    ``post[c]`` is P after a step of map class c, ``S[c]`` its innovation covariance,
    ``whiten[c]`` ``L^-1`` with ``S = L L^T`` (the whitened residual is ``whiten @ r``),
    ``gain[c]`` its K; ``P0`` the estimator's P before the first step (None: not known
    yet, the first step takes its steady state); ``mcls[s]`` the map class of step s.

    """

    def __init__(self, P0, post, S, gain, steady_from, mcls):
        self.P0, self.post, self.S, self.gain, self.mcls = P0, post, S, gain, mcls
        self.whiten = np.linalg.inv(np.linalg.cholesky(S))
        self.steady_from = steady_from          # first step of the steady gains (K: none)

    def before(self, s):
        """Return P before step s (after step s - 1)."""
        return self.P0 if s == 0 else self.post[self.mcls[s - 1]]

    def set_on(self, est, s):
        """Put the covariance before step s into an estimator (a twin that checks it)."""
        P = self.before(s)
        est._P = None if P is None else P.copy()


def _steady_prior(step, C, Q, R, prior=None):
    """
    Return the steady-state prior covariance of one step class, or None.

    ``solve_discrete_are``'s solution, then (with ``prior``, the filter's own prior of a
    posterior) the filter's recursion from it until it repeats to :data:`FIXED_RTOL`, at
    most :data:`FIXED_STEPS` steps: the fixed point the filter's calls come to, which
    ``solve_discrete_are`` can miss by more than :data:`STEADY_RTOL` when a noise is small
    against R (submarine, input noise 1.2e-8 against R 1e-6: 1e-10); a stretch that starts
    at steady state (the replay's later chunks) would otherwise never be found there.

    """
    try:
        P = scipy.linalg.solve_discrete_are(step.Ad.T, C.T, Q, R)
    except (ValueError, np.linalg.LinAlgError):
        return None
    if not np.all(np.isfinite(P)):
        return None
    P = 0.5 * (P + P.T)
    if prior is not None:
        eye = np.eye(P.shape[0])
        for _ in range(FIXED_STEPS):
            _, _, post = kalman_correction(P, C, R, eye)
            nxt = prior(post)
            if not np.all(np.isfinite(nxt)):
                break
            done = np.max(np.abs(nxt - P)) <= FIXED_RTOL * np.max(np.abs(nxt))
            P = nxt
            if done:
                break
    return P


def kalman_maps(est, run, first, cls, sens, rows):
    """
    Return the maps of a Kalman run's steps (see the module), or None.

    Parameters
    ----------
    est : KalmanEstimator
        The filter at the start of the run (its P known).
    run : dict
        The run (``bulk_runs``).
    first, cls : int arrays
        The first step of each step class and the class of each step.
    sens : int array
        The sensor of each step.
    rows : list of tuple
        ``rows[k]``: the output rows of sensor k.

    Returns
    -------
    maps : tuple
        ``(F, G, H, Rx, Ry, Ru)`` stacked over the map classes.
    mcls : (K,) int array
        The map class of each step.
    mfirst : int array
        The first step of each map class.
    cov : KalmanCovariances
        None is returned instead of all four when P is not known yet or the sensors of
        the run measure different numbers of outputs.

    """
    if est.P is None and est.t != getattr(est, '_t_anchor', None):   # its first step: h
        return None
    P = est.P
    a = run['a']
    keys = run['keys'][run['step_class'][a + first] // len(rows)]
    ks = sens[first]
    if len({len(rows[k]) for k in ks.tolist()}) != 1:
        return None
    n = est.plant.n
    eye = np.eye(n)
    zero = np.zeros((n, n))
    discrete = est.plant.is_discrete        # a discrete plant's keys are whole samples
    steps = [est.cache.get(int(round(k)) if discrete else float(k)) for k in keys.tolist()]
    model = [est.rows_model(rows[k]) for k in ks.tolist()]
    noise = [est.prior_covariance(st, zero) for st in steps]        # Qk: Ad 0 Ad^T + Qk
    steady = None
    if len(steps) <= MAX_STEADY_CLASSES:
        steady = []
        for st, (C, _, R), Q, k in zip(steps, model, noise, ks.tolist()):
            tag = ('kalman_steady_prior', tuple(rows[k]))
            if tag not in st.extra:
                st.extra[tag] = _steady_prior(
                    st, C, Q, R, lambda post, st=st: est.prior_covariance(st, post))
            steady.append(st.extra[tag])
        if any(p is None for p in steady):
            steady = None
    K = cls.size
    gains, covs, posts = [], [], []
    T = K
    cls_list = cls.tolist()
    for s in range(K):
        c = cls_list[s]
        if P is None:               # the first correction: its step's steady state
            Pm = est.first_prior(steps[c], rows[ks[c]])
        else:
            Pm = est.prior_covariance(steps[c], P)
        if steady is not None:
            ref = steady[c]
            if np.max(np.abs(Pm - ref)) <= STEADY_RTOL * np.max(np.abs(ref)):
                T = s
                break
        C, _, R = model[c]
        S, gain, P = kalman_correction(Pm, C, R, eye)
        gains.append(gain)
        covs.append(S)
        posts.append(P)
    # map classes: each time-varying step its own, then one per step class
    rest = np.unique(cls[T:])
    for c in rest.tolist():
        C, _, R = model[c]
        S, gain, Pp = kalman_correction(steady[c], C, R, eye)
        gains.append(gain)
        covs.append(S)
        posts.append(Pp)
    mcls = np.empty(K, dtype=np.int64)
    mcls[:T] = np.arange(T)
    mfirst = np.concatenate([np.arange(T), np.zeros(rest.size, dtype=np.int64)])
    if rest.size:
        where = np.searchsorted(rest, cls[T:])
        mcls[T:] = T + where
        firsts = np.full(rest.size, K, dtype=np.int64)
        np.minimum.at(firsts, where, np.arange(T, K))
        mfirst[T:] = firsts
    base = np.concatenate([np.asarray(cls[:T]), rest]).astype(np.int64)   # class per map
    Gs = np.stack(gains)
    Ad = np.stack([steps[c].Ad for c in base.tolist()])
    Bd = np.stack([steps[c].Bd for c in base.tolist()])
    Cs = np.stack([model[c][0] for c in base.tolist()])
    Ds = np.stack([model[c][1] for c in base.tolist()])
    IKC = eye - Gs @ Cs
    F = IKC @ Ad
    H = IKC @ Bd - Gs @ Ds
    q = Cs.shape[1]
    Rx = -(Cs @ Ad)
    Ry = np.broadcast_to(np.eye(q), (base.size, q, q)).copy()
    Ru = -(Cs @ Bd + Ds)
    cov = KalmanCovariances(est.P, np.stack(posts), np.stack(covs), Gs, T, mcls)
    return (F, Gs, H, Rx, Ry, Ru), mcls, mfirst, cov
