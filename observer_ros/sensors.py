# observer_ros.sensors: which message field carries which model output (no ROS imports).
"""
Read model outputs from sensor messages and write them into messages.

The functions work by attribute access, so they take rclpy messages
(``sensor_msgs.msg.Imu``), rosbags messages
(``get_typestore(Stores.ROS2_JAZZY).types['sensor_msgs/msg/Imu']``) and plain
stand-ins (``types.SimpleNamespace``) alike. The caller passes the message instance;
this module imports neither rclpy nor rosbags.

Fields (``sensors.<s>.fields`` in the vehicle file):

- ``sensor_msgs/msg/Imu``: ``angular_velocity.x|y|z``, ``linear_acceleration.x|y|z``,
  and ``orientation.roll|pitch|yaw``: the Euler angles (rad, ZYX: yaw, then pitch, then
  roll) of the orientation quaternion an attitude reference (AHRS) publishes;
- ``sensor_msgs/msg/JointState``: ``position.<joint>``, ``velocity.<joint>``,
  ``effort.<joint>``, the joint looked up by name in ``msg.name``;
- ``std_msgs/msg/Float64``: ``data``.

"""

from dataclasses import dataclass
import functools
import math
from typing import Optional, Tuple

import numpy as np

from .core.errors import ObserverError, VehicleFileError

__all__ = ['IMU', 'JOINT_STATE', 'FLOAT64', 'MESSAGE_FIELDS', 'FIELD_UNITS', 'field_units',
           'MeasurementError',
           'FieldAccessor', 'parse_field', 'field_help', 'extract_measurement',
           'fill_measurement', 'quaternion_to_euler', 'euler_to_quaternion',
           'max_components', 'too_many_components', 'vector_indices', 'vector_from_joint_state']

IMU = 'sensor_msgs/msg/Imu'
JOINT_STATE = 'sensor_msgs/msg/JointState'
FLOAT64 = 'std_msgs/msg/Float64'

_IMU_BLOCKS = ('angular_velocity', 'linear_acceleration')
_AXES = ('x', 'y', 'z')
_EULER = ('roll', 'pitch', 'yaw')
_JOINT_ARRAYS = ('position', 'velocity', 'effort')

# The fields a sensor may read, per message type (JointState: any joint name).
MESSAGE_FIELDS = {
    IMU: tuple(f'{block}.{axis}' for block in _IMU_BLOCKS for axis in _AXES) +
    tuple(f'orientation.{angle}' for angle in _EULER),
    JOINT_STATE: tuple(f'{array}.<joint>' for array in _JOINT_ARRAYS),
    FLOAT64: ('data',),
}


# The units ROS gives each field (REP 103: SI; sensor_msgs' own comments), by its first
# part: a JointState joint is revolute (rad) or prismatic (m); Float64 has no convention.
FIELD_UNITS = {
    (IMU, 'angular_velocity'): ('rad/s',),
    (IMU, 'linear_acceleration'): ('m/s^2',),
    (IMU, 'orientation'): ('rad',),
    (JOINT_STATE, 'position'): ('rad', 'm'),
    (JOINT_STATE, 'velocity'): ('rad/s', 'm/s'),
    (JOINT_STATE, 'effort'): ('N*m', 'N'),
}


def field_units(msg_type, field):
    """Return the units ROS allows for a sensor field (empty: no convention)."""
    return FIELD_UNITS.get((msg_type, field.split('.', 1)[0]), ())


class MeasurementError(ObserverError, ValueError):
    """A message cannot give the sensor's outputs (joint missing, value not finite, ...)."""


def field_help(msg_type):
    """Return the fields of msg_type as one line, for error messages."""
    if msg_type == IMU:
        return ('angular_velocity.x|y|z, linear_acceleration.x|y|z, '
                'orientation.roll|pitch|yaw')
    if msg_type == JOINT_STATE:
        return 'position.<joint>, velocity.<joint>, effort.<joint>'
    if msg_type == FLOAT64:
        return 'data'
    return 'none (unsupported message type)'


@dataclass(frozen=True)
class FieldAccessor:
    """
    How to read one field of a message: an attribute path, or a JointState joint.

    Call it on a message to get the value as a float: ``accessor(msg, topic='imu')``.

    """

    msg_type: str
    field: str
    path: Tuple[str, ...]               # attributes: ('angular_velocity', 'y'), ('position',)
    joint: Optional[str] = None         # JointState: the name looked up in msg.name

    def __call__(self, msg, topic=''):
        """Return the field's value in msg; MeasurementError if it cannot be read."""
        where = f'{topic}: ' if topic else ''
        if self.path[0] == 'orientation':
            return self._euler_value(msg, where)
        try:
            value = msg
            for attr in self.path:
                value = getattr(value, attr)
        except AttributeError:
            raise MeasurementError(
                f'{where}message {type(msg).__name__} has no field {self.field!r} '
                f'(expected a {self.msg_type})') from None
        if self.joint is not None:
            value = self._joint_value(msg, value, where)
        try:
            value = float(value)
        except (TypeError, ValueError):
            raise MeasurementError(
                f'{where}{self.field} is not a number: {value!r}') from None
        if not math.isfinite(value):
            raise MeasurementError(f'{where}{self.field} is {value} (not finite)')
        return value

    def _euler_value(self, msg, where):
        try:
            q = msg.orientation
            quat = tuple(float(c) for c in (q.x, q.y, q.z, q.w))
        except (AttributeError, TypeError, ValueError):
            raise MeasurementError(
                f'{where}message {type(msg).__name__} has no orientation quaternion '
                f'(expected a {self.msg_type})') from None
        if not all(math.isfinite(c) for c in quat):
            raise MeasurementError(f'{where}orientation is not finite: {quat}')
        if abs(math.sqrt(sum(c * c for c in quat)) - 1.0) > 1e-3:
            raise MeasurementError(f'{where}orientation is not a unit quaternion: {quat}')
        return quaternion_to_euler(*quat)[_EULER.index(self.path[1])]

    def _joint_value(self, msg, array, where):
        try:
            names = list(msg.name)
        except (AttributeError, TypeError):
            raise MeasurementError(f'{where}JointState has no name list') from None
        try:
            index = names.index(self.joint)
        except ValueError:
            shown = names[:8] + (['...'] if len(names) > 8 else [])   # a bounded log line
            raise MeasurementError(
                f'{where}joint {self.joint!r} is not in JointState.name {shown} '
                f'({len(names)} names)') from None
        if len(array) <= index:
            raise MeasurementError(
                f'{where}joint {self.joint!r}: JointState.{self.path[0]} has {len(array)} '
                f'values for {len(names)} names')
        return array[index]


def parse_field(msg_type, field):
    """
    Parse a field name of a message type into an accessor.

    Parameters
    ----------
    msg_type : str
        ``sensor_msgs/msg/Imu``, ``sensor_msgs/msg/JointState`` or ``std_msgs/msg/Float64``.
    field : str
        For example ``angular_velocity.y``, ``position.cart`` or ``data``.

    Returns
    -------
    accessor : FieldAccessor
        Callable ``accessor(msg, topic='') -> float``.

    Raises
    ------
    VehicleFileError
        The message type is not supported or has no such field; the message lists the
        fields it has.

    """
    if msg_type not in MESSAGE_FIELDS:
        raise VehicleFileError(
            f'unsupported message type {msg_type!r}; types are {list(MESSAGE_FIELDS)}')
    if not isinstance(field, str):
        raise VehicleFileError(f'field {field!r} is not a string')
    if msg_type == JOINT_STATE:
        array, _, joint = field.partition('.')
        if array in _JOINT_ARRAYS and joint:
            return FieldAccessor(msg_type, field, (array,), joint)
    elif field in MESSAGE_FIELDS[msg_type]:
        return FieldAccessor(msg_type, field, tuple(field.split('.')))
    raise VehicleFileError(
        f'{field!r} is not a field of {msg_type}; fields are {field_help(msg_type)}')


@functools.lru_cache(maxsize=256)
def _accessors(msg_type, fields):
    return tuple(parse_field(msg_type, field) for field in fields)


def extract_measurement(msg, sensor):
    """
    Read a sensor's outputs from one of its messages.

    Parameters
    ----------
    msg : message
        An rclpy or rosbags message (or any object with the same attributes) of the
        sensor's type.
    sensor : SensorSpec
        The sensor: its ``msg_type``, ``fields`` and ``topic``.

    Returns
    -------
    y : ndarray
        1-D float array, one finite value per field, in the order of ``sensor.outputs``.

    Raises
    ------
    MeasurementError
        A JointState lacks the joint, a value is not finite, or the message lacks a field;
        the message names the topic.

    """
    accessors = _accessors(sensor.msg_type, tuple(sensor.fields))
    return np.array([read(msg, sensor.topic) for read in accessors], dtype=float)


def fill_measurement(msg, sensor, values):
    """
    Write a sensor's output values into a message (for the simulator).

    Imu: the fields are set; for each of the angular_velocity and linear_acceleration
    blocks that the sensor uses, the covariance diagonal holds ``noise_std**2`` on the
    axes read and 0 on the others (the model has no motion there); an unused block and
    the orientation get element 0 = -1 ("not provided", REP 145). JointState: ``name``
    lists the joints in the order they first appear in the fields, and each array read
    by a field has one entry per joint (NaN where that joint has no such field); arrays
    not read are empty. Float64: ``data``. ``header.frame_id`` is set to the sensor's
    ``frame_id`` when the message has a header; the stamp is left to the caller.

    Parameters
    ----------
    msg : message
        A message instance of the sensor's type (rclpy, rosbags or a stand-in).
    sensor : SensorSpec
        The sensor: its fields, noise and frame.
    values : array_like
        One value per field of the sensor.

    Returns
    -------
    msg : message
        The same message object, filled.

    """
    accessors = _accessors(sensor.msg_type, tuple(sensor.fields))
    values = np.asarray(values, dtype=float).reshape(-1)
    if values.size != len(accessors):
        raise MeasurementError(
            f'{sensor.topic}: {values.size} values for the {len(accessors)} fields of '
            f'sensor {sensor.name}')
    header = getattr(msg, 'header', None)
    if header is not None and hasattr(header, 'frame_id'):
        header.frame_id = sensor.frame_id
    if sensor.msg_type == IMU:
        _fill_imu(msg, sensor, accessors, values)
    elif sensor.msg_type == JOINT_STATE:
        _fill_joint_state(msg, accessors, values)
    else:
        msg.data = float(values[0])
    return msg


def _fill_imu(msg, sensor, accessors, values):
    noise = np.broadcast_to(np.asarray(sensor.noise_std, dtype=float), values.shape)
    variances = {block: [0.0] * 9 for block in _IMU_BLOCKS + ('orientation',)}
    used = set()
    angles = [0.0, 0.0, 0.0]
    for accessor, value, std in zip(accessors, values, noise):
        block, axis = accessor.path
        if block == 'orientation':
            i = _EULER.index(axis)
            angles[i] = float(value)
        else:
            setattr(getattr(msg, block), axis, float(value))
            i = _AXES.index(axis)
        variances[block][4 * i] = float(std) ** 2
        used.add(block)
    if 'orientation' in used:
        q = msg.orientation
        q.x, q.y, q.z, q.w = euler_to_quaternion(*angles)
    for block in _IMU_BLOCKS + ('orientation',):
        if block not in used:
            variances[block][0] = -1.0
        _set_array(msg, f'{block}_covariance', variances[block], in_place=True)


def quaternion_to_euler(x, y, z, w):
    """
    Return (roll, pitch, yaw) in rad of a unit quaternion (ZYX convention).

    Parameters
    ----------
    x, y, z, w : float
        The quaternion (normalised here).

    Returns
    -------
    roll, pitch, yaw : float

    """
    norm = math.sqrt(x * x + y * y + z * z + w * w)
    if norm == 0.0:
        raise MeasurementError('orientation quaternion is zero')
    x, y, z, w = x / norm, y / norm, z / norm, w / norm
    roll = math.atan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2.0 * (w * y - z * x))))
    yaw = math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    return roll, pitch, yaw


def euler_to_quaternion(roll, pitch, yaw):
    """
    Return the quaternion (x, y, z, w) of ZYX Euler angles in rad.

    Parameters
    ----------
    roll, pitch, yaw : float
        Rotations about x, y and z in rad.

    Returns
    -------
    x, y, z, w : float

    """
    cr, sr = math.cos(roll / 2.0), math.sin(roll / 2.0)
    cp, sp = math.cos(pitch / 2.0), math.sin(pitch / 2.0)
    cy, sy = math.cos(yaw / 2.0), math.sin(yaw / 2.0)
    return (sr * cp * cy - cr * sp * sy, cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy, cr * cp * cy + sr * sp * sy)


def _fill_joint_state(msg, accessors, values):
    joints = []
    for accessor in accessors:
        if accessor.joint not in joints:
            joints.append(accessor.joint)
    arrays = {}
    for accessor, value in zip(accessors, values):
        array = arrays.setdefault(accessor.path[0], [math.nan] * len(joints))
        array[joints.index(accessor.joint)] = float(value)
    msg.name = list(joints)
    for name in _JOINT_ARRAYS:
        _set_array(msg, name, arrays.get(name, []))


def _set_array(msg, name, values, in_place=False):
    """Set a float array field, keeping the container type the message uses."""
    current = getattr(msg, name, None)
    if in_place and current is not None:
        try:
            if len(current) == len(values):
                current[:] = values
                return
        except TypeError:
            pass
    if isinstance(current, np.ndarray):   # rosbags messages need numpy arrays
        setattr(msg, name, np.array(values, dtype=np.float64))
    else:                                 # rclpy converts lists; stand-ins keep them
        setattr(msg, name, list(values))


def max_components(names):
    """
    Return the most components a vector message of ``names`` may carry (extra joints).

    A vector topic (state, estimate, command) is a JointState read by name; the node and
    the replay refuse a larger one by its counts alone.

    """
    return max(64, 4 * len(names))


def too_many_components(topic, count, names):
    """Return the error text of a vector message of ``count`` components, too many for names."""
    return _about(topic, f'{count} components, more than the {max_components(names)} accepted '
                         f'for {len(names)}')


def _few(items, limit=5):
    """Return at most ``limit`` items as text, with the count of the rest (bounded logs)."""
    items = list(items[:limit + 1])
    text = ', '.join(repr(x) for x in items[:limit])
    return f'[{text}, ...]' if len(items) > limit else f'[{text}]'


def vector_indices(got, n_values, names, topic=''):
    """
    Return where each of ``names`` stands in a vector message; None: in order.

    The one judgement of a vector topic's message (state, estimate, command), made on
    its names ``got`` (a list) and its number of positions ``n_values``, so the nodes
    (on the message object) and the replay (on the bytes' layout) decide alike. The
    sizes are checked first: a message of 10^6 components costs no lookup. A repeated
    name stands at its first position, as a sensor's joint does
    (:func:`extract_measurement`).

    Raises
    ------
    ObserverError
        Too many components, as many names as positions not given, a name missing; the
        text names the topic (when one is given) and lists at most a few names.

    """
    n_names = len(got)
    if max(n_names, n_values) > max_components(names):
        raise ObserverError(too_many_components(topic, max(n_names, n_values), names))
    if n_values != n_names:
        raise ObserverError(_about(topic, f'{n_names} names but {n_values} positions'))
    if (got == list(names)) if got else n_values == len(names):
        return None                     # the usual case, in order (or unnamed): no lookup
    index = {}
    for i, name in enumerate(got):
        index.setdefault(name, i)
    missing = [name for name in names if name not in index]
    if missing:
        raise ObserverError(_about(topic, f'missing component(s) {_few(missing)}; '
                                          f'got names {_few(got)}'))
    return [index[name] for name in names]


def _about(topic, text):
    return f'{topic}: {text}' if topic else text


def vector_from_joint_state(msg, names, topic):
    """
    Read the components ``names`` of a vector topic by name, in that order.

    Judged by :func:`vector_indices`; raises ObserverError naming the topic as it does,
    and for values that are not finite (the text lists at most a few).

    """
    order = vector_indices(msg.name, len(msg.position), names, topic)
    if order is None:
        values = np.array(msg.position, dtype=float)
    else:
        values = np.array([msg.position[i] for i in order], dtype=float)
    if not all(map(math.isfinite, values.tolist())):     # floats: a third of np.isfinite's
        raise ObserverError(f'{topic}: non-finite value in {_few(values.tolist())}')
    return values
