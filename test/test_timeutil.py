# test/test_timeutil.py: one conversion between nanoseconds and seconds, scalar and array.
"""Stamps in seconds are the same floats whether converted one by one or as an array."""

import numpy as np
from observer_ros.bag.spill import SpilledColumn
from observer_ros.timeutil import ns_to_sec, ns_to_secs


NS = np.array([0, 1, 999_999_999, 1_700_000_000_123_456_789, 2**62 + 12345,
               -1_000_000_001, 10**18 + 1], dtype=np.int64)


def test_an_array_of_stamps_converts_as_each_stamp_does():
    secs = ns_to_secs(NS)
    assert secs.dtype == np.float64
    assert [float(s).hex() for s in secs] == [ns_to_sec(int(n)).hex() for n in NS]


def test_a_spilled_column_converts_as_its_array(tmp_path):
    col = SpilledColumn(np.int64, (), tmp_path)
    col.append(NS)
    assert ns_to_secs(col).tobytes() == ns_to_secs(NS).tobytes()
