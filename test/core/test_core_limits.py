"""Tests of core.limits: RHP poles and zeros, the bounds they put on every controller."""

import math

import control
import numpy as np
from numpy.testing import assert_allclose
from observer_ros.core.limits import best_disk_margin, fundamental_limit, transmission_zeros
from observer_ros.core.margins import loop_margins
from observer_ros.core.vehicle_design import design_vehicle
import pytest

CART_A = np.array([[0, 0, 1, 0], [0, 0, 0, 1], [10.78, 0, 0, 0], [-0.98, 0, 0, 0]], float)
CART_B = np.array([[0.0], [0.0], [-1.0], [1.0]])
NAMES = ('theta', 'x', 'theta_dot', 'x_dot')


def test_cart_with_the_encoder_alone_every_controller_has_ms_42():
    lim = fundamental_limit(CART_A, CART_B, [[0, 1.0, 0, 0]], output_names=('x',),
                            state_names=NAMES)
    p, z = math.sqrt(10.78), math.sqrt(9.8)           # x/u = (s^2 - 9.8) / (s^2 (s^2 - 10.78))
    assert_allclose(lim.rhp_poles.real, [p], rtol=1e-9)
    assert_allclose(lim.rhp_zeros.real, [z], rtol=1e-9)
    assert_allclose(lim.ms_bound, (z + p) / (p - z), rtol=1e-9)
    assert 41.9 < lim.ms_bound < 42.0
    alpha, gain, phase = lim.best_disk
    assert_allclose(alpha, 1.0 / (lim.ms_bound - 0.5))
    assert 1.02 < gain < 1.03 and phase < 1.5
    assert_allclose([lim.delay_max, lim.crossover_min, lim.crossover_max], [2 / p, 2 * p, z / 2])
    assert lim.sensor_obstacle and lim.better_with == 'theta' and lim.better_bound == 1.0
    text = '\n'.join(lim.lines())
    assert 'every stabilising controller has Ms >= 42' in text
    assert 'the sensor set is the obstacle' in text and 'measuring theta' in text
    assert 'the two cannot both hold' in text


def test_the_seed_design_and_any_other_respect_the_bound(tmp_path):
    from observer_ros.vehicle import load_vehicle
    from pathlib import Path
    v = load_vehicle(Path(__file__).resolve().parents[2] / 'config' / 'cart_pendulum.yaml')
    P = control.ss(v.plant.A, v.plant.B, v.plant.C, v.plant.D)
    lim = fundamental_limit(v.plant.A, v.plant.B, v.plant.C)
    rng = np.random.default_rng(0)
    for trial in range(6):
        d = design_vehicle(v) if trial == 0 else design_vehicle(_with_poles(v, rng))
        ms = loop_margins(P, d.compensator, 'input')[0].peak_sensitivity
        assert ms >= lim.ms_bound * (1 - 1e-3)


def _with_poles(v, rng):
    from dataclasses import replace
    ctrl = -rng.uniform(0.5, 3.0, 2)
    obs = -rng.uniform(3.0, 30.0, 2)
    cpoles = np.array([complex(ctrl[0], 1.0), complex(ctrl[0], -1.0), ctrl[1], ctrl[1] * 1.3])
    opoles = np.array([complex(obs[0], 2.0), complex(obs[0], -2.0), obs[1], obs[1] * 1.2])
    return replace(v, controller=replace(v.controller, poles=cpoles),
                   observer=replace(v.observer, poles=opoles))


def test_cart_with_both_encoders_has_no_zero_and_no_bound():
    lim = fundamental_limit(CART_A, CART_B, np.eye(4)[:2], output_names=('theta', 'x'))
    assert lim.rhp_zeros.size == 0 and lim.ms_bound == 1.0 and not lim.sensor_obstacle
    assert_allclose(lim.delay_max, 2 / math.sqrt(10.78))
    # theta alone does not see x: no controller stabilises the cart
    lim = fundamental_limit(CART_A, CART_B, [[1.0, 0, 0, 0]], state_names=NAMES)
    assert math.isinf(lim.ms_bound) and lim.better_with == 'x'
    assert 'no controller stabilises' in '\n'.join(lim.lines())
    assert lim.to_json()['ms_bound'] is None


def test_transmission_zeros_match_python_control_siso():
    rng = np.random.default_rng(5)
    for _ in range(5):
        A = rng.normal(size=(4, 4))
        B = rng.normal(size=(4, 1))
        C = rng.normal(size=(1, 4))
        want = np.sort_complex(control.zeros(control.ss2tf(control.ss(A, B, C, 0))))
        assert_allclose(np.sort_complex(transmission_zeros(A, B, C)), want, rtol=1e-6,
                        atol=1e-8)


def test_mimo_bound_uses_the_directions():
    # two decoupled channels, the second with an RHP pole and zero: the pair is in the same
    # output direction, the bound is that channel's SISO bound
    p, z = 2.0, 5.0
    A = np.diag([-1.0, p, -3.0])
    B = np.array([[1.0, 0.0], [0.0, 1.0], [0.0, 1.0]])
    # channel 2: (s - z) / ((s - p)(s + 3)) = C (sI - A)^-1 B with residues at p and -3
    r1, r2 = (p - z) / (p + 3), (-3 - z) / (-3 - p)
    C = np.array([[1.0, 0.0, 0.0], [0.0, r1, r2]])
    lim = fundamental_limit(A, B, C)
    assert_allclose(lim.rhp_zeros.real, [z], rtol=1e-8)
    assert_allclose(lim.ms_bound, (z + p) / (z - p), rtol=1e-8)
    # a discrete plant: Blaschke factor |1 - p z| / |z - p|
    Ad, Bd, Cd = np.diag([0.5, 2.0]), np.array([[1.0], [1.0]]), np.array([[1.0, -1.5]])
    lim = fundamental_limit(Ad, Bd, Cd, discrete=True, dt=0.1)
    zero = transmission_zeros(Ad, Bd, Cd)
    outside = [zz for zz in zero if abs(zz) > 1]
    if outside:
        zz = outside[0]
        assert_allclose(lim.ms_bound, abs(1 - 2.0 * zz) / abs(zz - 2.0), rtol=1e-8)


@pytest.mark.parametrize('bound', [1.0, 2.0, 42.0])
def test_best_disk_margin(bound):
    alpha, gain, phase = best_disk_margin(bound)
    assert alpha == pytest.approx(min(2.0, 1.0 / (bound - 0.5)) if bound > 1 else 2.0)
    if math.isfinite(gain):
        assert gain == pytest.approx((1 + alpha / 2) / (1 - alpha / 2))
    assert phase == pytest.approx(math.degrees(2 * math.atan(alpha / 2)))
