# test_nodes_parameter_storm: a client setting parameters a thousand times a second.
"""
A parameter-set storm does not starve estimation, and a SIGINT during one ends cleanly.

The cart's realtime loop (simulator, observer, compensator) runs while a separate
process sends ``SetParameters`` requests to ``/observer`` (a change of
``observer.poles`` each time, between two valid designs) at 1000 a second for 15 s,
without waiting for the answers. The observer's estimates per measurement during the
storm stay within 10 % of those before it.
"""

import signal
import subprocess
import sys
import time

from diagnostic_msgs.msg import DiagnosticArray
from observer_ros.nodes.common import STATE_QOS
import pytest
from ros_helpers import CONFIG, Probe, Proc, ros_env, WAIT
from sensor_msgs.msg import JointState

pytestmark = [pytest.mark.ros,       # processes or DDS participants
              pytest.mark.realtime]  # realtime closed loops or rates: one at a time

STORM = """
import sys, time, warnings
warnings.filterwarnings('ignore')
import rclpy
from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
from rcl_interfaces.srv import SetParameters
rate, seconds = float(sys.argv[1]), float(sys.argv[2])
rclpy.init()
node = rclpy.create_node('parameter_storm')
client = node.create_client(SetParameters, '/observer/set_parameters')
while not client.wait_for_service(timeout_sec=1.0):
    pass
designs = ([-10.0, -10.0, -20.0, -20.0], [-11.0, -11.0, -21.0, -21.0])


def request(k):
    value = ParameterValue(type=ParameterType.PARAMETER_DOUBLE_ARRAY,
                           double_array_value=designs[k % 2])
    return SetParameters.Request(parameters=[Parameter(name='observer.poles', value=value)])


print('storm start', flush=True)
start = time.monotonic()
sent, answered, applied = 0, [], 0
futures = []
while time.monotonic() - start < seconds:
    due = int((time.monotonic() - start) * rate)
    while sent < due:
        futures.append(client.call_async(request(sent)))
        sent += 1
    rclpy.spin_once(node, timeout_sec=0.0005)
    done = [f for f in futures if f.done()]
    for f in done:
        futures.remove(f)
        r = f.result()
        applied += bool(r and r.results and r.results[0].successful)
        answered.append(r)
print(f'storm sent {sent} answered {len(answered)} applied {applied} '
      f'in {time.monotonic() - start:.1f} s', flush=True)
node.destroy_node()
rclpy.try_shutdown()
"""
LOOP = ('simulator.mode:=realtime', 'simulator.duration:=3000.0', 'diagnostics_period:=0.2')


class CartLoop:
    """The cart's realtime loop, with the simulator's stamps and the estimates counted."""

    def __init__(self, tmp_path):
        self.probe = Probe('storm_probe')
        self.estimates, self.steps = [], []
        self.diagnostics = []
        node = self.probe.node
        node.create_subscription(JointState, 'state/estimate',
                                 lambda m: self.estimates.append(_stamp(m)), STATE_QOS)
        node.create_subscription(JointState, 'state/true',
                                 lambda m: self.steps.append(_stamp(m)), STATE_QOS)
        node.create_subscription(DiagnosticArray, '/diagnostics', self.diagnostics.append, 50)
        self.procs = {name: Proc(name, CONFIG / 'cart_pendulum.yaml', *LOOP, log_dir=tmp_path)
                      for name in ('observer_node', 'compensator', 'plant_simulator')}

    def wait_sim(self, t, what):
        self.probe.spin_until(lambda: self.steps and self.steps[-1] >= t, WAIT, what)

    def answered(self, since, until):
        """Estimates per step of the plant between two plant times."""
        steps = sum(1 for t in self.steps if since <= t < until)
        stamps = {round(t, 6) for t in self.estimates if since <= t < until}
        return len(stamps) / max(steps, 1)

    def counter(self, key):
        for array in reversed(self.diagnostics):
            for status in array.status:
                if status.name.endswith('/observer'):
                    for kv in status.values:
                        if kv.key == key:
                            return int(kv.value)
        return 0

    def close(self):
        for proc in self.procs.values():
            proc.stop()
        self.probe.close()


def _stamp(msg):
    return msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9


@pytest.fixture
def cart_loop(tmp_path):
    loop = CartLoop(tmp_path)
    yield loop
    loop.close()


def _storm(rate, seconds):
    return subprocess.Popen([sys.executable, '-c', STORM, str(rate), str(seconds)],
                            env=ros_env(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True)


def test_a_storm_of_parameter_sets_leaves_the_estimate_rate(cart_loop):
    loop = cart_loop
    loop.wait_sim(6.0, 'the loop running')
    t0 = loop.steps[-1]
    loop.wait_sim(t0 + 5.0, '5 s before the storm')
    before = loop.answered(t0, t0 + 5.0)
    storm = _storm(1000.0, 15.0)
    try:
        assert storm.stdout.readline().startswith('storm start')
        t1 = loop.steps[-1]
        loop.probe.spin_until(lambda: storm.poll() is not None, WAIT + 60, 'the storm')
        t2 = loop.steps[-1]
        out = storm.stdout.read()
    finally:
        if storm.poll() is None:
            storm.kill()
    during = loop.answered(t1, t2)
    print(f'estimates per step: {before:.3f} before, {during:.3f} during the storm '
          f'({t2 - t1:.1f} s of plant time); {out.strip()}; refused '
          f'{loop.counter("parameter_changes_refused")}, applied '
          f'{loop.counter("parameter_changes_applied")}')
    assert storm.returncode == 0, out
    assert during >= 0.9 * before, (before, during, out)
    assert loop.counter('parameter_changes_applied') >= 1
    assert loop.counter('parameter_changes_refused') >= 100
    assert loop.procs['observer_node'].alive()


def test_sigint_during_a_storm_ends_the_observer_cleanly(cart_loop):
    loop = cart_loop
    loop.wait_sim(3.0, 'the loop running')
    storm = _storm(1000.0, 30.0)
    try:
        assert storm.stdout.readline().startswith('storm start')
        started = time.monotonic()
        loop.probe.spin_until(lambda: time.monotonic() - started > 3.0, 30.0, 'the storm')
        observer = loop.procs['observer_node']
        observer.popen.send_signal(signal.SIGINT)
        code = observer.popen.wait(timeout=30.0)
    finally:
        storm.kill()
        storm.wait()
    out = observer.output()
    assert code == 0, out[-3000:]
    assert 'Traceback' not in out and 'SystemError' not in out, out[-3000:]
