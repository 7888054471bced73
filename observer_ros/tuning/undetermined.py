# observer_ros.tuning.undetermined: the filter's value of a noise the data do not determine.
"""
The process noise a tuned Kalman filter is given where the data do not determine it.

An identified variance whose +-2 sigma reaches zero is known only to lie in
``[max(0, q - 2 sigma), q + 2 sigma]``. No value there is right for every plant the data
allow, but their filters do not lose alike: :func:`minimax_Q` gives the filter the value
whose excess mean square estimation error over the Kalman filter that knew the true value
is least at worst over that range (minimax regret; the other entries at their identified
values, zero never chosen). The excess is also what one run's error scatters with: the
optimal filter's error is orthogonal to the difference of the two estimates, so the mean
square error of a filter is the optimal one's plus the mean square of that difference,
and over a run of few independent stretches of a slow mode the cross term scatters with
it. The prediction is the steady state of the sampled model at the nominal step, as in
:func:`~observer_ros.tuning.gain_search.model_errors`: the error covariance after the
correction under the true noise solves a discrete Lyapunov equation and is linear in the
true noise, so one adjoint equation per candidate serves every true value.

"""

from dataclasses import dataclass, field
import itertools
import math
from typing import List

import numpy as np
import scipy.linalg

__all__ = ['MAX_CANDIDATES', 'Choice', 'undetermined', 'minimax_Q']

#: Most grid points (candidate filters, each also a true value) over the joint range.
MAX_CANDIDATES = 1024


@dataclass
class Choice:
    """What :func:`minimax_Q` chose (``Q`` is what the filter is given)."""

    Q: np.ndarray
    entries: List[int] = field(default_factory=list)    # the diagonal entries chosen
    low: np.ndarray = None                              # the range of each chosen entry
    high: np.ndarray = None
    worst: float = math.nan         # the chosen filter's worst RMS error / the best one's
    worst_identified: float = math.nan      # the same, given the identified values

    def to_dict(self):
        """Return JSON-ready data."""
        return {'entries': [int(i) for i in self.entries],
                'value': [float(self.Q[i, i]) for i in self.entries],
                'low': [] if self.low is None else [float(x) for x in self.low],
                'high': [] if self.high is None else [float(x) for x in self.high],
                'worst_rms_ratio': self.worst,
                'worst_rms_ratio_identified': self.worst_identified}


def undetermined(Q, Q_std):
    """Return the diagonal entries whose +-2 sigma reaches zero (or that are not positive)."""
    q, s = np.diag(np.asarray(Q, float)), np.diag(np.asarray(Q_std, float))
    return [i for i in range(q.size) if not q[i] > 0.0 or
            (math.isfinite(s[i]) and 2.0 * s[i] >= q[i])]


def _filter(Ad, C, Qk, R):
    """Return the steady Kalman filter gain of (Qk, R), or None where there is none."""
    try:
        with np.errstate(all='ignore'):
            P = scipy.linalg.solve_discrete_are(Ad.T, C.T, Qk, R)
            K = np.linalg.solve(C @ P @ C.T + R, C @ P).T
    except (ValueError, np.linalg.LinAlgError):
        return None
    return K if np.all(np.isfinite(K)) else None


def _error_map(Ad, C, K, R, basis):
    """
    Return ``(t0, t)``: the filter of gain K's mean square error is ``t0 + t @ a``.

    ``a`` the true variances of the noises whose per-step covariances are ``basis``. The
    error after the correction is ``(I - K C) e`` with ``e+ = Ad (I - K C) e + Ad K v + w``:
    its trace is ``trace(Y W)`` + ``trace(K R K^T)``, ``Y`` the solution of the adjoint
    Lyapunov equation ``Y = Phi^T Y Phi + (I - K C)^T (I - K C)``.

    """
    J = np.eye(Ad.shape[0]) - K @ C
    Phi = Ad @ J
    if np.max(np.abs(np.linalg.eigvals(Phi))) >= 1.0:
        return None
    Y = scipy.linalg.solve_discrete_lyapunov(Phi.T, J.T @ J)
    KRK = K @ R @ K.T
    t0 = float(np.sum(Y * (Ad @ KRK @ Ad.T))) + float(np.trace(KRK))
    t = np.array([float(np.sum(Y * F)) for F in basis])
    return t0, t


def minimax_Q(Ad, C, basis, Q, Q_std, R, entries=None, points=None):
    """
    Return the Q whose filter loses least over the range of the undetermined entries.

    Parameters
    ----------
    Ad : (n, n) array_like
        The sampled plant.
    C : (p, n) array_like
        The outputs.
    basis : sequence of (n, n) array_like
        The per-step covariance of a unit variance of each noise (Q's diagonal).
    Q, Q_std : (k, k) array_like
        The identified diagonal Q and its standard errors.
    R : (p, p) array_like
        The identified measurement noise covariance.
    entries : sequence of int, optional
        The entries to choose (default :func:`undetermined`).
    points : int, optional
        Grid points per entry (default: as many as :data:`MAX_CANDIDATES` allows, at most
        41).

    Returns
    -------
    choice : Choice
        ``Q`` with the chosen entries (the identified Q when none is undetermined or no
        candidate has a steady-state filter).

    """
    Ad, C, R = (np.atleast_2d(np.asarray(M, float)) for M in (Ad, C, R))
    Q, S = np.asarray(Q, float), np.asarray(Q_std, float)
    basis = [np.asarray(F, float) for F in basis]
    idx = list(undetermined(Q, S) if entries is None else entries)
    if not idx or not np.all(np.isfinite(np.diag(S)[idx])):
        return Choice(Q.copy())
    q = np.clip(np.diag(Q), 0.0, None)
    low = np.clip(q[idx] - 2.0 * np.diag(S)[idx], 0.0, None)
    high = q[idx] + 2.0 * np.diag(S)[idx]
    d = len(idx)
    if points is None:
        points = int(min(41, max(3, math.floor(MAX_CANDIDATES ** (1.0 / d)))))
    axes = [np.linspace(lo, hi, points) for lo, hi in zip(low, high)]
    grid = np.array(list(itertools.product(*axes)))             # (m, d): true values too
    true = np.tile(q, (grid.shape[0], 1))
    true[:, idx] = grid
    maps, best = [], np.full(grid.shape[0], math.nan)
    for j, a in enumerate(true):
        K = _filter(Ad, C, sum(x * F for x, F in zip(a, basis)), R)
        m = None if K is None else _error_map(Ad, C, K, R, basis)
        maps.append(m)
        if m is not None:
            best[j] = m[0] + m[1] @ a             # the filter that knew a: the least error
    ok = np.isfinite(best) & (best > 0.0)
    if not ok.any():
        return Choice(Q.copy())

    def regret(m):
        """Worst excess mean square error of a filter (its error map m) over the range."""
        if m is None:
            return math.inf
        return float(np.max(m[0] + true[ok] @ m[1] - best[ok]))

    def worst(m):
        """Worst RMS error ratio to the filter that knew the true value, over the range."""
        if m is None:
            return math.inf
        return float(np.sqrt(np.max((m[0] + true[ok] @ m[1]) / best[ok])))

    # never zero: a filter given zero stops following that noise for good
    scores = np.array([regret(m) if np.all(g > 0.0) else math.inf
                       for m, g in zip(maps, grid)])
    if not np.isfinite(scores).any():
        return Choice(Q.copy())
    pick = int(np.argmin(scores))
    out = Q.copy()
    for i, v in zip(idx, grid[pick]):
        out[i, i] = v
    K = _filter(Ad, C, sum(x * F for x, F in zip(q, basis)), R)
    identified = worst(None if K is None else _error_map(Ad, C, K, R, basis))
    return Choice(out, idx, low, high, worst(maps[pick]), identified)
