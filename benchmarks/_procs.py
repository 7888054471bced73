# benchmarks/_procs.py: start and stop the ROS processes of a benchmark.
"""Child processes of a benchmark: started in their own session, stopped by their id."""

import os
from pathlib import Path
import signal
import subprocess
import sys
import time

from _common import REPO, ros_env

__all__ = ['node_command', 'start', 'stop_all']


def node_command(node, *params, namespace=None, vehicle='config/submarine.yaml'):
    """Return the argv of one of the package's nodes with the vehicle file and overrides."""
    cmd = [sys.executable, '-W', 'ignore::DeprecationWarning', '-m',
           f'observer_ros.nodes.{node}', '--ros-args', '--params-file', str(REPO / vehicle)]
    if namespace:
        cmd += ['-r', f'__ns:={namespace}']
    for p in params:
        cmd += ['-p', p]
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
