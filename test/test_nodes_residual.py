# test_nodes_residual: the observer node's residuals go to whoever subscribes, when they do.
"""
The residual topic over DDS, a subscriber arriving after the node started.

The node counts the residuals' subscribers from the middleware's matched events (not an
rcl call per message): a subscription created while measurements flow gets the residual
of each measurement from then on, stamped as the measurement and named by its outputs.
"""

import time

from observer_ros.nodes.common import SENSOR_QOS, STATE_QOS
from observer_ros.timeutil import stamp_to_ns
from ros_helpers import CONFIG, Probe, Proc
from sensor_msgs.msg import Imu, JointState
from test_nodes_faults import Listener
from test_nodes_late import _gyro


def test_a_late_subscriber_gets_the_residuals(tmp_path):
    proc = Proc('observer_node', CONFIG / 'submarine.yaml', 'simulator.mode:=realtime',
                'diagnostics_period:=0.2', log_dir=tmp_path)
    probe = Probe()
    try:
        listener = Listener(probe)
        node = probe.node
        gyro = node.create_publisher(Imu, 'imu/data', SENSOR_QOS)
        probe.spin_until(lambda: gyro.get_subscription_count() >= 1, 30.0, 'imu/data matched')
        listener.wait_matched('state/estimate')
        ns = time.time_ns() - 10_000_000_000       # in the past of the clock
        sent = 0

        def send():
            nonlocal sent
            sent += 1
            gyro.publish(_gyro(ns + sent * 4_000_000, 0.001 * sent))
            probe.spin_until(lambda: len(listener.estimates) >= sent, 10.0,
                             f'the answer to gyro message {sent}')

        for _ in range(5):                          # nobody listens to the residuals yet
            send()
        residuals = []
        sub = node.create_subscription(JointState, 'observer/residual', residuals.append,
                                       STATE_QOS)
        probe.spin_until(lambda: sub.get_publisher_count() >= 1, 20.0, 'residual matched')
        # the node hears of the subscriber through its matched event: from some message
        # on (within 200 more), every measurement's residual is published
        for _ in range(200):
            send()
            if residuals:
                break
        assert residuals, 'no residual in 200 measurements after the subscription matched'
        first = (stamp_to_ns(residuals[0].header.stamp) - ns) // 4_000_000
        assert 1 <= first <= sent
        for _ in range(5):
            send()
        probe.spin_until(lambda: len(residuals) >= sent - first + 1, 10.0,
                         'the next residuals')
        # one residual per measurement from the first on, each with its message's stamp
        stamps = [stamp_to_ns(m.header.stamp) for m in residuals]
        assert stamps == [ns + k * 4_000_000 for k in range(first, sent + 1)], stamps
        assert all(list(m.name) == ['q'] for m in residuals), residuals[0].name
    finally:
        probe.close()
    assert proc.stop() == 0, proc.output()
