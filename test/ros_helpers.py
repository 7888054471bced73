# Shared helpers of the tests that start ROS 2 processes.
"""Processes, a probe node, discovery waits and one set-up for the node tests (no sleeps)."""

import contextlib
import ctypes
import fcntl
import os
from pathlib import Path
import random
import shutil
import signal
import subprocess
import sys
import time
import warnings

from diagnostic_msgs.msg import DiagnosticArray
import numpy as np
from observer_ros.nodes.common import SENSOR_QOS, STATE_QOS
from observer_ros.timeutil import sec_to_stamp_parts, stamp_to_sec
from observer_ros.tools.run_closed_loop import node_command
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from sensor_msgs.msg import Imu, JointState

REPO = Path(__file__).resolve().parents[1]
CONFIG = REPO / 'config'
SUBMARINE = CONFIG / 'submarine.yaml'

# The parameters of the nodes a test starts unless it says otherwise: no lock-step waiting
# for commands, and diagnostics 5 times a second (waits on their counters end sooner).
REALTIME = 'simulator.mode:=realtime'
NODE_PARAMS = (REALTIME, 'diagnostics_period:=0.2')

# The probe's publishers of the nodes' inputs: (topic, type, QoS).
GYRO = ('imu/data', Imu, SENSOR_QOS)
COMMANDS = ('control/u', JointState, STATE_QOS)
ESTIMATES = ('state/estimate', JointState, STATE_QOS)


# The lowest domain a test process picks itself (make test's realtime stage is given one
# below it); Fast DDS refuses domains above LAST_DOMAIN with its default ports.
FIRST_DOMAIN, LAST_DOMAIN = 100, 232


def _domain_id():
    """
    Return this test process's DDS domain: one per pytest session, one per xdist worker.

    Workers of one run (``pytest -n N``) share a random base (from the run's id) and add
    their index, so they never share a domain; other runs on the machine pick other bases.
    ``OBSERVER_TEST_DOMAIN_ID``, when set, is the domain of every test process (`make test`
    gives its realtime stage one below FIRST_DOMAIN, so that the two stages can run at once).
    """
    fixed = os.environ.get('OBSERVER_TEST_DOMAIN_ID')
    if fixed:
        return int(fixed)
    worker = os.environ.get('PYTEST_XDIST_WORKER', '')
    if not worker.startswith('gw'):
        return random.SystemRandom().randint(FIRST_DOMAIN, FIRST_DOMAIN + 99)
    index = int(worker[2:])
    count = int(os.environ.get('PYTEST_XDIST_WORKER_COUNT', '1'))
    run = os.environ.get('PYTEST_XDIST_TESTRUNUID', '')
    base = random.Random(run).randint(FIRST_DOMAIN, LAST_DOMAIN - count) if run else \
        FIRST_DOMAIN
    return base + index


# One DDS domain per test process, so concurrent runs on the machine do not cross-talk.
DOMAIN_ID = _domain_id()

# A seed for the moments tests draw at random, the same in every xdist worker of one run
# (xdist requires every worker to collect the same test ids), new for each run.
RUN_SEED = os.environ.get('PYTEST_XDIST_TESTRUNUID') or str(os.getpid())

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
    """Environment of the processes a test starts: this test process's DDS domain."""
    env = dict(os.environ)
    env['ROS_DOMAIN_ID'] = str(DOMAIN_ID)
    env['PYTHONUNBUFFERED'] = '1'
    return env


@contextlib.contextmanager
def domain_env():
    """Run code (e.g. run_closed_loop) with this test process's domain in os.environ."""
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
    """An in-process node in this test process's domain, with waits that spin it."""

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


class Listener:
    """Collect the estimates, commands and diagnostics of the nodes under test."""

    def __init__(self, probe):
        self.probe = probe
        self.estimates, self.commands, self.diagnostics = [], [], []
        self.heard_at = {}          # status name -> (monotonic s of its last report, count)
        node = probe.node
        self.subs = {
            'state/estimate': node.create_subscription(
                JointState, 'state/estimate', self.estimates.append, STATE_QOS),
            'control/u': node.create_subscription(
                JointState, 'control/u', self.commands.append, STATE_QOS),
            '/diagnostics': node.create_subscription(
                DiagnosticArray, '/diagnostics', self._on_diagnostics, 50)}

    def _on_diagnostics(self, msg):
        self.diagnostics.append(msg)
        now = time.monotonic()
        for status in msg.status:
            self.heard_at[status.name] = (now, self.heard_at.get(status.name, (0, 0))[1] + 1)

    def wait_alive(self, node_name, timeout=WAIT):
        """Wait for a diagnostics message from the node under test (it is up and matched)."""
        self.probe.spin_until(lambda: self.latest_status(node_name) is not None, timeout,
                              f'diagnostics from {node_name}')

    def wait_matched(self, *topics):
        """Wait until each topic's subscription has a matched publisher."""
        for topic in topics:
            self.probe.wait_matched(self.subs[topic], topic)

    def estimate_at(self, t, timeout=WAIT):
        """Wait for an estimate stamped t; return its values."""
        def found():
            return any(abs(stamp_to_sec(m.header.stamp) - t) < 1e-6 for m in self.estimates)
        self.probe.spin_until(found, timeout, f'an estimate stamped {t}')
        msg = [m for m in self.estimates if abs(stamp_to_sec(m.header.stamp) - t) < 1e-6][-1]
        return np.array(msg.position)

    def counter(self, node_name, key):
        """Latest value of a diagnostics counter of a node (0 if never reported)."""
        for array in reversed(self.diagnostics):
            for status in array.status:
                if status.name.endswith(node_name):
                    for kv in status.values:
                        if kv.key == key:
                            return int(kv.value)
        return 0

    def wait_counter(self, node_name, key, at_least, timeout=WAIT):
        """Wait until a diagnostics counter reaches a value."""
        self.probe.spin_until(lambda: self.counter(node_name, key) >= at_least, timeout,
                              f'{node_name} diagnostics {key} >= {at_least}')

    def latest_status(self, node_name):
        """Return the node's latest DiagnosticStatus."""
        for array in reversed(self.diagnostics):
            for status in array.status:
                if status.name.endswith(node_name):
                    return status
        return None


class NodesUnderTest:
    """
    The node processes a test runs, the probe and its listener and publishers.

    Attributes
    ----------
    procs : list of Proc
        The node processes, in the order they were named.
    probe : Probe
        The test's in-process node.
    listener : Listener
        The probe's subscriptions to the nodes' outputs.
    pubs : dict
        The probe's publishers by topic, each matched before the test starts.

    """

    def __init__(self, procs, probe, listener):
        self.procs, self.probe, self.listener = procs, probe, listener
        self.pubs = {}

    @property
    def proc(self):
        """Return the first (often the only) node process."""
        return self.procs[0]

    def report(self):
        """Return what the listener heard, and each node's state and last log lines."""
        now = time.monotonic()
        heard = [f'{name} ({count}, the last {now - at:.1f} s ago: '
                 f'{self.listener.latest_status(name).message!r})'
                 for name, (at, count) in sorted(self.listener.heard_at.items())]
        lines = [f'the probe heard {len(self.listener.estimates)} estimates, '
                 f'{len(self.listener.commands)} commands, diagnostics from '
                 f'{", ".join(heard) or "nobody"}']
        for proc in self.procs:
            state = 'running' if proc.alive() else f'exited {proc.popen.returncode}'
            log = '\n'.join(proc.output().splitlines()[-40:])
            lines.append(f'--- {proc.log_path.name} ({state}), its last lines:\n{log}')
        return '\n'.join(lines)


@contextlib.contextmanager
def nodes_under_test(tmp_path, *nodes, vehicle=SUBMARINE, params=NODE_PARAMS, remaps=(),
                     publish=(), listen=(), alive=(), probe_name='probe'):
    """
    Run node processes and a probe matched to them; each node must exit 0 after a pass.

    Every wait is on a condition, with the deadline WAIT. A wait that fails says what the
    probe heard and shows each node's last log lines; so does a failing test (on stdout).

    Parameters
    ----------
    tmp_path : pathlib.Path
        The folder of the nodes' logs.
    *nodes : str
        The nodes' executables (``observer_node``, ``compensator``, ...).
    vehicle : pathlib.Path
        Their parameters file.
    params : sequence of str
        The ``name:=value`` overrides of every node.
    remaps : sequence of str
        The ``from:=to`` remappings of every node.
    publish : sequence of tuple
        The ``(topic, type, qos)`` of each probe publisher, waited for until matched.
    listen : sequence of str
        The listener's topics (state/estimate, control/u, /diagnostics) to wait for until
        matched.
    alive : sequence of str
        The node names whose diagnostics to wait for: the node is up, its side of the
        matching done too (a message sent on the probe's side's match alone can be lost).
    probe_name : str
        The probe node's name.

    Yields
    ------
    NodesUnderTest
        The processes, the probe, its listener and its publishers by topic.

    """
    procs = [Proc(node, vehicle, *params, log_dir=tmp_path, remaps=remaps) for node in nodes]
    probe = None
    try:
        probe = Probe(probe_name)
        run = NodesUnderTest(procs, probe, Listener(probe))
        try:
            for topic, msg_type, qos in publish:
                run.pubs[topic] = probe.wait_matched(
                    probe.node.create_publisher(msg_type, topic, qos), topic)
            run.listener.wait_matched(*listen)
            for name in alive:
                run.listener.wait_alive(name)
        except AssertionError as err:
            raise AssertionError(f'{err}\n{run.report()}') from None
        try:
            yield run
        except Exception:
            print(run.report())         # pytest shows it with the failure
            raise
    finally:
        if probe is not None:
            probe.close()
        codes = [proc.stop() for proc in procs]
    for proc, code in zip(procs, codes):
        assert code == 0, proc.output()


def observer_under_test(tmp_path, publish=(GYRO, COMMANDS), **options):
    """
    Run the observer node, its estimates and diagnostics heard: nodes_under_test.

    The probe publishes gyro measurements and commands unless ``publish`` says otherwise;
    ``options`` are those of nodes_under_test.
    """
    return nodes_under_test(tmp_path, 'observer_node', publish=publish,
                            listen=('state/estimate', '/diagnostics'), alive=('observer',),
                            **options)


def compensator_under_test(tmp_path, publish=(ESTIMATES,), **options):
    """
    Run the compensator, its commands and diagnostics heard: nodes_under_test.

    The probe publishes estimates unless ``publish`` says otherwise; ``options`` are those
    of nodes_under_test.
    """
    return nodes_under_test(tmp_path, 'compensator', publish=publish,
                            listen=('control/u', '/diagnostics'), alive=('compensator',),
                            **options)


def made_once(tmp_path_factory, name, make):
    """
    Return the folder ``name``, made by ``make(folder)`` once per test run; read it only.

    In pytest-xdist's workers the first to ask makes it in the run's shared temporary
    folder while the others wait on a lock file beside it; then every worker uses it. In
    one process it is made in the session's temporary folder.
    """
    if os.environ.get('PYTEST_XDIST_WORKER'):
        folder = tmp_path_factory.getbasetemp().parent / name
    else:
        folder = tmp_path_factory.getbasetemp() / name
    done = folder.with_name(f'{name}.done')
    with open(folder.with_name(f'{name}.lock'), 'w') as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not done.exists():
            shutil.rmtree(folder, ignore_errors=True)
            folder.mkdir(parents=True)
            make(folder)
            done.touch()
    return folder


def python():
    """Return the interpreter the tests run with (the .venv one)."""
    return sys.executable


@contextlib.contextmanager
def tmpfs(path, options, what):
    """
    Mount a tmpfs at ``path`` with ``options`` (``size=2m``, ``ro``) for a test; unmount it.

    The test is skipped, saying ``what`` it needed, where mounting is not allowed (not root,
    no mount command).
    """
    import shutil

    import pytest
    if shutil.which('mount') is None:
        pytest.skip(f'no mount command: cannot make {what}')
    path.mkdir(exist_ok=True)
    out = subprocess.run(['mount', '-t', 'tmpfs', '-o', options, 'tmpfs', str(path)],
                         capture_output=True, text=True)
    if out.returncode != 0:
        pytest.skip(f'cannot mount {what} (needs root): {out.stderr.strip()}')
    try:
        yield path
    finally:
        subprocess.run(['umount', '-l', str(path)], check=False)


def processes():
    """Yield ``(pid, ppid, argv)`` of every process on the machine (from /proc)."""
    for entry in Path('/proc').iterdir():
        if not entry.name.isdigit():
            continue
        try:
            ppid = int((entry / 'stat').read_text().rsplit(')', 1)[1].split()[1])
            argv = (entry / 'cmdline').read_bytes().decode(errors='replace').split('\0')
        except (OSError, ValueError, IndexError):
            continue
        yield int(entry.name), ppid, argv


def rss_kib(pid):
    """Return a process's resident set size (VmRSS, KiB)."""
    for line in Path(f'/proc/{pid}/status').read_text().splitlines():
        if line.startswith('VmRSS:'):
            return int(line.split()[1])
    raise AssertionError(f'no VmRSS for process {pid}')


def stamped(msg, ns):
    """Stamp a message ``ns`` nanoseconds; return it."""
    msg.header.stamp.sec = ns // 1_000_000_000
    msg.header.stamp.nanosec = ns % 1_000_000_000
    return msg


def gyro_msg(ns, q):
    """Return a gyro measurement (Imu, q on angular_velocity.y) stamped ``ns``."""
    msg = stamped(Imu(), ns)
    msg.angular_velocity.y = float(q)
    return msg


def innovation_status(listener, sensor):
    """Return the latest innovation status of a sensor (None before one)."""
    for array in reversed(listener.diagnostics):
        for status in array.status:
            if status.name.endswith(f'observer/innovation/{sensor}'):
                return status
    return None


def level_of(status):
    level = status.level
    return level if isinstance(level, int) else int.from_bytes(level, 'little')


def imu_msg(t, q):
    msg = Imu()
    # rounded once to the ns (100.2 - 0.2 is 99.99999999999999: not 99 s + 10^9 ns)
    msg.header.stamp.sec, msg.header.stamp.nanosec = sec_to_stamp_parts(t)
    msg.angular_velocity.y = q
    return msg
