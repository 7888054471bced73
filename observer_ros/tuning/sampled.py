# observer_ros.tuning.sampled: a recording as regularly sampled arrays (y, u) for identification.
"""
A recording's measurements and commands at their stamps, and the sampled model.

Noise identification (:mod:`observer_ros.core.als`) works on the steps of a recording:
the stamps at which an output was measured and, for a continuous plant, those at which
the command changed (so the command is held from one step to the next). ``y[k]`` has
each output measured at step k and NaN for those that were not (a message lost, a sensor
at another rate or latency), ``u[k]`` the command held from step k to k + 1 (the last one
stamped at or before it: the compensator answers the measurement of a sample with a
command of the same stamp) and ``u_meas[k]`` the one in effect when ``y[k]`` was measured
(the last stamped strictly before it, for ``D u``). Step lengths are the stamps' own: a
continuous plant is sampled exactly at each (:mod:`observer_ros.core.als_ltv`). A
discrete plant's steps are its samples: each stamp is put on the nearest sample of its
``model.sample_time`` grid (refused when it is more than a quarter of a sample off).

"""

from dataclasses import dataclass, field
import math
from typing import Dict, List, Tuple

import numpy as np

from ..bag.errors import BagToolError
from ..core.als import kalman_predictor_gain, process_noise_map
from ..core.design import observer_gain
from ..core.model import map_poles_to_discrete, zoh_matrices

__all__ = ['BLOCK', 'GRID_TOLERANCE', 'REGULAR', 'Sampled', 'sampled_data', 'sampled_model',
           'noise_input', 'reference_gain', 'present_patterns', 'unstable_pattern',
           'unit_kalman_gain']

#: Samples looked at a time by :func:`sampled_data`'s command look-up.
BLOCK = 1 << 16
#: A discrete plant's stamps may be this fraction of a sample off its grid.
GRID_TOLERANCE = 0.25
#: Steps within this fraction of the median step count as regular.
REGULAR = 1e-6


@dataclass
class Sampled:
    """A recording at its steps (see the module)."""

    stamp_ns: np.ndarray          # (N,) the steps
    y: np.ndarray                 # (N, p), outputs in the plant's order, NaN: not measured
    u: np.ndarray                 # (N, m)
    u_meas: np.ndarray            # (N, m)
    dt: float                     # the median step between measurements, s
    warnings: List[str]
    regular: bool = True          # every output at every step, every step dt long
    missing: Dict[str, float] = field(default_factory=dict)   # output -> fraction
    steps: Tuple[float, float] = (math.nan, math.nan)         # shortest, longest / dt
    measured: int = 0             # steps with a measurement

    @property
    def t(self):
        """Return the steps' stamps in seconds from the first."""
        return (self.stamp_ns - self.stamp_ns[0]).astype(np.float64) * 1e-9


def _sensor_stamps(sensor, stream, warnings):
    """
    Return a sensor's valid stamps (sorted) and the rows of its values they come from.

    The rows are None when they are every row in order (no copy of the stamps is made).

    """
    sel = None if stream.valid.all() else np.flatnonzero(stream.valid)
    ns = stream.stamp_ns if sel is None else stream.stamp_ns[sel]
    if ns.size > 1 and not _increasing(ns):
        if _any_back(ns):
            steps = np.diff(ns)
            typical = float(np.median(np.abs(steps))) if steps.size else 0.0
            back = float(-steps.min())
            del steps
            if back > max(10.0 * typical, 1e9):
                raise BagToolError(f'sensor {sensor.name!r} ({stream.topic}): its stamps go '
                                   f'back by {back * 1e-9:.3g} s (a clock jump: two runs in '
                                   'one bag): cut the bag to one run')
            order = np.argsort(ns, kind='stable')
            sel = order if sel is None else sel[order]
            ns = ns[order]
        same = np.flatnonzero(ns[1:] == ns[:-1])
        if same.size:
            keep = np.ones(ns.size, dtype=bool)
            keep[same] = False                      # the later message of a stamp wins
            warnings.append(f'sensor {sensor.name!r}: {same.size} messages repeat an '
                            'earlier stamp; the last of each is used')
            sel = np.flatnonzero(keep) if sel is None else sel[keep]
            ns = ns[keep]
    return ns, sel


def _increasing(ns, block=BLOCK):
    """Tell whether the stamps strictly increase (checked a block at a time)."""
    return all(_later(ns[a:a + block + 1]).all() for a in range(0, ns.size - 1, block))


def _any_back(ns, block=BLOCK):
    """Tell whether a stamp is earlier than the one before it."""
    return any((part[1:] < part[:-1]).any()
               for part in (ns[a:a + block + 1] for a in range(0, ns.size - 1, block)))


def _later(part):
    """Return whether each stamp of ``part`` is after the one before it."""
    return part[1:] > part[:-1]


def _sorted_union(parts):
    """Return the sorted distinct values of sorted arrays (one array: itself, no copy)."""
    if len(parts) == 1:
        return parts[0]
    out = np.sort(np.concatenate(parts), kind='stable')
    keep = np.ones(out.size, dtype=bool)
    keep[1:] = out[1:] != out[:-1]
    return out[keep]


def _all_in(values, steps, block=BLOCK):
    """Tell whether every one of ``values`` is one of the sorted ``steps``."""
    for a in range(0, values.size, block):
        v = values[a:a + block]
        at = np.minimum(np.searchsorted(steps, v), steps.size - 1)
        if not np.array_equal(steps[at], v):
            return False
    return True


def _step_range(meas, block=BLOCK):
    """Return the shortest and longest step between stamps (ns), a block at a time."""
    lo, hi = np.inf, -np.inf
    for a in range(0, meas.size - 1, block):
        d = np.diff(meas[a:a + block + 1])
        lo, hi = min(lo, float(d.min())), max(hi, float(d.max()))
    return lo, hi


def sampled_data(recording, vehicle, block=BLOCK):
    """
    Return the recording's outputs and inputs at its steps (see the module).

    Raises
    ------
    BagToolError
        Fewer than 100 steps with a measurement, an output never measured, stamps going
        back (a clock jump), or a discrete plant's stamps off its sample grid.

    """
    plant = vehicle.plant
    warnings = []
    picks = []
    for sensor in vehicle.sensors:
        stream = recording.sensors[sensor.name]
        ns, sel = _sensor_stamps(sensor, stream, warnings)
        if not ns.size:
            raise BagToolError(f'sensor {sensor.name!r} ({stream.topic}) has no valid '
                               'message: its outputs cannot be identified')
        picks.append((sensor, stream, ns, sel))
    meas = _sorted_union([ns for _, _, ns, _ in picks])
    if meas.size < 100:
        raise BagToolError(f'{meas.size} samples: too few to identify noise covariances '
                           '(need at least 100)')
    dt = float(np.median(np.diff(meas), overwrite_input=True)) * 1e-9
    cmd = recording.command
    m = plant.m
    c_ns = c_val = None
    if m and (cmd is None or not cmd.valid.any()):
        warnings.append('no control/u in the bag: the inputs are taken as zero')
    elif m:
        sel = None if cmd.valid.all() else np.flatnonzero(cmd.valid)
        c_ns = cmd.stamp_ns if sel is None else cmd.stamp_ns[sel]
        c_val = cmd.values if sel is None else cmd.values[sel]
        if c_ns.size > 1 and _any_back(c_ns):
            order = np.argsort(c_ns, kind='stable')
            c_ns, c_val = c_ns[order], c_val[order]
    if plant.is_discrete:
        T = float(vehicle.sample_time)
        steps, index = _grid(meas, T)
        if c_ns is not None:
            c_ns = meas[0] + np.rint((c_ns - meas[0]) * 1e-9 / T).astype(np.int64) * \
                int(round(T * 1e9))
        dt = T
    else:
        steps, index = meas, None           # None: every step is a measurement's
        if c_ns is not None:
            a = np.searchsorted(c_ns, meas[0], side='right')
            b = np.searchsorted(c_ns, meas[-1], side='left')
            inside = c_ns[a:max(a, b)]                  # strictly between the first and last
            if inside.size and not _all_in(inside, meas):
                steps = _sorted_union([meas, inside])
                index = np.searchsorted(steps, meas)
    N = steps.size
    y = np.full((N, plant.p), np.nan)
    present = np.zeros((N, plant.p), dtype=bool)
    for sensor, stream, ns, sel in picks:
        if ns is meas and index is None:
            at = slice(None)                    # the one sensor's stamps are the steps
        else:
            at = np.searchsorted(meas, ns)
            if index is not None:
                at = index[at]
        if plant.is_discrete and np.any(np.diff(at) == 0):
            raise BagToolError(f'sensor {sensor.name!r}: two of its stamps fall on one sample '
                               "of the discrete model's grid (model.sample_time "
                               f'{vehicle.sample_time:.6g} s)')
        for j, row in enumerate(plant.output_rows(sensor.outputs)):
            y[at, row] = stream.values[:, j] if sel is None else stream.values[sel, j]
            present[at, row] = True
    measured = present.any(axis=1)
    count = int(np.count_nonzero(measured))
    missing = {name: 1.0 - float(np.count_nonzero(present[measured, i])) / count
               for i, name in enumerate(plant.output_names)}
    u = np.zeros((N, m))
    u_meas = np.zeros((N, m))
    if c_ns is not None:
        for a in range(0, N, block):
            t = steps[a:a + block]
            at = np.searchsorted(c_ns, t, side='right') - 1       # stamp <= t_k
            before = np.searchsorted(c_ns, t, side='left') - 1    # stamp < t_k
            u[a:a + block][at >= 0] = c_val[at[at >= 0]]
            u_meas[a:a + block][before >= 0] = c_val[before[before >= 0]]
    shortest, longest = (x * 1e-9 / dt for x in _step_range(meas))
    regular = bool(N == meas.size and present.all() and
                   abs(shortest - 1.0) <= REGULAR and abs(longest - 1.0) <= REGULAR)
    return Sampled(steps, y, u, u_meas, dt, warnings, regular, missing,
                   (shortest, longest), count)


def _grid(meas, T):
    """Return a discrete plant's sample stamps (first to last) and each stamp's sample."""
    rel = (meas - meas[0]).astype(np.float64) * 1e-9 / T
    k = np.rint(rel).astype(np.int64)
    off = np.abs(rel - k)
    worst = int(np.argmax(off))
    if off[worst] > GRID_TOLERANCE:
        raise BagToolError(f'measurement at {meas[worst] * 1e-9:.9g} s is {off[worst]:.0%} of '
                           f"a sample off the discrete model's grid (model.sample_time "
                           f'{T:.6g} s): stamps must be within {GRID_TOLERANCE:.0%} of it')
    step = int(round(T * 1e9))
    return meas[0] + np.arange(k[-1] + 1, dtype=np.int64) * step, k


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
    Lp = unit_kalman_gain(vehicle, Ad, dt, G)
    return Lp, 'a Kalman predictor of unit noise (the vehicle has no full or kalman observer)'


def unit_kalman_gain(vehicle, Ad, dt, G):
    """Return the Kalman predictor gain of unit noise on G's columns and on each output."""
    plant = vehicle.plant
    return kalman_predictor_gain(Ad, np.asarray(plant.C, float), process_noise_map(
        plant.A, G, dt, plant.is_discrete)(np.eye(G.shape[1])), np.eye(plant.p))


def present_patterns(samples):
    """Return the distinct sets of outputs present at a measured sample, as bool rows."""
    rows = []
    for s in samples:
        present = np.isfinite(s.y)
        present = present[present.any(axis=1)]
        if present.size:
            codes = np.packbits(present, axis=1, bitorder='little')
            rows.append(present[np.unique(codes, axis=0, return_index=True)[1]])
    if not rows:
        return np.zeros((0, 0), dtype=bool)
    return np.unique(np.concatenate(rows), axis=0)


def unstable_pattern(Ad, C, Lp, patterns):
    """
    Return ``(radius, pattern)`` of the worst predictor step with only some outputs present.

    The step from a sample with the outputs ``pattern`` present is ``Ad - Lp_S C_S`` (the
    gain's other columns unused). None when every such step (all outputs present
    excluded) has spectral radius below 1.

    """
    worst = None
    for row in patterns:
        if row.all():
            continue
        S = np.flatnonzero(row)
        rho = float(np.max(np.abs(np.linalg.eigvals(Ad - Lp[:, S] @ C[S]))))
        if rho >= 1.0 and (worst is None or rho > worst[0]):
            worst = (rho, row)
    return worst
