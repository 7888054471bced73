# observer_ros.core.estimators.sampled: the observer the loop runs, checked at the vehicle's rates.
"""
Verification of the sampled observer a vehicle will run, at its nominal sensor pattern.

The observer node does not run ``A - L C``: it corrects with the gain of each sampled
step (``FullOrderEstimator`` / ``ReducedOrderEstimator``), designed per step length and
per set of measured outputs. :func:`check_sampled_observer` builds that estimator and,
over one period of the pattern the simulator publishes the sensors in (sensor ``k``
every ``rate_divider_k`` steps of ``vehicle.sample_time``; the period is the least
common multiple of the dividers):

1. designs the gain of every correction of the period (each passes
   ``verify.verify_placement`` in ``placement.place``; a refused one raises its
   ``DesignVerificationError`` naming ``observer.poles``, the step and the outputs);
2. multiplies the error maps ``F_j = (I - M_j C_j) Ad(h_j)`` of the period's
   corrections and refuses the vehicle when the product is not stable (stability
   rule of ``core.verify``): each step's gain places the poles of its own map, but
   with sensors at different rates the product of alternating maps can grow (the
   two-sensor submarine of ``test/late_sensors.py`` with poles -2, -2.1, -2.2:
   spectral radius 1.02 per 0.05 s). A stable product that decays much slower than
   the requested poles is a warning.

"""

from dataclasses import dataclass
import math
from typing import Optional, Tuple

import numpy as np

from .factory import make_estimator
from ..errors import DesignVerificationError
from ..verify import describe_status, unstable_eigenvalues

__all__ = ['MAX_PATTERN_STEPS', 'SampledCheck', 'sensor_pattern', 'check_sampled_observer']

#: Longest sensor pattern (simulator steps per period) that is checked step by step.
MAX_PATTERN_STEPS = 10000

#: A stable period map is a warning when its decay rate is below this fraction of the
#: slowest requested pole's.
SLOW_DECAY_FRACTION = 0.5


@dataclass(frozen=True)
class SampledCheck:
    """
    The sampled observer over one period of the vehicle's sensor pattern.

    ``corrections`` lists ``(h, output names)`` of each correction of the period,
    ``spectral_radius`` is that of the product of their error maps, ``decay_rate``
    ``ln(spectral_radius) / period`` (1/s; per sample for a discrete plant the period
    is in samples times the sample time) and ``designed_rate`` the slowest requested
    pole's real part (continuous) or ``ln|z|`` per sample time (discrete); -inf for a
    deadbeat map or design. ``period_map`` is the product of the period's error maps.

    """

    period: float
    corrections: Tuple[Tuple[float, Tuple[str, ...]], ...]
    spectral_radius: float
    decay_rate: float
    designed_rate: float
    sensors: Tuple[str, ...]
    period_map: Optional[np.ndarray] = None

    def to_json(self):
        """Return a JSON-serialisable summary."""
        def num(x):
            return None if not np.isfinite(x) else float(x)
        return {'period': self.period,
                'corrections': [{'h': h, 'outputs': list(o)} for h, o in self.corrections],
                'spectral_radius': self.spectral_radius,
                'decay_rate': num(self.decay_rate),
                'designed_rate': num(self.designed_rate),
                'sensors': list(self.sensors)}


def sensor_pattern(vehicle):
    """
    Return the sensors' publication pattern over one period.

    Parameters
    ----------
    vehicle : observer_ros.core.spec.Vehicle
        The vehicle.

    Returns
    -------
    steps : int
        Simulator steps in one period (lcm of the sensors' ``rate_divider``), 0 when no
        sensor measures a model output.
    events : list of (int, tuple of int, tuple of str)
        Each step of the period (1..steps) at which a sensor publishes: the step, the
        sorted output rows and the sensors' names.

    """
    outputs = vehicle.plant.output_names
    sensors = [(s, max(1, int(s.rate_divider)),
                tuple(outputs.index(o) for o in s.outputs if o in outputs))
               for s in vehicle.sensors]
    sensors = [t for t in sensors if t[2]]
    if not sensors:
        return 0, []
    steps = 1
    for _, div, _ in sensors:
        steps = steps * div // math.gcd(steps, div)
    if steps > MAX_PATTERN_STEPS:
        return steps, []
    events = []
    for j in range(1, steps + 1):
        now = [(s.name, rows) for s, div, rows in sensors if j % div == 0]
        if now:
            rows = tuple(sorted({r for _, rr in now for r in rr}))
            events.append((j, rows, tuple(name for name, _ in now)))
    return steps, events


def _describe(vehicle, names):
    dt = vehicle.sample_time
    parts = []
    for s in vehicle.sensors:
        if s.name in names:
            div = max(1, int(s.rate_divider))
            parts.append(f'{s.name} ({1.0 / (dt * div):.4g} Hz)')
    return ', '.join(parts)


def check_sampled_observer(vehicle):
    """
    Design and verify the gains the observer will use at the vehicle's sensor rates.

    Parameters
    ----------
    vehicle : observer_ros.core.spec.Vehicle
        A vehicle whose observer is ``full`` or ``reduced`` with ``observer.poles``
        (anything else returns None: a given gain is checked by ``design_vehicle``,
        a Kalman filter handles any pattern).

    Returns
    -------
    check : SampledCheck or None
    warnings : list of str
        A stable period map that decays slower than :data:`SLOW_DECAY_FRACTION` of the
        slowest requested pole; a pattern too long to check.

    Raises
    ------
    DesignVerificationError
        A step's gain fails ``verify_placement``, or the error map over one period is
        not stable; one line naming ``observer.poles``, the sensors, the spectral
        radius and what to do.

    """
    spec = vehicle.observer
    if spec.kind not in ('full', 'reduced') or spec.poles is None:
        return None, []
    steps, events = sensor_pattern(vehicle)
    if steps == 0:
        return None, []
    if not events:
        return None, [f'observer: the sensor pattern repeats every {steps} steps, more than '
                      f'{MAX_PATTERN_STEPS}: the sampled observer was not checked over it']
    plant = vehicle.plant
    dt = vehicle.sample_time
    est = make_estimator(plant, spec)
    n = plant.n
    product = np.eye(n)
    prev = events[-1][0] - steps
    corrections = []
    used = set()
    for j, rows, names in events:
        h = (j - prev) * dt
        prev = j
        F = est.error_matrix(h, rows)
        product = F @ product
        corrections.append((h, tuple(plant.output_names[r] for r in rows)))
        used.update(names)
    period = steps * dt
    lam = np.linalg.eigvals(product)
    rho = float(np.max(np.abs(lam))) if lam.size else 0.0
    poles = np.asarray(spec.poles, dtype=complex)
    with np.errstate(divide='ignore'):     # deadbeat (z = 0): -inf, said as such
        if plant.is_discrete:
            designed = float(np.log(np.max(np.abs(poles))) / dt)
        else:
            designed = float(np.max(poles.real))
        rate = float(np.log(rho) / period) if rho > 0 else -np.inf
    check = SampledCheck(period, tuple(corrections), rho, rate, designed, tuple(sorted(used)),
                         product)
    sensors = _describe(vehicle, used)
    multi = len({rows for _, rows, _ in events}) > 1
    bad = unstable_eigenvalues(product, discrete=True, with_bounds=True)
    if bad:
        why = ("each step's gain places the poles of its own map, but the product of the "
               'alternating maps is not stable; use observer.type: kalman (it handles '
               'sensors at different rates), slower observer.poles, or sensors at one rate '
               '(the same rate_divider)') if multi else \
              'the sampled gains do not stabilize the error; use slower observer.poles or ' \
              'observer.type: kalman'
        raise DesignVerificationError(
            f'observer.poles: with sensors {sensors} the sampled observer diverges: the '
            f'error map over one period of the sensor pattern ({period:.6g} s, '
            f'{len(events)} corrections) has spectral radius {rho:.4g} '
            f'({describe_status(*bad[0], discrete=True)}); {why}')
    messages = []
    if multi and np.isfinite(designed) and rate > SLOW_DECAY_FRACTION * designed:
        messages.append(
            f"observer.poles: with sensors {sensors} the sampled observer's error decays at "
            f'{-rate:.3g}/s over one period of the sensor pattern ({period:.6g} s, spectral '
            f'radius {rho:.4g}), not at the designed {-designed:.3g}/s: the per-step gains '
            f'interact; a Kalman observer (observer.type: kalman) handles sensors at '
            f'different rates')
    return check, messages
