# test/bag/test_bag_integrity.py: chunk CRCs in the bags observer_ros writes, and their check.
"""
Integrity: the bags this project writes carry chunk CRCs; the evaluation checks them.

A bag written by rosbags' own Writer has every chunk CRC 0 (no checksum), and the
evaluation says so; :class:`~observer_ros.bag.integrity.CrcWriter` writes the CRC32 of
each chunk, the file still opens with rosbags, and a value changed on disk is refused
with a clear error by ``observer-eval`` (exit 2, one ``error:`` line).

"""

from binascii import crc32
import contextlib
import io
from pathlib import Path
import shutil

from bag_synth import bag_file, CONFIG, simulate, STORE, write_bag
import numpy as np
from observer_ros.bag.errors import BagToolError
from observer_ros.bag.integrity import chunk_crcs, CRC_OFFSET, CrcWriter
from observer_ros.bag.reader import BagReader
from observer_ros.evaluation.evaluate import main
from observer_ros.evaluation.evaluator import evaluate_bag
from observer_ros.vehicle import load_vehicle
import pytest
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin
from rosbags.rosbag2.storage_mcap import McapReader

VEHICLE = CONFIG / 'submarine.yaml'
SAMPLES = Path(__file__).resolve().parents[2] / 'bags' / 'samples'


@pytest.fixture(scope='module')
def run():
    # long enough for several 1 MiB chunks
    return simulate(load_vehicle(VEHICLE), steps=6000)


@pytest.fixture(scope='module')
def written(run, tmp_path_factory):
    """Return the run written as a plain and a CRC mcap bag, once (copy before changing)."""
    root = tmp_path_factory.mktemp('written')
    return {'plain': write_bag(root / 'plain' / 'bag', run['messages']),
            'crc': write_bag(root / 'crc' / 'bag', run['messages'], writer_class=CrcWriter)}


def _copy(bag, to):
    """Return a copy of a bag folder at ``to`` (a test changes its copy)."""
    return Path(shutil.copytree(bag, to))


def _chunks(path):
    reader = McapReader(bag_file(path))
    reader.open()
    try:
        crcs = chunk_crcs(reader)
        datas = []
        for chunk in reader.chunks:
            reader.bio.seek(chunk.chunk_start_offset + 9 + 40 + len(chunk.compression))
            datas.append((chunk, reader.bio.read(chunk.compressed_size)))
        return crcs, datas
    finally:
        reader.close()


def _messages(path):
    with AnyReader([Path(path)], default_typestore=STORE) as reader:
        return [(c.topic, t, bytes(raw)) for c, t, raw in reader.messages()]


def test_crc_writer_writes_each_chunks_crc32_and_is_otherwise_rosbags_file(written):
    plain, crc = written['plain'], written['crc']
    crcs, datas = _chunks(crc)
    assert len(crcs) >= 2
    for value, (chunk, data) in zip(crcs, datas):
        assert chunk.compression == ''
        assert value == crc32(data) != 0
    assert chunk_crcs_of(plain) == [0] * len(crcs)
    # the same file byte for byte but the 4 CRC bytes of each chunk
    a = bytearray(bag_file(plain).read_bytes())
    b = bag_file(crc).read_bytes()
    assert len(a) == len(b)
    for chunk, _ in datas:
        at = chunk.chunk_start_offset + CRC_OFFSET
        a[at:at + 4] = b[at:at + 4]
    assert bytes(a) == b
    # rosbags opens it (and checks the CRCs) and reads the same messages
    assert _messages(crc) == _messages(plain)


def chunk_crcs_of(path):
    return _chunks(path)[0]


def test_crc_writer_compressed_chunks_open_with_rosbags(tmp_path):
    path = tmp_path / 'zstd'
    writer = CrcWriter(path, version=9, storage_plugin=StoragePlugin.MCAP)
    writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    kind = 'std_msgs/msg/Float64MultiArray'
    with writer:            # 8 KiB messages: a chunk (1 MiB before compression) each 128
        conn = writer.add_connection('/x', kind, typestore=STORE)
        for i in range(300):
            msg = STORE.types[kind](layout=STORE.types['std_msgs/msg/MultiArrayLayout'](
                dim=[], data_offset=0), data=np.arange(1024, dtype=np.float64) + i)
            writer.write(conn, i + 1, STORE.serialize_cdr(msg, kind))
    crcs, _ = _chunks(path)
    assert all(crcs) and len(crcs) >= 2
    for i, (_, _, raw) in enumerate(_messages(path)):
        np.testing.assert_array_equal(STORE.deserialize_cdr(raw, kind).data,
                                      np.arange(1024, dtype=np.float64) + i)
    assert i == 299


def test_evaluation_says_when_a_bag_has_no_crcs(tmp_path, run, written):
    plain, crc = written['plain'], written['crc']
    res_plain = evaluate_bag(plain, VEHICLE)
    res_crc = evaluate_bag(crc, VEHICLE)
    assert any('no chunk CRCs' in w for w in res_plain.warnings)
    assert not any('CRC' in w for w in res_crc.warnings)
    # the same numbers either way
    for name, vr in res_crc.variants.items():
        np.testing.assert_array_equal(vr.x_hat, res_plain.variants[name].x_hat)
    sq = write_bag(tmp_path / 'sq', run['messages'], storage='sqlite3')
    with BagReader(sq) as bag:
        assert any('no chunk checksums' in w for w in bag.info.warnings)


def _change_one_value(path):
    """Change one float64 of a sensor message inside the bag's second chunk."""
    crcs, datas = _chunks(path)
    chunk, data = datas[1]
    with AnyReader([Path(path)], default_typestore=STORE) as reader:
        for conn, t, raw in reader.messages():
            if conn.topic.endswith('state/true') and chunk.message_start_time < t:
                target = bytes(raw)[-24:]        # the last three position values
                break
    at = data.find(target)
    assert at > 0
    start = chunk.chunk_start_offset + 9 + 40 + len(chunk.compression) + at
    f = bag_file(path)
    blob = bytearray(f.read_bytes())
    value = np.frombuffer(bytes(blob[start:start + 8]), '<f8')[0]
    blob[start:start + 8] = np.array([value * 1.5 + 1.0], '<f8').tobytes()
    f.write_bytes(bytes(blob))


def test_a_changed_value_is_detected_with_a_clear_error(tmp_path, written):
    crc = _copy(written['crc'], tmp_path / 'crc')
    _change_one_value(crc)
    with pytest.raises(BagToolError, match='checksum mismatch.*CRC32 does not match'):
        evaluate_bag(crc, VEHICLE)
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        code = main([str(crc), '--vehicle', str(VEHICLE), '--out', str(tmp_path / 'o'),
                     '--no-plots', '--no-bag'])
    assert code == 2
    lines = err.getvalue().strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith('error: ')
    assert bag_file(crc).name in lines[0] and 'checksum mismatch' in lines[0]
    # without CRCs the same change is read silently (what the note warns about)
    plain = _copy(written['plain'], tmp_path / 'plain')
    _change_one_value(plain)
    res = evaluate_bag(plain, VEHICLE)
    assert any('no chunk CRCs' in w for w in res.warnings)


def test_results_bag_carries_crcs(tmp_path):
    out = tmp_path / 'out'
    with contextlib.redirect_stdout(io.StringIO()):
        code = main([str(SAMPLES / 'submarine'), '--vehicle', str(VEHICLE), '--out', str(out),
                     '--no-plots'])
    assert code == 0
    crcs = chunk_crcs_of(out / 'results_bag')
    assert crcs and all(crcs)
    assert _messages(out / 'results_bag')
