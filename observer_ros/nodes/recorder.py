# observer_ros.nodes.recorder: record a vehicle's topics to a ROS 2 bag with rosbags.
"""
Recorder node: subscribes raw (no deserialisation) and writes a rosbag2 bag.

Topics: the vehicle's sensors, ``state/true``, ``state/estimate``, ``observer/residual``,
``control/u``, ``control/reference``, ``/clock`` and ``/diagnostics`` (resolved in the
node's namespace), plus ``extra_topics`` ("name:pkg/msg/Type"). The storage is mcap
(Jazzy's default) or sqlite3, metadata version 9, each topic's QoS recorded as offered.
Messages are stamped with the node clock at reception (sim time with use_sim_time).

SIGINT or SIGTERM closes the bag cleanly: every message received before the signal is
in it. The writer flushes (mcap: a chunk) every ``flush_period`` seconds, so a SIGKILL
loses at most that much.

"""

from pathlib import Path

from diagnostic_msgs.msg import DiagnosticStatus
from rclpy.qos import DurabilityPolicy, ReliabilityPolicy
from rosbags.interfaces import (Qos, QosDurability, QosHistory, QosLiveliness,
                                QosReliability, QosTime)
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import get_typestore, Stores
from std_msgs.msg import Bool

from ..core.errors import ObserverError
from .common import (LATCHED_QOS, SENSOR_QOS, STATE_PUB_QOS, STATE_QOS, TOPICS, VehicleNode,
                     run_node)

__all__ = ['RecorderNode', 'main', 'recorded_topics']

STORAGES = {'mcap': StoragePlugin.MCAP, 'sqlite3': StoragePlugin.SQLITE3}


def _message_class(msgtype):
    pkg, _, name = msgtype.split('/')
    module = __import__(f'{pkg}.msg', fromlist=[name])
    return getattr(module, name)


def recorded_topics(vehicle):
    """
    Return the (relative name, type, QoS) of every topic a vehicle's run produces.

    Parameters
    ----------
    vehicle : observer_ros.core.spec.Vehicle

    Returns
    -------
    list of tuple

    """
    topics = [(s.topic, s.msg_type, SENSOR_QOS) for s in vehicle.sensors]
    js = 'sensor_msgs/msg/JointState'
    topics += [(TOPICS['true_state'], js, STATE_PUB_QOS),
               (TOPICS['estimate'], js, STATE_PUB_QOS),
               (TOPICS['residual'], js, STATE_PUB_QOS), (TOPICS['command'], js, STATE_PUB_QOS),
               (TOPICS['reference'], js, LATCHED_QOS),
               ('/clock', 'rosgraph_msgs/msg/Clock', STATE_QOS),
               ('/diagnostics', 'diagnostic_msgs/msg/DiagnosticArray', STATE_QOS)]
    return topics


def _bag_qos(qos):
    """Translate an rclpy QoS profile into rosbags' Qos for the metadata."""
    reliable = qos.reliability == ReliabilityPolicy.RELIABLE
    latched = qos.durability == DurabilityPolicy.TRANSIENT_LOCAL
    return Qos(
        history=QosHistory.KEEP_LAST, depth=qos.depth,
        reliability=QosReliability.RELIABLE if reliable else QosReliability.BEST_EFFORT,
        durability=QosDurability.TRANSIENT_LOCAL if latched else QosDurability.VOLATILE,
        deadline=QosTime(sec=0, nsec=0), lifespan=QosTime(sec=0, nsec=0),
        liveliness=QosLiveliness.AUTOMATIC, liveliness_lease_duration=QosTime(sec=0, nsec=0),
        avoid_ros_namespace_conventions=False)


class RecorderNode(VehicleNode):
    """Write the vehicle's topics to a bag."""

    def __init__(self):
        super().__init__('recorder', own_parameters=(
            ('output', ''),                 # bag directory to create (must not exist)
            ('storage', 'mcap'),            # mcap | sqlite3
            ('extra_topics', ['']),         # "name:pkg/msg/Type"
            ('flush_period', 1.0),
        ))
        output = self.param('output')
        if not output:
            raise ObserverError('recorder: parameter output (the bag directory) is required')
        storage = self.param('storage')
        if storage not in STORAGES:
            raise ObserverError(f'recorder: storage must be mcap or sqlite3; got {storage!r}')
        path = Path(output)
        if path.exists():
            raise ObserverError(f'recorder: {path} exists; refusing to overwrite a bag')
        topics = recorded_topics(self.vehicle)
        for entry in self.param('extra_topics'):
            if entry:
                name, _, msgtype = entry.partition(':')
                if not msgtype:
                    raise ObserverError(f'recorder: extra_topics entry {entry!r} is not '
                                        '"name:pkg/msg/Type"')
                topics.append((name, msgtype, STATE_QOS))
        self.typestore = get_typestore(Stores.ROS2_JAZZY)
        self.writer = Writer(path, version=9, storage_plugin=STORAGES[storage])
        self.writer.open()
        self.path = path
        self.counts = {}
        self._subs = []
        for name, msgtype, qos in topics:
            resolved = self.resolve_topic_name(name)
            conn = self.writer.add_connection(resolved, msgtype, typestore=self.typestore,
                                              offered_qos_profiles=[_bag_qos(qos)])
            self.counts[resolved] = 0
            self._subs.append(self.create_subscription(
                _message_class(msgtype), name,
                lambda data, c=conn: self._on_message(c, data), qos, raw=True))
        self.get_logger().info(f'recording {len(topics)} topics to {path} ({storage})')
        self._flush_timer = self.wall_timer(float(self.param('flush_period')), self._flush)
        # 'recorder/ready' (latched) once every recorded topic has a matched publisher, so a
        # simulator started with wait_for_recorder loses nothing to DDS matching
        self._ready_pub = self.create_publisher(Bool, 'recorder/ready', LATCHED_QOS)
        self._ready_timer = self.wall_timer(0.05, self._check_ready)

    def _check_ready(self):
        waiting = [sub.topic_name for sub in self._subs if sub.get_publisher_count() < 1]
        if waiting:
            self.get_logger().info(f'waiting for publishers of {waiting}',
                                   throttle_duration_sec=2.0)
            return
        self._ready_timer.cancel()
        self._ready_pub.publish(Bool(data=True))
        self.get_logger().info('every topic has a publisher: ready')

    def _flush(self):
        """Report the counts; push buffered messages to disk (a SIGKILL loses less)."""
        total = sum(self.counts.values())
        self.publish_diagnostics(DiagnosticStatus.OK, f'recording to {self.path}',
                                 {'messages': total})

    def _on_message(self, connection, data):
        t = self.get_clock().now().nanoseconds
        self.writer.write(connection, t, data)
        self.counts[connection.topic] += 1

    def close(self):
        """Close the bag (idempotent)."""
        if self.writer is not None:
            self.writer.close()
            self.writer = None
            total = sum(self.counts.values())
            self.get_logger().info(f'bag closed: {self.path} ({total} messages)')

    def destroy_node(self):
        """Close the bag, then destroy the node."""
        self.close()
        return super().destroy_node()


def main(args=None):
    """Run the recorder node (rclpy turns SIGINT and SIGTERM into a clean shutdown)."""
    return run_node(RecorderNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
