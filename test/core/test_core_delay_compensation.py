# test_core_delay_compensation: late estimates predicted to when their command applies.
"""Tests of observer_ros.core.delay_compensation, against python-control and a sampled loop."""

from pathlib import Path

import control
import numpy as np
from numpy.testing import assert_allclose
from observer_ros.core.delay_compensation import DelayCompensation, loop_delay_margin
from observer_ros.core.estimators import History, make_estimator
from observer_ros.core.model import zoh_matrices
from observer_ros.core.vehicle_design import design_vehicle
from observer_ros.core.vehicle_report import format_report
from observer_ros.nodes.compensator import control_law
from observer_ros.vehicle import load_vehicle
import pytest

CART = Path(__file__).resolve().parents[2] / 'config' / 'cart_pendulum.yaml'
MARGIN_POINTS = 20001
DT = 0.01


def cart():
    vehicle = load_vehicle(CART)
    Ad, Bd = zoh_matrices(vehicle.plant.A, vehicle.plant.B, DT)
    return vehicle, Ad, Bd


def test_prediction_is_the_zoh_response_to_the_commands_in_force():
    vehicle, Ad, Bd = cart()
    comp = DelayCompensation(Ad, Bd, DT)
    t0 = 1.0
    # commands sent for t0 + 0, 2, 3 steps (step 1 holds step 0's; a repeat replaces)
    comp.sent(t0, [0.5])
    comp.sent(t0 + 2 * DT, [9.0])
    comp.sent(t0 + 2 * DT, [-1.0])
    comp.sent(t0 + 3 * DT, [2.0])
    x0 = np.array([0.1, 0.2, -0.3, 0.4])
    got = comp.predict(x0, t0, 5)
    sys = control.c2d(control.ss(vehicle.plant.A, vehicle.plant.B, np.eye(4), 0), DT, 'zoh')
    u = np.array([[0.5, 0.5, -1.0, 2.0, 2.0, 0.0]])
    resp = control.forced_response(sys, T=np.arange(6) * DT, U=u, X0=x0)
    assert_allclose(got, resp.states[:, 5], rtol=1e-9, atol=1e-12)
    assert_allclose(comp.predict(x0, t0, 0), x0)
    # before any command: zero
    assert_allclose(DelayCompensation(Ad, Bd, DT).in_force(5.0), [0.0])


def test_a_command_sent_far_ahead_caps_the_horizon_and_the_commands_kept_cover_it():
    vehicle, Ad, Bd = cart()
    comp = DelayCompensation(Ad, Bd, DT, max_delay=0.25, lead=3)
    rng = np.random.default_rng(0)
    stamps = np.round(1.0 + DT * np.arange(111), 2)
    for t in stamps:                        # a command a step, and a second within it
        comp.sent(t, rng.normal(size=1))
        comp.sent(t + 0.5 * DT, rng.normal(size=1))
    newest = float(stamps[-1]) + 0.5 * DT     # 2.105
    # a measurement answered no earlier than the newest command sent: at most max_delay
    # (25 steps) plus the lead (3) and a step; older ones get no answer (None)
    assert comp.steps_late(1.86, 1.82) == 29
    assert comp.steps_late(1.85, 1.81) is None
    # the 29-step prediction uses the commands sent, every one of them (none dropped)
    x0 = np.array([0.01, 0.0, -0.02, 0.0])
    sys = control.c2d(control.ss(vehicle.plant.A, vehicle.plant.B, np.eye(4), 0), DT, 'zoh')
    t0 = 1.82
    u = np.array([[comp.in_force(t0 + k * DT)[0] for k in range(30)]])
    assert np.count_nonzero(u) == 30 and newest > t0 + 28 * DT
    resp = control.forced_response(sys, T=np.arange(30) * DT, U=u, X0=x0)
    assert_allclose(comp.predict(x0, t0, 29), resp.states[:, 29], rtol=1e-9, atol=1e-12)


def test_lateness_is_the_plant_time_past_the_stamp_and_stamps_never_go_back():
    _, Ad, Bd = cart()
    comp = DelayCompensation(Ad, Bd, DT, max_delay=0.25, lead=0)
    assert comp.steps_late(1.0, 1.0) == 0
    assert comp.steps_late(1.04, 1.0) == 4
    assert comp.steps_late(1.044, 1.0) == 4 and comp.steps_late(1.046, 1.0) == 5
    assert comp.steps_late(1.3, 1.0) is None            # past max_delay: not predicted
    # late by max_delay (the plant's time capped there), in floats a few ulps more: 25
    assert (1.78 + 0.25) - 1.78 > 0.25 and comp.steps_late(1.78 + 0.25, 1.78) == 25
    assert comp.steps_late(None, 1.0) == 0              # the plant's time unknown
    assert comp.steps_late(1.7e9, 1.0) == 0             # another time base (wall vs sim)
    # a command was sent for 1.05: the next is stamped no earlier, whatever the lateness
    comp.sent(1.05, [1.0])
    assert comp.steps_late(1.02, 1.02) == 3
    assert comp.steps_late(1.06, 1.02) == 4
    comp.reset()
    assert comp.steps_late(1.02, 1.02) == 0
    # a lead of one step: every command has a whole step to reach the plant
    lead = DelayCompensation(Ad, Bd, DT, lead=1)
    assert lead.steps_late(1.0, 1.0) == 1 and lead.steps_late(1.03, 1.0) == 4
    assert lead.steps_late(1.3, 1.0) is None
    # an estimate predicted ahead of the plant (through a command stamped ahead): to the
    # plant's time plus the lead, not to its own stamp plus the lead
    two = DelayCompensation(Ad, Bd, DT, lead=2)
    assert two.steps_late(1.0, 1.01) == 1 and two.steps_late(1.0, 1.03) == 0
    two.sent(1.05, [0.0])
    assert two.steps_late(1.0, 1.01) == 4


def _loop(compensate, stalls, steps=800):
    """
    Run the cart's sampled loop with the observer stalling; return max |x - x_d| per 100 steps.

    ``stalls`` maps a step k to s: the estimates of steps k .. k+s-1 all reach the
    compensator at step k+s (a busy observer catching up). Without compensation each is
    answered with a command stamped with its own step, which the plant applies only from
    step k+s (the observer takes the stamps at their word, as the node did); with it, each
    is predicted to step k+s and its command stamped there.
    """
    vehicle, Ad, Bd = cart()
    design = design_vehicle(vehicle)
    c = vehicle.controller
    x_d, K = np.asarray(c.reference, float), design.K
    Kd = np.zeros_like(K)
    history = History(make_estimator(vehicle.plant, vehicle.observer), 0.25)
    comp = DelayCompensation(Ad, Bd, DT, lead=0)     # answered within the step
    x, u_plant = np.array(vehicle.simulator.initial_state, float), np.zeros(1)
    waiting, until = [], None           # estimates not yet answered; the stall's end
    worst = []
    for k in range(steps):
        t = 1.0 + k * DT
        history.correct(t, vehicle.plant.C @ x)
        waiting.append((t, history.x_hat.copy()))
        if until is None and k in stalls:
            until = k + stalls[k]
        if until is not None and k < until:
            x = Ad @ x + Bd @ u_plant       # nothing answered yet: the plant holds
            continue
        for t_est, x_hat in waiting:        # answered in order; the newest command wins
            late = comp.steps_late(t, t_est)
            if compensate:
                u = control_law(K, comp.predict(x_hat, t_est, late), x_d, Kd)
                history.set_input(t, u)
                comp.sent(t, u)
            else:
                u = control_law(K, x_hat, x_d, Kd)
                history.set_input(t_est, u)
            u_plant = u
        waiting, until = [], None
        x = Ad @ x + Bd @ u_plant
        worst.append(float(np.max(np.abs(x - x_d))))
    return [max(worst[i:i + 100]) for i in range(0, len(worst), 100)]


def test_the_loop_survives_a_stalling_observer_only_with_compensation():
    # a 30 ms stall every 0.2 s. Without compensation the loop also diverged with 10 ms
    # stalls every 50 ms and 50 ms every 0.5 s; with it, none of these diverged
    stalls = dict.fromkeys(range(40, 800, 20), 3)
    assert max(_loop(True, {})) < 1.5       # the seed's response: 1 m step, settles ~7 s
    with_comp = _loop(True, stalls)
    without = _loop(False, stalls)
    assert with_comp[-1] < 0.05, with_comp          # converged to x_d
    assert max(with_comp) < 1.5, with_comp
    assert without[-1] > 1e3 * with_comp[-1], (without, with_comp)    # diverged


def test_the_carts_delay_margin_is_where_a_pade_delay_destabilises_the_loop():
    vehicle, _, _ = cart()
    design = design_vehicle(vehicle)
    A, B, C = vehicle.plant.A, vehicle.plant.B, vehicle.plant.C
    plant = control.ss(A, B, C, 0)
    # a tenth of the default grid (20001 frequencies, 4000 a decade): the crossover is
    # interpolated between grid points, and the report's figure at the default grid is
    # checked by the next test
    tau, w = loop_delay_margin(plant, design.compensator, points=MARGIN_POINTS)
    assert tau == pytest.approx(0.576e-3, rel=0.01) and w == pytest.approx(19.7, rel=0.01)

    def worst_pole(delay):
        num, den = control.pade(delay, 12)
        loop = control.feedback(plant, design.compensator * control.tf(num, den))
        return np.max(control.poles(loop).real)
    assert worst_pole(0.97 * tau) < 0.0 < worst_pole(1.03 * tau)
    # the stable submarine's loop has far more
    sub = load_vehicle(CART.parent / 'submarine.yaml')
    tau_sub, _ = loop_delay_margin(control.ss(sub.plant.A, sub.plant.B, sub.plant.C, 0),
                                   design_vehicle(sub).compensator, points=MARGIN_POINTS)
    assert tau_sub > 100 * tau


def test_the_design_report_gives_the_delay_margin_and_says_when_it_is_below_a_sample():
    vehicle, _, _ = cart()
    report = format_report(design_vehicle(vehicle), vehicle)
    assert 'Delay margin at the plant input: 0.576 ms (at 19.7 rad/s)' in report, report
    assert 'less than one sample (10 ms)' in report
    assert 'controller.delay_compensation' in report
    sub = load_vehicle(CART.parent / 'submarine.yaml')
    report = format_report(design_vehicle(sub), sub)
    assert 'Delay margin at the plant input: no gain crossover' in report
    assert 'less than one sample' not in report
