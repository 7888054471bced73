# test_nodes_lockstep_outage: a lock-step run whose observer stops mid-run.
"""
A lock-step run goes on on the compensator's safe commands once no observer is left.

A lock-step simulator waits for each step's answer; the compensator's safe commands while
an estimate publisher is matched would be waited out (and taken by the observer for the
step's input), so none is sent then. Once no estimate publisher is left, they are, and the
simulator applies them: the run goes on to its end.
"""

from observer_ros.nodes.common import SENSOR_SUB_QOS
from observer_ros.timeutil import stamp_to_sec
import pytest
from ros_helpers import CONFIG, Probe, Proc
from sensor_msgs.msg import Imu

pytestmark = pytest.mark.ros

VEHICLE = CONFIG / 'submarine.yaml'
# 200 Hz: the observer's stop lands mid-run (1200 steps, at least 1.5 s of lock-step with it
# here), and the safe commands after it step the plant at that rate
RUN = ('use_sim_time:=true', 'simulator.duration:=6.0', 'simulator.rate_hz:=200.0')


def test_a_lockstep_run_ends_on_safe_commands_once_its_observer_is_gone(tmp_path):
    # the probe reads the gyro, and the simulator waits for it as for the observer: the run
    # (thousands of steps a second while the observer answers) starts once it is matched
    probe = Probe('lockstep_outage_probe')
    stamps = [0.0]
    probe.node.create_subscription(
        Imu, 'imu/data',
        lambda m: stamps.__setitem__(0, max(stamps[0], stamp_to_sec(m.header.stamp))),
        SENSOR_SUB_QOS)
    procs = [Proc('observer_node', VEHICLE, *RUN, log_dir=tmp_path),
             Proc('compensator', VEHICLE, *RUN, log_dir=tmp_path)]
    sim = Proc('plant_simulator', VEHICLE, *RUN[1:], 'wait_for_subscribers:=2',
               log_dir=tmp_path)
    procs.append(sim)
    try:
        probe.spin_until(lambda: stamps[0] >= 1.5, what='the run at t >= 1.5 s (from 1 s)')
        observer = procs[0]
        assert observer.stop() == 0
        probe.spin_until(lambda: not sim.alive(), what="the simulator's run to its end")
        assert 'run complete at t=7.000' in sim.output(), sim.output()
        text = procs[1].output()
        assert 'estimate stale' in text and 'safe command' in text, text
    finally:
        for proc in procs:
            proc.stop()
        probe.close()
