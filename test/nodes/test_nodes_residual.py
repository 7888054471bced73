# test_nodes_residual: the observer node's residuals go to whoever subscribes, when they do.
"""
The residual topic over DDS, a subscriber arriving after the node started.

The node counts the residuals' subscribers from the middleware's matched events (not an
rcl call per message): a subscription created while measurements flow gets the residual
of each measurement from then on, stamped as the measurement and named by its outputs.
"""

import os
import subprocess
import sys
import time

from observer_ros.nodes.common import STATE_QOS
from observer_ros.timeutil import stamp_to_ns
import pytest
from ros_helpers import CONFIG, DOMAIN_ID, GYRO, gyro_msg, observer_under_test, REPO, WAIT
from sensor_msgs.msg import JointState

pytestmark = pytest.mark.ros      # processes or DDS participants


def test_a_late_subscriber_gets_the_residuals(tmp_path):
    # the probe sends gyro messages only; the observer's diagnostics heard: the node has been
    # up a while, its side of the gyro's match done too
    with observer_under_test(tmp_path, publish=[GYRO]) as run:
        probe, listener, node = run.probe, run.listener, run.probe.node
        gyro = run.pubs['imu/data']
        # an hour in the past of the clock: the stamps (4 ms apart) never reach it, however
        # many messages the wait for the node's matched event takes
        ns = time.time_ns() - 3_600_000_000_000
        sent = 0

        def send():
            nonlocal sent
            sent += 1
            gyro.publish(gyro_msg(ns + sent * 4_000_000, 0.001 * sent))
            probe.spin_until(lambda: len(listener.estimates) >= sent, WAIT,
                             f'the answer to gyro message {sent}')

        for _ in range(5):                          # nobody listens to the residuals yet
            send()
        residuals = []
        sub = node.create_subscription(JointState, 'observer/residual', residuals.append,
                                       STATE_QOS)
        probe.spin_until(lambda: sub.get_publisher_count() >= 1, WAIT, 'residual matched')
        # the node hears of the subscriber through its matched event (its own side of the
        # discovery, which may come later than ours): from some message on, every
        # measurement's residual is published
        deadline = time.monotonic() + WAIT
        while not residuals:
            assert time.monotonic() < deadline, \
                f'no residual in {sent} measurements after the subscription matched'
            send()
        first = (stamp_to_ns(residuals[0].header.stamp) - ns) // 4_000_000
        assert 1 <= first <= sent
        for _ in range(5):
            send()
        probe.spin_until(lambda: len(residuals) >= sent - first + 1, WAIT,
                         'the next residuals')
        # one residual per measurement from the first on, each with its message's stamp
        stamps = [stamp_to_ns(m.header.stamp) for m in residuals]
        assert stamps == [ns + k * 4_000_000 for k in range(first, sent + 1)], stamps
        assert all(list(m.name) == ['q'] for m in residuals), residuals[0].name


FALLBACK = """
import sys, time, warnings
warnings.filterwarnings('ignore')
import rclpy
from rclpy.event_handler import UnsupportedEventTypeError
from sensor_msgs.msg import JointState
from observer_ros.nodes import observer_node
from observer_ros.nodes.common import STATE_QOS
from ros_helpers import gyro_msg


def unsupported(*args, **kwargs):       # a middleware without matched events
    raise UnsupportedEventTypeError('matched events not supported')


observer_node.PublisherEventCallbacks = unsupported
rclpy.init(args=['--ros-args', '--params-file', sys.argv[1], '-p', 'simulator.mode:=realtime',
                 '-r', '__ns:=/residual_fallback'])
node = observer_node.ObserverNode()
assert node._res_pub.subscribers is None, node._res_pub.subscribers
residuals = []
node.create_subscription(JointState, 'observer/residual', residuals.append, STATE_QOS)
sensor = next(s for s in node.vehicle.sensors if s.topic.endswith('imu/data'))
ns = time.time_ns() - 3_600_000_000_000
for k in range(1, 6):
    node._on_measurement(sensor, gyro_msg(ns + k * 4_000_000, 0.001 * k))
deadline = time.monotonic() + float(sys.argv[2])
while len(residuals) < 5 and time.monotonic() < deadline:
    rclpy.spin_once(node, timeout_sec=0.05)
print('residuals', len(residuals))
"""


def test_residuals_without_matched_events():
    # a middleware whose publishers have no matched events: the node still starts, and
    # asks for the residuals' subscribers per message (an in-process subscriber gets them)
    env = dict(os.environ, ROS_DOMAIN_ID=str(DOMAIN_ID),
               PYTHONPATH=os.pathsep.join([str(REPO), str(REPO / 'test'),
                                           os.environ.get('PYTHONPATH', '')]))
    out = subprocess.run([sys.executable, '-c', FALLBACK, str(CONFIG / 'submarine.yaml'),
                          str(WAIT)], env=env, capture_output=True, text=True,
                         timeout=WAIT + 60)
    assert out.returncode == 0, out.stderr[-3000:]
    assert 'residuals 5' in out.stdout, out.stdout + out.stderr[-3000:]
