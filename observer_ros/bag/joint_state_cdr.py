# observer_ros.bag.joint_state_cdr: where a JointState's fields lie in its CDR bytes.
"""
Walk the little-endian CDR bytes of a ``sensor_msgs/msg/JointState`` once.

The offline decoder (:mod:`observer_ros.bag.cdr_decode`) and the nodes' byte readers
(:mod:`observer_ros.nodes.wire`) both find a JointState's joint names and arrays here, so a
message is laid out the same way on both sides. Two modes:

- :func:`joint_state_layout`: the names, each array's offset and count, and the bytes
  that decide them. A name is read as rclpy reads it (its bytes up to the first NUL,
  UTF-8 with U+FFFD for a bad sequence; a zero length is an empty name), so the names
  are the ones ``deserialize_message`` would give.
- :func:`joint_state_counts`: the counts alone, without decoding a name (a message of
  10^6 names is judged by its size without making its strings).

Both raise :class:`CdrError` (a ``ValueError``) naming the field that does not fit: bytes
that are not little-endian plain CDR, a length or count past the end of the message.
Everything else about the message (its header's stamp, its values) is read by the callers
at the offsets given here. No ROS import: the offline tools use it without rclpy.

"""

import struct

__all__ = ['JOINT_ARRAYS', 'LITTLE_ENDIAN', 'CdrError', 'JointStateLayout', 'joint_state_layout',
           'joint_state_counts', 'field_offsets', 'is_little_endian']

JOINT_ARRAYS = ('position', 'velocity', 'effort')
# the encapsulation header of little-endian plain CDR (the second byte: the scheme)
LITTLE_ENDIAN = b'\x00\x01'
_U32 = struct.Struct('<I')
_NUL = b'\x00'
_HEADER = 16        # encapsulation (4), stamp (8), frame_id's length (4)


class CdrError(ValueError):
    """Bytes that are not a little-endian JointState: the text names the field."""


class JointStateLayout:
    """
    Where a JointState's arrays are, and the bytes that decide it.

    ``names``: tuple of str; ``arrays``: ``{'position': (offset, count), ...}`` (byte
    offset of the first value, number of float64 values); ``structure``: ``(start, end)``
    byte spans of every length, count and name (a message with the same bytes there and
    the same size has the same layout); ``size``: the message's length in bytes.

    """

    __slots__ = ('size', 'names', 'arrays', 'structure')

    def __init__(self, size, names, arrays, structure):
        """Keep what :func:`joint_state_layout` found."""
        self.size = size
        self.names = names
        self.arrays = arrays
        self.structure = structure

    def outside_values(self):
        """Return the ``(start, end)`` spans from the stamp's end on that hold no value."""
        spans, pos = [], 12
        for array in JOINT_ARRAYS:
            start, count = self.arrays[array]
            if count:
                spans.append((pos, start))
                pos = start + 8 * count
        spans.append((pos, self.size))
        return [(a, b) for a, b in spans if b > a]


def is_little_endian(raw):
    """Tell whether raw starts with the encapsulation header of little-endian plain CDR."""
    return raw[0:2] == LITTLE_ENDIAN


def _past_end(field, what, pos, size):
    return CdrError(f'JointState.{field}: {what} at byte {pos} runs past the end of the '
                    f'{size}-byte message')


def _walk(raw, decode, max_names):
    """Walk the message once: ``(names or their count, arrays, structure)``."""
    size = len(raw)
    if size < _HEADER or raw[0:2] != LITTLE_ENDIAN:
        raise CdrError(f'JointState: not little-endian plain CDR ({size} bytes, '
                       f'encapsulation {bytes(raw[0:2]).hex() or "missing"})')
    u32 = _U32.unpack_from
    # every length and count is aligned to 4 from the end of the encapsulation header
    pos = _HEADER + u32(raw, 12)[0]
    pos += -(pos - 4) % 4
    if pos + 4 > size:
        raise _past_end('name', 'its count', pos, size)
    structure = [(12, _HEADER), (pos, pos + 4)]
    count = u32(raw, pos)[0]
    pos += 4
    if count > (size - pos) // 4:       # a name takes 4 bytes at least
        raise CdrError(f'JointState.name: {count} names cannot fit in the '
                       f'{size - pos} bytes left of the {size}-byte message')
    if max_names is not None and count > max_names:
        raise CdrError(f'JointState.name: {count} names, more than the {max_names} read here')
    if not decode:                      # counting: past the names as fast as it goes
        for _ in range(count):
            pos += -(pos - 4) % 4
            if pos + 4 > size:          # the caller walks again to name the field
                raise _past_end('name', 'a length', pos, size)
            pos += 4 + u32(raw, pos)[0]
        names = count
    else:
        names = []
        for i in range(count):
            pos += -(pos - 4) % 4
            if pos + 4 > size:
                raise _past_end(f'name[{i}]', 'its length', pos, size)
            end = pos + 4 + u32(raw, pos)[0]
            if end > size:
                raise _past_end(f'name[{i}]', f'{end - pos - 4} bytes', pos + 4, size)
            structure.append((pos, end))
            # as rclpy reads it: up to the first NUL (a C string), bad UTF-8 replaced
            names.append(raw[pos + 4:end].partition(_NUL)[0].decode('utf-8', 'replace'))
            pos = end
    arrays = {}
    for array in JOINT_ARRAYS:
        pos += -(pos - 4) % 4
        if pos + 4 > size:
            raise _past_end(array, 'its count', pos, size)
        structure.append((pos, pos + 4))
        count = u32(raw, pos)[0]
        pos += 4
        if count:
            pos += -(pos - 4) % 8
            if count > (size - pos) // 8:
                raise _past_end(array, f'{count} values', pos, size)
        arrays[array] = (pos, count)
        pos += 8 * count
    return names, arrays, structure


def joint_state_layout(raw, max_names=None):
    """
    Return the :class:`JointStateLayout` of a little-endian JointState.

    Parameters
    ----------
    raw : bytes
        The serialized message, with its 4-byte encapsulation header.
    max_names : int, optional
        Refuse (CdrError) a message with more names than this.

    Raises
    ------
    CdrError
        Not little-endian plain CDR, or a length, count, name or array past the end of
        the message (the text names the field and the byte).

    """
    names, arrays, structure = _walk(raw, True, max_names)
    return JointStateLayout(len(raw), tuple(names), arrays, tuple(structure))


def joint_state_counts(raw):
    """
    Return ``(names, position, velocity, effort)``: the counts of a little-endian JointState.

    The same walk as :func:`joint_state_layout` without decoding a name. Raises
    :class:`CdrError` as it does.

    """
    try:
        count, arrays, _ = _walk(raw, False, None)
    except CdrError:
        joint_state_layout(raw)         # raises, naming the field that does not fit
        raise
    return (count,) + tuple(arrays[a][1] for a in JOINT_ARRAYS)


def field_offsets(names, arrays, fields):
    """
    Return ``(offsets, error)``: where a layout holds each ``array.joint`` field.

    ``names`` and ``arrays`` as in :class:`JointStateLayout`; ``offsets`` has the byte
    offset of each field's value, None where the message lacks it (the joint is not
    named, or its array is shorter than its index); ``error`` says why the first missing
    one is missing ('' when none is). The joint is the first of its name, as
    :func:`~observer_ros.sensors.extract_measurement` looks it up.

    """
    offsets, error = [], ''
    for f in fields:
        array, _, joint = f.partition('.')
        start, count = arrays.get(array, (0, 0))
        if joint not in names:
            offsets.append(None)
            error = error or f'joint {joint!r} is not in JointState.name {list(names)}'
            continue
        i = names.index(joint)
        if i >= count:
            offsets.append(None)
            error = error or (f'joint {joint!r}: JointState.{array} has {count} values '
                              f'for {len(names)} names')
            continue
        offsets.append(start + 8 * i)
    return offsets, error
