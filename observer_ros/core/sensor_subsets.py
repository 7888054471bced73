# observer_ros.core.sensor_subsets: which of a vehicle's outputs are worth measuring.
"""
Sensor subsets: observability, detectability, the fundamental limit and Kalman error variance.

For every non-empty subset of the plant's outputs, the pair (A, C[subset]) is tested
(:func:`~observer_ros.core.analysis.observability_report`: unobservable modes named), the
least peak sensitivity any controller reaches with those outputs is computed
(:func:`~observer_ros.core.limits.fundamental_limit`: unstable poles against
non-minimum-phase zeros; inf when no controller stabilises) and,
when it is detectable and the noise levels are known, the steady-state Kalman error
variance of every state is computed for the sampled loop the simulator runs: ``x[k+1] =
Ad x[k] + w``, ``w ~ N(0, Qd)``, measured with the sensors' ``noise_std``; the variance is
the a-posteriori one (after the measurement update), the error of the published estimate.

"""

from dataclasses import dataclass
from itertools import combinations
import math
from typing import Optional, Tuple

import numpy as np

from .analysis import observability_report
from .design import kalman_gain, kalman_update_gain
from .errors import ObserverError
from .limits import fundamental_limit
from .model import zoh_matrices

__all__ = ['SensorSubset', 'sensor_subsets', 'format_sensor_subsets']


@dataclass(frozen=True)
class SensorSubset:
    """One subset of outputs: verdicts, unobservable modes, Kalman error variance per state."""

    outputs: Tuple[str, ...]
    observable: bool
    detectable: bool
    rank: int
    unobservable_modes: Tuple[str, ...]
    variance: Optional[np.ndarray]
    ms_bound: float = 1.0

    def to_json(self, state_names):
        """Return a JSON-serialisable dict."""
        return {'outputs': list(self.outputs), 'observable': self.observable,
                'detectable': self.detectable, 'rank': self.rank,
                'unobservable_modes': list(self.unobservable_modes),
                'ms_bound': float(self.ms_bound) if np.isfinite(self.ms_bound) else None,
                'kalman_error_variance': None if self.variance is None else
                {nm: float(v) for nm, v in zip(state_names, self.variance)}}


def _noise(vehicle):
    plant = vehicle.plant
    sigma = np.full(plant.p, np.nan)
    for s in vehicle.sensors:
        std = np.asarray(s.noise_std, dtype=float).reshape(-1)
        for j, out in enumerate(s.outputs):
            if out in plant.output_names and j < std.size:
                sigma[plant.output_names.index(out)] = std[j]
    return sigma


def _process_noise(vehicle):
    """Per-step process noise covariance: the simulator's, or a kalman observer's Qd."""
    n = vehicle.plant.n
    std = vehicle.simulator.process_noise_std
    if std is not None and np.all(np.asarray(std) > 0):
        return np.diag(np.asarray(std, dtype=float) ** 2)
    obs = vehicle.observer
    if obs.kind == 'kalman' and obs.Qd is not None and obs.Bd is None and \
            np.shape(obs.Qd) == (n, n):
        return np.asarray(obs.Qd, dtype=float)
    return None


def sensor_subsets(vehicle):
    """
    Analyse every non-empty subset of a vehicle's outputs.

    Parameters
    ----------
    vehicle : observer_ros.core.spec.Vehicle
        The vehicle (plant, sensors' noise_std, simulator's process noise).

    Returns
    -------
    list of SensorSubset
        Observable subsets first, then detectable, then the rest; within each, by the
        least Ms any controller reaches (``ms_bound``), then smallest first, then in
        output order. ``variance`` is None when the subset
        is not detectable, a noise level is unknown or zero, or there is no process
        noise (``simulator.process_noise_std``, or a kalman observer's ``Qd``).

    """
    plant = vehicle.plant
    A, C = plant.A, plant.C
    sigma = _noise(vehicle)
    Qd = _process_noise(vehicle)
    Ad = A if plant.is_discrete else zoh_matrices(A, plant.B, vehicle.sample_time)[0]
    out = []
    for size in range(1, plant.p + 1):
        for rows in combinations(range(plant.p), size):
            rows = list(rows)
            rep = observability_report(A, C[rows], plant.state_names, plant.is_discrete)
            var = None
            if rep.detectable and Qd is not None and np.all(sigma[rows] > 0):
                Rd = np.diag(sigma[rows] ** 2)
                try:
                    _, P, _ = kalman_gain(Ad, C[rows], Qd, Rd, discrete=True)
                    M = kalman_update_gain(P, C[rows], Rd)
                    var = np.diag(P - M @ C[rows] @ P).copy()
                except (ObserverError, np.linalg.LinAlgError, ValueError):
                    var = None
            try:
                bound = fundamental_limit(A, plant.B, C[rows], plant.D[rows],
                                          plant.is_discrete, plant.dt, explain=False).ms_bound
            except (ValueError, ArithmeticError, np.linalg.LinAlgError):
                bound = math.nan
            out.append(SensorSubset(tuple(plant.output_names[i] for i in rows),
                                    rep.observable, rep.detectable, rep.rank,
                                    tuple(rep.unobservable_modes), var, bound))
    order = {True: 0, False: 1}
    return sorted(out, key=lambda s: (order[s.observable], order[s.detectable],
                                      round(math.log10(s.ms_bound), 2) if
                                      math.isfinite(s.ms_bound) else math.inf,
                                      len(s.outputs)))


def format_sensor_subsets(subsets, state_names):
    """
    Return the console table of :func:`sensor_subsets`.

    Parameters
    ----------
    subsets : list of SensorSubset
        From :func:`sensor_subsets`.
    state_names : sequence of str
        The plant's state names.

    Returns
    -------
    str

    """
    lines = ['Sensor subsets (observable first, then by the least peak sensitivity Ms any '
             'controller reaches with them, smallest first):']
    for s in subsets:
        verdict = 'observable' if s.observable else \
            ('detectable' if s.detectable else 'NOT detectable')
        bound = ('bound on Ms not computed' if math.isnan(s.ms_bound) else
                 'no controller stabilises' if not math.isfinite(s.ms_bound) else
                 'no bound on Ms' if s.ms_bound <= 1.0 else f'every controller Ms >= '
                 f'{s.ms_bound:.3g} (unstable pole, non-minimum-phase zero)')
        lines.append(f'  {", ".join(s.outputs)}: {verdict} (rank {s.rank}); {bound}')
        for mode in s.unobservable_modes:
            lines.append(f'    unobservable {mode}')
        if s.variance is not None:
            parts = ', '.join(f'{nm} {v:.3g}' for nm, v in zip(state_names, s.variance))
            lines.append(f'    Kalman error variance: {parts}')
    return '\n'.join(lines)
