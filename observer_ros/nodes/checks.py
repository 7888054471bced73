# observer_ros.nodes.checks: run-time parameter checks.
"""
What a node checks when a parameter changes.

``own_parameter_problem`` refuses a node's own tolerances, periods and timeouts that are
not finite or out of range (a negative ``future_tolerance`` silently stopped the
observer); ``changed_pole_problem`` refuses poles without a stability margin on the
plant's time scale (core.health.pole_margin_problem).

"""

import math

from ..vehicle.schema import bound_problem, NODE_KEYS

__all__ = ['own_parameter_problem', 'changed_pole_problem']


def own_parameter_problem(params):
    """
    Return why one of these parameter changes is refused, or None.

    The bounds are the schema's (``observer_ros.vehicle.schema.NODE_KEYS``), the ones the
    nodes' descriptors give ROS.

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
        spec = NODE_KEYS.get(p.name)
        if spec is None:
            continue
        value = p.value
        if spec.param_type == 'BOOL':
            if not isinstance(value, bool):
                return f'{p.name}: expected true or false; got {value!r}'
            continue
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            return f'{p.name}: expected a number; got {value!r}'
        if not math.isfinite(value):
            return f'{p.name}: {value} is not finite'
        problem = bound_problem(spec, value)
        if problem is not None:
            return f'{p.name}: {problem}'
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
