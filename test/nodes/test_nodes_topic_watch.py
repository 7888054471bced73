# Publishers a node cannot hear: an incompatible QoS offer, another message type.
"""The observer names on /diagnostics the topic, the publisher, the offer and what it expects."""

from diagnostic_msgs.msg import DiagnosticStatus
from observer_ros.nodes.topic_watch import describe_qos, level_rank, TopicWatch
import pytest
from rclpy.qos import QoSProfile, ReliabilityPolicy
from ros_helpers import COMMANDS, GYRO, observer_under_test, STATE_QOS
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64


def _wait_status(run, level, *words):
    """Wait for an observer status of ``level`` whose message holds every word."""
    def found():
        status = run.listener.latest_status('observer')
        return status is not None and status.level == level and \
            all(w in status.message for w in words)
    run.probe.spin_until(found, what=f'observer status {level} with {words}')
    return run.listener.latest_status('observer')


@pytest.mark.ros
def test_a_best_effort_command_publisher_is_reported_not_silently_unused(tmp_path):
    with observer_under_test(tmp_path, publish=(GYRO,)) as run:
        node = run.probe.node
        best_effort = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT)
        pub = node.create_publisher(JointState, 'control/u', best_effort)
        status = _wait_status(run, DiagnosticStatus.ERROR, '/control/u', '/probe',
                              'reliability best_effort', 'expects reliability reliable',
                              'not received')
        assert describe_qos(best_effort) in status.message
        # rclpy's QoS event is counted too
        run.listener.wait_counter('observer', 'incompatible_qos /control/u', 1)
        # the publisher gone: no longer reported
        node.destroy_publisher(pub)
        run.probe.spin_until(lambda: '/probe offers' not in
                             run.listener.latest_status('observer').message,
                             what='the problem no longer reported')


@pytest.mark.ros
def test_a_publisher_of_another_type_on_a_sensor_topic_is_named(tmp_path):
    with observer_under_test(tmp_path, publish=(COMMANDS,)) as run:
        run.probe.node.create_publisher(Float64, GYRO[0], 10)
        status = _wait_status(run, DiagnosticStatus.ERROR, '/imu/data', '/probe',
                              'publishes std_msgs/msg/Float64',
                              'expects sensor_msgs/msg/Imu')
        # what the node said before (no data) is kept after the cause
        assert 'predicting only: no data on /imu/data' in status.message


class _Info:
    def __init__(self, node, msg_type, qos):
        self.node_name, self.node_namespace = node, '/'
        self.topic_type, self.qos_profile = msg_type, qos


class _Graph:
    """A node whose graph holds the given publishers."""

    def __init__(self, publishers):
        self.publishers = publishers

    def get_publishers_info_by_topic(self, topic):
        return self.publishers.get(topic, [])


class _Sub:
    topic_name = '/control/u'


def test_problems_are_errors_when_nothing_can_be_heard_else_warnings():
    best_effort = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT)
    js = 'sensor_msgs/msg/JointState'
    graph = _Graph({'/control/u': [_Info('bad', js, best_effort),
                                   _Info('other', 'std_msgs/msg/Float64', STATE_QOS)]})
    watch = TopicWatch(graph)
    watch.add(_Sub(), JointState, STATE_QOS)
    graph.get_logger = lambda: type('L', (), {'warning': lambda self, text: None})()
    found = watch.problems(now=0.0)
    assert [level for level, _ in found] == [DiagnosticStatus.ERROR] * 2
    assert '/bad offers reliability best_effort' in found[0][1]
    assert '/other publishes std_msgs/msg/Float64, this node expects ' + js in found[1][1]
    # one publisher that can be heard: the others are warnings
    graph.publishers['/control/u'].append(_Info('good', js, STATE_QOS))
    assert watch.problems(now=0.1) == found         # asked again only after GRAPH_PERIOD
    found = watch.problems(now=1.0)
    assert [level for level, _ in found] == [DiagnosticStatus.WARN] * 2
    assert level_rank(DiagnosticStatus.ERROR) == 2 and level_rank(2) == 2
