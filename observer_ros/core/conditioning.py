# observer_ros.core.conditioning: how sensitive a loop's poles are, how far its error grows.
"""
Pole sensitivity and transient growth of a closed-loop (or observer error) matrix.

**Pole sensitivity.** A perturbation E of a matrix M moves its simple eigenvalue
``lambda_i`` by ``kappa_i ||E||`` to first order, ``kappa_i = 1 / |y_i^H x_i|`` (unit left
and right eigenvectors); every eigenvalue moves by at most ``cond(V) ||E||`` (Bauer-Fike,
V the eigenvector matrix with unit columns). Forming M in double precision is such a
perturbation, ``||E|| ~ eps ||M||``: the loop as computed has its poles that far from the
designed ones, and a model error of relative size delta moves them ``delta / eps`` times
further. The condition numbers are taken on M balanced (scipy ``matrix_balance``), so
that states in other units do not change them; ``cond(V)`` on M as formed, in the
states' own units, where it bounds the transient growth below.

**Transient growth.** ``sup_t ||e^{M t}||_2`` (``sup_k ||M^k||_2``): how much larger
than its start an error (of the estimate, or of the whole loop) can become before it
decays, in the states' own units. A stable but non-normal M can grow by orders of
magnitude first; it is at most ``cond(V)``.

"""

from dataclasses import dataclass
import math

import numpy as np
import scipy.linalg
import scipy.optimize

from .pole_placement import eigenvector_condition

__all__ = ['PoleSensitivity', 'pole_sensitivity', 'transient_growth',
           'POLE_CONDITION_WARN', 'TRANSIENT_GROWTH_WARN']

_EPS = np.finfo(float).eps

#: Warned when a pole's condition number, or cond(V), exceeds this.
POLE_CONDITION_WARN = 1e4

#: Warned when an error can grow more than this before it decays.
TRANSIENT_GROWTH_WARN = 100.0


@dataclass(frozen=True)
class PoleSensitivity:
    """
    Condition numbers of a matrix's eigenvalues and what one rounding of it does.

    ``poles`` (eig of M), ``condition`` (kappa_i, M balanced), ``rounding_move``
    (``eps ||M_b|| kappa_i``: how far forming M in double precision moves each),
    ``eigenvector_condition`` (cond(V) of M as formed) and ``worst``, the index of the
    pole with the largest ``rounding_move / max(|lambda|, eps ||M||)``.

    """

    poles: np.ndarray
    condition: np.ndarray
    rounding_move: np.ndarray
    eigenvector_condition: float
    worst: int

    @property
    def max_condition(self):
        """Return the largest eigenvalue condition number."""
        return float(np.max(self.condition)) if self.condition.size else 1.0

    @property
    def relative_move(self):
        """``rounding_move / |lambda|`` at the worst pole."""
        if not self.poles.size:
            return 0.0
        lam = abs(self.poles[self.worst])
        return float(self.rounding_move[self.worst] / max(lam, 1e-300))

    @property
    def warn(self):
        """Return True above :data:`POLE_CONDITION_WARN`."""
        return max(self.max_condition, self.eigenvector_condition) > POLE_CONDITION_WARN

    def to_json(self):
        """Return a JSON-serialisable dict."""
        w = self.worst
        return {'max_condition': self.max_condition,
                'eigenvector_condition': (None if not np.isfinite(self.eigenvector_condition)
                                          else self.eigenvector_condition),
                'worst_pole': None if not self.poles.size else
                [float(self.poles[w].real), float(self.poles[w].imag)],
                'rounding_move': None if not self.poles.size else float(self.rounding_move[w]),
                'relative_move': self.relative_move, 'warn': self.warn}


def pole_sensitivity(M):
    """
    Return the :class:`PoleSensitivity` of a square matrix.

    Parameters
    ----------
    M : (N, N) array_like
        Closed-loop or error matrix.

    Returns
    -------
    PoleSensitivity

    """
    M = np.atleast_2d(np.asarray(M, dtype=float))
    if not M.size:
        z = np.zeros(0)
        return PoleSensitivity(z.astype(complex), z, z, 1.0, 0)
    Mb, _ = scipy.linalg.matrix_balance(M)
    lam, vl, vr = scipy.linalg.eig(Mb, left=True, right=True)
    dots = np.abs(np.sum(vl.conj() * vr, axis=0))
    kappa = 1.0 / np.maximum(dots, _EPS)
    norm = float(np.linalg.norm(Mb, 2))
    move = _EPS * norm * kappa
    floor = max(_EPS * norm, 1e-300)
    worst = int(np.argmax(move / np.maximum(np.abs(lam), floor)))
    return PoleSensitivity(lam, kappa, move, eigenvector_condition(M), worst)


def _decays(M, discrete):
    lam = np.linalg.eigvals(M)
    if discrete:
        return bool(np.all(np.abs(lam) < 1.0))
    return bool(np.all(lam.real < 0.0))


def transient_growth(M, discrete=False, points=160):
    """
    Return ``sup_t ||e^{M t}||_2`` (``sup_k ||M^k||_2``) and where it is reached.

    Parameters
    ----------
    M : (N, N) array_like
        A stable matrix (continuous time, or one step of a discrete loop).
    discrete : bool
        Powers instead of the exponential.
    points : int
        Continuous time: log-spaced times from ``0.01 / ||M||`` to 20 time constants of
        the slowest eigenvalue, then a local search around the largest.

    Returns
    -------
    growth : float
        At least 1 (t = 0); inf when M is not stable.
    t : float
        The time (s) or step count where it is reached.

    """
    M = np.atleast_2d(np.asarray(M, dtype=float))
    if not M.size:
        return 1.0, 0.0
    if not _decays(M, discrete):
        return math.inf, math.nan
    lam = np.linalg.eigvals(M)
    if discrete:
        rho = float(np.max(np.abs(lam)))
        steps = 1000 if rho == 0.0 else int(min(100000, max(10, 20.0 / -math.log(rho))))
        best, at, P = 1.0, 0, np.eye(M.shape[0])
        for k in range(1, steps + 1):
            P = M @ P
            g = float(np.linalg.norm(P, 2))
            if g > best:
                best, at = g, k
            if g < 1e-3 * best and k > 2 * at:
                break
        return best, float(at)
    slowest = float(np.min(-lam.real))
    norm = max(float(np.linalg.norm(M, 2)), 1e-300)
    t = np.logspace(math.log10(0.01 / norm), math.log10(20.0 / slowest), points)

    def growth(tt):
        return float(np.linalg.norm(scipy.linalg.expm(M * tt), 2))

    g = np.array([growth(tt) for tt in t])
    i = int(np.argmax(g))
    best, at = max(1.0, float(g[i])), float(t[i]) if g[i] > 1.0 else 0.0
    if g[i] > 1.0:
        lo = math.log(t[max(i - 1, 0)])
        hi = math.log(t[min(i + 1, t.size - 1)])
        res = scipy.optimize.minimize_scalar(lambda s: -growth(math.exp(s)), bounds=(lo, hi),
                                             method='bounded', options={'xatol': 1e-4})
        if -res.fun > best:
            best, at = float(-res.fun), float(math.exp(res.x))
    return best, at
