# test_bag_mcap_fast: the chunk-by-chunk MCAP reader gives exactly rosbags' message stream.
"""observer_ros.bag.mcap_fast against rosbags' own Reader.messages."""

from pathlib import Path

from bag_synth import blank, JOINT_STATE, STORE, vector_msg
import numpy as np
from observer_ros.bag.mcap_fast import fast_chunks, fast_messages
from observer_ros.bag.reader import BagReader, read_recording
from observer_ros.vehicle import load_vehicle
import pytest
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from rosbags.rosbag2.enums import CompressionFormat, CompressionMode

SAMPLES = Path(__file__).resolve().parents[2] / 'bags' / 'samples'


def _stream(messages):
    return [(c.id, c.topic, t, bytes(raw)) for c, t, raw in messages]


def _write(path, entries, compress=False):
    """
    entries: (topic, log_ns, value) as JointState vectors of 2000 values (16 kB).

    rosbags closes a chunk after 1 MiB, so 70 messages make a chunk.
    """
    writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
    if compress:
        writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    with writer:
        conns = {}
        for topic, ns, value in entries:
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, JOINT_STATE, typestore=STORE)
            msg = vector_msg(['a'], np.full(2000, value), ns)
            writer.write(conns[topic], ns, STORE.serialize_cdr(msg, JOINT_STATE))
    return path


def _flatten(chunks):
    """Yield the (connection, log_ns, raw) stream of fast_chunks' arrays."""
    for conns, logs, flat, starts, lengths in chunks:
        assert flat.size >= int((starts + lengths).max()) + 512      # the padding
        for c, t, b, n in zip(conns, logs.tolist(), starts.tolist(), lengths.tolist()):
            yield c, t, flat[b:b + n].tobytes()


def _compare(path, start=None, topics=None):
    with Reader(path) as reader:
        conns = [c for c in reader.connections if topics is None or c.topic in topics]
        fast = fast_messages(reader, conns, start)
        assert fast is not None
        got = _stream(fast)
        chunked = _stream(_flatten(fast_chunks(reader, conns, start)))
        want = _stream(reader.messages(connections=conns, start=start))
    assert got == want
    assert chunked == want
    return got


@pytest.mark.parametrize('name', ['submarine', 'cart_pendulum'])
def test_samples_same_stream_as_rosbags(name):
    path = SAMPLES / name
    if not path.exists():
        pytest.skip(f'{path} not present')
    got = _compare(path)
    assert len(got) > 1000
    mid = got[len(got) // 2][2]
    with Reader(path) as reader:
        one = [reader.connections[0].topic]
    _compare(path, start=mid, topics=one)


@pytest.mark.parametrize('compress', [False, True], ids=['plain', 'zstd'])
def test_many_chunks_ties_and_unsorted_chunks(tmp_path, compress):
    # log times that tie across topics and go back inside a chunk: rosbags sorts each
    # chunk stably by log time; the fast reader must give the same order
    rng = np.random.default_rng(0)
    entries = []
    for k in range(600):
        ns = 1_000_000_000 + 1000 * k
        entries.append(('/a', ns, float(k)))
        entries.append(('/b', ns, float(-k)))
        if k % 7 == 0:
            entries.append(('/c', ns - int(rng.integers(0, 500)), 0.5))   # back in time
    path = _write(tmp_path / 'bag', entries, compress)
    with Reader(path) as reader:
        assert len(reader.storage.storages[0].chunks) > 10
    got = _compare(path)
    assert len(got) == len(entries)
    _compare(path, start=1_000_000_000 + 1000 * 300 + 3, topics=['/b', '/c'])


def test_overlapping_chunks_are_left_to_rosbags(tmp_path):
    # a message far back in time in a later chunk makes the chunks overlap: rosbags
    # merges them, so the fast reader declines
    entries = [('/a', 2_000_000_000 + 1000 * k, float(k)) for k in range(200)]
    entries.append(('/a', 1_000_000_000, -1.0))
    path = _write(tmp_path / 'bag', entries)
    with Reader(path) as reader:
        assert fast_messages(reader, list(reader.connections)) is None
    with BagReader(path) as bag:          # BagReader falls back to rosbags: same stream
        got = [(c.topic, t) for c, t, _ in bag.messages()]
    assert got[0] == ('/a', 1_000_000_000) and len(got) == 201


def test_blank_sensor_messages_round_trip(tmp_path):
    path = tmp_path / 'bag'
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conn = writer.add_connection('/imu', 'sensor_msgs/msg/Imu', typestore=STORE)
        for k in range(100):
            msg = blank('sensor_msgs/msg/Imu', 1_000_000_000 + k, 'imu')
            writer.write(conn, 1_000_000_000 + k, STORE.serialize_cdr(msg, 'sensor_msgs/msg/Imu'))
    assert len(_compare(path)) == 100


@pytest.mark.parametrize('name', ['submarine', 'cart_pendulum', 'submarine_reduced'])
def test_recording_read_by_chunks_equals_message_by_message(name, monkeypatch):
    """read_recording decodes chunk buffers directly; the result must not change."""
    path = SAMPLES / name
    vehicle = load_vehicle(Path(__file__).resolve().parents[2] / 'config' / f'{name}.yaml')
    calls = []
    real = BagReader.message_chunks

    def spy(self, topics=None):
        chunks = real(self, topics)
        calls.append(chunks is not None)
        return chunks
    monkeypatch.setattr(BagReader, 'message_chunks', spy)
    by_chunks = read_recording(path, vehicle)
    assert calls == [True]
    monkeypatch.setattr(BagReader, 'message_chunks', lambda self, topics=None: None)
    by_message = read_recording(path, vehicle)
    pairs = [(by_chunks.sensors[k], by_message.sensors[k]) for k in by_chunks.sensors]
    pairs += [(getattr(by_chunks, k), getattr(by_message, k))
              for k in ('truth', 'estimate', 'command', 'residual')]
    for a, b in pairs:
        if a is None:
            assert b is None
            continue
        assert len(a) > 100
        for field in ('seq', 'log_ns', 'stamp_ns', 'valid'):
            assert np.array_equal(getattr(a, field), getattr(b, field)), (a.topic, field)
        assert np.array_equal(a.values, b.values, equal_nan=True), a.topic
