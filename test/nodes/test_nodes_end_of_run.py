# How a simulated run ends, and who owns /clock when several vehicles share a graph.
"""The simulator ends a realtime run cleanly; peers then stand by, silent; one /clock."""

from diagnostic_msgs.msg import DiagnosticStatus
from observer_ros.nodes.common import STATE_QOS
import pytest
from ros_helpers import CONFIG, Listener, Probe, Proc, WAIT
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState

pytestmark = pytest.mark.ros      # processes or DDS participants

# long enough for the loop to close on a loaded machine (DDS matching can take seconds)
REALTIME = ('simulator.mode:=realtime', 'simulator.duration:=5.0', 'diagnostics_period:=0.2')


@pytest.mark.realtime
def test_realtime_run_ends_cleanly_and_peers_stand_by(tmp_path):
    probe = Probe()
    listener = Listener(probe)
    commands, estimates = [], []
    probe.node.create_subscription(JointState, '/end/control/u', commands.append, STATE_QOS)
    probe.node.create_subscription(JointState, '/end/state/estimate', estimates.append,
                                   STATE_QOS)
    peers = [Proc(node, CONFIG / 'submarine.yaml', *REALTIME, 'use_sim_time:=true',
                  namespace='/end', log_dir=tmp_path)
             for node in ('observer_node', 'compensator')]
    sim = None
    try:
        probe.wait_subscribers('/end/imu/data', timeout=WAIT)
        probe.wait_subscribers('/end/control/u', timeout=WAIT)
        probe.wait_subscribers('/end/state/estimate', timeout=WAIT)
        probe.wait_publishers('/end/state/estimate', timeout=WAIT)
        sim = Proc('plant_simulator', CONFIG / 'submarine.yaml', *REALTIME, namespace='/end',
                   log_dir=tmp_path)
        probe.spin_until(
            lambda: (s := listener.latest_status('/end/compensator')) is not None and
            s.level == DiagnosticStatus.OK, WAIT, 'the compensator closing the loop')
        # the run ends on its own: exit 0, a log line, no FATAL and no traceback
        assert sim.popen.wait(timeout=WAIT) == 0, sim.output()
        out = sim.output()
        assert 'run complete at t=' in out, out
        assert 'FATAL' not in out and 'Traceback' not in out, out
        # the observer names the (resolved) silent topic; the compensator knows the run is
        # over (simulator/run_complete) and sends nothing more
        probe.spin_until(
            lambda: (s := listener.latest_status('/end/observer')) is not None and
            s.level == DiagnosticStatus.WARN and 'no data on /end/imu/data' in s.message,
            WAIT, 'the observer reporting /end/imu/data silent')
        probe.spin_until(
            lambda: (s := listener.latest_status('/end/compensator')) is not None and
            s.level == DiagnosticStatus.OK and 'run complete' in s.message,
            WAIT, 'the compensator standing by')
        sent = len(commands)
        assert sent and estimates, 'no command or estimate heard during the run'
        reports = _reports(listener, '/end/compensator')
        # longer than controller.stale_timeout (0.5 s): five more reports 0.2 s apart
        probe.spin_until(lambda: _reports(listener, '/end/compensator') >= reports + 5, WAIT,
                         'five more compensator reports')
        assert len(commands) == sent, 'commands after the run'
        # one frame for the estimates: the vehicle's base_frame (the submarine's FRD body)
        assert {m.header.frame_id for m in estimates} == {'base_link_frd'}
    finally:
        probe.close()
        codes = {p.log_path.name: p.stop() for p in peers}
        if sim is not None:
            sim.stop()
    assert set(codes.values()) == {0}, codes
    for peer in peers:      # nothing to warn about once the run is over
        assert 'ahead of the clock' not in peer.output(), peer.output()


def _reports(listener, node_name):
    """Return how many /diagnostics reports of a node the listener heard."""
    return sum(1 for array in listener.diagnostics for status in array.status
               if status.name == node_name)


def test_zero_duration_runs_until_stopped(tmp_path):
    probe = Probe()
    sim = Proc('plant_simulator', CONFIG / 'submarine.yaml', 'simulator.mode:=realtime',
               'simulator.duration:=0.0', 'simulator.realtime_factor:=20.0',
               namespace='/forever', log_dir=tmp_path)
    clocks = []
    probe.node.create_subscription(Clock, '/clock', clocks.append, 10)
    try:
        # 40 s of simulated time: longer than the file's 30 s duration, still running
        probe.spin_until(lambda: clocks and clocks[-1].clock.sec >= 41, WAIT,
                         '/clock past 41 s')
        assert sim.alive(), sim.output()
    finally:
        probe.close()
    assert sim.stop() == 0, sim.output()


def test_two_vehicles_share_one_clock(tmp_path):
    """The vehicle that owns time publishes /clock; the other (publish_clock false) not."""
    probe = Probe()
    clocks = []
    sub = probe.node.create_subscription(Clock, '/clock', clocks.append, 100)
    sims = [Proc('plant_simulator', CONFIG / 'submarine.yaml', 'simulator.mode:=realtime',
                 'simulator.duration:=0.0', f'simulator.publish_clock:={owner}',
                 namespace=ns, log_dir=tmp_path)
            for ns, owner in (('/sub1', 'true'), ('/sub2', 'false'))]
    try:
        # both simulators are up (their sensors are in the graph) and stepping
        probe.wait_publishers('/sub1/imu/data', timeout=WAIT)
        probe.wait_publishers('/sub2/imu/data', timeout=WAIT)
        probe.spin_until(lambda: sub.get_publisher_count() >= 1, WAIT, '/clock matched')
        probe.spin_until(lambda: len(clocks) >= 200, WAIT, '200 /clock messages')
        assert probe.node.count_publishers('/clock') == 1
        times = [m.clock.sec + m.clock.nanosec * 1e-9 for m in clocks]
        # one time source: it never goes back (two would interleave 52, 310, 52, ...)
        assert all(b > a for a, b in zip(times, times[1:])), times[:20]
    finally:
        probe.close()
        codes = [sim.stop() for sim in sims]
    assert codes == [0, 0], [sim.output() for sim in sims]
