# observer_ros.bag.cdr_decode: sensor messages decoded in bulk from their CDR bytes.
"""
Decode the fixed-layout sensor messages in bulk from their CDR bytes with numpy.

Messages of the types the sensors use (``sensor_msgs/msg/Imu``,
``sensor_msgs/msg/JointState``, ``std_msgs/msg/Float64``) are decoded at offsets computed
from the string and sequence lengths. A JointState's layout is found by the walk the nodes
use (:mod:`.joint_state_cdr`), so every little-endian JointState is read from its bytes
with the names rclpy would give; anything else (big-endian CDR, an unexpected layout)
falls back to rosbags' ``deserialize_cdr`` and the same field access as the nodes
(:func:`observer_ros.sensors.extract_measurement`). Stamps stay integer nanoseconds.

"""

from dataclasses import dataclass
import itertools
import math
from typing import Optional

import numpy as np

from .joint_state_cdr import field_offsets, JOINT_ARRAYS, joint_state_layout
from ..core.errors import ObserverError
from ..core.estimators.admission import stamp_ns
from ..sensors import vector_indices

__all__ = ['IMU', 'JOINT_STATE', 'FLOAT64', 'CLOCK', 'IMU_OFFSETS', 'IMU_TAIL', 'Decoded',
           'decode_messages', 'decode_packed']

IMU = 'sensor_msgs/msg/Imu'
JOINT_STATE = 'sensor_msgs/msg/JointState'
FLOAT64 = 'std_msgs/msg/Float64'
CLOCK = 'rosgraph_msgs/msg/Clock'

# sensor_msgs/msg/Imu after the header: orientation (4 doubles), its covariance (9),
# angular_velocity (3), covariance (9), linear_acceleration (3), covariance (9); the
# byte offsets of the fields a sensor reads (the nodes' readers use them too).
IMU_TAIL = 296
IMU_OFFSETS = {
    'orientation.x': 0, 'orientation.y': 8, 'orientation.z': 16, 'orientation.w': 24,
    'angular_velocity.x': 104, 'angular_velocity.y': 112, 'angular_velocity.z': 120,
    'linear_acceleration.x': 200, 'linear_acceleration.y': 208,
    'linear_acceleration.z': 216,
}
_IMU_EULER = ('orientation.roll', 'orientation.pitch', 'orientation.yaw')
PAD = 512          # zero bytes appended so that gathers past a short message stay inside


@dataclass
class Decoded:
    """Decoded messages of one topic."""

    stamp_ns: Optional[np.ndarray]      # (N,) int64 header stamps; None without a header
    values: np.ndarray                  # (N, k) float64; NaN where missing
    valid: np.ndarray                   # (N,) bool: the message gives every value, finite
    first_error: str = ''               # why the first invalid message is invalid
    bulk: int = 0                       # how many were read from their bytes (not the fallback)


def _gather(flat, offsets, dtype):
    """Read one little-endian scalar per row at byte offsets of flat."""
    dt = np.dtype(dtype)
    idx = offsets[:, None] + np.arange(dt.itemsize, dtype=np.int64)
    return np.ascontiguousarray(flat[idx]).view(dt).reshape(-1)


def _joint_field_offsets(names, arrays, fields, mode):
    """
    Byte offsets (within a message) of the fields, or why they cannot be read.

    Returns (offsets, error): offsets is a list with None for a missing field.

    """
    if mode == 'vector':                # judged as the nodes judge it
        start, count = arrays['position']
        try:
            order = vector_indices(list(names), count, [f.partition('.')[2] for f in fields])
        except ObserverError as err:
            return [None] * len(fields), str(err)
        return [start + 8 * i for i in (range(count) if order is None else order)], ''
    return field_offsets(names, arrays, fields)


def decode_messages(raws, msgtype, fields, mode='sensor', fallback=None, max_layouts=64):
    """
    Decode the fields of a list of CDR messages of one type.

    Parameters
    ----------
    raws : list of bytes
        Serialized messages (CDR with the 4-byte encapsulation header).
    msgtype : str
        ``sensor_msgs/msg/Imu``, ``sensor_msgs/msg/JointState`` or ``std_msgs/msg/Float64``
        are decoded in bulk; other types only through ``fallback``.
    fields : sequence of str
        Field names as in the vehicle file (``angular_velocity.y``, ``position.cart``,
        ``data``).
    mode : {'sensor', 'vector', 'partial'}
        ``sensor``: a message is valid when it gives every field, finite (as
        ``extract_measurement``). ``vector``: JointState named vector (state, command):
        as ``sensor`` and the names must match the positions; an unnamed vector of the
        right length is read in order. ``partial``: missing fields are NaN and the
        message is valid when it gives at least one (residuals).
    fallback : callable, optional
        ``fallback(raw) -> (stamp_ns or None, values)`` for messages the bulk decoder
        cannot read (big-endian, other types); raises ValueError for a bad message.
        Without it such messages are invalid.
    max_layouts : int
        JointState: at most this many distinct layouts are decoded in bulk; the
        messages of further layouts are read one by one from their bytes.

    Returns
    -------
    decoded : Decoded

    """
    n = len(raws)
    lengths = np.array(list(map(len, raws)), dtype=np.int64)
    starts = np.zeros(n, dtype=np.int64)
    if n:
        np.cumsum(lengths[:-1], out=starts[1:])
    # one copy of the batch (joining, then appending the padding, made two)
    flat = np.frombuffer(b''.join(itertools.chain(raws, (bytes(PAD),))), dtype=np.uint8)
    return decode_packed(flat, starts, lengths, msgtype, fields, mode, fallback, max_layouts,
                         raws=raws)


class _PackedRaws:
    """``raws[i]``: the bytes of message i of a packed batch (for the rare per-message path)."""

    def __init__(self, flat, starts, lengths):
        self.flat, self.starts, self.lengths = flat, starts, lengths

    def __len__(self):
        return len(self.starts)

    def __getitem__(self, i):
        b = int(self.starts[i])
        return self.flat[b:b + int(self.lengths[i])].tobytes()


def decode_packed(flat, starts, lengths, msgtype, fields, mode='sensor', fallback=None,
                  max_layouts=64, raws=None):
    """
    :func:`decode_messages` for messages already in one buffer.

    Message i is ``flat[starts[i]:starts[i] + lengths[i]]``; ``flat`` (uint8) must have
    at least ``PAD`` bytes after the last message. ``raws`` (a list of the same
    messages) is optional: without it a message is sliced out of ``flat`` when the
    per-message path needs it.

    """
    fields = tuple(fields)
    n, k = len(starts), len(fields)
    raws = _PackedRaws(flat, starts, lengths) if raws is None else raws
    values = np.full((n, k), np.nan)
    stamps = np.zeros(n, dtype=np.int64)
    has_header = msgtype != FLOAT64
    done = np.zeros(n, dtype=bool)
    errors = {}
    walk_errors = {}        # a JointState the walk refused: why, if rosbags cannot read it
    if n:
        little = (lengths >= 4) & (flat[starts] == 0) & (flat[starts + 1] == 1)
        if msgtype == IMU and all(f in IMU_OFFSETS or f in _IMU_EULER for f in fields):
            _decode_imu(flat, starts, lengths, little, fields, stamps, values, done)
        elif msgtype == FLOAT64 and fields == ('data',):
            ok = little & (lengths >= 12)
            values[ok, 0] = _gather(flat, starts[ok] + 4, '<f8')
            done |= ok
        elif msgtype == JOINT_STATE and all(
                f.partition('.')[0] in JOINT_ARRAYS and f.partition('.')[2] for f in fields):
            _decode_joint_state(raws, flat, starts, lengths, little, fields, mode,
                                stamps, values, done, errors, walk_errors, max_layouts)
    bulk = int(done.sum())
    for i in np.flatnonzero(~done):
        if fallback is None:
            errors.setdefault(i, walk_errors.get(i) or f'cannot decode {msgtype}')
            continue
        try:
            stamp, vals = fallback(raws[i])
        except (ValueError, ArithmeticError) as err:   # MeasurementError is a ValueError
            errors.setdefault(i, str(err))
            continue
        except Exception as err:   # noqa: BLE001 - a corrupted message in rosbags' serde
            errors.setdefault(i, walk_errors.get(i) or f'cannot deserialize: {err}')
            continue
        if stamp is not None:
            stamps[i] = stamp
        values[i] = vals
    with np.errstate(invalid='ignore'):
        finite = np.isfinite(values)
    if mode == 'partial':
        valid = finite.any(axis=1) if k else np.ones(n, dtype=bool)
    else:
        valid = finite.all(axis=1)
    for i in errors:
        valid[i] = False
    first_error = ''
    bad = np.flatnonzero(~valid)
    if bad.size:
        i = int(bad[0])
        first_error = errors.get(i) or _nonfinite_error(fields, values[i])
    return Decoded(stamp_ns=stamps if has_header else None, values=values, valid=valid,
                   first_error=first_error, bulk=bulk)


def _nonfinite_error(fields, row):
    for f, v in zip(fields, row):
        if not math.isfinite(v):
            return f'{f} is {v} (not finite)'
    return 'invalid message'


def _decode_imu(flat, starts, lengths, little, fields, stamps, values, done):
    ok = little & (lengths >= 16)
    rows = np.flatnonzero(ok)
    s = starts[rows]
    strlen = _gather(flat, s + 12, '<u4').astype(np.int64)
    base = 4 + (12 + strlen + 7) // 8 * 8          # aligned start of orientation
    fits = base + IMU_TAIL <= lengths[rows]       # an empty frame_id too, as rclpy reads it
    rows, s, base = rows[fits], s[fits], base[fits]
    sec = _gather(flat, s + 4, '<i4').astype(np.int64)
    nsec = _gather(flat, s + 8, '<u4').astype(np.int64)
    stamps[rows] = stamp_ns(sec, nsec)     # malformed: below 1 s
    for j, f in enumerate(fields):
        if f in IMU_OFFSETS:
            values[rows, j] = _gather(flat, s + base + IMU_OFFSETS[f], '<f8')
    euler = [j for j, f in enumerate(fields) if f in _IMU_EULER]
    if euler:
        # the sensors module's own conversion, on the same Python floats, so the angles
        # are bit for bit what extract_measurement gives
        from ..sensors import quaternion_to_euler
        quat = np.stack([_gather(flat, s + base + off, '<f8') for off in (0, 8, 16, 24)],
                        axis=1)
        angles = np.full((rows.size, 3), np.nan)
        for r, q in enumerate(quat.tolist()):
            if all(math.isfinite(c) for c in q) and any(q):
                angles[r] = quaternion_to_euler(*q)
        for j in euler:
            values[rows, j] = angles[:, _IMU_EULER.index(fields[j])]
    done[rows] = True


def _decode_joint_state(raws, flat, starts, lengths, little, fields, mode, stamps, values,
                        done, errors, walk_errors, max_layouts):
    ok = little & (lengths >= 16)
    rows = np.flatnonzero(ok)
    if not rows.size:
        return
    strlen = _gather(flat, starts[rows] + 12, '<u4').astype(np.int64)
    key = lengths[rows] * (1 << 32) + strlen
    order = np.argsort(key, kind='stable')
    rows, key = rows[order], key[order]
    bounds = np.flatnonzero(np.diff(key)) + 1
    layouts = 0
    for group in np.split(rows, bounds):
        while group.size:
            first = int(group[0])
            try:
                layout = joint_state_layout(raws[first])
            except ValueError as err:
                walk_errors[first] = str(err)   # said if rosbags cannot deserialize it
                group = group[1:]
                continue
            if layouts < max_layouts:           # every message of this layout at once
                layouts += 1
                idx = np.concatenate([np.arange(a, b, dtype=np.int64)
                                      for a, b in layout.structure])
                template = flat[starts[first] + idx]
                s = starts[group]
                same = (flat[s[:, None] + idx[None, :]] == template[None, :]).all(axis=1)
                members, group = group[same], group[~same]
            else:                               # one by one, with the same walk
                members, group = group[:1], group[1:]
            _read_joint_state(layout, members, flat, starts, fields, mode, stamps, values,
                              errors)
            done[members] = True


def _read_joint_state(layout, members, flat, starts, fields, mode, stamps, values, errors):
    """Read the stamps and fields of the messages ``members``, all of one layout."""
    s = starts[members]
    sec = _gather(flat, s + 4, '<i4').astype(np.int64)
    nsec = _gather(flat, s + 8, '<u4').astype(np.int64)
    stamps[members] = stamp_ns(sec, nsec)
    offsets, error = _joint_field_offsets(layout.names, layout.arrays, fields, mode)
    for j, off in enumerate(offsets):
        if off is not None:
            values[members, j] = _gather(flat, s + off, '<f8')
    if error and mode != 'partial':
        values[members] = np.nan
        for i in members:
            errors.setdefault(int(i), error)
