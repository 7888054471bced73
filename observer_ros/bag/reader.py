# observer_ros.bag.reader: open a ROS 2 bag and load a vehicle's topics as arrays.
"""
Open a ROS 2 bag (mcap or sqlite3) and load a vehicle's topics as numpy arrays.

A bag is a directory with ``metadata.yaml`` (as written by ``ros2 bag record`` or by
rosbags' Writer) or a single ``.mcap`` / ``.db3`` file. It is read with rosbags'
``AnyReader`` and the ROS 2 Jazzy typestore for bags without type definitions
(STYLE.md §3, §10). Every problem is a :class:`BagToolError` naming the file.

The vehicle file names its topics relative to the vehicle's namespace (``imu/gyro``);
the bag holds absolute names (``/imu/gyro``, ``/sub1/imu/gyro``). The namespace is given
or detected: the one under which every sensor topic of the vehicle is in the bag.

Messages of the fixed-layout types the sensors use (``sensor_msgs/msg/Imu``,
``sensor_msgs/msg/JointState``, ``std_msgs/msg/Float64``) are decoded in bulk from their
CDR bytes with numpy, at offsets computed from the string and sequence lengths; anything
else (big-endian CDR, an unexpected layout) falls back to rosbags' ``deserialize_cdr`` and
the same field access as the nodes (:func:`observer_ros.sensors.extract_measurement`).
Stamps stay integer nanoseconds; seconds are ``ns * 1e-9`` exactly as
:func:`observer_ros.timeutil.stamp_to_sec` computes them.

"""

from dataclasses import dataclass, field
import functools
import gc
import itertools
import math
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import numpy as np
from rosbags.highlevel import AnyReader
from rosbags.typesys import get_typestore, Stores

from .errors import BagToolError
from .integrity import checksum_note, chunk_crcs
from .mcap_fast import fast_chunks, fast_messages
from ..timeutil import stamp_to_ns

__all__ = ['IMU', 'JOINT_STATE', 'FLOAT64', 'CLOCK', 'VEHICLE_TOPICS', 'jazzy_typestore',
           'normalize_namespace', 'BagInfo', 'BagReader', 'bag_info', 'TopicMap',
           'resolve_topics', 'Decoded', 'decode_messages', 'Stream', 'Recording',
           'read_recording']

IMU = 'sensor_msgs/msg/Imu'
JOINT_STATE = 'sensor_msgs/msg/JointState'
FLOAT64 = 'std_msgs/msg/Float64'
CLOCK = 'rosgraph_msgs/msg/Clock'

# The vector topics of the nodes (relative names, JointState named by the vector's names).
VEHICLE_TOPICS = {
    'truth': 'state/true',
    'estimate': 'state/estimate',
    'command': 'control/u',
    'residual': 'observer/residual',
}

_STORAGE_SUFFIXES = {'.mcap': 'mcap', '.db3': 'sqlite3'}
_FLUSH = 1 << 16            # decode a topic's raw messages every this many (bounds memory)
_INT32_LIMIT = 1 << 31
_PROGRESS_EVERY = 1 << 16   # call the progress callback every this many messages


@functools.lru_cache(maxsize=1)
def jazzy_typestore():
    """Return the (cached) ROS 2 Jazzy typestore of rosbags."""
    return get_typestore(Stores.ROS2_JAZZY)


def normalize_namespace(namespace):
    """
    Return a namespace as ``''`` (root) or ``'/a/b'``.

    Parameters
    ----------
    namespace : str or None
        ``None``, ``''``, ``'/'``, ``'sub1'``, ``'/sub1/'`` ...

    Returns
    -------
    ns : str
        ``''`` for the root namespace, else a name with one leading and no trailing ``/``.

    """
    if namespace is None:
        return ''
    parts = [p for p in str(namespace).strip().split('/') if p]
    return '/' + '/'.join(parts) if parts else ''


def _join(namespace, topic):
    """Absolute name of a (relative or absolute) topic in a namespace."""
    if topic.startswith('/'):
        return topic
    return f'{namespace}/{topic.lstrip("~/")}'


# ---------------------------------------------------------------------------------------
# Opening a bag
# ---------------------------------------------------------------------------------------

@dataclass
class BagInfo:
    """What a bag holds: its file, storage, topics and time span."""

    path: Path                          # as given
    storage_path: Path                  # what was opened (the directory or one file)
    storage: str                        # 'mcap' or 'sqlite3'
    topics: Dict[str, Tuple[str, int]]  # topic -> (message type, message count)
    message_count: int
    start_ns: int
    end_ns: int
    ros_distro: Optional[str] = None
    warnings: List[str] = field(default_factory=list)
    chunk_crcs: Optional[List[int]] = None  # MCAP: each chunk's CRC32 (0: none)

    def describe_topics(self, limit=12):
        """Return the bag's topics as one line: ``/a (Imu, 10 msgs), ...``."""
        items = [f'{name} ({msgtype.rsplit("/", 1)[-1]}, {count} msgs)'
                 for name, (msgtype, count) in sorted(self.topics.items())]
        if not items:
            return 'none'
        more = len(items) - limit
        return ', '.join(items[:limit]) + (f', ... ({more} more)' if more > 0 else '')


def _reason(path, err):
    """Turn a rosbags exception into a short explanation with a hint."""
    text = ' '.join(str(a) for a in getattr(err, 'args', ()) if a) or type(err).__name__
    low = text.lower()
    if 'end magic' in low or 'unexpected end' in low or 'could not read' in low \
            and 'bytes' in low:
        hint = ('the file ends early: truncated, or a recording that was not closed '
                '(`ros2 bag reindex` or `mcap recover` may repair it)')
    elif 'file magic' in low:
        hint = 'not an MCAP file'
    elif 'malformed' in low or 'not a database' in low:
        hint = 'the sqlite3 database is truncated or corrupted'
    elif 'checksum mismatch' in low:
        hint = ('the data changed on disk after it was written: its CRC32 does not match; '
                'do not trust this bag')
    elif 'hash mismatch' in low:
        hint = ("the bag's message definitions do not match their hashes (another ROS "
                'release or a modified message?)')
    else:
        hint = 'truncated or corrupted?'
    return f'{path}: cannot read the bag: {text} ({hint})'


def _storage_file(path):
    """Return the one storage file of a bag directory (for messages), else the path."""
    path = Path(path)
    if path.is_dir():
        files = sorted(x for x in path.iterdir() if x.suffix in _STORAGE_SUFFIXES)
        if len(files) == 1:
            return files[0]
    return path


class BagReader:
    """
    An open bag: rosbags' AnyReader plus a :class:`BagInfo`, with clear errors.

    Use as a context manager::

        with BagReader('bags/run1') as bag:
            print(bag.info.describe_topics())
            for conn, log_ns, raw in bag.messages(['/imu/gyro']):
                ...

    Parameters
    ----------
    path : str or Path
        A bag directory, or one ``.mcap`` or ``.db3`` file. A directory without its
        ``metadata.yaml`` is read through its single storage file (with a warning).

    Raises
    ------
    BagToolError
        The path is missing, is not a ROS 2 bag, or cannot be read (truncated,
        corrupted); the message names the file.

    """

    def __init__(self, path):
        self.path = Path(path)
        self.reader = None
        self.info = None
        self.warnings = []

    def __enter__(self):
        """Open the bag."""
        return self.load()

    def __exit__(self, *exc):
        """Close the bag."""
        self.close()

    def _storage_path(self):
        p = self.path
        if not p.exists():
            raise BagToolError(f'{p}: no such file or directory')
        if p.is_dir():
            if (p / 'metadata.yaml').exists():
                return p
            files = sorted(x for x in p.iterdir() if x.suffix in _STORAGE_SUFFIXES)
            if not files:
                raise BagToolError(
                    f'{p}: not a bag: the directory has no metadata.yaml and no .mcap or '
                    '.db3 file')
            if len(files) > 1:
                raise BagToolError(
                    f'{p}: metadata.yaml is missing and the directory holds '
                    f'{len(files)} storage files ({", ".join(f.name for f in files)}); '
                    f'restore it with `ros2 bag reindex {p}` or pass one file')
            self.warnings.append(
                f'{p}: metadata.yaml is missing; reading {files[0].name} directly')
            return files[0]
        if p.suffix == '.bag':
            raise BagToolError(
                f'{p}: a ROS 1 bag; observer_ros reads ROS 2 bags (mcap or sqlite3); '
                'convert it with `rosbags-convert`')
        if p.suffix not in _STORAGE_SUFFIXES:
            raise BagToolError(
                f'{p}: not a bag: expected a bag directory, a .mcap or a .db3 file')
        return p

    def load(self):
        """Open the bag and fill :attr:`info`; return self."""
        storage_path = self._storage_path()
        try:
            reader = AnyReader([storage_path], default_typestore=jazzy_typestore())
            reader.open()
        except BagToolError:
            raise
        except Exception as err:   # noqa: BLE001 - rosbags raises many types
            raise BagToolError(_reason(_storage_file(storage_path), err)) from None
        self.reader = reader
        try:
            self.info = self._make_info(storage_path)
        except Exception as err:   # noqa: BLE001
            self.close()
            raise BagToolError(_reason(_storage_file(storage_path), err)) from None
        return self

    def _make_info(self, storage_path):
        reader = self.reader
        if not reader.is2:
            raise BagToolError(f'{self.path}: a ROS 1 bag; observer_ros reads ROS 2 bags')
        topics = {}
        for conn in reader.connections:
            msgtype, count = topics.get(conn.topic, (conn.msgtype, 0))
            topics[conn.topic] = (msgtype, count + int(conn.msgcount or 0))
        sub = reader.readers[0]
        inner = getattr(sub, 'storage', None)
        inner = (getattr(inner, 'storages', None) or [inner])[0]
        storage = 'mcap' if 'mcap' in type(inner).__name__.lower() else 'sqlite3'
        count = int(reader.message_count)
        crcs = chunk_crcs(inner) if storage == 'mcap' and getattr(inner, 'bio', None) \
            else None
        note = checksum_note(_storage_file(storage_path), storage, crcs)
        return BagInfo(path=self.path, storage_path=storage_path, storage=storage,
                       topics=topics, message_count=count,
                       start_ns=int(reader.start_time) if count else 0,
                       end_ns=int(reader.end_time) if count else 0,
                       ros_distro=getattr(sub, 'ros_distro', None),
                       warnings=list(self.warnings) + ([note] if note else []),
                       chunk_crcs=crcs)

    def close(self):
        """Close the bag (idempotent)."""
        if self.reader is not None:
            reader, self.reader = self.reader, None
            try:
                reader.close()
            except Exception:   # noqa: BLE001 - closing a broken bag
                pass

    def connections(self, topics=None):
        """Return the connections of the given topics (all when None)."""
        conns = self.reader.connections
        if topics is None:
            return list(conns)
        wanted = set(topics)
        return [c for c in conns if c.topic in wanted]

    def messages(self, topics=None, start=None):
        """
        Yield ``(connection, log_ns, raw)`` in bag order; read errors become BagToolError.

        Parameters
        ----------
        topics : iterable of str, optional
            Only these topics (all when None).
        start : int, optional
            Only messages received at or after this time (ns).

        """
        conns = self.connections(topics)
        if topics is not None and not conns:
            return
        readers = self.reader.readers
        # one rosbag2 recording: read it directly (AnyReader merges several bags)
        source = readers[0] if len(readers) == 1 else self.reader
        try:
            # an indexed mcap file: read chunk by chunk, same stream (benchmarks P3)
            fast = fast_messages(source, conns, start) if len(readers) == 1 else None
            if fast is not None:
                yield from fast
                return
            yield from source.messages(connections=conns, start=start)
        except BagToolError:
            raise
        except Exception as err:   # noqa: BLE001 - rosbags raises many types
            raise BagToolError(_reason(_storage_file(self.info.storage_path), err)) from None

    def message_chunks(self, topics=None):
        """
        Return the messages of :meth:`messages` chunk by chunk as arrays, or None.

        For one indexed MCAP file (see :func:`~observer_ros.bag.mcap_fast.fast_chunks`);
        None when the bag must be read message by message.

        """
        conns = self.connections(topics)
        readers = self.reader.readers
        if len(readers) != 1 or (topics is not None and not conns):
            return None
        try:
            chunks = fast_chunks(readers[0], conns, pad=_PAD)
        except Exception:   # noqa: BLE001 - any doubt: the message-by-message path
            return None
        return None if chunks is None else self._guarded(chunks)

    def _guarded(self, chunks):
        try:
            yield from chunks
        except BagToolError:
            raise
        except Exception as err:   # noqa: BLE001 - rosbags raises many types
            raise BagToolError(_reason(_storage_file(self.info.storage_path), err)) from None

    def deserialize(self, raw, msgtype):
        """Deserialize one message with the bag's typestore."""
        return self.reader.deserialize(raw, msgtype)

    def check_definition(self, msgtype):
        """
        Return why the bag's definition of msgtype differs from ROS 2 Jazzy's, or ''.

        Compares the recorded type hash (RIHS01, when the bag has one) and the field
        definitions, nested types included.

        """
        store = jazzy_typestore()
        if msgtype not in store.fielddefs:
            return ''
        for conn in self.reader.connections:
            if conn.msgtype == msgtype and conn.digest and \
                    conn.digest != store.hash_rihs01(msgtype):
                return (f"the bag's {msgtype} has type hash {conn.digest[:22]}...; "
                        f"ROS 2 Jazzy's is {store.hash_rihs01(msgtype)[:22]}...")
        bag_store = self.reader.typestore
        todo, seen = [msgtype], set()
        while todo:
            name = todo.pop()
            if name in seen:
                continue
            seen.add(name)
            mine, theirs = bag_store.fielddefs.get(name), store.fielddefs.get(name)
            if mine is None or theirs is None:
                continue
            if mine != theirs:
                return f"the bag's definition of {name} differs from ROS 2 Jazzy's"
            todo.extend(_nested_types(mine))
        return ''


def _nested_types(desc):
    if isinstance(desc, str):
        if '/msg/' in desc:
            yield desc
    elif isinstance(desc, (tuple, list)):
        for item in desc:
            yield from _nested_types(item)


def bag_info(path):
    """
    Return the :class:`BagInfo` of a bag (topics, counts, time span).

    Parameters
    ----------
    path : str or Path
        The bag: its folder or a storage file, as :class:`BagReader` takes it.

    Returns
    -------
    info : BagInfo

    Raises
    ------
    BagToolError
        As :class:`BagReader`.

    """
    with BagReader(path) as bag:
        return bag.info


# ---------------------------------------------------------------------------------------
# Topic names
# ---------------------------------------------------------------------------------------

@dataclass
class TopicMap:
    """The absolute topic names of a vehicle in a bag."""

    namespace: str
    sensors: Dict[str, str]                     # sensor name -> topic
    truth: Optional[str] = None                 # present in the bag, else None
    estimate: Optional[str] = None
    command: Optional[str] = None
    residual: Optional[str] = None


def resolve_topics(info, vehicle, namespace=None):
    """
    Find a vehicle's topics in a bag.

    Parameters
    ----------
    info : BagInfo
        The bag's topics and counts, from :func:`bag_info`.
    vehicle : Vehicle
        Its sensors say which topics to find.
    namespace : str, optional
        The vehicle's namespace (``/sub1``); detected when None: the one namespace under
        which every sensor topic of the vehicle is in the bag.

    Returns
    -------
    topics : TopicMap
        Sensor topics are in the bag and have messages; the vector topics are None
        when the bag does not have them.

    Raises
    ------
    BagToolError
        The bag is empty, a sensor topic is missing or has no messages ("bag has no
        messages on /sub1/imu/gyro (sensor 'gyro' of vehicle submarine); topics in the
        bag: ..."), several namespaces match, or a topic has the wrong type.

    """
    where = info.path
    if info.message_count == 0:
        raise BagToolError(f'{where}: the bag is empty (no messages); topics in the '
                           f'bag: {info.describe_topics()}')
    sensors = list(vehicle.sensors)
    if namespace is not None:
        ns = normalize_namespace(namespace)
    else:
        ns = _detect_namespace(info, vehicle)
    names = {s.name: _join(ns, s.topic) for s in sensors}
    for s in sensors:
        topic = names[s.name]
        msgtype, count = info.topics.get(topic, (None, 0))
        if msgtype is None or count == 0:
            hint = '' if namespace is not None or msgtype is not None else \
                ' (pass --namespace if the vehicle ran in a namespace)'
            raise BagToolError(
                f'{where}: bag has no messages on {topic} (sensor {s.name!r} of vehicle '
                f'{vehicle.name}); topics in the bag: {info.describe_topics()}{hint}')
        if msgtype != s.msg_type:
            raise BagToolError(
                f'{where}: topic {topic} is {msgtype} in the bag; sensor {s.name!r} of '
                f'vehicle {vehicle.name} expects {s.msg_type}')
    topics = TopicMap(namespace=ns, sensors=names)
    for key, rel in VEHICLE_TOPICS.items():
        topic = _join(ns, rel)
        msgtype, count = info.topics.get(topic, (None, 0))
        if msgtype is None or count == 0:
            continue
        if msgtype != JOINT_STATE:
            info.warnings.append(f'{topic} is {msgtype}, not {JOINT_STATE}; ignored')
            continue
        setattr(topics, key, topic)
    return topics


def _detect_namespace(info, vehicle):
    """Return the one namespace under which all the vehicle's sensor topics are."""
    rels = [s.topic for s in vehicle.sensors]
    relative = [r for r in rels if not r.startswith('/')]
    if not relative:
        return ''
    candidates = {}
    for rel in relative:
        tail = '/' + rel.lstrip('~/')
        for topic in info.topics:
            if topic == tail or topic.endswith(tail):
                ns = topic[:len(topic) - len(tail)]
                candidates.setdefault(ns, set()).add(rel)
    full = sorted(ns for ns, found in candidates.items() if len(found) == len(set(relative)))
    if len(full) == 1:
        return full[0]
    if len(full) > 1:
        shown = ', '.join(repr(ns or '/') for ns in full)
        raise BagToolError(
            f'{info.path}: the sensor topics of vehicle {vehicle.name} are in the bag under '
            f'several namespaces ({shown}); choose one with --namespace')
    if candidates:   # the namespace that has most of them: its missing topic is the error
        return max(sorted(candidates), key=lambda ns: len(candidates[ns]))
    # no sensor topic at all: the namespace of the vehicle's other topics, if one
    others = set()
    for rel in VEHICLE_TOPICS.values():
        for topic in info.topics:
            if topic.endswith('/' + rel):
                others.add(topic[:len(topic) - len(rel) - 1])
    return others.pop() if len(others) == 1 else ''


# ---------------------------------------------------------------------------------------
# Bulk CDR decoding
# ---------------------------------------------------------------------------------------

# sensor_msgs/msg/Imu after the header: orientation (4 doubles), its covariance (9),
# angular_velocity (3), covariance (9), linear_acceleration (3), covariance (9).
_IMU_TAIL = 296
_IMU_OFFSETS = {
    'orientation.x': 0, 'orientation.y': 8, 'orientation.z': 16, 'orientation.w': 24,
    'angular_velocity.x': 104, 'angular_velocity.y': 112, 'angular_velocity.z': 120,
    'linear_acceleration.x': 200, 'linear_acceleration.y': 208,
    'linear_acceleration.z': 216,
}
_IMU_EULER = ('orientation.roll', 'orientation.pitch', 'orientation.yaw')
_JOINT_ARRAYS = ('position', 'velocity', 'effort')
_PAD = 512          # zero bytes appended so that gathers past a short message stay inside


@dataclass
class Decoded:
    """Decoded messages of one topic."""

    stamp_ns: Optional[np.ndarray]      # (N,) int64 header stamps; None without a header
    values: np.ndarray                  # (N, k) float64; NaN where missing
    valid: np.ndarray                   # (N,) bool: the message gives every value, finite
    first_error: str = ''               # why the first invalid message is invalid
    bulk: int = 0                       # how many were decoded in bulk (the rest one by one)


def _gather(flat, offsets, dtype):
    """Read one little-endian scalar per row at byte offsets of flat."""
    dt = np.dtype(dtype)
    idx = offsets[:, None] + np.arange(dt.itemsize, dtype=np.int64)
    return np.ascontiguousarray(flat[idx]).view(dt).reshape(-1)


def _align(pos, alignment):
    """CDR alignment of an absolute offset (the origin is after the 4-byte header)."""
    rel = pos - 4
    return 4 + (rel + alignment - 1) // alignment * alignment


def _joint_state_layout(buf):
    """
    Parse one little-endian JointState: names, arrays (offset, count), structural bytes.

    The structural bytes (every length and count, and the joint names) decide the
    layout: a message with the same structural bytes has the same offsets.

    """
    if len(buf) < 16 or buf[0] != 0 or buf[1] != 1:
        raise ValueError('not little-endian CDR')

    def u32(off):
        if off + 4 > len(buf):
            raise ValueError('truncated')
        return int.from_bytes(buf[off:off + 4], 'little')

    structural = [(12, 16)]
    pos = 16 + u32(12)
    pos = _align(pos, 4)
    count = u32(pos)
    structural.append((pos, pos + 4))
    pos += 4
    names = []
    for _ in range(count):
        pos = _align(pos, 4)
        n = u32(pos)
        if n < 1 or pos + 4 + n > len(buf):
            raise ValueError('bad string')
        structural.append((pos, pos + 4 + n))
        names.append(bytes(buf[pos + 4:pos + 3 + n]).decode('utf-8', 'replace'))
        pos += 4 + n
    arrays = {}
    for array in _JOINT_ARRAYS:
        pos = _align(pos, 4)
        c = u32(pos)
        structural.append((pos, pos + 4))
        pos += 4
        if c:
            pos = _align(pos, 8)
        arrays[array] = (pos, c)
        pos += 8 * c
    if pos > len(buf):
        raise ValueError('truncated')
    return names, arrays, structural


def _joint_field_offsets(names, arrays, fields, mode):
    """
    Byte offsets (within a message) of the fields, or why they cannot be read.

    Returns (offsets, error): offsets is a list with None for a missing field.

    """
    offsets, error = [], ''
    if mode == 'vector':
        count = arrays['position'][1]
        if count != len(names):
            return [None] * len(fields), f'{len(names)} names but {count} positions'
        if not names and count == len(fields):      # positional, as the nodes accept
            start = arrays['position'][0]
            return [start + 8 * i for i in range(count)], ''
    for f in fields:
        array, _, joint = f.partition('.')
        start, count = arrays.get(array, (0, 0))
        if joint not in names:
            offsets.append(None)
            error = error or f'joint {joint!r} is not in JointState.name {names}'
            continue
        i = names.index(joint)
        if i >= count:
            offsets.append(None)
            error = error or (f'joint {joint!r}: JointState.{array} has {count} values '
                              f'for {len(names)} names')
            continue
        offsets.append(start + 8 * i)
    return offsets, error


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
        JointState: at most this many distinct layouts are decoded in bulk.

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
    flat = np.frombuffer(b''.join(itertools.chain(raws, (bytes(_PAD),))), dtype=np.uint8)
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
    at least ``_PAD`` bytes after the last message. ``raws`` (a list of the same
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
    if n:
        little = (lengths >= 4) & (flat[starts] == 0) & (flat[starts + 1] == 1)
        if msgtype == IMU and all(f in _IMU_OFFSETS or f in _IMU_EULER for f in fields):
            _decode_imu(flat, starts, lengths, little, fields, stamps, values, done)
        elif msgtype == FLOAT64 and fields == ('data',):
            ok = little & (lengths >= 12)
            values[ok, 0] = _gather(flat, starts[ok] + 4, '<f8')
            done |= ok
        elif msgtype == JOINT_STATE and all(
                f.partition('.')[0] in _JOINT_ARRAYS and f.partition('.')[2] for f in fields):
            _decode_joint_state(raws, flat, starts, lengths, little, fields, mode,
                                stamps, values, done, errors, max_layouts)
    bulk = int(done.sum())
    for i in np.flatnonzero(~done):
        if fallback is None:
            errors.setdefault(i, f'cannot decode {msgtype}')
            continue
        try:
            stamp, vals = fallback(raws[i])
        except (ValueError, ArithmeticError) as err:   # MeasurementError is a ValueError
            errors.setdefault(i, str(err))
            continue
        except Exception as err:   # noqa: BLE001 - a corrupted message in rosbags' serde
            errors.setdefault(i, f'cannot deserialize: {err}')
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
    fits = (strlen >= 1) & (base + _IMU_TAIL <= lengths[rows])
    rows, s, base = rows[fits], s[fits], base[fits]
    sec = _gather(flat, s + 4, '<i4').astype(np.int64)
    nsec = _gather(flat, s + 8, '<u4').astype(np.int64)
    stamps[rows] = sec * 1_000_000_000 + nsec
    for j, f in enumerate(fields):
        if f in _IMU_OFFSETS:
            values[rows, j] = _gather(flat, s + base + _IMU_OFFSETS[f], '<f8')
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
                        done, errors, max_layouts):
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
        while group.size and layouts < max_layouts:
            first = int(group[0])
            try:
                names, arrays, structural = _joint_state_layout(memoryview(raws[first]))
            except ValueError:
                group = group[1:]           # left to the fallback
                continue
            layouts += 1
            idx = np.concatenate([np.arange(a, b, dtype=np.int64) for a, b in structural])
            s = starts[group]
            template = flat[starts[first] + idx]
            same = (flat[s[:, None] + idx[None, :]] == template[None, :]).all(axis=1)
            members, group = group[same], group[~same]
            s = starts[members]
            sec = _gather(flat, s + 4, '<i4').astype(np.int64)
            nsec = _gather(flat, s + 8, '<u4').astype(np.int64)
            stamps[members] = sec * 1_000_000_000 + nsec
            offsets, error = _joint_field_offsets(names, arrays, fields, mode)
            for j, off in enumerate(offsets):
                if off is not None:
                    values[members, j] = _gather(flat, s + off, '<f8')
            if error and mode != 'partial':
                values[members] = np.nan
                for i in members:
                    errors.setdefault(int(i), error)
            done[members] = True


# ---------------------------------------------------------------------------------------
# Loading a vehicle's topics
# ---------------------------------------------------------------------------------------

@dataclass
class Stream:
    """
    The decoded messages of one topic, in bag order.

    ``seq`` is each message's position among all the messages loaded from the bag, so
    streams can be merged back into bag (receive) order. ``stamp_ns`` is the header
    stamp, or the receive time for a message without a header (std_msgs/Float64, as the
    observer node uses its clock). ``t`` is ``stamp_ns * 1e-9``, the nodes' conversion.

    """

    topic: str
    msgtype: str
    names: Tuple[str, ...]
    seq: np.ndarray
    log_ns: np.ndarray
    stamp_ns: np.ndarray
    values: np.ndarray
    valid: np.ndarray
    has_header: bool = True
    first_error: str = ''
    bulk: int = 0

    @property
    def t(self):
        """Stamps in seconds (float64), as ``stamp_to_sec``."""
        return self.stamp_ns.astype(np.float64) * 1e-9

    def __len__(self):
        """Return the number of messages."""
        return int(self.seq.size)


@dataclass
class Recording:
    """A vehicle's topics loaded from a bag."""

    info: BagInfo
    topics: TopicMap
    sensors: Dict[str, Stream]            # by sensor name, in the vehicle's order
    truth: Optional[Stream] = None
    estimate: Optional[Stream] = None
    command: Optional[Stream] = None
    residual: Optional[Stream] = None
    warnings: List[str] = field(default_factory=list)

    @property
    def namespace(self):
        """Return the vehicle's namespace in the bag ('' for the root)."""
        return self.topics.namespace

    def streams(self):
        """Return every loaded stream as (key, Stream): sensors first."""
        out = [(f'sensor:{name}', s) for name, s in self.sensors.items()]
        for key in ('command', 'truth', 'estimate', 'residual'):
            stream = getattr(self, key)
            if stream is not None:
                out.append((key, stream))
        return out


class _Accumulator:
    """
    Raw messages of one topic, decoded in chunks while the bag is read.

    The decoded columns go straight into arrays sized by the topic's message count in
    the bag's index (grown if the bag has more), not into parts joined at the end: a
    stream is held once, not twice, while it is read.
    """

    def __init__(self, topic, msgtype, names, fields, mode, fallback, expected=0,
                 seq_dtype=np.int64):
        self.topic, self.msgtype, self.names = topic, msgtype, tuple(names)
        self.fields, self.mode, self.fallback = tuple(fields), mode, fallback
        self.raws, self.logs, self.seqs = [], [], []
        self.expected, self.seq_dtype = int(expected), seq_dtype
        self.cols = None            # seq, log, stamp (None: no header), values, valid
        self.n = self.bulk = 0
        self.first_error = ''

    def add(self, raws, logs, seqs):
        """Take a batch: raw messages (list), receive times and bag positions (arrays)."""
        self.raws.extend(raws)
        self.logs.append(logs)
        self.seqs.append(seqs)
        if len(self.raws) >= _FLUSH:
            self.flush()

    def add_packed(self, flat, starts, lengths, logs, seqs):
        """Take a batch already in one buffer (see :func:`decode_packed`): decoded at once."""
        self.flush()
        dec = decode_packed(flat, starts, lengths, self.msgtype, self.fields, self.mode,
                            self.fallback)
        self._put(seqs, logs, dec)

    def flush(self):
        if not self.raws:
            return
        dec = decode_messages(self.raws, self.msgtype, self.fields, self.mode, self.fallback)
        self._put(np.concatenate(self.seqs), np.concatenate(self.logs), dec)
        self.raws, self.logs, self.seqs = [], [], []

    def _put(self, seqs, logs, dec):
        n = len(seqs)
        if n and self.seq_dtype != np.int64 and seqs[-1] >= _INT32_LIMIT:   # bad index
            self.seq_dtype = np.int64
            if self.cols is not None:
                self.cols[0] = self.cols[0].astype(np.int64)
        if self.cols is None:
            size = max(self.expected, n)
            self.cols = [np.empty(size, dtype=self.seq_dtype), np.empty(size, dtype=np.int64),
                         None if dec.stamp_ns is None else np.empty(size, dtype=np.int64),
                         np.empty((size, len(self.fields))), np.empty(size, dtype=bool)]
        elif self.n + n > self.cols[0].shape[0]:        # more than the index said
            size = max(2 * self.cols[0].shape[0], self.n + n)
            self.cols = [None if c is None else _resized(c, size) for c in self.cols]
        stamps = logs if self.cols[2] is None else dec.stamp_ns
        for col, part in zip(self.cols, (seqs, logs, stamps, dec.values, dec.valid)):
            if col is not None:
                col[self.n:self.n + n] = part
        self.n += n
        self.bulk += dec.bulk
        self.first_error = self.first_error or dec.first_error

    def stream(self):
        self.flush()
        if self.cols is None:
            empty = np.zeros(0, dtype=np.int64)
            return Stream(self.topic, self.msgtype, self.names, empty, empty, empty,
                          np.zeros((0, len(self.fields))), np.zeros(0, dtype=bool),
                          self.msgtype != FLOAT64)
        cols = [c if c is None or c.shape[0] == self.n else c[:self.n].copy()
                for c in self.cols]
        seq, log, stamp, values, valid = cols
        has_header = stamp is not None
        # without a header the stamp is the receive time: the same array, not a copy
        return Stream(self.topic, self.msgtype, self.names, seq, log,
                      stamp if has_header else log, values, valid, has_header,
                      self.first_error, self.bulk)


def _resized(col, size):
    out = np.empty((size,) + col.shape[1:], dtype=col.dtype)
    out[:col.shape[0]] = col
    return out


def _sensor_fallback(bag, sensor):
    from ..sensors import extract_measurement

    def decode(raw):
        msg = bag.deserialize(raw, sensor.msg_type)
        header = getattr(msg, 'header', None)
        stamp = stamp_to_ns(header.stamp) if header is not None else None
        return stamp, extract_measurement(msg, sensor)
    return decode


def _vector_fallback(bag, names, mode):
    def decode(raw):
        msg = bag.deserialize(raw, JOINT_STATE)
        stamp = stamp_to_ns(msg.header.stamp)
        got = list(msg.name)
        position = np.asarray(msg.position, dtype=float)
        if mode == 'vector':
            if len(position) != len(got):
                raise ValueError(f'{len(got)} names but {len(position)} positions')
            if not got and len(position) == len(names):
                return stamp, position
        index = {n: i for i, n in enumerate(got)}
        out = np.full(len(names), np.nan)
        for j, n in enumerate(names):
            if n in index and index[n] < len(position):
                out[j] = position[index[n]]
            elif mode != 'partial':
                raise ValueError(f'missing component {n!r}; got names {got}')
        return stamp, out
    return decode


def read_recording(path, vehicle, namespace=None, progress=None, vectors=True):
    """
    Load a vehicle's sensor, command and state topics from a bag.

    Parameters
    ----------
    path : str or Path
        Bag directory or storage file.
    vehicle : Vehicle
        Its sensors say which topics, types and fields to read.
    namespace : str, optional
        The vehicle's namespace in the bag; detected when None.
    progress : callable, optional
        ``progress(done, total)`` called while reading (total may be 0 if unknown).
    vectors : bool
        Also load ``state/true``, ``state/estimate``, ``control/u`` and
        ``observer/residual`` when the bag has them.

    Returns
    -------
    recording : Recording

    Raises
    ------
    BagToolError
        Unreadable, empty or truncated bag; missing sensor topic; wrong type; a message
        definition other than ROS 2 Jazzy's; a sensor none of whose messages gives the
        vehicle's outputs.

    """
    plant = vehicle.plant
    with BagReader(path) as bag:
        info = bag.info
        topics = resolve_topics(info, vehicle, namespace)
        # a message's bag position fits int32 in any bag of fewer than 2^31 messages
        seq_dtype = np.int32 if info.message_count < _INT32_LIMIT else np.int64

        def sizes(topic):
            return info.topics.get(topic, (None, 0))[1], seq_dtype
        accs = {}
        for sensor in vehicle.sensors:
            topic = topics.sensors[sensor.name]
            why = bag.check_definition(sensor.msg_type)
            if why:
                raise BagToolError(
                    f'{info.path}: {topic} (sensor {sensor.name!r}): {why} (another ROS '
                    f'release or a modified message? the bag says ros_distro '
                    f'{info.ros_distro or "(not recorded)"})')
            accs[topic] = (f'sensor:{sensor.name}', _Accumulator(
                topic, sensor.msg_type, sensor.outputs, sensor.fields, 'sensor',
                _sensor_fallback(bag, sensor), *sizes(topic)))
        if vectors:
            vector_names = {'truth': plant.state_names, 'estimate': plant.state_names,
                            'command': plant.input_names, 'residual': plant.output_names}
            for key, names in vector_names.items():
                topic = getattr(topics, key)
                if topic is None or topic in accs:
                    continue
                if bag.check_definition(JOINT_STATE):
                    info.warnings.append(f'{topic}: {bag.check_definition(JOINT_STATE)}; '
                                         'ignored')
                    setattr(topics, key, None)
                    continue
                mode = 'partial' if key == 'residual' else 'vector'
                accs[topic] = (key, _Accumulator(
                    topic, JOINT_STATE, names, [f'position.{n}' for n in names], mode,
                    _vector_fallback(bag, names, mode), *sizes(topic)))
        total = sum(info.topics[t][1] for t in accs)
        by_conn = {}
        for conn in bag.connections(accs):
            by_conn[conn.id] = accs[conn.topic][1]
        _read_all(bag, list(accs), by_conn, progress, total)
        streams = {key: acc.stream() for key, acc in accs.values()}
    recording = Recording(
        info=info, topics=topics,
        sensors={s.name: streams[f'sensor:{s.name}'] for s in vehicle.sensors},
        truth=streams.get('truth'), estimate=streams.get('estimate'),
        command=streams.get('command'), residual=streams.get('residual'),
        warnings=list(info.warnings))
    for sensor in vehicle.sensors:
        stream = recording.sensors[sensor.name]
        if len(stream) and not stream.valid.any():
            raise BagToolError(
                f'{info.path}: none of the {len(stream)} messages on {stream.topic} gives '
                f'the outputs {list(sensor.outputs)} of sensor {sensor.name!r} '
                f'(fields {list(sensor.fields)}): {stream.first_error}')
        if len(stream) == 0:
            raise BagToolError(f'{info.path}: bag has no messages on {stream.topic} '
                               f'(sensor {sensor.name!r} of vehicle {vehicle.name})')
        bad = int((~stream.valid).sum())
        if bad:
            recording.warnings.append(
                f'{stream.topic}: {bad} of {len(stream)} messages skipped '
                f'(first: {stream.first_error})')
    return recording


def _read_all(bag, topics, by_conn, progress, total):
    """Read the topics' messages once, in bag order, into their accumulators."""
    chunks = bag.message_chunks(topics)
    if chunks is not None:
        _read_chunks(chunks, by_conn, progress, total)
        return
    messages = bag.messages(topics)
    single = len({id(acc) for acc in by_conn.values()}) == 1
    # the batches hold many tuples: keep the cyclic garbage collector from scanning them
    # again and again (nothing read here forms reference cycles)
    enabled = gc.isenabled()
    gc.disable()
    try:
        _read_batches(messages, by_conn, single, progress, total)
    finally:
        if enabled:
            gc.enable()


def _read_chunks(chunks, by_conn, progress, total):
    """Read chunk by chunk, each chunk's messages decoded from its buffer (no bytes each)."""
    done = reported = 0
    for conns, logs, flat, starts, lengths in chunks:
        n = len(conns)
        ids = np.fromiter((c.id for c in conns), dtype=np.int64, count=n)
        seqs = np.arange(done, done + n, dtype=np.int64)
        for cid, acc in by_conn.items():
            sel = np.flatnonzero(ids == cid)
            if sel.size == n:
                acc.add_packed(flat, starts, lengths, logs, seqs)
            elif sel.size:
                acc.add_packed(flat, starts[sel], lengths[sel], logs[sel], seqs[sel])
        done += n
        if progress is not None and done - reported >= _PROGRESS_EVERY:
            progress(done, total)
            reported = done
    if progress is not None:
        progress(done, total)


def _read_batches(messages, by_conn, single, progress, total):
    """Read in batches; the bag position of a message is its index in the stream."""
    done = 0
    while True:
        batch = list(itertools.islice(messages, _PROGRESS_EVERY))
        if not batch:
            break
        conns, logs, raws = zip(*batch)
        n = len(batch)
        logs = np.array(logs, dtype=np.int64)
        seqs = np.arange(done, done + n, dtype=np.int64)
        if single:
            next(iter(by_conn.values())).add(raws, logs, seqs)
        else:
            ids = np.fromiter((c.id for c in conns), dtype=np.int64, count=n)
            for cid, acc in by_conn.items():
                sel = np.flatnonzero(ids == cid)
                if sel.size:
                    acc.add([raws[i] for i in sel.tolist()], logs[sel], seqs[sel])
        done += n
        if progress is not None:
            progress(done, total)
    if progress is not None:
        progress(done, total)
