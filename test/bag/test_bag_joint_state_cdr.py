# test/bag/test_bag_joint_state_cdr.py: the one walk of a JointState's CDR bytes.
"""
The JointState walk against the real serializers, and the node and the replay judging alike.

Messages written by rclpy's ``serialize_message`` and by rosbags' serializer (empty and odd
names, 0 to 300 joints, arrays of different lengths, big-endian) and bytes crafted where
the serializers would not go (names without their NUL, with a NUL inside, of zero length,
not UTF-8; cut short anywhere) are walked by :mod:`observer_ros.bag.joint_state_cdr`; the
names are the ones rclpy deserializes, the offsets hold the values, and a message cut
short is refused naming the field. Then every case is read by the node's byte readers
(:mod:`observer_ros.nodes.wire`) and by the offline decoder with the replay's fallback
(:mod:`observer_ros.bag.reader`): both accept the same messages with the same values and
stamps, and refuse the same ones; so are Imu and Float64 messages (an empty frame_id,
big-endian, NaN, cut short).
"""

import re
import struct

from hypothesis import given, HealthCheck, settings, strategies as st
import numpy as np
from observer_ros.bag.cdr_decode import decode_messages, JOINT_STATE
from observer_ros.bag.joint_state_cdr import (CdrError, field_offsets, JOINT_ARRAYS,
                                              joint_state_counts, joint_state_layout)
from observer_ros.bag.reader import _sensor_fallback, _vector_fallback
from observer_ros.core.errors import ObserverError
from observer_ros.core.spec import SensorSpec
from observer_ros.nodes.wire import SensorReader, VectorReader, WireError
from observer_ros.sensors import extract_measurement, vector_from_joint_state, vector_indices
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.typesys import get_typestore, Stores
from sensor_msgs.msg import Imu, JointState
from std_msgs.msg import Float64

STORE = get_typestore(Stores.ROS2_JAZZY)
_ROSBAGS_JS = STORE.types[JOINT_STATE]


def _rclpy(names, position=(), velocity=(), effort=(), frame='base_link', stamp=(7, 11)):
    msg = JointState(name=list(names), position=list(position), velocity=list(velocity),
                     effort=list(effort))
    msg.header.stamp.sec, msg.header.stamp.nanosec = stamp
    msg.header.frame_id = frame
    return serialize_message(msg)


def _rosbags(names, position=(), velocity=(), effort=(), frame='odd', little_endian=True):
    header = STORE.types['std_msgs/msg/Header'](
        stamp=STORE.types['builtin_interfaces/msg/Time'](sec=7, nanosec=11), frame_id=frame)
    msg = _ROSBAGS_JS(header=header, name=list(names),
                      position=np.array(position, dtype=float),
                      velocity=np.array(velocity, dtype=float),
                      effort=np.array(effort, dtype=float))
    return bytes(STORE.serialize_cdr(msg, JOINT_STATE, little_endian=little_endian))


def _crafted(name_bytes, position, frame=b'f\x00'):
    """Little-endian JointState bytes with each name's bytes as given (any bytes)."""
    out = bytearray(b'\x00\x01\x00\x00' + struct.pack('<iI', 7, 11))

    def word(value):
        out.extend(bytes(-(len(out) - 4) % 4) + struct.pack('<I', value))
    word(len(frame))
    out.extend(frame)
    word(len(name_bytes))
    for b in name_bytes:
        word(len(b))
        out.extend(b)
    word(len(position))
    if position:
        out.extend(bytes(-(len(out) - 4) % 8) + struct.pack(f'<{len(position)}d', *position))
    word(0)
    word(0)
    return bytes(out)


MANY = [f'joint_{i}' for i in range(300)]
# name: (bytes, the names a node of the cases below expects)
CASES = {
    'no joints': _rclpy([]),
    'no joints, rosbags': _rosbags([]),
    'an empty name': _rclpy(['', 'b'], [1.0, 2.0]),
    'odd-length names': _rclpy(['abc', 'de', 'f'], [1.0, 2.0, 3.0], [0.5]),
    'names of different lengths': _rosbags(['a', 'longer_name', 'mid'], [1.0, 2.0, 3.0],
                                           [4.0, 5.0, 6.0], [7.0]),
    'positions without names': _rclpy([], [1.0, 2.0]),
    'more positions than names': _rclpy(['a', 'b'], [1.0, 2.0, 3.0]),
    'fewer positions than names': _rosbags(['a', 'b', 'c'], [1.0, 2.0]),
    'velocity and effort only': _rclpy(['a', 'b'], [], [1.0, 2.0], [3.0]),
    'effort longer than position': _rclpy(['a', 'b'], [1.0], [], [3.0, 4.0, 5.0]),
    'NaN value': _rclpy(['a', 'b'], [float('nan'), 2.0]),
    'a repeated name': _rclpy(['a', 'b', 'a'], [1.0, 2.0, 3.0], [4.0, 5.0, 6.0]),
    'many joints': _rclpy(MANY, [float(i) for i in range(300)], [0.0] * 300),
    'many joints, rosbags': _rosbags(MANY, [float(i) for i in range(300)]),
    'big-endian': _rosbags(['a', 'b'], [1.0, 2.0], [3.0, 4.0], little_endian=False),
    'big-endian, no joints': _rosbags([], little_endian=False),
    'a name without its NUL': _crafted([b'ab', b'b\x00'], [1.0, 2.0]),
    'a NUL inside a name': _crafted([b'a\x00zz\x00', b'b\x00'], [1.0, 2.0]),
    'a zero-length name': _crafted([b'', b'b\x00'], [1.0, 2.0]),
    'a name not UTF-8': _crafted([b'\xff\xfe\x00', b'b\x00'], [1.0, 2.0]),
    'an empty frame': _crafted([b'a\x00', b'b\x00'], [1.0, 2.0], frame=b''),
}


def _truncations():
    """Every cut of a few messages short of their end."""
    for key in ('odd-length names', 'names of different lengths', 'no joints'):
        raw = CASES[key]
        for cut in range(len(raw)):
            yield f'{key} cut at {cut}', raw[:cut]


ALL_CASES = dict(CASES, **dict(_truncations()))


def _values_at(raw, offset, count):
    return list(struct.unpack_from(f'<{count}d', raw, offset)) if count else []


def _same(a, b):
    if a is None or b is None:
        return a is None and b is None
    return [struct.pack('<d', x) for x in a] == [struct.pack('<d', x) for x in b]


@pytest.mark.parametrize('key', [k for k in CASES if not k.startswith('big-endian')])
def test_the_layout_is_what_rclpy_deserializes(key):
    raw = CASES[key]
    msg = deserialize_message(raw, JointState)
    layout = joint_state_layout(raw)
    assert list(layout.names) == list(msg.name)
    for array in JOINT_ARRAYS:
        offset, count = layout.arrays[array]
        assert _same(_values_at(raw, offset, count), list(getattr(msg, array)))
    assert joint_state_counts(raw) == (len(msg.name),) + tuple(
        len(getattr(msg, a)) for a in JOINT_ARRAYS)
    assert layout.size == len(raw)
    # the structure and the values together cover every byte after the stamp but the
    # frame and the padding; no value byte is structure
    values = set()
    for offset, count in layout.arrays.values():
        values.update(range(offset, offset + 8 * count))
    assert not values & {b for s, e in layout.structure for b in range(s, e)}
    assert not values & {b for s, e in layout.outside_values() for b in range(s, e)}
    assert len(values) + sum(e - s for s, e in layout.outside_values()) == len(raw) - 12


@pytest.mark.parametrize('key', ['big-endian', 'big-endian, no joints'])
def test_big_endian_is_left_to_the_deserializers(key):
    with pytest.raises(CdrError, match='JointState: not little-endian plain CDR'):
        joint_state_layout(CASES[key])
    with pytest.raises(CdrError, match='not little-endian'):
        joint_state_counts(CASES[key])


def test_a_cut_message_is_refused_naming_the_field():
    raw = _rclpy(['abc', 'de'], [1.0, 2.0], [3.0], [])
    layout = joint_state_layout(raw)
    position, _ = layout.arrays['position']
    name1 = layout.structure[3][0]          # stamp's frame length, count, name[0], name[1]
    effort = layout.structure[-1][0]        # the last count: what rclpy writes after it is
    assert effort + 4 < len(raw)            # padding, which no reader needs
    expected = {
        10: r'JointState: not little-endian plain CDR \(10 bytes',
        name1 + 5: r'JointState\.name\[1\]: 3 bytes at byte %d' % (name1 + 4),
        position + 12: r'JointState\.position: 2 values at byte %d' % position,
        effort + 2: r'JointState\.effort: its count at byte %d' % effort,
    }
    for cut, text in expected.items():
        with pytest.raises(CdrError, match=text):
            joint_state_layout(raw[:cut])
        with pytest.raises(CdrError, match=text):
            joint_state_counts(raw[:cut])
    # the replay says the same where rosbags cannot read the message either
    sensor = _sensor(('position.abc',))
    dec = decode_messages([raw[:name1 + 5]], JOINT_STATE, sensor.fields,
                          fallback=_sensor_fallback(_Bag, sensor))
    assert not dec.valid[0]
    assert re.match(expected[name1 + 5], dec.first_error), dec.first_error
    for cut in range(effort + 4):
        with pytest.raises(CdrError, match=r'^JointState(\.\w+(\[\d+\])?)?: .*\b%d-byte '
                           r'message|^JointState: not little' % cut):
            joint_state_layout(raw[:cut])


def test_counts_no_name_is_decoded_for():
    """A count of names that cannot fit is refused before any walk over them."""
    raw = bytearray(_rclpy(['a'], [1.0]))
    count_at = joint_state_layout(bytes(raw)).structure[1][0]
    raw[count_at:count_at + 4] = struct.pack('<I', 2**32 - 1)
    with pytest.raises(CdrError, match=r'JointState\.name: 4294967295 names cannot fit'):
        joint_state_counts(bytes(raw))
    with pytest.raises(CdrError, match='more than the 2 read here'):
        joint_state_layout(_rclpy(['a', 'b', 'c']), max_names=2)


def test_field_offsets_name_the_first_missing_field():
    raw = _rclpy(['a', 'b', 'a'], [1.0, 2.0, 3.0], [4.0])
    layout = joint_state_layout(raw)
    offsets, error = field_offsets(layout.names, layout.arrays,
                                   ['position.a', 'velocity.b', 'position.c', 'effort.a'])
    assert offsets[0] == layout.arrays['position'][0]      # the first joint of the name
    assert offsets[1:] == [None, None, None]
    assert error == "joint 'b': JointState.velocity has 1 values for 3 names"
    _, error = field_offsets(layout.names, layout.arrays, ['position.c'])
    assert error == "joint 'c' is not in JointState.name ['a', 'b', 'a']"
    offsets, error = field_offsets(layout.names, layout.arrays, ['velocity.a', 'position.b'])
    assert error == '' and _values_at(raw, offsets[0], 1) == [4.0]
    assert _values_at(raw, offsets[1], 1) == [2.0]


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(names=st.lists(st.binary(max_size=6), max_size=4), data=st.data())
def test_any_name_bytes_are_read_as_rclpy_reads_them(names, data):
    position = data.draw(st.lists(st.floats(allow_nan=False), min_size=len(names),
                                  max_size=len(names)))
    raw = _crafted(names, position)
    msg = deserialize_message(raw, JointState)
    layout = joint_state_layout(raw)
    assert list(layout.names) == list(msg.name)
    assert _same(_values_at(raw, *layout.arrays['position']), list(msg.position))


# ------------------------------------------------------- the node and the replay agree

class _Bag:
    """What the replay's fallback takes from a bag: rosbags' deserializer."""

    @staticmethod
    def deserialize(raw, msgtype):
        return STORE.deserialize_cdr(raw, msgtype)


def _sensor(fields):
    return SensorSpec(name='enc', topic='enc', msg_type=JOINT_STATE, fields=tuple(fields),
                      outputs=tuple(f'y{i}' for i in range(len(fields))),
                      noise_std=np.ones(len(fields)))


SENSOR_FIELDS = [('position.a',), ('position.b', 'velocity.a'), ('effort.a',),
                 ('position.joint_299', 'velocity.joint_0'), ('position.missing',)]
VECTORS = [('a', 'b'), ('b',), (), ('u0', 'u1'), tuple(MANY[:2]), tuple(MANY)]


def _node(reader, raw):
    """Return (stamp, values) the node takes from raw, or None where it refuses it."""
    try:
        header, values, _ = reader.read(raw)
    except WireError:
        return None
    return None if values is None else (header[0] * 10**9 + header[1], values)


def _replay(raw, fields, mode, fallback):
    """Return (stamp, values) the replay takes from raw, or None where it refuses it."""
    for max_layouts in (64, 0):         # the bulk decoder, and the fallback alone
        dec = decode_messages([raw], JOINT_STATE, fields, mode=mode, fallback=fallback,
                              max_layouts=max_layouts)
        got = (int(dec.stamp_ns[0]), dec.values[0].tolist()) if dec.valid[0] else None
        if max_layouts:
            bulk = got
        else:
            assert (got is None) == (bulk is None) and (got is None or (
                got[0] == bulk[0] and _same(got[1], bulk[1])))
    return bulk


@pytest.mark.parametrize('key', list(ALL_CASES))
def test_the_node_and_the_replay_judge_each_message_alike(key):
    raw = ALL_CASES[key]
    for fields in SENSOR_FIELDS:
        sensor = _sensor(fields)
        node = _node(SensorReader(sensor, JointState), raw)
        offline = _replay(raw, fields, 'sensor', _sensor_fallback(_Bag, sensor))
        assert (node is None) == (offline is None), (fields, node, offline)
        if node is not None:
            assert node[0] == offline[0] and _same(node[1], offline[1]), (fields, node, offline)
    for names in VECTORS:
        node = _node(VectorReader(names, 'control/u'), raw)
        offline = _replay(raw, [f'position.{n}' for n in names], 'vector',
                          _vector_fallback(_Bag, names, 'vector', 'control/u'))
        assert (node is None) == (offline is None), (names[:3], node, offline)
        if node is not None:
            assert node[0] == offline[0] and _same(node[1], offline[1]), (names[:3], node)


def test_the_cases_cover_acceptance_and_refusal():
    """The agreement above is not vacuous: each side accepts some cases and refuses others."""
    verdicts = set()
    for raw in CASES.values():
        for fields in SENSOR_FIELDS:
            verdicts.add(_node(SensorReader(_sensor(fields), JointState), raw) is None)
    assert verdicts == {True, False}
    accepted = [k for k, raw in CASES.items()
                if _node(VectorReader(('a', 'b'), 'u'), raw) is not None]
    assert 'big-endian' in accepted and 'a name not UTF-8' not in accepted
    assert re.search('empty frame', ' '.join(accepted))


# ------------------------------------------- the other sensor types: Imu and Float64

def _imu(frame='imu_link', value=0.25):
    msg = Imu()
    msg.header.stamp.sec, msg.header.stamp.nanosec = 7, 11
    msg.header.frame_id = frame
    msg.orientation.w = 1.0
    msg.angular_velocity.y = value
    msg.linear_acceleration.z = 9.81
    return serialize_message(msg)


def _empty_frame(raw):
    """Return the same message with a frame_id of length 0 (rclpy writes one NUL)."""
    assert raw[12:17] == b'\x01\x00\x00\x00\x00'
    return raw[:12] + bytes(4) + raw[16:]


def _rosbags_imu(little_endian):
    msg = STORE.deserialize_cdr(_imu(), 'sensor_msgs/msg/Imu')
    return bytes(STORE.serialize_cdr(msg, 'sensor_msgs/msg/Imu', little_endian=little_endian))


IMU_CASES = {
    'plain': _imu(), 'an odd frame': _imu('abc'), 'NaN': _imu(value=float('nan')),
    'an empty frame': _empty_frame(_imu('')), 'rosbags': _rosbags_imu(True),
    'big-endian': _rosbags_imu(False),
}
IMU_CASES.update({f'cut at {cut}': _imu()[:cut] for cut in (0, 3, 15, 20, 200, 300)})
FLOAT64_CASES = {
    'plain': serialize_message(Float64(data=1.5)),
    'NaN': serialize_message(Float64(data=float('nan'))),
    'big-endian': bytes(STORE.serialize_cdr(STORE.types['std_msgs/msg/Float64'](data=2.5),
                                            'std_msgs/msg/Float64', little_endian=False)),
    'cut at 10': serialize_message(Float64(data=1.5))[:10],
}


@pytest.mark.parametrize('msgtype, msg_class, key, fields', [
    ('sensor_msgs/msg/Imu', Imu, k, f) for k in IMU_CASES
    for f in [('angular_velocity.y',), ('linear_acceleration.z', 'orientation.pitch')]] + [
    ('std_msgs/msg/Float64', Float64, k, ('data',)) for k in FLOAT64_CASES])
def test_the_node_and_the_replay_judge_other_sensors_alike(msgtype, msg_class, key, fields):
    raw = (IMU_CASES if msg_class is Imu else FLOAT64_CASES)[key]
    sensor = SensorSpec(name='s', topic='s', msg_type=msgtype, fields=fields,
                        outputs=tuple(f'y{i}' for i in range(len(fields))),
                        noise_std=np.ones(len(fields)))
    try:
        header, node, _ = SensorReader(sensor, msg_class).read(raw)
    except WireError:
        node = None
    dec = decode_messages([raw], msgtype, fields, fallback=_sensor_fallback(_Bag, sensor))
    assert (node is not None) == bool(dec.valid[0]), (node, dec.first_error)
    if node is not None:
        assert _same(node, dec.values[0].tolist())
        if msg_class is Imu:
            assert header[0] * 10**9 + header[1] == dec.stamp_ns[0]
    if key.startswith('cut'):
        assert node is None
    elif key in ('plain', 'an empty frame', 'big-endian'):
        assert node is not None


def test_a_vector_with_a_repeated_name_gives_its_first_position():
    """As a sensor's joint: the node's readers and the replay read the same component."""
    msg = JointState(name=['a', 'b', 'a'], position=[1.0, 2.0, 3.0])
    assert vector_from_joint_state(msg, ['b', 'a'], 'state/true').tolist() == [2.0, 1.0]
    assert extract_measurement(msg, _sensor(['position.a'])).tolist() == [1.0]
    raw = serialize_message(msg)
    assert VectorReader(['b', 'a'], 'state/true').read(raw)[1] == [2.0, 1.0]
    assert _replay(raw, ['position.b', 'position.a'], 'vector',
                   _vector_fallback(_Bag, ['b', 'a'], 'vector', 'state/true'))[1] == [2.0, 1.0]


def test_vector_indices_one_judgement_with_or_without_a_topic():
    assert vector_indices(['a', 'b'], 2, ['a', 'b']) is None
    assert vector_indices([], 0, []) is None
    assert vector_indices(['b', 'a', 'b'], 3, ['b', 'a']) == [0, 1]
    for args, text in [((['a'], 2, ['a']), '1 names but 2 positions'),
                       (([], 2, ['a', 'b']), '0 names but 2 positions'),
                       ((['a', 'c'], 2, ['a', 'b']),
                        r"missing component\(s\) \['b'\]; got names \['a', 'c'\]"),
                       ((['x'] * 65, 65, ['a']), '65 components, more than the 64 accepted')]:
        with pytest.raises(ObserverError, match='^' + text):
            vector_indices(*args)
        with pytest.raises(ObserverError, match='^control/u: ' + text):
            vector_indices(*args, topic='control/u')
