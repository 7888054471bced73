# benchmarks/_common.py: what the benchmarks share (machine, statistics, ratio lines).
"""
Shared helpers of the observer_ros benchmarks.

Every figure is a ratio against a baseline measured in the same run: the two are
alternated (A B B A ...) and repeated, each repetition gives one ratio, and the
median and the spread (min..max) of those ratios are reported. A benchmark prints
one line per figure that starts with ``RATIO <id>`` (the smoke test looks for them)
and writes its figures as JSON for ``run_all.py``.

"""

import importlib.metadata
import json
import os
from pathlib import Path
import platform
import statistics
import time

__all__ = ['REPO', 'FLOOD_FALLBACK', 'machine_info', 'summary', 'ratio_line', 'write_json',
           'ros_env', 'common_parser', 'Timer', 'percentile', 'gyro_imu']

REPO = Path(__file__).resolve().parents[1]
# what a node logs when its flood watch left the events executor (nodes/callback_watch.py;
# its CPU per message then rises): said beside a run, whose figures are not those of the
# nodes' usual executor
FLOOD_FALLBACK = 'going on with the wait-set executor'
BENCH_DOMAIN_ID = '47'         # ROS_DOMAIN_ID of the benchmarks' DDS traffic (40..49)


def machine_info():
    """Return where the figures come from: cores, CPU model, python, package versions."""
    model = ''
    try:
        for line in Path('/proc/cpuinfo').read_text().splitlines():
            if line.startswith('model name'):
                model = line.split(':', 1)[1].strip()
                break
    except OSError:
        pass
    versions = {}
    for dist in ('numpy', 'scipy', 'control', 'rosbags', 'ros-jazzy-rclpy'):
        try:
            versions[dist] = importlib.metadata.version(dist)
        except importlib.metadata.PackageNotFoundError:
            versions[dist] = None
    try:
        affinity = len(os.sched_getaffinity(0))
    except AttributeError:
        affinity = os.cpu_count()
    return {
        'nproc': affinity,
        'cpu_count': os.cpu_count(),
        'cpu_model': model or platform.processor(),
        'python': platform.python_version(),
        'platform': platform.platform(),
        'versions': versions,
        'loadavg_at_start': list(os.getloadavg()),
        'date': time.strftime('%Y-%m-%d %H:%M:%S %Z'),
    }


def gyro_imu():
    """
    Return the Imu message P1 sends: the submarine's rate gyro (q), orientation unset.

    Only ``header.stamp`` and ``angular_velocity`` are set per message by the callers.

    """
    from sensor_msgs.msg import Imu      # not at the top: _common serves ROS-free tools too
    msg = Imu()
    msg.header.frame_id = 'base_link_frd'
    msg.orientation.w = 1.0
    msg.orientation_covariance[0] = -1.0
    msg.linear_acceleration_covariance[0] = -1.0
    msg.angular_velocity_covariance[4] = 1e-6
    return msg


def percentile(values, q):
    """Return the q-th percentile of values (q in 0..100), interpolated linearly."""
    xs = sorted(values)
    if not xs:
        return float('nan')
    pos = (len(xs) - 1) * q / 100.0
    lo = int(pos)
    hi = min(lo + 1, len(xs) - 1)
    return xs[lo] + (xs[hi] - xs[lo]) * (pos - lo)


def summary(values):
    """Median, min, max and count of a list of numbers."""
    values = [float(v) for v in values]
    if not values:
        return {'median': float('nan'), 'min': float('nan'), 'max': float('nan'), 'n': 0}
    return {'median': statistics.median(values), 'min': min(values), 'max': max(values),
            'n': len(values)}


def ratio_line(bench_id, name, ratios, op, target, unit='x', smoke=False, note=''):
    """
    Print the line of one figure and return its record.

    Parameters
    ----------
    bench_id : str
        P1, P2, ...
    name : str
        What the ratio is (``median_latency_observer/relay``).
    ratios : list of float
        One value per repetition (or a single value).
    op : {'<=', '>='}
        How the median is judged against the target.
    target : float or None
        None: a figure given for information (not judged).
    unit : str
        Printed after the values (``x`` for a ratio).
    smoke : bool
        Smoke run: the line is printed, the target is not judged.
    note : str
        Printed in brackets after the verdict (absolute figures).

    """
    s = summary(ratios)
    value = s['median']
    if target is None:
        met = None
        verdict = 'information'
        goal = 'no target'
    else:
        met = value <= target if op == '<=' else value >= target
        verdict = 'SMOKE (not judged)' if smoke else ('MET' if met else 'MISSED')
        goal = f'target {op} {target:g}{unit}'
    fmt = '.4f' if unit != 'x' else '.3f'
    if unit == '':
        fmt = '.6g'
    text = (f'RATIO {bench_id} {name} = {value:{fmt}}{unit} '
            f'[spread {s["min"]:{fmt}}..{s["max"]:{fmt}}, n={s["n"]}] {goal}: {verdict}')
    if note:
        text += f'  ({note})'
    print(text, flush=True)
    return {'id': bench_id, 'name': name, 'value': value, 'min': s['min'], 'max': s['max'],
            'n': s['n'], 'op': op, 'target': target, 'unit': unit,
            'met': None if smoke or met is None else bool(met), 'note': note}


def write_json(path, data):
    """Write a benchmark's figures (``--json PATH``)."""
    if path:
        Path(path).write_text(json.dumps(data, indent=2, default=float))


def log(text):
    """Print a benchmark's progress line at once (its output is read while it runs)."""
    print(text, flush=True)


def report(json_path, data):
    """Add the machine to a benchmark's figures and write them (``--json``); return 0."""
    data['machine'] = machine_info()
    write_json(json_path, data)
    return 0


def ros_env(domain_id=None):
    """Environment for the ROS processes of a benchmark: its own ROS_DOMAIN_ID, no colour."""
    env = dict(os.environ)
    env['ROS_DOMAIN_ID'] = str(domain_id or env.get('BENCH_ROS_DOMAIN_ID', BENCH_DOMAIN_ID))
    env.setdefault('RCUTILS_COLORIZED_OUTPUT', '0')
    env['PYTHONUNBUFFERED'] = '1'
    return env


def common_parser(description):
    """Return an argparse parser with ``--smoke`` and ``--json``."""
    import argparse
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument('--smoke', action='store_true',
                        help='a few seconds: check that the benchmark runs (targets not judged)')
    parser.add_argument('--json', metavar='PATH', help='write the figures as JSON')
    return parser


class Timer:
    """``with Timer() as t: ...`` then ``t.seconds`` (perf_counter)."""

    def __enter__(self):
        self._start = time.perf_counter()
        return self

    def __exit__(self, *exc):
        self.seconds = time.perf_counter() - self._start
        return False
