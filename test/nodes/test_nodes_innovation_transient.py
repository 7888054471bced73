# test_nodes_innovation_transient: the demo's own design is not WARN on /diagnostics.
"""
The observer node given the submarine's closed loop (``make demo``) over DDS.

The gyro messages and commands of test_core_innovation_transient's simulation: while the
estimate converges from its 30 deg error the node says so, then the gyro is consistent
(it was a WARN before the transient was discounted); a bias after that is named.
"""

from bag_cases import GYRO_NOISE, innovation_run
from observer_ros.nodes.common import joint_state
from observer_ros.timeutil import ns_to_sec
import pytest
from ros_helpers import gyro_msg, innovation_status, level_of, observer_under_test, WAIT

pytestmark = pytest.mark.ros      # processes or DDS participants

OK, WARN = 0, 1


def _value(status, key):
    return next((kv.value for kv in status.values if kv.key == key), None)


@pytest.mark.parametrize('fault', [{}, {'bias': 10 * GYRO_NOISE}], ids=['correct', 'bias'])
def test_the_demo_design_is_consistent_after_its_transient(submarine_design, fault,  # noqa: F811
                                                           tmp_path):
    monitor, _, _, _ = innovation_run(submarine_design, steps=350, onset=300, **fault)
    expected = monitor.health('gyro')
    with observer_under_test(tmp_path) as run:
        probe, listener = run.probe, run.listener
        gyro, command = run.pubs['imu/data'], run.pubs['control/u']
        answered = 0
        for topic, _, ns, msg in innovation_run.messages:
            if topic == 'imu/data':                  # the bag's message, as rclpy's
                gyro.publish(gyro_msg(ns, msg.angular_velocity.y))
                answered += 1
                probe.spin_until(lambda: len(listener.estimates) >= answered, WAIT,
                                 f'the answer to the gyro stamped {ns}')
            elif topic == 'control/u':
                command.publish(joint_state(['delta'], msg.position, ns_to_sec(ns)))
            if answered == 100 and topic == 'control/u':         # 5 s: still converging
                probe.spin_until(lambda: (s := innovation_status(listener, 'gyro')) is not None and
                                 _value(s, 'transient_samples') == '100', WAIT,
                                 'the status after 100 gyro messages')
                status = innovation_status(listener, 'gyro')
                assert level_of(status) == OK
                assert 'estimate converging' in status.message, status.message
        probe.spin_until(lambda: (s := innovation_status(listener, 'gyro')) is not None and
                         _value(s, 'samples') == str(expected.samples), WAIT,
                         'the status after the last gyro message')
        status = innovation_status(listener, 'gyro')
        assert _value(status, 'transient_samples') == str(expected.transient)
        if fault:
            assert level_of(status) == WARN
            assert status.message.startswith('gyro: residuals too large'), status.message
        else:
            assert level_of(status) == OK
            assert status.message == 'gyro: consistent'
