# The nodes against bad messages, bad files, stale estimates and run-time parameter changes.
"""Each node survives bad input, reports it, and keeps its design unless a change is sound."""

import time

from diagnostic_msgs.msg import DiagnosticStatus
import numpy as np
from observer_ros.nodes.common import joint_state, SENSOR_QOS
from observer_ros.nodes.observer_node import silence_watch_period
from observer_ros.timeutil import stamp_to_sec
import pytest
from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
from rcl_interfaces.srv import SetParameters
from ros_helpers import CONFIG, imu_msg, NODE_PARAMS, observer_under_test, Proc, REALTIME, WAIT
from sensor_msgs.msg import Imu
import yaml


@pytest.mark.ros
def test_observer_survives_every_bad_message(observer_setup):
    proc, probe, listener, pub, cmd = observer_setup
    t = 100.0

    def good(q=0.01):
        nonlocal t
        t += 0.05
        pub.publish(imu_msg(t, q))
        x = listener.estimate_at(t)
        assert np.all(np.isfinite(x))
        return x

    good()
    good()
    # NaN and Inf measurements: skipped, counted
    for bad in (float('nan'), float('inf')):
        pub.publish(imu_msg(t + 0.01, bad))
    listener.wait_counter('observer', 'bad_messages', 2)
    good()
    # a zero stamp: a malformed stamp, refused and counted
    pub.publish(imu_msg(0.0, 0.0))
    listener.wait_counter('observer', 'bad_stamps', 1)
    good()
    # an older stamp (out of order: older than the history, 0.25 s, and less than the
    # clock-jump tolerance back)
    pub.publish(imu_msg(t - 0.4, 0.0))
    listener.wait_counter('observer', 'out_of_order', 1)
    # a duplicate stamp: not corrected twice, the estimate is re-published
    n_before = len(listener.estimates)
    pub.publish(imu_msg(t, 0.5))
    listener.wait_counter('observer', 'duplicates', 1)
    probe.spin_until(lambda: len(listener.estimates) > n_before, 5.0, 're-published estimate')
    np.testing.assert_array_equal(listener.estimates[-1].position,
                                  listener.estimates[-2].position)
    good()
    # a stamp far in the future of the node's clock
    pub.publish(imu_msg(time.time() + 1e6, 0.0))
    listener.wait_counter('observer', 'future_stamps', 1)
    good()
    # commands with unknown names, too few values, or NaN
    for names, values in ((['rudder'], [1.0]), (['delta', 'x'], [1.0]),
                          (['delta'], [float('nan')])):
        msg = joint_state(['delta'], [0.0], t)
        msg.name, msg.position = names, values
        cmd.publish(msg)
    listener.wait_counter('observer', 'bad_commands', 3)
    good()
    # a burst: 50 measurements at once; none is lost by our code (the DDS queue may drop)
    received_before = listener.counter('observer', 'measurements')
    for _ in range(50):
        t += 0.001
        pub.publish(imu_msg(t, 0.0))
    probe.spin_until(lambda: any(abs(stamp_to_sec(m.header.stamp) - t) < 1e-6
                                 for m in listener.estimates), WAIT, 'end of the burst')
    # the clock jumps back (a looping bag): the first two messages back are skipped as
    # outliers, the third in a row is the clock jump: the estimator resets and goes on
    t -= 30.0
    for _ in range(2):
        t += 0.05
        pub.publish(imu_msg(t, 0.0))
    listener.wait_counter('observer', 'far_back_stamps', 2)
    good()
    listener.wait_counter('observer', 'clock_jumps', 1)
    # a sensor that stops: diagnostics warn 'predicting only', and it comes back
    probe.spin_until(lambda: (s := listener.latest_status('observer')) is not None
                     and 'predicting only' in s.message, WAIT, 'a silent-sensor warning')
    good()
    probe.spin_until(lambda: (s := listener.latest_status('observer')) is not None
                     and s.message == 'estimating', WAIT, 'the sensor back')
    assert listener.counter('observer', 'measurements') > received_before
    assert proc.alive(), proc.output()
    assert all(np.all(np.isfinite(m.position)) for m in listener.estimates)


def _set_parameter(probe, node, name, values):
    client = probe.node.create_client(SetParameters, f'/{node}/set_parameters')
    probe.spin_until(client.service_is_ready, WAIT, f'/{node}/set_parameters')
    value = ParameterValue(type=ParameterType.PARAMETER_DOUBLE_ARRAY, double_array_value=values)
    future = client.call_async(SetParameters.Request(
        parameters=[Parameter(name=name, value=value)]))
    probe.spin_until(future.done, WAIT, f'the answer to setting {name}')
    return future.result().results[0]


@pytest.mark.ros
def test_observer_pole_change_is_validated(observer_setup):
    proc, probe, listener, pub, cmd = observer_setup
    result = _set_parameter(probe, 'observer', 'observer.poles', [0.5, -1.0, -2.0])
    assert not result.successful
    assert '0.5' in result.reason and 'stable' in result.reason, result.reason
    result = _set_parameter(probe, 'observer', 'observer.poles', [-1.0, -1.1])
    assert not result.successful and 'observer.poles' in result.reason, result.reason
    result = _set_parameter(probe, 'observer', 'observer.poles', [-1.0, -1.1, -1.2])
    assert result.successful, result.reason
    # the node still estimates with the new gain
    pub.publish(imu_msg(200.0, 0.0))
    assert np.all(np.isfinite(listener.estimate_at(200.0)))
    assert proc.alive()


@pytest.mark.ros
def test_compensator_stale_and_bad_estimates_give_the_safe_command(compensator_setup):
    proc, probe, listener, est = compensator_setup
    names = ['theta', 'w', 'q']
    est.publish(joint_state(names, [0.1, 0.0, 0.0], 5.0))
    probe.spin_until(lambda: any(abs(stamp_to_sec(m.header.stamp) - 5.0) < 1e-9
                                 for m in listener.commands), WAIT, 'a command')
    u = [m for m in listener.commands if abs(stamp_to_sec(m.header.stamp) - 5.0) < 1e-9][0]
    assert u.name == ['delta'] and u.position[0] != 0.0
    # no more estimates: after stale_timeout the safe command (zero) and an ERROR
    listener.wait_counter('compensator', 'safe_commands', 1)
    # the counter (on /diagnostics) can overtake the command it counts (on control/u)
    probe.spin_until(lambda: listener.commands[-1] is not u, WAIT, 'the safe command')
    assert listener.commands[-1].position[0] == 0.0
    probe.spin_until(lambda: (s := listener.latest_status('compensator')) is not None
                     and s.level == DiagnosticStatus.ERROR, WAIT, 'an ERROR on /diagnostics')
    # a non-finite estimate: safe command, the node stays up
    before = listener.counter('compensator', 'bad_estimates')
    est.publish(joint_state(names, [float('nan'), 0.0, 0.0], 6.0))
    listener.wait_counter('compensator', 'bad_estimates', before + 1)
    assert listener.commands[-1].position[0] == 0.0
    # good estimates again: the loop is closed again
    est.publish(joint_state(names, [0.1, 0.0, 0.0], 7.0))
    probe.spin_until(lambda: any(abs(stamp_to_sec(m.header.stamp) - 7.0) < 1e-9
                                 for m in listener.commands), WAIT, 'a command again')
    assert proc.alive()


@pytest.mark.ros
def test_controller_pole_change_is_validated(compensator_setup):
    proc, probe, listener, est = compensator_setup
    result = _set_parameter(probe, 'compensator', 'controller.poles', [0.3, -0.31, -0.32])
    assert not result.successful and 'stable' in result.reason, result.reason
    result = _set_parameter(probe, 'compensator', 'controller.poles', [-1.0, -1.1, -1.2])
    assert result.successful, result.reason
    est.publish(joint_state(['theta', 'w', 'q'], [0.1, 0.0, 0.0], 9.0))
    probe.spin_until(lambda: any(abs(stamp_to_sec(m.header.stamp) - 9.0) < 1e-9
                                 for m in listener.commands), WAIT, 'a command')
    u = [m for m in listener.commands if abs(stamp_to_sec(m.header.stamp) - 9.0) < 1e-9][0]
    # the new gain: K for poles -1, -1.1, -1.2 times x_hat
    from observer_ros.core.design import controller_gain
    from observer_ros.vehicle import load_vehicle
    plant = load_vehicle(CONFIG / 'submarine.yaml').plant
    K = controller_gain(plant.A, plant.B, [-1.0, -1.1, -1.2])
    assert u.position[0] == pytest.approx(-(K @ [0.1, 0.0, 0.0])[0], rel=1e-9)


def _write_vehicle(tmp_path, mutate):
    with open(CONFIG / 'submarine.yaml') as f:
        doc = yaml.safe_load(f)
    mutate(doc['/**']['ros__parameters'])
    path = tmp_path / 'vehicle.yaml'
    path.write_text(yaml.safe_dump(doc))
    return path


@pytest.mark.ros
@pytest.mark.parametrize('node', ['observer_node', 'compensator', 'plant_simulator'])
def test_unusable_file_stops_the_node_before_it_starts(tmp_path, node):
    path = _write_vehicle(tmp_path, lambda p: p['model'].pop('A'))
    proc = Proc(node, path, log_dir=tmp_path)
    code = proc.popen.wait(timeout=60)
    assert code == 2, proc.output()
    # one line, the tools' form: no log line of rcl's before it
    lines = proc.output().strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith('error: ') and 'model.A' in lines[0], lines


@pytest.mark.ros
def test_a_refused_override_is_one_line_naming_both_rates(tmp_path):
    proc = Proc('observer_node', CONFIG / 'submarine.yaml', 'observer.rate_hz:=5000.0',
                log_dir=tmp_path)
    assert proc.popen.wait(timeout=60) == 2, proc.output()
    lines = proc.output().strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith('error: node /observer: observer.rate_hz: '
                                                   '5000 Hz is faster than'), lines


@pytest.mark.ros
def test_undetectable_plant_is_refused_with_the_mode_named(tmp_path):
    """Seed 002, Example 5.15: x3 (eigenvalue 5) is unobservable and unstable."""
    def example_5_15(p):
        p['model'].update(states=['x1', 'x2', 'x3'], inputs=['u'], outputs=['y1', 'y2'],
                          A=[2.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, 5.0],
                          B=[3.0, 0.0, -1.0], C=[1.0, 0.0, 0.0, 1.0, 2.0, 0.0],
                          D=[0.0, 1.0])
        p['sensors'] = {'names': ['s'], 's': {
            'topic': 'measurements', 'type': 'sensor_msgs/msg/JointState',
            'fields': ['position.y1', 'position.y2'], 'outputs': ['y1', 'y2'],
            'noise_std': [0.001, 0.001]}}
        p['observer'] = {'type': 'full', 'poles': [-1.0, -2.0]}
        p['controller'] = {'poles': [-1.0, -2.0, -3.0]}
        p['simulator']['initial_state'] = [0.0, 0.0, 0.0]
    path = _write_vehicle(tmp_path, example_5_15)
    proc = Proc('observer_node', path, log_dir=tmp_path)
    assert proc.popen.wait(timeout=60) == 2, proc.output()
    out = proc.output()
    assert 'x3' in out and '5' in out, out


@pytest.mark.ros
def test_estimate_carries_the_measurement_stamp_to_the_nanosecond(observer_setup):
    """A wall-clock stamp does not survive float seconds; the estimate must carry it as is."""
    proc, probe, listener, pub, cmd = observer_setup
    msg = imu_msg(0.0, 0.01)
    # an hour old: the node publishes no predictions for it (they are for stamps on its
    # clock), which in the same second would be counted as answers below
    msg.header.stamp.sec = int(time.time()) - 3600
    msg.header.stamp.nanosec = 123_456_789
    sec = msg.header.stamp.sec
    assert round((sec + 0.123456789) * 1e9) % 1_000_000_000 != 123_456_789   # float loses it
    pub.publish(msg)
    probe.spin_until(lambda: any(m.header.stamp.sec == sec for m in listener.estimates),
                     10.0, 'the estimate')
    got = [m.header.stamp.nanosec for m in listener.estimates if m.header.stamp.sec == sec]
    assert got[0] == 123_456_789
    # the same message again: a duplicate, answered by re-publishing; the same exact stamp
    pub.publish(msg)
    listener.wait_counter('observer', 'duplicates', 1)
    probe.spin_until(lambda: sum(m.header.stamp.sec == sec for m in listener.estimates) >= 2,
                     10.0, 'the re-published estimate')
    got = [m.header.stamp.nanosec for m in listener.estimates if m.header.stamp.sec == sec]
    assert got == [123_456_789, 123_456_789]


@pytest.mark.ros
def test_silent_sensor_means_predict_only(observer_setup):
    """Stamps on the node's clock; the sensor stops: predictions are published, with a WARN."""
    proc, probe, listener, pub, cmd = observer_setup
    t = time.time()
    pub.publish(imu_msg(t, 0.01))
    listener.estimate_at(t)
    listener.wait_counter('observer', 'predictions', 3)

    def later():
        return [m for m in listener.estimates if stamp_to_sec(m.header.stamp) > t + 0.4]
    # the counter (on /diagnostics) can overtake the predictions (on state/estimate)
    probe.spin_until(lambda: len(later()) >= 3, WAIT, 'three predictions')
    assert all(np.all(np.isfinite(m.position)) for m in later())
    status = listener.latest_status('observer')
    assert status.level == DiagnosticStatus.WARN and 'predicting only' in status.message


@pytest.mark.realtime
@pytest.mark.ros
def test_silence_is_watched_slowly_and_predicted_at_the_rate(tmp_path):
    """
    ``observer.rate_hz`` 200 (a 200 Hz gyro): once it is silent, predictions 5 ms apart; twice.

    While the sensors speak their silence is watched every 50 ms (a tenth of the 0.5 s
    timeout), not at the prediction rate: the timer must switch both ways.
    """
    params = NODE_PARAMS + ('simulator.rate_hz:=200.0', 'observer.rate_hz:=200.0')
    with observer_under_test(tmp_path, params=params) as run:
        pub, listener, probe = run.pubs['imu/data'], run.listener, run.probe
        for _ in range(2):
            t = time.time()
            pub.publish(imu_msg(t, 0.01))
            listener.estimate_at(t)

            def predictions():
                return sorted(s for s in (stamp_to_sec(m.header.stamp)
                                          for m in listener.estimates) if s > t + 0.4)
            probe.spin_until(lambda: len(predictions()) >= 40, WAIT, '40 predictions')
            stamps = predictions()[:40]
            # 5 ms apart (a loaded host skips some periods); watched, they would be 50 ms
            assert np.median(np.diff(stamps)) < 0.025, np.diff(stamps)
            # the first within the timeout and the watch's period (room for a loaded host)
            assert stamps[0] - t < 0.5 + 0.05 + 0.4, stamps[0] - t


def test_silence_watch_period():
    assert silence_watch_period(1000.0, [0.5]) == pytest.approx(0.05)
    assert silence_watch_period(1000.0, [0.5, 0.02]) == pytest.approx(0.002)
    assert silence_watch_period(10.0, [0.5]) == pytest.approx(0.1)     # not faster than it


@pytest.mark.ros
def test_observer_follows_remaps_and_overrides(tmp_path):
    """`-r imu/data:=robot/gyro` points it at another topic; `-p` changes its poles."""
    with observer_under_test(tmp_path, publish=[('robot/gyro', Imu, SENSOR_QOS)],
                             params=[REALTIME, 'observer.poles:=[-2.0, -2.1, -2.2]'],
                             remaps=['imu/data:=robot/gyro']) as run:
        run.pubs['robot/gyro'].publish(imu_msg(50.0, 0.0))
        assert np.all(np.isfinite(run.listener.estimate_at(50.0)))
    out = run.proc.output()
    assert '-2.2, -2.1, -2' in out or '[-2.2' in out, out


@pytest.mark.ros
def test_a_transition_the_state_has_not_is_refused_and_the_node_goes_on(observer_setup):
    """A ChangeState by id, configure while active: refused, counted; the node goes on."""
    from lifecycle_msgs.msg import Transition
    from lifecycle_msgs.srv import ChangeState, GetState
    proc, probe, listener, pub, cmd = observer_setup
    change = probe.node.create_client(ChangeState, '/observer/change_state')
    get = probe.node.create_client(GetState, '/observer/get_state')
    probe.spin_until(lambda: change.service_is_ready() and get.service_is_ready(), WAIT,
                     '/observer/change_state and get_state')
    for transition in (Transition(id=Transition.TRANSITION_CONFIGURE),
                       Transition(id=Transition.TRANSITION_CLEANUP), Transition(id=99)):
        future = change.call_async(ChangeState.Request(transition=transition))
        probe.spin_until(future.done, WAIT, f'the answer to transition {transition.id}')
        assert future.result().success is False, transition
    future = get.call_async(GetState.Request())
    probe.spin_until(future.done, WAIT, 'the state')
    assert future.result().current_state.label == 'active'
    listener.wait_counter('observer', 'refused_transitions', 3)
    seen = len(listener.estimates)
    for k in range(5):
        pub.publish(imu_msg(1.0 + 0.05 * k, 0.0))
    probe.spin_until(lambda: len(listener.estimates) > seen, WAIT, 'estimates after them')
    assert proc.alive(), proc.output()
    assert 'refused: not available from the state' in proc.output()
