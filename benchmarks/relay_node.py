# benchmarks/relay_node.py: P1's baseline, a bare relay with the observer's topics and QoS.
"""
A bare relay: ``imu/data`` (Imu, sensor-data QoS) in, ``state/estimate`` out at once.

It republishes each Imu as the JointState the observer node publishes (the vehicle's
three state names, the three angular rates as positions, the message's stamp and
frame_id), built by the same helper (``nodes.common.joint_state``) and with the same
QoS (what the observer subscribes and publishes with), in a node spun as the package's
nodes are (``nodes.runner.make_executor``: the EventsExecutor unless
``OBSERVER_ROS_EXECUTOR`` says otherwise). So observer / relay is the cost of the
estimator and its bookkeeping over the middleware's own.

Run: ``python benchmarks/relay_node.py --ros-args -r __ns:=/p1_relay``.

"""

import sys
import warnings

warnings.filterwarnings('ignore', category=DeprecationWarning)

from observer_ros.nodes.common import (joint_state, SENSOR_SUB_QOS,  # noqa: E402
                                       stamp_to_sec, STATE_PUB_QOS, TOPICS)
from observer_ros.nodes.runner import make_executor, spin_until  # noqa: E402
import rclpy  # noqa: E402
from rclpy.executors import ExternalShutdownException  # noqa: E402
from rclpy.node import Node  # noqa: E402
from sensor_msgs.msg import Imu, JointState  # noqa: E402

STATE_NAMES = ('theta', 'w', 'q')       # config/submarine.yaml model.states


class Relay(Node):
    """Republish every measurement as an estimate-shaped message, at once."""

    def __init__(self):
        super().__init__('relay')
        self._pub = self.create_publisher(JointState, TOPICS['estimate'], STATE_PUB_QOS)
        self._sub = self.create_subscription(Imu, 'imu/data', self._on_imu, SENSOR_SUB_QOS)

    def _on_imu(self, msg):
        w = msg.angular_velocity
        self._pub.publish(joint_state(STATE_NAMES, (w.x, w.y, w.z),
                                      stamp_to_sec(msg.header.stamp), msg.header.frame_id,
                                      msg.header.stamp))


def main(args=None):
    """Spin the relay until interrupted."""
    rclpy.init(args=args)
    node = Relay()
    executor, _ = make_executor()
    executor.add_node(node)
    try:
        spin_until(executor)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == '__main__':
    sys.exit(main())
