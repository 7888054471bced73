"""Tests of core.margins and core.conditioning: margins, disk margin, Ms, growth, sensitivity."""

import math
from pathlib import Path

import control
import numpy as np
from numpy.testing import assert_allclose
from observer_ros.core.conditioning import pole_sensitivity, transient_growth
from observer_ros.core.delay_compensation import loop_delay_margin
from observer_ros.core.margins import frequency_grid, loop_margins, margin_warnings
from observer_ros.core.pole_placement import eigenvector_condition
from observer_ros.core.vehicle_design import design_vehicle
from observer_ros.vehicle import load_vehicle
import pytest
import scipy.linalg

CONFIG = Path(__file__).resolve().parents[2] / 'config'


def cart():
    v = load_vehicle(CONFIG / 'cart_pendulum.yaml')
    d = design_vehicle(v)
    return v, d, control.ss(v.plant.A, v.plant.B, v.plant.C, v.plant.D)


def test_seed_cart_margins_at_the_plant_input():
    # docs/reliability.md: crossings at 1.08, 3.94 and 19.7 rad/s, gain margins 1.007 /
    # 0.991, 0.576 ms of delay at 19.7 rad/s
    v, d, P = cart()
    (m,) = loop_margins(P, d.compensator, 'input')
    assert m.channel is None
    assert_allclose([m.gain_low, m.gain_high], [0.99147, 1.00709], rtol=2e-4)
    assert_allclose(m.phase, 0.304, atol=2e-3)
    assert_allclose(m.phase_frequency, 3.94, rtol=2e-3)
    tau, wc = loop_delay_margin(P, d.compensator)
    assert_allclose([m.delay, m.delay_frequency], [tau, wc], rtol=1e-3)
    assert_allclose(m.delay * 1e3, 0.576, atol=1e-3)
    # Ms is the inverse distance of the Nyquist plot from -1, the disk margin python-control's
    w = frequency_grid([P, d.compensator])
    L = d.compensator * P
    dist = np.min(np.abs(1.0 + np.asarray(L(1j * w)).reshape(-1)))
    assert_allclose(m.peak_sensitivity, 1.0 / dist, rtol=1e-6)
    assert m.peak_sensitivity > 200
    assert_allclose(m.disk, control.disk_margins(L, w)[0], rtol=1e-9)
    assert m.disk <= 2.0 / (2.0 * m.peak_sensitivity - 1.0) + 1e-12     # |S - 1/2| >= Ms - 1/2
    warnings = margin_warnings([m], v.sample_time)
    assert any('gain margin at the plant input' in w for w in warnings)
    assert any('delay margin at the plant input: 0.576 ms' in w for w in warnings)
    assert any('Ms = 210' in w for w in warnings)


def test_numeric_margins_agree_with_python_control():
    # the submarine, continuous and discrete: python-control's stability_margins and the
    # frequency-response crossing search give the same figures
    for name in ('submarine.yaml', 'submarine_discrete.yaml'):
        v = load_vehicle(CONFIG / name)
        d = design_vehicle(v)
        dt = v.plant.dt
        P = control.ss(v.plant.A, v.plant.B, v.plant.C, v.plant.D, dt or 0)
        (m,) = loop_margins(P, d.compensator, 'input', dt=dt)
        gm, pm, _, _, wgc, _ = control.stability_margins(d.compensator * P, returnall=True)
        gm = [g for g in np.atleast_1d(gm) if np.isfinite(g) and g < 1e12]
        assert_allclose(m.gain_high, min(g for g in gm if g > 1), rtol=1e-4)
        if np.size(wgc):
            assert_allclose(m.phase, min(abs(p) for p in np.atleast_1d(pm)), rtol=1e-3)
        else:
            assert math.isinf(m.phase) and math.isinf(m.delay)
    # the library's warnings (discrete: its polynomial method judged inaccurate) are said
    # in words, not passed through
    assert all('python-control' in n for n in m.notes)


def test_loop_at_a_time_of_decoupled_loops_is_each_loop():
    # two decoupled SISO loops: each channel's margins are those of its own loop
    P1 = control.ss([[0.0, 1.0], [0.0, 0.0]], [[0.0], [1.0]], [[1.0, 0.0]], 0)
    P2 = control.ss([[-1.0]], [[1.0]], [[1.0]], 0)
    D1 = control.ss([[-5.0]], [[-12.0]], [[1.0]], [[4.0]])        # lead on the integrators
    D2 = control.ss([], [], [], [[3.0]])
    P = control.append(P1, P2)
    D = control.append(D1, D2)
    both = loop_margins(P, D, 'input', names=('a', 'b'))
    assert [m.channel for m in both] == ['a', 'b']
    for m, (p, c) in zip(both, ((P1, D1), (P2, D2))):
        (single,) = loop_margins(p, c, 'input', w=frequency_grid([P, D]))
        assert_allclose([m.gain_low, m.phase, m.delay], [single.gain_low, single.phase,
                                                         single.delay], rtol=1e-3)
        assert m.gain_high == single.gain_high or \
            abs(m.gain_high - single.gain_high) < 1e-3 * single.gain_high
    # a square loop: the whole loop's Ms is the larger of the two
    assert_allclose(both[0].peak_sensitivity, max(
        loop_margins(P1, D1, 'input', w=frequency_grid([P, D]))[0].peak_sensitivity,
        loop_margins(P2, D2, 'input', w=frequency_grid([P, D]))[0].peak_sensitivity),
        rtol=1e-6)


def test_the_wider_side_of_a_non_square_loop_states_no_whole_loop_figure():
    v = load_vehicle(CONFIG / 'cart_pendulum_two_encoders.yaml')
    d = design_vehicle(v)
    P = control.ss(v.plant.A, v.plant.B, v.plant.C, v.plant.D)
    out = loop_margins(P, d.compensator, 'output', v.plant.output_names)
    assert [m.channel for m in out] == ['theta', 'x']
    assert all(math.isnan(m.peak_sensitivity) and math.isnan(m.disk) for m in out)
    assert all(np.isfinite(m.delay) for m in out)
    assert not any('peak sensitivity' in w for w in margin_warnings(out, 0.01))


# ---------------------------------------------------------------- conditioning


def test_transient_growth_of_a_non_normal_matrix():
    a = 50.0
    M = np.array([[-1.0, a], [0.0, -2.0]])
    t = np.linspace(0.0, 5.0, 20001)
    dense = max(np.linalg.norm(scipy.linalg.expm(M * tt), 2) for tt in t[::20])
    g, at = transient_growth(M)
    assert g >= dense * (1 - 1e-6) and g < dense * 1.01
    assert 0.3 < at < 1.2                     # e^-t - e^-2t peaks at ln 2
    assert g <= eigenvector_condition(M) * (1 + 1e-9)
    # discrete: powers
    Md = scipy.linalg.expm(M * 0.1)
    gd, k = transient_growth(Md, discrete=True)
    powers = [np.linalg.norm(np.linalg.matrix_power(Md, j), 2) for j in range(200)]
    assert_allclose(gd, max(powers), rtol=1e-12)
    assert k == int(np.argmax(powers))
    assert transient_growth(np.diag([-1.0, -3.0]))[0] == 1.0
    assert math.isinf(transient_growth(np.diag([1.0, -3.0]))[0])


def test_pole_sensitivity_predicts_what_one_rounding_does():
    rng = np.random.default_rng(2)
    Q = np.linalg.qr(rng.normal(size=(6, 6)))[0]
    R = np.diag(-np.arange(1.0, 7.0)) + np.triu(rng.normal(size=(6, 6)) * 30.0, 1)
    M = Q @ R @ Q.T                 # far from normal, and balancing cannot undo it
    s = pole_sensitivity(M)
    eps = np.finfo(float).eps
    lam = np.linalg.eigvals(M)
    moved = []
    for _ in range(20):      # perturb every entry by a relative eps, as forming M does
        E = M * eps * rng.choice([-1.0, 1.0], size=M.shape)
        got = np.linalg.eigvals(M + E)
        moved.append(max(np.min(np.abs(got - z)) for z in lam))
    assert max(moved) < 50 * float(np.max(s.rounding_move))
    assert s.max_condition > 10.0 and s.worst in range(6)
    assert pole_sensitivity(np.diag([-1.0, -2.0])).max_condition == pytest.approx(1.0)
