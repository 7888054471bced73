# test_nodes_admission: the node and the replay judge every message alike, over DDS.
"""
A realtime closed loop recorded with faults injected; the replay equals the node.

A probe injects, between the simulator's steps, a duplicate, late messages, a message
older than the history, future-stamped and malformed messages, bad commands, a lone
stamp far back and a clock jump (three messages in a row); the bag is replayed and the
replay's answers equal the estimates the node published, message for message, with the
same counters. The recorder runs in the observer's process
(test/nodes/observer_recorder_process.py), so the bag holds the messages in the order the
observer took them. The lone outlier and the agreement a clock jump needs are also
checked against a reference estimator on the observer alone.
"""

import math
from pathlib import Path
import subprocess
import sys
import time

from builtin_interfaces.msg import Time
import numpy as np
from observer_ros.bag.reader import read_recording
from observer_ros.core.estimators import make_estimator
from observer_ros.nodes.common import joint_state, SENSOR_QOS, STATE_PUB_QOS
from observer_ros.replay.replay import replay
from observer_ros.sensors import extract_measurement
from observer_ros.timeutil import sec_to_stamp_parts, stamp_to_ns, stamp_to_sec
from observer_ros.vehicle import load_vehicle
import pytest
from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
from rcl_interfaces.srv import SetParameters
from ros_helpers import (_die_with_parent, Listener, observer_under_test, Probe, Proc,
                         ros_env, SUBMARINE, WAIT)
from sensor_msgs.msg import Imu, JointState

pytestmark = pytest.mark.ros      # processes or DDS participants

# The loop: realtime, 10 s simulated at half the wall clock's pace (room for the probe's
# injections between steps); the gyro never silent for the observer's prediction (a
# loaded host may pause the simulator: predictions would be estimates of no message)
VEHICLE_PARAMS = ('simulator.mode:=realtime', 'simulator.duration:=10.0',
                  'simulator.realtime_factor:=0.5', 'sensors.gyro.timeout:=600.0')
LOOP = (*VEHICLE_PARAMS, 'diagnostics_period:=0.2')
VEHICLE = load_vehicle(SUBMARINE, overrides=list(VEHICLE_PARAMS))
HELPER = Path(__file__).resolve().parent / 'observer_recorder_process.py'
STEP = VEHICLE.sample_time
# What the admission and the callbacks count, compared between node and replay.
COUNTED = ('measurements', 'commands', 'bad_messages', 'bad_commands', 'bad_stamps',
           'out_of_order', 'duplicates', 'future_stamps', 'far_back_stamps', 'clock_jumps',
           'late_measurements', 'late_commands', 'late_commands_held_from_now',
           'estimator_resets', 'rejected_updates', 'numerical_resets')


def _imu(t, q=0.01, stamp=None):
    msg = Imu()
    if stamp is None:
        sec, nanosec = sec_to_stamp_parts(t)
        stamp = Time(sec=sec, nanosec=nanosec)
    msg.header.stamp = stamp
    msg.angular_velocity.y = float(q)
    return msg


def _command(t, u, names=('delta',), stamp=None):
    msg = joint_state(list(names), [float(v) for v in u], t, stamp=stamp)
    return msg


class _ObserverAndRecorder(Proc):
    """test/nodes/observer_recorder_process.py as a Proc: the two nodes in one process."""

    def __init__(self, params_file, *params, log_dir):
        self.log_path = Path(log_dir) / f'observer_recorder_{time.monotonic_ns()}.log'
        self._log = open(self.log_path, 'w')
        argv = [sys.executable, '-W', 'ignore::DeprecationWarning', str(HELPER),
                '--ros-args', '--params-file', str(params_file)]
        for param in params:
            argv += ['-p', param]
        self.popen = subprocess.Popen(argv, stdout=self._log, stderr=subprocess.STDOUT,
                                      env=ros_env(), preexec_fn=_die_with_parent)


def _injections(t, u):
    """
    Return the probe's faults for the step stamped t (u: the command in force), in order.

    Each entry: (topic, message, what the admission must say). The clock jump is three
    messages in a row stamped 5 s back, off the simulator's grid.
    """
    return [
        [('imu', _imu(t, 0.3), 'duplicate')],
        [('imu', _imu(t - 0.02), 'late')],
        [('imu', _imu(t - 0.07), 'late, two steps')],
        [('imu', _imu(t - 0.35), 'older than the history')],
        [('imu', _imu(t + 1e5), 'far in the future')],
        [('imu', _imu(0.0, stamp=Time(sec=int(t) + 1, nanosec=1_500_000_000)), 'nanosec'),
         ('imu', _imu(0.0, stamp=Time(sec=0, nanosec=5)), 'the first second'),
         ('imu', _imu(t + 0.01, float('nan')), 'a NaN')],
        [('u', _command(t, u, names=('rudder',)), 'unknown name'),
         ('u', _command(0.0, u, stamp=Time(sec=int(t), nanosec=2_000_000_000)), 'nanosec'),
         ('u', _command(t + 1e5, u), 'far in the future'),
         ('u', _command(t + 3.0, u), 'ahead of the estimate'),
         ('u', _command(t - 0.3, u), 'older than the history: held'),
         ('u', _command(t - 2.0, u), 'far back: held')],
        [('imu', _imu(t - 2.0, 5.0), 'a lone stamp far back')],
        [('imu', _imu(t - 5.0 + 0.013 + 0.05 * k, 0.01), 'the clock jumps back')
         for k in range(3)],
    ]


@pytest.mark.realtime
def test_replay_of_a_faulty_realtime_run_equals_the_node_message_for_message(tmp_path):
    bag = tmp_path / 'faults'
    common = (*LOOP, 'use_sim_time:=true')
    procs = {'observer and recorder': _ObserverAndRecorder(SUBMARINE, *common,
                                                           f'output:={bag}', log_dir=tmp_path),
             'compensator': Proc('compensator', SUBMARINE, *common, log_dir=tmp_path)}
    probe = Probe('fault_probe')
    try:
        listener = Listener(probe)
        node = probe.node
        # matched to the observer and the recorder before the simulator starts: both get
        # every injected message (the probe reads no sensor topic, so the simulator's
        # wait for two sensor readers is a wait for those two)
        imu = node.create_publisher(Imu, 'imu/data', SENSOR_QOS)
        # (as the compensator offers them: the recorder reads commands transient-local)
        cmd = node.create_publisher(JointState, 'control/u', STATE_PUB_QOS)
        probe.spin_until(lambda: imu.get_subscription_count() >= 2, WAIT, 'imu readers')
        # the observer's, the recorder's and the listener's
        probe.spin_until(lambda: cmd.get_subscription_count() >= 3, WAIT, 'u readers')
        listener.wait_matched('state/estimate', 'control/u')
        listener.wait_alive('observer')
        # kept alive after its run: its last (best-effort) measurement reaches the
        # recorder as well as the observer
        procs['plant_simulator'] = Proc('plant_simulator', SUBMARINE, *LOOP,
                                        'wait_for_subscribers:=2', 'wait_for_recorder:=true',
                                        'exit_when_done:=false', log_dir=tmp_path)
        _inject(probe, listener, imu, cmd)
        probe.spin_until(lambda: _run_complete(listener), WAIT, 'the end of the run')
        # the compensator would go on sending safe commands: stopped before the count
        assert procs['compensator'].stop() == 0, procs['compensator'].output()
        # one more measurement after the run's last step: a report whose x_hat is its
        # answer was made after it, and its counters hold every message
        last = 1.0 + VEHICLE.simulator.duration          # start_time 1 s
        listener.estimate_at(last)
        imu.publish(_imu(last + STEP))
        x_hat = np.array2string(listener.estimate_at(last + STEP), precision=6)
        probe.spin_until(lambda: _value(listener, 'observer', 'x_hat') == x_hat, WAIT,
                         'a report after the last answer')
        node_counts = {k: listener.counter('observer', k) for k in COUNTED}
        published = len(listener.estimates)
        probe.spin_until(lambda: listener.counter('recorder', 'messages /state/estimate')
                         >= published, WAIT, 'the recorder holding every estimate')
    finally:
        probe.close()
        codes = {name: proc.stop() for name, proc in procs.items()}
    assert all(code == 0 for code in codes.values()), codes

    rec = read_recording(bag, VEHICLE)
    rep = replay(rec, VEHICLE, answers=True)
    live = rec.estimate
    assert live.valid.all()
    # message for message: the same stamps to the ns, the same estimates
    assert rep.answer_ns.size == len(live), _first_difference(rep.answer_ns, live.stamp_ns)
    np.testing.assert_array_equal(rep.answer_ns, live.stamp_ns)
    np.testing.assert_allclose(rep.answer_x, live.values, rtol=0, atol=1e-12)
    assert {k: rep.counts.get(k, 0) for k in COUNTED} == node_counts
    # every fault was met (the run could not have passed them by)
    expected = {'duplicates': 1, 'late_measurements': 2, 'out_of_order': 1,
                'future_stamps': 3, 'bad_stamps': 3, 'bad_messages': 1, 'bad_commands': 1,
                'late_commands': 1, 'late_commands_held_from_now': 1,
                'far_back_stamps': 3, 'clock_jumps': 1, 'estimator_resets': 1}
    for key, n in expected.items():
        assert node_counts[key] >= n, (key, node_counts)


def _value(listener, node, key):
    status = listener.latest_status(node)
    return None if status is None else next((kv.value for kv in status.values
                                             if kv.key == key), None)


def _run_complete(listener):
    status = listener.latest_status('plant_simulator')
    return status is not None and status.message == 'run complete'


def _first_difference(a, b):
    i = next((i for i, (x, y) in enumerate(zip(a, b)) if x != y), min(len(a), len(b)))
    return f'{len(a)} answers, {len(b)} published; from {i}: {a[i:i + 8]} vs {b[i:i + 8]}'


def _inject(probe, listener, imu, cmd):
    """Inject one group of faults every fourth step from 2 s on, between two steps."""
    done = 0
    newest = -math.inf       # the newest step answered (estimate and command)
    groups = None
    next_at = 2.0
    while groups is None or done < len(groups):
        def step_answered():
            stamps = {stamp_to_ns(m.header.stamp) for m in listener.commands}
            return any(stamp_to_sec(m.header.stamp) > max(newest, next_at) and
                       stamp_to_ns(m.header.stamp) in stamps for m in listener.estimates)
        probe.spin_until(lambda: step_answered() or _run_complete(listener), WAIT,
                         'the next step')
        assert not _run_complete(listener), 'the run ended before every fault was injected'
        answered = {stamp_to_ns(m.header.stamp) for m in listener.commands}
        newest = max(stamp_to_sec(m.header.stamp) for m in listener.estimates
                     if stamp_to_ns(m.header.stamp) in answered)
        u = listener.commands[-1].position.tolist()
        if groups is None:
            groups = _injections(newest, u)
        for topic, msg, _ in (_injections(newest, u)[done]):
            (imu if topic == 'imu' else cmd).publish(msg)
        done += 1
        next_at = newest + 4 * STEP
        if done == len(groups) - 1:
            next_at = max(next_at, 7.0)     # the jump back 5 s stays after the first 1 s


class _Reference:
    """The vehicle's estimator fed offline with what the node should take."""

    def __init__(self):
        self.est = make_estimator(VEHICLE.plant, VEHICLE.observer)
        self.sensor = VEHICLE.sensors[0]
        self.rows = VEHICLE.plant.output_rows(self.sensor.outputs)

    def correct(self, msg):
        return self.est.correct(stamp_to_sec(msg.header.stamp),
                                extract_measurement(msg, self.sensor), self.rows)


def _set_agreement(probe, n):
    client = probe.node.create_client(SetParameters, '/observer/set_parameters')
    probe.spin_until(client.service_is_ready, WAIT, '/observer/set_parameters')
    future = client.call_async(SetParameters.Request(parameters=[Parameter(
        name='clock_jump_agreement',
        value=ParameterValue(type=ParameterType.PARAMETER_INTEGER, integer_value=n))]))
    probe.spin_until(future.done, WAIT, 'the answer to setting clock_jump_agreement')
    return future.result().results[0]


def test_a_lone_stamp_an_hour_back_leaves_the_estimate_and_agreeing_ones_reset_it(tmp_path):
    """A wall-clock stamped gyro: one message 1 h back is skipped; two in a row (N=2) reset."""
    with observer_under_test(tmp_path) as run:
        pub, listener, probe = run.pubs['imu/data'], run.listener, run.probe
        ref = _Reference()
        t = float(int(stamp_to_sec(probe.node.get_clock().now().to_msg())))

        def good(q=0.02):
            nonlocal t
            t = round(t + 0.05, 6)
            msg = _imu(t, q)
            pub.publish(msg)
            np.testing.assert_allclose(listener.estimate_at(t), ref.correct(msg), rtol=0,
                                       atol=1e-12)
        for _ in range(5):
            good()
        pub.publish(_imu(t - 3600.0, 5.0))
        listener.wait_counter('observer', 'far_back_stamps', 1)
        for _ in range(5):          # the estimate goes on as if it never came
            good()
        assert listener.counter('observer', 'estimator_resets') == 0
        # refused out of range, then two in a row make a clock jump
        assert not _set_agreement(probe, 0).successful
        assert _set_agreement(probe, 2).successful
        for k in range(2):
            pub.publish(_imu(t - 3600.0 + 0.05 * k, 0.01))
        listener.wait_counter('observer', 'clock_jumps', 1)
        assert listener.counter('observer', 'far_back_stamps') == 2
        assert listener.counter('observer', 'estimator_resets') == 1
        listener.estimate_at(round(t - 3600.0 + 0.05, 6))
    assert 'clock jumped back' in run.proc.output()
