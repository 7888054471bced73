# Faults the loop must survive honestly: restarts, pauses, divergence, overload.
"""A restarted simulator, a paused observer, a diverging estimate and an overloaded observer."""

import signal
import time

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
import numpy as np
from observer_ros.core.delay_compensation import DelayCompensation
from observer_ros.core.model import zoh_matrices
from observer_ros.core.vehicle_design import design_vehicle
from observer_ros.nodes.common import joint_state, SENSOR_QOS, STATE_QOS
from observer_ros.timeutil import stamp_to_sec
from observer_ros.vehicle import load_vehicle
import pytest
from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
from rcl_interfaces.srv import SetParameters
from ros_helpers import compensator_under_test, CONFIG, ESTIMATES, imu_msg, Probe, Proc, WAIT
from sensor_msgs.msg import Imu, JointState

pytestmark = pytest.mark.ros      # processes or DDS participants

REALTIME = ['simulator.mode:=realtime', 'simulator.duration:=3000.0']
# the vehicle, its reference, the realtime factor, and |x - x_d| that counts as converged
LOOPS = {
    'cart_pendulum': ([0.0, 1.0, 0.0, 0.0], 1.0, 0.05),
    'submarine': ([0.0, 0.0, 0.0], 4.0, 0.02),
}


class Loop:
    """Simulator, observer and compensator of a vehicle in realtime, watched by a probe."""

    def __init__(self, tmp_path, vehicle):
        self.tmp, self.file = tmp_path, CONFIG / f'{vehicle}.yaml'
        x_d, factor, self.tol = LOOPS[vehicle]
        self.x_d = np.array(x_d)
        self.params = REALTIME + [f'simulator.realtime_factor:={factor}',
                                  'diagnostics_period:=0.2']
        self.procs = {}
        self.probe = Probe('recovery_probe')
        self.true = []              # (t, x)
        self.status = {}            # node name -> latest DiagnosticStatus
        self.levels = []            # (node, level, message)
        self.streams = None         # record_streams()
        node = self.probe.node
        node.create_subscription(JointState, 'state/true', self._on_true, STATE_QOS)
        node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diag, 100)

    def _on_true(self, msg):
        self.true.append((stamp_to_sec(msg.header.stamp), np.array(msg.position)))

    def _on_diag(self, msg):
        for s in msg.status:
            name = s.name.rsplit('/', 1)[-1]
            self.status[name] = s
            self.levels.append((name, s.level, s.message))
            if self.streams is not None:
                t = self.true[-1][0] if self.true else 0.0
                self.streams.append(('report', t, name, [s.level, s.message],
                                     {kv.key: kv.value for kv in s.values}))

    def record_streams(self):
        """Record the estimates (with their writers' sequence numbers) and the commands."""
        self.streams = []           # (kind, stamp, sequence number, values, frame)
        node = self.probe.node

        def keep(kind):
            def on_message(msg, info):
                self.streams.append((kind, stamp_to_sec(msg.header.stamp),
                                     info['publication_sequence_number'],
                                     list(msg.position), msg.header.frame_id))
            return on_message
        node.create_subscription(JointState, 'state/estimate', keep('estimate'), STATE_QOS)
        node.create_subscription(JointState, 'control/u', keep('command'), STATE_QOS)

    def write_streams(self):
        """Write the true states, estimates, commands and reports by stamp; return the file."""
        rows = [(t, 'true', '', np.round(x, 5).tolist(), '') for t, x in self.true]
        rows += [(t, kind, seq, v if kind == 'report' else np.round(v, 5).tolist(), frame)
                 for kind, t, seq, v, frame in self.streams]
        path = self.tmp / 'streams.txt'
        with open(path, 'w') as out:
            for row in sorted(rows, key=lambda r: r[0]):
                out.write(' '.join(map(str, row)) + '\n')
        return path

    def start(self, name):
        self.procs[name] = Proc(name, self.file, *self.params, log_dir=self.tmp)

    def counter(self, node, key):
        s = self.status.get(node)
        return 0 if s is None else int(next((kv.value for kv in s.values if kv.key == key), 0))

    def wait(self, predicate, what, timeout=WAIT):
        self.probe.spin_until(predicate, timeout, what)

    def wait_converged(self, since, after_t):
        """Wait for the true state within tol of x_d at a stamp past after_t."""
        def done():
            return any(t > after_t and np.max(np.abs(x - self.x_d)) < self.tol
                       for t, x in self.true[since:])
        try:
            self.wait(done, f'|x - x_d| < {self.tol} after t = {after_t} s')
        except AssertionError as err:
            trail = [(round(t, 2), np.round(x, 3).tolist()) for t, x in self.true[since::20]]
            kept = '' if self.streams is None else f'; streams in {self.write_streams()}'
            raise AssertionError(f'{err}; true state since: {trail[:20]} ... {trail[-20:]}; '
                                 f'diagnostics: {self.levels[-12:]}{kept}') from None

    def close(self):
        for proc in self.procs.values():
            proc.stop()
        self.probe.close()


@pytest.fixture
def loop_of(tmp_path):
    loops = []

    def make(vehicle):
        lp = Loop(tmp_path, vehicle)
        loops.append(lp)
        for name in ('observer_node', 'compensator', 'plant_simulator'):
            lp.start(name)
        return lp
    yield make
    for lp in loops:
        lp.close()


@pytest.mark.realtime
@pytest.mark.parametrize('vehicle', ['cart_pendulum', 'submarine'])
def test_simulator_killed_and_restarted_converges_again(loop_of, vehicle):
    lp = loop_of(vehicle)
    lp.record_streams()
    lp.wait_converged(0, 8.0)
    lp.procs['plant_simulator'].stop(signal.SIGKILL)
    since = len(lp.true)
    t_kill = lp.true[-1][0]
    lp.start('plant_simulator')        # simulated time starts over at 1.0 s

    def back(t):
        return t < t_kill - 1.0
    lp.wait(lambda: any(back(t) for t, _ in lp.true[since:]), 'the restarted simulator')
    restart = next(i for i in range(since, len(lp.true)) if back(lp.true[i][0]))
    lp.wait_converged(restart, 8.0)
    # converged as after the first start: never far from the reference on the way
    worst = max(np.max(np.abs(x - lp.x_d)) for _, x in lp.true[restart:])
    assert worst < 2.0, (worst, str(lp.write_streams()))
    assert lp.counter('observer', 'clock_jumps') >= 1
    assert all(p.alive() for p in lp.procs.values())


def paused_observer_run(lp, pause=3.0):
    """
    SIGSTOP the cart's observer for ``pause`` s; return the true states meanwhile.

    ``pause`` s of wall time and of the plant's (a simulator on a busy host runs slower
    than the wall clock). Returns ``(during, t_stop, t_cont)``: the true states stamped
    between the plant's time at SIGSTOP and at SIGCONT, and those two times.
    """
    lp.wait_converged(0, 6.0)
    obs = lp.procs['observer_node'].popen
    t_stop = lp.true[-1][0]
    obs.send_signal(signal.SIGSTOP)
    try:
        paused = time.monotonic()
        lp.wait(lambda: time.monotonic() - paused > pause and lp.true[-1][0] - t_stop > pause,
                f'{pause} s of pause', 10.0 * pause)
        t_cont = lp.true[-1][0]
    finally:
        obs.send_signal(signal.SIGCONT)
    return [x for t, x in lp.true if t_stop <= t <= t_cont], t_stop, t_cont


@pytest.mark.realtime
def test_paused_observer_the_standby_holds_the_cart(loop_of):
    """The observer stopped 3 s: the compensator's standby observer closes the loop."""
    lp = loop_of('cart_pendulum')
    during, t_stop, t_cont = paused_observer_run(lp)
    assert t_cont - t_stop > 3.0 and len(during) > 150, (t_stop, t_cont, len(during))
    theta = max(abs(x[0]) for x in during)
    off = max(abs(x[1] - lp.x_d[1]) for x in during)
    print(f'observer paused {t_cont - t_stop:.2f} s of plant time: max |theta| {theta:.3g} rad, '
          f'max |x - x_d| {off:.3g} m')
    assert theta < 0.3 and off < 0.2, (theta, off)
    lp.wait(lambda: lp.counter('compensator', 'standby_commands') > 100,
            'commands of the standby observer')
    assert any(node == 'compensator' and 'standby observer closes the loop' in message
               for node, _, message in lp.levels), lp.levels[-12:]
    # back on the observer's estimates once they agree with the standby's: OK again
    since = len(lp.true)
    lp.wait(lambda: (s := lp.status.get('compensator')) is not None
            and s.level == DiagnosticStatus.OK, 'the loop closed on the observer again')
    lp.wait_converged(since, t_cont + 1.0)


@pytest.mark.realtime
def test_a_second_observer_with_the_same_name_does_not_move_the_cart(loop_of):
    """Two observers on state/estimate: the compensator follows one stream and says so."""
    lp = loop_of('cart_pendulum')
    lp.record_streams()
    lp.wait_converged(0, 6.0)
    since = len(lp.true)
    second = Proc('observer_node', lp.file, *lp.params, log_dir=lp.tmp)
    lp.procs['observer_node_2'] = second
    # its start takes seconds of CPU on a busy host: the 10 s count from its match

    def both():
        return any(node == 'compensator' and '/state/estimate (2 publishers)' in message
                   for node, _, message in lp.levels)
    lp.wait(both, 'the compensator reporting two publishers of state/estimate')
    t_start = lp.true[-1][0]
    lp.wait(lambda: lp.true[-1][0] > t_start + 10.0, '10 s with two observers')
    off = max(abs(x[1] - lp.x_d[1]) for _, x in lp.true[since:])
    theta = max(abs(x[0]) for _, x in lp.true[since:])
    print(f'two observers for 10 s: max |x - x_d| {off:.3g} m, max |theta| {theta:.3g} rad, '
          f'{lp.counter("compensator", "other_stream_estimates")} estimates of the other '
          f'stream ignored; node logs and {lp.write_streams()} in {lp.tmp}')
    assert off < 0.2 and theta < 0.3, (off, theta, str(lp.tmp))
    for proc in (lp.procs['observer_node'], second):
        assert 'truth value of an array' not in proc.output()


@pytest.mark.realtime
@pytest.mark.parametrize('vehicle, sensor', [('cart_pendulum', ('joint_states', JointState)),
                                             ('submarine', ('imu/data', Imu))])
def test_a_realtime_simulator_unanswered_runs_open_loop_only_if_its_plant_is_stable(
        tmp_path, vehicle, sensor):
    """No command answers step 0: the cart waits and says for what, the submarine runs on."""
    # the wait: READY_WAIT (10) x command_timeout
    proc = Proc('plant_simulator', CONFIG / f'{vehicle}.yaml', *REALTIME,
                'simulator.command_timeout:=0.1', log_dir=tmp_path)
    probe = Probe('start_probe')
    stamps = []
    try:
        node = probe.node
        node.create_publisher(JointState, 'control/u', STATE_QOS)     # matched, silent
        node.create_subscription(sensor[1], sensor[0], lambda msg: None, SENSOR_QOS)
        node.create_subscription(JointState, 'state/true',
                                 lambda msg: stamps.append(stamp_to_sec(msg.header.stamp)),
                                 STATE_QOS)
        probe.spin_until(lambda: stamps, WAIT, 'step 0')
        if vehicle == 'submarine':
            probe.spin_until(lambda: stamps[-1] > 1.5, WAIT, 'the open loop')
            assert 'no command answered step 0 after' in proc.output()
            return
        probe.spin_until(lambda: proc.output().count('waiting for /control/u') >= 2, WAIT,
                         'the simulator saying twice what it waits for')
        assert set(stamps) == {1.0}, sorted(set(stamps))[:5]
        assert 'running open loop' not in proc.output()
        assert 'an unstable plant does not run open loop' in proc.output()
    finally:
        proc.stop()
        probe.close()


def test_compensator_predicts_a_late_estimate_to_when_its_command_applies(tmp_path):
    cart = CONFIG / 'cart_pendulum.yaml'
    encoder = ('joint_states', JointState, SENSOR_QOS)
    with compensator_under_test(tmp_path, vehicle=cart, publish=[ESTIMATES, encoder],
                                probe_name='delay_probe') as run:
        probe, listener = run.probe, run.listener
        est, enc = run.pubs['state/estimate'], run.pubs['joint_states']
        names = ['theta', 'x', 'theta_dot', 'x_dot']
        x_hat = np.array([0.01, 0.2, -0.03, 0.1])

        def plant_time_is(t):
            """Publish the encoder stamped t (best effort: again) until the node has it."""
            sent = [0.0]

            def seen():
                if time.monotonic() - sent[0] > 0.5:
                    enc.publish(joint_state(['cart'], [0.2], t))
                    sent[0] = time.monotonic()
                s = listener.latest_status('compensator')
                return s is not None and any(kv.key == 'plant_time' and float(kv.value) == t
                                             for kv in s.values)
            probe.spin_until(seen, WAIT, f'the compensator at plant time {t}')
        # the plant is at 10.05 (its encoder's stamp) when the estimate of 10.0 comes
        plant_time_is(10.05)
        est.publish(joint_state(names, x_hat, 10.0))
        probe.spin_until(lambda: listener.commands, WAIT, 'the command')
        msg = listener.commands[0]
        # at least 5 steps late plus the lead of 3; more by the wall time since the encoder's
        # message (this plant stands still, a real one runs on: core/plant_clock.py)
        steps = (stamp_to_sec(msg.header.stamp) - 10.0) / 0.01
        assert abs(steps - round(steps)) < 1e-6 and 8 <= round(steps) <= 8 + 100, steps
        vehicle = load_vehicle(cart)
        Ad, Bd = zoh_matrices(vehicle.plant.A, vehicle.plant.B, 0.01)
        x_pred = DelayCompensation(Ad, Bd, 0.01).predict(x_hat, 10.0, round(steps))
        K = design_vehicle(vehicle).K
        expected = K @ (np.asarray(vehicle.controller.reference) - x_pred)
        np.testing.assert_allclose(msg.position, expected, rtol=1e-9)
        assert not np.allclose(expected, K @ (vehicle.controller.reference - x_hat), rtol=1e-3)
        # the plant at 10.5 with no estimate since 10.0: the standby observer (its
        # measurements since 10.05: warm after the observer's settling time, 0.4 s) answers
        plant_time_is(10.5)
        listener.wait_counter('compensator', 'standby_commands', 1)
        # an estimate later than observer.history_length (0.25 s): not used, ERROR
        est.publish(joint_state(names, x_hat, 10.1))
        listener.wait_counter('compensator', 'too_late_estimates', 1)
        probe.spin_until(lambda: any(
            s.name.endswith('compensator') and s.level == DiagnosticStatus.ERROR
            and 'later than observer.history_length' in s.message
            and 'standby observer closes the loop' in s.message
            for a in listener.diagnostics for s in a.status), WAIT, 'the ERROR')


def _set(probe, node, name, value):
    client = probe.node.create_client(SetParameters, f'/{node}/set_parameters')
    probe.spin_until(client.service_is_ready, WAIT, f'/{node}/set_parameters')
    if isinstance(value, list):
        pv = ParameterValue(type=ParameterType.PARAMETER_DOUBLE_ARRAY, double_array_value=value)
    else:
        pv = ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=value)
    future = client.call_async(SetParameters.Request(parameters=[Parameter(name=name,
                                                                           value=pv)]))
    probe.spin_until(future.done, WAIT, f'the answer to setting {name}')
    return future.result().results[0]


def test_observer_refuses_tolerances_and_poles_that_stop_it(observer_setup):
    proc, probe, listener, pub, cmd = observer_setup
    for name, value, words in (
            ('future_tolerance', -1.0, ['future_tolerance', '-1']),
            ('clock_jump_tolerance', float('nan'), ['clock_jump_tolerance', 'nan']),
            ('observer.poles', [-1e-300, -1.0, -1.1], ['-1e-300', 'margin']),
            ('observer.poles', [-1e6, -1.0, -1.1], ['-1e+06', 'realis'])):
        result = _set(probe, 'observer', name, value)
        assert not result.successful, (name, value)
        assert all(w in result.reason for w in words), result.reason
    assert _set(probe, 'observer', 'future_tolerance', 5.0).successful
    # the observer still answers
    pub.publish(imu_msg(300.0, 0.01))
    assert np.all(np.isfinite(listener.estimate_at(300.0)))


def test_observer_reports_a_diverging_estimate(observer_setup):
    proc, probe, listener, pub, cmd = observer_setup
    t = 400.0
    pub.publish(imu_msg(t, 0.0))
    listener.estimate_at(t)
    # measurements far beyond anything the file makes plausible (q = 1e6 rad/s)
    for k in range(1, 16):
        pub.publish(imu_msg(t + 0.05 * k, 1e6 * k))
    probe.spin_until(lambda: (s := listener.latest_status('observer')) is not None
                     and s.level == DiagnosticStatus.ERROR and 'diverging' in s.message,
                     10.0, 'a divergence ERROR')
    assert 'x_hat' in listener.latest_status('observer').message
    assert listener.counter('observer', 'divergence_reports') >= 1
    assert proc.alive()


def test_compensator_reports_divergence_and_sends_the_safe_command(
        compensator_setup):
    proc, probe, listener, est = compensator_setup
    names = ['theta', 'w', 'q']
    est.publish(joint_state(names, [0.1, 0.0, 0.0], 5.0))
    probe.spin_until(lambda: listener.counter('compensator', 'commands') >= 1, WAIT,
                     'a command')
    x = 0.1
    for k in range(1, 30):          # an estimate growing x2.6 per step
        x *= 2.6
        est.publish(joint_state(names, [x, 0.0, 0.0], 5.0 + 0.05 * k))
    probe.spin_until(lambda: (s := listener.latest_status('compensator')) is not None
                     and s.level == DiagnosticStatus.ERROR and 'diverging' in s.message,
                     10.0, 'a divergence ERROR')
    message = listener.latest_status('compensator').message
    assert 'theta' in message or 'delta' in message, message
    assert listener.counter('compensator', 'divergence_safe_commands') >= 1
    # once the growth is declared (5 growing estimates beyond the envelope), zero
    probe.spin_until(lambda: any(stamp_to_sec(m.header.stamp) > 6.35
                                 for m in listener.commands), WAIT, 'the last commands')
    last = [m for m in listener.commands if stamp_to_sec(m.header.stamp) > 6.3]
    assert last and all(m.position[0] == 0.0 for m in last), [   # submarine: zero
        (stamp_to_sec(m.header.stamp), m.position[0]) for m in last]


def test_after_an_outage_estimates_are_gated_and_the_loop_closes_again(
        compensator_setup):
    proc, probe, listener, est = compensator_setup
    names = ['theta', 'w', 'q']
    est.publish(joint_state(names, [0.1, 0.0, 0.0], 5.0))
    listener.wait_counter('compensator', 'commands', 1)
    listener.wait_counter('compensator', 'safe_commands', 1)     # stale
    # back: the first estimate starts the resync, one past its deadline (10 observer
    # settling times, 67 s on the submarine) ends it and the recovery begins
    est.publish(joint_state(names, [0.1, 0.0, 0.0], 6.0))
    est.publish(joint_state(names, [0.1, 0.0, 0.0], 500.0))
    listener.wait_counter('compensator', 'resync_commands', 2)
    # far beyond the envelope (theta bound 52 rad) while recovering: refused, every one
    for k, x in enumerate([1e4, 0.9e4, 1.0e4, 1.1e4, 1.2e4, 1.3e4]):
        est.publish(joint_state(names, [x, 0.0, 0.0], 500.05 + 0.05 * k))
    listener.wait_counter('compensator', 'divergence_safe_commands', 6)
    probe.spin_until(lambda: (s := listener.latest_status('compensator')) is not None
                     and s.level == DiagnosticStatus.ERROR and 'diverging' in s.message,
                     WAIT, 'diverging reported')
    # plausible again for an observer settling time (6.7 s of stamps): OK again
    est.publish(joint_state(names, [0.1, 0.0, 0.0], 600.0))
    est.publish(joint_state(names, [0.1, 0.0, 0.0], 607.0))
    probe.spin_until(lambda: (s := listener.latest_status('compensator')) is not None
                     and s.level == DiagnosticStatus.OK, WAIT, 'the compensator OK again')
    assert listener.counter('compensator', 'commands') >= 3


@pytest.mark.realtime
def test_overloaded_observer_says_so(observer_setup):
    proc, probe, listener, pub, cmd = observer_setup
    t = 500.0
    pub.publish(imu_msg(t, 0.0))
    listener.estimate_at(t)
    # a flood: stamps 0.05 s apart (the sensor's period) sent as fast as we can, for
    # as long as it takes the observer to say it is overloaded
    start = time.monotonic()
    found = None
    while found is None:
        assert time.monotonic() - start < WAIT, 'no overload report'
        for _ in range(500):
            t += 0.05
            pub.publish(imu_msg(t, 0.0))
        probe.executor.spin_once(timeout_sec=0.0)
        found = next((s for a in reversed(listener.diagnostics) for s in a.status
                      if s.name.endswith('observer') and 'overloaded' in s.message), None)
    assert found.level == DiagnosticStatus.ERROR
    assert 'measurements/s' in found.message, found.message
    # the flood over, the report clears (the node drained its queue and is idle again)
    n = len(listener.diagnostics)
    probe.spin_until(lambda: any(s.name.endswith('observer') and s.level != DiagnosticStatus.ERROR
                                 for a in listener.diagnostics[n:] for s in a.status),
                     WAIT, 'the overload report cleared')
    assert proc.alive()
