# observer_ros.bag.identify: noise covariances of a vehicle from bags (ALS).
"""
Identify a vehicle's process and measurement noise covariances from bags.

The bags' outputs and commands on their sample grid (:mod:`observer_ros.bag.sampled`),
the innovations of a stable reference predictor (the vehicle's own observer), the
transient dropped, and autocovariance least squares (:mod:`observer_ros.core.als`),
pooled over the bags. A second pass repeats it with the Kalman predictor of the first
pass's covariances as the reference, started from the reference's state (Rajamani &
Rawlings 2009 recommend a reference close to the optimal filter). Mehra's whiteness test
of the innovations before (reference) and after (Kalman filter of the identified
covariances).

"""

from dataclasses import dataclass, field
import math
from typing import Dict, List

import numpy as np

from .errors import BagToolError
from .evaluate import _load_vehicle
from .metrics import WHITENESS_LAGS
from .reader import read_recording
from .results import jsonable
from .sampled import noise_input, reference_gain, sampled_data, sampled_model
from ..core.als import (ALSError, DEFAULT_LAGS, identify_noise, kalman_predictor_gain,
                        predictor_blocks, process_noise_map)
from ..core.autocovariance import LaggedSums

__all__ = ['BLOCK', 'TRANSIENT_DECAY', 'Identification', 'identify']

#: Samples dropped at the start of each bag: until the reference predictor's slowest mode
#: has decayed to this fraction.
TRANSIENT_DECAY = 1e-6
#: Innovations are computed and summed this many samples at a time.
BLOCK = 1 << 16


@dataclass
class Identification:
    """What :func:`identify` found (see the module)."""

    vehicle: object
    bags: List[str]
    dt: float
    G: np.ndarray
    noise_names: List[str]
    reference: str
    passes: list                  # ALSResult per pass; the last is the answer
    samples: Dict[str, int]
    burn: int
    whiteness_before: Dict[str, dict]
    whiteness_after: Dict[str, dict]
    warnings: List[str] = field(default_factory=list)

    @property
    def result(self):
        """Return the last pass's ALSResult."""
        return self.passes[-1]

    def to_dict(self):
        """Return JSON-ready data."""
        r = self.result
        return jsonable({
            'bags': self.bags, 'vehicle': self.vehicle.name, 'dt': self.dt,
            'noise_input': self.G.tolist(), 'noise_names': self.noise_names,
            'reference': self.reference, 'samples': self.samples, 'burn': self.burn,
            'Qd': r.Q.tolist(), 'Rd': r.R.tolist(), 'condition': r.condition,
            'passes': [p.to_dict() for p in self.passes],
            'whiteness_reference': self.whiteness_before,
            'whiteness_tuned_kalman': self.whiteness_after, 'warnings': self.warnings})


def _mehra(sums, names):
    """Mehra's test per output: white when at most 5 % of the lags leave +-1.96/sqrt(N)."""
    out = {}
    for j, name in enumerate(names):
        w = sums.whiteness(j, WHITENESS_LAGS)
        w['white'] = bool(w['acf_outside'] <= 0.05) if math.isfinite(w['acf_outside']) \
            else None
        w.pop('acf', None)
        out[name] = w
    return out


def identify(bags, vehicle, namespace=None, lags=DEFAULT_LAGS, full=False, states=None,
             burn=None, passes=2, input_noise=False, block=BLOCK):
    """
    Identify the process and measurement noise covariances from bags (ALS).

    Parameters
    ----------
    bags : sequence of str or Path
        Bags of the same vehicle at the same sample rate.
    vehicle : str or Path or Vehicle
        The vehicle (its model, sensors and observer, the reference).
    namespace : str, optional
        The vehicle's namespace in the bags (detected when None).
    lags : int
        Autocovariance lags.
    full : bool
        Full symmetric covariances (default diagonal).
    states : sequence of str, optional
        Process noise on these states (default ``observer.Bd``, else every state).
    burn : int, optional
        Samples dropped at the start of each bag (default: the reference's transient).
    passes : int
        ALS passes; each after the first uses the previous pass's Kalman predictor.
    input_noise : bool
        Process noise on the inputs (G = B) instead.
    block : int
        Innovations computed this many at a time (never held whole).

    Returns
    -------
    result : Identification

    Raises
    ------
    BagToolError
        A bag cannot be used (see :func:`~observer_ros.bag.sampled.sampled_data`).
    ALSError
        The noise is not identifiable with this model and these data.

    """
    vehicle = _load_vehicle(vehicle)
    plant = vehicle.plant
    data, warn = [], []
    for bag in bags:
        rec = read_recording(bag, vehicle, namespace)
        s = sampled_data(rec, vehicle)
        warn += [f'{bag}: {w}' for w in rec.warnings + s.warnings]
        data.append(s)
    del rec                 # only the sampled arrays are kept
    dt = data[0].dt
    for bag, s in zip(bags, data):
        if abs(s.dt / dt - 1.0) > 1e-3:
            raise BagToolError(f'{bag}: sample step {s.dt:.6g} s differs from {dt:.6g} s of '
                               f'{bags[0]}: identify bags of one rate together')
    Ad, Bd = sampled_model(vehicle, dt)
    C, D = np.asarray(plant.C, float), np.asarray(plant.D, float)
    G, noise_names = noise_input(vehicle, states, input_noise)
    F = process_noise_map(plant.A, G, dt, plant.is_discrete)
    Lp, reference = reference_gain(vehicle, Ad, dt, G)
    rho = float(np.max(np.abs(np.linalg.eigvals(Ad - Lp @ C))))
    drop = max(10, int(math.ceil(math.log(TRANSIENT_DECAY) / math.log(rho)))) \
        if 0.0 < rho < 1.0 else 10
    if burn is not None:
        drop = int(burn)
    short = [str(b) for b, s in zip(bags, data) if s.y.shape[0] - drop < 10 * lags]
    if short:
        raise BagToolError(f'{short[0]}: fewer than {10 * lags} samples after dropping the '
                           f'first {drop} (the transient); record longer or lower --burn')
    names = (noise_names, list(plant.output_names))
    outputs = list(plant.output_names)
    p = len(outputs)

    # the innovations are never held whole: each pass runs its predictor a block at a
    # time into running lagged sums (per bag for ALS; one sequence, the bags end to end,
    # for Mehra's test); the reference's prediction at the end of the transient starts
    # every later pass
    starts = [predictor_blocks(Ad, Bd, C, D, Lp, s.y[:drop], s.u[:drop], s.u_meas[:drop],
                               block=block) for s in data]

    def run(gain, mehra=False):
        """Run the predictor of ``gain`` after the transient; return its sums."""
        sums = LaggedSums(p, lags)
        white = LaggedSums(p, WHITENESS_LAGS + 1) if mehra else None
        for s, x0 in zip(data, starts):
            sums.new_sequence()
            predictor_blocks(Ad, Bd, C, D, gain, s.y[drop:], s.u[drop:], s.u_meas[drop:],
                             x0=x0, sinks=[sums] + ([white] if mehra else []), block=block)
        return sums, white

    results = []
    gain = Lp
    before = None
    for i in range(max(1, int(passes))):
        sums, white = run(gain, mehra=i == 0)
        if i == 0:
            before = _mehra(white, outputs)
        res = identify_noise(sums, Ad, C, gain, F, G.shape[1], lags, full, names)
        results.append(res)
        if np.min(np.linalg.eigvalsh(res.R)) <= 0.0:
            raise ALSError('the identified measurement noise covariance R is not positive '
                           f'definite (diag {np.diag(res.R).tolist()}): the data do not '
                           'show measurement noise; a Kalman filter cannot be designed')
        gain = kalman_predictor_gain(Ad, C, res.Qk, res.R)
    after = _mehra(run(gain, mehra=True)[1], outputs)
    return Identification(vehicle, [str(b) for b in bags], dt, G, noise_names, reference,
                          results, {str(b): int(s.y.shape[0]) for b, s in zip(bags, data)},
                          drop, before, after, warn)
