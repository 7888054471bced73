# observer_ros.nodes.checks: run-time parameter checks and the nodes' divergence envelopes.
"""
What a node checks when a parameter changes, and the bounds of a plausible run.

``own_parameter_problem`` refuses a node's own tolerances, periods and timeouts that are
not finite or out of range (a negative ``future_tolerance`` silently stopped the
observer); ``changed_pole_problem`` refuses poles without a stability margin on the
plant's time scale (core.health.pole_margin_problem). ``divergence_envelopes`` sets the
bounds of the estimate and the command from the vehicle file.

"""

import math

import numpy as np

from ..core.health import Envelope

__all__ = ['OWN_PARAMETER_RANGES', 'own_parameter_problem', 'changed_pole_problem',
           'divergence_envelopes']

# A node's own numeric parameters: (lowest, highest, lowest excluded), in their units.
OWN_PARAMETER_RANGES = {
    'clock_jump_tolerance': (0.0, 3600.0, True),     # s
    'future_tolerance': (0.0, 1e9, True),            # s
    'diagnostics_period': (0.01, 3600.0, False),     # s
    'start_time': (0.0, 1e9, True),                  # s
    'wait_for_subscribers': (0, 1000, False),
    'command_lead_steps': (0, 100, False),
}
BOOL_PARAMETERS = ('publish_array', 'publish_clock', 'wait_for_recorder', 'exit_when_done')


def own_parameter_problem(params):
    """
    Return why one of these parameter changes is refused, or None.

    Parameters
    ----------
    params : sequence of rclpy.parameter.Parameter
        The changes (a node's own parameters are checked; others are ignored).

    Returns
    -------
    reason : str or None
        Names the parameter, the value and the allowed range.

    """
    for p in params:
        if p.name in BOOL_PARAMETERS and not isinstance(p.value, bool):
            return f'{p.name}: expected true or false; got {p.value!r}'
        if p.name not in OWN_PARAMETER_RANGES:
            continue
        low, high, strict = OWN_PARAMETER_RANGES[p.name]
        value = p.value
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            return f'{p.name}: expected a number; got {value!r}'
        if not math.isfinite(value):
            return f'{p.name}: {value} is not finite'
        if value < low or (strict and value == low) or value > high:
            bracket = '(' if strict else '['
            return f'{p.name}: {value} is outside {bracket}{low:g}, {high:g}]'
    return None


def changed_pole_problem(vehicle, prefix, names):
    """
    Return why the poles of ``prefix`` (observer or controller) lack a margin, or None.

    Only when a ``<prefix>.poles`` or ``<prefix>.poles_imag`` is among the changed
    ``names`` (the file's own poles are the design's business).

    """
    from ..core.health import pole_margin_problem
    if not names & {f'{prefix}.poles', f'{prefix}.poles_imag'}:
        return None
    spec = vehicle.observer if prefix == 'observer' else vehicle.controller
    if spec.poles is None:
        return None
    plant = vehicle.plant
    return pole_margin_problem(spec.poles, plant.A, vehicle.sample_time, plant.is_discrete,
                               f'{prefix}.poles')


def state_scale(vehicle, x_d=None):
    """Return the plausible magnitude of each state from the file (initial values, x_d)."""
    n = vehicle.plant.n
    parts = [np.zeros(n)]
    for v in (vehicle.simulator.initial_state, vehicle.observer.initial_estimate, x_d,
              vehicle.controller.reference):
        if v is not None:
            parts.append(np.abs(np.asarray(v, dtype=float)))
    return np.max(parts, axis=0)


def divergence_envelopes(vehicle, K, x_d, Kd):
    """
    Return the envelopes of the estimate and of the command (before its limits).

    The command's scale is the file's input limits where given, else what the control law
    gives for the states' scale.
    """
    plant = vehicle.plant
    xs = Envelope(plant.state_names, state_scale(vehicle, x_d), 'x_hat')
    x_scale = xs.scale
    u_scale = np.abs(K) @ (x_scale + np.abs(x_d)) + np.abs(Kd @ x_d)
    c = vehicle.controller
    for limit in (c.u_min, c.u_max):
        if limit is not None:
            lim = np.abs(np.asarray(limit, dtype=float))
            u_scale = np.where(np.isfinite(lim), np.maximum(u_scale, lim), u_scale)
    return xs, Envelope(plant.input_names, u_scale, 'u')
