# benchmarks/flood_observer.py: the observer node's memory and /diagnostics under a flood.
"""
The observer under a measurement flood (not part of CI; figures in docs/reliability.md).

The observer runs as its own process (the submarine's vehicle file, realtime mode, wall
clock, ``diagnostics_period`` 1 s). After ``--before`` s, ``test/nodes/flood_publisher.py`` (its
own process) publishes Imu on ``imu/data`` as fast as Python can for ``--seconds`` s, while
this script publishes the gyro at 20 Hz on the same topic and listens to /diagnostics. It
reports:

- the observer's VmRSS (/proc/PID/status), sampled every second: before the flood (the
  baseline of the same run), the largest, at the end, and the growth over the flood's
  last ``--window`` s (flat: within 10 MB over 60 s);
- the gaps between the observer's /diagnostics reports (their header stamps) during the
  flood, against the period;
- what the observer said (``flooded``, ``late``, the counters ``flood_dropped``,
  ``flood_episodes``) and the flood's rate;
- how soon after the flood's process ended it said ``estimating`` again, and what it said
  over the ``--after`` s that follow.

Usage::

    .venv/bin/python benchmarks/flood_observer.py [--seconds 60] [--executor events]

ROS_DOMAIN_ID is ``--domain`` (default 75).

"""

import argparse
import os
from pathlib import Path
import signal
import subprocess
import sys
import time
import warnings

REPO = Path(__file__).resolve().parents[1]
FLOOD = REPO / 'test' / 'nodes' / 'flood_publisher.py'
sys.path.insert(0, str(REPO / 'benchmarks'))   # benchmarks/ is not a package

from soak_observer import rss_kib  # noqa: E402


def main(argv=None):
    """Run the flood; print the figures."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--seconds', type=float, default=60.0, help='the flood (s)')
    parser.add_argument('--before', type=float, default=10.0, help='s before the flood')
    parser.add_argument('--after', type=float, default=10.0, help='s after the flood')
    parser.add_argument('--window', type=float, default=60.0,
                        help="the growth is measured over the flood's last WINDOW s")
    parser.add_argument('--executor', default='events', choices=('events', 'single_threaded'))
    parser.add_argument('--domain', type=int, default=75)
    args = parser.parse_args(argv)
    warnings.filterwarnings('ignore', category=DeprecationWarning)
    env = dict(os.environ, ROS_DOMAIN_ID=str(args.domain), PYTHONUNBUFFERED='1',
               OBSERVER_ROS_EXECUTOR=args.executor)
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import Imu

    from observer_ros.nodes.common import SENSOR_QOS
    from observer_ros.timeutil import stamp_to_sec
    from observer_ros.tools.run_closed_loop import node_command, stop_process
    log = open(os.devnull, 'w')
    observer = subprocess.Popen(node_command('observer_node', REPO / 'config' / 'submarine.yaml',
                                             'simulator.mode:=realtime'),
                                env=env, stdout=log, stderr=subprocess.STDOUT)
    rclpy.init(domain_id=args.domain)
    node = rclpy.create_node('flood_driver')
    reports = []

    def on_diag(msg):
        for s in msg.status:
            if s.name.endswith('/observer'):
                reports.append((time.monotonic(), stamp_to_sec(msg.header.stamp), s.message,
                                {kv.key: kv.value for kv in s.values}))
    node.create_subscription(DiagnosticArray, '/diagnostics', on_diag, 100)
    pub = node.create_publisher(Imu, 'imu/data', SENSOR_QOS)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    while not reports:                      # the observer is up and heard
        executor.spin_once(timeout_sec=0.1)
    start = time.monotonic()
    flood_at = start + args.before
    flood = None
    flood_end = None
    rss = []
    next_imu = next_rss = start
    try:
        while True:
            now = time.monotonic()
            if flood is None and now >= flood_at:
                flood = subprocess.Popen([sys.executable, '-W', 'ignore', str(FLOOD),
                                          'imu/data', str(args.seconds)],
                                         env=env, stdout=subprocess.PIPE, text=True)
                flood_at = now
            if flood is not None and flood_end is None and flood.poll() is not None:
                flood_end = now
            if flood_end is not None and now > flood_end + args.after:
                break
            if now >= next_imu:
                msg = Imu()
                msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(time.time_ns(),
                                                                        1_000_000_000)
                pub.publish(msg)
                next_imu += 0.05
            if now >= next_rss:
                rss.append((now - flood_at if flood else now - start - args.before,
                            rss_kib(observer.pid)))
                next_rss += 1.0
            executor.spin_once(timeout_sec=0.01)
        out = flood.stdout.read().strip()
    finally:
        if flood is not None and flood.poll() is None:
            flood.send_signal(signal.SIGINT)
            flood.wait()
        stop_process(observer)
        node.destroy_node()
        rclpy.try_shutdown()
    base = [k for t, k in rss if t < 0 and k]
    during = [(t, k) for t, k in rss if 0 <= t <= args.seconds and k]
    last = [k for t, k in during if t >= args.seconds - args.window]
    flood_reports = [r for r in reports if flood_at <= r[0] <= flood_at + args.seconds]
    gaps = [b[1] - a[1] for a, b in zip(flood_reports, flood_reports[1:])]
    said = sorted({r[2].split(':')[0] for r in flood_reports})
    final = reports[-1][3] if reports else {}
    print(f'executor {args.executor}; flood: {out}; load average {os.getloadavg()[0]:.1f}')
    print(f'VmRSS before the flood {base[-1]} KiB; largest during it '
          f'{max(k for _, k in during)} KiB (+{max(k for _, k in during) - base[-1]}); '
          f'growth over its last {args.window:g} s {max(last) - min(last)} KiB '
          f'(end {during[-1][1]} KiB)')
    print('VmRSS every 10 s of the flood (KiB): ' + ', '.join(
        f'{t:.0f} s {k}' for t, k in during if round(t) % 10 == 0))
    print(f'/diagnostics during the flood: {len(flood_reports)} reports, gaps '
          f'median {sorted(gaps)[len(gaps) // 2]:.2f} s, largest {max(gaps):.2f} s '
          f'(period 1 s); said: {said}')
    back = next((r[0] for r in reports if r[0] > flood_end and r[2] == 'estimating'), None)
    back_text = (f'`estimating` again after {back - flood_end:.2f} s' if back is not None
                 else f'no `estimating` within {args.after:g} s')
    said_after = sorted({r[2].split(':')[0] for r in reports if r[0] > flood_end})
    print(f'after the flood (its process ended): {back_text}; said: {said_after}')
    print(f'counters at the end: flood_dropped {final.get("flood_dropped")}, flood_episodes '
          f'{final.get("flood_episodes")}, measurements {final.get("measurements")}; '
          f'last message: {reports[-1][2] if reports else None}')


if __name__ == '__main__':
    main()
