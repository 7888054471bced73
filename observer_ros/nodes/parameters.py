# observer_ros.nodes.parameters: how the nodes declare their parameters (descriptors).
"""
Declare a node's parameters with ROS ParameterDescriptors made from the vehicle schema.

Every parameter a node has is declared with what ``observer_ros.vehicle.schema`` says of
it (``KNOWN_KEYS``/``SENSOR_KEYS`` for the vehicle file, ``NODE_KEYS`` for the node's own):
the description, ``read_only`` for what the node reads once at start (the vehicle, model,
sensors and simulator sections), and the bound as ``floating_point_range`` or
``integer_range``, with the bound in words in ``additional_constraints``.
``ros2 param describe`` shows them; rclpy refuses a value outside the range, and
``ros2 param set`` of a read-only parameter with ``Trying to set a read-only parameter``.

ROS ranges are closed intervals: a bound that excludes 0 (``> 0``) is given as the least
positive double, 5e-324 (``schema.ros_range``), and said as ``> 0`` in the constraints.

A writable vehicle key that the file did not give (``observer.rate_hz``) is declared
when it is first set (:func:`set_undeclared`); any other undeclared name is refused
with a reason that names it.

"""

import time

from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                SetParametersResult)
from rcl_interfaces.srv import SetParameters
from rclpy.exceptions import InvalidParameterValueException
from rclpy.parameter import Parameter
from rclpy.parameter_service import ParameterService

from ..core.errors import ObserverError
from ..core.health import WorkBudget
from ..vehicle.schema import (bound_problem, interval_text, known_keys, NODE_KEYS,
                              READ_ONLY_SECTIONS, ros_range)

__all__ = ['READ_ONLY_SECTIONS', 'declare_parameters', 'describe', 'node_schema',
           'set_undeclared', 'GatedParameterService']

_OPEN_NOTE = ' (Min value 5e-324, the least double above 0: ROS ranges are closed)'


def _matches(param_type, value):
    if param_type == 'DOUBLE':
        return isinstance(value, float)
    return param_type == 'INTEGER' and isinstance(value, int) and not isinstance(value, bool)


def describe(name, value, schema, own=None):
    """
    Return the ParameterDescriptor of one parameter.

    Parameters
    ----------
    name : str
        The parameter name (``model.A``, ``diagnostics_period``).
    value : object
        Its value (the range is given only when its type is the schema's: a value of
        another type is refused by the loader with its own message).
    schema : dict
        :func:`node_schema` (or :func:`observer_ros.vehicle.known_keys`) for the node.
    own : str, optional
        The description of a parameter of the node's own that the schema does not have.

    Returns
    -------
    rcl_interfaces.msg.ParameterDescriptor

    """
    descriptor = ParameterDescriptor(name=name)
    spec = schema.get(name, NODE_KEYS.get(name))
    if spec is None:
        descriptor.description = own if own is not None else (
            'not a key of the vehicle schema (docs/vehicle_schema.md); ignored')
        descriptor.read_only = own is None and name.split('.', 1)[0] in READ_ONLY_SECTIONS
        return descriptor
    text = spec.description + ('; required' if spec.required else '')
    if spec.choices:
        text += f'; one of {", ".join(spec.choices)}'
    descriptor.description = text + (f' [{spec.unit}]' if spec.unit else '')
    descriptor.read_only = spec.read_only
    limits = ros_range(spec)
    if limits is not None and _matches(spec.param_type, value):
        if spec.param_type == 'DOUBLE':
            descriptor.floating_point_range = [FloatingPointRange(
                from_value=limits[0], to_value=limits[1])]
        else:
            descriptor.integer_range = [IntegerRange(from_value=limits[0],
                                                     to_value=limits[1], step=1)]
    said = [interval_text(spec) + (_OPEN_NOTE if spec.low_open else '')] if spec.bounded \
        else []
    said += [spec.rule] if spec.rule else []
    descriptor.additional_constraints = '; '.join(said)
    return descriptor


def node_schema(node):
    """Return the schema of a node's parameters: the vehicle keys for its sensors."""
    overrides = dict(node._parameter_overrides)    # noqa: SLF001 - rclpy keeps them here
    declared = node._parameters                      # noqa: SLF001
    names = declared.get('sensors.names') or overrides.get('sensors.names')
    sensors = names.value if names is not None and isinstance(names.value, list) else []
    return known_keys([s for s in sensors if isinstance(s, str)])


def declare_parameters(node, own_parameters=()):
    """
    Declare the command line's parameters and the node's own, each with a descriptor.

    Parameters
    ----------
    node : rclpy.node.Node
        Built with ``automatically_declare_parameters_from_overrides=False``: the
        overrides (``--params-file``, ``-p``) are declared here instead.
    own_parameters : sequence of str or tuple
        The node's own parameters: names of ``NODE_KEYS`` (default, description and
        bound from the schema), or ``(name, default, description)`` for others.

    Raises
    ------
    ObserverError
        A value outside its range, naming the parameter and the bound.

    """
    overrides = dict(node._parameter_overrides)    # noqa: SLF001 - rclpy keeps them here
    schema = node_schema(node)
    own = {}
    for entry in own_parameters:
        if isinstance(entry, str):
            entry = (entry, NODE_KEYS[entry].default, None)
        name, default, text = (tuple(entry) + (None,))[:3]
        own[name] = (default, None if name in NODE_KEYS else (text or ''))
    for name, param in overrides.items():
        if not node.has_parameter(name):
            text = own[name][1] if name in own else None
            _declare(node, name, param.value, describe(name, param.value, schema, text))
    for name, (default, text) in own.items():
        if not node.has_parameter(name):
            _declare(node, name, default, describe(name, default, schema, text))


def _declare(node, name, value, descriptor):
    try:
        node.declare_parameter(name, value, descriptor)
    except InvalidParameterValueException as err:
        spec = node_schema(node).get(name, NODE_KEYS.get(name))
        problem = bound_problem(spec, value) if spec is not None and spec.bounded and \
            _matches(spec.param_type, value) else None
        raise ObserverError(f'{name}: {problem}' if problem else
                            f'{name}: {value!r} refused: {err}') from None


def _reason(err, name):
    """Return the reason in an rclpy InvalidParameterValueException's text."""
    text = str(err)
    text = text.split('Reason: ', 1)[1] if 'Reason: ' in text else text
    return text[:-len(name) - 2] if text.endswith(f': {name}') else text


def set_undeclared(node, parameters):
    """
    Declare parameters the node has not declared, with their values; return the result.

    A writable vehicle key (``observer.*``, ``controller.*``) the file did not give is
    declared with its value and its descriptor, which runs the node's checks of a change
    as a set would; a read-only key or a name the schema does not know is refused with a
    reason that names it, and then none is declared.

    Parameters
    ----------
    node : rclpy.node.Node
        The node (its parameters include ``sensors.names``).
    parameters : sequence of rclpy.parameter.Parameter
        Undeclared parameters, as a ``ros2 param set`` asks for them.

    Returns
    -------
    rcl_interfaces.msg.SetParametersResult

    """
    schema = node_schema(node)
    where = node.get_fully_qualified_name()
    for p in parameters:
        spec = schema.get(p.name)
        if spec is None:
            return SetParametersResult(successful=False, reason=(
                f'{p.name}: not a parameter of {where}: neither a key of the vehicle schema '
                f'(docs/vehicle_schema.md) nor one of its own (ros2 param list {where})'))
        if spec.read_only:
            return SetParametersResult(successful=False, reason=(
                f'{p.name}: read-only (read once, at start), and not among the parameters '
                f'{where} started with'))
    for p in parameters:
        try:
            node.declare_parameter(p.name, p.value, describe(p.name, p.value, schema))
        except InvalidParameterValueException as err:
            return SetParametersResult(successful=False, reason=_reason(err, p.name))
    return SetParametersResult(successful=True)


class GatedParameterService(ParameterService):
    """
    rclpy's parameter services, with the set requests admitted by a work budget.

    A change of the observer's or controller's keys redesigns the node (tenths of a
    second of its executor, where estimation and control run too); a client that sends
    a thousand a second would leave it no time for anything else. Each SetParameters or
    SetParametersAtomically request is answered at once, without running the node's
    checks, when every writable parameter in it already has the value asked (``ros2 param
    load`` of a dump; read-only ones are refused by rclpy as always), and refused at once
    (``busy: ...``, counted ``parameter_changes_refused``) while the node's parameter work
    of the last ``PARAMETER_WINDOW`` s took more than ``PARAMETER_SHARE`` of it
    (core.health.WorkBudget); otherwise it is handled as rclpy handles it (SetParameters
    one parameter at a time), and timed (the CPU time of the executor's thread).
    """

    def __init__(self, node, budget=None):
        self.budget = budget or WorkBudget()
        super().__init__(node)

    def _gate(self, request):
        """Return (parameters to change, why they are refused or None)."""
        node = self._get_node()
        changed = [p for p in request.parameters if not _unchanged(node, p)]
        if not changed or all(_read_only(node, p) for p in changed):
            return changed, None            # rclpy refuses a read-only one at no cost
        return changed, self.budget.refuse(time.monotonic())

    def _timed(self, handle, request, response):
        start = time.thread_time()
        try:
            return handle(request, response)
        finally:
            self.budget.spent(time.thread_time() - start, time.monotonic())

    def _refused(self, reason):
        node = self._get_node()
        if hasattr(node, 'count'):
            node.count('parameter_changes_refused')
        return SetParametersResult(successful=False, reason=reason)

    def _set_parameters_callback(self, request, response):
        # one result per parameter, each set on its own (as rclpy's service does)
        for p in request.parameters:
            one = SetParameters.Request(parameters=[p])
            changed, reason = self._gate(one)
            if not changed:
                response.results.append(SetParametersResult(successful=True))
            elif reason is not None:
                response.results.append(self._refused(reason))
            else:
                response.results.extend(self._timed(super()._set_parameters_callback, one,
                                                    SetParameters.Response()).results)
        return response

    def _set_parameters_atomically_callback(self, request, response):
        changed, reason = self._gate(request)
        if not changed:
            response.result = SetParametersResult(successful=True)
            return response
        if reason is not None:
            response.result = self._refused(reason)
            return response
        return self._timed(super()._set_parameters_atomically_callback, request, response)


def _read_only(node, msg):
    """Tell whether a parameter message names a read-only parameter of the node."""
    return node.has_parameter(msg.name) and node.describe_parameter(msg.name).read_only


def _unchanged(node, msg):
    """
    Tell whether a parameter message asks for the value (and type) the node has.

    Never for a read-only parameter: rclpy refuses a set of one, whatever its value, at
    no cost (``ros2 param load`` reports them as not set).
    """
    if not node.has_parameter(msg.name) or _read_only(node, msg):
        return False
    current = node.get_parameter(msg.name)
    try:
        asked = Parameter.from_parameter_msg(msg)
    except (TypeError, ValueError):
        return False
    if asked.type_ != current.type_:
        return False
    a, b = asked.value, current.value
    if isinstance(a, (list, tuple)) or hasattr(a, 'tolist'):
        return list(a) == list(b)
    return a == b
