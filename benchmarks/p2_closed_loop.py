# benchmarks/p2_closed_loop.py: P2, the closed loop at 1 kHz in free-running real time.
"""
P2: simulator -> observer -> compensator -> simulator, free-running at 1 kHz.

The three nodes of ``config/submarine.yaml`` run as separate processes (namespace
``/p2``) with ``simulator.mode:=realtime`` and ``simulator.rate_hz:=1000.0``: the
simulator steps on a wall-clock timer, publishes the gyro, and applies the latest
command it has; the observer answers each measurement at once; the compensator
answers each estimate. The simulator counts, at each step, whether the command
answering the previous step has arrived (``late_commands``; steps before the first
command ever arrives are ``open_loop_steps``: the peers were still starting), and
reports its counters on /diagnostics, which this driver reads.

Figure: on-time fraction ``1 - late / checked steps`` per run [>= 0.999], over
``--runs`` runs. Also reported: the step rate achieved (rcl timers skip periods the
process was too busy to serve, so a late step is not counted twice).

"""

import os
from pathlib import Path
import sys
import tempfile
import threading
import time

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import (common_parser, machine_info, percentile, ratio_line,  # noqa: E402
                     ros_env, summary, write_json)
from _procs import node_command, start, stop_all  # noqa: E402

NS = '/p2'


def _one_run(node, state, duration, rate, logdir, run, pythonpath=None):
    """Start observer and compensator, then the simulator; wait for it to finish."""
    common = ['simulator.mode:=realtime', f'simulator.rate_hz:={float(rate)}']
    procs = []
    try:
        procs.append(start(node_command('observer_node', *common, namespace=NS),
                           logdir / f'observer_{run}.log', pythonpath))
        procs.append(start(node_command('compensator', *common, namespace=NS),
                           logdir / f'compensator_{run}.log', pythonpath))
        deadline = time.monotonic() + 60.0
        while time.monotonic() < deadline:
            if node.count_publishers(f'{NS}/state/estimate') >= 1 and \
                    node.count_publishers(f'{NS}/control/u') >= 1 and \
                    node.count_subscribers(f'{NS}/imu/data') >= 1 and \
                    node.count_subscribers(f'{NS}/state/estimate') >= 1:
                break
            time.sleep(0.05)
        else:
            raise RuntimeError('P2: observer and compensator did not come up')
        with state['lock']:
            state['diag'] = []
            state['seen'], state['loop'] = {}, []
        sim = start(node_command('plant_simulator', *common,
                                 f'simulator.duration:={float(duration)}',
                                 'diagnostics_period:=0.25', namespace=NS),
                    logdir / f'plant_simulator_{run}.log', pythonpath)
        procs.append(sim)
        try:
            sim.wait(duration + 60.0)
        except Exception:   # noqa: BLE001 - a hung simulator: stop it below
            raise RuntimeError(f'P2: the simulator did not finish; see {logdir}')
        time.sleep(0.3)                     # the last diagnostics
    finally:
        stop_all(procs)
    with state['lock']:
        diag = list(state['diag'])
    with state['lock']:
        loop = sorted(state['loop'])
    if not diag:
        raise RuntimeError(f'P2: no diagnostics from the simulator; see {logdir}')
    last = max(diag, key=lambda d: int(d['values'].get('steps', 0)))
    v = last['values']
    steps = int(v.get('steps', 0))
    late = int(v.get('late_commands', 0))
    open_loop = int(v.get('open_loop_steps', 0))
    checked = max(0, steps - 1 - open_loop)
    running = [d for d in diag if int(d['values'].get('steps', 0)) > open_loop + 1]
    rate_achieved = float('nan')
    if len(running) >= 2:
        a, b = running[0], running[-1]
        span = b['stamp'] - a['stamp']
        if span > 0:
            rate_achieved = (int(b['values']['steps']) - int(a['values']['steps'])) / span
    loop_us = [x / 1000.0 for x in loop]
    return {'loop_median_us': percentile(loop_us, 50), 'loop_p99_us': percentile(loop_us, 99),
            'loop_samples': len(loop_us),
            'steps': steps, 'late_commands': late, 'open_loop_steps': open_loop,
            'checked': checked, 'on_time': 1.0 - late / checked if checked else float('nan'),
            'rate_achieved_hz': rate_achieved, 'exit_code': sim.returncode}


def run(smoke=False, runs=None, duration=None, rate=1000.0, nodes_pythonpath=None, log=print):
    runs = runs or (1 if smoke else 3)
    # the simulator steps from its start; DDS matching takes it 1-3 s here, and those
    # open-loop steps are not judged: the run is that much longer than what is measured
    duration = duration or (5.0 if smoke else 15.0)
    os.environ['ROS_DOMAIN_ID'] = ros_env()['ROS_DOMAIN_ID']
    import warnings
    warnings.filterwarnings('ignore', category=DeprecationWarning)
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from sensor_msgs.msg import Imu, JointState

    from observer_ros.nodes.common import SENSOR_QOS, STATE_QOS

    logdir = Path(tempfile.mkdtemp(prefix='p2_logs_'))
    rclpy.init()
    node = Node('p2_driver')
    state = {'lock': threading.Lock(), 'diag': [], 'seen': {}, 'loop': []}

    def on_diag(msg):
        for status in msg.status:
            if status.name.endswith('plant_simulator') and status.name.startswith(NS):
                s = msg.header.stamp
                rec = {'stamp': s.sec + s.nanosec * 1e-9,
                       'values': {kv.key: kv.value for kv in status.values}}
                with state['lock']:
                    state['diag'].append(rec)

    node.create_subscription(DiagnosticArray, '/diagnostics', on_diag, 50)

    # the loop as this process sees it: a gyro message, then the command with its stamp
    def on_imu(msg):
        s = msg.header.stamp
        with state['lock']:
            state['seen'][(s.sec, s.nanosec)] = time.perf_counter_ns()

    def on_command(msg):
        now = time.perf_counter_ns()
        s = msg.header.stamp
        with state['lock']:
            sent = state['seen'].pop((s.sec, s.nanosec), None)
            if sent is not None:
                state['loop'].append(now - sent)

    node.create_subscription(Imu, f'{NS}/imu/data', on_imu, SENSOR_QOS)
    node.create_subscription(JointState, f'{NS}/control/u', on_command, STATE_QOS)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    results = []
    try:
        for r in range(runs):
            res = _one_run(node, state, duration, rate, logdir, r, nodes_pythonpath)
            results.append(res)
            log(f'  P2 run {r + 1}/{runs}: {res["steps"]} steps at {rate:g} Hz, '
                f'{res["open_loop_steps"]} before the loop closed, {res["late_commands"]} '
                f'late of {res["checked"]} -> on time {res["on_time"]:.5f}; achieved '
                f'{res["rate_achieved_hz"]:.0f} Hz; loop gyro -> command seen here: median '
                f'{res["loop_median_us"]:.0f} us, p99 {res["loop_p99_us"]:.0f} us')
    finally:
        executor.shutdown(timeout_sec=1.0)
        node.destroy_node()
        rclpy.try_shutdown()
    figures = [ratio_line(
        'P2', 'on_time_fraction_at_1kHz', [r['on_time'] for r in results], '>=', 0.999,
        unit='', smoke=smoke,
        note=f'{sum(r["late_commands"] for r in results)} late of '
             f'{sum(r["checked"] for r in results)} steps; achieved step rate median '
             f'{summary([r["rate_achieved_hz"] for r in results])["median"]:.0f} Hz')]
    period_us = 1e6 / rate
    figures.append(ratio_line(
        'P2', 'loop_round_trip_median/step_period',
        [r['loop_median_us'] / period_us for r in results], '<=', None, smoke=smoke,
        note=f'gyro published -> command received, seen from a 4th process: median '
             f'{summary([r["loop_median_us"] for r in results])["median"]:.0f} us, p99 '
             f'{summary([r["loop_p99_us"] for r in results])["median"]:.0f} us; period '
             f'{period_us:.0f} us'))
    return {'benchmark': 'P2', 'smoke': smoke, 'rate_hz': rate, 'duration_s': duration,
            'figures': figures, 'runs': results, 'logs': str(logdir)}


def main(argv=None):
    parser = common_parser(__doc__.splitlines()[1])
    parser.add_argument('--runs', type=int, help='closed-loop runs (default 3)')
    parser.add_argument('--duration', type=float,
                        help='seconds per run, start-up included (default 15)')
    parser.add_argument('--rate', type=float, default=1000.0, help='step rate, Hz')
    parser.add_argument('--nodes-pythonpath', metavar='DIR',
                        help='run the nodes with this copy of observer_ros first on '
                             'PYTHONPATH (to measure a previous version)')
    args = parser.parse_args(argv)
    print('P2: closed loop in free-running real time', flush=True)
    data = run(smoke=args.smoke, runs=args.runs, duration=args.duration, rate=args.rate,
               nodes_pythonpath=args.nodes_pythonpath, log=lambda s: print(s, flush=True))
    data['machine'] = machine_info()
    write_json(args.json, data)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
