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

from ..core.errors import ObserverError
from ..core.vehicle_design import design_vehicle
from ..vehicle import (apply_overrides, load_parameters, load_vehicle, parameters_to_yaml,
                       vehicle_from_parameters)

__all__ = ['main', 'run_closed_loop', 'run_limit', 'check_outputs', 'node_command',
           'stop_process', 'summarize_bag', 'comparison_variants', 'lessons']

NODES = ('plant_simulator', 'observer_node', 'compensator', 'container', 'recorder')


def node_command(node, params_file, *ros_args, namespace=None, remaps=(), nodes=()):
    """
    Return the argv that runs one of the package's nodes with a vehicle file.

    The node runs as ``python -m observer_ros.nodes.<node>`` with this interpreter, which is
    what the installed console scripts run too (lib/observer_ros/<exe> on a colcon install).
    For ``node='container'``, ``nodes`` names the nodes it runs.

    """
    cmd = [sys.executable, '-W', 'ignore::DeprecationWarning', '-m',
           f'observer_ros.nodes.{node}', *nodes, '--ros-args', '--params-file',
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
        Wall-time limit in seconds (default: 60 s plus 20 ms per simulated step).
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
    check_outputs([bag_path] + [log_dir / f'{name}.log' for name in NODES])
    log_dir.mkdir(parents=True, exist_ok=True)
    common = ['use_sim_time:=true', *overrides]
    procs = {}
    env = dict(os.environ)
    env.setdefault('PYTHONUNBUFFERED', '1')

    def start(name, *args, nodes=()):
        out = open(log_dir / f'{name}.log', 'x')     # checked above: never overwritten
        procs[name] = (subprocess.Popen(node_command(name, params_file, *args,
                                                     namespace=namespace, nodes=nodes),
                                        stdout=out, stderr=subprocess.STDOUT, env=env), out)

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
        deadline = time.monotonic() + timeout
        while sim.poll() is None:
            if time.monotonic() > deadline:
                raise ObserverError(f'the run did not finish within {timeout:.0f} s (lock-step '
                                    'waits for every answer; a slow observer, e.g. one '
                                    'designing many gains at its first steps, needs a '
                                    f'longer --timeout); see the logs in {log_dir}')
            for name, (proc, _) in procs.items():
                if proc.poll() is not None and name != 'plant_simulator':
                    raise ObserverError(f'{name} exited with code {proc.returncode}; '
                                        f'see {log_dir / (name + ".log")}')
            time.sleep(0.05)
        if sim.returncode != 0:
            raise ObserverError(f'plant_simulator exited with code {sim.returncode}; see '
                                f'{log_dir / "plant_simulator.log"}')
    finally:
        _stop_all(procs)
    if not quiet:
        print(f'bag: {bag_path}  (logs: {log_dir})')
    return bag_path


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


def _planned_outputs(bag, evaluate):
    """Return every path ``observer-run`` (with ``--evaluate``) will create."""
    paths = [bag] + [bag.parent / (bag.name + '_logs') / f'{n}.log' for n in NODES]
    if evaluate:
        slow = bag.parent / (bag.name + '_slow_poles')
        paths += [bag.parent / (bag.name + '_eval'), slow, slow.with_name(slow.name + '.yaml')]
        paths += [slow.parent / (slow.name + '_logs') / f'{n}.log' for n in NODES]
    return paths


def _stop_all(procs):
    """SIGINT every process still running (the recorder closes its bag), then wait."""
    # the recorder last, so it records everything the others publish while stopping
    order = [n for n in NODES if n != 'recorder'] + ['recorder']
    for name in order:
        if name not in procs:
            continue
        proc, out = procs[name]
        stop_process(proc)
        out.close()


def stop_process(proc, timeout=10.0):
    """
    Stop a node process as Ctrl-C would: SIGINT, then SIGKILL after `timeout` s.

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
        ``samples`` per topic, per state ``settling_time`` (2% band around its final
        value, measured from the start of the run; None when the run diverges),
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
    growing = diverging(x_true)
    settle = {}
    for j, name in enumerate(names):
        if growing:
            settle[name] = None   # a diverging state is not settling, whatever its band
            continue
        x = x_true[:, j]
        band = 0.02 * max(np.max(np.abs(x)), 1e-12)
        outside = np.nonzero(np.abs(x - x[-1]) > band)[0]
        settle[name] = float(t_true[outside[-1] + 1] - t_true[0]) if outside.size and \
            outside[-1] + 1 < len(t_true) else 0.0
    return {
        'final_time': float(t_true[-1] - t_true[0]),
        'final_state': x_true[-1].tolist(),
        'final_estimate': x_est[-1].tolist(),
        'final_error_norm': float(np.linalg.norm(err)),
        'settling_time': settle,
        'samples': {'state/true': int(len(t_true)), 'state/estimate': int(len(t_est))},
        'lost_steps': lost,
        'expected_steps': expected,
        'diverging': growing,
    }


def diverging(x, growth=10.0, blow_up=1e6):
    """
    Return True when a trajectory grows or blows up instead of settling.

    Parameters
    ----------
    x : (N, n) array_like
        The true state, one row per step.
    growth : float
        Diverging when the largest ``|x|`` of the last tenth of the run exceeds the
        largest of the first tenth by this factor,
    blow_up : float
        or when ``|x|`` anywhere exceeds ``|x(0)|`` by this factor (a loop that reached
        1e57 in its first steps and "decays" from there), or is not finite.

    Returns
    -------
    bool

    """
    x = np.asarray(x, dtype=float)
    if not np.all(np.isfinite(x)):
        return True
    if not x.size:
        return False
    k = max(1, len(x) // 10)
    first = float(np.max(np.abs(x[:k])))
    last = float(np.max(np.abs(x[-k:])))
    start = float(np.max(np.abs(x[0])))
    return last > growth * max(first, 1e-300) or \
        float(np.max(np.abs(x))) > blow_up * max(start, 1e-300)


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
        verdict = 'DIVERGING, not settled' if settle is None else \
            f'settled (2%) after {settle:.2f} s'
        print(f'  {name:>10}: final {summary["final_state"][j]: .6f}  '
              f'estimate {summary["final_estimate"][j]: .6f}  {verdict}')
    problems = []
    if summary['lost_steps']:
        problems.append(f'{summary["lost_steps"]} of {summary["expected_steps"]} steps have no '
                        'estimate or no command in the bag (lost, or timed out and held): the '
                        'run is not the lock-step closed loop of the design')
    if summary['diverging']:
        problems.append('the closed loop diverges: the true state grows more than 10x over '
                        'the run, or to more than 1e6 times its initial size')
    for text in problems:
        print(f'  FAILED: {text}')
    return problems


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
                        help='wall-time limit of the run in seconds (default 60 s plus 20 ms '
                             'per step; lock-step waits for every answer, and a large '
                             "observer's first steps can take a minute)")
    parser.add_argument('--evaluate', action='store_true',
                        help='replay the bag through the design, slower and faster poles and '
                             'the open-loop observer; run the loop again with the slower '
                             'poles; print the comparison')
    args = parser.parse_args(argv)
    if args.no_clock:       # one /clock per ROS graph
        args.param = args.param + ['simulator.publish_clock:=false']
    vehicle_path = Path(args.vehicle) if args.vehicle else _default_vehicle()
    try:
        # the file with every -p override, and every output, checked before anything starts
        vehicle = load_vehicle(vehicle_path, overrides=args.param)
        design = design_vehicle(vehicle)
        stamp = datetime.datetime.now().strftime('%Y%m%d_%H%M%S')
        bag = Path(args.out) if args.out else Path('bags/runs') / f'{vehicle.name}_{stamp}'
        check_outputs(_planned_outputs(bag, args.evaluate))
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
    except ObserverError as err:
        print(f'error: {err}', file=sys.stderr)
        return 2
    return 1 if problems else 0


def _evaluate(vehicle_path, vehicle, design, bag, summary, args):
    """Replay the bag through several observers, rerun with slow poles, print the lessons."""
    from ..bag.evaluate import evaluate_bag, format_table, write_results
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
    with open(slow_file, 'x') as f:        # checked up front: never overwritten
        f.write(parameters_to_yaml(flat))
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
    return 'never (diverging)' if t is None else f'{t:.2f} s'


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
