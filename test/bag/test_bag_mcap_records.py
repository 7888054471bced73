# test/bag/test_bag_mcap_records.py: the MCAP parser against rosbags' own reader and on damage.
"""
observer_ros.bag.mcap_records: records, chunks and CRCs of MCAP files.

The parser finds in each chunk of a sample bag the messages rosbags counts, decompresses
zstd and lz4 chunks as written by rosbags, and reports a changed byte, a wrong size and
a record cut short as ValueError naming what is wrong.

"""

from pathlib import Path

from bag_synth import JOINT_STATE, STORE, vector_msg
import numpy as np
from observer_ros.bag import mcap_records as mr
import pytest
from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer
from rosbags.rosbag2.storage_mcap import McapReader

SAMPLES = Path(__file__).resolve().parents[2] / 'bags' / 'samples'


def _mcap(bag):
    return next(Path(bag).glob('*.mcap'))


def _write(path, zstd=False, n=3000):
    w = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
    if zstd:
        w.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    with w:
        conn = w.add_connection('/control/u', JOINT_STATE, typestore=STORE)
        for k in range(n):
            msg = vector_msg(['a', 'b'], np.full(100, float(k)), k * 1_000_000)
            w.write(conn, k * 1_000_000, STORE.serialize_cdr(msg, JOINT_STATE))
    return _mcap(path)


def _chunks_of(path):
    reader = McapReader(path)
    reader.open()
    try:
        with path.open('rb') as f:
            return [(c, mr.read_chunk(f, c.chunk_start_offset, c.compression,
                                      c.compressed_size, c.uncompressed_size))
                    for c in reader.chunks]
    finally:
        reader.close()


def test_every_chunk_of_a_sample_bag_holds_the_messages_rosbags_counts():
    bag = next(p for p in sorted(SAMPLES.iterdir()) if list(p.glob('*.mcap')))
    reader = McapReader(_mcap(bag))
    reader.open()
    try:
        expected = sum(int(c.msgcount) for c in reader.connections)
    finally:
        reader.close()
    found = 0
    for chunk, records in _chunks_of(_mcap(bag)):
        off = mr.message_offsets(records)
        channel, log, _ = mr.message_fields(np.frombuffer(records, np.uint8), off)
        assert set(channel.tolist()) <= set(chunk.channel_count)
        if off.size:
            assert chunk.message_start_time <= log.min() <= log.max() <= chunk.message_end_time
        found += off.size
    assert found == expected > 0


def test_compressed_chunks_decompress_to_their_messages(tmp_path):
    chunks = _chunks_of(_write(tmp_path / 'bag', zstd=True))
    assert len(chunks) > 1 and {c.compression for c, _ in chunks} == {'zstd'}
    assert sum(mr.message_offsets(records).size for _, records in chunks) == 3000
    records = chunks[0][1]          # lz4 (rosbags writes zstd only): a frame of the records
    import lz4.frame
    packed = lz4.frame.compress(records)
    assert mr.decompress_chunk(packed, 'lz4', len(records), mr.chunk_crc(records)) == records


def test_a_changed_byte_a_wrong_size_and_a_cut_record_are_named(tmp_path):
    path = _write(tmp_path / 'bag')
    chunk, records = _chunks_of(path)[0]
    crc = mr.chunk_crc(records)
    assert mr.decompress_chunk(records, '', len(records), crc) == records
    changed = bytearray(records)
    changed[-1] ^= 0xFF
    with pytest.raises(ValueError, match='checksum mismatch'):
        mr.decompress_chunk(bytes(changed), '', len(records), crc)
    assert mr.decompress_chunk(bytes(changed), '', len(records), 0) == bytes(changed)
    with pytest.raises(ValueError, match='size mismatch'):
        mr.decompress_chunk(records, '', len(records) + 1)
    with pytest.raises(ValueError, match='unsupported chunk compression'):
        mr.decompress_chunk(records, 'bz2', len(records))
    with pytest.raises(ValueError, match='truncated record'):
        list(mr.iter_records(records[:-1]))
    with pytest.raises(ValueError, match='truncated record'):
        list(mr.iter_records(records + b'\x05\x00'))
