# test/nodes/test_compensator_callback.py: the compensator's estimate callback in process.
"""
The compensator node's hot path, called in process (not spun; no DDS peers).

The commands it sends equal numpy's control law with and without binding limits (the
plant's time the loop reads for delay compensation is tested in
test_core_loop_supervisor.py, without a node).
"""

import math
import os
import subprocess
import sys

import numpy as np
from observer_ros.core.errors import ObserverError
from observer_ros.nodes.common import vector_from_joint_state
import pytest
from ros_helpers import CONFIG, DOMAIN_ID, REPO, WAIT
from sensor_msgs.msg import JointState

SCRIPT = """
import sys, time, warnings
warnings.filterwarnings('ignore')
import numpy as np
import rclpy
from builtin_interfaces.msg import Time
from sensor_msgs.msg import JointState
from observer_ros.core.control_law import control_law
from observer_ros.nodes.compensator import CompensatorNode
from observer_ros.timeutil import stamp_to_sec
config, case = sys.argv[1], sys.argv[2]
extra = ['-p', 'controller.u_min:=[-0.05]', '-p', 'controller.u_max:=[0.05]'] \\
    if case == 'limits' else []
rclpy.init(args=['--ros-args', '--params-file', config, '-p', 'simulator.mode:=realtime',
                 '-r', f'__ns:=/callback_{case}'] + extra)
node = CompensatorNode()


def stamped(ns, msg):
    msg.header.stamp = Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)
    return msg


names = list(node.vehicle.plant.state_names)
rng = np.random.default_rng(1)
ns0 = time.time_ns() - 3_600_000_000_000
clipped = 0
for k in range(500):
    x_hat = rng.normal(scale=0.05, size=len(names))
    msg = stamped(ns0 + k * 1_000_000, JointState(name=names, position=x_hat.tolist()))
    node._on_estimate(msg)
    want = control_law(node.K, x_hat, node.x_d, node.Kd, node.u_min, node.u_max)
    got = node.safe.last_command
    assert np.allclose(got, want, rtol=1e-12, atol=1e-15), (k, got, want)
    clipped += int(not np.array_equal(want, control_law(node.K, x_hat, node.x_d, node.Kd)))
assert node._counters.get('commands') == 500, node._counters
assert not node._counters.get('safe_commands'), node._counters
print('clipped', clipped)
node.destroy_node()
rclpy.try_shutdown()
"""

# The cart in realtime: estimates with the measurements, then measurements alone (the
# observer silent); the order in which commands are published and log lines written.
TAKEOVER = """
import sys, warnings
warnings.filterwarnings('ignore')
import rclpy
from builtin_interfaces.msg import Time
from sensor_msgs.msg import JointState
from observer_ros.nodes.compensator import CompensatorNode
from rclpy.serialization import deserialize_message
from observer_ros.timeutil import stamp_to_sec
rclpy.init(args=['--ros-args', '--params-file', sys.argv[1], '-p', 'simulator.mode:=realtime',
                 '-r', '__ns:=/callback_takeover'])
node = CompensatorNode()
# this script feeds the measurements as fast as it runs, not at the plant's rate: a stall
# of the script on a loaded host is no wait of the plant's messages, and the commands'
# lead stays the vehicle's 3 steps
node.loop.plant_clock.extra_steps = lambda now, dt: 0
events = []


class Logger:
    def __getattr__(self, level):
        return lambda text, **kw: events.append(('log', level, text))


node.get_logger = lambda: Logger()
publish = node._cmd_pub.publish
# the command goes out as its CDR bytes (nodes/wire.py)
node._cmd_pub.publish = lambda raw: (events.append(
    ('command', stamp_to_sec(deserialize_message(raw, JointState).header.stamp))), publish(raw))


def stamped(t, msg):
    msg.header.stamp = Time(sec=int(t), nanosec=int(round((t - int(t)) * 1e9)))
    return msg


sensor = node.vehicle.sensors[0]
names = list(node.vehicle.plant.state_names)
for k in range(100, 180):
    t = k / 100.0
    node._on_sensor(sensor, stamped(t, JointState(name=['cart'], position=[0.0])), True)
    if k <= 150:        # the observer's estimate: once the standby is warm, its own
        x = node.loop.standby.at(stamp_to_sec(stamped(t, JointState()).header.stamp)) \
            if node.loop.standby.warm else None
        x = [0.0] * 4 if x is None else x.tolist()
        node._on_estimate(stamped(t, JointState(name=names, position=x)))
for event in events:
    print(*event)
node.destroy_node()
rclpy.try_shutdown()
"""


def _run(config, case, script=SCRIPT):
    env = dict(os.environ, ROS_DOMAIN_ID=str(DOMAIN_ID),
               PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get('PYTHONPATH', '')]))
    out = subprocess.run([sys.executable, '-c', script, str(config), case], env=env,
                         capture_output=True, text=True, timeout=WAIT + 120)
    assert out.returncode == 0, out.stderr[-3000:]
    return out.stdout


@pytest.mark.ros
def test_commands_equal_numpy_law_without_limits():
    assert 'clipped 0' in _run(CONFIG / 'submarine.yaml', 'free')


@pytest.mark.ros
def test_commands_equal_numpy_law_with_binding_limits():
    out = _run(CONFIG / 'submarine.yaml', 'limits')
    clipped = int(out.split('clipped')[1])
    assert 50 < clipped < 500, out           # the limits bound some commands, not all


@pytest.mark.ros
def test_the_standby_takes_over_with_its_command_before_the_log_line():
    """
    The observer silent: the standby's first command is out before the ERROR is written.

    A process's first log line costs tens of milliseconds on a loaded host; written
    before the command, it made the command late at the plant.
    """
    events = _run(CONFIG / 'cart_pendulum.yaml', 'takeover', TAKEOVER).splitlines()
    stale = next(i for i, e in enumerate(events) if 'no estimate within' in e)
    assert events[stale].startswith('log error'), events[stale]
    # the command answering the measurement that found the silence (1.60 s, 0.1 s after
    # the last estimate) came first, stamped with the lead of 3 steps
    kind, stamp = events[stale - 1].split()
    assert kind == 'command' and float(stamp) == pytest.approx(1.63), events[stale - 3:stale + 1]
    kind, stamp = events[-1].split()
    assert kind == 'command' and float(stamp) == pytest.approx(1.82), events[-1]


@pytest.mark.parametrize('bad', [math.nan, math.inf, -math.inf])
def test_estimate_with_a_non_finite_value_is_refused_naming_the_topic(bad):
    names = ['theta', 'w', 'q']
    good = vector_from_joint_state(JointState(name=names, position=[0.1, -2.0, 3e300]),
                                   names, 'state/estimate')
    assert isinstance(good, np.ndarray) and good.tolist() == [0.1, -2.0, 3e300]
    msg = JointState(name=names, position=[0.1, bad, 0.3])
    with pytest.raises(ObserverError, match='state/estimate: non-finite value'):
        vector_from_joint_state(msg, names, 'state/estimate')
