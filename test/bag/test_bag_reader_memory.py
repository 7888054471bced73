# test/bag/test_bag_reader_memory.py: what read_recording keeps per message.
"""
The recording holds each message once, in narrow exact dtypes.

Each stream's columns are filled in place, sized by the bag's index (grown when the bag
has more messages than it says), so reading does not hold a stream twice; a message's
bag position is int32; a message without a header shares its receive times as stamps.
The streams are the same whichever way they are filled, and the same in temporary files
(``spill``). What reading keeps per message, in memory and spilled, is measured by
benchmarks/m1_memory.py.

"""

from bag_cases import p3_benchmark
from bag_synth import CONFIG
import numpy as np
from numpy.testing import assert_array_equal
from observer_ros.bag import reader as reader_mod
from observer_ros.bag.reader import read_recording
from observer_ros.bag.spill import SpilledColumn
from observer_ros.vehicle import load_vehicle
import pytest

SAMPLES = CONFIG.parent / 'bags' / 'samples'
FIELDS = ('seq', 'log_ns', 'stamp_ns', 'values', 'valid')


def test_bag_reader_keeps_narrow_exact_dtypes(tmp_path):
    # the bytes this keeps per message, in memory and spilled: benchmarks/m1_memory.py
    veh = load_vehicle(CONFIG / 'submarine.yaml')
    bag = p3_benchmark().generate(3000, data=tmp_path, log=lambda *a: None)
    gyro = read_recording(bag, veh).sensors['gyro']
    assert len(gyro) == 3000
    assert gyro.seq.dtype == np.int32 and gyro.stamp_ns.dtype == np.int64
    assert gyro.log_ns.dtype == np.int64 and gyro.valid.dtype == np.bool_
    arrays = bag.parent / 'arrays'                     # what the generator wrote
    assert_array_equal(gyro.stamp_ns, np.load(arrays / 'stamp_ns.npy'))
    assert_array_equal(gyro.values[:, 0], np.load(arrays / 'y.npy').reshape(-1))
    assert np.all(np.diff(gyro.seq) > 0) and gyro.valid.all()


@pytest.mark.parametrize('name', ['submarine', 'cart_pendulum', 'submarine_reduced'])
def test_bag_reader_streams_do_not_depend_on_the_index_counts(name, monkeypatch):
    veh = load_vehicle(CONFIG / f'{name}.yaml')
    ref = read_recording(SAMPLES / name, veh)
    made = reader_mod._Accumulator.__init__

    def wrong(self, *args, expected=0, seq_dtype=np.int64):
        made(self, *args[:6], expected=1, seq_dtype=np.int64)  # the index says 1
    monkeypatch.setattr(reader_mod._Accumulator, '__init__', wrong)
    got = read_recording(SAMPLES / name, veh)
    assert [k for k, _ in got.streams()] == [k for k, _ in ref.streams()]
    for (key, a), (_, b) in zip(got.streams(), ref.streams()):
        assert len(a) == len(b) > 1, key
        for field in FIELDS:
            assert_array_equal(getattr(a, field), getattr(b, field), err_msg=f'{key} {field}')
        assert (a.first_error, a.bulk, a.has_header) == (b.first_error, b.bulk, b.has_header)
        assert a.seq.dtype == np.int64 and b.seq.dtype == np.int32


@pytest.mark.parametrize('name', ['submarine', 'cart_pendulum', 'submarine_reduced'])
def test_bag_reader_spilled_streams_equal_the_in_memory_ones(name, tmp_path):
    veh = load_vehicle(CONFIG / f'{name}.yaml')
    ref = read_recording(SAMPLES / name, veh)
    got = read_recording(SAMPLES / name, veh, spill=tmp_path)
    assert [k for k, _ in got.streams()] == [k for k, _ in ref.streams()]
    for (key, a), (_, b) in zip(got.streams(), ref.streams()):
        assert len(a) == len(b) > 1, key
        for field in FIELDS:
            have = getattr(a, field)
            assert isinstance(have, SpilledColumn), f'{key} {field}'
            assert have.dtype == getattr(b, field).dtype, f'{key} {field}'
            assert_array_equal(np.asarray(have), getattr(b, field), err_msg=f'{key} {field}')
        assert (a.first_error, a.bulk, a.has_header) == (b.first_error, b.bulk, b.has_header)
    assert got.warnings == ref.warnings
    assert list(tmp_path.iterdir()) == []          # the files have no name on disk
