# The health checks and the safe-command policy, against scipy and by hand.
"""Divergence envelope, load meter, pole margins, own-parameter ranges, safe command."""

import time
from types import SimpleNamespace

import numpy as np
from observer_ros.core.design import controller_gain
from observer_ros.core.health import (Envelope, HeldOff, LoadMeter, pole_margin_problem,
                                      SettleCheck, WorkBudget)
from observer_ros.core.model import zoh_matrices
from observer_ros.core.safe_command import SafeCommand
from observer_ros.nodes.checks import own_parameter_problem
from observer_ros.vehicle import load_vehicle
import pytest
from ros_helpers import CONFIG
from scipy import signal


def test_envelope_flags_growth_and_names_the_component():
    env = Envelope(['theta', 'x'], [0.0, 1.0], 'x_hat')
    assert env.check(0.0, [0.5, 1.0]) is None
    assert env.check(1.0, [50.0, 20.0]) is None          # within 100 x the scale
    # a divergence that starts at once cannot teach the envelope: x2.6 every 10 ms
    x = np.array([0.1, 1.0])
    reports = []
    for k in range(40):
        x = x * 2.6
        reports.append(env.check(1.0 + 0.01 * k, x))
    first = next(r for r in reports if r is not None)
    assert 'theta' in first or 'x ' in first
    assert 'x_hat' in first and 'plausible' in first
    assert env.check(2.0, [float('nan'), 0.0]) is not None
    env.reset()
    assert env.check(0.0, [0.5, 1.0]) is None


def test_envelope_after_learning_judges_as_during_it():
    # after the learning seconds check() compares plain floats (the per-message fast
    # path): the same verdicts as the numpy path on the same values, NaN and growth included
    rng = np.random.default_rng(4)
    values = list(rng.normal(scale=[1.0, 50.0, 3.0], size=(300, 3)))
    values[120] = np.array([np.nan, 0.0, 0.0])
    values += [np.array([0.0, 1e5 * 1.5 ** k, 0.0]) for k in range(8)]       # diverging
    values += [np.array([0.1, 0.2, 0.3])] * 3 + [np.array([0.0, 0.0, -np.inf])]
    learnt = Envelope(['a', 'b', 'c'], [1.0, 2.0, 3.0], 'x_hat')
    for k in range(100):                                # 4 s: learning over
        assert learnt.check(0.04 * k, np.ones(3)) is None
    assert learnt._fixed_bound is not None
    fast = [learnt.check(10.0 + 0.01 * k, v) for k, v in enumerate(values)]
    slow = []
    reference = Envelope(['a', 'b', 'c'], [1.0, 2.0, 3.0], 'x_hat')
    for k in range(100):
        reference.check(0.04 * k, np.ones(3))
    for k, v in enumerate(values):
        reference._fixed_bound = None                   # never the fast path
        slow.append(reference.check(10.0 + 0.01 * k, v))
    assert fast == slow
    assert fast[120] is not None and 'a = nan' in fast[120]
    assert any(r is not None and 'x_hat b' in r for r in fast[300:308])
    assert fast[-1] is not None and fast[-2] is None
    # a list is judged as an array is
    assert learnt.check(20.0, [0.1, 0.2, 0.3]) is None


def test_envelope_inside_is_strict_where_check_lets_a_shrinking_excursion_pass():
    # what the compensator's recovery after an outage waits for: a value far beyond the
    # bound but shrinking passes check() (not growing), and is still not inside
    env = Envelope(['theta', 'x'], [1.0, 1.0], 'x_hat')
    for k, v in enumerate([1e4, 5e3, 2e3, 1e3, 500.0, 200.0]):
        assert env.check(0.01 * k, [v, 0.0]) is None
        assert not env.inside([v, 0.0])
    assert env.inside([99.0, -100.0])
    assert not env.inside([0.0, float('inf')])
    assert not env.inside([float('nan'), 0.0])


def _meter():
    """Return a load meter on a CPU clock the test advances, and that clock's list."""
    cpu = [0.0]
    return LoadMeter(window=0.5, cpu_clock=lambda: cpu[0]), cpu


def test_load_meter_busy_and_missed():
    meter, cpu = _meter()
    # 100 Hz with 1 ms of work each: idle, not overloaded, 100 answers/s
    t = 0.0
    closed = False
    for _ in range(60):
        cpu[0] += 0.001
        closed = meter.took(t, t + 0.001) or closed
        t += 0.01
    assert closed and not meter.overloaded and meter.rate == pytest.approx(100, rel=0.05)
    assert meter.busy == pytest.approx(0.1, rel=0.05)
    # back to back (a queue that only grows): the thread never waits, busy, overloaded,
    # its rate reported
    meter, cpu = _meter()
    t = 0.0
    for _ in range(600):
        cpu[0] += 0.002 + 1e-5                  # the callback and the executor's overhead
        meter.took(t, t + 0.002)
        t += 0.002 + 1e-5
    assert meter.overloaded and meter.busy > 0.99 and meter.rate == pytest.approx(500, rel=0.05)
    # idle but messages missed (stamp gaps): overloaded too
    meter, cpu = _meter()
    for k in range(60):
        cpu[0] += 0.001
        meter.took(k * 0.01, k * 0.01 + 0.001, missed=1)
    assert meter.overloaded and meter.missed_rate > 50
    meter.idle(100.0)
    assert not meter.overloaded


def test_load_meter_keeps_up_at_1khz_with_short_pauses():
    """
    1 kHz, 0.3 ms of CPU per message (P2's observer): 30 % busy, not overloaded.

    The pauses between messages (0.7 ms) are shorter than the executor's overhead per
    message at lower rates: the meter judged by them read this node 95 % busy (ERROR).
    """
    meter, cpu = _meter()
    t = 0.0
    verdicts = 0
    for _ in range(2000):
        cpu[0] += 0.0003
        verdicts += meter.took(t, t + 0.0001)
        t += 0.001
    assert verdicts >= 3 and not meter.overloaded
    assert meter.busy == pytest.approx(0.3, rel=0.05)


def test_load_meter_reads_the_cpu_time_of_the_calling_thread():
    """The default clock: a thread that spins the whole window is busy, one that sleeps not."""
    meter = LoadMeter(window=0.05)
    cpu_start = time.thread_time()
    start = time.monotonic()
    while not meter.took(start, time.monotonic()):
        pass                                    # a callback that never returns to wait
    # The share of a core this thread got: ~1.0 on an idle host, 1/load on a loaded one.
    share = (time.thread_time() - cpu_start) / (time.monotonic() - start)
    assert meter.busy == pytest.approx(share, abs=0.05 + 0.2 * share)
    meter = LoadMeter(window=0.05)
    start = time.monotonic()
    meter.took(start, start)
    time.sleep(0.06)
    assert meter.took(start, time.monotonic()) and meter.busy < 0.1


def test_pole_margin_on_the_plant_time_scale():
    cart = load_vehicle(CONFIG / 'cart_pendulum.yaml')
    A, dt = cart.plant.A, cart.sample_time
    assert pole_margin_problem(cart.observer.poles, A, dt) is None
    assert pole_margin_problem(cart.controller.poles, A, dt) is None
    slow = pole_margin_problem([-1e-300, -1.0, -2.0, -3.0], A, dt, name='observer.poles')
    assert 'observer.poles' in slow and '-1e-300' in slow and 'margin' in slow
    fast = pole_margin_problem([-1e6, -1.0, -2.0, -3.0], A, dt)
    assert '-1e+06' in fast and 'realis' in fast
    sub = load_vehicle(CONFIG / 'submarine_discrete.yaml')
    assert pole_margin_problem(sub.observer.poles, sub.plant.A, sub.sample_time, True) is None
    assert pole_margin_problem([1.0 - 1e-12, 0.9, 0.9], sub.plant.A, sub.sample_time,
                               True) is not None


@pytest.mark.parametrize('name, value, ok', [
    ('future_tolerance', -1.0, False), ('future_tolerance', 0.0, False),
    ('future_tolerance', 10.0, True), ('clock_jump_tolerance', float('nan'), False),
    ('clock_jump_tolerance', float('inf'), False), ('diagnostics_period', 0.0, False),
    ('diagnostics_period', 0.2, True), ('publish_array', 1.0, False),
    ('clock_jump_tolerance', 'a', False), ('unrelated', -1.0, True)])
def test_own_parameter_ranges(name, value, ok):
    problem = own_parameter_problem([SimpleNamespace(name=name, value=value)])
    assert (problem is None) == ok, problem
    if not ok:
        assert name in problem


def test_safe_command_predicts_the_closed_loop_like_scipy():
    """Predict-and-hold is the discrete closed loop x+ = (Ad - Bd K) x: scipy's dlsim."""
    v = load_vehicle(CONFIG / 'cart_pendulum.yaml')
    plant, dt = v.plant, v.sample_time
    K = controller_gain(plant.A, plant.B, v.controller.poles).reshape(1, -1)
    x_d = np.asarray(v.controller.reference)

    def law(x):
        return K @ (x_d - x)
    safe = SafeCommand(plant, law, dt, 'zero', predict_timeout=1.0)
    x0 = np.array([0.05, 0.2, 0.0, 0.1])
    u0 = law(x0)
    safe.trusted(10.0, x0, u0)
    got = [safe.command(10.0 + k * dt)[0] for k in range(1, 51)]
    Ad, Bd = zoh_matrices(plant.A, plant.B, dt)
    # x_{k+1} = Ad x_k + Bd K (x_d - x_k): input x_d, output u = K (x_d - x)
    sys = signal.dlti(Ad - Bd @ K, Bd @ K, -K, K, dt=dt)
    _, u_ref, _ = signal.dlsim(sys, np.tile(x_d, (52, 1)), x0=Ad @ x0 + Bd @ u0)
    np.testing.assert_allclose(np.ravel(got), u_ref[:50, 0], rtol=1e-9, atol=1e-12)
    # past predict_timeout: the fallback
    u, mode = safe.command(11.5)
    assert mode == 'zero' and np.all(u == 0.0)
    hold = SafeCommand(plant, law, dt, 'hold', predict_timeout=0.0)
    hold.trusted(0.0, x0, u0)
    u, mode = hold.command(1.0)
    assert mode == 'hold' and np.allclose(u, u0)
    hold.reset()
    assert np.all(hold.command(2.0)[0] == 0.0)


def test_settle_check_waits_for_estimates_that_follow_the_model():
    v = load_vehicle(CONFIG / 'cart_pendulum.yaml')
    dt = v.sample_time
    Ad, Bd = zoh_matrices(v.plant.A, v.plant.B, dt)
    check = SettleCheck(Ad, Bd, dt, np.ones(4), tol=0.1, count=10)
    check.start(deadline=100.0)
    rng = np.random.default_rng(0)
    x, u = np.array([0.01, 1.0, 0.0, 0.0]), np.array([0.1])
    # a converging observer's estimates jump by far more than the scale: never settled
    for k in range(30):
        assert not check.settled(k * dt, x + rng.normal(0, 5.0, 4), u)
    # estimates that follow the model step by step: settled after 10 in a row
    results = []
    for k in range(30, 45):
        x = Ad @ x + Bd @ u
        results.append(check.settled(k * dt, x, u))
    assert results.index(True) == 10
    # a gap in the stamps is not compared; the deadline ends the wait anyway
    check.start(deadline=1.0)
    assert not check.settled(0.5, x, u)
    assert check.settled(1.0, x + 100.0, u)


def test_the_work_budget_admits_work_while_it_takes_less_than_its_share():
    budget = WorkBudget(share=0.03, window=10.0)      # 0.3 s of work per 10 s
    assert budget.refuse(100.0) is None                # nothing done yet
    budget.spent(0.5, 100.5)                           # one long redesign: admitted
    reason = budget.refuse(101.0)
    assert reason.startswith('busy: parameter changes took 500 ms of the last 10 s')
    assert 'at most 3 %' in reason and 'try again in 9.5 s' in reason
    assert budget.refuse(110.6) is None                # it has left the window
    for end in (111.0, 112.0, 113.0):                  # 0.1 s each: the third reaches 0.3 s
        assert budget.refuse(end) is None
        budget.spent(0.1, end)
    assert budget.refuse(113.5) is not None
    assert budget.used(113.5) == pytest.approx(0.3)
    assert budget.refuse(121.1) is None                # the first has left: 0.2 s used


def test_a_check_after_the_process_was_held_off_judges_nothing():
    held = HeldOff()
    assert held.check(10.0, 0.5) is False              # the first check judges
    assert held.check(10.1, 0.5) is False
    assert held.check(12.1, 0.5) is True               # 2 s without a check: held off
    assert held.check(12.2, 0.5) is False              # the next one judges again
    assert held.check(12.9, 1.0) is False              # the gap is the caller's, per check
    assert held.check(13.5, 0.5) is True
