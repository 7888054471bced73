# observer_ros.core.simulate: an exact plant simulator for the tests and the simulator node.
"""
Exact sampled simulation of a Plant with zero-order-hold input and optional noise.

The state is advanced with the exact ZOH model of each step (cached per step
length), so a noise-free simulation is the true plant sampled at any times. The
noise comes from one numpy Generator in a fixed order, so a seed reproduces a
run.

"""

from collections import OrderedDict
import math

import numpy as np

from .errors import DimensionError, ObserverError
from .estimators import process_noise_covariance, StepCache
from .model import as_vector, Plant, zoh_matrices

__all__ = ['PlantSimulator', 'process_noise_factor']


def _sqrtm_psd(Q):
    """Symmetric square root factor S with S S^T = Q, for Q positive semidefinite."""
    w, V = np.linalg.eigh(0.5 * (Q + Q.T))
    return V * np.sqrt(np.clip(w, 0.0, None))


def process_noise_factor(plant, process_noise_std, dt, samples=None):
    """
    Factor S (S S^T = Q) of the covariance the process noise adds over one step.

    Parameters
    ----------
    plant : Plant
        The model.
    process_noise_std : (n,) array_like
        Continuous plant: square root of the diagonal intensity of w (units per
        square-root second), so the noise does not depend on the step. Discrete
        plant: standard deviation per sample.
    dt : float
        Step in seconds (continuous plant).
    samples : int, optional
        Discrete plant: samples in the step (default 1).

    Returns
    -------
    S : (n, n) ndarray
        ``S @ standard_normal(n)`` has the exact covariance of the step:
        ``Qd(dt)`` of :func:`~observer_ros.core.estimators.process_noise_covariance`
        (continuous), ``sum A^i W A^i^T`` over the samples (discrete).

    """
    W = np.diag(np.asarray(process_noise_std, dtype=float) ** 2)
    if not plant.is_discrete:
        return _sqrtm_psd(process_noise_covariance(plant.A, W, dt))
    Q = np.zeros_like(W)
    term = W
    for _ in range(1 if samples is None else samples):
        Q = Q + term
        term = plant.A @ term @ plant.A.T
    return _sqrtm_psd(Q)


class PlantSimulator:
    """
    Simulate x' = A x + B u + w, y = C x + D u + v exactly at arbitrary steps.

    Parameters
    ----------
    plant : Plant
        Continuous or discrete model.
    x0 : array_like, optional
        Initial state (n); default zeros.
    seed : int, optional
        Seed of the noise generator (ignored when ``rng`` is given).
    rng : numpy.random.Generator, optional
        Generator to draw the noise from.
    measurement_noise_std : array_like, optional
        Standard deviation of v per output (p); default no measurement noise.
    process_noise_std : array_like, optional
        Per state (n). For a continuous plant the square root of the diagonal
        intensity of the white noise w (units per square-root second), so the
        noise does not depend on the step; each step adds the exact covariance
        ``Qd(dt)`` of :func:`~observer_ros.core.estimators.process_noise_covariance`.
        For a discrete plant the standard deviation per sample. Default none.
    t0 : float
        Initial time in seconds.

    Notes
    -----
    :meth:`measure` uses the input applied over the last step (the one held at
    the time of the measurement): a new command takes effect at the next
    :meth:`step`. This is the convention the estimators use for D u.

    """

    def __init__(self, plant, x0=None, seed=None, rng=None, measurement_noise_std=None,
                 process_noise_std=None, t0=0.0):
        if not isinstance(plant, Plant):
            raise ObserverError(f'plant must be a Plant; got {type(plant).__name__}')
        self._plant = plant
        n, p = plant.n, plant.p
        self._x0 = np.zeros(n) if x0 is None else as_vector(x0, 'x0', n)
        self._rng = rng if rng is not None else np.random.default_rng(seed)
        self._v_std = None if measurement_noise_std is None else \
            as_vector(measurement_noise_std, 'measurement_noise_std', p)
        self._w_std = None if process_noise_std is None else \
            as_vector(process_noise_std, 'process_noise_std', n)
        for name, std in (('measurement_noise_std', self._v_std),
                          ('process_noise_std', self._w_std)):
            if std is not None and np.any(std < 0.0):
                raise DimensionError(f'{name} has negative entries: {std}')
        if self._w_std is not None and not np.any(self._w_std > 0.0):
            self._w_std = None
        self._steps = OrderedDict()
        self._exact = StepCache(plant, digits=17, size=64) if plant.is_discrete else None
        self._t0 = float(t0)
        self.reset()

    @property
    def plant(self):
        """Return the simulated model."""
        return self._plant

    @property
    def x(self):
        """Return the true state (a copy)."""
        return self._x.copy()

    @property
    def t(self):
        """Return the simulated time in seconds."""
        return self._t

    @property
    def u(self):
        """Return the input applied over the last step (a copy)."""
        return self._u.copy()

    def reset(self, x0=None, t0=None):
        """
        Set the state and time back (the noise generator goes on).

        Parameters
        ----------
        x0 : array_like, optional
            Default the constructor's x0.
        t0 : float, optional
            Default the constructor's t0.

        """
        self._x = (self._x0 if x0 is None else as_vector(x0, 'x0', self._plant.n)).copy()
        self._t = self._t0 if t0 is None else float(t0)
        self._u = np.zeros(self._plant.m)

    def _step_matrices(self, dt):
        ent = self._steps.get(dt)
        if ent is not None:
            self._steps.move_to_end(dt)
            return ent
        plant = self._plant
        if plant.is_discrete:
            step = self._exact.step(dt)
            Ad, Bd, k = step.Ad, step.Bd, step.k
        else:
            Ad, Bd = zoh_matrices(plant.A, plant.B, dt)
            k = None
        S = None
        if self._w_std is not None:
            S = process_noise_factor(plant, self._w_std, dt, k)
        ent = (Ad, Bd, S)
        self._steps[dt] = ent
        if len(self._steps) > 64:
            self._steps.popitem(last=False)
        return ent

    def step(self, u=None, dt=None):
        """
        Advance by dt with the input u held over the step.

        Parameters
        ----------
        u : array_like, optional
            Input over the step (m); default the previous one.
        dt : float, optional
            Step length in seconds; default the sample time of a discrete plant
            (required for a continuous plant).

        Returns
        -------
        x : ndarray
            The state at the end of the step (a copy).

        """
        plant = self._plant
        if dt is None:
            if not plant.is_discrete:
                raise ObserverError('dt is required to step a continuous plant')
            dt = plant.dt
        dt = float(dt)
        if not (dt > 0.0 and math.isfinite(dt)):
            raise ObserverError(f'dt must be positive and finite; got {dt!r}')
        if u is not None:
            u = np.asarray(u, dtype=float).reshape(-1)
            if u.size != plant.m:
                raise DimensionError(f'u has {u.size} elements; expected {plant.m}')
            self._u = u.copy()
        Ad, Bd, S = self._step_matrices(dt)
        x = Ad @ self._x + Bd @ self._u
        if S is not None:
            x += S @ self._rng.standard_normal(plant.n)
        self._x = x
        self._t += dt
        return x.copy()

    def measure(self, rows=None, noise=True):
        """
        Measure the outputs ``rows``: ``C[rows] x + D[rows] u + v``.

        Parameters
        ----------
        rows : sequence of int, optional
            Output indices; default all.
        noise : bool
            Add the measurement noise (when a standard deviation was given).

        Returns
        -------
        y : ndarray
            One value per row.

        """
        plant = self._plant
        idx = np.arange(plant.p) if rows is None else np.asarray(rows, dtype=np.intp).reshape(-1)
        if idx.size and (idx.min() < 0 or idx.max() >= plant.p):
            raise DimensionError(f'rows {idx.tolist()} out of range; the plant has '
                                 f'{plant.p} outputs')
        y = plant.C[idx] @ self._x + plant.D[idx] @ self._u
        if noise and self._v_std is not None:
            y = y + self._v_std[idx] * self._rng.standard_normal(idx.size)
        return y
