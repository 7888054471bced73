# observer_ros.bag.vectors: read a named-vector topic (JointState) out of a bag.
"""Read JointState vector topics (true state, estimate, command) from a bag as arrays."""

from pathlib import Path

import numpy as np
from rosbags.highlevel import AnyReader
from rosbags.typesys import get_typestore, Stores

from ..core.errors import ObserverError
from ..timeutil import stamp_to_sec

__all__ = ['read_vector_topic']


def read_vector_topic(bag_path, topic, names):
    """
    Return (t, X) of a JointState topic, components ordered as ``names``.

    Parameters
    ----------
    bag_path : path
        Bag directory or storage file.
    topic : str
        Absolute topic name.
    names : sequence of str
        Component names to read, in order.

    Returns
    -------
    t : (N,) ndarray
        header stamps in seconds, in increasing order (ties keep bag order).
    X : (N, len(names)) ndarray

    """
    store = get_typestore(Stores.ROS2_JAZZY)
    try:
        with AnyReader([Path(bag_path)], default_typestore=store) as reader:
            conns = [c for c in reader.connections if c.topic == topic]
            times, rows = [], []
            for conn, _, raw in reader.messages(connections=conns):
                msg = reader.deserialize(raw, conn.msgtype)
                index = {n: i for i, n in enumerate(msg.name)}
                if any(n not in index for n in names):
                    continue
                times.append(stamp_to_sec(msg.header.stamp))
                rows.append([msg.position[index[n]] for n in names])
    except Exception as err:   # noqa: BLE001 - rosbags raises several types
        raise ObserverError(f'{bag_path}: cannot read {topic}: {err}') from None
    # stamp order: a transient-local history sample can arrive after newer live ones
    times = np.array(times)
    order = np.argsort(times, kind='stable')
    return times[order], np.array(rows, dtype=float).reshape(len(rows), len(names))[order]
