# observer_ros.core.estimators.steps: the exactly sampled model of a step, and its caches.
"""
The sampled step: ``Ad``, ``Bd`` of a step length, cached, and the grid of gain steps.

Every matrix is a function of the quantised step only (see :class:`StepCache`), so a
result never depends on what is already cached. Also the exact process noise of a step
(:func:`process_noise_covariance`).

"""

from collections import OrderedDict
import math

import numpy as np
import scipy.linalg

from ..errors import ObserverError
from ..model import as_matrix, Plant

__all__ = ['DT_DIGITS', 'GAIN_DIGITS', 'CACHE_SIZE', 'GAIN_CACHE_SIZE', 'StepCache',
           'process_noise_covariance']

#: Significant decimal digits kept of a step length (the cache key and the value
#: the matrices are computed from). Twelve digits represent any step that is a
#: whole number of nanoseconds below 1000 s exactly, change an irregular step by
#: at most 5e-12 of itself (10 digits left a 1e-9 relative error floor on the
#: unstable cart with random steps), and map the float jitter of ``t[k+1] - t[k]``
#: at a fixed rate to a handful of keys (at most 9 in an hour at 1 kHz).
DT_DIGITS = 12

#: Significant decimal digits of the steps the correction gains are designed for
#: (pole placement, reduced-order Lr, Kalman process noise): a grid of steps
#: (2 digits: ..., 0.0039, 0.0040, 0.0041, ... s, 90 per decade, 1 % to 10 %
#: apart). The gain of a step between two grid steps is interpolated linearly
#: between theirs; on a grid step it is the designed one. Propagation always uses
#: the step itself (``DT_DIGITS``). Time stamps of real sensors jitter, so nearly
#: every step is new to twelve digits: it then costs one matrix exponential (tens
#: of microseconds) and an interpolation, while pole placements (0.1 to 10 ms
#: each) run once per grid step, a few dozen for a jittering rate. The gains are
#: smooth in the step, so the interpolated gain places the poles to about
#: ``(spacing / step)^2 / 8`` of themselves (1e-3 at worst for 2 digits); a
#: noise-free run still converges to round-off, since the propagation is exact and
#: the error obeys a homogeneous recursion.
GAIN_DIGITS = 2

#: Number of step lengths whose matrices are kept (least recently used ones are
#: dropped).
CACHE_SIZE = 64

#: Steps remembered by the exact float dt they were asked for (:meth:`StepCache.step`):
#: stamps on a regular grid give a handful of distinct dt, so the key's decimal rounding
#: is skipped for most messages. Emptied when full or when a step leaves the cache.
BY_DT_SIZE = 64

#: Number of grid steps whose gains are kept: all those a jittering rate meets
#: must fit (about 90 per decade of step lengths), or gains would be designed again.
GAIN_CACHE_SIZE = 1024

#: Significant digits of the base steps a new continuous step is factored on:
#: ``expm(M key) = expm(M base) expm(M (key - base))``, the first from a cache of base
#: steps (0.00400, 0.00401, ... s: a jittering rate meets a few dozen), the second a
#: short Taylor series. Both are the same matrix function of commuting arguments, so
#: the product is the exponential of the step itself to round-off (tested against
#: ``scipy.linalg.expm``). A few small matrix products instead of scipy's expm: the
#: same time in a tight loop, but far less code to run cold between two messages of
#: a node (benchmarks/README.md, P1).
BASE_DIGITS = 3

#: The factored exponential is used when ``|M (key - base)|_1`` is at most this (the
#: Taylor series then needs at most 8 terms); otherwise ``scipy.linalg.expm``.
FACTOR_NORM_MAX = 0.02

#: Base steps kept (their exponentials); the cache is emptied when it is full.
BASE_CACHE_SIZE = 4096

#: A step of a discrete plant may differ from a whole number of sample times by
#: this fraction of the sample time (time-stamp rounding).
DISCRETE_STEP_TOL = 1e-6


def process_noise_covariance(A, Qc, dt, G=None):
    """
    Exact covariance of the process noise accumulated over one step (Van Loan).

    For x' = A x + G w with w white of intensity Qc, the noise added over a step
    dt is ``Qd = int_0^dt expm(A s) G Qc G^T expm(A^T s) ds``. It is computed
    from one matrix exponential: with ``E = expm([[-A, G Qc G^T], [0, A^T]] dt)``,
    ``Phi = E22^T = expm(A dt)`` and ``Qd = Phi E12``.

    Parameters
    ----------
    A : (n, n) array_like
        State matrix of the continuous plant.
    Qc : (k, k) array_like
        Intensity (power spectral density) of w.
    dt : float
        Step length, > 0.
    G : (n, k) array_like, optional
        Noise input matrix; default the identity (k = n).

    Returns
    -------
    Qd : (n, n) ndarray
        Symmetric positive semidefinite.

    References
    ----------
    C. F. Van Loan, "Computing integrals involving the matrix exponential",
    IEEE Trans. Automatic Control 23(3), 1978.

    """
    A = as_matrix(A, 'A', square=True)
    n = A.shape[0]
    G = np.eye(n) if G is None else as_matrix(G, 'G', rows=n)
    Qc = as_matrix(Qc, 'Qc', rows=G.shape[1], cols=G.shape[1])
    if not (dt > 0.0 and math.isfinite(dt)):
        raise ObserverError(f'step must be positive and finite; got {dt!r}')
    M = np.zeros((2 * n, 2 * n))
    M[:n, :n] = -A * dt
    M[:n, n:] = G @ Qc @ G.T * dt
    M[n:, n:] = A.T * dt
    E = scipy.linalg.expm(M)
    Qd = E[n:, n:].T @ E[:n, n:]
    return 0.5 * (Qd + Qd.T)


def discrete_noise(A, GQG, k):
    """Covariance sum_{i<k} A^i GQG A^iT of k steps of a discrete plant."""
    Q = np.zeros_like(GQG)
    term = GQG.copy()
    for _ in range(k):
        Q += term
        term = A @ term @ A.T
    return 0.5 * (Q + Q.T)


def _grid_step(mant, exp):
    """Return the float of the decimal number mant * 10**exp (correctly rounded)."""
    return float(f'{mant}e{exp}')


def bracket(key, digits):
    """
    Grid steps g0 <= key < g1 of ``digits`` significant digits and the weight of g1.

    Returns ``(key_on_grid, None, 0.0)`` when key is a grid step (to 1e-12 of
    itself); a function of key only.

    """
    text = format(key, f'.{digits - 1}e')          # d.ddd e+XX: nearest grid step
    mantissa, exponent = text.split('e')
    mant = int(mantissa.replace('.', ''))
    exp = int(exponent) - (digits - 1)
    near = _grid_step(mant, exp)
    if abs(key - near) <= 1e-12 * key:
        return near, None, 0.0
    low, high = 10 ** (digits - 1), 10 ** digits
    if near < key:
        m1, e1 = (mant + 1, exp) if mant + 1 < high else (low, exp + 1)
        g0, g1 = near, _grid_step(m1, e1)
    else:
        m0, e0 = (mant - 1, exp) if mant - 1 >= low else (high - 1, exp - 1)
        g0, g1 = _grid_step(m0, e0), near
    return g0, g1, (key - g0) / (g1 - g0)


def check_plant(plant):
    """Return ``plant``; raise ObserverError when it is not a core.model.Plant."""
    if not isinstance(plant, Plant):
        raise ObserverError(f'plant must be an observer_ros.core.model.Plant; got '
                            f'{type(plant).__name__}')
    return plant


class _Step:
    """Matrices of one step length: Ad, Bd and whatever an estimator derives from them."""

    __slots__ = ('key', 'h', 'k', 'Ad', 'Bd', 'extra')

    def __init__(self, key, h, k, Ad, Bd):
        self.key = key
        self.h = h
        self.k = k
        self.Ad = Ad
        self.Bd = Bd
        self.extra = {}


class StepCache:
    """
    Least-recently-used cache of the exactly sampled model, keyed by the step length.

    For a continuous plant the key of a step dt is dt rounded to ``digits``
    significant decimal digits, and ``Ad = expm(A key)``, ``Bd`` (exact ZOH,
    :func:`~observer_ros.core.model.zoh_matrices`) are computed from the key
    itself, so a result never depends on which step of a bucket came first. For a
    discrete plant the key is the whole number of sample times k, with
    ``Ad = A^k`` and ``Bd = sum_{i<k} A^i B``; a step that is not a whole number
    of sample times raises :class:`~observer_ros.core.errors.ObserverError`.

    Parameters
    ----------
    plant : Plant
        The model.
    digits : int
        Significant digits of a continuous step kept in the key.
    size : int
        Number of step lengths kept.

    """

    def __init__(self, plant, digits=DT_DIGITS, size=CACHE_SIZE):
        self._plant = check_plant(plant)
        if int(digits) < 3 or int(digits) > 17:
            raise ObserverError(f'dt_digits must be between 3 and 17; got {digits!r}')
        if int(size) < 1:
            raise ObserverError(f'cache_size must be at least 1; got {size!r}')
        self._fmt = f'.{int(digits)}g'
        self._size = int(size)
        self._steps = OrderedDict()
        self._by_dt = {}                # dt as given -> its step (the key's rounding skipped)
        self._Ts = plant.dt
        n, m = plant.n, plant.m
        # [[A, B], [0, 0]]: expm(aug * h) holds Ad and Bd (zoh_matrices, without its checks)
        self._aug = np.zeros((n + m, n + m))
        self._aug[:n, :n] = plant.A
        self._aug[:n, n:] = plant.B
        self._aug_norm = float(np.abs(self._aug).sum(axis=0).max())     # 1-norm
        self._base = {}                 # base step -> expm(aug * base)
        self._eye = np.eye(n + m)

    def __len__(self):
        return len(self._steps)

    def key(self, dt):
        """
        Return the cache key of a step of ``dt`` seconds (dt > 0).

        Parameters
        ----------
        dt : float
            Step length in seconds.

        Returns
        -------
        key : float or int
            The rounded step (continuous plant) or the number of samples (discrete).

        """
        Ts = self._Ts
        if Ts is None:
            return float(format(dt, self._fmt))
        k = round(dt / Ts)
        if k < 1 or abs(dt - k * Ts) > DISCRETE_STEP_TOL * Ts:
            raise ObserverError(
                f'the plant is discrete with sample time {Ts:g} s: a step of {dt:.9g} s '
                f'({dt / Ts:.6g} samples) is not a whole number of samples')
        return int(k)

    def get(self, key):
        """
        Return the step entry of a key (computed on a miss).

        Parameters
        ----------
        key : float or int
            From :meth:`key`.

        Returns
        -------
        step : object
            With attributes ``h`` (seconds), ``k`` (samples or None), ``Ad``,
            ``Bd`` and ``extra`` (a dict the estimators cache their gains in).

        """
        steps = self._steps
        step = steps.get(key)
        if step is not None:
            steps.move_to_end(key)
            return step
        plant = self._plant
        if self._Ts is None:
            n = plant.n
            E = self._exponential(key)
            step = _Step(key, key, None, E[:n, :n].copy(), E[:n, n:].copy())
        else:
            n = plant.n
            aug = np.eye(n + plant.m)
            aug[:n, :n] = plant.A
            aug[:n, n:] = plant.B
            P = np.linalg.matrix_power(aug, key)
            step = _Step(key, key * self._Ts, key, P[:n, :n].copy(), P[:n, n:].copy())
        steps[key] = step
        if len(steps) > self._size:
            steps.popitem(last=False)
            self._by_dt.clear()         # none of them holds a step no longer kept
        return step

    def _exponential(self, key):
        """
        Return ``expm(aug * key)``, factored on a cached base step when the rest is small.

        ``expm(M base) @ expm(M d)`` with ``d = key - base``: the Taylor series of the
        second factor is summed until a term is below 1e-17 (at most 8 terms, see
        ``FACTOR_NORM_MAX``).

        """
        base = float(format(key, f'.{BASE_DIGITS - 1}e'))
        d = key - base
        if d == 0.0 or abs(d) * self._aug_norm > FACTOR_NORM_MAX:
            return scipy.linalg.expm(self._aug * key)
        E0 = self._base.get(base)
        if E0 is None:
            if len(self._base) >= BASE_CACHE_SIZE:
                self._base.clear()
            E0 = self._base[base] = scipy.linalg.expm(self._aug * base)
        Md = self._aug * d
        term = Md
        T = self._eye + Md
        for k in range(2, 12):
            term = (term @ Md) * (1.0 / k)
            T += term
            if np.abs(term).max() <= 1e-17:
                break
        return E0 @ T

    def step(self, dt):
        """
        Return the step entry for a step of ``dt`` seconds.

        Parameters
        ----------
        dt : float
            Step length in seconds, > 0.

        Returns
        -------
        step : object
            See :meth:`get`.

        """
        step = self._by_dt.get(dt)
        if step is None:
            step = self.get(self.key(dt))
            by_dt = self._by_dt
            if len(by_dt) >= BY_DT_SIZE:
                by_dt.clear()
            by_dt[dt] = step
        return step
