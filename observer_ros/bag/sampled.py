# observer_ros.bag.sampled: a recording as regularly sampled arrays (y, u) for identification.
"""
A recording's measurements and commands on the sample grid, and the sampled model.

Noise identification (:mod:`observer_ros.core.als`) works on a regularly sampled model:
``y[k]`` every output at sample k, ``u[k]`` the command held from sample k to k + 1 (the
last command stamped at or before it: the compensator answers the measurement of sample k
with a command of the same stamp) and ``u_meas[k]`` the one in effect when ``y[k]`` was
measured (the last stamped strictly before it, for ``D u``). A continuous plant is sampled
with a zero-order hold at the median step, as the estimators do.

"""

from dataclasses import dataclass
from typing import List, Tuple

import numpy as np

from .errors import BagToolError
from ..core.als import kalman_predictor_gain, process_noise_map
from ..core.design import observer_gain
from ..core.model import map_poles_to_discrete, zoh_matrices

__all__ = ['BLOCK', 'JITTER_MAX', 'Sampled', 'sampled_data', 'sampled_model', 'noise_input',
           'reference_gain']

#: Largest relative deviation of a sample step from the median step.
JITTER_MAX = 0.05
#: Samples looked at a time by :func:`sampled_data`'s checks and command look-up.
BLOCK = 1 << 16


@dataclass
class Sampled:
    """A recording on its sample grid (see the module)."""

    stamp_ns: np.ndarray          # (N,)
    y: np.ndarray                 # (N, p), outputs in the plant's order
    u: np.ndarray                 # (N, m)
    u_meas: np.ndarray            # (N, m)
    dt: float
    warnings: List[str]


def sampled_data(recording, vehicle, block=BLOCK):
    """
    Return the recording's outputs and inputs on the sample grid.

    The checks and the commands' look-up go a block of ``block`` samples at a time, so
    the transient memory is that of the one array of steps (8 bytes a sample) beside
    the result (``y``, ``u``, ``u_meas``); a stream whose messages are all valid is not
    copied for its stamps.

    Raises
    ------
    BagToolError
        An output is missing at a sample (sensors at different rates), too few samples,
        or the stamps are not regular (a step more than :data:`JITTER_MAX` from the
        median, e.g. a clock jump or a gap).

    """
    plant = vehicle.plant
    warnings = []
    stamps, picks = None, []
    for sensor in vehicle.sensors:
        stream = recording.sensors[sensor.name]
        sel = None if stream.valid.all() else np.flatnonzero(stream.valid)
        ns = stream.stamp_ns if sel is None else stream.stamp_ns[sel]
        if stamps is None:
            stamps = ns
        elif ns.size != stamps.size or not np.array_equal(ns, stamps):
            raise BagToolError(f'sensor {sensor.name!r} ({stream.topic}) is not measured at '
                               f'the same stamps as {vehicle.sensors[0].name!r} '
                               f'({ns.size} against {stamps.size} messages): the noise '
                               'identification needs every output at every sample')
        picks.append((sensor, stream, sel))
    if stamps is None or stamps.size < 100:
        raise BagToolError(f'{0 if stamps is None else stamps.size} samples: too few to '
                           'identify noise covariances (need at least 100)')
    dt = _regular_step(stamps, block)
    if vehicle.plant.is_discrete and abs(dt / vehicle.sample_time - 1.0) > JITTER_MAX:
        raise BagToolError(f"measurement step {dt:.6g} s is not the discrete model's "
                           f'model.sample_time {vehicle.sample_time:.6g} s')
    N, m = stamps.size, plant.m
    y = np.empty((N, plant.p))
    for sensor, stream, sel in picks:
        for j, row in enumerate(plant.output_rows(sensor.outputs)):
            y[:, row] = stream.values[:, j] if sel is None else stream.values[sel, j]
    u = np.zeros((N, m))
    u_meas = np.zeros((N, m))
    cmd = recording.command
    if m and (cmd is None or not cmd.valid.any()):
        warnings.append('no control/u in the bag: the inputs are taken as zero')
    elif m:
        sel = np.flatnonzero(cmd.valid)
        order = np.argsort(cmd.stamp_ns[sel], kind='stable')
        c_ns, c_val = cmd.stamp_ns[sel][order], cmd.values[sel][order]
        for a in range(0, N, block):
            t = stamps[a:a + block]
            at = np.searchsorted(c_ns, t, side='right') - 1       # stamp <= t_k
            before = np.searchsorted(c_ns, t, side='left') - 1    # stamp < t_k
            u[a:a + block][at >= 0] = c_val[at[at >= 0]]
            u_meas[a:a + block][before >= 0] = c_val[before[before >= 0]]
    return Sampled(stamps, y, u, u_meas, dt, warnings)


def _regular_step(stamps, block):
    """Return the median step in seconds; refuse stamps that are not increasing or regular."""
    steps = np.diff(stamps)
    if np.any(steps <= 0):
        raise BagToolError('measurement stamps are not increasing (a clock jump or '
                           'reordered messages): cut the bag to one run')
    # np.median of the steps in seconds, partitioning the integer steps in place: the
    # middle one, or the mean of the two middle ones, converted as the steps were
    k = steps.size // 2
    steps.partition([k - 1, k] if steps.size % 2 == 0 else [k])
    middle = steps[k - 1:k + 1] if steps.size % 2 == 0 else steps[k:k + 1]
    middle = [float(x) * 1e-9 for x in middle]
    dt = float(np.mean(middle))
    del steps
    worst, where = -1.0, 0
    for a in range(0, stamps.size - 1, block):
        rel = np.abs(np.diff(stamps[a:a + block + 1]).astype(np.float64) * 1e-9 / dt - 1.0)
        k = int(np.argmax(rel))
        if rel[k] > worst:
            worst, where = float(rel[k]), a + k
    if worst > JITTER_MAX:
        step = float(stamps[where + 1] - stamps[where]) * 1e-9
        raise BagToolError(f'measurement steps are not regular: {step:.6g} s at sample '
                           f'{where + 1} against a median of {dt:.6g} s (more than '
                           f'{JITTER_MAX:.0%} off)')
    return dt


def sampled_model(vehicle, dt):
    """Return (Ad, Bd) of the plant at step dt (zero-order hold for a continuous plant)."""
    plant = vehicle.plant
    if plant.is_discrete:
        return np.asarray(plant.A, float), np.asarray(plant.B, float)
    return zoh_matrices(plant.A, plant.B, dt)


def noise_input(vehicle, states=None, inputs=False):
    """
    Return the process noise input G (n x k) and the names of its columns.

    ``inputs``: noise added to the inputs (G = the plant's B, a force or torque
    disturbance); ``states`` (names): noise on those states; otherwise the vehicle's
    ``observer.Bd`` when it has one, else noise on every state.

    """
    plant = vehicle.plant
    names = list(plant.state_names)
    if inputs and states:
        raise BagToolError('--input-noise and --states: give one of them')
    if inputs:
        if not plant.m:
            raise BagToolError(f'--input-noise: {vehicle.name} has no inputs')
        return np.asarray(plant.B, float).copy(), [f'w_{u}' for u in plant.input_names]
    if states:
        bad = [s for s in states if s not in names]
        if bad:
            raise BagToolError(f'--states: {bad[0]!r} is not a state of {vehicle.name} '
                               f'({", ".join(names)})')
        G = np.zeros((plant.n, len(states)))
        for j, s in enumerate(states):
            G[names.index(s), j] = 1.0
        return G, [f'w_{s}' for s in states]
    Bd = vehicle.observer.Bd
    if Bd is not None:
        Bd = np.asarray(Bd, dtype=float).reshape(plant.n, -1)
        return Bd, [f'Bd[:, {j}]' for j in range(Bd.shape[1])]
    return np.eye(plant.n), [f'w_{s}' for s in names]


def reference_gain(vehicle, Ad, dt, G) -> Tuple[np.ndarray, str]:
    """
    Return a stable predictor gain and what it is.

    The vehicle's own observer in predictor form when it is a ``full`` observer given by
    poles (``eig(Ad - Lp C)`` at its poles, mapped by ``z = exp(s dt)`` for a continuous
    model) or a ``kalman`` one (the steady-state predictor of its Qd, Rd); otherwise the
    Kalman predictor of unit noise on G's columns and on each output (any stable gain
    will do).

    """
    plant = vehicle.plant
    C = np.asarray(plant.C, float)
    obs = vehicle.observer
    if obs.kind == 'full' and obs.poles is not None:
        z = obs.poles if plant.is_discrete else map_poles_to_discrete(obs.poles, dt)
        return observer_gain(Ad, C, z, discrete=True), "the vehicle's observer poles"
    F = process_noise_map(plant.A, G if obs.kind != 'kalman' or obs.Bd is None
                          else np.asarray(obs.Bd, float).reshape(plant.n, -1),
                          dt, plant.is_discrete)
    if obs.kind == 'kalman' and obs.Qd is not None and obs.Rd is not None:
        Lp = kalman_predictor_gain(Ad, C, F(np.asarray(obs.Qd, float)),
                                   np.asarray(obs.Rd, float))
        return Lp, "the vehicle's Kalman filter (its Qd, Rd)"
    Lp = kalman_predictor_gain(Ad, C, process_noise_map(plant.A, G, dt, plant.is_discrete)(
        np.eye(G.shape[1])), np.eye(plant.p))
    return Lp, 'a Kalman predictor of unit noise (the vehicle has no full or kalman observer)'
