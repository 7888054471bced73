# test_core_loop_supervisor: the compensator's decisions, in process, without DDS.
"""
Tests of observer_ros.core.loop_supervisor and core.standby.

The loops here are simulated in the test: the plant on its exact ZOH model, applying each
command from its stamp as the realtime simulator does; an observer (the same History the
observer node runs) fed with the measurements and the commands; the supervisor given
both, with wall times equal to the stamps.
"""

import itertools
import math
import random

import numpy as np
from observer_ros.core import plant_clock
from observer_ros.core.estimators import History, make_estimator
from observer_ros.core.health import ENVELOPE_FACTOR, ENVELOPE_PERSIST
from observer_ros.core.loop_command import command_refusal
from observer_ros.core.loop_supervisor import ERROR, LoopSupervisor, OK, RESYNC_AGREE, WARN
from observer_ros.core.model import zoh_matrices
from observer_ros.core.standby import unstable_plant
from observer_ros.core.vehicle_design import design_vehicle
from observer_ros.timeutil import ns_to_sec, stamp_sec
from observer_ros.vehicle import load_vehicle
import pytest
from ros_helpers import CONFIG

# One message in this many is delayed by up to the loop's ``jitter`` (see CartLoop).
SPIKES = 100


def supervisor(name, *overrides, **kwargs):
    """Return a LoopSupervisor of a shipped vehicle, its counters and its log lines."""
    v = load_vehicle(str(CONFIG / f'{name}.yaml'), overrides=list(overrides))
    counts, logs = {}, []

    def count(key, n=1):
        counts[key] = counts.get(key, 0) + n
    sup = LoopSupervisor(v, design_vehicle(v), count=count,
                         log=lambda level, text: logs.append((level, text)), **kwargs)
    return sup, counts, logs


class CartLoop:
    """
    The realtime cart: plant, observer processes, the supervisor, and the time between.

    Every message takes time: a measurement reaches the compensator and each observer
    ``lag()`` s after its stamp, an estimate the compensator ``lag()`` s after the
    observer took the measurement, a command the plant and the observers ``lag()`` s after
    it was decided; ``lag`` draws from 0 to ``jitter`` s (a loaded host: several sample
    times). The plant applies a command from its stamp, or from when it arrives if that
    is later, and ignores one older than the newest it has (the realtime simulator).
    ``stalls``: (from, to) when the compensator's process does not run (a busy host): the
    messages that reach it meanwhile are taken at the end, one after the other.
    ``plant_rate``: seconds of plant time per wall second (a simulator whose timer skips
    ticks on a busy host runs slower than the wall clock), each step ``spread`` of its
    mean wall time early or late at random; times given to the supervisor, lags and
    stalls are wall times, stamps and the trace plant times. ``busy``: (from, to, most)
    when every message, either way, takes up to ``most`` s more (the host's processes
    short of CPU). ``hold``: s the plant waits at its step 0, its state held, before it
    steps (a /clock follower whose peers start late: its step 1 is stamped on /clock's
    time, this much after step 0).
    """

    def __init__(self, seed=0, jitter=0.0, stalls=(), plant_rate=1.0, spread=0.0, busy=(),
                 hold=0.0):
        self.sup, self.counts, self.logs = supervisor('cart_pendulum',
                                                      'simulator.mode:=realtime')
        v = self.v = self.sup.vehicle
        self.dt = v.sample_time
        self.Ad, self.Bd = zoh_matrices(v.plant.A, v.plant.B, self.dt)
        self.rng = np.random.default_rng(seed)
        self.jitter = jitter
        self.stalls = list(stalls)
        self.plant_rate, self.spread = plant_rate, spread
        self.busy = list(busy)
        self.hold = float(hold)
        self._walls = [1.0]         # the wall time of each step
        self.ticks = np.random.default_rng(seed + 1)
        self.busy_rng = np.random.default_rng(seed + 2)
        self._last = {}             # busy: the last arrival on each channel
        self.known_publishers = True    # the node learns of a publisher from its match
        self.late = []              # commands applied after their stamp: (stamp, arrival)
        self.x = np.zeros(4)
        self.u, self.newest = np.zeros(1), -math.inf
        self.at_plant = []          # commands on their way: (arrival, stamp, u)
        self.scheduled = []         # arrived, applied from: (time, u)
        self.events = []            # (arrival, seq, what, payload)
        self._seq = itertools.count()
        self.observers = []         # [History, started at, paused (from, to)]
        self.trace = []             # (t, x, mode)
        self.commands = []

    def arrival(self, now, channel):
        """
        Return when a message sent at now arrives: now plus ``lag()``.

        While busy, up to the busy time more, and never before the one sent before it on
        its channel (DDS keeps a writer's order to a reader).
        """
        busy = next((most for a, b, most in self.busy if a <= now < b), 0.0)
        if not busy:
            return now + self.lag()
        last = self._last.get(channel, -math.inf)
        self._last[channel] = when = max(now + float(self.busy_rng.uniform(0.0, busy)), last)
        return when

    def lag(self):
        """Half a millisecond and more (mean 1 ms); one in SPIKES up to ``jitter`` s."""
        if not self.jitter:
            return 0.0
        lag = 0.0005 + float(self.rng.exponential(0.0005))
        if self.rng.random() < 1.0 / SPIKES:
            lag += float(self.rng.uniform(0.0, self.jitter))
        return lag

    def observer(self, start=0.0, pause=(math.inf, math.inf)):
        obs = History(make_estimator(self.v.plant, self.v.observer),
                      self.v.observer.history_length)
        self.observers.append((obs, start, pause))

    def _observe(self, obs, t, y):
        """Step as the observer node does: a gap the model cannot bridge restarts at y."""
        if obs.t is not None and t - obs.t > 1.0:
            obs.reset(None, None)
            x0, C = obs.estimator.x_hat, self.v.plant.C
            obs.reset(x0 + np.linalg.pinv(C) @ (y - C @ x0), None)
        return np.array(obs.correct(t, y, (0,)))

    def _stalled(self, when):
        return next((b for a, b in self.stalls if a <= when < b), None)

    def _at(self, when, what, payload):
        if what in ('measurement', 'estimate'):
            end = self._stalled(when)
            if end is not None:
                when = end      # queued for the compensator, taken in the order they came
        self.events.append((when, next(self._seq), what, payload))

    def _handle(self, now, what, payload, spike):
        sup = self.sup
        out = []
        if what == 'measurement':
            t, y = payload
            out.append(sup.measurement('encoder', t, y, now))
        elif what == 'observe':
            k, t, y = payload
            obs, start, (a, b) = self.observers[k]
            # the node learns of a publisher from the match, before its first message
            if self.known_publishers:
                sup.publishers = max(1, sum(t >= o[1] for o in self.observers))
            if t >= start and not a <= t < b and not self.wall(a) <= now < self.wall(b):
                x_hat = self._observe(obs, t, y)
                if spike is not None and abs(t - spike) < 1e-9:
                    x_hat = np.full(4, 1e304)
                self._at(self.arrival(now, ('estimate', k)), 'estimate', (t, x_hat))
        elif what == 'estimate':
            out.append(sup.estimate(*payload, now))
        elif what == 'command':
            k, stamp, u = payload
            self.observers[k][0].set_input(stamp, u)
        else:
            out.append(sup.safe_tick(now))
        for command in out:
            if command is None:
                continue
            self.commands.append(command)
            u = np.array(command.u, dtype=float)
            stamp = stamp_sec(command.t)        # as it reads back from the wire
            self.at_plant.append((self.arrival(now, 'plant'), stamp, u))
            for k in range(len(self.observers)):
                self._at(self.arrival(now, ('command', k)), 'command', (k, stamp, u))

    def wall(self, t):
        """Return the wall time at which the plant reaches its time t."""
        if math.isinf(t):
            return t
        k, frac = divmod((t - 1.0) / self.dt, 1.0)
        k = int(k)
        walls, step = self._walls, self.dt / self.plant_rate
        while len(walls) < k + 2:
            walls.append(walls[-1] + step * (1.0 + self.spread * self.ticks.uniform(-1.0, 1.0)))
        return walls[k] + frac * (walls[k + 1] - walls[k])

    def run(self, until, spike=None):
        """Step the loop to the (plant) time ``until``."""
        sup = self.sup
        while True:
            k = len(self.trace)
            t = stamp_sec(1.0 + k * self.dt + (self.hold if k else 0.0))   # read from the wire
            if t > until:
                return
            w = self.wall(t)
            # the plant's command at t: those arrived by its step, each from its stamp
            for entry in sorted((e for e in self.at_plant if e[0] <= w + 1e-9),
                                key=lambda e: e[0]):     # in the order sent at one time
                self.at_plant.remove(entry)
                if entry[0] > self.wall(entry[1] + 0.25 * self.dt):
                    self.late.append((entry[1], entry[0]))
                if entry[1] >= self.newest - 0.25 * self.dt:
                    self.newest = max(self.newest, entry[1])
                    self.scheduled.append((max(entry[1], t), entry[2]))
            for entry in sorted((e for e in self.scheduled if e[0] <= t + 1e-9),
                                key=lambda e: e[0]):
                self.u = entry[1]
                self.scheduled.remove(entry)
            y = self.v.plant.C @ self.x + 1e-5 * self.rng.standard_normal(1)
            self._at(self.arrival(w, 'measurement'), 'measurement', (t, y))
            for k in range(len(self.observers)):
                self._at(self.arrival(w, ('observe', k)), 'observe', (k, t, y))
            # everything that arrives before the next step, in the order it arrives
            end = self.wall(t + self.dt)
            while True:
                ready = sorted(e for e in self.events if e[0] < end)
                if not ready:
                    break
                event = ready[0]
                self.events.remove(event)
                self._handle(event[0], event[2], event[3], spike)
            if self._stalled(end) is None:
                sup.watchdog(end)
                self._handle(end, 'tick', None, spike)
            self.x = self.Ad @ self.x + self.Bd @ self.u
            self.trace.append((t, self.x.copy(), sup.mode))

    def worst(self, since, until=math.inf):
        """Return max |theta| and max |x - x_d| between two times."""
        states = [x for t, x, _ in self.trace if since <= t < until]
        return max(abs(x[0]) for x in states), max(abs(x[1] - 1.0) for x in states)


def test_plant_time_is_the_newest_sensor_stamp_started_over_on_an_agreed_clock_jump():
    sup, counts, _ = supervisor('cart_pendulum', 'simulator.mode:=realtime')
    tolerance, agreement = sup.sensor_jumps.tolerance, sup.sensor_jumps.agreement
    plant, streak, jumps = None, 0, 0
    rnd = random.Random(2)
    clock = 10.0
    for k in range(3000):
        name = rnd.choice(['encoder', 'imu'])
        if rnd.random() < 0.005:
            clock = rnd.uniform(1.0, 5.0)               # the simulator restarts
        clock += rnd.uniform(-0.2, 0.3) * 0.01          # a little out of order at times
        t = clock
        if plant is not None and plant - t > tolerance:
            streak += 1                                 # far back: skipped until agreed
            if streak == agreement:
                plant, streak = t, 0
                jumps += 1
        else:
            plant, streak = t if plant is None else max(plant, t), 0
        sup.measurement(name, t, None, float(k))
        assert sup.plant_time == plant, (k, sup.plant_time, plant)
        assert sup._steps_late(t - 0.05) == sup.delay.steps_late(plant, t - 0.05), k
        assert sup._steps_late(t - 0.05, float(k)) == sup._steps_late(t - 0.05), k
    assert jumps >= 5 and counts['clock_jumps'] == jumps, (jumps, counts)


def test_a_single_wild_sensor_stamp_resets_nothing_a_restart_after_the_agreed_count():
    sup, counts, logs = supervisor('cart_pendulum', 'simulator.mode:=realtime')
    x = np.array([0.0, 1.0, 0.0, 0.0])
    for k in range(150):
        t = round(10.0 + 0.01 * k, 9)
        sup.measurement('encoder', t, [1.0], t)
        sup.estimate(t, x, t)
    # one stamp from nowhere (2 s, or an hour, back): skipped, counted, said
    for wild in (8.0, t - 3600.0):
        before = (sup.plant_time, sup.standby.t, sup.standby.history.x_hat.copy())
        assert sup.measurement('encoder', wild, [5.0], t) is None
        assert (sup.plant_time, sup.standby.t) == before[:2]
        np.testing.assert_array_equal(sup.standby.history.x_hat, before[2])
        t = round(t + 0.01, 9)
        sup.measurement('encoder', t, [1.0], t)             # the old time base goes on
    assert counts['far_back_stamps'] == 2 and 'clock_jumps' not in counts
    assert any('skipped (a clock jump needs 3 such messages in a row)' in text
               for _, text in logs)
    # the simulator restarts at 1.0 s and re-sends its step 0: the third agrees
    newest = sup.plant_time
    assert sup.measurement('encoder', 1.0, [0.0], 12.0) is None
    assert sup.measurement('encoder', 1.0, [0.0], 12.2) is None
    assert sup.plant_time == newest and sup.standby.warm
    sup.measurement('encoder', 1.0, [0.0], 12.4)
    assert counts['clock_jumps'] == 1 and counts['far_back_stamps'] == 4
    assert sup.plant_time == 1.0 and sup.standby.t == 1.0 and not sup.standby.warm
    np.testing.assert_array_equal(sup.safe.last_command, [0.0])   # the old run's forgotten
    # the observer's estimates follow by the same rule: one far back is ignored
    assert sup.estimate(1.0, np.zeros(4), 12.41) is None
    assert counts['far_back_estimates'] == 1 and 'estimate_clock_jumps' not in counts


@pytest.mark.parametrize('name', ['submarine', 'cart_pendulum'])
def test_one_absurd_estimate_never_becomes_a_command(name):
    """1e304 on state/estimate: refused at once; the safe command never grows from it."""
    sup, counts, logs = supervisor(name, 'simulator.mode:=realtime')
    assert sup.u_min is None and sup.u_max is None          # every shipped file
    n = sup.vehicle.plant.n
    bound = np.array(sup.u_envelope.bound)
    x = np.zeros(n)
    first = sup.estimate(5.0, x, 0.0)
    assert first.source == 'observer'
    command = sup.estimate(5.05, np.full(n, 1e304), 0.05)
    assert command.source == 'safe' and command.answers        # refused the first time
    assert counts['implausible_estimates'] == 1
    assert logs[-1][0] == ERROR and logs[-1][1].startswith('implausible:'), logs
    level, message, _ = sup.status()
    assert level == ERROR and 'implausible' in message and '1e+304' in message
    # silent from here on: the safe command every sample time, predicted from the last
    # estimate that passed (zero), then the fallback; never near 1e304
    sent = [command]
    now = 0.05
    while len(sent) < 224:
        now += sup.dt
        sup.watchdog(now)
        tick = sup.safe_tick(now)
        if tick is not None:
            sent.append(tick)
    u = np.array([c.u for c in sent])
    assert np.all(np.isfinite(u)) and np.all(np.abs(u) <= bound), np.max(np.abs(u))
    assert np.max(np.abs(u)) < 1e-9 * max(1.0, float(np.max(bound))) or name == 'cart_pendulum'


def test_without_limits_the_command_is_bounded_by_the_design():
    sup, _, _ = supervisor('cart_pendulum')
    scale = np.array(sup.x_envelope.file_scale)
    want = ENVELOPE_FACTOR * (np.abs(sup.K) @ (scale + np.abs(sup.x_d)))
    np.testing.assert_allclose(sup.u_envelope.bound, want)
    assert command_refusal(sup.law, sup.u_envelope, [0.5 * want[0]]) is None
    reason = command_refusal(sup.law, sup.u_envelope, [2.0 * want[0]])
    assert 'beyond the bound' in reason and 'no controller.u_min/u_max' in reason
    # with limits the limits decide (a command is clipped into them, never refused by K)
    limited, _, _ = supervisor('cart_pendulum', 'controller.u_min:=[-50.0]',
                               'controller.u_max:=[50.0]')
    assert command_refusal(limited.law, limited.u_envelope, [49.0]) is None
    assert 'outside the limits' in command_refusal(limited.law, limited.u_envelope, [51.0])


def test_estimates_beyond_the_envelope_in_a_row_are_diverging():
    sup, counts, logs = supervisor('submarine')
    sup.estimate(5.0, np.zeros(3), 0.0)
    x = 1.0
    for k in range(1, ENVELOPE_PERSIST + 2):
        x *= 30.0
        command = sup.estimate(5.0 + 0.05 * k, np.array([x, 0.0, 0.0]), 0.05 * k)
        if x > ENVELOPE_FACTOR * sup.x_envelope.file_scale[0]:
            assert command.source == 'safe'
    assert counts['implausible_estimates'] >= ENVELOPE_PERSIST
    words = [text.split(':', 1)[0] for _, text in logs]
    assert words[0] == 'implausible' and words[-1] == 'diverging', words
    assert sup.status()[1].startswith('diverging: x_hat theta')
    # a plausible estimate closes the loop again: OK
    command = sup.estimate(6.0, np.zeros(3), 1.0)
    assert command.source == 'observer' and sup.status()[0] == OK


def test_a_repeated_stamp_gets_the_same_command_and_an_older_one_none():
    sup, counts, _ = supervisor('submarine')
    first = sup.estimate(5.0, np.array([0.1, 0.0, 0.0]), 0.0)
    again = sup.estimate(5.0, np.array([0.2, 0.0, 0.0]), 0.001)    # a repeat: not redone
    assert again is first and sup.safe.last_command.tolist() == list(first.u)
    assert sup.estimate(4.95, np.zeros(3), 0.002) is None
    assert counts['repeated_estimates'] == 2 and counts['commands'] == 1
    sup.publishers = 2                      # from another publisher: nothing
    assert sup.estimate(5.0, np.zeros(3), 0.003) is None


def test_with_two_publishers_the_stream_followed_is_kept():
    """Without a standby: the other stream is told by the model's prediction."""
    sup, counts, logs = supervisor('submarine')
    sup.publishers = 2
    x = np.array([0.3, 0.0, 0.0])
    followed = []
    for k in range(40):
        t = 5.0 + 0.05 * k
        if k:       # the other stream's estimate arrives first (not at the first stamp)
            assert sup.estimate(t, np.array([-0.4, 0.2, 0.1]), t) is None
        command = sup.estimate(t, x, t + 0.001)
        assert command is not None and command.source == 'observer'
        followed.append(command.u)
        x = sup.safe.predict_from(x, 1)
    assert counts['other_stream_estimates'] == 40 - 1
    level, message, _ = sup.status(['/state/estimate (2 publishers)'])
    assert level == ERROR and 'following one estimate stream' in message
    assert sum('does not follow the stream' in text for _, text in logs) == 1   # said once


def test_the_standby_closes_the_loop_while_the_observer_is_paused():
    """The cart, observer silent 3 s: held near x_d throughout, then back on the observer."""
    assert unstable_plant(load_vehicle(str(CONFIG / 'cart_pendulum.yaml')).plant)
    loop = CartLoop()
    loop.observer(pause=(12.0, 15.0))
    loop.run(20.0)
    assert loop.sup.standby is not None
    theta, dx = loop.worst(12.0, 15.0)
    assert theta < 0.03 and dx < 0.05, (theta, dx)
    modes = [m for t, _, m in loop.trace if 12.2 <= t < 15.0]
    assert set(modes) == {'stale'}, set(modes)
    assert loop.counts['standby_commands'] >= 250          # one per measurement
    assert loop.trace[-1][2] == 'closed'
    back = next(t for t, _, m in loop.trace if t > 15.0 and m == 'closed')
    assert back < 16.0, back
    assert loop.counts['resync_estimates'] >= RESYNC_AGREE - 1
    assert loop.worst(15.0)[1] < 0.05


def test_a_plant_that_waited_at_step_0_is_followed_from_its_first_step():
    """
    A /clock follower waits 3.66 s at step 0 for its peers, then steps on /clock's time.

    The gap is longer than the cart's model can be predicted over (1.40 s): the observer
    restarts at the measurement, and so does the standby (its admission is the
    observer's); it is not warm again before 0.4 s of measurements, so the observer's
    estimates close the loop, none ignored, and the cart reaches x_d.
    """
    loop = CartLoop(hold=3.66)
    loop.observer()
    loop.run(13.0)
    standby = loop.sup.standby
    assert standby.counts.get('long_gap_resets') == 1, standby.counts
    assert loop.counts['standby_restarts'] == 1
    assert any('standby observer: encoder 3.67 s after its estimate' in text
               for _, text in loop.logs), loop.logs
    assert 'other_stream_estimates' not in loop.counts, loop.counts
    assert 'implausible_estimates' not in loop.counts, loop.counts
    assert {m for t, _, m in loop.trace if t > 4.66} == {'closed'}
    assert all(c.source == 'observer' for c in loop.commands), \
        {c.source for c in loop.commands}
    # as without the wait (x within 0.003 of x_d 8 s after the start), 3.66 s later
    theta, dx = loop.worst(12.66)
    assert theta < 0.005 and dx < 0.005, (theta, dx)


def test_the_envelopes_learn_again_after_a_wait_at_step_0():
    """
    The first seconds after a long gap are learned as the first seconds of a run.

    The observer restarts at the measurement after the wait, and its new initial
    transient may reach beyond what step 0 alone made plausible (theta_dot 100 on the
    cart's file); growing from within the bound, it is learned, not refused.
    """
    loop = CartLoop(hold=3.66)
    loop.observer()
    loop.run(4.7)
    sup = loop.sup
    assert loop.counts['standby_restarts'] == 1
    t = loop.trace[-1][0]
    for k, rate in enumerate((50.0, 150.0)):
        x = [0.0, 0.0, 0.0, rate]
        t_k = t + 0.01 * (k + 1)
        command = sup.estimate(t_k, x, loop.wall(t_k) + 0.001)
        assert command is not None and command.source == 'observer', (rate, command)
    assert 'implausible_estimates' not in loop.counts, loop.counts


def test_a_standby_beyond_the_envelope_vetoes_no_estimate():
    """
    A diverged standby is no reference for which estimates are the stream followed.

    An estimate 0.6 s after the last one followed (past the model's 50-step check) that
    the standby, predicted far beyond the envelope, disagrees with is followed, not
    ignored as another stream's.
    """
    loop = CartLoop()
    loop.observer()
    loop.run(3.0)
    sup = loop.sup
    assert sup.standby.warm
    t, x = loop.trace[-1][0] + 0.6, loop.trace[-1][1]
    sup.standby.history.reset(np.array([0.0, 0.0, 0.0, -1.2e6]), sup.standby.history.t)
    sup.standby._recent.clear()
    command = sup.estimate(t, x, loop.wall(t) + 0.001)
    assert command is not None and command.source == 'observer', command
    assert 'other_stream_estimates' not in loop.counts, loop.counts


def test_the_standby_answers_a_repeated_stamp_without_correcting_again():
    """Step 0 re-sent: the standby's estimate at it is the same, as the observer's."""
    sup, _, _ = supervisor('cart_pendulum', 'simulator.mode:=realtime')
    standby = sup.standby
    y = np.array([0.3])
    first = standby.measurement('encoder', 1.0, y)
    for _ in range(3):
        again = standby.measurement('encoder', 1.0, y)
        assert np.array_equal(again, first)
    assert standby.counts['duplicates'] == 3
    assert np.array_equal(standby.history.x_hat, first)


def test_before_the_standby_is_warm_the_loop_stays_on_the_estimates():
    """
    A silence in the standby's first settling time: the estimates stay followed.

    The standby (warm after 0.4 s of measurements) is no reference yet: a delay of the
    estimates then is not a switch to it (the plant holds the last command), and the
    estimates that come back are followed at once, not ignored until it is warm.
    """
    loop = CartLoop(jitter=0.03)
    loop.observer(pause=(1.1, 1.2))
    loop.run(3.0)
    assert loop.sup.standby.warm
    modes = {m for t, _, m in loop.trace if t < 1.45}
    assert modes == {'closed'}, modes
    early = [c for c in loop.commands if c.t < 1.4]
    assert all(c.source == 'observer' for c in early), {c.source for c in early}
    assert loop.worst(1.0)[0] < 0.12
    # the same silence once it is warm: the standby answers the measurements
    loop = CartLoop(jitter=0.03)
    loop.observer(pause=(2.1, 2.2))
    loop.run(3.0)
    assert any(c.source == 'standby' and 2.1 < c.t < 2.3 for c in loop.commands)


def test_the_standby_holds_the_cart_when_messages_are_late():
    """
    One message in SPIKES up to 30 ms late: the paused observer's cart stays near x_d.

    Over seeds 0-9: |theta| under 0.3 rad in every run, x within 0.2 m of x_d in at least
    8 and within 0.3 m in all; the same loop without the standby (predict-and-hold, then
    hold) drops the pendulum.
    """
    worst = []
    for seed in range(10):
        loop = CartLoop(seed, jitter=0.03)
        loop.observer(pause=(12.0, 15.0))
        loop.run(17.0)
        worst.append(loop.worst(12.0, 15.0))
        assert loop.trace[-1][2] == 'closed', seed
    assert all(theta < 0.3 and dx < 0.3 for theta, dx in worst), worst
    assert sum(dx < 0.2 for _, dx in worst) >= 8, worst
    seed = 0
    bare = CartLoop(seed, jitter=0.03)
    bare.sup.standby = None
    bare.observer(pause=(12.0, 15.0))
    bare.run(15.0)
    assert bare.worst(12.0, 15.0)[0] > 1.0


@pytest.mark.parametrize('stall', [0.08, 0.2])
@pytest.mark.parametrize('at', [12.105, 13.0])
def test_a_stalled_compensator_stamps_its_commands_where_the_plant_will_be(stall, at):
    """
    The compensator's process stalls while the standby closes the loop (as it takes over).

    The measurements queued meanwhile are taken one after the other: the commands
    answering them are stamped after the plant's time by the wall clock, not their
    stamps, so none is applied after its stamp and the cart stays near x_d.
    """
    loop = CartLoop(stalls=[(at, at + stall)])
    loop.observer(pause=(12.0, 15.0))
    loop.run(16.0)
    theta, dx = loop.worst(12.0, 16.0)
    assert theta < 0.03 and dx < 0.06, (theta, dx)
    assert loop.late == [], loop.late[:5]
    assert loop.counts['standby_commands'] >= 250


def test_the_plant_clock_moves_stamps_only_when_measurements_queued():
    """
    On time, a command is stamped its measurement's stamp plus the lead; queued, later.

    For 2 s after a measurement waited, the lead is longer by that wait (a busy host
    delays the commands too).
    """
    sup, _, _ = supervisor('cart_pendulum', 'simulator.mode:=realtime')
    lead = sup.delay.lead
    x = [0.0, 1.0, 0.0, 0.0]
    for k in range(5):
        t = 1.0 + 0.01 * k
        sup.measurement('encoder', t, None, 100.0 + 0.01 * k + 0.002)
        command = sup.estimate(t, x, 100.0 + 0.01 * k + 0.003)
        assert abs(command.t - (t + lead * 0.01)) < 1e-9, command
    # then 0.1 s without this process running: the next measurement is taken 0.1 s late
    t = 1.05
    sup.measurement('encoder', t, None, 100.15 + 0.002)
    command = sup.estimate(t, x, 100.15 + 0.003)
    assert abs(command.t - (t + (lead + 9 + 10) * 0.01)) < 1e-9, command
    # the queue drained: on time again, the lead 0.1 s longer for 2 s
    for k in range(6, 9):
        t = 1.0 + 0.01 * k
        sup.measurement('encoder', t, None, 100.15 + 0.0002 * k)
    t = 1.18
    sup.measurement('encoder', t, None, 100.182)
    command = sup.estimate(t, x, 100.183)
    assert abs(command.t - (t + (lead + 10) * 0.01)) < 1e-9, command
    for k in range(19, 320):
        t = stamp_sec(1.0 + 0.01 * k)
        sup.measurement('encoder', t, None, t + 99.002)
        command = sup.estimate(t, x, t + 99.003)
    assert abs(command.t - (t + lead * 0.01)) < 1e-9, command


@pytest.mark.parametrize('seed', [0, 1])
@pytest.mark.parametrize('fault', ['second observer', 'observer paused'])
def test_a_plant_slower_than_the_wall_clock_gets_commands_stamped_from_its_own_time(
        fault, seed):
    """
    The simulator at 40 % of real time, its steps irregular (a timer on a busy host).

    The plant's rate is measured: commands are stamped from the plant's own time, not
    0.3 s ahead of it, and the standby does not take safe commands between its own for
    sample times of the wall clock. A second, unconverged observer from t = 8 s or the
    observer silent 3 s: the cart stays within 0.2 m of x_d, no command applied late.
    """
    loop = CartLoop(seed, jitter=0.03, plant_rate=0.4, spread=0.9)
    loop.observer(pause=(12.0, 15.0) if fault == 'observer paused' else (math.inf, math.inf))
    if fault == 'second observer':
        loop.observer(start=8.0)
    loop.run(15.0)
    theta, dx = loop.worst(8.0)
    assert theta < 0.3 and dx < 0.2, (theta, dx)
    assert loop.late == [], loop.late[:5]
    assert 0.3 < loop.sup.plant_clock.rate < 0.7, loop.sup.plant_clock.rate
    if fault == 'observer paused':
        assert loop.counts['standby_commands'] > 250
        assert loop.counts.get('safe_commands', 0) < 20, loop.counts
    else:
        assert loop.counts['other_stream_estimates'] >= 5


@pytest.mark.parametrize('seed', [0, 1, 3])
def test_on_a_busy_host_commands_are_stamped_further_ahead(seed, monkeypatch):
    """
    2 s in which every message takes up to 30 ms more, as a second observer starts.

    The measurements' waits raise the lead: no command reaches the plant after its stamp
    and the cart stays within 0.2 m of x_d; with command_lead_steps alone the commands come
    late (up to 30 ms against a lead of 30 ms) and the loop diverges.
    """
    loop = CartLoop(seed, jitter=0.002, busy=[(9.0, 11.0, 0.03)])
    loop.observer()
    loop.observer(start=9.0)
    loop.run(13.0)
    theta, dx = loop.worst(8.0)
    assert theta < 0.3 and dx < 0.2, (theta, dx)
    assert loop.late == [], loop.late[:5]
    monkeypatch.setattr(plant_clock, 'LEAD_MOST', 0.0)
    bare = CartLoop(seed, jitter=0.002, busy=[(9.0, 11.0, 0.03)])
    bare.observer()
    bare.observer(start=9.0)
    bare.run(13.0)
    assert len(bare.late) > 50 and bare.worst(8.0)[0] > 1.0, (len(bare.late), bare.worst(8.0))


def test_no_estimate_is_due_while_the_plant_waits_at_its_first_step():
    """
    A realtime simulator sends its step 0 and waits for a command before it steps.

    The watchdog judges nothing meanwhile (no false stale), and the wait is no lag of
    the compensator: the first commands after it are stamped their measurement's stamp
    plus the lead. Once the plant steps, a silent observer is stale as ever.
    """
    sup, counts, logs = supervisor('cart_pendulum', 'simulator.mode:=realtime')
    lead = sup.delay.lead
    x = [0.0, 0.0, 0.0, 0.0]
    for now in (99.2, 99.6, 100.0):     # step 0, sent again until a command answers it
        sup.measurement('encoder', 1.0, None, now)
    command = sup.estimate(1.0, x, 100.001)
    assert abs(command.t - (1.0 + lead * 0.01)) < 1e-9, command
    # the command reaches the plant late (DDS matching on a busy host); step 0 re-sent
    for k in range(1, 16):
        now = 100.0 + 0.1 * k
        if k % 4 == 0:
            sup.measurement('encoder', 1.0, None, now)
            assert sup.estimate(1.0, x, now + 0.001) is command     # a repeat
        assert not sup.watchdog(now + 0.05), now
        assert sup.safe_tick(now + 0.05) is None
    assert not sup.stale and 'safe_commands' not in counts, counts
    assert not any(text.startswith('estimate stale') for _, text in logs), logs
    # the plant steps: its measurements on time, the commands stamped without the wait;
    # the estimate of step 1 is due from the plant's first step, not from step 0's
    sup.measurement('encoder', 1.01, None, 101.61)
    assert not sup.watchdog(101.62) and not sup.stale
    for k in range(1, 6):
        t, now = 1.0 + 0.01 * k, 101.6 + 0.01 * k
        if k > 1:
            sup.measurement('encoder', t, None, now)
        command = sup.estimate(t, x, now + 0.002)
        assert abs(command.t - (t + lead * 0.01)) < 1e-9, (k, command)
    # then the observer falls silent while the plant steps: stale
    assert not sup.watchdog(101.7)
    assert sup.watchdog(102.2) and sup.stale
    assert logs[-1][1].startswith('estimate stale (0.'), logs[-1]


def test_a_second_observer_with_the_same_topic_does_not_move_the_cart():
    loop = CartLoop(jitter=0.002)       # which observer's estimate comes first varies
    loop.observer()
    loop.observer(start=8.0)            # unconverged: x_hat(0) = 0 with the cart at 1 m
    loop.run(12.0)
    assert loop.worst(8.0)[1] < 0.05, loop.worst(8.0)
    assert loop.counts['other_stream_estimates'] >= 5


def test_a_second_observer_not_yet_known_as_a_publisher_does_not_move_the_cart():
    """Its estimates come before its match is known: the warm standby tells them apart."""
    loop = CartLoop(jitter=0.002)
    loop.known_publishers = False
    loop.observer()
    loop.observer(start=8.0)            # unconverged: x_hat(0) = 0 with the cart at 1 m
    loop.run(12.0)
    assert loop.sup.publishers == 1
    assert loop.worst(8.0)[1] < 0.05, loop.worst(8.0)
    assert loop.counts['other_stream_estimates'] >= 5


def test_an_absurd_estimate_in_the_cart_loop_moves_nothing():
    loop = CartLoop()
    loop.observer()
    loop.run(12.0, spike=9.0)
    assert loop.counts['implausible_estimates'] == 1
    assert 'divergence_safe_commands' not in loop.counts    # the standby's reference: ignored
    assert loop.worst(8.0)[1] < 0.05
    assert max(max(abs(v) for v in c.u) for c in loop.commands) < 100.0


def _gone_stale(sup, x):
    """Feed 10 estimates 0.05 s apart from t = 5 s, then 1 s of silence; return 5.5."""
    t = 5.0
    for _ in range(10):
        sup.estimate(t, x, t)
        t += 0.05
    assert sup.watchdog(t + 1.0)
    return t


def test_a_compensator_that_did_not_run_takes_its_queued_estimates_before_judging():
    # the watchdog checks every 0.1 s; the process stops for 0.63 s (a busy host) while
    # the observer goes on: the first check after the stop comes before the estimates
    # that queued meanwhile, and judges nothing; the observer really silent: the next
    # check goes stale
    for observer_runs in (True, False):
        sup, counts, logs = supervisor('cart_pendulum_robust', 'simulator.mode:=realtime')
        x = np.array([0.0, 1.0, 0.0, 0.0])
        now = 1.0
        for _ in range(5):
            sup.estimate(now, x, now)
            assert not sup.watchdog(now + 0.05)
            now += 0.1
        now += 0.63
        assert not sup.watchdog(now) and counts['watchdog_deferred'] == 1
        assert not sup.stale
        if observer_runs:
            for k in range(63):
                sup.estimate(now - 0.63 + 0.01 * k, x, now + 0.001 * k)
        assert sup.watchdog(now + 0.1) is not observer_runs
        assert sup.stale is not observer_runs
        if not observer_runs:
            assert logs[-1][1].startswith('estimate stale (0.')


def test_without_a_standby_stale_predicts_then_falls_back_then_resyncs():
    sup, counts, logs = supervisor('submarine', 'simulator.mode:=realtime',
                                   'controller.predict_timeout:=3.0',
                                   'controller.safe_command:=hold')
    assert sup.standby is None          # a stable plant can be held
    x = np.array([0.1, 0.0, 0.0])
    t = now = _gone_stale(sup, x)
    assert sup.stale and logs[-1][1].startswith('estimate stale')
    modes = []
    for k in range(60):
        command = sup.safe_tick(now + 1.0 + 0.05 * k)
        assert command.marked and command.source == 'safe'
        modes.append(sup.safe_mode)
    assert modes[0] == 'predict' and modes[-1] == 'hold'
    # back: the prediction closes the loop until the observer's estimates follow the model
    command = sup.estimate(t + 5.0, x, now + 5.0)
    assert sup.mode == 'resync' and command.source == 'safe' and command.answers
    assert counts['resync_commands'] == 1


def test_a_restarted_clock_starts_the_loop_over():
    sup, counts, _ = supervisor('cart_pendulum', 'simulator.mode:=realtime')
    sup.measurement('encoder', 30.0, [1.0], 0.0)
    sup.estimate(30.0, np.array([0.0, 1.0, 0.0, 0.0]), 0.0)
    assert sup.standby.t == 30.0
    assert sup.estimate(1.01, np.zeros(4), 0.01) is None      # one alone: an outlier
    assert sup.estimate(1.01, np.zeros(4), 0.02) is None
    assert counts['far_back_estimates'] == 2 and sup.standby.t == 30.0
    command = sup.estimate(1.01, np.zeros(4), 0.03)            # the third agrees
    assert counts['estimate_clock_jumps'] == 1 and command.source == 'observer'
    assert [stamp for stamp, _ in sup.delay._sent] == [stamp_sec(command.t)]   # the old run's


def test_safe_commands_are_never_stamped_past_the_clock_followed():
    # a second vehicle follows /clock; its owner stops: the wall clock runs on, /clock not
    clock = [5.45]
    sup, _, _ = supervisor('submarine', 'simulator.mode:=realtime',
                           clock_bound=lambda: clock[0])
    x = np.array([0.1, 0.0, 0.0])
    now = _gone_stale(sup, x)
    stamps = [sup.safe_tick(now + 1.0 + 0.05 * k).t for k in range(40)]
    assert max(stamps) == pytest.approx(5.45)       # not 7.4 s: 2 s of wall clock on
    clock[0] = 5.5                                  # /clock moves again
    assert sup.safe_tick(now + 3.0).t == pytest.approx(5.5)
    # without a clock followed, the stamps go on with the wall clock from the last estimate
    sup, _, _ = supervisor('submarine', 'simulator.mode:=realtime')
    _gone_stale(sup, x)
    assert sup.safe_tick(7.4).t == pytest.approx(7.4)


def test_commands_for_one_step_reach_the_standby_as_the_plant_reads_them():
    """
    Commands for one step, stamped t + k dt from different t, differ in their last bits.

    1.24 and 1.2400000000000002 are one stamp on the wire (to the nanosecond), where the
    plant and the observer hold the last one sent; so does the standby.
    """
    sup, _, _ = supervisor('cart_pendulum', 'simulator.mode:=realtime')
    v, dt = sup.vehicle, sup.dt
    t = [ns_to_sec(1_000_000_000 + k * 10_000_000) for k in range(40)]
    a = 24
    assert len({t[a - s] + s * dt for s in range(3, 8)}) > 1     # the float stamps differ
    plant = History(make_estimator(v.plant, v.observer), v.observer.history_length)
    for k in range(a + 5):
        sup.measurement('encoder', t[k], [0.001 * k], t[k])
        plant.correct(t[k], [0.001 * k], (0,))
        s = a - k
        if 3 <= s <= 7:                     # five commands for step a; the last one holds
            sup._send([10.0 * (s - 5)], t[k] + s * dt)
            if s == 3:
                plant.set_input(t[a], np.array([-20.0]))
    np.testing.assert_allclose(sup.standby.history.x_hat, plant.x_hat, rtol=0, atol=1e-12)


def test_an_observer_restarted_by_a_clock_jump_resyncs_with_a_warm_standby():
    """
    Its new initial transient is not followed: the warm standby answers meanwhile.

    As after an outage (resync): its estimates are followed again once RESYNC_AGREE in a
    row agree with the standby's.
    """
    sup, counts, _ = supervisor('cart_pendulum', 'simulator.mode:=realtime')
    x = np.array([0.0, 1.0, 0.0, 0.0])
    t = 10.0
    for k in range(150):                                # the first run, converged
        t = round(10.0 + 0.01 * k, 9)
        sup.measurement('encoder', t, [1.0], t)
        sup.estimate(t, x, t)
    wall = t + 2.0                                      # the simulator restarts at 1.0 s
    for k in range(150):
        s = round(1.0 + 0.01 * k, 9)
        sup.measurement('encoder', s, [1.0], wall + 0.01 * k)
    assert counts['clock_jumps'] == 1 and sup.standby.warm
    # the observer restarts later, its estimate far from the standby's at first
    wall, others = wall + 1.5, counts.get('other_stream_estimates', 0)
    s = 2.5
    for k in range(3):
        sup.measurement('encoder', s, [1.0], wall)
        command = sup.estimate(s, x + [0.0, 0.0, 3.0, 0.0], wall)
        s, wall = round(s + 0.01, 9), wall + 0.01
    assert counts['estimate_clock_jumps'] == 1 and sup.mode == 'resync'
    assert command is None                          # the standby answers the measurements
    assert counts['other_stream_estimates'] == others + 1     # its transient: not followed


def _corrupted_standby(u):
    """Run the cart loop with one command the plant never got, known to the standby alone."""
    loop = CartLoop(jitter=0.002)
    loop.observer()
    loop.run(8.0)
    # between two sample times: no command the compensator sends replaces it
    loop.sup.standby.command(8.0555, [u])
    loop.run(12.0)
    return loop


@pytest.mark.parametrize('u', [5.0, 50.0])
def test_a_standby_that_disagrees_with_the_stream_followed_does_not_take_the_loop(u):
    """
    The standby wrong, the observer right: the loop stays closed on the observer.

    With the standby as the only reference, the observer's estimates were taken for
    another stream's and ignored, the standby closed the loop, and the cart left x_d by
    0.46 m (5 N) to 3.6 m (50 N).
    """
    loop = _corrupted_standby(u)
    theta, off = loop.worst(8.0)
    assert off < 0.02 and theta < 0.01, (theta, off)
    assert loop.counts.get('standby_disagreements', 0) >= 10
    assert 'other_stream_estimates' not in loop.counts
    assert 'standby_commands' not in loop.counts
    assert any(level == WARN and text.startswith('standby observer: more than 0.1')
               for level, text in loop.logs), loop.logs


def test_a_second_observer_is_ignored_then_followed_if_the_first_stops():
    loop = CartLoop(jitter=0.002)
    loop.observer(pause=(9.5, 99.0))    # the first falls silent for good at 9.5 s
    loop.observer(start=8.0)            # unconverged: x_hat(0) = 0 with the cart at 1 m
    loop.run(9.5)
    theta, off = loop.worst(8.0)
    assert off < 0.02, off
    # ignored while it converges (those after the first's at a stamp: repeats)
    assert loop.counts['other_stream_estimates'] >= 5
    # silent: the second one's estimates, converged, continue the stream followed (the
    # model's prediction from the last estimate followed) and agree with the standby:
    # followed; none ignored from then on
    loop.run(11.0)
    n = loop.counts['other_stream_estimates']
    loop.run(13.0)
    theta, off = loop.worst(8.0)
    assert off < 0.05 and theta < 0.05, (theta, off)
    assert loop.sup.mode == 'closed'
    assert loop.counts['other_stream_estimates'] == n


def test_a_restarted_observer_after_a_restarted_plant_keeps_the_commands_order():
    """
    An observer that jumps to a restarted plant's clock after the sensors keeps the order.

    The simulator restarted: its sensors jumped first, the standby closes the loop on the
    new run; while the compensator's process stalled, safe commands went out stamped ahead
    on the plant's clock. The observer's estimates jump to the new run later: no command
    after that is stamped before one already sent (the plant would not apply it, the
    observers would, at its stamp).
    """
    # at rest at its reference: every estimate agrees with the standby's
    sup, counts, _ = supervisor('cart_pendulum', 'simulator.mode:=realtime',
                                'controller.reference:=[0.0, 0.0, 0.0, 0.0]')
    sent = []

    def take(command, stamp):
        if command is not None:
            sent.append(stamp if command.answers else stamp_sec(command.t))

    now = 0.0
    for k in range(100):                    # the first run, closed on the observer
        t = 7.0 + 0.01 * k
        take(sup.measurement('encoder', t, [0.0], now), t)
        take(sup.estimate(t, sup.standby.at(t), now), t)
        sup.watchdog(now)
        now += 0.01
    while not sup.watchdog(now):            # the simulator killed
        now += 0.1
    assert sup.mode == 'stale'
    sent.clear()                            # the restarted plant starts its stamps over
    for _ in range(3):                      # its restart: step 0 until a command answers
        take(sup.measurement('encoder', 1.0, [0.0], now), 1.0)
        now += 0.01
    assert counts['clock_jumps'] == 1
    t = 1.0
    for _ in range(60):                     # the standby closes the loop (warm at 0.4 s)
        t = round(t + 0.01, 2)
        take(sup.measurement('encoder', t, [0.0], now), t)
        now += 0.01
    assert sup.standby.warm and counts['standby_commands'] > 10
    for _ in range(20):                     # a stall: safe commands on the plant's clock
        now += 0.01
        take(sup.safe_tick(now), None)
    assert max(sent) > t + 0.1, (max(sent), t)
    before = len(sent)
    for _ in range(3):                      # the observer restarted: its estimates jump
        t = round(t + 0.01, 2)
        take(sup.measurement('encoder', t, [0.0], now), t)
        take(sup.estimate(t, np.array([0.0, 0.0, 0.0, 0.0]), now), t)
    assert counts['estimate_clock_jumps'] == 1
    for _ in range(30):
        t = round(t + 0.01, 2)
        take(sup.measurement('encoder', t, [0.0], now), t)
        now += 0.01
    assert len(sent) > before + 10
    assert all(b >= a for a, b in zip(sent, sent[1:])), \
        [(i, a, b) for i, (a, b) in enumerate(zip(sent, sent[1:])) if b < a][:5]


def test_an_estimate_taken_before_the_queued_measurements_is_answered_where_the_plant_is():
    """
    After a stall, the newest estimate can come before the measurements that queued.

    Its stamp is where the plant was when its measurement was taken: the command answering
    it is stamped past where the plant is now, not at the estimate's stamp behind it (the
    plant would apply it late, the observers at its stamp).
    """
    sup, _, _ = supervisor('cart_pendulum', 'simulator.mode:=realtime',
                           'controller.reference:=[0.0, 0.0, 0.0, 0.0]')
    x = np.zeros(4)
    for k in range(100):                    # the plant at rest, the loop closed on time
        t = 9.01 + 0.01 * k
        sup.measurement('encoder', t, [0.0], t - 8.0)
        sup.estimate(t, x, t - 8.0)
        sup.watchdog(t - 8.0)
    assert sup.mode == 'closed' and sup.plant_time == pytest.approx(10.0)
    # the compensator's process stalls 0.37 s; the observer's newest estimate (10.34) is
    # taken first, 0.03 s after its measurement, then the 34 measurements that queued
    now = 10.37 - 8.0
    command = sup.estimate(10.34, x, now)
    stamp = 10.34 if command.answers else stamp_sec(command.t)
    assert stamp > 10.37, (stamp, command)
    for k in range(34):
        sup.measurement('encoder', 10.01 + 0.01 * k, [0.0], now)
