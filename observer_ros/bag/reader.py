# observer_ros.bag.reader: load a vehicle's topics from a ROS 2 bag as arrays.
"""
Load a vehicle's topics from a ROS 2 bag (mcap or sqlite3) as numpy arrays.

:func:`read_recording` opens the bag (:mod:`.bag_file`), finds the vehicle's topics
(:mod:`.bag_topics`), decodes the sensor messages in bulk (:mod:`.cdr_decode`) and keeps
each topic as a :class:`Stream` of arrays in bag order (with ``spill``, columns in
temporary files: :class:`~observer_ros.bag.spill.SpilledColumn`). Stamps stay integer
nanoseconds; seconds are ``ns * 1e-9`` exactly as
:func:`observer_ros.timeutil.stamp_to_sec` computes them. The names of those modules
are importable from here too.

"""

from dataclasses import dataclass, field
import gc
import itertools
from typing import Dict, List, Optional, Tuple

import numpy as np

from .bag_file import bag_info, BagInfo, BagReader, jazzy_typestore
from .bag_topics import normalize_namespace, resolve_topics, TopicMap, VEHICLE_TOPICS
from .cdr_decode import CLOCK, decode_messages, decode_packed, Decoded, FLOAT64, IMU, JOINT_STATE
from .errors import BagToolError
from .spill import count_true, spill_folder, SpilledColumn
from ..core.errors import ObserverError
from ..core.estimators.admission import stamp_ns
from ..sensors import vector_from_joint_state
from ..timeutil import ns_to_secs

__all__ = ['IMU', 'JOINT_STATE', 'FLOAT64', 'CLOCK', 'VEHICLE_TOPICS', 'jazzy_typestore',
           'normalize_namespace', 'BagInfo', 'BagReader', 'bag_info', 'TopicMap',
           'resolve_topics', 'Decoded', 'decode_messages', 'Stream', 'Recording',
           'read_recording']

_FLUSH = 1 << 16            # decode a topic's raw messages every this many (bounds memory)
_INT32_LIMIT = 1 << 31
_PROGRESS_EVERY = 1 << 16   # call the progress callback every this many messages


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
        return ns_to_secs(self.stamp_ns)

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
                 seq_dtype=np.int64, spill=None):
        self.topic, self.msgtype, self.names = topic, msgtype, tuple(names)
        self.fields, self.mode, self.fallback = tuple(fields), mode, fallback
        self.raws, self.logs, self.seqs = [], [], []
        self.expected, self.seq_dtype = int(expected), seq_dtype
        self.spill = spill          # None: in memory; else the columns in temporary files
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
                self.cols[0] = _retyped(self.cols[0], np.int64)
        if self.spill is not None:
            self._append(seqs, logs, dec)
            return
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

    def _append(self, seqs, logs, dec):
        """Append the decoded columns to their temporary files."""
        if self.cols is None:
            folder = spill_folder(self.spill)
            self.cols = [SpilledColumn(self.seq_dtype, (), folder),
                         SpilledColumn(np.int64, (), folder),
                         None if dec.stamp_ns is None else SpilledColumn(np.int64, (), folder),
                         SpilledColumn(np.float64, (len(self.fields),), folder),
                         SpilledColumn(bool, (), folder)]
        stamps = logs if self.cols[2] is None else dec.stamp_ns
        for col, part in zip(self.cols, (seqs, logs, stamps, dec.values, dec.valid)):
            if col is not None:
                col.append(part)
        self.n += len(seqs)
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
                for c in self.cols]     # a spilled column holds its rows alone
        seq, log, stamp, values, valid = cols
        has_header = stamp is not None
        # without a header the stamp is the receive time: the same array, not a copy
        return Stream(self.topic, self.msgtype, self.names, seq, log,
                      stamp if has_header else log, values, valid, has_header,
                      self.first_error, self.bulk)


def _retyped(col, dtype):
    """Return a column (array or spilled) converted to ``dtype``."""
    if not isinstance(col, SpilledColumn):
        return col.astype(dtype)
    out = SpilledColumn(dtype, col.row_shape, col.directory)
    for lo in range(0, col.rows, 1 << 16):
        out.append(col[lo:lo + (1 << 16)])
    return out


def _resized(col, size):
    out = np.empty((size,) + col.shape[1:], dtype=col.dtype)
    out[:col.shape[0]] = col
    return out


def _sensor_fallback(bag, sensor):
    from ..sensors import extract_measurement

    def decode(raw):
        msg = bag.deserialize(raw, sensor.msg_type)
        header = getattr(msg, 'header', None)
        stamp = stamp_ns(header.stamp.sec, header.stamp.nanosec) if header is not None \
            else None
        return stamp, extract_measurement(msg, sensor)
    return decode


def _vector_fallback(bag, names, mode, topic):
    def decode(raw):
        msg = bag.deserialize(raw, JOINT_STATE)
        stamp = stamp_ns(msg.header.stamp.sec, msg.header.stamp.nanosec)
        if mode == 'vector':            # judged as the nodes judge it
            try:
                return stamp, vector_from_joint_state(msg, names, topic)
            except ObserverError as err:
                raise ValueError(str(err)) from None
        # partial (residuals): the components the message has, NaN for the others
        position = np.asarray(msg.position, dtype=float)
        index = {}
        for i, n in enumerate(msg.name):
            index.setdefault(n, i)      # a repeated name: its first position
        out = np.full(len(names), np.nan)
        for j, n in enumerate(names):
            if n in index and index[n] < len(position):
                out[j] = position[index[n]]
        return stamp, out
    return decode


def read_recording(path, vehicle, namespace=None, progress=None, vectors=True, spill=None):
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
    spill : True or path, optional
        Keep the decoded columns in temporary files (in this folder; True: the system's
        temporary folder) instead of in memory: the streams' columns are then
        :class:`~observer_ros.bag.spill.SpilledColumn` objects with the same values, and
        the memory of reading does not grow with the bag.

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
            return info.topics.get(topic, (None, 0))[1], seq_dtype, spill
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
                    _vector_fallback(bag, names, mode, topic), *sizes(topic)))
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
        good = count_true(stream.valid)
        if len(stream) and not good:
            raise BagToolError(
                f'{info.path}: none of the {len(stream)} messages on {stream.topic} gives '
                f'the outputs {list(sensor.outputs)} of sensor {sensor.name!r} '
                f'(fields {list(sensor.fields)}): {stream.first_error}')
        if len(stream) == 0:
            raise BagToolError(f'{info.path}: bag has no messages on {stream.topic} '
                               f'(sensor {sensor.name!r} of vehicle {vehicle.name})')
        bad = len(stream) - good
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
