# test_nodes_lockstep_start: a recorded lock-step run starts only once the bag has step 0.
"""
The lock-step simulator holds step 0 until the recorder has its estimate and command.

The recorder is ready when its readers have matched every publisher, but the observer's
and the compensator's writers may not have matched its readers yet; their first messages
would not be recorded. Here a probe plays the recorder (recorder/ready, recorder/heard),
the observer (a publisher of state/estimate) and the compensator (the commands).
"""

import json

from observer_ros.nodes.common import LATCHED_QOS, SENSOR_SUB_QOS, STATE_PUB_QOS, STATE_QOS
from observer_ros.timeutil import stamp_to_sec
import pytest
from ros_helpers import CONFIG, Probe, Proc
from sensor_msgs.msg import Imu, JointState
from std_msgs.msg import Bool, String

pytestmark = pytest.mark.ros


def test_step_0_is_held_until_the_recorder_has_its_estimate_and_command(tmp_path):
    probe = Probe('lockstep_start_probe')
    node = probe.node
    true, imu = [], []
    node.create_subscription(JointState, 'state/true',
                             lambda m: true.append(stamp_to_sec(m.header.stamp)), STATE_QOS)
    cmd = node.create_publisher(JointState, 'control/u', STATE_PUB_QOS)
    est = node.create_publisher(JointState, 'state/estimate', STATE_PUB_QOS)
    node.create_subscription(JointState, 'state/estimate', lambda m: None, STATE_QOS)
    ready = node.create_publisher(Bool, 'recorder/ready', LATCHED_QOS)
    heard = node.create_publisher(String, 'recorder/heard', LATCHED_QOS)

    def answer(msg):
        """Answer each measurement (the observer and the compensator in one)."""
        imu.append(stamp_to_sec(msg.header.stamp))
        u = JointState(name=['delta'], position=[0.0])
        u.header.stamp = msg.header.stamp
        est.publish(JointState(header=msg.header, name=['theta', 'w', 'q'],
                               position=[0.0, 0.0, 0.0]))
        cmd.publish(u)
    node.create_subscription(Imu, 'imu/data', answer, SENSOR_SUB_QOS)
    recording = ['/state/true', '/state/estimate', '/control/u', '/imu/data']

    def say(*topics):
        heard.publish(String(data=json.dumps({'recording': recording, 'heard': list(topics)})))
    ready.publish(Bool(data=True))
    say('/state/true')
    sim = Proc('plant_simulator', CONFIG / 'submarine.yaml', 'simulator.mode:=lockstep',
               'simulator.duration:=1.0', 'wait_for_recorder:=true', log_dir=tmp_path)
    try:
        # step 0 answered, and sent again while the bag lacks its estimate and command
        probe.spin_until(lambda: len(imu) >= 3, what='step 0 sent three times')
        assert set(imu) == {imu[0]} and max(true) == imu[0], (imu, true)
        say('/state/true', '/state/estimate')
        probe.spin_until(lambda: len(imu) >= 4, what='step 0 sent a fourth time')
        assert set(imu) == {imu[0]}, imu
        say('/state/true', '/state/estimate', '/control/u')
        probe.spin_until(lambda: max(imu) > imu[0], what='step 1')
        # then every step at once, none held
        probe.spin_until(lambda: max(true) >= imu[0] + 1.0 - 1e-9, what='the end of the run')
    finally:
        probe.close()
        code = sim.stop()
    out = sim.output()
    assert code == 0, out[-2000:]
    # every answer was taken: the hold was the recorder's
    assert 'missing component' not in out and 'no command for step' not in out, out[-2000:]
