# benchmarks/p1_latency.py: P1, measurement -> estimate latency of the observer node vs a relay.
"""
P1: sensor message published -> x_hat received, over DDS, three processes.

Processes: the observer node (``config/submarine.yaml``, ``simulator.mode:=realtime``
so it answers every measurement without waiting for a command) in namespace
``/p1_obs``; the baseline, ``relay_node.py`` (same topics, QoS and message layout, no
estimator) in ``/p1_relay``; and this driver, which publishes ``imu/data`` to one of
them at ``--rate`` Hz and receives its ``state/estimate``.

Each Imu is stamped with the wall clock just before it is published (as a driver
stamping real data would: the steps jitter by the publishing thread's wake-up
jitter, so nearly every step is new to the estimator); the latency of an answer is
the wall clock when the driver's callback runs minus that stamp.

After a warm-up (DDS matching, the observer's first gains), blocks of ``--count``
messages go alternately to the relay and to the observer (A B, B A, ...), ``--pairs``
pairs. Per pair: observer / relay of the median and of the 99th percentile.

With ``--baseline-observer-pythonpath DIR`` (a copy of an earlier version: ``git
archive``) a third process runs that version's observer in ``/p1_base``, and each round
sends a block to each of the three, the order rotated from round to round; then also:
observer / baseline of the median, the p99 and the CPU per message, per round (the same
host in the same minute).

Targets: median <= 1.10x relay, p99 <= 1.20x relay, CPU per message <= 1.25x relay.

"""

import os
from pathlib import Path
import sys
import tempfile
import threading
import time

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import (common_parser, FLOOD_FALLBACK, gyro_imu, log, percentile,  # noqa: E402
                     ratio_line, REPO, report, ros_env, summary)
from _procs import node_command, start, stop_all  # noqa: E402

TARGETS = {'relay': '/p1_relay', 'observer': '/p1_obs'}
BASELINE = ('baseline', '/p1_base')     # an earlier version's observer (optional)


def _cpu_seconds(pid):
    """User + system CPU time of a process (all its threads), from /proc."""
    try:
        fields = Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()
    except OSError:
        return float('nan')
    return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')


def _wait(predicate, timeout, what):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return
        time.sleep(0.05)
    raise RuntimeError(f'P1: timed out waiting for {what}')


def run(smoke=False, rate=None, count=None, pairs=None, observer_pythonpath=None,
        log=print, baseline_pythonpath=None):
    rate = rate or (200.0 if smoke else 250.0)
    count = count or (200 if smoke else 1500)
    pairs = pairs or (1 if smoke else 4)
    os.environ['ROS_DOMAIN_ID'] = ros_env()['ROS_DOMAIN_ID']
    import warnings
    warnings.filterwarnings('ignore', category=DeprecationWarning)
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from sensor_msgs.msg import Imu, JointState
    from builtin_interfaces.msg import Time

    from observer_ros.nodes.common import SENSOR_QOS, STATE_QOS

    targets = dict(TARGETS)
    if baseline_pythonpath:
        targets[BASELINE[0]] = BASELINE[1]
    logdir = Path(tempfile.mkdtemp(prefix='p1_logs_'))
    procs = []
    rclpy.init()
    node = Node('p1_driver')
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    state = {'block': None, 'lat': [], 'sent': set()}
    lock = threading.Lock()

    def on_estimate(target):
        def cb(msg):
            now = time.time_ns()
            s = msg.header.stamp
            stamp = s.sec * 1_000_000_000 + s.nanosec
            with lock:
                # answers to this block's messages only: not a late one from the warm-up,
                # nor a prediction the observer publishes on its own (sensor silent)
                if state['block'] == target and stamp in state['sent']:
                    state['sent'].discard(stamp)
                    state['lat'].append(now - stamp)
        return cb

    pubs, subs = {}, {}
    for target, ns in targets.items():
        pubs[target] = node.create_publisher(Imu, f'{ns}/imu/data', SENSOR_QOS)
        subs[target] = node.create_subscription(JointState, f'{ns}/state/estimate',
                                                on_estimate(target), STATE_QOS)
    msg = gyro_imu()

    def send(target, n, seconds_per=None):
        """Publish n messages to target at the rate; stamp = wall clock at publish."""
        pub = pubs[target]
        period = 1.0 / rate
        t0 = time.perf_counter() + 0.01
        for i in range(n):
            deadline = t0 + i * period
            while True:
                left = deadline - time.perf_counter()
                if left <= 0:
                    break
                time.sleep(left if left > 0.002 else 0.0)
            now = time.time_ns()
            msg.header.stamp = Time(sec=now // 1_000_000_000, nanosec=now % 1_000_000_000)
            with lock:
                state['sent'].add(now)
            msg.angular_velocity.y = 0.001 * ((i % 200) - 100) / 100.0
            pub.publish(msg)

    def block(target, n):
        with lock:
            state['block'], state['lat'] = target, []
            state['sent'] = set()
        pid = pids.get(target)
        cpu0 = _cpu_seconds(pid) if pid else float('nan')
        send(target, n)
        time.sleep(0.3)                    # drain
        with lock:
            lat, state['block'] = state['lat'], None
        state['cpu'] = (_cpu_seconds(pid) - cpu0) if pid else float('nan')
        return lat

    results = {target: [] for target in targets}
    pids = {}
    try:
        procs.append(start([sys.executable, str(REPO / 'benchmarks' / 'relay_node.py'),
                            '--ros-args', '-r', f'__ns:={TARGETS["relay"]}'],
                           logdir / 'relay.log'))
        procs.append(start(node_command('observer_node', 'simulator.mode:=realtime',
                                        namespace=TARGETS['observer'],
                                        pythonpath=observer_pythonpath),
                           logdir / 'observer.log', pythonpath=observer_pythonpath))
        if baseline_pythonpath:
            procs.append(start(node_command('observer_node', 'simulator.mode:=realtime',
                                            namespace=BASELINE[1],
                                            pythonpath=baseline_pythonpath),
                               logdir / 'baseline.log', pythonpath=baseline_pythonpath))
        pids = dict(zip(targets, (p.pid for p in procs)))
        spinner.start()
        for target in targets:
            _wait(lambda t=target: pubs[t].get_subscription_count() >= 1
                  and subs[t].get_publisher_count() >= 1, 60.0, f'{target} to match')
        # warm-up: matching in both directions, the observer's first gains
        for target in targets:
            deadline = time.monotonic() + 30.0
            while True:
                lat = block(target, int(rate * (0.5 if smoke else 1.5)))
                if len(lat) > 0.5 * rate * (0.5 if smoke else 1.5) or \
                        time.monotonic() > deadline:
                    break
        log(f'  P1: {rate:g} Hz, blocks of {count} messages, {pairs} pairs')
        names = list(targets)
        for i in range(pairs):
            if len(names) == 2:
                order = names if i % 2 == 0 else names[::-1]      # A B, B A, ...
            else:
                order = names[i % len(names):] + names[:i % len(names)]
            for target in order:
                lat = block(target, count)
                us = [x / 1000.0 for x in lat]
                results[target].append({
                    'sent': count, 'received': len(us),
                    'median_us': percentile(us, 50), 'p99_us': percentile(us, 99),
                    'max_us': max(us) if us else float('nan'),
                    'cpu_us_per_msg': state['cpu'] / count * 1e6})
                r = results[target][-1]
                log(f'  P1 pair {i + 1}/{pairs} {target:>8}: median {r["median_us"]:.0f} us, '
                    f'p99 {r["p99_us"]:.0f} us, max {r["max_us"]:.0f} us, '
                    f'received {r["received"]}/{count}, CPU {r["cpu_us_per_msg"]:.0f} us/msg')
    finally:
        executor.shutdown(timeout_sec=1.0)
        node.destroy_node()
        rclpy.try_shutdown()
        stop_all(procs)
    # an observer that took the warm-up for a flood left the events executor for the run
    fell_back = [name for name in ('observer', 'baseline') if (logdir / f'{name}.log').exists()
                 and FLOOD_FALLBACK in (logdir / f'{name}.log').read_text(errors='replace')]
    if fell_back:
        log(f'  P1: {" and ".join(fell_back)} took its messages for a flood and left the '
            "events executor: its figures are the wait-set executor's")
    figures = []
    rel, obs = results['relay'], results['observer']
    for key, target in (('median_us', 1.10), ('p99_us', 1.20)):
        ratios = [o[key] / r[key] for o, r in zip(obs, rel)]
        figures.append(ratio_line(
            'P1', f'{key[:-3]}_latency_observer/relay', ratios, '<=', target, smoke=smoke,
            note=f'observer {summary([o[key] for o in obs])["median"]:.0f} us, relay '
                 f'{summary([r[key] for r in rel])["median"]:.0f} us'))
    figures.append(ratio_line(
        'P1', 'cpu_per_message_observer/relay',
        [o['cpu_us_per_msg'] / r['cpu_us_per_msg'] for o, r in zip(obs, rel)], '<=', 1.25,
        smoke=smoke,
        note=f'observer {summary([o["cpu_us_per_msg"] for o in obs])["median"]:.0f} us, relay '
             f'{summary([r["cpu_us_per_msg"] for r in rel])["median"]:.0f} us of CPU per message '
             '(process utime + stime)' + ('; the observer left the events executor (flood)'
                                          if 'observer' in fell_back else '')))
    lost = sum(o['sent'] - o['received'] for o in obs)
    lost_r = sum(r['sent'] - r['received'] for r in rel)
    figures.append(ratio_line(
        'P1', 'answered_observer/relay',
        [o['received'] / max(1, r['received']) for o, r in zip(obs, rel)], '>=', None,
        smoke=smoke, note=f'unanswered: observer {lost}, relay {lost_r} of {count * pairs}'))
    base = results.get(BASELINE[0])
    for key, what in (('median_us', 'median_latency'), ('p99_us', 'p99_latency'),
                      ('cpu_us_per_msg', 'cpu_per_message')):
        if not base:
            break
        figures.append(ratio_line(
            'P1', f'{what}_observer/baseline', [o[key] / b[key] for o, b in zip(obs, base)],
            '<=', None, smoke=smoke,
            note=f'observer {summary([o[key] for o in obs])["median"]:.0f} us, baseline '
                 f'({baseline_pythonpath}) {summary([b[key] for b in base])["median"]:.0f} '
                 f'us, relay {summary([r[key] for r in rel])["median"]:.0f} us'))
    return {'benchmark': 'P1', 'smoke': smoke, 'rate_hz': rate, 'count': count,
            'pairs': pairs, 'figures': figures, 'blocks': results, 'logs': str(logdir),
            'flood_fallback': fell_back}


def main(argv=None):
    parser = common_parser(__doc__.splitlines()[1])
    parser.add_argument('--rate', type=float, help='messages per second (default 250)')
    parser.add_argument('--count', type=int, help='messages per block (default 1500)')
    parser.add_argument('--pairs', type=int, help='relay/observer block pairs (default 4)')
    parser.add_argument('--observer-pythonpath', metavar='DIR',
                        help='run the observer with this copy of observer_ros first on '
                             'PYTHONPATH (to measure a previous version)')
    parser.add_argument('--baseline-observer-pythonpath', metavar='DIR',
                        help="also run this copy's observer (e.g. git archive of an earlier "
                             'commit) in each round, and report observer / baseline')
    args = parser.parse_args(argv)
    print('P1: observer node latency against a bare relay', flush=True)
    return report(args.json, run(smoke=args.smoke, rate=args.rate, count=args.count,
                                 pairs=args.pairs,
                                 observer_pythonpath=args.observer_pythonpath, log=log,
                                 baseline_pythonpath=args.baseline_observer_pythonpath))


if __name__ == '__main__':
    raise SystemExit(main())
