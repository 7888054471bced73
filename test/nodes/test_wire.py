# test/test_nodes_wire.py: the nodes' messages read from and written as CDR bytes.
"""
The byte readers give what the message objects gave, value for value and error for error.

Messages serialized by rclpy (random names, frames, values with NaN and infinity, joints
missing) are read by :class:`SensorReader` and :class:`VectorReader` and compared with
``extract_measurement`` and ``vector_from_joint_state`` on the objects rclpy deserializes;
corrupted bytes (flipped, cut, lengthened, big-endian) are either refused with
:class:`WireError`, exactly when rclpy cannot deserialize them, or read as rclpy reads
them. :class:`JointStateWriter` writes what rclpy deserializes into the same JointState.
"""

import math
import struct

from hypothesis import given, HealthCheck, settings, strategies as st
import numpy as np
from observer_ros.core.errors import ObserverError
from observer_ros.core.spec import SensorSpec
from observer_ros.nodes.common import vector_from_joint_state
from observer_ros.nodes.wire import (JointStateWriter, SensorReader, stamp_bytes, stamp_of,
                                     VectorReader, WireError)
from observer_ros.sensors import euler_to_quaternion, extract_measurement
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import Imu, JointState
from std_msgs.msg import Float64

SETTINGS = settings(max_examples=300, deadline=None,
                    suppress_health_check=[HealthCheck.too_slow])

names_st = st.lists(st.text(min_size=1, max_size=6).filter(lambda s: '\x00' not in s),
                    max_size=5, unique=True)
values_st = st.floats(allow_nan=True, allow_infinity=True)
finite_st = st.floats(allow_nan=False, allow_infinity=False)
frame_st = st.text(max_size=12).filter(lambda s: '\x00' not in s)
stamp_st = st.tuples(st.integers(-5, 2**31 - 1), st.integers(0, 2**32 - 1))


def _sensor(msg_type, fields, topic='s/topic'):
    return SensorSpec(name='s', topic=topic, msg_type=msg_type, fields=tuple(fields),
                      outputs=tuple(f'y{i}' for i in range(len(fields))),
                      noise_std=np.ones(len(fields)))


def _joint_state(stamp, frame, names, position, velocity=(), effort=()):
    msg = JointState(name=list(names), position=list(position), velocity=list(velocity),
                     effort=list(effort))
    msg.header.stamp.sec, msg.header.stamp.nanosec = stamp
    msg.header.frame_id = frame
    return msg


def _object_result(call):
    """Return (values, error text) of a message-object function."""
    try:
        return call().tolist(), None
    except (ObserverError, ValueError) as err:
        return None, str(err)


def _same(a, b):
    """Value lists equal bit for bit (NaN equal to NaN)."""
    if a is None or b is None:
        return a is b
    return len(a) == len(b) and all(struct.pack('<d', x) == struct.pack('<d', y)
                                    for x, y in zip(a, b))


def _deserialized(reader, raw, msg_class):
    """Return rclpy's message of raw; None when rclpy refuses it (and so does the reader)."""
    try:
        return deserialize_message(raw, msg_class)
    except Exception:   # noqa: BLE001 - rclpy refuses these bytes: so must the reader
        with pytest.raises(WireError):
            reader.read(raw)
        return None


def _check_sensor(reader, raw, sensor, msg_class):
    """Check that the reader gives what deserialize + extract_measurement give, or WireError."""
    msg = _deserialized(reader, raw, msg_class)
    if msg is None:
        return None
    header, y, problem = reader.read(raw)
    want, error = _object_result(lambda: extract_measurement(msg, sensor))
    assert problem == error
    assert _same(y, want), (y, want)
    if reader.stamped:
        stamp = msg.header.stamp
        assert header[:2] == (stamp.sec, stamp.nanosec)
        assert stamp_of(header[2]) == (stamp.sec, stamp.nanosec)
    else:
        assert header is None
    # a message object (a caller in process) is read as the object it is: the same
    header_o, y_o, problem_o = reader.read(msg)
    assert (header_o, problem_o) == (header, problem) and _same(y_o, y)
    return y


def _check_vector(reader, raw, names):
    """Check that the reader gives what deserialize + vector_from_joint_state give."""
    msg = _deserialized(reader, raw, JointState)
    if msg is None:
        return None
    header, values, problem = reader.read(raw)
    want, error = _object_result(lambda: vector_from_joint_state(msg, names, reader.topic))
    assert problem == error
    assert _same(values, want), (values, want)
    assert header[:2] == (msg.header.stamp.sec, msg.header.stamp.nanosec)
    assert reader.read(msg)[1:] == (values, problem) or _same(reader.read(msg)[1], values)
    return values


@SETTINGS
@given(stamp=stamp_st, frame=frame_st, names=names_st, data=st.data())
def test_vector_reader_as_vector_from_joint_state(stamp, frame, names, data):
    # the names a node expects: the message's own, another order, fewer, or none
    expected = data.draw(st.sampled_from([names, names[::-1], names[:1], ['a', 'b']]))
    position = data.draw(st.lists(values_st, min_size=max(0, len(names) - 1),
                                  max_size=len(names) + 1))
    if data.draw(st.booleans()):       # an unnamed vector
        names = []
    msg = _joint_state(stamp, frame, names, position,
                       data.draw(st.lists(finite_st, max_size=3)),
                       data.draw(st.lists(finite_st, max_size=3)))
    reader = VectorReader(expected, 'state/estimate')
    for _ in range(2):                  # the second time from the reader's known layouts
        _check_vector(reader, serialize_message(msg), expected)


@SETTINGS
@given(stamp=stamp_st, frame=frame_st, names=names_st, data=st.data())
def test_joint_state_sensor_as_extract_measurement(stamp, frame, names, data):
    joints = names + ['missing']
    fields = data.draw(st.lists(st.tuples(st.sampled_from(['position', 'velocity', 'effort']),
                                          st.sampled_from(joints)), min_size=1, max_size=3))
    sensor = _sensor('sensor_msgs/msg/JointState', [f'{a}.{j}' for a, j in fields])
    n = len(names)
    msg = _joint_state(stamp, frame, names, *(data.draw(st.lists(
        values_st, min_size=max(0, n - 1), max_size=n + 1)) for _ in range(3)))
    reader = SensorReader(sensor, JointState)
    for _ in range(2):
        _check_sensor(reader, serialize_message(msg), sensor, JointState)


IMU_FIELDS = ('angular_velocity.x', 'angular_velocity.y', 'angular_velocity.z',
              'linear_acceleration.x', 'linear_acceleration.y', 'linear_acceleration.z',
              'orientation.roll', 'orientation.pitch', 'orientation.yaw')


@SETTINGS
@given(stamp=stamp_st, frame=frame_st, values=st.lists(values_st, min_size=10, max_size=10),
       fields=st.lists(st.sampled_from(IMU_FIELDS), min_size=1, max_size=4),
       euler=st.tuples(finite_st, finite_st, finite_st) | st.none())
def test_imu_sensor_as_extract_measurement(stamp, frame, values, fields, euler):
    msg = Imu()
    msg.header.stamp.sec, msg.header.stamp.nanosec = stamp
    msg.header.frame_id = frame
    msg.angular_velocity.x, msg.angular_velocity.y, msg.angular_velocity.z = values[:3]
    (msg.linear_acceleration.x, msg.linear_acceleration.y,
     msg.linear_acceleration.z) = values[3:6]
    q = msg.orientation
    if euler is not None and all(abs(a) < 10 for a in euler):
        q.x, q.y, q.z, q.w = euler_to_quaternion(*euler)
    else:
        q.x, q.y, q.z, q.w = values[6:10]
    sensor = _sensor('sensor_msgs/msg/Imu', fields)
    _check_sensor(SensorReader(sensor, Imu), serialize_message(msg), sensor, Imu)


@SETTINGS
@given(value=values_st)
def test_float64_sensor_as_extract_measurement(value):
    sensor = _sensor('std_msgs/msg/Float64', ['data'])
    y = _check_sensor(SensorReader(sensor, Float64), serialize_message(Float64(data=value)),
                      sensor, Float64)
    assert (y is None) == (not math.isfinite(value))


def _mutations(raw, data):
    """Bytes near a valid message: flipped, cut, lengthened, re-encapsulated."""
    raw = bytearray(raw)
    kind = data.draw(st.sampled_from(['flip', 'cut', 'extend', 'big_endian', 'word']))
    if kind == 'flip':
        for _ in range(data.draw(st.integers(1, 4))):
            raw[data.draw(st.integers(0, len(raw) - 1))] ^= 1 << data.draw(st.integers(0, 7))
    elif kind == 'cut':
        del raw[data.draw(st.integers(0, len(raw))):]
    elif kind == 'extend':
        raw += bytes(data.draw(st.integers(1, 16)))
    elif kind == 'big_endian':
        raw[1] = 0
    else:                               # a length or count overwritten
        i = data.draw(st.integers(0, max(0, len(raw) - 4))) // 4 * 4
        raw[i:i + 4] = struct.pack('<I', data.draw(st.sampled_from([0, 1, 7, 2**31, 2**32 - 1])))
    return bytes(raw)


@SETTINGS
@given(names=names_st.filter(bool), data=st.data())
def test_corrupted_joint_states_refused_or_read_as_rclpy_reads_them(names, data):
    msg = _joint_state((5, 7), 'base_link', names, [0.5] * len(names), [1.0])
    raw = _mutations(serialize_message(msg), data)
    _check_vector(VectorReader(names, 'control/u'), raw, names)
    sensor = _sensor('sensor_msgs/msg/JointState', [f'position.{names[0]}'])
    _check_sensor(SensorReader(sensor, JointState), raw, sensor, JointState)


@SETTINGS
@given(data=st.data())
def test_corrupted_imus_refused_or_read_as_rclpy_reads_them(data):
    msg = Imu()
    msg.header.stamp.sec = 5
    msg.header.frame_id = 'base_link_frd'
    msg.orientation.w = 1.0
    msg.angular_velocity.y = 0.25
    raw = _mutations(serialize_message(msg), data)
    sensor = _sensor('sensor_msgs/msg/Imu', ['angular_velocity.y', 'orientation.pitch'])
    _check_sensor(SensorReader(sensor, Imu), raw, sensor, Imu)


def test_garbage_is_a_wire_error_naming_the_topic():
    reader = VectorReader(['u'], 'control/u')
    for raw in (b'', b'\x00', b'\x00\x01\x00\x00', b'\xff' * 40):
        with pytest.raises(WireError, match='control/u: not a JointState message'):
            reader.read(raw)


@pytest.mark.parametrize('names, positions', [(10**5, 10**5), (3, 10**5), (10**5, 1)])
def test_too_many_components_refused_from_the_bytes(monkeypatch, names, positions):
    """Refused with vector_from_joint_state's text, without a message object (its memory)."""
    msg = JointState(name=[f'j{i}' for i in range(names)], position=[0.0] * positions)
    msg.header.stamp.sec, msg.header.stamp.nanosec = 12, 345
    raw = serialize_message(msg)
    with pytest.raises(ObserverError) as want:
        vector_from_joint_state(msg, ['u'], 'control/u')

    def no_objects(*args):
        raise AssertionError('deserialized')
    monkeypatch.setattr('observer_ros.nodes.wire.deserialize_message', no_objects)
    reader = VectorReader(['u'], 'control/u')
    header, values, problem = reader.read(raw)
    assert (header[:2], values, problem) == ((12, 345), None, str(want.value))


@SETTINGS
@given(stamp=stamp_st.filter(lambda s: s[0] >= 0), frame=frame_st, data=st.data())
def test_writer_gives_the_joint_state_rclpy_reads(stamp, frame, data):
    names = data.draw(names_st)
    values = data.draw(st.lists(finite_st, min_size=len(names), max_size=len(names)))
    writer = JointStateWriter(names)
    tag = struct.pack('<iI', *stamp)
    msg = deserialize_message(writer.write(tag, frame, values), JointState)
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == stamp
    assert msg.header.frame_id == frame
    assert list(msg.name) == names
    assert list(msg.position) == values
    assert list(msg.velocity) == [] and list(msg.effort) == []
    # and the reader takes it on its fast path, to the same values
    header, got, problem = VectorReader(names, 't').read(writer.write(tag, frame, values))
    assert problem is None and got == values and header[2] == tag


def test_stamp_bytes_round_to_the_nanosecond():
    assert stamp_of(stamp_bytes(12.000000001)) == (12, 1)
    assert stamp_of(stamp_bytes(1.9999999996)) == (2, 0)
