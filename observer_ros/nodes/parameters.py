# observer_ros.nodes.parameters: how the nodes declare their parameters (descriptors).
"""
Declare a node's parameters with ROS ParameterDescriptors built from the vehicle schema.

Every parameter a node has is declared with a description (the vehicle keys' from
``observer_ros.vehicle.KNOWN_KEYS``/``SENSOR_KEYS``, which test/test_vehicle.py checks
against docs/vehicle_schema.md), ``read_only`` for what the node reads once at start (the
vehicle, model, sensors and topics, and the simulator's set-up), and a range for scalars
with a lower bound. ``ros2 param describe`` shows them; ``ros2 param set`` of a read-only
parameter is refused by rclpy with ``Trying to set a read-only parameter``.

"""

import sys

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.exceptions import InvalidParameterValueException

from ..core.errors import ObserverError
from ..vehicle import known_keys

__all__ = ['READ_ONLY_SECTIONS', 'declare_parameters', 'describe']

# Vehicle sections a node reads once, at start: changing them at run time would have no
# effect (or leave the node inconsistent), so they are read-only.
READ_ONLY_SECTIONS = ('vehicle', 'model', 'sensors', 'simulator')

_INT_MAX = 2 ** 63 - 1


def describe(name, value, schema, own=None):
    """
    Return the ParameterDescriptor of one parameter.

    Parameters
    ----------
    name : str
        The parameter name (``model.A``, ``diagnostics_period``).
    value : object
        Its value (the range is given only when its type is the schema's).
    schema : dict
        :func:`observer_ros.vehicle.known_keys` for the node's sensors.
    own : str, optional
        The description of one of the node's own parameters.

    Returns
    -------
    rcl_interfaces.msg.ParameterDescriptor

    """
    section = name.split('.', 1)[0]
    descriptor = ParameterDescriptor(name=name)
    spec = schema.get(name)
    if own is not None:
        descriptor.description = own
    elif spec is not None:
        text = spec.description + ('; required' if spec.required else '')
        if spec.choices:
            text += f'; one of {", ".join(spec.choices)}'
        descriptor.description = text
        if spec.minimum is not None:
            if spec.param_type == 'DOUBLE' and isinstance(value, float):
                descriptor.floating_point_range = [FloatingPointRange(
                    from_value=float(spec.minimum), to_value=sys.float_info.max)]
            elif spec.param_type == 'INTEGER' and isinstance(value, int) and \
                    not isinstance(value, bool):
                descriptor.integer_range = [IntegerRange(
                    from_value=int(spec.minimum), to_value=_INT_MAX, step=1)]
    else:
        descriptor.description = ('not a key of the vehicle schema (docs/vehicle_schema.md); '
                                  'ignored')
    descriptor.read_only = section in READ_ONLY_SECTIONS
    return descriptor


def declare_parameters(node, own_parameters=()):
    """
    Declare the command line's parameters and the node's own, each with a descriptor.

    Parameters
    ----------
    node : rclpy.node.Node
        Built with ``automatically_declare_parameters_from_overrides=False``: the
        overrides (``--params-file``, ``-p``) are declared here instead.
    own_parameters : sequence of tuple
        ``(name, default, description)`` of the node's own parameters.

    Raises
    ------
    ObserverError
        A value outside its range, naming the parameter.

    """
    overrides = dict(node._parameter_overrides)    # noqa: SLF001 - rclpy keeps them here
    names = overrides.get('sensors.names')
    sensors = names.value if names is not None and isinstance(names.value, list) else []
    schema = known_keys([s for s in sensors if isinstance(s, str)])
    own = {entry[0]: entry for entry in own_parameters}
    for name, param in overrides.items():
        if node.has_parameter(name):
            continue
        text = own[name][2] if name in own else None
        _declare(node, name, param.value, describe(name, param.value, schema, text))
    for name, default, text in own_parameters:
        if not node.has_parameter(name):
            _declare(node, name, default, describe(name, default, schema, text))


def _declare(node, name, value, descriptor):
    try:
        node.declare_parameter(name, value, descriptor)
    except InvalidParameterValueException as err:
        raise ObserverError(f'{name}: {value!r} refused: {err}') from None
