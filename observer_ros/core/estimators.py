# observer_ros.core.estimators: the estimator step shared by the observer node and bag replay.
"""
State estimators stepped at the times the measurements arrive.

The same calls in the same order give bit-identical estimates: the step has no
randomness, no wall clock and no dependence on what is already cached (every
matrix is a function of the quantised step only, see :class:`StepCache`). The
ROS observer node and the offline bag replay both drive these classes.

Two keys per step: the state is propagated with the exact sampled model of the
step rounded to ``dt_digits`` (12) significant digits, while correction gains
(pole placement, reduced-order Lr, Kalman process noise) are designed for the
step rounded to ``gain_digits`` (3). Real time stamps jitter, so nearly every
step is new to twelve digits; it then costs a matrix exponential, not a pole
placement (see :data:`GAIN_DIGITS`).

Time is a float in seconds. Keep it small: pass times relative to the start of
a run (a float holding Unix time has a resolution of about 0.2 microseconds,
which would make every step different).

Estimators
----------
:class:`FullOrderEstimator`
    Luenberger observer in current (filter) form, exact at any sample times.
:class:`ReducedOrderEstimator`
    Reduced-order observer (seeds 000 section 3.5 and 002 section 5.4.2) that
    reproduces the measured combinations C x_hat = y - D u exactly.
:class:`OpenLoopEstimator`
    The model alone; measurements only give a residual.
:class:`KalmanEstimator`
    Time-varying discrete Kalman filter on the exactly sampled model.

"""

from collections import OrderedDict
import math

import numpy as np
import scipy.linalg

from .analysis import is_stable_eigenvalue, observable_decomposition, stability_margin
from .design import observer_gain, pole_placement_error, reduced_coordinates
from .errors import DesignError, DimensionError, NotDetectableError, ObserverError
from .model import as_matrix, as_poles, as_vector, Plant
from .spec import OBSERVER_TYPES, ObserverSpec

__all__ = ['DT_DIGITS', 'GAIN_DIGITS', 'CACHE_SIZE', 'GAIN_CACHE_SIZE', 'TimeOrderError',
           'StepCache', 'Estimator', 'FullOrderEstimator',
           'ReducedOrderEstimator', 'OpenLoopEstimator', 'KalmanEstimator',
           'make_estimator', 'process_noise_covariance']

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

#: A gain from the quick placement (:func:`_quick_gain`) is kept only if its poles
#: are within this relative error (``design.pole_placement_error``) of those asked
#: for; otherwise the full design (place and acker compared) runs.
QUICK_PLACE_TOL = 1e-10


class TimeOrderError(ObserverError, ValueError):
    """A time is before the time of the current estimate (the clock went backwards)."""


# ---------------------------------------------------------------- helpers


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


def _discrete_noise(A, GQG, k):
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


def _bracket(key, digits):
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


def _pick_poles(z, count):
    """
    Choose ``count`` of the desired z-plane poles ``z`` (conjugate pairs kept).

    The fastest poles (smallest ``|z|``) are taken first. When only one place is
    left for a complex pair, the real pole ``|z|`` (same decay) is used.

    """
    z = np.asarray(z, dtype=complex)
    if z.size == count:
        return z
    if z.size < count:
        raise DesignError(f'{count} poles are needed but only {z.size} were given')
    tol = 1e-9 * max(1.0, float(np.max(np.abs(z))))
    order = sorted(range(z.size), key=lambda i: (abs(z[i]), -z[i].imag, z[i].real))
    used = set()
    chosen = []
    for i in order:
        if len(chosen) == count:
            break
        if i in used:
            continue
        used.add(i)
        if abs(z[i].imag) <= tol:
            chosen.append(complex(z[i].real))
            continue
        partner = [j for j in order if j not in used and abs(z[j] - np.conj(z[i])) <= tol]
        if partner:
            used.add(partner[0])
        if len(chosen) + 2 <= count:
            chosen.extend([z[i], np.conj(z[i])])
        else:
            chosen.append(complex(abs(z[i])))
    return np.array(chosen, dtype=complex)


def _quick_gain(A, C, z, method):
    """
    M with eig(A - M C) = z by one direct formula, or None when it is not accurate.

    One output (``auto`` or ``acker``): Ackermann's formula for the observer,
    ``M = phi(A) O^-1 e_n`` with ``O = [C; C A; ...; C A^(n-1)]`` and phi the
    polynomial with roots z (tens of microseconds). Then, for ``auto`` when
    Ackermann lost digits, for several outputs, or for ``place``: scipy's
    ``place_poles`` on the dual (what python-control's place calls; about a
    millisecond). A result is kept only if its placed poles are within
    :data:`QUICK_PLACE_TOL` of z, where neither method can lose to the other by
    much, so it stands for the comparison ``design.observer_gain`` makes (several
    milliseconds: decompositions, both methods, four pole errors). Every failure
    (singular O, repeated poles, loss of digits) returns None.

    """
    p = C.shape[0]
    if p == 1 and method in ('auto', 'acker'):
        M = _checked(A, C, z, _ackermann)
        if M is not None or method == 'acker':
            return M
    if method in ('auto', 'place'):
        return _checked(A, C, z, _place_poles)
    return None


def _ackermann(A, C, z):
    n = A.shape[0]
    obsv = np.empty((n, n))
    row = C[0]
    for i in range(n):
        obsv[i] = row
        row = row @ A
    coeffs = np.poly(z).real
    P = np.eye(n)
    for c in coeffs[1:]:
        P = P @ A
        P.flat[::n + 1] += c
    e = np.zeros(n)
    e[-1] = 1.0
    return (P @ np.linalg.solve(obsv, e)).reshape(n, 1)


def _place_poles(A, C, z):
    import scipy.signal
    return scipy.signal.place_poles(A.T, C.T, z, method='YT').gain_matrix.T


def _checked(A, C, z, formula):
    try:
        M = formula(A, C, z)
    except (ValueError, np.linalg.LinAlgError):
        return None
    if not np.all(np.isfinite(M)) or pole_placement_error(A - M @ C, z) > QUICK_PLACE_TOL:
        return None
    return np.ascontiguousarray(M, dtype=float)


def _place(A, C, zpoles, method):
    """
    Gain M with the observable part of eig(A - M C) at (some of) ``zpoles``.

    The quick formula of :func:`_quick_gain` is tried first (all n poles, checked).
    Otherwise, when (A, C) is observable all n poles are placed
    (design.observer_gain). Otherwise the pair is split by the orthogonal
    observable decomposition ``T^T A T = [[Ao, 0], [A21, Au]]``, ``C T = [Co, 0]``;
    r = rank poles are chosen by :func:`_pick_poles` and placed for (Ao, Co), and
    the unobservable eigenvalues eig(Au) are kept: ``M = T[:, :r] Mo``.

    """
    n = A.shape[0]
    if len(zpoles) == n:
        M = _quick_gain(A, C, np.asarray(zpoles, dtype=complex), method)
        if M is not None:
            return M
    _, _, _, T, r = observable_decomposition(A, None, C)
    if r == n:
        return observer_gain(A, C, _pick_poles(zpoles, n), method)
    if r == 0:
        return np.zeros((n, C.shape[0]))
    To = T[:, :r]
    Mo = observer_gain(To.T @ A @ To, C @ To, _pick_poles(zpoles, r), method)
    return To @ Mo


def _check_plant(plant):
    if not isinstance(plant, Plant):
        raise ObserverError(f'plant must be an observer_ros.core.model.Plant; got '
                            f'{type(plant).__name__}')
    return plant


def _measured_rows(plant, measured_rows):
    if measured_rows is None:
        return tuple(range(plant.p))
    rows = _as_rows(measured_rows, 'measured_rows', plant)
    if not rows:
        raise DimensionError('measured_rows is empty; an estimator needs at least one output')
    return tuple(sorted(rows))


def _as_rows(rows, name, plant):
    try:
        out = tuple(int(r) for r in np.asarray(rows).reshape(-1))
    except (TypeError, ValueError):
        raise DimensionError(f'{name} must be a list of output indices; got {rows!r}') from None
    for r in out:
        if not 0 <= r < plant.p:
            raise DimensionError(f'{name} has index {r}; the plant has {plant.p} outputs '
                                 f'{list(plant.output_names)}')
    if len(set(out)) != len(out):
        raise DimensionError(f'{name} has duplicate indices: {list(out)}')
    return out


def _unobservable_check(A, C, discrete, what):
    """Rank of (A, C); raise NotDetectableError if an unobservable mode is not stable."""
    Abar, _, _, _, r = observable_decomposition(A, None, C)
    n = A.shape[0]
    if r < n:
        margin = stability_margin(A)
        for lam in np.linalg.eigvals(Abar[r:, r:]):
            if not is_stable_eigenvalue(lam, discrete, margin):
                raise NotDetectableError(
                    f'{what}: (A, C) is not detectable: the unobservable eigenvalue '
                    f'{complex(lam):.6g} is not stable')
    return r


# ---------------------------------------------------------------- step cache


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
        self._plant = _check_plant(plant)
        if int(digits) < 3 or int(digits) > 17:
            raise ObserverError(f'dt_digits must be between 3 and 17; got {digits!r}')
        if int(size) < 1:
            raise ObserverError(f'cache_size must be at least 1; got {size!r}')
        self._fmt = f'.{int(digits)}g'
        self._size = int(size)
        self._steps = OrderedDict()
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
        return self.get(self.key(dt))


class _Rows:
    """A validated set of output rows with its parts of C and D."""

    __slots__ = ('rows', 'idx', 'C', 'D', 'names', 'is_sorted')

    def __init__(self, plant, rows):
        self.rows = rows
        self.is_sorted = list(rows) == sorted(rows)
        self.idx = np.array(rows, dtype=np.intp)
        self.C = plant.C[self.idx]
        self.D = plant.D[self.idx]
        self.names = [plant.output_names[r] for r in rows]


# ---------------------------------------------------------------- base class


class Estimator:
    """
    Base class: time keeping, held input, propagation and the public step calls.

    An estimator holds x_hat at time t. Every call that carries a time first
    propagates x_hat from its time to the new one with the held input u
    (zero-order hold on u, exact sampled model of the step). Times must not go
    backwards; equal times are allowed (several messages with one time stamp).

    Parameters
    ----------
    plant : Plant
        The model (continuous, or discrete with sample time ``plant.dt``).
    x0 : array_like, optional
        Initial estimate (n); default zeros.
    t0 : float, optional
        Time of x0 in seconds; default None: the time of the first call.
    measured_rows : sequence of int, optional
        The outputs (rows of C) the estimator may be given; default all.
    dt_digits : int
        Significant digits of a step length kept for propagation (see
        :class:`StepCache`). The default keeps the step exact to 5e-12; a new
        step length costs one matrix exponential (tens of microseconds), a known
        one a few microseconds.
    cache_size : int
        Number of step lengths whose propagation matrices are kept.
    gain_digits : int
        Significant digits of the grid of steps the correction gains are
        designed for, interpolated in between (see :data:`GAIN_DIGITS`); 2 to
        17. A new grid step costs a pole placement (0.1 to 10 ms), so with
        stamps that jitter a few dozen are designed once and reused.
        ``gain_digits >= dt_digits`` designs the gain of every step exactly (a
        pole placement for every new step).

    """

    kind = 'base'

    def __init__(self, plant, x0=None, t0=None, measured_rows=None,
                 dt_digits=DT_DIGITS, cache_size=CACHE_SIZE, gain_digits=GAIN_DIGITS):
        self._plant = _check_plant(plant)
        n = plant.n
        self._x0 = np.zeros(n) if x0 is None else as_vector(x0, 'x0', n)
        self._t0 = None if t0 is None else self._as_time(t0)
        self._measured = _measured_rows(plant, measured_rows)
        self._measured_set = frozenset(self._measured)
        self._cache = StepCache(plant, dt_digits, cache_size)
        if not 2 <= int(gain_digits) <= 17:
            raise ObserverError(f'gain_digits must be between 2 and 17; got {gain_digits!r}')
        self._gain_digits = int(gain_digits)
        if plant.is_discrete or int(gain_digits) >= int(dt_digits):
            self._gain_cache = None          # gains designed on the propagation step itself
        else:
            # keyed by grid steps (exact decimal numbers), computed by gain_steps
            self._gain_cache = StepCache(plant, DT_DIGITS, GAIN_CACHE_SIZE)
        self._rows_cache = {}
        self._all = self._rows_info(self._measured, 'rows')
        self._x = np.zeros(n)
        self._u = np.zeros(plant.m)
        self._buf = np.zeros(n)
        self._t = None
        self._t_anchor = None
        self._residual = None
        self._residual_rows = None

    # ------------------------------------------------------------ properties

    @property
    def plant(self):
        """Return the model (Plant)."""
        return self._plant

    @property
    def n(self):
        """Return the number of states."""
        return self._plant.n

    @property
    def measured_rows(self):
        """Return the output rows this estimator accepts (tuple of int)."""
        return self._measured

    @property
    def x_hat(self):
        """Return the estimate at time :attr:`t` (a copy, ndarray of n)."""
        return self._x.copy()

    @property
    def t(self):
        """Time of :attr:`x_hat` in seconds, or None before the first call."""
        return self._t

    @property
    def u(self):
        """Return the held input (a copy, ndarray of m); zeros until set."""
        return self._u.copy()

    @property
    def residual(self):
        """Last ``y - (C x_prior + D u)`` for the rows of the last correction, or None."""
        return None if self._residual is None else self._residual.copy()

    @property
    def residual_rows(self):
        """Return the output rows of :attr:`residual` (tuple of int), or None."""
        return self._residual_rows

    @property
    def cache(self):
        """Return the :class:`StepCache` of this estimator (propagation matrices)."""
        return self._cache

    @property
    def gain_cache(self):
        """Return the :class:`StepCache` the gains are designed on (:attr:`cache` if the same)."""
        return self._cache if self._gain_cache is None else self._gain_cache

    def gain_steps(self, key):
        """
        Return the grid steps whose gains make the gain of a step, and the weight.

        Parameters
        ----------
        key : float or int
            From ``cache.key(dt)``.

        Returns
        -------
        g0, g1 : float or int
            The grid steps (``gain_digits`` significant digits) with
            ``g0 <= key < g1``; ``g1`` is None when ``key`` is a grid step, or for a
            discrete plant (``g0 = key`` samples) or gain_digits >= dt_digits
            (``g0 = key``).
        w : float
            The gain is ``(1 - w) M(g0) + w M(g1)``, ``w = (key - g0) / (g1 - g0)``.
            A function of ``key`` only.

        """
        if self._gain_cache is None:
            return key, None, 0.0
        return _bracket(key, self._gain_digits)

    def _gain_value(self, key, name, design):
        """
        Return a gain (or Kalman noise) of a step: designed on the grid, interpolated.

        ``name`` identifies the value in the steps' ``extra`` dicts; the interpolated
        value is cached on the step of ``key`` itself.

        """
        step = self._cache.get(key)
        value = step.extra.get(name)
        if value is not None:
            return value
        if self._gain_cache is None:
            value = design(step)
        else:
            g0, g1, w = _bracket(key, self._gain_digits)
            value = self._grid_value(g0, name, design)
            if g1 is not None:
                value = (1.0 - w) * value + w * self._grid_value(g1, name, design)
        step.extra[name] = value
        return value

    def _grid_value(self, g, name, design):
        step = self._gain_cache.get(g)
        value = step.extra.get(name)
        if value is None:
            value = design(step)
            step.extra[name] = value
        return value

    # ------------------------------------------------------------ public steps

    def reset(self, x0=None, t0=None):
        """
        Go back to an initial estimate (for example when the clock jumps back).

        The held input goes back to zeros and the residual to None. The cached
        matrices and gains are kept: they depend on the step length only.

        Parameters
        ----------
        x0 : array_like, optional
            New initial estimate; default the one given to the constructor.
        t0 : float, optional
            Its time; default None (the time of the next call).

        """
        x0 = self._x0 if x0 is None else as_vector(x0, 'x0', self._plant.n)
        self._x[:] = x0
        self._u[:] = 0.0
        self._t = None if t0 is None else self._as_time(t0)
        self._t_anchor = self._t
        self._residual = None
        self._residual_rows = None
        self._reset_state()

    def set_input(self, t, u):
        """
        Propagate to t with the previous input, then hold u from t on.

        Parameters
        ----------
        t : float
            Time in seconds, not before :attr:`t`.
        u : array_like
            The input (m).

        Raises
        ------
        TimeOrderError
            If t is before :attr:`t`.

        """
        t = self._check_time(t)
        u = self._as_input(u)
        self._advance(t)
        self._u[:] = u

    def predict(self, t):
        """
        Propagate x_hat to t with the held input (no measurement).

        Parameters
        ----------
        t : float
            Time in seconds, not before :attr:`t`.

        Returns
        -------
        x_hat : ndarray
            The estimate at t.

        """
        self._advance(self._check_time(t))
        return self._x.copy()

    def correct(self, t, y, rows=None):
        """
        Propagate to t, then correct with the measured outputs y of the given rows.

        Parameters
        ----------
        t : float
            Time of the measurement in seconds, not before :attr:`t`.
        y : array_like
            Measured values (with their D u part) of the outputs ``rows``, in that
            order.
        rows : sequence of int, optional
            Indices of the outputs (rows of C); default all measured rows.

        Returns
        -------
        x_hat : ndarray
            The estimate at t.

        Notes
        -----
        The residual ``y - (C[rows] x_prior + D[rows] u)`` is stored in
        :attr:`residual`; u is the input held before this call.

        """
        t = self._check_time(t)
        info = self._all if rows is None else self._rows_info(rows, 'rows')
        y = self._as_measurement(y, info)
        self._advance(t)
        self._correct(y, info)
        self._residual_rows = info.rows
        return self._x.copy()

    def update(self, t, u=None, y=None, rows=None):
        """
        Propagate to t, correct with y if given, then hold u if given.

        Parameters
        ----------
        t : float
            Time in seconds.
        u : array_like, optional
            Input applied from t on.
        y : array_like, optional
            Measurement at t of the outputs ``rows``.
        rows : sequence of int, optional
            See :meth:`correct`.

        Returns
        -------
        x_hat : ndarray
            The estimate at t.

        """
        t = self._check_time(t)
        u = None if u is None else self._as_input(u)
        if y is not None:
            self.correct(t, y, rows)
        else:
            self._advance(t)
        if u is not None:
            self._u[:] = u
        return self._x.copy()

    # ------------------------------------------------------------ internals

    @staticmethod
    def _as_time(t):
        try:
            t = float(t)
        except (TypeError, ValueError):
            raise ObserverError(f'time must be a number of seconds; got {t!r}') from None
        if not math.isfinite(t):
            raise ObserverError(f'time must be finite; got {t!r}')
        return t

    def _check_time(self, t):
        t = self._as_time(t)
        if self._t is not None and t < self._t:
            raise TimeOrderError(
                f'time {t!r} s is before the time of the estimate {self._t!r} s; '
                'call reset() to start again')
        return t

    def _as_input(self, u):
        u = np.asarray(u, dtype=float).reshape(-1)
        if u.size != self._plant.m:
            raise DimensionError(f'u has {u.size} elements; expected {self._plant.m} '
                                 f'({list(self._plant.input_names)})')
        if not np.isfinite(u).all():
            raise DimensionError(f'u has non-finite entries: {u}')
        return u

    def _as_measurement(self, y, info):
        y = np.asarray(y, dtype=float).reshape(-1)
        if y.size != len(info.rows):
            raise DimensionError(f'y has {y.size} elements; expected {len(info.rows)} '
                                 f'(outputs {info.names})')
        if not np.isfinite(y).all():
            raise DimensionError(f'y has non-finite entries: {y} (outputs {info.names})')
        return y

    def _rows_info(self, rows, name):
        kind = type(rows)
        key = rows if kind is tuple else tuple(rows) if kind is list else None
        if key is not None:
            info = self._rows_cache.get(key)
            if info is not None:
                return info
        rows = _as_rows(rows, name, self._plant)
        info = self._rows_cache.get(rows)
        if info is not None:
            return info
        if not rows:
            raise DimensionError(f'{name} is empty')
        extra = [r for r in rows if r not in self._measured_set]
        if extra:
            names = [self._plant.output_names[r] for r in extra]
            raise DimensionError(
                f'{name} has output(s) {names} that this estimator does not measure; '
                f'measured outputs are {[self._plant.output_names[r] for r in self._measured]}')
        info = _Rows(self._plant, rows)
        if len(self._rows_cache) < 256:
            self._rows_cache[rows] = info
        return info

    def _advance(self, t):
        if self._t is None:
            self._t = t
            if self._t_anchor is None:
                self._t_anchor = t
            return
        dt = t - self._t
        if dt > 0.0:
            self._propagate(self._cache.step(dt))
            self._t = t

    def _propagate_model(self, step):
        buf = self._buf
        np.dot(step.Ad, self._x, out=buf)
        buf += step.Bd @ self._u
        self._x, self._buf = buf, self._x

    # hooks ----------------------------------------------------------------

    def _reset_state(self):
        pass

    def _propagate(self, step):
        self._propagate_model(step)

    def _correct(self, y, info):
        raise NotImplementedError


# ---------------------------------------------------------------- open loop


class OpenLoopEstimator(Estimator):
    """
    The model alone: x_hat is propagated with (Ad, Bd) and never corrected.

    A measurement only sets :attr:`residual`. The error obeys ``e_{k+1} = Ad e_k``:
    it dies out on a stable plant and grows on an unstable one (seed 004).

    Parameters
    ----------
    plant : Plant
        The model.
    x0, t0, measured_rows, dt_digits, cache_size, gain_digits
        See :class:`Estimator`.

    """

    kind = 'open_loop'

    def __init__(self, plant, x0=None, t0=None, measured_rows=None,
                 dt_digits=DT_DIGITS, cache_size=CACHE_SIZE, gain_digits=GAIN_DIGITS):
        super().__init__(plant, x0, t0, measured_rows, dt_digits, cache_size, gain_digits)
        self.reset(t0=self._t0)

    def _correct(self, y, info):
        self._residual = y - info.D @ self._u - info.C @ self._x
        self._t_anchor = self._t


# ---------------------------------------------------------------- current form


class _CurrentForm(Estimator):
    """
    Estimators whose correction is ``x+ = x- + M(h, rows) (ybar - C x-)``.

    h is the time since the previous correction (or since the initial estimate),
    so predictions in between do not change the error dynamics from one
    correction to the next, ``e+ <- (I - M C) Ad(h) e+``. Several corrections
    at one time are fused: the correction is recomputed from the prior at that
    time with all the rows received at that time (ybar = y - D u of each row as
    received).

    """

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        p = self._plant.p
        n = self._plant.n
        self._x_prior = np.zeros(n)
        self._acc = np.zeros(p)
        self._acc_rows = set()
        self._acc_key = None
        self._t_corr = None
        self._init_gains = {}

    def _reset_state(self):
        self._acc_rows = set()
        self._acc_key = None
        self._t_corr = None

    def _correct(self, y, info):
        t = self._t
        ybar = y - info.D @ self._u
        if self._t_corr is None or t != self._t_corr:
            h = t - self._t_anchor
            self._acc_key = None if h <= 0.0 else self._cache.key(h)
            np.copyto(self._x_prior, self._x)
            self._acc_rows = set(info.rows)
            self._t_corr = t
            union = info if info.is_sorted else \
                self._rows_info(tuple(sorted(info.rows)), 'rows')
        else:
            self._acc_rows.update(info.rows)
            union = self._rows_info(tuple(sorted(self._acc_rows)), 'rows')
        self._acc[info.idx] = ybar
        self._residual = ybar - info.C @ self._x_prior
        self._t_anchor = t
        M = self._gain(self._acc_key, union)
        if M is None:
            np.copyto(self._x, self._x_prior)
            return
        innov = self._acc[union.idx] - union.C @ self._x_prior
        np.dot(M, innov, out=self._buf)
        self._buf += self._x_prior
        self._x, self._buf = self._buf, self._x

    def _gain(self, key, info):
        """Return M (n x len(info.rows)) for the interval key, or None (no correction)."""
        raise NotImplementedError

    def _zpoles(self, step):
        if step.k is None:
            return np.exp(self._poles * step.h)
        return self._poles ** step.k

    def correction_gain(self, dt, rows=None):
        """
        Return the gain M of a correction that comes dt seconds after the previous one.

        Parameters
        ----------
        dt : float
            Time since the previous correction, > 0.
        rows : sequence of int, optional
            Output rows of the correction; default all measured rows.

        Returns
        -------
        M : (n, len(rows)) ndarray
            ``x+ = x- + M (y - D u - C[rows] x-)``.

        """
        info = self._all if rows is None else self._rows_info(tuple(sorted(
            _as_rows(rows, 'rows', self._plant))), 'rows')
        return self._gain(self._cache.key(self._as_time(dt)), info).copy()

    def error_matrix(self, dt, rows=None):
        """
        Return the error transition from one correction to the next, dt seconds later.

        Parameters
        ----------
        dt : float
            Time between the corrections, > 0.
        rows : sequence of int, optional
            Output rows of the second correction; default all measured rows.

        Returns
        -------
        F : (n, n) ndarray
            ``e+_{k+1} = F e+_k`` with ``F = (I - M C[rows]) Ad(dt)``; its
            eigenvalues are the z-plane observer poles exp(s dt).

        """
        info = self._all if rows is None else self._rows_info(tuple(sorted(
            _as_rows(rows, 'rows', self._plant))), 'rows')
        step = self._cache.step(self._as_time(dt))
        M = self._gain(step.key, info)
        return (np.eye(self._plant.n) - M @ info.C) @ step.Ad


# ---------------------------------------------------------------- full order


class FullOrderEstimator(_CurrentForm):
    """
    Full-order Luenberger observer, exact at any (irregular) sample times.

    With poles, the observer runs in current (filter) form so that x_hat at t
    uses y(t)::

        x-  = Ad(dt) x+ + Bd(dt) u                    (propagate, ZOH on u)
        x+  = x- + M (y - D u - C x-)                 (correct)

    The error of two successive corrections h seconds apart obeys
    ``e+ <- (I - M C) Ad(h) e+``, and ``eig((I - M C) Ad) = eig(Ad - M (C Ad))``,
    so M is designed on the pair (Ad(h), C Ad(h)) with the z-plane poles
    ``exp(s h)`` (continuous plant, s the given poles) or ``z^k`` (discrete
    plant, k samples). For a continuous plant h is the step rounded to
    ``gain_digits`` significant digits (Ad of the step itself propagates), so
    with a step that is not a 3-digit number the poles of the error map are
    within about ``|A| |h - dt|`` of ``exp(s h)`` (:meth:`error_matrix` gives the
    map actually applied). With the true plant and no noise the error goes to
    zero to round-off at any sampling, with no step-dependent bias.

    Partial rows: a gain is designed for each set of rows. If (Ad, C[rows] Ad)
    is not observable only its observable part is placed (with the fastest of
    the given poles that fit, see ``_pick_poles``) and the unobservable modes
    are left as they are, even when unstable: the other rows, when they arrive,
    correct them. Messages with the same time stamp are fused (one correction
    with all their rows). Rows that always come at different times still
    converge in the cases tested, but not at the designed rate: on the cart
    with theta and x alternating at 200 Hz the error decays at about -6.2/s
    instead of -10/s (the product of the two maps has other eigenvalues).

    With a gain L given instead of poles:

    * continuous plant: L is the continuous-time gain of
      ``x_hat' = A x_hat + B u + L (y - C x_hat - D u)``, sampled exactly with
      ``ybar = y - D u`` (D u taken with the input held when y arrived) and u held
      constant over each step (ZOH on both): one matrix exponential of
      ``[[A - L C, B, L], [0, 0, 0], [0, 0, 0]] dt``. With D = 0 this is the
      ``[[A - L C, B - L D, L], ...]`` form with y held; holding ybar instead of y
      keeps a later change of u from looking like a change of the measured
      states. x_hat(t) is the prediction before y(t) (ybar(t) is held from t on;
      each output keeps its last value, outputs never received do not enter). This is exact for the
      continuous observer fed by sample-and-hold signals, not for the sampled
      plant: the held y lags the true one, so in a noise-free run the error
      tends to a bias proportional to dt and to dy/dt. Measured on the
      submarine (test_core_estimators.py): the bias is first order in dt (about
      10 times smaller at 100 Hz than at 10 Hz) and vanishes only as the plant
      comes to rest.
    * discrete plant: L is the predictor gain of
      ``x_{k+1} = A x_k + B u_k + L (y_k - C x_k - D u_k)``; the error obeys
      ``e_{k+1} = (A - L C) e_k``. Seed 001 writes the same observer as
      ``z_{k+1} = (A + L C) z_k - L y_k + B u_k``, with the opposite sign of L.
      A measurement enters the next sample step only.

    Parameters
    ----------
    plant : Plant
        The model.
    poles : array_like of complex, optional
        Desired observer poles: n, or the observable rank of (A, C[measured]) for
        a detectable plant; s-plane for a continuous plant, z-plane for a
        discrete one.
    gain : (n, p) array_like, optional
        L given directly (columns for all plant outputs); exactly one of poles
        and gain.
    method : {'auto', 'place', 'acker'}
        Pole-placement method (design.observer_gain).
    x0, t0, measured_rows, dt_digits, cache_size, gain_digits
        See :class:`Estimator`.

    """

    kind = 'full'

    def __init__(self, plant, poles=None, gain=None, method='auto', x0=None, t0=None,
                 measured_rows=None, dt_digits=DT_DIGITS, cache_size=CACHE_SIZE,
                 gain_digits=GAIN_DIGITS):
        super().__init__(plant, x0, t0, measured_rows, dt_digits, cache_size, gain_digits)
        if (poles is None) == (gain is None):
            raise DesignError('give exactly one of poles and gain for a full-order observer')
        if method not in ('auto', 'place', 'acker'):
            raise DesignError(f"method must be 'auto', 'place' or 'acker'; got {method!r}")
        self._method = method
        n, p = plant.n, plant.p
        C_m = plant.C[list(self._measured)]
        rank = _unobservable_check(plant.A, C_m, plant.is_discrete, 'full-order observer')
        if poles is not None:
            self._mode = 'poles'
            self._poles = as_poles(poles, 'poles', discrete=plant.is_discrete)
            if self._poles.size not in (n, rank):
                expected = f'{n}' if rank == n else f'{n} (or {rank}, the observable rank)'
                raise DimensionError(f'poles has {self._poles.size} poles; expected {expected}')
            self._L = None
        else:
            self._L = as_matrix(gain, 'gain', rows=n, cols=p)
            self._poles = None
            self._mode = 'predictor' if plant.is_discrete else 'held'
        self._held = np.zeros(p)
        self._held_rows = ()
        self.reset(t0=self._t0)

    @property
    def poles(self):
        """Desired poles as a copy; None when a gain was given."""
        return None if self._poles is None else self._poles.copy()

    @property
    def gain(self):
        """Copy of the gain L given to the constructor; None when poles were given."""
        return None if self._L is None else self._L.copy()

    def _reset_state(self):
        super()._reset_state()
        self._held_rows = ()

    def _gain(self, key, info):
        if key is None:
            return None
        if self._mode != 'poles':
            raise ObserverError('correction_gain and error_matrix apply to a full-order '
                                'observer given poles')
        return self._gain_value(key, info.rows, lambda step: _place(
            step.Ad, info.C @ step.Ad, self._zpoles(step), self._method))

    def _propagate(self, step):
        mode = self._mode
        if mode == 'poles' or not self._held_rows:
            self._propagate_model(step)
        elif mode == 'held':
            key = ('held', self._held_rows)
            ent = step.extra.get(key)
            if ent is None:
                ent = self._held_matrices(step.h, self._held_rows)
                step.extra[key] = ent
            Phi, Gu, Gy, idx = ent
            x = Phi @ self._x + Gu @ self._u + Gy @ self._held[idx]
            self._x = x
        else:
            self._predictor_step(step)

    def _held_matrices(self, h, rows):
        plant = self._plant
        n, m = plant.n, plant.m
        idx = np.array(rows, dtype=np.intp)
        L = self._L[:, idx]
        k = idx.size
        aug = np.zeros((n + m + k, n + m + k))
        aug[:n, :n] = plant.A - L @ plant.C[idx]
        aug[:n, n:n + m] = plant.B
        aug[:n, n + m:] = L
        E = scipy.linalg.expm(aug * h)
        return E[:n, :n].copy(), E[:n, n:n + m].copy(), E[:n, n + m:].copy(), idx

    def _predictor_step(self, step):
        plant = self._plant
        idx = np.array(self._held_rows, dtype=np.intp)
        L = self._L[:, idx]
        x = plant.A @ self._x + plant.B @ self._u + L @ (self._held[idx] - plant.C[idx] @ self._x)
        if step.k > 1:
            rest = self._cache.get(step.k - 1)
            x = rest.Ad @ x + rest.Bd @ self._u
        self._x = x
        self._held_rows = ()

    def _correct(self, y, info):
        if self._mode == 'poles':
            super()._correct(y, info)
            return
        ybar = y - info.D @ self._u
        self._residual = ybar - info.C @ self._x
        # held (continuous): ybar held from t on; predictor (discrete): ybar used by the
        # next sample step. Holding ybar = y - D u rather than y means a later change of
        # u does not look like a change of the measured states.
        self._held[info.idx] = ybar
        self._held_rows = tuple(sorted(set(self._held_rows) | set(info.rows)))
        self._t_anchor = self._t


# ---------------------------------------------------------------- reduced order


class ReducedOrderEstimator(_CurrentForm):
    """
    Reduced-order observer: measured combinations taken from y, the rest estimated.

    In the coordinates ``x_bar = T x`` of design.reduced_coordinates(C) (C the
    measured rows), ``x_bar[:p] = C x = ybar = y - D u`` and ``x_bar[p:]`` are
    the states ``rest``. On the exactly sampled model ``Phi = T Ad Tinv``,
    ``Gam = T Bd`` (blocks 11, 12, 21, 22 and 1, 2) the current-form observer of
    Franklin and Powell is::

        x2_{k+1} = Phi22 x2_k + Phi21 ybar_k + Gam2 u_k
                   + Lr (ybar_{k+1} - Phi11 ybar_k - Gam1 u_k - Phi12 x2_k)

    with the error ``e2_{k+1} = (Phi22 - Lr Phi12) e2_k``; Lr places the n - p
    poles exp(s h) (continuous) or z^k (discrete) for (Phi22, Phi12). This is the
    full-order current form with ``M = Tinv [I; Lr]``, so predictions between
    measurements are the model's, and ``C x_hat = y - D u`` holds exactly (to
    round-off) after every correction. The first measurement sets ybar and
    keeps x2 from x0 (``M = Tinv [I; 0]``).

    Outputs missing from a message: the correction uses the columns of M of the
    rows received (the missing measured coordinates keep their predicted value).
    Rows with the same time stamp are fused into one full correction, so sensors
    stamped together give the exact reduced-order observer; rows that always come
    at different times give a heuristic that is not guaranteed to converge.

    With a gain Lr given instead of poles:

    * continuous plant: Lr is the continuous gain of seeds 000/002,
      ``x2_hat = Lr ybar + z``, ``z' = F z + G ybar + H u`` with
      ``F = A22 - Lr A12``, ``G = A21 - Lr A11 + F Lr``, ``H = B2 - Lr B1``
      (blocks of ``T A Tinv`` and ``T B``), integrated exactly with u held over
      each step. Between measurements ybar is held (predictions); when a
      measurement arrives, the step since the previous one is redone with ybar
      ramping linearly from the previous measurement to this one (first-order
      hold, one extra matrix ``Gamma1(h)``). A held ybar would leave a bias of
      order ``|F^-1 G| dt dy/dt``, and G is large for a reduced observer: with
      the seed's cart gain at 1 kHz it was 4 rad/s on theta', against 2e-4
      with the ramp (second order: 2e-2 at 100 Hz, test_core_estimators.py).
      A missing output keeps its last value; the first measurement sets ybar
      and keeps x2.
    * discrete plant: Lr is the current-form gain of the equation above (exact
      when measurements come every sample; used as is for longer steps).

    Parameters
    ----------
    plant : Plant
        The model.
    poles : array_like of complex, optional
        n - p desired poles (or the observable rank minus p for a detectable
        plant); s-plane (continuous) or z-plane (discrete).
    gain : (n - p, p) array_like, optional
        Lr given directly; exactly one of poles and gain.
    method : {'auto', 'place', 'acker'}
        Pole-placement method.
    x0, t0, measured_rows, dt_digits, cache_size, gain_digits
        See :class:`Estimator`; p is the number of measured rows, which must be
        independent.

    """

    kind = 'reduced'

    def __init__(self, plant, poles=None, gain=None, method='auto', x0=None, t0=None,
                 measured_rows=None, dt_digits=DT_DIGITS, cache_size=CACHE_SIZE,
                 gain_digits=GAIN_DIGITS):
        super().__init__(plant, x0, t0, measured_rows, dt_digits, cache_size, gain_digits)
        if (poles is None) == (gain is None):
            raise DesignError('give exactly one of poles and gain for a reduced-order observer')
        if method not in ('auto', 'place', 'acker'):
            raise DesignError(f"method must be 'auto', 'place' or 'acker'; got {method!r}")
        self._method = method
        n = plant.n
        C_m = plant.C[list(self._measured)]
        pm = C_m.shape[0]
        self._T, self._Tinv, self._rest = reduced_coordinates(C_m)
        self._pm = pm
        self._pos = {r: i for i, r in enumerate(self._measured)}
        rank = _unobservable_check(plant.A, C_m, plant.is_discrete, 'reduced-order observer')
        self._L = None
        self._poles = None
        if poles is not None:
            self._poles = as_poles(poles, 'poles', discrete=plant.is_discrete)
            if self._poles.size not in (n - pm, rank - pm):
                expected = f'{n - pm}' if rank == n else \
                    f'{n - pm} (or {rank - pm}, the observable rank minus p)'
                raise DimensionError(f'poles has {self._poles.size} poles; expected {expected}')
            self._mode = 'poles'
        else:
            self._L = as_matrix(gain, 'gain', rows=n - pm, cols=pm)
            self._mode = 'discrete_gain' if plant.is_discrete else 'held'
            if self._mode == 'held':
                self._setup_held()
        self._ybar = np.zeros(pm)
        self._z = np.zeros(n - pm)
        self.reset(t0=self._t0)

    @property
    def coordinates(self):
        """Return copies of T, Tinv and rest as given by design.reduced_coordinates."""
        return self._T.copy(), self._Tinv.copy(), list(self._rest)

    @property
    def poles(self):
        """Desired poles as a copy; None when a gain was given."""
        return None if self._poles is None else self._poles.copy()

    @property
    def gain(self):
        """Copy of the gain Lr given to the constructor; None when poles were given."""
        return None if self._L is None else self._L.copy()

    def _cols(self, info):
        return [self._pos[r] for r in info.rows]

    def _full_gain(self, Lr):
        return self._Tinv @ np.vstack([np.eye(self._pm), Lr])

    def _gain(self, key, info):
        if self._mode == 'held':
            raise ObserverError('correction_gain and error_matrix apply to a reduced-order '
                                'observer given poles (or a discrete plant)')
        if key is None:
            M = self._init_gains.get(info.rows)
            if M is None:
                M = self._Tinv[:, :self._pm][:, self._cols(info)]
                self._init_gains[info.rows] = M
            return M
        step = self._cache.get(key)
        M = step.extra.get(info.rows)
        if M is None:
            Mfull = self._gain_value(key, 'Mfull', self._design_gain)
            M = Mfull[:, self._cols(info)]
            step.extra[info.rows] = M
        return M

    def _design_gain(self, step):
        """Tinv [I; Lr] of a step: Lr places the poles on (Phi22, Phi12) (or is given)."""
        if self._mode == 'poles':
            pm = self._pm
            Phi = self._T @ step.Ad @ self._Tinv
            Lr = _place(Phi[pm:, pm:], Phi[:pm, pm:], self._zpoles(step), self._method)
        else:
            Lr = self._L
        return self._full_gain(Lr)

    # continuous given gain: z-form with ybar held ---------------------------

    def _setup_held(self):
        plant = self._plant
        pm = self._pm
        Ab = self._T @ plant.A @ self._Tinv
        Bb = self._T @ plant.B
        A11, A12, A21, A22 = Ab[:pm, :pm], Ab[:pm, pm:], Ab[pm:, :pm], Ab[pm:, pm:]
        L = self._L
        F = A22 - L @ A12
        self._F = F
        self._G = A21 - L @ A11 + F @ L
        self._H = Bb[pm:] - L @ Bb[:pm]

    def _held_matrices(self, h):
        q, pm, m = self._F.shape[0], self._pm, self._plant.m
        aug = np.zeros((q + pm + m, q + pm + m))
        aug[:q, :q] = self._F
        aug[:q, q:q + pm] = self._G
        aug[:q, q + pm:] = self._H
        E = scipy.linalg.expm(aug * h)
        return E[:q, :q].copy(), E[:q, q:q + pm].copy(), E[:q, q + pm:].copy()

    def _held_x(self):
        x2 = self._L @ self._ybar + self._z
        self._x = self._Tinv @ np.concatenate([self._ybar, x2])

    def _reset_state(self):
        super()._reset_state()
        if self._mode == 'held':
            xb = self._T @ self._x
            self._ybar = xb[:self._pm].copy()
            self._z = xb[self._pm:] - self._L @ self._ybar

    def _propagate(self, step):
        if self._mode != 'held':
            self._propagate_model(step)
            return
        ent = step.extra.get('held')
        if ent is None:
            ent = self._held_matrices(step.h)
            step.extra['held'] = ent
        Phi, Gy, Gu = ent
        self._z = Phi @ self._z + Gy @ self._ybar + Gu @ self._u
        self._held_x()

    def _foh_matrix(self, step):
        """Gamma1(h) = (1/h) int_0^h expm(F (h - s)) G s ds (ybar ramping over the step)."""
        ent = step.extra.get('foh')
        if ent is None:
            q, pm = self._F.shape[0], self._pm
            aug = np.zeros((q + 2 * pm, q + 2 * pm))
            aug[:q, :q] = self._F
            aug[:q, q:q + pm] = self._G
            aug[q:q + pm, q + pm:] = np.eye(pm)
            E = scipy.linalg.expm(aug * step.h)
            ent = E[:q, q + pm:] / step.h
            step.extra['foh'] = ent
        return ent

    def _correct(self, y, info):
        if self._mode != 'held':
            super()._correct(y, info)
            return
        t = self._t
        ybar = y - info.D @ self._u
        self._residual = ybar - info.C @ self._x
        new = self._ybar.copy()
        new[self._cols(info)] = ybar
        if self._t_corr is None or t != self._t_corr:
            self._acc_key = None if self._t_corr is None else self._cache.key(t - self._t_corr)
            self._t_corr = t
        if self._acc_key is None:
            # First measurement: it sets ybar and keeps x2 (z absorbs the jump of Lr ybar).
            self._z += self._L @ (self._ybar - new)
        else:
            # The held ybar is replaced, over the step just ended, by the ramp from the
            # previous measurement to this one (first-order hold): the lag of a held y,
            # amplified by the large G of a reduced observer, is removed.
            self._z += self._foh_matrix(self._cache.get(self._acc_key)) @ (new - self._ybar)
        self._ybar = new
        self._held_x()
        self._t_anchor = t


# ---------------------------------------------------------------- Kalman


class KalmanEstimator(Estimator):
    """
    Time-varying discrete Kalman filter on the exactly sampled plant.

    Propagation over dt: ``x- = Ad x + Bd u``, ``P- = Ad P Ad^T + Qk(dt)``. For a
    continuous plant Qd is the intensity of continuous white process noise w in
    ``x' = A x + B u + Bd w`` and ``Qk(dt)`` its exact discretisation (Van Loan,
    :func:`process_noise_covariance`) for dt rounded to ``gain_digits``
    significant digits (Ad is that of dt itself); for a discrete plant Qd is the covariance
    of w per sample (``Qk = sum_{i<k} A^i Bd Qd Bd^T A^iT`` over k samples).
    Rd is the covariance of the measurement noise of each sample.

    Correction with the rows r of a message: ``S = C_r P C_r^T + R_rr``,
    ``K = P C_r^T S^-1``, ``x+ = x- + K (y - D_r u - C_r x-)`` and the Joseph form
    ``P+ = (I - K C_r) P (I - K C_r)^T + K R_rr K^T``. Messages are processed one
    after the other (sequential update); with a diagonal Rd this equals a joint
    update of all rows of one time stamp (correlations of Rd between rows of
    different messages are ignored).

    P0 default: the steady-state filter covariance (from
    scipy.linalg.solve_discrete_are) of the step between the initial estimate
    and the first correction after it, for the rows of that correction
    (identity if the Riccati equation has no solution). Until that step is
    known (a measurement at the very time of the initial estimate) there is no
    correction.

    Parameters
    ----------
    plant : Plant
        The model.
    Qd : (k, k) array_like
        Process-noise intensity (continuous plant) or per-sample covariance.
    Rd : (p, p) array_like
        Measurement-noise covariance, for all plant outputs.
    Bd : (n, k) array_like, optional
        Process-noise input matrix; default the identity (k = n).
    P0 : (n, n) array_like, optional
        Covariance of x0.
    x0, t0, measured_rows, dt_digits, cache_size, gain_digits
        See :class:`Estimator`.

    """

    kind = 'kalman'

    def __init__(self, plant, Qd, Rd, Bd=None, P0=None, x0=None, t0=None,
                 measured_rows=None, dt_digits=DT_DIGITS, cache_size=CACHE_SIZE,
                 gain_digits=GAIN_DIGITS):
        super().__init__(plant, x0, t0, measured_rows, dt_digits, cache_size, gain_digits)
        n, p = plant.n, plant.p
        G = np.eye(n) if Bd is None else as_matrix(Bd, 'Bd', rows=n)
        k = G.shape[1]
        Q = _as_covariance(Qd, 'Qd', k)
        R = _as_covariance(Rd, 'Rd', p)
        Rm = R[np.ix_(self._measured, self._measured)]
        if np.min(np.linalg.eigvalsh(Rm)) <= 0.0:
            raise DesignError('Rd is not positive definite on the measured outputs '
                              f'{[plant.output_names[r] for r in self._measured]}')
        self._G, self._Q, self._R = G, Q, R
        self._GQG = G @ Q @ G.T
        self._P0 = None if P0 is None else _as_covariance(P0, 'P0', n)
        self._P = None
        self._I = np.eye(n)
        self._rows_R = {}
        self.reset(t0=self._t0)

    @property
    def P(self):
        """Covariance of x_hat (copy), or None before it is known (see P0)."""
        return None if self._P is None else self._P.copy()

    def _reset_state(self):
        self._P = None if self._P0 is None else self._P0.copy()

    def _noise(self, step):
        """Qk of a step (interpolated between grid steps, see :data:`GAIN_DIGITS`)."""
        return self._gain_value(step.key, 'Q', self._noise_at)

    def _noise_at(self, step):
        if step.k is None:
            return process_noise_covariance(self._plant.A, self._Q, step.h, self._G)
        return _discrete_noise(self._plant.A, self._GQG, step.k)

    def _propagate(self, step):
        self._propagate_model(step)
        if self._P is not None:
            Ad = step.Ad
            P = Ad @ self._P @ Ad.T
            P += self._noise(step)
            self._P = P

    def _R_rows(self, info):
        R = self._rows_R.get(info.rows)
        if R is None:
            R = self._R[np.ix_(info.idx, info.idx)]
            self._rows_R[info.rows] = R
        return R

    def _steady_prior(self, step, info, R):
        Qk = self._noise(step)
        try:
            P = scipy.linalg.solve_discrete_are(step.Ad.T, info.C.T, Qk, R)
        except (ValueError, np.linalg.LinAlgError):
            return self._I.copy()
        if not np.all(np.isfinite(P)):
            return self._I.copy()
        return 0.5 * (P + P.T)

    def _correct(self, y, info):
        ybar = y - info.D @ self._u
        innov = ybar - info.C @ self._x
        self._residual = innov
        R = self._R_rows(info)
        if self._P is None:
            h = self._t - self._t_anchor
            if h <= 0.0:
                return
            self._P = self._steady_prior(self._cache.step(h), info, R)
        P = self._P
        C = info.C
        PCt = P @ C.T
        S = C @ PCt + R
        K = np.linalg.solve(S, PCt.T).T
        self._x = self._x + K @ innov
        IKC = self._I - K @ C
        P = IKC @ P @ IKC.T + K @ R @ K.T
        self._P = 0.5 * (P + P.T)
        self._t_anchor = self._t


def _as_covariance(X, name, size):
    M = as_matrix(X, name, rows=size, cols=size)
    scale = max(1.0, float(np.max(np.abs(M))))
    if np.max(np.abs(M - M.T)) > 1e-9 * scale:
        raise DesignError(f'{name} is not symmetric')
    M = 0.5 * (M + M.T)
    if size and np.min(np.linalg.eigvalsh(M)) < -1e-9 * scale:
        raise DesignError(f'{name} is not positive semidefinite')
    return M


# ---------------------------------------------------------------- factory


def make_estimator(plant, observer_spec, measured_rows=None, **kwargs):
    """
    Build the estimator an ObserverSpec describes.

    Parameters
    ----------
    plant : Plant
        The model.
    observer_spec : ObserverSpec
        ``kind`` one of full, reduced, open_loop, kalman; poles or gain;
        Qd, Rd, Bd for kalman; initial_estimate.
    measured_rows : sequence of int, optional
        The outputs the estimator will be given; default all.
    **kwargs
        Passed on to the estimator (t0, dt_digits, cache_size, gain_digits, P0 for
        kalman).

    Returns
    -------
    Estimator

    """
    spec = observer_spec
    if not isinstance(spec, ObserverSpec):
        raise ObserverError(f'observer_spec must be an ObserverSpec; got {type(spec).__name__}')
    kind = spec.kind
    common = dict(x0=spec.initial_estimate, measured_rows=measured_rows, **kwargs)
    if kind == 'full':
        return FullOrderEstimator(plant, poles=spec.poles, gain=spec.gain,
                                  method=spec.method, **common)
    if kind == 'reduced':
        return ReducedOrderEstimator(plant, poles=spec.poles, gain=spec.gain,
                                     method=spec.method, **common)
    if kind == 'open_loop':
        return OpenLoopEstimator(plant, **common)
    if kind == 'kalman':
        if spec.Qd is None or spec.Rd is None:
            raise ObserverError('observer.Qd and observer.Rd are required for a kalman observer')
        return KalmanEstimator(plant, spec.Qd, spec.Rd, spec.Bd, **common)
    raise ObserverError(f'observer.type is {kind!r}; expected one of {list(OBSERVER_TYPES)}')
