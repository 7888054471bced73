# test_nodes_one_clock: two vehicles on one ROS graph follow one /clock, over DDS.
"""
One time base per ROS graph: a second vehicle stamps in /clock's time.

It does so from its first step after a wait at step 0 for a late observer.

A clock owner that restarts is a clock jump the other vehicle handles (its estimator
resets, the loop converges again).
"""

import signal

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
import numpy as np
from observer_ros.nodes.common import STATE_QOS
from observer_ros.timeutil import stamp_to_sec
import pytest
from ros_helpers import CONFIG, Probe, Proc, WAIT
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState

pytestmark = pytest.mark.ros      # processes or DDS participants

# the owner of /clock: a submarine (20 Hz); the follower: the cart (100 Hz, unstable open
# loop), both realtime at the wall clock's pace
OWNER, FOLLOWER = '/sub1', '/sub2'
COMMON = ('simulator.mode:=realtime', 'simulator.duration:=3000.0',
          'simulator.realtime_factor:=1.0', 'diagnostics_period:=0.2')
PEERS = ('use_sim_time:=true',)
CART_X_D = np.array([0.0, 1.0, 0.0, 0.0])
CONVERGED = 0.05        # |x - x_d| of the cart, and |x_hat - x|


class _Graph:
    """The probe's view: /clock, the follower's true state and estimate, diagnostics."""

    def __init__(self):
        self.probe = Probe('clock_probe')
        node = self.probe.node
        self.clock = []             # s
        self.true = []              # (t, x)
        self.lag = []               # s: /clock when a follower's step came, less its stamp
        self.estimate = {}          # stamp (s) -> x_hat
        self.status = {}            # fully qualified node name -> latest DiagnosticStatus
        # fully qualified node name -> the simulator time of its latest report that had one,
        # and the reports that had one (a report sent for a node whose executor lags, by
        # its callback watch's thread, has the counters but not the node's own values)
        self.sim_time = {}
        self.timed_reports = {}
        node.create_subscription(Clock, '/clock', self._on_clock, 100)
        node.create_subscription(JointState, f'{FOLLOWER}/state/true', self._on_true,
                                 STATE_QOS)
        node.create_subscription(JointState, f'{FOLLOWER}/state/estimate',
                                 self._on_estimate, STATE_QOS)
        node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diag, 100)

    def _on_clock(self, msg):
        self.clock.append(msg.clock.sec + msg.clock.nanosec * 1e-9)

    def _on_true(self, msg):
        t = stamp_to_sec(msg.header.stamp)
        self.true.append((t, np.array(msg.position)))
        if self.clock:
            self.lag.append(self.clock[-1] - t)     # /clock heard last, less the stamp

    def _on_estimate(self, msg):
        self.estimate[stamp_to_sec(msg.header.stamp)] = np.array(msg.position)

    def _on_diag(self, msg):
        for s in msg.status:
            self.status[s.name] = s
            t = next((kv.value for kv in s.values if kv.key == 't'), None)
            if t is not None:
                self.sim_time[s.name] = float(t)
                self.timed_reports[s.name] = self.timed_reports.get(s.name, 0) + 1

    def counter(self, name, key):
        s = self.status.get(name)
        return 0 if s is None else int(next((kv.value for kv in s.values if kv.key == key), 0))

    def wait(self, predicate, what):
        self.probe.spin_until(predicate, WAIT, what)

    def converged(self, since, after_t):
        """Return the stamp at which the cart is at x_d and its estimate on it, or None."""
        for t, x in self.true[max(since, len(self.true) - 200):]:
            x_hat = self.estimate.get(t)
            if t > after_t and x_hat is not None and \
                    np.max(np.abs(x - CART_X_D)) < CONVERGED and \
                    np.max(np.abs(x_hat - x)) < CONVERGED:
                return t
        return None

    def on_clock_time(self):
        """Tell whether the follower's newest stamp is within half a second of /clock."""
        return self.true and self.clock and abs(self.true[-1][0] - self.clock[-1]) < 0.5


def _start(name, vehicle, namespace, *params, tmp_path):
    return Proc(name, CONFIG / f'{vehicle}.yaml', *COMMON, *params, namespace=namespace,
                log_dir=tmp_path)


@pytest.fixture
def graph(tmp_path):
    g = _Graph()
    procs = {}
    g.procs = procs
    g.start = lambda key, *args: procs.__setitem__(key, _start(*args, tmp_path=tmp_path))
    yield g
    g.probe.close()
    codes = {key: proc.stop() for key, proc in procs.items() if key != 'killed'}
    assert all(code == 0 for code in codes.values()), \
        {key: procs[key].output()[-3000:] for key, code in codes.items() if code}


@pytest.mark.realtime
def test_the_second_vehicle_follows_clock_and_survives_its_owners_restart(graph):
    g = graph
    for name in ('observer_node', 'compensator'):
        g.start(f'owner {name}', name, 'submarine', OWNER, *PEERS)
    g.start('owner sim', 'plant_simulator', 'submarine', OWNER)
    # the follower starts once the graph's time is past 5 s: on its own time, it would
    # stamp from 1 s
    g.wait(lambda: g.clock and g.clock[-1] > 5.0, '/clock past 5 s')
    g.start('follower sim', 'plant_simulator', 'cart_pendulum', FOLLOWER,
            'simulator.publish_clock:=false')
    g.start('follower compensator', 'compensator', 'cart_pendulum', FOLLOWER, *PEERS)
    g.wait(lambda: g.true, "the follower's first step")
    assert g.true[0][0] > 5.0, g.true[0]
    # its observer starts late (a loaded host: seconds): the plant waits at step 0 while
    # /clock goes on, and steps on /clock's time, longer after step 0 than the cart's model
    # can be predicted over (1.40 s): the observer and the compensator's standby restart
    # at that measurement, and the loop closes on the observer
    g.wait(lambda: g.clock[-1] - g.true[0][0] > 2.0, '/clock 2 s past step 0')
    g.start('follower observer_node', 'observer_node', 'cart_pendulum', FOLLOWER, *PEERS)
    g.wait(g.on_clock_time, "the follower's stamps on /clock's time")
    first = g.true[0][0]
    g.wait(lambda: g.converged(0, first + 3.0) is not None, 'the follower converged')
    lag = np.array(g.lag)
    assert g.counter(f'{FOLLOWER}/observer', 'clock_jumps') == 0
    # the owner of /clock is killed and started again: /clock starts over at 1 s
    t_kill = g.clock[-1]
    g.procs['killed'] = g.procs.pop('owner sim')
    g.procs['killed'].stop(signal.SIGKILL)
    since = len(g.true)
    g.start('owner sim', 'plant_simulator', 'submarine', OWNER)
    g.wait(lambda: any(t < t_kill - 1.0 for t, _ in g.true[since:]),
           "the follower's stamps back on the restarted /clock")
    back = next(i for i in range(since, len(g.true)) if g.true[i][0] < t_kill - 1.0)
    restart = g.true[back][0]
    g.wait(g.on_clock_time, "the follower's stamps on the new /clock's time")
    g.wait(lambda: g.counter(f'{FOLLOWER}/observer', 'clock_jumps') >= 1,
           "the follower's estimator reset")
    g.wait(lambda: g.converged(back, restart + 3.0) is not None,
           'the follower converged again')
    again = next(t for t, x in g.true[back:] if t > restart + 3.0 and t in g.estimate and
                 np.max(np.abs(x - CART_X_D)) < CONVERGED and
                 np.max(np.abs(g.estimate[t] - x)) < CONVERGED)
    print(f'follower behind /clock: median {np.median(lag):.3f} s, 99th percentile '
          f'{np.percentile(lag, 99):.3f} s; converged again at t = {again:.2f} s (checked '
          f'from {restart + 3.0:.2f} s)')
    assert g.counter(f'{FOLLOWER}/plant_simulator', 'clock_resyncs') >= 1
    assert all(p.alive() for key, p in g.procs.items() if key != 'killed')


def test_a_lockstep_follower_steps_only_as_far_as_clock(tmp_path):
    """A probe owns /clock: held, the follower waits; ahead, it steps to it; back, it resyncs."""
    g = _Graph()
    ns = '/sub3'
    clock = Clock()
    pub = g.probe.node.create_publisher(Clock, '/clock', 10)
    true = []
    g.probe.node.create_subscription(
        JointState, f'{ns}/state/true',
        lambda m: true.append(stamp_to_sec(m.header.stamp)), STATE_QOS)
    params = ('simulator.mode:=lockstep', 'simulator.duration:=0.0', 'diagnostics_period:=0.2')
    procs = [Proc(name, CONFIG / 'submarine.yaml', *params, *extra, namespace=ns,
                  log_dir=tmp_path)
             for name, extra in (('observer_node', ()), ('compensator', ()),
                                 ('plant_simulator', ('simulator.publish_clock:=false',)))]

    def at(t):
        clock.clock.sec, clock.clock.nanosec = int(t), round((t - int(t)) * 1e9)

    def wait(predicate, what):
        def published_then(predicate=predicate):
            pub.publish(clock)          # best effort on the follower's side: again and again
            return predicate()
        g.wait(published_then, what)

    def sim_time():
        return g.sim_time.get(f'{ns}/plant_simulator')
    try:
        at(20.0)
        wait(lambda: true, 'step 0')
        assert true[0] == 20.0
        # /clock held: answered, the follower waits at its step (two reports after the
        # answer say so)
        wait(lambda: g.counter(f'{ns}/compensator', 'commands') >= 1, 'the answer')
        seen = g.timed_reports.get(f'{ns}/plant_simulator', 0)
        wait(lambda: g.timed_reports.get(f'{ns}/plant_simulator', 0) >= seen + 2, 'two reports')
        assert sim_time() == 20.0 and max(true) == 20.0, (sim_time(), true)
        at(20.5)
        wait(lambda: max(true) >= 20.5 - 1e-9, 'the steps up to /clock')
        wait(lambda: sim_time() is not None and sim_time() >= 20.5 - 1e-9, 'the report at 20.5')
        assert max(true) <= 20.5 + 1e-9, max(true)
        # /clock back (its owner restarted; published again and again, so the follower's
        # agreement of 3 far-back /clock messages in a row is met): it starts again there
        at(10.0)
        wait(lambda: min(true) < 15.0, 'the stamps back')
        at(10.2)
        wait(lambda: g.counter(f'{ns}/observer', 'clock_jumps') >= 1, 'the clock jump')
        assert g.counter(f'{ns}/observer', 'far_back_stamps') == 2
        wait(lambda: g.counter(f'{ns}/plant_simulator', 'clock_resyncs') >= 1, 'the resync')
        assert g.counter(f'{ns}/plant_simulator', 'clock_resyncs') == 1
        # on the new time base (the old one's last steps are in ``true`` before them)
        wait(lambda: max(t for t in true if t < 15.0) >= 10.2 - 1e-9,
             'the steps up to the new /clock')
        assert max(t for t in true if t < 15.0) <= 10.2 + 1e-9
    finally:
        g.probe.close()
        codes = [proc.stop() for proc in procs]
    assert codes == [0, 0, 0], [proc.output()[-2000:] for proc in procs]


@pytest.mark.realtime
def test_safe_commands_follow_clock_and_stop_while_it_stands_still(tmp_path):
    """A compensator on /clock's time whose estimates stop, then /clock stops too."""
    from observer_ros.nodes.common import joint_state
    from ros_helpers import compensator_under_test, ESTIMATES
    names = ['theta', 'w', 'q']
    params = ('simulator.mode:=realtime', 'diagnostics_period:=0.2', 'use_sim_time:=true')
    with compensator_under_test(tmp_path, publish=(ESTIMATES, ('/clock', Clock, 10)),
                                params=params) as run:
        est, clock_pub = run.pubs['state/estimate'], run.pubs['/clock']
        commands = run.listener.commands
        state = {'t': 10.0, 'clock': True, 'estimates': True, 'next': None}

        def tick():
            """Step /clock (and an estimate) every 0.05 s of the wall clock while on."""
            import time
            now = time.monotonic()
            if state['next'] is None:
                state['next'] = now
            while state['next'] <= now and state['clock']:
                state['next'] += 0.05
                state['t'] = round(state['t'] + 0.05, 6)
                msg = Clock()
                msg.clock.sec, msg.clock.nanosec = divmod(round(state['t'] * 1e9), 10**9)
                clock_pub.publish(msg)
                if state['estimates']:
                    est.publish(joint_state(names, [0.01, 0.0, 0.0], state['t']))
            if not state['clock']:
                state['next'] = None
            return False

        def until(predicate, what):
            run.probe.spin_until(lambda: tick() or predicate(), what=what)

        def stamps(since):
            return [stamp_to_sec(m.header.stamp) for m in commands[since:]]
        until(lambda: len(commands) >= 10, 'commands answering the estimates')
        state['estimates'] = False          # the vehicle's own data stops, /clock goes on
        until(lambda: run.listener.counter('compensator', 'safe_commands') >= 10,
              'safe commands')
        n = len(commands)
        until(lambda: len(commands) >= n + 10, 'more safe commands')
        # on /clock's time: never ahead of it (the estimates' time base)
        assert max(stamps(n)) <= state['t'] + 1e-9, (stamps(n), state['t'])
        state['clock'] = False              # /clock's owner stops
        stopped = state['t']
        until(lambda: '/clock stopped at' in (run.listener.latest_status('compensator')
                                              .message), '/clock stopped said')
        held = len(commands)
        status = run.listener.latest_status('compensator')
        assert status.level == DiagnosticStatus.ERROR and \
            f'/clock stopped at {stopped:.3f} s' in status.message, status.message
        until(lambda: run.listener.counter('compensator', 'safe_commands_held') >= 20,
              'safe commands held')
        late = stamps(held)
        assert not late or max(late) <= stopped + 1e-9, (late, stopped)
        state['clock'] = True               # /clock moves again: the commands follow it
        until(lambda: any(s > stopped for s in stamps(held)), 'safe commands again')
        again = [s for s in stamps(held) if s > stopped]
        assert min(again) <= stopped + 0.2, (again, stopped)
