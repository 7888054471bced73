# observer_ros.core.estimators.base: time keeping, held input and the public step calls.
"""
The base class of every estimator, and the open-loop estimator (the model alone).

An estimator holds x_hat at a time; every call that carries a time first propagates it
there with the held input (:class:`Estimator`).

"""

import math
from operator import attrgetter

import numpy as np

from .steps import (bracket, CACHE_SIZE, check_plant, DT_DIGITS, GAIN_CACHE_SIZE, GAIN_DIGITS,
                    StepCache)
from ..errors import DimensionError, ObserverError
from ..model import as_vector

__all__ = ['TimeOrderError', 'Estimator', 'OpenLoopEstimator']


class TimeOrderError(ObserverError, ValueError):
    """A time is before the time of the current estimate (the clock went backwards)."""


# ---------------------------------------------------------------- helpers


def _measured_rows(plant, measured_rows):
    if measured_rows is None:
        return tuple(range(plant.p))
    rows = as_rows(measured_rows, 'measured_rows', plant)
    if not rows:
        raise DimensionError('measured_rows is empty; an estimator needs at least one output')
    return tuple(sorted(rows))


def as_rows(rows, name, plant):
    """Return ``rows`` as distinct output indices of ``plant``; DimensionError names ``name``."""
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

    #: The attributes that make the state of an estimator (everything but its caches):
    #: what :meth:`save_state` copies. Subclasses add theirs.
    _STATE = ('_x', '_u', '_t', '_t_anchor', '_residual', '_residual_rows')
    #: corrections skipped because their gain failed its verification (observers given
    #: poles count them; the others never skip one)
    unverified_corrections = 0
    #: Whether a late input change can be added to saved states (see
    #: :mod:`.superposition`): the kinds linear in (x, u, y) with gains that do not
    #: depend on u, which give ``_shift_correction``.
    _superposable = False
    #: The parts of the state besides x and u that a late input moves (superposition).
    _MOVED = ('_residual',)

    def __init__(self, plant, x0=None, t0=None, measured_rows=None,
                 dt_digits=DT_DIGITS, cache_size=CACHE_SIZE, gain_digits=GAIN_DIGITS):
        self._plant = check_plant(plant)
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
        self._D_zero = not np.any(plant.D)
        #: the place of each attribute of _STATE in a saved state, and those of _MOVED
        self._slots = {name: i for i, name in enumerate(self._STATE)}
        self._state_values = attrgetter(*self._STATE)
        self._moved = tuple((self._slots[name], name) for name in self._MOVED)

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
    def innovation_covariance(self):
        """Covariance S of :attr:`residual` when the estimator has one (Kalman), or None."""
        return None

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
        return bracket(key, self._gain_digits)

    def _gain_value(self, key, name, design):
        """
        Return a gain (or Kalman noise) of a step: designed on the grid, interpolated.

        ``name`` identifies the value in the steps' ``extra`` dicts; the interpolated
        value is cached on the step of ``key`` itself. A design that returns None (a
        gain refused by its verification, see ``_verified_gain``) is cached as None,
        and so is the interpolation of a step whose grid neighbours include one.

        """
        step = self._cache.get(key)
        if name in step.extra:
            return step.extra[name]
        if self._gain_cache is None:
            value = design(step)
        else:
            g0, g1, w = bracket(key, self._gain_digits)
            value = self._grid_value(g0, name, design)
            if g1 is not None and value is not None:
                other = self._grid_value(g1, name, design)
                value = None if other is None else (1.0 - w) * value + w * other
        step.extra[name] = value
        return value

    def _grid_value(self, g, name, design):
        step = self._gain_cache.get(g)
        if name not in step.extra:
            step.extra[name] = design(step)
        return step.extra[name]

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

    def check_input(self, u):
        """
        Return u as the estimator would hold it, or raise as :meth:`set_input` would.

        Parameters
        ----------
        u : array_like
            The input (m).

        Returns
        -------
        u : ndarray
            Finite, of m elements.

        """
        return self._as_input(u)

    def check_measurement(self, y, rows=None):
        """
        Raise as :meth:`correct` would for a bad measurement (its stamp aside).

        Parameters
        ----------
        y : array_like
            Measured values of the outputs ``rows``.
        rows : sequence of int, optional
            See :meth:`correct`.

        """
        self._as_measurement(y, self._all if rows is None else self._rows_info(rows, 'rows'))

    def last_residual(self):
        """
        Return the residual of the last correction and its covariance S, not copied.

        For a caller that keeps them (the history): no call changes them in place, each
        correction makes new ones.

        Returns
        -------
        residual : ndarray or None
            As :attr:`residual`.
        S : ndarray or None
            As :attr:`innovation_covariance`.

        """
        return self._residual, None

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
        if not all(map(math.isfinite, u.tolist())):     # a few floats: no ufunc
            raise DimensionError(f'u has non-finite entries: {u}')
        return u

    def _as_measurement(self, y, info):
        y = np.asarray(y, dtype=float).reshape(-1)
        if y.size != len(info.rows):
            raise DimensionError(f'y has {y.size} elements; expected {len(info.rows)} '
                                 f'(outputs {info.names})')
        if not all(map(math.isfinite, y.tolist())):
            raise DimensionError(f'y has non-finite entries: {y} (outputs {info.names})')
        return y

    def _rows_info(self, rows, name):
        kind = type(rows)
        key = rows if kind is tuple else tuple(rows) if kind is list else None
        if key is not None:
            info = self._rows_cache.get(key)
            if info is not None:
                return info
        rows = as_rows(rows, name, self._plant)
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

    # ------------------------------------------------------------ state

    def save_state(self):
        """
        Return a copy of the estimator's state (estimate, input, time and internals).

        Returns
        -------
        state : tuple
            For :meth:`restore_state`; the caches (matrices, gains) are not part of it.

        """
        # _copy inlined: this runs every CHECKPOINT_EVERY messages of the history
        return tuple([value.copy() if type(value) is np.ndarray else
                      set(value) if type(value) is set else value
                      for value in self._state_values(self)])

    def _shifted(self, state, new, dx, dres):
        """Put x + dx and residual + dres into ``new``; return (a copy of x, the residual)."""
        slots = self._slots
        ix, ires = slots['_x'], slots['_residual']
        new[ix] = x = state[ix] + dx
        new[ires] = residual = state[ires] + dres
        return x.copy(), residual

    def _restore_shifted(self, state):
        """Restore the parts of a state a late input moves (the rest is as saved)."""
        slots = self._slots
        self._x = state[slots['_x']].copy()
        self._u = state[slots['_u']].copy()
        for i, name in self._moved:
            setattr(self, name, _copy(state[i]))        # None before a first residual

    def restore_state(self, state):
        """
        Go back to a state returned by :meth:`save_state` of this estimator.

        Parameters
        ----------
        state : tuple
            From :meth:`save_state`; it is copied, so it can be restored again.

        """
        for name, value in zip(self._STATE, state):
            setattr(self, name, _copy(value))

    # hooks ----------------------------------------------------------------

    def _reset_state(self):
        pass

    def _propagate(self, step):
        self._propagate_model(step)

    def _correct(self, y, info):
        raise NotImplementedError


# ---------------------------------------------------------------- open loop


def _copy(value):
    """Copy a mutable part of a state (arrays and sets); numbers and tuples as they are."""
    kind = type(value)
    if kind is np.ndarray:
        return value.copy()
    return set(value) if kind is set else value


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
    _superposable = True

    def __init__(self, plant, x0=None, t0=None, measured_rows=None,
                 dt_digits=DT_DIGITS, cache_size=CACHE_SIZE, gain_digits=GAIN_DIGITS):
        super().__init__(plant, x0, t0, measured_rows, dt_digits, cache_size, gain_digits)
        self.reset(t0=self._t0)

    def _correct(self, y, info):
        self._residual = y - info.D @ self._u - info.C @ self._x
        self._t_anchor = self._t

    def _shift_correction(self, state, new, dx, dyb, info, t, carry):
        """Move a saved state by a late input change: only the residual moves."""
        dres = -(info.C @ dx) if dyb is None else dyb - info.C @ dx
        return (dx,) + self._shifted(state, new, dx, dres) + (None,)
