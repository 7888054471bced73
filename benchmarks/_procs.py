# benchmarks/_procs.py: start and stop the ROS processes of a benchmark.
"""Child processes of a benchmark: started in their own session, stopped by their id."""

import os
from pathlib import Path
import signal
import subprocess
import time

from _common import REPO, ros_env

__all__ = ['MODULES', 'node_command', 'start', 'stop_all']


# python -m observer_ros.nodes.<module> for a node: how a copy without nodes/entry.py runs it
MODULES = {'observer_node': 'observer_node', 'observer': 'observer_node',
           'compensator': 'compensator', 'plant_simulator': 'plant_simulator',
           'container': 'container'}


def node_command(node, *params, namespace=None, vehicle='config/submarine.yaml', nodes=(),
                 pythonpath=None):
    """
    Return the argv of one of the package's nodes with the vehicle file and overrides.

    The package's own ``node_command`` (``observer-run`` starts its nodes with it); for
    ``node='container'``, ``nodes`` names the nodes it runs. ``pythonpath``: the copy of
    the package the node will run from; one from before ``observer_ros.nodes.entry``
    runs the node's own module (``python -m observer_ros.nodes.observer_node``).

    """
    from observer_ros.tools.run_closed_loop import node_command as package_command
    cmd = package_command(node, REPO / vehicle, *params, namespace=namespace, nodes=nodes)
    if pythonpath and not (Path(pythonpath) / 'observer_ros' / 'nodes' / 'entry.py').exists():
        i = cmd.index('observer_ros.nodes.entry')
        cmd[i:i + 2] = [f'observer_ros.nodes.{MODULES[node]}']
    return cmd


def start(cmd, log_path, pythonpath=None):
    """Start a process (own session, output to log_path) with the benchmark's ROS domain."""
    env = ros_env()
    cwd = REPO
    if pythonpath:
        env['PYTHONPATH'] = os.pathsep.join([str(pythonpath), env.get('PYTHONPATH', '')])
        cwd = Path(log_path).parent        # python -m puts the cwd first on sys.path
    log = open(log_path, 'w')
    proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env, cwd=cwd,
                            start_new_session=True)
    proc._bench_log = log
    return proc


def stop_all(procs, timeout=5.0):
    """SIGINT each process (its own process group, by id), then SIGKILL what is left."""
    for p in procs:
        if p.poll() is None:
            try:
                os.killpg(p.pid, signal.SIGINT)
            except ProcessLookupError:
                pass
    deadline = time.monotonic() + timeout
    for p in procs:
        try:
            p.wait(max(0.1, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            try:
                os.killpg(p.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            p.wait(2.0)
        log = getattr(p, '_bench_log', None)
        if log is not None:
            log.close()
