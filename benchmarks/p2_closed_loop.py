# benchmarks/p2_closed_loop.py: P2, the closed loop at 1 kHz in free-running real time.
"""
P2: simulator -> observer -> compensator -> simulator, free-running at 1 kHz.

The three nodes of ``config/submarine.yaml`` run in namespace ``/p2`` with
``simulator.mode:=realtime`` and ``simulator.rate_hz:=1000.0``: the simulator steps on
a wall-clock timer, publishes the gyro, and applies the latest command it has; the
observer answers each measurement at once; the compensator answers each estimate. The
simulator counts, at each step, whether the command answering the previous step has
arrived (``late_commands``; steps before the first command ever arrives are
``open_loop_steps``: the peers were still starting), times each measurement -> command
round trip, and reports both on /diagnostics, which this driver reads (it subscribes to
nothing else, so that it does not load the loop it measures).

Layouts, each run ``--runs`` times (``--configs``):

- ``processes``: three processes, one per node (``ros2 run`` each);
- ``container``: the observer and the compensator in one process (``ros2 run
  observer_ros container observer compensator``), the simulator in its own, as a
  vehicle's estimator and controller would run beside a separate driver;
- ``one_process``: all three in one container;
- ``LAYOUT@fifoN``: the same with every process at SCHED_FIFO priority N (``chrt``), as
  the ROS 2 real-time guides set a control loop up; by default ``container@fifo50``,
  skipped where this user may not.

The bare loop (``--loops nodes,bare``, both by default): the same simulator with the
observer and the compensator replaced by bare rclpy relays (``relay_node.py``: the same
messages, QoS and executor, no estimator, no control law; ``processes``: one process
each, ``container``: both in one process), run beside the nodes, the two alternated run
by run (A B, B A, ...). What the host can do is what the bare loop does on it; the nodes
are judged against that in the same run:

- on-time fraction at 1 kHz, nodes minus bare, per pair of runs [>= -0.005];
- ``--sweep LAYOUTS``: the highest step rate at which each loop keeps 99.9 % of its steps
  on time. Each rate is a run of ``--sweep-warmup`` s of closed loop (1 s; its steps not
  judged, in every loop alike) and then ``--sweep-steps`` judged steps (10000: the rate
  holds with at most 10 of them late; one late step is 0.01 %, the resolution). From
  500 Hz up by 1.5x to the first rate that misses (down by 1.5x to the first that holds
  when 500 Hz misses, 148 Hz at the lowest), then geometric bisections between the two
  (``--sweep-bisections``, 3, fewer once missed / held <= 1.06); the loops probed in
  turn, the order reversed
  from one round to the next. Figure: nodes / bare [>= 0.9], bracketed by the rates each
  loop missed, with both rates and the bare loop's round trip at the main rate (the
  host's relay figure) beside it. Each probe says where its late steps fell: in the
  warm-up, after a short step (the timer catching up after a late tick), in how many
  0.25 s windows and at most how many in one (bursts are stalls of the host or of a
  process; lone ones round trips longer than a period).

Figure per configuration: on-time fraction ``1 - late / checked steps`` per run (an
absolute figure, information: it measures the host as much as the code). Also reported:
the loop round trip and the step rate achieved (rcl timers skip periods the process was
too busy to serve, so a late step is not counted twice), and each process's CPU time
(user + system, /proc) per simulator step over the closed loop: which node a slower loop
comes from. ``--baseline-nodes-pythonpath DIR`` adds a third loop per round (and to the
sweep): the observer and the compensator of DIR's copy with this simulator.
``--observer-pythonpath`` runs the observer of another version than the simulator and
compensator (``processes`` layout).

``--baseline-observer-pythonpath DIR`` (a checkout of an earlier version, e.g. ``git
archive``) follows each ``processes`` run with one whose observer is that version's, the
simulator and compensator the same (the order alternates from run to run), and reports
the observer's CPU per step against the baseline's, per pair of runs: as measured, and
divided in each run by the simulator's CPU per step (the same code in both runs of a
pair, so what the host's speed does to both cancels; on this host it drifted by 20 %
from one run to the next).

"""

import os
from pathlib import Path
import re
import subprocess
import sys
import tempfile
import threading
import time

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import (common_parser, FLOOD_FALLBACK, log, percentile,  # noqa: E402
                     ratio_line, report, ros_env, summary)
from _procs import node_command, start, stop_all  # noqa: E402

NS = '/p2'


# What runs by default: each layout, and the container as a real-time deployment would
# run it (SCHED_FIFO 50, when this user may); the smoke run has no SCHED_FIFO run.
CONFIGS = ('processes', 'container', 'one_process', 'container@fifo50')
CONFIGS_SMOKE = ('processes', 'container', 'one_process')

LAYOUTS = {
    'processes': (('observer_node',), ('compensator',), ('plant_simulator',)),
    'container': (('container', 'observer', 'compensator'), ('plant_simulator',)),
    'one_process': (('container', 'observer', 'compensator', 'plant_simulator'),),
}
# The bare loop of a layout: the relays in place of the observer and the compensator.
BARE = {
    'processes': (('relay', 'estimate'), ('relay', 'command'), ('plant_simulator',)),
    'container': (('relay', 'estimate', 'command'), ('plant_simulator',)),
}
LOOPS = ('nodes', 'bare', 'baseline')
ON_TIME = 0.999             # the on-time fraction a rate of the sweep must keep
SWEEP_START = 500.0         # Hz, the sweep's first rate
SWEEP_FACTOR = 1.5          # and its steps up, to the first rate that misses
SWEEP_MAX = 8000.0          # Hz: the sweep stops here even if every rate held
SWEEP_MIN = 140.0           # Hz: and goes no lower when the first rate misses (148 Hz)
# steps judged per rate of the sweep: 0.1 % of them is 10 steps, one late step 0.01 %
SWEEP_STEPS = 10000
# s of closed loop at the start of every run of the sweep, in every loop alike, whose
# steps are not judged: the first steps' stalls (first publishes and callbacks,
# the simulator's first step) are start-up, not the loop's rate
SWEEP_WARMUP = 1.0
SWEEP_RESOLUTION = 1.06     # the bisection ends once missed / held is at most this


def _command(parts, params, rt_priority=None, pythonpath=None):
    """Return the argv of one process of a layout: a node, the container, or relays."""
    if parts[0] == 'relay':
        cmd = [sys.executable, str(Path(__file__).resolve().parent / 'relay_node.py'),
               '--roles', ','.join(parts[1:]), '--ros-args', '-r', f'__ns:={NS}']
    else:
        cmd = node_command(parts[0], *params, namespace=NS, nodes=parts[1:],
                           pythonpath=pythonpath)
    if rt_priority:
        # SCHED_FIFO, as the ROS 2 real-time guides set up a control loop (needs the right)
        cmd = ['chrt', '--fifo', str(int(rt_priority))] + cmd
    return cmd


class DiscoveryLate(RuntimeError):
    """A simulator ended its run (exit 0) before its /diagnostics reached the driver."""


#: Runs again of a layout whose simulator ran before the driver discovered it: one_process
#: runs the simulator with its observer and compensator, so its 2-s smoke run starts at
#: once, and discovery takes seconds on a loaded host.
DISCOVERY_RETRIES = 2


def _one_run_heard(log, *args, **kwargs):
    """Return ``_one_run(*args, **kwargs)``, run again while its simulator was not heard."""
    for attempt in range(DISCOVERY_RETRIES + 1):
        try:
            return _one_run(*args, **kwargs)
        except DiscoveryLate as err:
            if attempt == DISCOVERY_RETRIES:
                raise
            log(f'  {err}: run again ({attempt + 2} of {DISCOVERY_RETRIES + 1})')


def _one_run(node, state, layout, duration, rate, logdir, run, pythonpath=None,
             rt_priority=None, observer_pythonpath=None, loop='nodes', baseline=None,
             warmup=0.0):
    """
    Start the layout's processes, the simulator last; wait for the simulator's end.

    ``loop``: ``nodes`` (the package's), ``bare`` (relays in their place, this
    checkout's: only the simulator takes ``pythonpath``), or ``baseline`` (the nodes of
    the copy ``baseline``, the simulator of ``pythonpath``).
    """
    common = ['simulator.mode:=realtime', f'simulator.rate_hz:={float(rate)}']
    sim_params = [f'simulator.duration:={float(duration)}', 'diagnostics_period:=0.25']
    layouts = BARE if loop == 'bare' else LAYOUTS
    procs, logs = [], []
    sim_parts = next(p for p in layouts[layout] if 'plant_simulator' in p)
    sim = None
    try:
        # the simulator first: its run waits for a command to answer step 0, and its
        # /diagnostics must reach this driver before that run starts (a probe of the sweep
        # is over in 2 s, less than discovery takes on a loaded host)
        with state['lock']:
            state['diag'] = []
        sim = start(_command(sim_parts, common + sim_params, rt_priority, pythonpath),
                    logdir / f'{layout}_{loop}_simulator_{run}_{rate:g}Hz.log', pythonpath)
        deadline = time.monotonic() + 60.0
        while sim.poll() is None and time.monotonic() < deadline:
            with state['lock']:
                if state['diag']:
                    break
            time.sleep(0.05)
        else:
            if sim.returncode == 0:
                raise DiscoveryLate(f'P2: the simulator ended its run before its diagnostics '
                                    f'reached this driver; see {logdir}')
            raise RuntimeError(f'P2: no diagnostics from the simulator before its run; '
                               f'see {logdir}')
        for parts in layouts[layout]:
            if 'plant_simulator' in parts:
                continue
            own = observer_pythonpath if parts == ('observer_node',) else None
            tag = f'{loop}_{"_".join(parts)}'
            path = {'bare': None, 'baseline': baseline}.get(loop, own or pythonpath)
            logs.append(logdir / f'{tag}_{run}_{rate:g}Hz.log')
            procs.append(start(_command(parts, common, rt_priority, path), logs[-1], path))
        deadline = time.monotonic() + 60.0
        while procs and time.monotonic() < deadline:
            if node.count_publishers(f'{NS}/state/estimate') >= 1 and \
                    node.count_publishers(f'{NS}/control/u') >= 1 and \
                    node.count_subscribers(f'{NS}/imu/data') >= 1 and \
                    node.count_subscribers(f'{NS}/state/estimate') >= 1:
                break
            time.sleep(0.05)
        else:
            if procs:
                raise RuntimeError('P2: observer and compensator did not come up')
        procs.append(sim)       # last: _sample_cpu follows it
        names = [parts[-1] if len(parts) == 1 else
                 ('+'.join(parts) if parts[0] == 'relay' else 'container')
                 for parts in layouts[layout] if 'plant_simulator' not in parts]
        names.append('plant_simulator' if len(sim_parts) == 1 else 'container')
        samples = _sample_cpu(procs, names, state, duration + 60.0)
        if sim.poll() is None:
            raise RuntimeError(f'P2: the simulator did not finish; see {logdir}')
        time.sleep(0.3)                     # the last diagnostics
    finally:
        stop_all(procs + ([sim] if sim is not None and sim not in procs else []))
    with state['lock']:
        diag = list(state['diag'])
    if not diag:
        raise RuntimeError(f'P2: no diagnostics from the simulator; see {logdir}')
    last = max(diag, key=lambda d: int(d['values'].get('steps', 0)))
    v = last['values']
    steps = int(v.get('steps', 0))
    late = int(v.get('late_commands', 0))
    late_short = int(v.get('late_commands_short_step', 0))
    open_loop = int(v.get('open_loop_steps', 0))
    checked = max(0, steps - 1 - open_loop)
    running = [d for d in diag if int(d['values'].get('steps', 0)) > open_loop + 1]
    rate_achieved = float('nan')
    if len(running) >= 2:
        a, b = running[0], running[-1]
        span = b['stamp'] - a['stamp']
        if span > 0:
            rate_achieved = (int(b['values']['steps']) - int(a['values']['steps'])) / span
    # the simulator's loop timing, one report per diagnostics period (0.25 s)
    windows = [d['values'] for d in running if 'loop_us_p50' in d['values']]
    judged = _judged(diag, open_loop, int(round(warmup * rate)))
    return {**judged, 'cpu_us_per_step': _cpu_per_step(samples, open_loop),
            'loop_median_us': percentile([float(w['loop_us_p50']) for w in windows], 50),
            'loop_p99_us': percentile([float(w['loop_us_p99']) for w in windows], 50),
            'loop_max_us': max((float(w['loop_us_max']) for w in windows),
                               default=float('nan')),
            'loop_samples': sum(int(w['loop_samples']) for w in windows),
            'steps': steps, 'late_commands': late, 'late_after_short_step': late_short,
            'open_loop_steps': open_loop,
            'checked': checked, 'on_time': 1.0 - late / checked if checked else float('nan'),
            'rate_achieved_hz': rate_achieved, 'exit_code': sim.returncode,
            'flood_fallback': any(FLOOD_FALLBACK in path.read_text(errors='replace')
                                  for path in logs if path.exists())}


def _judged(diag, open_loop, warmup_steps):
    """
    Return the steps judged after ``warmup_steps`` of closed loop, and where the late fell.

    From the simulator's cumulative counters, one report per diagnostics period: the
    counts at the first report at least ``warmup_steps`` past the loop's closing are
    subtracted from the last report's. Also: the late steps in the warm-up, how many of
    the judged ones followed a short step (the timer catching up after a late tick), and
    in how many reporting windows (0.25 s) the judged ones fell, the most in one window
    (a few windows with many: stalls of the host or of a process; many windows with one:
    round trips longer than a period now and then).
    """
    reports = sorted(diag, key=lambda d: int(d['values'].get('steps', 0)))
    counts = [(int(d['values'].get('steps', 0)), int(d['values'].get('late_commands', 0)),
               int(d['values'].get('late_commands_short_step', 0))) for d in reports]
    closed = open_loop + 1
    base = next((c for c in counts if c[0] >= closed + warmup_steps), None)
    if base is None or not counts or counts[-1][0] <= base[0]:
        return {'judged_steps': 0, 'judged_late': 0, 'judged_on_time': float('nan'),
                'warmup_late': 0, 'judged_late_short': 0, 'late_windows': 0,
                'late_window_max': 0}
    last = counts[-1]
    per_window = [b[1] - a[1] for a, b in zip(counts, counts[1:]) if a[0] >= base[0]]
    checked = last[0] - base[0]
    return {'judged_steps': checked, 'judged_late': last[1] - base[1],
            'judged_on_time': 1.0 - (last[1] - base[1]) / checked,
            'warmup_late': base[1], 'judged_late_short': last[2] - base[2],
            'late_windows': sum(1 for n in per_window if n),
            'late_window_max': max(per_window, default=0)}


def _cpu_ticks(pid):
    """CPU time (user + system) of a process in clock ticks, or None once it is gone."""
    try:
        fields = Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()
    except OSError:
        return None
    return int(fields[11]) + int(fields[12])      # utime, stime (fields 14 and 15)


def _sample_cpu(procs, names, state, timeout, period=0.25):
    """Until the simulator (the last process) ends: (steps so far, CPU ticks per process)."""
    samples = []
    deadline = time.monotonic() + timeout
    while procs[-1].poll() is None and time.monotonic() < deadline:
        with state['lock']:
            steps = max((int(d['values'].get('steps', 0)) for d in state['diag']), default=0)
        ticks = {}
        for name, proc in zip(names, procs):
            value = _cpu_ticks(proc.pid)
            if value is not None:
                ticks[name] = value
        samples.append((steps, ticks))
        time.sleep(period)
    return samples


def _cpu_per_step(samples, open_loop):
    """
    Return each process's CPU per simulator step (us) over the closed loop.

    From the first sample 500 steps past the open-loop steps (start-up, design and
    matching excluded) to the last sample in which the process was still alive.
    """
    tick_us = 1e6 / os.sysconf('SC_CLK_TCK')
    start = next((i for i, (steps, _) in enumerate(samples) if steps > open_loop + 500), None)
    if start is None:
        return {}
    first_steps, first = samples[start]
    out = {}
    for name in first:
        last = [(steps, ticks[name]) for steps, ticks in samples[start + 1:] if name in ticks]
        if last and last[-1][0] > first_steps:
            steps, value = last[-1]
            out[name] = (value - first[name]) * tick_us / (steps - first_steps)
    return out


def _fifo_allowed():
    """Whether this process may start others with SCHED_FIFO (chrt)."""
    try:
        return subprocess.run(['chrt', '--fifo', '1', 'true'], capture_output=True,
                              timeout=10).returncode == 0
    except (OSError, subprocess.SubprocessError):
        return False


def _parse_config(text):
    """``layout`` or ``layout@fifoN`` -> (layout, N or None)."""
    layout, _, prio = text.partition('@')
    if layout not in LAYOUTS or (prio and not re.fullmatch(r'fifo[1-9][0-9]?', prio)):
        raise SystemExit(f'P2: unknown configuration {text!r}: LAYOUT or LAYOUT@fifoN, '
                         f'LAYOUT one of {", ".join(LAYOUTS)}')
    return layout, int(prio[4:]) if prio else None


def _log_run(log, label, r, runs, rate, res):
    """Print one run's line: steps, late, on time, rate, round trip, CPU per step."""
    log(f'  P2 {label:>16} run {r + 1}/{runs}: {res["steps"]} steps at '
        f'{rate:g} Hz, {res["open_loop_steps"]} before the loop closed, '
        f'{res["late_commands"]} late ({res["late_after_short_step"]} of them '
        f'after a short step; in {res["late_windows"]} windows of 0.25 s, at most '
        f'{res["late_window_max"]} in one) of {res["checked"]} -> on time '
        f'{res["on_time"]:.5f}; achieved {res["rate_achieved_hz"]:.0f} Hz; '
        f'loop measurement -> command: median {res["loop_median_us"]:.0f} us, '
        f'p99 {res["loop_p99_us"]:.0f} us, max {res["loop_max_us"]:.0f} us; '
        'CPU per step: ' + ', '.join(
            f'{name} {us:.0f} us' for name, us in res['cpu_us_per_step'].items())
        + ('; a node took the messages for a flood and left the events executor'
           if res.get('flood_fallback') else ''))


def run(smoke=False, runs=None, duration=None, rate=1000.0, nodes_pythonpath=None,
        configs=None, log=print, observer_pythonpath=None, baseline_observer=None,
        loops=LOOPS[:2], sweep=None, sweep_duration=None, sweep_bisections=None,
        baseline_nodes=None, sweep_steps=None, sweep_warmup=None, sweep_on_time=ON_TIME):
    runs = runs or (1 if smoke else 3)
    configs = list(configs or (CONFIGS_SMOKE if smoke else CONFIGS))
    parsed = {c: _parse_config(c) for c in configs}
    if any(prio for _, prio in parsed.values()) and not _fifo_allowed():
        log('  P2: no right to SCHED_FIFO here (chrt failed): '
            f'{", ".join(c for c, (_, prio) in parsed.items() if prio)} skipped')
        configs = [c for c in configs if not parsed[c][1]]
    layouts = configs
    loops = [lp for lp in LOOPS if lp in loops and (lp != 'baseline' or baseline_nodes)]
    sweep = [c for c in (sweep or ()) if c]
    parsed.update({c: _parse_config(c) for c in sweep if c not in parsed})
    bare_ok = [c for c in set(layouts) | set(sweep) if _parse_config(c)[0] in BARE]
    if smoke:       # a smoke run: one bare loop (the processes'), enough to see it runs
        bare_ok = [c for c in bare_ok if c == 'processes' or c in sweep]
    if 'bare' in loops and [c for c in sweep if c not in bare_ok]:
        raise SystemExit(f'P2: no bare loop for {sweep}: --sweep takes '
                         f'{", ".join(BARE)}')
    # the simulator steps from its start; DDS matching takes it 1-3 s here, and those
    # open-loop steps are not judged: the run is that much longer than what is measured
    duration = duration or (2.0 if smoke else 15.0)
    sweep_steps = sweep_steps or (250 if smoke else SWEEP_STEPS)
    sweep_warmup = (0.5 if smoke else SWEEP_WARMUP) if sweep_warmup is None else sweep_warmup
    sweep_bisections = (0 if smoke else 3) if sweep_bisections is None else sweep_bisections
    os.environ['ROS_DOMAIN_ID'] = ros_env()['ROS_DOMAIN_ID']
    import warnings
    warnings.filterwarnings('ignore', category=DeprecationWarning)
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node

    logdir = Path(tempfile.mkdtemp(prefix='p2_logs_'))
    rclpy.init()
    node = Node('p2_driver')
    state = {'lock': threading.Lock(), 'diag': []}

    def on_diag(msg):
        for status in msg.status:
            if status.name.endswith('plant_simulator') and status.name.startswith(NS):
                s = msg.header.stamp
                rec = {'stamp': s.sec + s.nanosec * 1e-9,
                       'values': {kv.key: kv.value for kv in status.values}}
                with state['lock']:
                    state['diag'].append(rec)

    node.create_subscription(DiagnosticArray, '/diagnostics', on_diag, 50)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    results = {layout: [] for layout in layouts}
    bare_runs = {layout: [] for layout in layouts}
    base_runs = {layout: [] for layout in layouts}
    baseline_runs = []
    sweeps = {}
    try:
        for r in range(runs):
            # alternate the order of the layouts (and loops) from run to run
            order = []
            for layout in layouts:
                order.append((layout, None, 'nodes'))
                if 'bare' in loops and layout in bare_ok:
                    order.append((layout, None, 'bare'))
                if 'baseline' in loops and _parse_config(layout)[0] != 'one_process':
                    order.append((layout, None, 'baseline'))
            if baseline_observer and 'processes' in layouts:
                # the baseline's observer just after this one's (before it every other run)
                order.insert(order.index(('processes', None, 'nodes')) + 1,
                             ('processes', baseline_observer, 'nodes'))
            for layout, base, loop in (order if r % 2 == 0 else order[::-1]):
                res = _one_run_heard(log, node, state, parsed[layout][0], duration, rate,
                                     logdir, r, nodes_pythonpath, parsed[layout][1],
                                     base or observer_pythonpath, loop, baseline_nodes)
                if base:
                    baseline_runs.append(res)
                else:
                    {'nodes': results, 'bare': bare_runs,
                     'baseline': base_runs}[loop][layout].append(res)
                label = f'{layout} [observer {base}]' if base else (
                    layout if loop == 'nodes' else f'{layout} [{loop}]')
                _log_run(log, label, r, runs, rate, res)
        for layout in sweep:
            sweeps[layout] = _sweep(
                lambda loop, hz, k, c=layout: dict(_one_run_heard(
                    log, node, state, parsed[c][0],
                    sweep_duration or sweep_warmup + sweep_steps / hz + 0.5, hz, logdir,
                    f'sweep{k}', nodes_pythonpath, parsed[c][1], observer_pythonpath,
                    loop, baseline_nodes, warmup=sweep_warmup), warmup_s=sweep_warmup),
                loops, sweep_bisections, layout, log,
                max_probes=1 if smoke else 12, steps=sweep_steps, on_time=sweep_on_time)
    finally:
        executor.shutdown(timeout_sec=1.0)
        node.destroy_node()
        rclpy.try_shutdown()
    figures = []
    period_us = 1e6 / rate
    rate_name = f'{rate / 1000:g}kHz' if rate >= 1000 else f'{rate:g}Hz'   # 1kHz, 2kHz
    for layout in layouts:
        res = results[layout]
        bare = bare_runs[layout]
        relay_note = ''
        if bare:
            relay_note = ("; the bare loop's round trip (the host's relay figure): median "
                          f'{summary([b["loop_median_us"] for b in bare])["median"]:.0f} us')
        figures.append(_on_time_line(
            f'on_time_fraction_at_{rate_name}[{layout}]', res, smoke,
            f'achieved step rate median '
            f'{summary([r["rate_achieved_hz"] for r in res])["median"]:.0f} Hz' + relay_note))
        figures.append(ratio_line(
            'P2', f'loop_round_trip_median/step_period[{layout}]',
            [r['loop_median_us'] / period_us for r in res], '<=', None, smoke=smoke,
            note=f'measurement published -> its command received, timed by the simulator: '
                 f'median {summary([r["loop_median_us"] for r in res])["median"]:.0f} us, '
                 f'p99 {summary([r["loop_p99_us"] for r in res])["median"]:.0f} us; period '
                 f'{period_us:.0f} us'))
        if bare:
            _versus_bare(figures, layout, rate_name, res, bare, smoke)
        if base_runs[layout]:
            _versus_baseline_nodes(figures, layout, rate_name, res, base_runs[layout],
                                   baseline_nodes, smoke)
    for layout, found in sweeps.items():
        _sweep_figure(figures, layout, found, bare_runs.get(layout, []), smoke,
                      sweep_on_time)
    if baseline_runs:
        _versus_baseline(figures, results['processes'], baseline_runs, baseline_observer)
    return {'benchmark': 'P2', 'smoke': smoke, 'rate_hz': rate, 'duration_s': duration,
            'figures': figures, 'runs': results, 'bare_runs': bare_runs,
            'baseline_runs': baseline_runs, 'baseline_nodes_runs': base_runs,
            'sweeps': sweeps, 'logs': str(logdir)}


def _versus_baseline_nodes(figures, layout, rate_name, res, base, baseline, smoke):
    """Add the figures of the nodes against an earlier version's nodes, per pair of runs."""
    figures.append(ratio_line(
        'P2', f'on_time_fraction_nodes-baseline_at_{rate_name}[{layout}]',
        [r['on_time'] - b['on_time'] for r, b in zip(res, base)], '>=', None, unit='',
        smoke=smoke,
        note=f'per pair of runs; on time: these nodes '
             f'{summary([r["on_time"] for r in res])["median"]:.4f}, the nodes of {baseline} '
             f'{summary([b["on_time"] for b in base])["median"]:.4f}'))
    for name in sorted({k for r in res + base for k in r['cpu_us_per_step']}):
        if name == 'plant_simulator':
            continue
        pairs = [(r['cpu_us_per_step'].get(name), b['cpu_us_per_step'].get(name))
                 for r, b in zip(res, base)]
        pairs = [(a, b) for a, b in pairs if a and b]
        if pairs:
            figures.append(ratio_line(
                'P2', f'cpu_per_step_{name}/baseline[{layout}]', [a / b for a, b in pairs],
                '<=', None, smoke=smoke,
                note=f'{summary([a for a, _ in pairs])["median"]:.0f} us against '
                     f'{summary([b for _, b in pairs])["median"]:.0f} us per step'))


def _on_time_line(name, runs, smoke, note):
    """Print and return the line of an on-time fraction (information: the host's as well)."""
    return ratio_line(
        'P2', name, [r['on_time'] for r in runs], '>=', None, unit='', smoke=smoke,
        note=f'{sum(r["late_commands"] for r in runs)} late of '
             f'{sum(r["checked"] for r in runs)} steps; {note}')


def _versus_bare(figures, layout, rate_name, res, bare, smoke):
    """Add the figures of the nodes against the bare loop at the run's rate, per pair."""
    figures.append(_on_time_line(
        f'on_time_fraction_at_{rate_name}[{layout},bare]', bare, smoke,
        f'round trip median {summary([b["loop_median_us"] for b in bare])["median"]:.0f} us, '
        f'p99 {summary([b["loop_p99_us"] for b in bare])["median"]:.0f} us'))
    figures.append(ratio_line(
        'P2', f'on_time_fraction_nodes-bare_at_{rate_name}[{layout}]',
        [r['on_time'] - b['on_time'] for r, b in zip(res, bare)], '>=', -0.005, unit='',
        smoke=smoke, note="per pair of runs: the nodes' on-time fraction minus the bare "
                          "loop's, the same host in the same minute"))


def _sweep(probe, loops, bisections, layout, log, max_probes=12, steps=SWEEP_STEPS,
           on_time=ON_TIME):
    """
    Return ``{loop: {'highest_hz', 'missed_hz', 'probes'}}``: the highest rate held on time.

    ``probe(loop, hz, k)`` runs one short run and returns its result: ``steps`` steps
    judged after the warm-up. A rate holds when at most ``(1 - on_time)`` of the judged
    steps were late (10 of 10000; one step is the resolution). Each loop goes up by
    SWEEP_FACTOR from SWEEP_START to the first rate that misses (or SWEEP_MAX), down
    by it to the first that holds (or SWEEP_MIN) when SWEEP_START misses, then bisects
    geometrically between the two, ``bisections`` times at most and until missed / held
    is SWEEP_RESOLUTION or less; ``max_probes`` runs per loop at most. The loops are
    probed in turn, the order reversed from one round to the next, so that each meets
    the host's minutes as the others do.
    """
    found = {loop: {'highest_hz': float('nan'), 'missed_hz': float('nan'), 'probes': [],
                    'next': SWEEP_START, 'left': bisections} for loop in loops}
    k = 0
    rnd = 0
    while any(f['next'] is not None for f in found.values()):
        for loop in (loops if rnd % 2 == 0 else loops[::-1]):
            f = found[loop]
            hz = f['next']
            if hz is None:
                continue
            res = probe(loop, hz, k)
            k += 1
            late, judged = res['judged_late'], res['judged_steps']
            # NaN (never closed, or nothing judged): missed
            held = judged > 0 and late <= (1.0 - on_time) * judged
            f['probes'].append({'rate_hz': hz, 'on_time': res['judged_on_time'],
                                'late': late, 'judged': judged,
                                'warmup_late': res['warmup_late'],
                                'late_after_short_step': res['judged_late_short'],
                                'late_windows': res['late_windows'],
                                'late_window_max': res['late_window_max'],
                                'loop_median_us': res['loop_median_us'],
                                'loop_max_us': res['loop_max_us']})
            log(f'  P2 sweep {layout} [{loop}] {hz:.0f} Hz: {late} late of {judged} judged '
                f'(on time {res["judged_on_time"]:.5f}): {"held" if held else "missed"}; '
                f'{res["warmup_late"]} late in the {res.get("warmup_s", 0):g} s warm-up; '
                f'the judged late: {res["judged_late_short"]} after a short step, in '
                f'{res["late_windows"]} windows of 0.25 s (at most {res["late_window_max"]} '
                f'in one); round trip median {res["loop_median_us"]:.0f} us, max '
                f'{res["loop_max_us"]:.0f} us'
                + ('; a node left the events executor (flood)' if res.get('flood_fallback')
                   else ''))
            if held:
                f['highest_hz'] = hz if f['highest_hz'] != f['highest_hz'] else \
                    max(f['highest_hz'], hz)
            else:
                f['missed_hz'] = hz if f['missed_hz'] != f['missed_hz'] else \
                    min(f['missed_hz'], hz)
            lo, hi = f['highest_hz'], f['missed_hz']
            if hi != hi:                        # no miss yet: up
                f['next'] = hz * SWEEP_FACTOR if hz * SWEEP_FACTOR <= SWEEP_MAX else None
            elif lo != lo:                      # nothing held yet: down
                f['next'] = hz / SWEEP_FACTOR if hz / SWEEP_FACTOR >= SWEEP_MIN else None
            elif f['left'] > 0 and hi / lo > SWEEP_RESOLUTION:
                f['left'] -= 1
                f['next'] = round((lo * hi) ** 0.5)
            else:
                f['next'] = None
            if len(f['probes']) >= max_probes:
                f['next'] = None
        rnd += 1
    for f in found.values():
        del f['next'], f['left']
    return found


def _sweep_figure(figures, layout, found, bare, smoke, on_time=ON_TIME):
    """Add the figure of the sweep: the nodes' highest rate held / the bare loop's."""
    nodes, base = found.get('nodes'), found.get('bare')
    if nodes is None or base is None:
        for loop, f in found.items():
            figures.append(ratio_line(
                'P2', f'highest_rate_on_time[{layout},{loop}]', [f['highest_hz']], '>=',
                None, unit=' Hz', smoke=smoke,
                note=f'{on_time:.1%} of the steps on time; first rate missed '
                     f'{f["missed_hz"]:.0f} Hz'))
        return
    relay = summary([b['loop_median_us'] for b in bare])['median'] if bare else float('nan')

    def bounds(f, g):
        # the ratio lies between (held / missed) and (missed / held) of the two loops
        return (f'[{f["highest_hz"] / g["missed_hz"]:.2f}..'
                f'{f["missed_hz"] / g["highest_hz"]:.2f}]')

    if 'baseline' in found:
        old = found['baseline']
        figures.append(ratio_line(
            'P2', f'highest_rate_on_time_baseline/bare[{layout}]',
            [old['highest_hz'] / base['highest_hz']], '>=', None, smoke=smoke,
            note=f'the baseline nodes {old["highest_hz"]:.0f} Hz (missed '
                 f'{old["missed_hz"]:.0f}), in the same sweep; bracket '
                 f'{bounds(old, base)}'))
    figures.append(ratio_line(
        'P2', f'highest_rate_on_time_nodes/bare[{layout}]' if on_time == ON_TIME else
        f'highest_rate_on_time@{on_time:g}_nodes/bare[{layout}]',
        [nodes['highest_hz'] / base['highest_hz']], '>=',
        0.9 if on_time == ON_TIME else None, smoke=smoke,
        note=f'the highest step rate with at most {1 - on_time:.1%} of the judged steps '
             f'late: nodes {nodes["highest_hz"]:.0f} Hz (missed {nodes["missed_hz"]:.0f}), '
             f'bare loop {base["highest_hz"]:.0f} Hz (missed {base["missed_hz"]:.0f}); the '
             f'ratio bracketed by the rates missed {bounds(nodes, base)}; bare round trip at '
             f'the main rate {relay:.0f} us'))


def _versus_baseline(figures, runs, base_runs, baseline):
    """Add the figures: this observer's CPU per step / the baseline's, per pair of runs."""
    pairs = [(r['cpu_us_per_step'], b['cpu_us_per_step']) for r, b in zip(runs, base_runs)]
    pairs = [(r, b) for r, b in pairs if 'observer_node' in r and 'observer_node' in b and
             r.get('plant_simulator') and b.get('plant_simulator')]
    if not pairs:
        return
    obs = [r['observer_node'] for r, _ in pairs]
    base = [b['observer_node'] for _, b in pairs]
    figures.append(ratio_line(
        'P2', 'observer_cpu_per_step/baseline_observer[processes]',
        [o / b for o, b in zip(obs, base)], '<=', None,
        note=f'this observer {summary(obs)["median"]:.0f} us, {baseline} '
             f'{summary(base)["median"]:.0f} us per step (medians of the runs)'))
    figures.append(ratio_line(
        'P2', 'observer_cpu_per_simulator_cpu/baseline_observer[processes]',
        [(r['observer_node'] / r['plant_simulator']) /
         (b['observer_node'] / b['plant_simulator']) for r, b in pairs], '<=', None,
        note="each run's observer CPU divided by its simulator's (the same code in both "
             "runs): the host's speed from one run to the next cancels"))


def main(argv=None):
    parser = common_parser(__doc__.splitlines()[1])
    parser.add_argument('--runs', type=int, help='closed-loop runs (default 3)')
    parser.add_argument('--duration', type=float,
                        help='seconds per run, start-up included (default 15)')
    parser.add_argument('--rate', type=float, default=1000.0, help='step rate, Hz')
    parser.add_argument('--configs', metavar='LIST',
                        help='comma-separated LAYOUT or LAYOUT@fifoN (the nodes run with '
                             f'SCHED_FIFO priority N; needs the right to), LAYOUT one of '
                             f'{", ".join(LAYOUTS)}; default {",".join(CONFIGS)}')
    parser.add_argument('--nodes-pythonpath', metavar='DIR',
                        help='run the nodes with this copy of observer_ros first on '
                             'PYTHONPATH (to measure a previous version)')
    parser.add_argument('--observer-pythonpath', metavar='DIR',
                        help='in the processes layout, run the observer alone with this '
                             'copy first on PYTHONPATH (the simulator and compensator '
                             'with --nodes-pythonpath): which node a difference comes from')
    parser.add_argument('--baseline-observer-pythonpath', metavar='DIR',
                        help='after (or before) each processes run, run it again with the '
                             'observer of this copy (e.g. git archive of an earlier commit) '
                             'and report the observer CPU per step against it')
    parser.add_argument('--loops', default=','.join(LOOPS[:2]),
                        help="comma-separated, of: nodes (the package's), bare (relays in "
                             'place of the observer and compensator); default both')
    parser.add_argument('--baseline-nodes-pythonpath', metavar='DIR',
                        help='also run the loop with the observer and compensator of this '
                             'copy (e.g. git archive of an earlier commit; the simulator '
                             'stays this one) beside the others, in the sweep too')
    parser.add_argument('--sweep', metavar='LAYOUTS', default=None,
                        help='comma-separated layouts (of ' + ', '.join(BARE) + ') whose '
                             'loops get the rate sweep: the highest rate with 99.9 %% on '
                             'time (default: processes; "none" for no sweep)')
    parser.add_argument('--sweep-steps', type=int,
                        help=f'steps judged per rate of the sweep (default {SWEEP_STEPS}: '
                             f'a rate holds with at most {(1 - ON_TIME) * 100:.1f} %% of them '
                             'late)')
    parser.add_argument('--sweep-on-time', type=float, default=ON_TIME,
                        help='the on-time fraction a rate of the sweep must keep (default '
                             f'{ON_TIME}; the figure is judged at the default only)')
    parser.add_argument('--sweep-warmup', type=float,
                        help='seconds of closed loop not judged at the start of each run '
                             f'of the sweep, in every loop alike (default {SWEEP_WARMUP:g})')
    parser.add_argument('--sweep-duration', type=float,
                        help='seconds per rate of the sweep (default: the warm-up, the '
                             'steps judged at the rate, and 0.5 s)')
    parser.add_argument('--sweep-bisections', type=int,
                        help='bisections after the first rate missed (default 3, fewer '
                             f'once missed / held <= {SWEEP_RESOLUTION})')
    args = parser.parse_args(argv)
    loops = [x for x in args.loops.split(',') if x]
    if not loops or any(x not in LOOPS[:2] for x in loops):
        parser.error(f'--loops: of {", ".join(LOOPS[:2])}')
    if args.baseline_nodes_pythonpath:
        loops.append('baseline')
    sweep = args.sweep if args.sweep is not None else 'processes'
    sweep = [] if sweep == 'none' else [x for x in sweep.split(',') if x]
    print('P2: closed loop in free-running real time', flush=True)
    return report(args.json, run(
        smoke=args.smoke, runs=args.runs, duration=args.duration, rate=args.rate,
        nodes_pythonpath=args.nodes_pythonpath, observer_pythonpath=args.observer_pythonpath,
        baseline_observer=args.baseline_observer_pythonpath,
        configs=[x for x in (args.configs or '').split(',') if x] or None, log=log,
        loops=loops, sweep=sweep, sweep_duration=args.sweep_duration,
        sweep_bisections=args.sweep_bisections,
        baseline_nodes=args.baseline_nodes_pythonpath, sweep_steps=args.sweep_steps,
        sweep_warmup=args.sweep_warmup, sweep_on_time=args.sweep_on_time))


if __name__ == '__main__':
    raise SystemExit(main())
