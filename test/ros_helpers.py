# Shared helpers of the tests that start ROS 2 processes.
"""Processes, a probe node and discovery waits for the node tests (no fixed sleeps)."""

import contextlib
import ctypes
import os
from pathlib import Path
import random
import signal
import subprocess
import sys
import time
import warnings

from observer_ros.tools.run_closed_loop import node_command
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor

REPO = Path(__file__).resolve().parents[1]
CONFIG = REPO / 'config'

# One DDS domain per test session, so concurrent runs on the machine do not cross-talk.
DOMAIN_ID = random.SystemRandom().randint(100, 199)

# s: the one deadline of every wait on a condition (discovery, a message, a counter on
# /diagnostics). CI runs 800 tests on a loaded 2-core machine, where discovery alone took
# seconds; every wait ends as soon as its condition holds, so a long deadline costs a
# passing test nothing.
WAIT = 120.0


def _die_with_parent():
    """In the child: get SIGTERM when the test process dies (no stray nodes)."""
    libc = ctypes.CDLL('libc.so.6', use_errno=True)
    libc.prctl(1, signal.SIGTERM)    # PR_SET_PDEATHSIG


def ros_env():
    """Environment of the processes a test starts: this session's DDS domain."""
    env = dict(os.environ)
    env['ROS_DOMAIN_ID'] = str(DOMAIN_ID)
    env['PYTHONUNBUFFERED'] = '1'
    return env


@contextlib.contextmanager
def domain_env():
    """Run code (e.g. run_closed_loop) with this session's domain in os.environ."""
    old = os.environ.get('ROS_DOMAIN_ID')
    os.environ['ROS_DOMAIN_ID'] = str(DOMAIN_ID)
    try:
        yield
    finally:
        if old is None:
            os.environ.pop('ROS_DOMAIN_ID', None)
        else:
            os.environ['ROS_DOMAIN_ID'] = old


class Proc:
    """A node process with its output captured to a file."""

    def __init__(self, node, params_file, *params, namespace=None, log_dir=None, remaps=()):
        log_dir = Path(log_dir or '/tmp')
        self.log_path = log_dir / f'{node}_{os.getpid()}_{time.monotonic_ns()}.log'
        self._log = open(self.log_path, 'w')
        self.popen = subprocess.Popen(
            node_command(node, params_file, *params, namespace=namespace, remaps=remaps),
            stdout=self._log, stderr=subprocess.STDOUT, env=ros_env(),
            preexec_fn=_die_with_parent)

    def alive(self):
        """Return True while the process runs."""
        return self.popen.poll() is None

    def output(self):
        """Return what the process printed so far."""
        if not self._log.closed:
            self._log.flush()
        return self.log_path.read_text()

    def stop(self, sig=signal.SIGINT, timeout=10.0):
        """Send a signal and wait; kill if it does not exit. Return the exit code."""
        if self.popen.poll() is None:
            self.popen.send_signal(sig)
            try:
                self.popen.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                self.popen.kill()
                self.popen.wait()
        self._log.close()
        return self.popen.returncode


class Probe:
    """An in-process node in this session's domain, with waits that spin it."""

    def __init__(self, name='probe'):
        warnings.filterwarnings('ignore', category=DeprecationWarning)
        self.context = Context()
        rclpy.init(context=self.context, domain_id=DOMAIN_ID)
        self.node = rclpy.create_node(name, context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)

    def spin_until(self, predicate, timeout=WAIT, what='condition'):
        """Spin until predicate() is true; fail the test with `what` after timeout."""
        deadline = time.monotonic() + timeout
        while not predicate():
            if time.monotonic() > deadline:
                raise AssertionError(f'timed out after {timeout} s waiting for {what}')
            self.executor.spin_once(timeout_sec=0.02)

    def wait_subscribers(self, topic, count=1, timeout=WAIT):
        """Wait until `count` subscribers see `topic` (discovery, never a sleep)."""
        self.spin_until(lambda: self.node.count_subscribers(topic) >= count, timeout,
                        f'{count} subscriber(s) on {topic}')

    def wait_publishers(self, topic, count=1, timeout=WAIT):
        """Wait until `count` publishers of `topic` are discovered."""
        self.spin_until(lambda: self.node.count_publishers(topic) >= count, timeout,
                        f'{count} publisher(s) of {topic}')

    def wait_matched(self, endpoint, what=None):
        """
        Wait until a publisher or subscription of the probe is matched; return it.

        Matched, not just discovered: a message sent now reaches the other side.
        """
        if hasattr(endpoint, 'get_subscription_count'):
            matched = endpoint.get_subscription_count
        else:
            matched = endpoint.get_publisher_count
        self.spin_until(lambda: matched() >= 1, WAIT, f'{what or endpoint.topic_name} matched')
        return endpoint

    def close(self):
        """Destroy the node and shut the context down."""
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)


def python():
    """Return the interpreter the tests run with (the .venv one)."""
    return sys.executable
