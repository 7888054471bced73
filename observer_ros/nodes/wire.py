# observer_ros.nodes.wire: the hot path's messages read from and written as CDR bytes.
"""
The observer's and the compensator's messages as their serialized (CDR) bytes.

rclpy turns every message it takes into Python objects (an Imu is six nested objects and
three numpy arrays) and every message published back into C structures. The observer and
the compensator skip both: they subscribe with ``raw=True`` and publish bytes (P1 in
benchmarks/README.md measures the node against a bare relay). The readers here take the
fields a node uses at fixed offsets of the little-endian CDR layout (the layouts
:mod:`observer_ros.bag.cdr_decode` reads in bulk; a JointState's found by the walk of
:mod:`observer_ros.bag.joint_state_cdr` both sides use), and
:class:`JointStateWriter` writes a JointState from a template made once per frame.

One rule keeps each message judged as its message object was: the fast path answers only
for a well-formed little-endian message whose values are all finite and whose joints are
where it expects them (a joint name is read as rclpy reads it). Anything else (a
big-endian publisher, a missing joint, a NaN) goes through rclpy's own
``deserialize_message`` and the message-object functions
(:func:`observer_ros.sensors.extract_measurement`,
:func:`observer_ros.sensors.vector_from_joint_state`), which give the same value or
the same error text as before. Bytes rclpy cannot deserialize raise :class:`WireError`,
which the nodes count as a bad message. A reader also takes a message object (tests and
in-process drivers call the callbacks with one), and reads it as the object it is.

"""

import math
import struct

from rclpy.serialization import deserialize_message

from ..bag.cdr_decode import IMU_OFFSETS, IMU_TAIL
from ..bag.joint_state_cdr import (CdrError, field_offsets, joint_state_counts, joint_state_layout,
                                   LITTLE_ENDIAN)
from ..core.errors import ObserverError
from ..sensors import (extract_measurement, IMU, JOINT_STATE, max_components,
                       too_many_components, vector_from_joint_state)
from ..timeutil import sec_to_stamp_parts

__all__ = ['WireError', 'SensorReader', 'VectorReader', 'JointStateWriter', 'stamp_bytes',
           'stamp_of', 'header_stamp']

_LE = LITTLE_ENDIAN
_U32 = struct.Struct('<I')
_STAMP = struct.Struct('<iI')
_F64 = struct.Struct('<d')
# names a JointState's layout is kept for at most: a larger message is read as an object
# (or refused from its counts), not remembered
_LAYOUT_NAMES = 256
_isfinite = math.isfinite


class WireError(ObserverError, ValueError):
    """Bytes that are not a message of the expected type (rclpy cannot deserialize them)."""


def stamp_bytes(t):
    """Return the 8 CDR bytes of the stamp of t seconds (rounded to the nanosecond)."""
    return _STAMP.pack(*sec_to_stamp_parts(t))


def stamp_of(tag):
    """Return ``(sec, nanosec)`` of stamp bytes (:func:`stamp_bytes`, a reader's tag)."""
    return _STAMP.unpack(tag)


def header_stamp(raw):
    """
    Return ``(sec, nanosec, tag)`` of the header stamp of a stamped message's bytes.

    The stamp is the first field, after CDR's 4-byte encapsulation header; ``tag`` is its
    8 bytes. ``struct.error`` for fewer than 12 bytes.
    """
    return _STAMP.unpack_from(raw, 4) + (raw[4:12],)


def _bytes_or_none(msg):
    """Return a message's bytes, or None for a message object."""
    if msg.__class__ is bytes:
        return msg
    if isinstance(msg, (bytearray, memoryview)):
        return bytes(msg)
    return None


def _deserialize(raw, msg_class, topic):
    """Return the message object of raw, as rclpy would have given it; WireError if none."""
    try:
        return deserialize_message(raw, msg_class)
    except Exception as err:    # noqa: BLE001 - rclpy's RMWError and friends: bad bytes
        text = str(err).split(', at ')[0]
        raise WireError(f'{topic}: not a {msg_class.__name__} message '
                        f'({len(raw)} bytes): {text}') from None


def _header_of(msg):
    """Return ``(sec, nanosec, tag)`` of a message object's header.stamp."""
    stamp = msg.header.stamp
    sec, nanosec = int(stamp.sec), int(stamp.nanosec)
    return sec, nanosec, _STAMP.pack(sec, nanosec)


class _Layout:
    """Where a JointState's arrays are, and the bytes that say so (its structure)."""

    __slots__ = ('size', 'regions', 'names', 'arrays')

    def __init__(self, size, regions, names, arrays):
        self.size = size            # the message's length in bytes
        self.regions = regions      # ((start, end, bytes), ...): every length and name
        self.names = names          # tuple of str
        self.arrays = arrays        # {'position': (offset, count), ...}

    def fits(self, raw):
        """Tell whether raw has this layout (the same length, names and counts)."""
        if len(raw) != self.size:
            return False
        for start, end, ref in self.regions:
            if raw[start:end] != ref:
                return False
        return True


def _joint_state_layout(raw):
    """Return the layout of a little-endian JointState (:mod:`..bag.joint_state_cdr`), or None."""
    try:
        layout = joint_state_layout(raw, _LAYOUT_NAMES)
    except CdrError:
        return None                     # rclpy is left to read it or to say why not
    spans = tuple((a, b, raw[a:b]) for a, b in layout.outside_values())
    return _Layout(layout.size, spans, layout.names, layout.arrays)


class _JointStateLayouts:
    """The layouts of the JointStates a reader has seen (a few: one per publisher)."""

    __slots__ = ('_last', '_known')

    def __init__(self):
        self._last = None
        self._known = []

    def find(self, raw):
        """Return the layout of raw (None: not well formed, or not plain)."""
        last = self._last
        if last is not None and last.fits(raw):
            return last
        for layout in self._known:
            if layout.fits(raw):
                self._last = layout
                return layout
        layout = _joint_state_layout(raw)
        if layout is not None:
            if len(self._known) >= 8:     # a publisher changing its names all the time
                self._known.pop(0)
            self._known.append(layout)
            self._last = layout
        return layout


def _values_struct(offsets):
    """Return (Struct, start, order): one unpack_from for values at offsets (8 bytes each)."""
    unique = sorted(set(offsets))       # a field may be read twice
    start = unique[0]
    fmt, pos = '<', start
    for offset in unique:
        fmt += f'{offset - pos}xd' if offset > pos else 'd'
        pos = offset + 8
    order = tuple(unique.index(offset) for offset in offsets)
    return struct.Struct(fmt), start, (None if order == tuple(range(len(unique))) else order)


def _unpack(plan, raw, base=0):
    """Return the values a plan of :func:`_values_struct` reads, in the fields' order."""
    st, start, order = plan
    values = st.unpack_from(raw, base + start)
    return list(values) if order is None else [values[i] for i in order]


class SensorReader:
    """
    Read a sensor's stamp and outputs from its message bytes.

    ``read(raw)`` returns ``(header, y, problem)``: ``header`` is ``(sec, nanosec, tag)``
    (``tag``: the stamp's 8 bytes, what an answer carries) or None for a type without
    one; ``y`` the outputs (a list of floats) or None with ``problem`` the text
    :func:`~observer_ros.sensors.extract_measurement` raises for that message. Raises
    :class:`WireError` for bytes that are not a message of the type.

    Parameters
    ----------
    sensor : SensorSpec
        The sensor (``msg_type``, ``fields``, ``topic``).
    msg_class : type
        Its rclpy message class.

    """

    def __init__(self, sensor, msg_class):
        self.sensor = sensor
        self.msg_class = msg_class
        self.stamped = hasattr(msg_class, 'header')
        self._imu = None
        self._layouts = None
        self._plans = {}
        fields = tuple(sensor.fields)
        if sensor.msg_type == IMU and all(f in IMU_OFFSETS for f in fields):
            self._imu = _values_struct([IMU_OFFSETS[f] for f in fields])
        elif sensor.msg_type == JOINT_STATE:
            self._layouts = _JointStateLayouts()
        elif not self.stamped and fields == ('data',):      # Float64
            self._imu = _values_struct([0])

    def read(self, msg):
        """Return ``(header, y, problem)`` of one message (bytes or a message object)."""
        raw = _bytes_or_none(msg)
        if raw is not None:
            y = self._fast(raw)
            if y is not None:
                return header_stamp(raw) if self.stamped else None, y, None
            msg = _deserialize(raw, self.msg_class, self.sensor.topic)
        header = _header_of(msg) if self.stamped else None
        try:
            return header, extract_measurement(msg, self.sensor).tolist(), None
        except (ObserverError, ValueError) as err:
            return header, None, str(err)

    def _fast(self, raw):
        """Return the outputs of a plain, finite message at fixed offsets, else None."""
        size = len(raw)
        if raw[0:2] != _LE:
            return None
        if self._layouts is not None:
            return self._joint_state(raw)
        if self._imu is None:
            return None
        if self.stamped:                # Imu: the header's frame_id moves the rest
            if size < 16:
                return None
            base = 4 + (12 + _U32.unpack_from(raw, 12)[0] + 7) // 8 * 8
            if base + IMU_TAIL > size:
                return None
        else:                           # Float64
            base = 4
            if size < 12:
                return None
        y = _unpack(self._imu, raw, base)
        return y if all(map(_isfinite, y)) else None

    def _joint_state(self, raw):
        layout = self._layouts.find(raw)
        if layout is None:
            return None
        plan = self._plans.get(layout, False)
        if plan is False:
            plan = self._plans[layout] = self._joint_plan(layout)
        if plan is None:
            return None
        y = _unpack(plan, raw)
        return y if all(map(_isfinite, y)) else None

    def _joint_plan(self, layout):
        """Return how to read the fields in a layout, None when one is not there."""
        if len(self._plans) >= 8:
            self._plans.clear()
        offsets, missing = field_offsets(layout.names, layout.arrays, self.sensor.fields)
        return None if missing else _values_struct(offsets)


class VectorReader:
    """
    Read a vector topic's stamp and components (a JointState named by ``names``).

    ``read(raw)`` returns ``(header, values, problem)`` as :class:`SensorReader` does:
    ``values`` a list of floats in the order of ``names``, or None with ``problem`` the
    text :func:`~observer_ros.sensors.vector_from_joint_state` raises.

    """

    def __init__(self, names, topic):
        self.names = tuple(names)
        self.topic = topic
        self._limit = max_components(names)
        self._layouts = _JointStateLayouts()
        self._plans = {}

    def read(self, msg):
        """Return ``(header, values, problem)`` of one JointState (bytes or an object)."""
        raw = _bytes_or_none(msg)
        if raw is None:
            return self._object(msg)
        if raw[0:2] == _LE:
            layout = self._layouts.find(raw)
            if layout is not None:
                plan = self._plans.get(layout, False)
                if plan is False:
                    plan = self._plans[layout] = self._plan(layout)
                if plan is not None:
                    values = _unpack(plan, raw) if plan[0].size else []
                    if all(map(_isfinite, values)):
                        return header_stamp(raw), values, None
            try:
                most = max(joint_state_counts(raw)[:2])
            except CdrError:
                most = 0                # rclpy is left to say why not
            if most > self._limit:
                # refused by its size, as vector_from_joint_state does, before any object
                return (header_stamp(raw), None,
                        too_many_components(self.topic, most, self.names))
        return self._object(_deserialize(raw, _joint_state_class(), self.topic))

    def _object(self, msg):
        header = _header_of(msg)
        try:
            return header, vector_from_joint_state(msg, self.names, self.topic).tolist(), None
        except (ObserverError, ValueError) as err:
            return header, None, str(err)

    def _plan(self, layout):
        """Return how to read the components in a layout: in order only (else None)."""
        if len(self._plans) >= 8:
            self._plans.clear()
        start, count = layout.arrays['position']
        n = len(self.names)
        if count != len(layout.names) or count > self._limit or count != n:
            return None
        if layout.names and layout.names != self.names:
            return None
        if not n:
            return struct.Struct('<'), start, None
        return _values_struct([start + 8 * i for i in range(n)])


def _joint_state_class():
    from sensor_msgs.msg import JointState
    return JointState


class JointStateWriter:
    """
    Write JointStates of fixed names as CDR bytes, for ``Publisher.publish``.

    ``write(tag, frame_id, values)``: ``tag`` the stamp's 8 bytes (:func:`stamp_bytes`,
    or a reader's tag: an answer carries its message's stamp exactly), the positions one
    per name; ``velocity`` and ``effort`` empty. What
    :func:`~observer_ros.nodes.common.joint_state` builds as an object, byte for byte as
    rclpy serializes it (padding aside).

    """

    def __init__(self, names):
        self.names = tuple(names)
        self._frames = {}

    def write(self, tag, frame_id, values):
        """Return the bytes of the JointState stamped ``tag``."""
        plan = self._frames.get(frame_id)
        if plan is None:
            plan = self._frames[frame_id] = self._plan(frame_id)
        return plan.pack(tag, *values)

    def _plan(self, frame_id):
        if len(self._frames) >= 64:
            self._frames.clear()
        out = bytearray()

        def align(n):                   # offsets count from the end of the 4-byte header
            out.extend(bytes(-(12 + len(out) - 4) % n))

        def string(text):
            data = text.encode('utf-8') + b'\x00'
            align(4)
            out.extend(_U32.pack(len(data)) + data)

        string(frame_id)
        align(4)
        out.extend(_U32.pack(len(self.names)))
        for name in self.names:
            string(name)
        align(4)
        out.extend(_U32.pack(len(self.names)))
        if self.names:
            align(8)
        # then the values, and velocity and effort empty (two zero counts)
        return _Packer(bytes(out), len(self.names))


class _Packer:
    """One JointState's bytes from its stamp and values: a single struct.pack."""

    __slots__ = ('_struct', '_head', '_middle')

    def __init__(self, middle, n):
        self._struct = struct.Struct(f'<2s2x8s{len(middle)}s{n}d8x')
        self._head = _LE
        self._middle = middle

    def pack(self, tag, *values):
        return self._struct.pack(self._head, tag, self._middle, *values)
