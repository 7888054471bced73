# observer_ros.timeutil: one conversion between ROS stamps and seconds, used everywhere.
"""Stamp conversions shared by the nodes and the bag tools (no ROS imports)."""

__all__ = ['stamp_to_sec', 'stamp_to_ns', 'sec_to_stamp_parts', 'ns_to_sec', 'ns_to_secs',
           'stamp_sec']


def stamp_to_ns(stamp):
    """Return integer nanoseconds of a stamp with ``sec`` and ``nanosec`` attributes."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def ns_to_sec(ns):
    """Return float seconds of integer nanoseconds (the one conversion used everywhere)."""
    return int(ns) * 1e-9


def ns_to_secs(ns):
    """
    Return float seconds of an array of integer nanoseconds, each as :func:`ns_to_sec`.

    ``ns`` is anything with numpy's ``astype`` (an int64 array, a spilled column).
    """
    return ns.astype('float64') * 1e-9


def stamp_to_sec(stamp):
    """Return float seconds of a stamp (rclpy or rosbags message)."""
    return ns_to_sec(stamp_to_ns(stamp))


def stamp_sec(t):
    """Return t seconds as a receiver reads it back from a stamp (rounded to the nanosecond)."""
    return ns_to_sec(round(float(t) * 1e9))


def sec_to_stamp_parts(t):
    """Return (sec, nanosec) for t seconds, rounded to the nearest nanosecond."""
    ns = int(round(float(t) * 1e9))
    return ns // 1_000_000_000, ns % 1_000_000_000
