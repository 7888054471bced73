# observer_ros.tools.run_closed_loop: the main job, a recorded closed-loop run of a vehicle.
"""
``observer-run VEHICLE.yaml``: a recorded closed-loop run of a vehicle.

Simulator, observer, compensator and recorder as four processes over DDS, in lock-step,
for the vehicle's simulated duration; the bag is written under bags/runs/ (or ``--out``)
and a summary is read back from it. With ``--evaluate`` the bag is then replayed through
the vehicle's design and other observers.

The vehicle file is checked (loaded and designed) before any process starts.

"""

import argparse
import datetime
import os
from pathlib import Path
import signal
import subprocess
import sys
import time
import warnings

import numpy as np

from . import interrupt
from ..core.errors import error_text, ObserverError, quiet_on_closed_pipe
from ..core.health import Envelope, ENVELOPE_FACTOR, state_scale
from ..core.vehicle_design import design_vehicle
from ..nodes import signals
from ..outputs.folders import check_output, mark_output, MARKER, prepare_output, seal_output
from ..outputs.staging import write_new_file
from ..params_file import regular_file
from ..ros_names import check_domain_id, check_namespace, check_parameter_override
from ..vehicle import (apply_overrides, load_parameters, load_vehicle, parameters_to_yaml,
                       vehicle_from_parameters)

__all__ = ['main', 'run_closed_loop', 'run_limit', 'run_started', 'check_outputs',
           'node_command',
           'stop_process', 'summarize_bag', 'comparison_variants', 'lessons']

NODES = ('plant_simulator', 'observer_node', 'compensator', 'container', 'recorder')

# s (wall): the nodes' start (imports, DDS discovery) before the simulator's first step;
# on a 2-core host at 1-minute load 20-30 it took 20 to 55 s
STARTUP_LIMIT = 180.0

# what the simulator logs at its first step (lock-step or realtime)
_RUN_STARTED = (': lockstep run of ', ': realtime run of ')


def node_command(node, params_file, *ros_args, namespace=None, remaps=(), nodes=()):
    """
    Return the argv that runs one of the package's nodes with a vehicle file.

    The node runs as ``python -m observer_ros.nodes.entry <node>`` with this interpreter,
    which is what the installed console scripts run too (lib/observer_ros/<exe> on a colcon
    install): the stop signals are handled before the node's modules load.
    For ``node='container'``, ``nodes`` names the nodes it runs.

    """
    cmd = [sys.executable, '-W', 'ignore::DeprecationWarning', '-m',
           'observer_ros.nodes.entry', node, *nodes, '--ros-args', '--params-file',
           str(params_file)]
    if namespace:
        cmd += ['-r', f'__ns:={namespace}']
    for remap in remaps:
        cmd += ['-r', remap]
    for arg in ros_args:
        cmd += ['-p', arg]
    return cmd


def run_closed_loop(params_file, bag_path, storage='mcap', namespace=None, overrides=(),
                    timeout=None, log_dir=None, quiet=False, container=False):
    """
    Run the four processes until the simulator finishes; return the bag path.

    Parameters
    ----------
    params_file : path
        The vehicle file.
    bag_path : path
        Bag directory to create (must not exist).
    storage : {'mcap', 'sqlite3'}
        The recorder's storage plugin.
    namespace : str, optional
        Run the vehicle in this namespace.
    overrides : sequence of str
        Extra ``name:=value`` parameters for every node (e.g. ``observer.poles:=[...]``).
    timeout : float, optional
        Wall-time limit in seconds from the simulator's first step (default: 60 s plus
        20 ms per simulated step); the nodes' start before it has its own limit,
        :data:`STARTUP_LIMIT`.
    log_dir : path, optional
        Where each process's output goes (default: next to the bag).
    quiet : bool
        Do not print the bag and log paths at the end.
    container : bool
        Run the observer and the compensator in one process (``container observer
        compensator``) instead of one process each.

    Returns
    -------
    Path

    """
    vehicle = load_vehicle(params_file, overrides=list(overrides))
    if vehicle.simulator.duration == 0.0:
        raise ObserverError(f'{params_file}: simulator.duration: 0 (run until stopped) has no '
                            'end for observer-run; give a duration in s')
    timeout = timeout if timeout is not None else run_limit(params_file, overrides)
    bag_path = Path(bag_path)
    log_dir = Path(log_dir) if log_dir else bag_path.parent / (bag_path.name + '_logs')
    check_outputs([bag_path])
    check_logs(log_dir, bag_path)
    log_files = [log_dir / f'{name}.log' for name in NODES]
    if log_dir.is_dir() and (log_dir / MARKER).exists():
        prepare_output(log_dir, True, 'observer-run')       # the logs of a run without a bag
    else:
        log_dir.mkdir(parents=True, exist_ok=True)
        mark_output(log_dir, 'observer-run')
    common = ['use_sim_time:=true', *overrides]
    procs = {}
    env = dict(os.environ)
    env.setdefault('PYTHONUNBUFFERED', '1')

    def start(name, *args, nodes=()):
        with interrupt.deferred():     # a Ctrl-C now: after the process is recorded
            out = open(log_dir / f'{name}.log', 'x')     # checked above: never overwritten
            procs[name] = (subprocess.Popen(node_command(name, params_file, *args,
                                                         namespace=namespace, nodes=nodes),
                                            stdout=out, stderr=subprocess.STDOUT, env=env,
                                            preexec_fn=signals.block_until_installed),
                           out)

    try:
        start('recorder', *common, f'output:={bag_path}', f'storage:={storage}')
        if container:
            start('container', *common, nodes=('observer', 'compensator'))
        else:
            start('observer_node', *common)
            start('compensator', *common)
        # the simulator waits until the observer and the recorder subscribe to each sensor
        start('plant_simulator', *overrides, 'wait_for_subscribers:=2',
              'wait_for_recorder:=true')
        sim = procs['plant_simulator'][0]
        sim_log = log_dir / 'plant_simulator.log'
        deadline, started = time.monotonic() + STARTUP_LIMIT, False
        while sim.poll() is None:
            if not started and run_started(sim_log):
                deadline, started = time.monotonic() + timeout, True
            if time.monotonic() > deadline and not started:
                raise ObserverError(f'the nodes did not start the run within '
                                    f'{STARTUP_LIMIT:.0f} s; see the logs in {log_dir}')
            if time.monotonic() > deadline:
                raise ObserverError(f'the run did not finish within {timeout:.0f} s of its '
                                    'first step (lock-step waits for every answer; a slow '
                                    'observer, e.g. one designing many gains at its first '
                                    f'steps, needs a longer --timeout); see the logs in '
                                    f'{log_dir}')
            for name, (proc, _) in procs.items():
                if proc.poll() is not None and name != 'plant_simulator':
                    raise ObserverError(f'{name} exited with code {proc.returncode}; '
                                        f'see {log_dir / (name + ".log")}')
            time.sleep(0.05)
        if sim.returncode != 0:
            raise ObserverError(f'plant_simulator exited with code {sim.returncode}; see '
                                f'{log_dir / "plant_simulator.log"}')
    except interrupt.RunInterrupted as err:
        err.exit_codes = _stop_all(procs)
        raise
    finally:
        _stop_all(procs)
        # the logs are this tool's: a rerun replaces them if the run left no bag
        seal_output(log_dir, 'observer-run', [p for p in log_files if p.exists()])
    if not quiet:
        print(f'bag: {bag_path}  (logs: {log_dir})')
    return bag_path


def run_started(log_path):
    """Return True once the simulator's log says it took its first step."""
    try:
        text = Path(log_path).read_text(errors='replace')
    except OSError:
        return False
    return any(marker in text for marker in _RUN_STARTED)


def run_limit(params_file, overrides=()):
    """
    Return the wall-time limit of a run: 60 s plus 20 ms per simulated step.

    The steps are those of the vehicle file with the ``-p`` overrides applied
    (``simulator.duration:=5000.0`` gets the limit of a 5000 s run), and never fewer than
    the file's own (a shortened run keeps the file's margin on a loaded machine).

    """
    steps = 0
    for vehicle in (load_vehicle(params_file), load_vehicle(params_file,
                                                            overrides=list(overrides))):
        steps = max(steps, int(round(vehicle.simulator.duration / vehicle.sample_time)))
    return 60.0 + 0.02 * steps


def check_outputs(paths):
    """Refuse, before anything is made, when one of the paths a run writes exists."""
    for path in map(Path, paths):
        if path.exists() or path.is_symlink():
            raise ObserverError(f'{path} exists; refusing to overwrite it (choose --out or '
                                'move it away)')


def check_logs(log_dir, bag):
    """
    Refuse log files a run would overwrite, unless they are an earlier run's that left no bag.

    The log folder of a run that stopped before its recorder made the bag (a node that
    could not start) does not block the next run with the same ``--out``: observer-run
    recognises its own, unchanged log files (``.observer_ros_output.json``) and replaces
    them. Any other file with a log's name is refused.
    """
    log_dir = Path(log_dir)
    if not bag.exists() and not bag.is_symlink() and (log_dir / MARKER).exists():
        check_output(log_dir, True, 'observer-run')     # names a log changed since
        return
    check_outputs([log_dir / f'{name}.log' for name in NODES])


def _check_planned(bag, evaluate):
    """Check every path ``observer-run`` (with ``--evaluate``) will create."""
    logs = [bag.parent / (bag.name + '_logs')]
    paths = [p for p in _planned_outputs(bag, evaluate) if p.parent not in logs]
    if evaluate:
        slow = bag.parent / (bag.name + '_slow_poles')
        logs.append(slow.parent / (slow.name + '_logs'))
        paths = [p for p in paths if p.parent not in logs]
    check_outputs(paths)
    check_logs(logs[0], bag)
    if evaluate:
        check_logs(logs[1], slow)


def _planned_outputs(bag, evaluate):
    """Return every path ``observer-run`` (with ``--evaluate``) will create."""
    paths = [bag] + [bag.parent / (bag.name + '_logs') / f'{n}.log' for n in NODES]
    if evaluate:
        slow = bag.parent / (bag.name + '_slow_poles')
        paths += [bag.parent / (bag.name + '_eval'), slow, slow.with_name(slow.name + '.yaml')]
        paths += [slow.parent / (slow.name + '_logs') / f'{n}.log' for n in NODES]
    return paths


def _stop_all(procs):
    """
    SIGINT every process still running (the recorder closes its bag), then wait.

    Returns each process's exit status by name; a Ctrl-C meanwhile does not cut it short.
    """
    # the recorder last, so it records everything the others publish while stopping
    order = [n for n in NODES if n != 'recorder'] + ['recorder']
    codes = {}
    with interrupt.deferred():
        for name in order:
            if name not in procs:
                continue
            proc, out = procs[name]
            codes[name] = stop_process(proc)
            out.close()
    return codes


def stop_process(proc, timeout=30.0):
    """
    Stop a node process as Ctrl-C would: SIGINT, then SIGKILL after `timeout` s.

    (A node stopped while it imports its modules, seconds on a loaded machine, exits once
    they are loaded.)

    Parameters
    ----------
    proc : subprocess.Popen
        The process (a node started with node_command).
    timeout : float
        Seconds to wait after SIGINT before SIGKILL.

    Returns
    -------
    int
        The exit status.

    """
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    return proc.returncode


def summarize_bag(bag_path, vehicle, namespace=None):
    """
    Read the true state and the estimate back from a bag and summarise the run.

    Returns
    -------
    dict
        ``final_time``, ``final_state``, ``final_estimate``, ``final_error_norm``,
        ``samples`` per topic, per state ``settling_time`` (from the start of the run
        until ``|x - x_d|`` stays within 2 % of the larger of its largest value in the
        run and the state's :func:`run_scale`; None when
        the run diverges or ends outside that band), ``settled`` (that time is within the
        first 90 % of the run), ``final_reference_error`` (the largest ``|x - x_d|`` of the
        run's last tenth and the mean of ``x - x_d`` over it),
        ``lost_steps`` (steps of the vehicle's run, at which a sensor was due, that have
        no estimate or no command in the bag: lost, or timed out and held),
        ``expected_steps`` and ``diverging`` (see :func:`diverging`).

    """
    from ..bag.vectors import read_vector_topic   # rosbags only when needed
    prefix = '/' + namespace.strip('/') + '/' if namespace else '/'
    names = vehicle.plant.state_names
    t_true, x_true = read_vector_topic(bag_path, prefix + 'state/true', names)
    t_est, x_est = read_vector_topic(bag_path, prefix + 'state/estimate', names)
    if not len(t_true) or not len(t_est):
        raise ObserverError(f'{bag_path}: no state/true or state/estimate messages')
    # the last estimate and the true state at its stamp
    i = int(np.searchsorted(t_true, t_est[-1]))
    i = min(i, len(t_true) - 1)
    err = x_true[i] - x_est[-1]
    lost, expected = _lost_steps(bag_path, vehicle, prefix, t_true, t_est)
    x_d = np.zeros(len(names)) if vehicle.controller.reference is None else \
        np.asarray(vehicle.controller.reference, dtype=float)
    scale = run_scale(vehicle)
    growing = diverging(x_true, x_d, scale)
    settle, settled, off = {}, {}, {}
    span = float(t_true[-1] - t_true[0])
    tenth = max(1, len(t_true) // 10)
    for j, name in enumerate(names):
        signed = x_true[:, j] - x_d[j]
        e = np.abs(signed)
        off[name] = (float(np.max(e[-tenth:])), float(np.mean(signed[-tenth:])))
        if growing:
            # a diverging state is not settling, whatever its band
            settle[name], settled[name] = None, False
            continue
        # the 2 % band around the reference, of the motion the file asks for or the
        # state's own, whichever is larger
        band = 0.02 * max(float(np.max(e)), scale[j])
        outside = np.nonzero(e > band)[0]
        if not outside.size:
            settle[name] = 0.0
        elif outside[-1] + 1 < len(t_true):
            settle[name] = float(t_true[outside[-1] + 1] - t_true[0])
        else:
            settle[name] = None     # outside at the end of the run
        # inside for the run's last tenth at least: one sample inside is no verdict
        settled[name] = settle[name] is not None and settle[name] <= 0.9 * span
    return {
        'final_time': float(t_true[-1] - t_true[0]),
        'final_state': x_true[-1].tolist(),
        'final_estimate': x_est[-1].tolist(),
        'final_error_norm': float(np.linalg.norm(err)),
        'settling_time': settle,
        'settled': settled,
        'final_reference_error': off,
        'samples': {'state/true': int(len(t_true)), 'state/estimate': int(len(t_est))},
        'lost_steps': lost,
        'expected_steps': expected,
        'diverging': growing,
    }


def run_scale(vehicle):
    """
    Return the scale of a run's motion, per state: what its errors are judged against.

    The largest magnitude the file gives each state (``simulator.initial_state``,
    ``observer.initial_estimate``, ``controller.reference``); a state none of them moves
    (a velocity, the cart's pendulum angle) takes the largest of the others, and a run with
    none (a regulator started at rest) takes 1: the divergence envelope's file scale
    (``nodes/checks.py``).
    """
    return Envelope(vehicle.plant.state_names, state_scale(vehicle), 'x').file_scale


def diverging(x, x_d=None, scale=None, growth=10.0, factor=ENVELOPE_FACTOR, floor=0.01):
    """
    Return True when a trajectory grows or blows up instead of converging to the reference.

    The error is ``x - x_d``, each state's in units of its ``scale`` (:func:`run_scale`:
    the motion the file asks for), so a cart moved by 1 m from rest is judged by how far it
    is from its 1 m, not by how far it went from x(0) = 0.

    Parameters
    ----------
    x : (N, n) array_like
        The true state, one row per step.
    x_d : (n,) array_like, optional
        The reference (default 0: a regulator).
    scale : (n,) array_like, optional
        The scale of each state's motion (default: the largest ``|x(0)|``, or 1).
    growth : float
        Diverging when the largest scaled error of the last tenth of the run exceeds
        ``growth`` times that of the first tenth (and ``growth * floor``),
    factor : float
        or when a scaled error anywhere exceeds ``factor`` (100: the nodes' divergence
        envelope; a loop that reached 1e57 in its first steps and "decays" from there),
        or a state is not finite.
    floor : float
        The smallest first-tenth error the growth is measured from (a regulator started at
        its reference is not diverging when noise moves it by a few thousandths of its scale).

    Returns
    -------
    bool

    """
    x = np.asarray(x, dtype=float)
    if not np.all(np.isfinite(x)):
        return True
    if not x.size:
        return False
    n = x.shape[1]
    x_d = np.zeros(n) if x_d is None else np.asarray(x_d, dtype=float)
    if scale is None:
        scale = np.full(n, max(float(np.max(np.abs(x[0]))), 1.0))
    err = np.abs(x - x_d) / np.asarray(scale, dtype=float)
    k = max(1, len(x) // 10)
    first = float(np.max(err[:k]))
    last = float(np.max(err[-k:]))
    return last > growth * max(first, floor) or float(np.max(err)) > factor


def _lost_steps(bag_path, vehicle, prefix, t_true, t_est):
    """Count the steps with a sensor due that have no estimate or no command stamped at them."""
    from ..bag.vectors import read_vector_topic
    dt = vehicle.sample_time
    steps = int(round(vehicle.simulator.duration / dt))
    dividers = [max(1, int(s.rate_divider)) for s in vehicle.sensors]
    due = [k for k in range(steps + 1) if any(k % d == 0 for d in dividers)]
    if not len(t_true):
        return len(due), len(due)
    t_cmd, _ = read_vector_topic(bag_path, prefix + 'control/u', vehicle.plant.input_names)

    def stamped(t):
        idx = np.rint((np.asarray(t, dtype=float) - t_true[0]) / dt).astype(np.int64)
        return set(idx.tolist())
    have_est, have_cmd = stamped(t_est), stamped(t_cmd)
    lost = sum(1 for k in due if k not in have_est or k not in have_cmd)
    return lost, len(due)


def _print_summary(vehicle, summary):
    """Print the summary; return the problems of the run (lost steps, divergence)."""
    names = vehicle.plant.state_names
    print(f'\n{vehicle.name}: {summary["final_time"]:.2f} s simulated, '
          f'{summary["samples"]["state/estimate"]} estimates')
    print(f'  final |x - x_hat| = {summary["final_error_norm"]:.3e}')
    for j, name in enumerate(names):
        settle = summary['settling_time'][name]
        if summary['diverging']:
            verdict = 'DIVERGING, not settled'
        elif summary['settled'][name]:
            verdict = f'settled (2%) after {settle:.2f} s'
        else:
            peak, mean = summary['final_reference_error'][name]
            verdict = (f'not settled: x - x_d in the last tenth of the run up to {peak:.3g} '
                       f'(mean {mean:.3g})')
        unit = vehicle.unit('state', name)
        unit = f' {unit}' if unit else ''
        print(f'  {name:>10}: final {summary["final_state"][j]: .6f}{unit}  '
              f'estimate {summary["final_estimate"][j]: .6f}{unit}  {verdict}')
    problems = []
    if summary['lost_steps'] and vehicle.simulator.mode == 'lockstep':
        problems.append(f'{summary["lost_steps"]} of {summary["expected_steps"]} steps have no '
                        'estimate or no command in the bag (lost, or timed out and held): the '
                        'run is not the lock-step closed loop of the design')
    elif summary['lost_steps']:
        print(f'  {summary["lost_steps"]} of {summary["expected_steps"]} steps have no estimate '
              'or no command stamped at them (realtime: the simulator does not wait for them)')
    if summary['diverging']:
        problems.append('the closed loop diverges: the error from the reference grows more than '
                        '10x over the run, or beyond 100 times the scale of the motion (the '
                        'initial state and x_d)')
    for text in problems:
        print(f'  FAILED: {text}')
    return problems


@quiet_on_closed_pipe
def main(argv=None):
    """Entry point of ``observer-run``."""
    warnings.filterwarnings('ignore', category=DeprecationWarning)
    parser = argparse.ArgumentParser(
        prog='observer-run',
        description='Closed-loop run of a vehicle over DDS (simulator, observer, compensator, '
                    'recorder), recorded to a bag and summarised.')
    parser.add_argument('vehicle', nargs='?', default=None,
                        help='vehicle file (default: config/submarine.yaml)')
    parser.add_argument('--out', help='bag directory to create (default bags/runs/<vehicle>_'
                        '<time>)')
    parser.add_argument('--storage', choices=('mcap', 'sqlite3'), default='mcap')
    parser.add_argument('--namespace', help='run the vehicle in this namespace')
    parser.add_argument('--no-clock', action='store_true',
                        help="another vehicle of this ROS graph owns /clock: this one's "
                             'simulator does not publish it (simulator.publish_clock:=false)')
    parser.add_argument('-p', '--param', action='append', default=[], metavar='NAME:=VALUE',
                        help='parameter override for every node, e.g. '
                             '"observer.poles:=[-1.0,-1.1,-1.2]"')
    parser.add_argument('--container', action='store_true',
                        help='run the observer and the compensator in one process')
    parser.add_argument('--timeout', type=float, default=None, metavar='S',
                        help='wall-time limit of the run in seconds from its first step '
                             '(default 60 s plus 20 ms per step; lock-step waits for every '
                             "answer, and a large observer's first steps can take a minute); "
                             f'the nodes start within {STARTUP_LIMIT:.0f} s before it')
    parser.add_argument('--evaluate', action='store_true',
                        help='replay the bag through the design, slower and faster poles and '
                             'the open-loop observer; run the loop again with the slower '
                             'poles; print the comparison')
    args = parser.parse_args(argv)
    if args.no_clock:       # one /clock per ROS graph
        args.param = args.param + ['simulator.publish_clock:=false']
    with interrupt.handling():  # Ctrl-C: the nodes are stopped cleanly, the bag closed
        return _run(args)


def _run(args):
    """Run observer-run's job for the parsed arguments; return the exit status."""
    vehicle_path = Path(args.vehicle) if args.vehicle else _default_vehicle()
    try:
        # names ROS would refuse only once a node is made, after others started
        args.namespace = check_namespace(args.namespace)
        for text in args.param:
            check_parameter_override(text)
        check_domain_id()
        # a pipe (<(cat v.yaml)) is read once: the nodes read a copy of it
        vehicle_path = Path(regular_file(vehicle_path))
        # the file with every -p override, and every output, checked before anything starts
        vehicle = load_vehicle(vehicle_path, overrides=args.param)
        design = design_vehicle(vehicle)
        stamp = datetime.datetime.now().strftime('%Y%m%d_%H%M%S')
        bag = Path(args.out) if args.out else Path('bags/runs') / f'{vehicle.name}_{stamp}'
        _check_planned(bag, args.evaluate)
        bag.parent.mkdir(parents=True, exist_ok=True)
        t0 = time.monotonic()
        if args.timeout is not None and not args.timeout > 0:
            raise ObserverError(f'--timeout must be > 0 s; got {args.timeout}')
        run_closed_loop(vehicle_path, bag, storage=args.storage, namespace=args.namespace,
                        overrides=args.param, container=args.container, timeout=args.timeout)
        print(f'closed loop ran in {time.monotonic() - t0:.1f} s wall time')
        summary = summarize_bag(bag, vehicle, args.namespace)
        problems = _print_summary(vehicle, summary)
        if args.evaluate:
            _evaluate(vehicle_path, vehicle, design, bag, summary, args)
    except (ObserverError, OSError) as err:     # OSError: a read-only or full disk
        print(f'error: {error_text(err)}', file=sys.stderr)
        return 2
    except interrupt.RunInterrupted as err:
        return _interrupted(err)
    return 1 if problems else 0


def _interrupted(err):
    """Say how an interrupted run stopped; return 130 (1 if a node did not exit 0)."""
    codes = ', '.join(f'{name} {code}' for name, code in err.exit_codes.items())
    failed = [name for name, code in err.exit_codes.items() if code != 0]
    print(f'observer-run: {err}' + (f'; node exit statuses: {codes}' if codes else ''),
          file=sys.stderr)
    if failed:
        print(f'error: {", ".join(failed)} did not stop cleanly; see its log', file=sys.stderr)
        return 1
    return 130


def _evaluate(vehicle_path, vehicle, design, bag, summary, args):
    """Replay the bag through several observers, rerun with slow poles, print the lessons."""
    from ..evaluation.evaluator import evaluate_bag, format_table, write_results
    variants = comparison_variants(vehicle, design)
    result = evaluate_bag(bag, vehicle, variants, namespace=args.namespace)
    out = bag.parent / (bag.name + '_eval')
    files = write_results(result, out)
    print()
    print(format_table(result))
    print(f'\nplots and tables: {out}/ ({", ".join(f.name for f in files)})')
    # Seed 000: slow observer poles slow the whole loop: run the loop again with them.
    slow_bag = bag.parent / (bag.name + '_slow_poles')
    slow_file = bag.parent / (bag.name + '_slow_poles.yaml')
    flat = apply_overrides(load_parameters(vehicle_path), variants['slow'])
    vehicle_from_parameters(flat, source=str(slow_file))     # the variant is valid
    write_new_file(slow_file, parameters_to_yaml(flat))     # checked up front, written whole
    print(f'\nclosed loop again with the slow observer poles ({slow_file}) ...')
    run_closed_loop(slow_file, slow_bag, storage=args.storage, namespace=args.namespace,
                    overrides=args.param, quiet=True, container=args.container)
    slow = summarize_bag(slow_bag, vehicle, args.namespace)
    print(lessons(vehicle, design, result, summary, slow))


def comparison_variants(vehicle, design):
    """
    Return the evaluation's comparison: observer poles 6x slower and 5x faster, and open loop.

    Returns
    -------
    dict
        ``{name: [overrides]}`` for ``evaluate_bag``.

    """
    poles = np.asarray(design.observer_poles, dtype=complex)
    kind = vehicle.observer.kind if vehicle.observer.kind in ('full', 'reduced') else 'full'
    variants = {}
    for name, factor in (('slow', 1.0 / 6.0), ('fast', 5.0)):
        p = poles ** factor if vehicle.plant.is_discrete else poles * factor
        variants[name] = [f'observer.type:={kind}', 'observer.gain:=null',
                          f'observer.poles:={_fmt(p.real)}',
                          f'observer.poles_imag:={_fmt(p.imag)}']
    variants['open_loop'] = ['observer.type:=open_loop']
    return variants


def lessons(vehicle, design, result, summary, slow_summary):
    """
    Return the seeds' lessons, read off this run: slow poles, fast poles, the open-loop observer.

    Returns
    -------
    str

    """
    names = vehicle.plant.state_names
    first = names[0]
    lines = ['', "what the seeds' lessons look like on this run:"]
    a, b = (_secs(x['settling_time'][first]) for x in (summary, slow_summary))
    lines.append(f'- slow observer poles slow the whole loop (closed loop, live): {first} '
                 f'settles (2%) in {a} with the design, {b} with the poles 6x slower')
    design_vr, fast_vr = result.variants['design'], result.variants['fast']
    ratios = []
    for name in names:
        d, f = design_vr.states[name]['ss_std'], fast_vr.states[name]['ss_std']
        if d > 0:
            ratios.append((f / d, name, d, f))
    if ratios:
        r, name, d, f = max(ratios)
        lines.append(f'- fast observer poles amplify noise (replay): steady-state spread of '
                     f'{name} {d:.3g} with the design, {f:.3g} with poles 5x faster '
                     f'({r:.1f}x)')
    open_vr = result.variants['open_loop']
    eig = np.linalg.eigvals(vehicle.plant.A)
    unstable = np.any(np.abs(eig) >= 1.0) if vehicle.plant.is_discrete else \
        np.any(eig.real >= 0.0)
    err = open_vr.error
    if err is not None and np.isfinite(err).any():
        norms = np.linalg.norm(np.nan_to_num(err), axis=1)
        k = max(1, len(norms) // 10)
        start, end = float(np.mean(norms[:k])), float(np.mean(norms[-k:]))
        verdict = ('drifts: the plant is unstable' if unstable else
                   "converges only at the plant's own rate (its slowest eigenvalue "
                   f'{max(eig.real):.3g}): no gain to speed it up')
        lines.append(f'- the open-loop observer {verdict}: |x - x_hat| from {start:.3g} '
                     f'(first 10%) to {end:.3g} (last 10%)')
    return '\n'.join(lines)


def _secs(t):
    return 'not within the run' if t is None else f'{t:.2f} s'


def _fmt(values):
    return '[' + ','.join(repr(float(v)) for v in values) + ']'


def _default_vehicle():
    """config/submarine.yaml here, or from the installed share/observer_ros."""
    local = Path('config/submarine.yaml')
    if local.exists():
        return local
    try:
        from ament_index_python.packages import get_package_share_directory
        return Path(get_package_share_directory('observer_ros')) / 'config' / 'submarine.yaml'
    except Exception:   # noqa: BLE001 - fall back to the relative path and its error
        return local


if __name__ == '__main__':
    raise SystemExit(main())
