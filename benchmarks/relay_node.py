# benchmarks/relay_node.py: P1's and P2's baseline, bare relays with the nodes' topics and QoS.
"""
Bare relays: rclpy nodes with the observer's and the compensator's topics, no estimator.

- ``estimate`` (P1, P2): ``imu/data`` (Imu, sensor-data QoS) in, ``state/estimate`` out at
  once. It republishes each Imu as the JointState the observer node publishes (the
  vehicle's three state names, the three angular rates as positions, the message's stamp
  and frame_id).
- ``command`` (P2): ``state/estimate`` in, ``control/u`` out at once: the JointState the
  compensator publishes (the input's name, u = 0: the submarine is stable open loop; the
  estimate's stamp, which is what the simulator takes for the answer to its step).

Each is built by the package's helper (``nodes.common.joint_state``) with the QoS the
node it stands for subscribes and publishes with, in a process spun as the package's
nodes are (``nodes.runner.make_executor``: the EventsExecutor unless
``OBSERVER_ROS_EXECUTOR`` says otherwise); ``--roles estimate,command`` runs both in one
process and one executor, as ``container observer compensator`` runs the two nodes. So
node / relay is the cost of the estimator, the control law and their bookkeeping over
the middleware's own.

Run: ``python benchmarks/relay_node.py [--roles estimate,command] --ros-args -r
__ns:=/p1_relay``.

"""

import argparse
import sys
import warnings

warnings.filterwarnings('ignore', category=DeprecationWarning)

from observer_ros.nodes.common import (joint_state, SENSOR_SUB_QOS,  # noqa: E402
                                       stamp_to_sec, STATE_PUB_QOS, STATE_QOS, TOPICS)
from observer_ros.nodes.runner import make_executor, spin_until  # noqa: E402
import rclpy  # noqa: E402
from rclpy.executors import ExternalShutdownException  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.utilities import remove_ros_args  # noqa: E402
from sensor_msgs.msg import Imu, JointState  # noqa: E402

STATE_NAMES = ('theta', 'w', 'q')       # config/submarine.yaml model.states
INPUT_NAMES = ('delta',)                # config/submarine.yaml model.inputs


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


class CommandRelay(Node):
    """Answer every estimate with a command-shaped message (u = 0), at once."""

    def __init__(self):
        super().__init__('command_relay')
        self._pub = self.create_publisher(JointState, TOPICS['command'], STATE_PUB_QOS)
        self._sub = self.create_subscription(JointState, TOPICS['estimate'],
                                             self._on_estimate, STATE_QOS)

    def _on_estimate(self, msg):
        u = [0.0 * v for v in msg.position[:len(INPUT_NAMES)]]
        self._pub.publish(joint_state(INPUT_NAMES, u, stamp_to_sec(msg.header.stamp), '',
                                      msg.header.stamp))


ROLES = {'estimate': Relay, 'command': CommandRelay}


def main(args=None):
    """Spin the relays until interrupted."""
    argv = sys.argv if args is None else args
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    parser.add_argument('--roles', default='estimate',
                        help='comma-separated, of: ' + ', '.join(ROLES) + ' (default estimate)')
    own = parser.parse_args(remove_ros_args(argv)[1:])
    roles = [r for r in own.roles.split(',') if r]
    unknown = [r for r in roles if r not in ROLES]
    if unknown or not roles:
        parser.error(f'unknown role(s) {unknown}: choose from {", ".join(ROLES)}')
    rclpy.init(args=argv)
    nodes = [ROLES[r]() for r in roles]
    executor, _ = make_executor()
    for node in nodes:
        executor.add_node(node)
    try:
        spin_until(executor)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        executor.shutdown()
        for node in nodes:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == '__main__':
    sys.exit(main())
