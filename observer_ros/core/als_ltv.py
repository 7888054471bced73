# observer_ros.core.als_ltv: ALS on irregular data (missing outputs, jittered stamps).
"""
Autocovariance least squares when outputs are missing at some samples or stamps jitter.

The innovations of a filter run at the actual stamps, and their model.

**The filter at the actual stamps.** The samples are the stamps at which at least one
output was measured (and, for a continuous plant, the stamps at which the command
changed, so that the input is held between steps). At each step the fixed gain corrects
with the outputs present (the gain's columns of the missing ones are zero), then the
state is propagated over the step to the next stamp with the plant sampled exactly at
that step's length (:mod:`observer_ros.core.step_matrices`; no resampling)::

    x+[k]   = x[k] + K M_k (z[k] - C x[k])           M_k = diag(outputs present at k)
    x[k+1]  = Ad(t_k+1 - t_k) x+[k] + Bd(t_k+1 - t_k) u[k]

K is the filter form of the reference predictor's gain Lp designed at the nominal step h
(``K = Ad(h)^-1 Lp``); for a discrete plant the step is a number of samples c and the
predictor form ``x[k+1] = Ad^(c-1) (Ad x + Bd u + Lp M_k (z - C x))`` is used instead
(no inverse of Ad). The innovation of step k is ``M_k (z[k] - C x[k])``, NaN where an
output is missing.

**Their autocovariances** (Lima & Rawlings, "Nonlinear stochastic modeling to improve
state estimation in process monitoring and control", AIChE J. 57(4), 2011: the
linear time-varying ALS). With ``Phi_k = Ad_k (I - K M_k C)`` and ``L_k = Ad_k K M_k``
the estimation error obeys ``e[k+1] = Phi_k e[k] + w_k - L_k v_k`` with ``cov w_k =
Qd(t_k+1 - t_k)`` (the exact integral of the intensity over that step), so with ``P_k =
cov e[k]``::

    P_k+1              = Phi_k P_k Phi_k^T + Qd_k + L_k R L_k^T
    E[Y_k Y_k^T]       = M_k (C P_k C^T + R) M_k
    E[Y_k+j Y_k^T]     = M_k+j C Phi_k+j-1 .. Phi_k+1 (Phi_k P_k C^T M_k - L_k R M_k)

all linear in (Q, R). :func:`ltv_autocovariance_sums` propagates these along the data's
own sequence of step lengths and present outputs, for each unknown at once, and sums
them over the pairs of steps that exist, as the data's sample autocovariances are summed
(:class:`~observer_ros.core.autocovariance.LaggedSums`): the model of each average is
that sum over the same kind of pairs divided by their count. Nothing is assumed of how
the stamps jitter or the measurements drop out (independent, in bursts or periodic): a
stretch of the bag's own sequence is the model's. For a long bag the model is taken over
a few evenly spaced stretches of it (:data:`MODEL_STEPS` steps in all), each started from
the nominal model's steady state and run in before it is summed.

No ROS here: numpy and scipy only.

"""

import numpy as np
import scipy.linalg

from .step_matrices import discrete_steps, noise_steps, zoh_steps

__all__ = ['MODEL_STEPS', 'StepModel', 'LTVModel', 'event_predictor', 'fit_initial_state',
           'ltv_autocovariance_sums', 'steady_covariances']

#: Steps of the bags' sequences over which the time-varying model is summed (all of them
#: when there are fewer).
MODEL_STEPS = 20_000


class StepModel:
    """
    The plant and a fixed reference gain over steps of any length (see the module).

    Parameters
    ----------
    A, B, C : array_like
        The plant (continuous, or discrete with ``discrete``).
    Lp : (n, p) array_like
        The reference predictor gain at the nominal step h.
    h : float
        The nominal step (s); for a discrete plant its sample time.
    discrete : bool
        A discrete plant: step lengths are whole numbers of samples.

    """

    def __init__(self, A, B, C, Lp, h, discrete=False):
        self.A = np.asarray(A, dtype=float)
        n = self.A.shape[0]
        self.B = np.asarray(B, dtype=float).reshape(n, -1)
        self.C = np.asarray(C, dtype=float)
        self.Lp = np.asarray(Lp, dtype=float)
        self.h = float(h)
        self.discrete = bool(discrete)
        if self.discrete:
            self.Ad, self.Bd = self.A, self.B
            self.K = None
        else:
            self.Ad, self.Bd = (x[0] for x in zoh_steps(self.A, self.B, [self.h], self.h))
            self.K = np.linalg.solve(self.Ad, self.Lp)

    def samples(self, tau):
        """Return the whole number of samples of each step (discrete plant)."""
        return np.maximum(np.rint(np.asarray(tau, float) / self.h).astype(np.int64), 1)

    def transitions(self, tau):
        """Return ``Ad_k, Bd_k`` of steps of lengths tau (s) (one sample each, discrete)."""
        tau = np.asarray(tau, dtype=float).reshape(-1)
        if self.discrete:
            n, m = self.B.shape
            return (np.broadcast_to(self.Ad, (tau.size, n, n)),
                    np.broadcast_to(self.Bd, (tau.size, n, m)))
        return zoh_steps(self.A, self.B, tau, self.h)

    def step_gains(self, tau, present):
        """
        Return ``Phi_k`` and ``L_k`` of steps from a sample with these outputs present.

        Parameters
        ----------
        tau : (K,) array_like
            Length of each step to the next sample (s).
        present : (K, p) array_like of bool
            The outputs measured at each sample.

        Returns
        -------
        Phi : (K, n, n) ndarray
        L : (K, n, p) ndarray

        """
        mask = np.asarray(present, dtype=float)
        if self.discrete:
            c = self.samples(tau)
            Lm = self.Lp[None] * mask[:, None, :]
            Phi0 = self.Ad[None] - Lm @ self.C
            ahead = discrete_steps(self.Ad, c - 1)
            return ahead @ Phi0, ahead @ Lm
        Ad, _ = self.transitions(tau)
        L = Ad @ (self.K[None] * mask[:, None, :])
        return Ad - L @ self.C, L

    def step_noise(self, tau, S):
        """Return each step's process noise for noise ``S`` (n x n) per unit intensity."""
        if self.discrete:
            return discrete_steps(self.Ad, self.samples(tau), S)[1]
        return noise_steps(self.A, S, tau, self.h)


def event_predictor(model, t, z, u, x0=None, sinks=(), block=1 << 14, free=0):
    """
    Run the filter of ``model`` at the actual stamps (see the module); return the last state.

    Parameters
    ----------
    model : StepModel
        Plant and gain.
    t : (E,) array_like
        Stamps (s) of the steps, increasing.
    z : (E, p) array_like
        ``y - D u_meas`` at each step, NaN where an output is not measured (a row of
        NaN: a step at which only the command changed).
    u : (E, m) array_like
        The command held from each step to the next.
    x0 : (n,) array_like, optional
        The state at the first stamp (zeros).
    sinks : sequence
        ``sink.add(rows)`` receives the innovations of the steps with a measurement,
        ``(k, p)`` a block at a time, NaN where missing.
    block : int
        Steps whose matrices are computed at once.
    free : int
        Also return, for the first ``free`` steps with a measurement, how each innovation
        depends on the initial state: ``Psi_k`` with ``dY_k = -Psi_k dx0`` (NaN rows where
        missing), and those innovations.

    Returns
    -------
    x_next : (n,) ndarray
        The prediction at the stamp after the last one (over the median step), to go on
        from.
    Psi : (K, p, n) ndarray
        Only with ``free``.
    innovations : (K, p) ndarray
        Only with ``free``.

    """
    t = np.asarray(t, dtype=float).reshape(-1)
    E = t.size
    C = model.C
    p, n = C.shape
    z = np.asarray(z, dtype=float).reshape(E, p)
    u = np.asarray(u, dtype=float).reshape(E, -1)
    x = np.zeros(n) if x0 is None else np.asarray(x0, dtype=float).reshape(n).copy()
    X = np.eye(n) if free else None
    psi, first = [], []
    kept = 0
    for a in range(0, E, int(block)):
        b = min(E, a + int(block))
        tau = np.diff(t[a:b + 1]) if b < E else np.append(np.diff(t[a:b]), model.h)
        present = np.isfinite(z[a:b])
        z0 = np.where(present, z[a:b], 0.0)
        _, Bd = model.transitions(tau)
        Phi, L = model.step_gains(tau, present)
        drive = (L @ z0[:, :, None])[:, :, 0]
        if u.shape[1]:
            drive += (Bd @ u[a:b, :, None])[:, :, 0]
        xs = np.empty((b - a, n))
        measured = present.any(axis=1)
        track = X is not None and kept < free
        Xs = np.empty((b - a, n, n)) if track else None
        for i in range(b - a):
            xs[i] = x
            x = Phi[i] @ x + drive[i]
            if track:
                Xs[i] = X
                X = Phi[i] @ X
        innov = np.where(present, z[a:b] - xs @ C.T, np.nan)[measured]
        if track:
            rows = np.where(present[:, :, None], C[None] @ Xs, np.nan)[measured]
            take = min(free - kept, rows.shape[0])
            psi.append(rows[:take])
            first.append(innov[:take])
            kept += take
        for sink in sinks:
            sink.add(innov)
    if free:
        return (x, np.concatenate(psi) if psi else np.zeros((0, p, n)),
                np.concatenate(first) if first else np.zeros((0, p)))
    return x


def fit_initial_state(psi, innovations):
    """
    Return the correction of the initial state that best explains the first innovations.

    Least squares of ``Y_k - Psi_k dx`` over the rows given (each output weighted by the
    inverse of its innovations' mean square; NaN rows left out): a filter started from a
    prediction that is not its own steady one (a later pass, started where the reference
    left off) carries that start's error for as long as its slowest mode takes to decay;
    fitting it removes the realisation of that transient from the innovations (n
    parameters out of many samples).

    Parameters
    ----------
    psi : (K, p, n) array_like
        ``Psi_k`` (:func:`event_predictor` with ``free``, or the time-invariant
        ``C (Ad - Lp C)^k``).
    innovations : (K, p) array_like
        The innovations from the uncorrected start.

    Returns
    -------
    dx : (n,) ndarray
        Add it to the initial state.

    """
    psi = np.asarray(psi, dtype=float)
    e = np.asarray(innovations, dtype=float)
    n = psi.shape[2]
    ok = np.isfinite(e)
    if not ok.any():
        return np.zeros(n)
    w = np.zeros(e.shape[1])
    for i in range(e.shape[1]):
        col = e[ok[:, i], i]
        w[i] = 1.0 / np.mean(col * col) if col.size and np.mean(col * col) > 0 else 0.0
    A = np.where(ok[:, :, None], psi, 0.0) * np.sqrt(w)[None, :, None]
    b = np.where(ok, e, 0.0) * np.sqrt(w)[None, :]
    return np.linalg.lstsq(A.reshape(-1, n), b.reshape(-1), rcond=1e-10)[0]


class _Accumulator:
    """The running state of :func:`ltv_autocovariance_sums` (its arrays a block at a time)."""

    def __init__(self, C, R_basis, Uq, lags, P0):
        self.C = np.asarray(C, dtype=float)
        p, n = self.C.shape
        self.Rb = np.asarray(R_basis, dtype=float).reshape(-1, p, p)
        self.Uq = int(Uq)
        U = self.Uq + self.Rb.shape[0]
        self.J = J = int(lags)
        self.R_all = np.concatenate([np.zeros((self.Uq, p, p)), self.Rb])
        self.P = np.array(P0, dtype=float).reshape(U, n, n)
        self.H = np.zeros((n, max(J - 1, 0), U, p))              # E[e_k Y_k-1-i^T]
        self.H2 = np.empty_like(self.H)
        self.S0 = np.zeros((U, p, p))
        self.S1 = np.zeros((p, max(J - 1, 0), U, p))
        self.counts = np.zeros((J, p, p))
        self._mask = np.zeros((0, p))          # the last J - 1 steps' outputs present

    def run(self, Phi, L, noise, present, summed):
        """Go on over the steps of a block; sum the steps where ``summed`` (bool (K,))."""
        C, Rb, R_all, J, Uq = self.C, self.Rb, self.R_all, self.J, self.Uq
        p, n = C.shape
        U = R_all.shape[0]
        width = U * p
        CT = C.T
        present = np.asarray(present, dtype=float)
        P, H, H2, S0, S1 = self.P, self.H, self.H2, self.S0, self.S1
        for k in range(Phi.shape[0]):
            m = present[k]
            if summed[k]:
                S0 += (C @ P @ CT + R_all) * np.outer(m, m)
                if J > 1:
                    lagged = (C @ H.reshape(n, -1)).reshape(p, J - 1, U, p)
                    S1 += lagged * m[:, None, None, None]
            PhiP = Phi[k] @ P
            G = (PhiP @ CT - L[k] @ R_all) * m                        # (U, n, p)
            if J > 1:
                flat = H.reshape(n, -1)
                H2.reshape(n, -1)[:, width:] = Phi[k] @ flat[:, :flat.shape[1] - width]
                H2[:, 0] = np.moveaxis(G, 1, 0)
                H, H2 = H2, H
            P = PhiP @ Phi[k].T
            P[:Uq] += noise[k]
            P[Uq:] += L[k] @ Rb @ L[k].T
        self.P, self.H, self.H2 = P, H, H2
        # the pairs whose later step is summed
        joined = np.concatenate([self._mask, present])
        t = self._mask.shape[0]
        later = np.flatnonzero(np.asarray(summed, dtype=bool)) + t
        for j in range(J):
            ok = later[later - j >= 0]
            if ok.size:
                self.counts[j] += joined[ok].T @ joined[ok - j]
        self._mask = joined[max(0, joined.shape[0] - (J - 1)):] if J > 1 else \
            np.zeros((0, p))

    def sums(self):
        """Return the sums ``(lags, p, p, U)``."""
        J, p = self.J, self.C.shape[0]
        U = self.S0.shape[0]
        out = np.zeros((J, p, p, U))
        out[0] = np.moveaxis(self.S0, 0, 2)
        if J > 1:
            out[1:] = np.moveaxis(self.S1, 0, 1).transpose(0, 1, 3, 2)
        return out


def ltv_autocovariance_sums(Phi, L, noise, R_basis, present, C, lags, start, P0):
    """
    Sum the model autocovariances of each unknown along a sequence of steps (see the module).

    Parameters
    ----------
    Phi : (K, n, n) array_like
        ``Phi_k`` of each step (to the next).
    L : (K, n, p) array_like
        ``L_k`` (zero columns for the outputs missing at k).
    noise : (K, Uq, n, n) array_like
        The process noise of each step for each process-noise unknown.
    R_basis : (Ur, p, p) array_like
        The measurement-noise unknowns' matrices.
    present : (K, p) array_like of bool
        Outputs measured at each step.
    C : (p, n) array_like
        Output matrix.
    lags : int
        Lags 0 .. lags-1.
    start : int
        Pairs are summed whose later step is at ``start`` or after (the steps before run
        the model in).
    P0 : (Uq + Ur, n, n) array_like
        The error covariance of each unknown at the first step.

    Returns
    -------
    sums : (lags, p, p, U) ndarray
        ``sum over pairs of E[Y_k+j Y_k^T]`` per unknown (later step ``k + j >= start``).
    counts : (lags, p, p) ndarray
        The number of pairs of each entry.

    """
    Phi = np.asarray(Phi, dtype=float)
    acc = _Accumulator(C, R_basis, np.shape(noise)[1], lags, P0)
    summed = np.arange(Phi.shape[0]) >= int(start)
    acc.run(Phi, np.asarray(L, dtype=float), np.asarray(noise, dtype=float), present,
            summed)
    return acc.sums(), acc.counts


class LTVModel:
    """
    The ALS matrix of irregular data: the time-varying model along the data's steps.

    Parameters
    ----------
    model : StepModel
        The plant and the reference gain.
    G : (n, k) array_like
        The process noise input (the unknown Q is on its columns).
    sequences : list of (t, present, start)
        Per bag, the stamps (s) of the steps with a measurement ``(K,)``, the outputs
        present at each ``(K, p)`` and the first step whose innovations are summed (the
        transient before it dropped).
    steps : int
        Steps over which the model is summed (:data:`MODEL_STEPS`).

    """

    def __init__(self, model, G, sequences, steps=MODEL_STEPS, block=2048):
        self.model = model
        self.G = np.asarray(G, dtype=float)
        self.sequences = [(np.asarray(t, float), np.asarray(pr, bool), int(s))
                          for t, pr, s in sequences]
        self.steps = int(steps)
        self.block = int(block)

    def stretches(self, runin, chunks=4):
        """Return ``(bag, first, start, stop)`` of the stretches the model is summed over."""
        lengths = [max(0, t.size - s) for t, _, s in self.sequences]
        total = sum(lengths)
        if total <= self.steps:
            return [(b, max(0, s - runin), s, t.size)
                    for b, (t, _, s) in enumerate(self.sequences) if t.size > s]
        size = self.steps // chunks
        out = []
        for c in range(chunks):
            at = int((c + 0.5) * total / chunks - size / 2)
            for b, n in enumerate(lengths):
                if at < n:
                    s = self.sequences[b][2] + max(at, 0)
                    stop = min(s + size, self.sequences[b][0].size)
                    out.append((b, max(0, s - runin), s, stop))
                    break
                at -= n
        return out

    def als_matrix(self, k, lags, full=False):
        """
        Return the ALS matrix ``(lags p p, unknowns)`` and the labels of its columns.

        Each column is the average over the model's stretches of the expected products
        of its unknown, per entry divided by the number of pairs (as the data's).

        """
        from .als import symmetric_basis
        m = self.model
        C = m.C
        p, n = C.shape
        qb, q_labels = symmetric_basis(k, full)
        rb, r_labels = symmetric_basis(p, full)
        S_q = [self.G @ E @ self.G.T for E in qb]
        Rb = np.array(rb).reshape(-1, p, p)
        h = m.h
        one = np.array([h])
        all_present = np.ones((1, p), dtype=bool)
        Phi0, L0 = (x[0] for x in m.step_gains(one, all_present))
        noise0 = [m.step_noise(one, S)[0] for S in S_q]
        P0 = steady_covariances(Phi0, L0, noise0, Rb)
        rho = float(np.max(np.abs(np.linalg.eigvals(Phi0))))
        runin = int(lags) + (int(min(np.ceil(np.log(1e-2) / np.log(rho)), 2000))
                             if 0.0 < rho < 1.0 else 0)
        total = None
        counts = np.zeros((int(lags), p, p))
        for b, first, start, stop in self.stretches(runin):
            t, present, _ = self.sequences[b]
            acc = _Accumulator(C, Rb, len(S_q), lags, P0)
            for a in range(first, stop, self.block):
                e = min(stop, a + self.block)
                tau = np.diff(t[a:e + 1]) if e < t.size else \
                    np.append(np.diff(t[a:e]), h)
                Phi, L = m.step_gains(tau, present[a:e])
                noise = np.stack([m.step_noise(tau, S) for S in S_q], axis=1) if S_q \
                    else np.zeros((e - a, 0, n, n))
                acc.run(Phi, L, noise, present[a:e], np.arange(a, e) >= start)
            sums = acc.sums()
            total = sums if total is None else total + sums
            counts += acc.counts
        with np.errstate(invalid='ignore', divide='ignore'):
            M = np.where(counts[..., None] > 0, total / counts[..., None], 0.0)
        return M.reshape(int(lags) * p * p, -1), q_labels, r_labels


def steady_covariances(Phi0, L0, noise0, R_basis):
    """Return the steady error covariance of each unknown for a constant Phi0, L0."""
    out = [scipy.linalg.solve_discrete_lyapunov(Phi0, N) for N in noise0]
    out += [scipy.linalg.solve_discrete_lyapunov(Phi0, L0 @ R @ L0.T) for R in R_basis]
    return np.array(out)
