# benchmarks/soak_observer.py: the observer node under a long 1 kHz stream of measurements.
"""
Soak test of the observer node (not part of CI; figures in docs/reliability.md).

The observer runs as its own process (``observer_ros.nodes.observer_node``, the submarine's
vehicle file, realtime mode, wall clock). This script publishes the gyro's
``sensor_msgs/Imu`` on ``imu/data`` at ``--rate`` Hz for ``--minutes`` minutes, with stamps
on an exact grid (t_k = t_0 + k / rate, each published at its wall time), and listens to
``state/estimate`` and the observer's ``/diagnostics``. It reports, per minute and for the
whole run:

- messages: published; processed by the observer (its ``measurements`` counter and the
  rejection counters); estimates received back. Lost on the way in (best-effort sensor
  QoS) = published - processed - rejected; not answered (lost by our code,
  in the observer or on the reliable way back) = processed - estimates received.
- latency: publish of a measurement -> arrival of the estimate with the same stamp
  (median, p99, max), in this process's monotonic clock.
- memory: the observer's VmRSS from /proc/PID/status, sampled every 10 s (start, end,
  slope of a least-squares line in KiB per minute).
- CPU: the observer's user+system time per wall second.
- publishing: how late the publisher thread was against its grid (p99), so that a
  latency figure can be told apart from a late sender.

Usage::

    .venv/bin/python benchmarks/soak_observer.py --minutes 10 --rate 1000 [--json out.json]

ROS_DOMAIN_ID is ``--domain`` (default 74).

"""

import argparse
import json
import os
from pathlib import Path
import statistics
import struct
import subprocess
import sys
import threading
import time
import warnings

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / 'benchmarks'))   # benchmarks/ is not a package

from _common import percentile  # noqa: E402
from observer_ros.tools.run_closed_loop import stop_process  # noqa: E402


def rss_kib(pid):
    """Return the resident set size (VmRSS) of a process in KiB (None once it is gone)."""
    try:
        for line in Path(f'/proc/{pid}/status').read_text().splitlines():
            if line.startswith('VmRSS:'):
                return int(line.split()[1])
    except OSError:
        return None
    return None


def cpu_seconds(pid):
    """User + system CPU seconds of a process."""
    try:
        fields = Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')
    except (OSError, IndexError, ValueError):
        return float('nan')


def slope(xs, ys):
    """Least-squares slope of ys over xs."""
    if len(xs) < 2:
        return float('nan')
    mx, my = statistics.fmean(xs), statistics.fmean(ys)
    den = sum((x - mx) ** 2 for x in xs)
    return sum((x - mx) * (y - my) for x, y in zip(xs, ys)) / den if den else float('nan')


class Driver:
    """The in-process node: publishes measurements, collects estimates and diagnostics."""

    def __init__(self, rate):
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import Imu, JointState

        from observer_ros.nodes.common import SENSOR_QOS

        self.rclpy = rclpy
        self.Imu = Imu
        rclpy.init()
        self.node = rclpy.create_node('soak_driver')
        self.pub = self.node.create_publisher(Imu, 'imu/data', SENSOR_QOS)
        deep = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE,
                          history=HistoryPolicy.KEEP_LAST)
        # raw: the stamp is read from the CDR bytes (cheaper than deserialising)
        self.sub = self.node.create_subscription(JointState, 'state/estimate',
                                                 self._on_estimate, deep, raw=True)
        self.diag_sub = self.node.create_subscription(DiagnosticArray, '/diagnostics',
                                                      self._on_diag, 100)
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)
        self.period_ns = int(round(1e9 / rate))
        self.lock = threading.Lock()
        self.sent_at = {}            # stamp ns -> perf_counter at publish
        self.published = 0
        self.lateness = []           # s behind the grid at publish (per minute, reset)
        self.latencies = []          # s (per minute, reset)
        self.received = 0
        self.unmatched = 0
        self.counters = {}           # the observer's latest diagnostics values
        self.diag_count = 0
        self.stop = threading.Event()
        self.first_due = None

    def _on_estimate(self, data):
        now = time.perf_counter()
        # CDR: 4-byte encapsulation header, then header.stamp (int32 sec, uint32 nanosec)
        order = '<' if data[1] == 1 else '>'
        sec, nanosec = struct.unpack_from(order + 'iI', data, 4)
        # the observer carries stamps as float seconds: ~0.2 us of rounding at today's
        # epoch, so the estimate is matched to its measurement on the grid
        key = round((sec * 1_000_000_000 + nanosec) / self.period_ns)
        with self.lock:
            t0 = self.sent_at.pop(key, None)
            self.received += 1
            if t0 is None:
                self.unmatched += 1
            else:
                self.latencies.append(now - t0)

    def _on_diag(self, msg):
        for status in msg.status:
            if status.name.endswith('/observer'):
                with self.lock:
                    self.counters = {kv.key: kv.value for kv in status.values}
                    self.counters['_level'] = status.level
                    self.counters['_message'] = status.message
                    self.diag_count += 1

    def wait_matched(self, timeout=30.0):
        """Wait until the observer reads imu/data and publishes state/estimate."""
        deadline = time.monotonic() + timeout
        while self.pub.get_subscription_count() < 1 or self.sub.get_publisher_count() < 1:
            if time.monotonic() > deadline:
                raise RuntimeError('the observer did not match within 30 s')
            self.executor.spin_once(timeout_sec=0.05)

    def publish_loop(self, duration):
        """Publish on the grid for `duration` seconds (runs in its own thread)."""
        msg = self.Imu()
        msg.header.frame_id = 'base_link_frd'
        msg.orientation_covariance[0] = -1.0
        msg.linear_acceleration_covariance[0] = -1.0
        t0_ns = (time.time_ns() // self.period_ns + 1) * self.period_ns
        p0 = time.perf_counter() + (t0_ns - time.time_ns()) * 1e-9
        self.first_due = p0
        k = 0
        n = int(duration * 1e9 / self.period_ns)
        while k < n and not self.stop.is_set():
            due = p0 + k * self.period_ns * 1e-9
            wait = due - time.perf_counter()
            if wait > 0:
                time.sleep(wait)
            stamp = t0_ns + k * self.period_ns
            msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp, 1_000_000_000)
            msg.angular_velocity.y = 0.01   # a constant pitch rate: the estimate moves
            now = time.perf_counter()
            with self.lock:
                self.sent_at[stamp // self.period_ns] = now
                self.lateness.append(now - due)
                self.published += 1
            self.pub.publish(msg)
            k += 1
            if k % 1000 == 0:
                self._forget((stamp - 10_000_000_000) // self.period_ns)

    def _forget(self, before):
        """Drop send times older than grid index `before` (answers that never came)."""
        with self.lock:
            old = [s for s in self.sent_at if s < before]
            for s in old:
                del self.sent_at[s]

    def spin_until(self, predicate, timeout):
        deadline = time.monotonic() + timeout
        while not predicate() and time.monotonic() < deadline:
            self.executor.spin_once(timeout_sec=0.05)
        return predicate()

    def take_minute(self):
        with self.lock:
            lat, self.latencies = self.latencies, []
            late, self.lateness = self.lateness, []
            return lat, late, self.published, self.received, dict(self.counters)

    def close(self):
        self.executor.shutdown()
        self.node.destroy_node()
        self.rclpy.try_shutdown()


def main(argv=None):
    warnings.filterwarnings('ignore', category=DeprecationWarning)
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--minutes', type=float, default=10.0)
    parser.add_argument('--rate', type=float, default=1000.0, help='Hz of measurements')
    parser.add_argument('--domain', type=int, default=74, help='ROS_DOMAIN_ID')
    parser.add_argument('--json', metavar='PATH', help='write the figures as JSON')
    parser.add_argument('--log', metavar='PATH', default='/tmp/soak_observer_node.log',
                        help="the observer's output")
    args = parser.parse_args(argv)
    os.environ['ROS_DOMAIN_ID'] = str(args.domain)
    env = dict(os.environ, PYTHONUNBUFFERED='1')
    cmd = [sys.executable, '-W', 'ignore::DeprecationWarning', '-m',
           'observer_ros.nodes.observer_node', '--ros-args', '--params-file',
           str(REPO / 'config' / 'submarine.yaml'), '-p', 'simulator.mode:=realtime',
           '-p', 'use_sim_time:=false', '-p', 'diagnostics_period:=1.0']
    log = open(args.log, 'w')
    proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env)
    driver = None
    try:
        driver = Driver(args.rate)
        driver.wait_matched()
        duration = args.minutes * 60.0
        pub_thread = threading.Thread(target=driver.publish_loop, args=(duration,),
                                      daemon=True)
        load_start = os.getloadavg()
        rss0 = rss_kib(proc.pid)
        pub_thread.start()
        while driver.first_due is None:
            time.sleep(0.001)
        # the minutes count from the first publish (perf_counter and monotonic are the
        # same clock on Linux; only differences are used)
        start = time.monotonic() + (driver.first_due - time.perf_counter())
        cpu0 = cpu_seconds(proc.pid)
        own0 = time.process_time()
        rss = [(0.0, rss0)]
        minutes = []
        next_rss, next_minute = start + 10.0, start + 60.0
        last_pub = last_rcv = 0
        last_cpu, last_t, last_own = cpu0, start, own0
        while True:
            driver.executor.spin_once(timeout_sec=0.01)
            now = time.monotonic()
            if now >= next_rss:
                rss.append((now - start, rss_kib(proc.pid)))
                next_rss += 10.0
            if now >= next_minute or not pub_thread.is_alive():
                lat, late, pub, rcv, counters = driver.take_minute()
                cpu = cpu_seconds(proc.pid)
                row = {
                    'minute': len(minutes) + 1,
                    'published': pub - last_pub, 'received': rcv - last_rcv,
                    'latency_ms_median': 1e3 * percentile(lat, 50),
                    'latency_ms_p99': 1e3 * percentile(lat, 99),
                    'latency_ms_max': 1e3 * max(lat) if lat else float('nan'),
                    'publish_late_ms_p99': 1e3 * percentile(late, 99),
                    'observer_cpu': (cpu - last_cpu) / (now - last_t),
                    'driver_cpu': (time.process_time() - last_own) / (now - last_t),
                    'loadavg_1min': os.getloadavg()[0],
                    'observer_rss_kib': rss_kib(proc.pid),
                }
                minutes.append(row)
                print(json.dumps(row), flush=True)
                last_pub, last_rcv, last_cpu, last_t = pub, rcv, cpu, now
                last_own = time.process_time()
                next_minute += 60.0
                if not pub_thread.is_alive():
                    break
            if proc.poll() is not None:
                raise RuntimeError(f'the observer exited ({proc.returncode}); see {args.log}')
        pub_thread.join()
        # drain: the last estimates, then one more diagnostics report with final counters
        driver.spin_until(lambda: driver.received >= driver.published, 5.0)
        n_diag = driver.diag_count
        driver.spin_until(lambda: driver.diag_count >= n_diag + 2, 5.0)
        rss.append((time.monotonic() - start, rss_kib(proc.pid)))
        counters = dict(driver.counters)
        processed = int(counters.get('measurements', 0))
        rejected = sum(int(v) for k, v in counters.items() if k in (
            'bad_messages', 'rejected_updates', 'out_of_order', 'duplicates',
            'future_stamps', 'numerical_resets', 'clock_jumps'))
        predictions = int(counters.get('predictions', 0))
        result = {
            'rate_hz': args.rate, 'minutes': args.minutes,
            'published': driver.published,
            'observer_measurements': processed,
            'observer_rejected': rejected,
            'observer_predictions': predictions,
            'estimates_received': driver.received,
            'estimates_unmatched': driver.unmatched,
            'lost_on_the_way_in': driver.published - processed - rejected,
            # a processed measurement is answered by one estimate (reliable QoS back)
            'not_answered': processed - (driver.received - driver.unmatched),
            'rss_kib_start': rss[0][1], 'rss_kib_end': rss[-1][1],
            'rss_kib_per_minute': 60.0 * slope([t for t, _ in rss[1:]],
                                               [r for _, r in rss[1:]]),
            'per_minute': minutes,
            'rss_kib_samples': rss,
            'observer_counters': counters,
            'machine': {'nproc': os.cpu_count(), 'loadavg_start': load_start,
                        'loadavg_end': os.getloadavg(),
                        'python': sys.version.split()[0]},
        }
        print(json.dumps({k: v for k, v in result.items()
                          if k not in ('per_minute', 'rss_kib_samples')}, indent=1,
                         default=str))
        if args.json:
            Path(args.json).write_text(json.dumps(result, indent=2, default=str))
        return 0
    finally:
        if driver is not None:
            driver.stop.set()
            driver.close()
        stop_process(proc)
        log.close()


if __name__ == '__main__':
    raise SystemExit(main())
