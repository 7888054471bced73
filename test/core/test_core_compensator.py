"""Tests of core.closed_loop, core.vehicle_design and core.vehicle_report: loop, D(s), design."""

import json
import warnings

import control
import numpy as np
from numpy.testing import assert_allclose
from observer_ros.core.closed_loop import (
    closed_loop_matrices, closed_loop_matrix, compensator_matrices, compensator_poles,
    compensator_ss, compensator_tf, error_dynamics_matrix, reduced_closed_loop_matrices,
    reduced_closed_loop_matrix, separation_check, spectrum_match, tracking_ok,
    tracking_residual)
from observer_ros.core.design import controller_gain, observer_gain, reduced_order_observer
from observer_ros.core.errors import (DesignError, DimensionError, NotDetectableError,
                                      ObserverDesignWarning)
from observer_ros.core.model import Plant, zoh_matrices
from observer_ros.core.spec import (ControllerSpec, ObserverSpec, SensorSpec, SimulatorSpec,
                                    Vehicle)
from observer_ros.core.vehicle_design import (design_vehicle, design_warnings,
                                              measurement_intensity, observer_noise_gain)
from observer_ros.core.vehicle_report import format_report, to_json_dict
import plants
import pytest
import scipy.linalg
import scipy.optimize

SUB_A, SUB_B = np.array(plants.SUBMARINE_A), np.array(plants.SUBMARINE_B)
SUB_C = np.array(plants.GYRO_C)
CART_A, CART_B = np.array(plants.CART_A), np.array(plants.CART_B)
CART_C = np.array([[0.0, 1.0, 0.0, 0.0]])


def random_design(seed, with_D=True):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(2, 5))
    m = int(rng.integers(1, 3))
    p = int(rng.integers(1, n))
    A = rng.normal(size=(n, n))
    B = rng.normal(size=(n, m))
    C = rng.normal(size=(p, n))
    D = rng.normal(size=(p, m)) if with_D else np.zeros((p, m))
    # well separated poles: clustered ones make a random SISO design ill-conditioned
    ctrl = -(0.5 + 0.7 * np.arange(n) + rng.uniform(0.0, 0.3, n))
    obs = -(3.0 + 0.9 * np.arange(n) + rng.uniform(0.0, 0.3, n))
    with warnings.catch_warnings():
        warnings.simplefilter('ignore')
        K = controller_gain(A, B, ctrl)
        L = observer_gain(A, C, obs)
        red = reduced_order_observer(A, B, C, D, poles=obs[:n - p])
    return rng, A, B, C, D, K, L, red, ctrl, obs


def match_error(a, b):
    """Largest relative distance between two sets of poles, optimally matched."""
    a = np.asarray(a, dtype=complex)
    b = np.asarray(b, dtype=complex)
    cost = np.abs(a[:, None] - b[None, :]) / np.maximum(1.0, np.abs(b))[None, :]
    rows, cols = scipy.optimize.linear_sum_assignment(cost)
    return float(cost[rows, cols].max())


def interconnect(A, B, C, D, Ac, Bc, Cc, Dc):
    """Close the loop of plant (A, B, C, D) and u = -(Cc xc + Dc y), solved by hand."""
    m = B.shape[1]
    X = np.linalg.inv(np.eye(m) + Dc @ D)       # u = -X (Cc xc + Dc C x)
    Ux, Uc = -X @ Dc @ C, -X @ Cc
    Y_x, Y_c = C + D @ Ux, D @ Uc
    return np.block([[A + B @ Ux, B @ Uc], [Bc @ Y_x, Ac + Bc @ Y_c]])


# ---------------------------------------------------------------- closed loop


def test_closed_loop_matrix_structure_and_D_cancels():
    _, A, B, C, D, K, L, _, _, _ = random_design(0)
    n = A.shape[0]
    Acl = closed_loop_matrix(A, B, C, K, L)
    assert_allclose(Acl[:n, :n], A)
    assert_allclose(Acl[:n, n:], -B @ K)
    assert_allclose(Acl[n:, :n], L @ C)
    assert_allclose(Acl[n:, n:], A - L @ C - B @ K)
    assert_allclose(closed_loop_matrix(A, B, C, K, L, D), Acl)
    Acl2, Bcl = closed_loop_matrices(A, B, C, K, L, D, Kd=0.5 * K)
    assert_allclose(Acl2, Acl)
    assert_allclose(Bcl, np.vstack([B @ (0.5 * K), B @ (0.5 * K)]))


def test_closed_loop_shape_errors_name_the_gain():
    _, A, B, C, _, K, L, _, _, _ = random_design(1)
    with pytest.raises(DimensionError, match='K has'):
        closed_loop_matrix(A, B, C, K.T, L)
    with pytest.raises(DimensionError, match='L has'):
        closed_loop_matrix(A, B, C, K, L.T if L.shape[1] > 1 else np.ones((1, 9)))
    with pytest.raises(DimensionError, match='D has'):
        closed_loop_matrix(A, B, C, K, L, D=np.ones((9, 9)))


@pytest.mark.parametrize('seed', range(8))
def test_separation_full_and_reduced(seed):
    _, A, B, C, D, K, L, red, ctrl, obs = random_design(seed)
    ok, cl, expected = separation_check(A, B, C, K, L, D=D)
    assert ok
    assert_allclose(cl, expected, rtol=1e-2)       # matched element by element
    assert match_error(expected, np.concatenate([ctrl, obs])) < 1e-4
    ok, cl, expected = separation_check(A, B, C, K, red, D=D)
    assert ok and cl.size == 2 * A.shape[0] - C.shape[0]
    assert match_error(expected, np.concatenate([ctrl, obs[:red.order]])) < 1e-4


def test_separation_check_detects_a_mismatch():
    _, A, B, C, _, K, L, _, _, _ = random_design(3)
    Acl = closed_loop_matrix(A, B, C, K, L)
    ok, _, expected = separation_check(A, B, C, K, L)
    assert ok
    assert not spectrum_match(Acl + 1e-4 * np.eye(len(Acl)), expected)[0]
    # and the observer of a slightly different plant moves the closed-loop poles
    L_wrong = observer_gain(A + 0.05, C, np.linalg.eigvals(A - L @ C))
    assert not spectrum_match(closed_loop_matrix(A, B, C, K, L_wrong), expected)[0]
    # spectrum_match itself: exact, shifted, repeated (defective) eigenvalues
    assert spectrum_match(np.diag([-1.0, -2.0]), [-2.0, -1.0])[0]
    assert not spectrum_match(np.diag([-1.0, -2.0]), [-2.0, -1.001])[0]
    assert spectrum_match([[-1.0, 1.0], [0.0, -1.0]], [-1.0, -1.0])[0]
    with pytest.raises(DimensionError, match='expected has 1 eigenvalues; expected 2'):
        spectrum_match(np.eye(2), [1.0])


def test_error_dynamics_matrix_eq_5_117():
    _, A, B, C, _, K, L, _, _, _ = random_design(4)
    n = A.shape[0]
    E = error_dynamics_matrix(A, B, C, K, L)
    assert_allclose(E[n:, :n], 0.0)
    # similar to the [x; x_hat] closed loop through e = -x (x_d = 0), e_o = x - x_hat
    S = np.block([[-np.eye(n), np.zeros((n, n))], [np.eye(n), -np.eye(n)]])
    assert_allclose(S @ closed_loop_matrix(A, B, C, K, L) @ np.linalg.inv(S), E, atol=1e-10)


@pytest.mark.parametrize('seed', range(5))
def test_reduced_closed_loop_coordinates_agree(seed):
    _, A, B, C, D, K, _, red, _, _ = random_design(seed)
    err = reduced_closed_loop_matrix(A, B, K, red, 'error')
    state = reduced_closed_loop_matrix(A, B, K, red, 'state')
    assert spectrum_match(state, np.linalg.eigvals(err))[0]
    Acl, Bcl = reduced_closed_loop_matrices(A, B, K, red, Kd=0.2 * K)
    assert_allclose(Acl, state)
    assert_allclose(Bcl[:A.shape[0]], B @ (0.8 * K))
    assert_allclose(Bcl[A.shape[0]:], red.H @ (0.8 * K))
    with pytest.raises(DesignError, match="coordinates is 'x'"):
        reduced_closed_loop_matrix(A, B, K, red, 'x')


def test_reduced_state_closed_loop_matches_a_simulation_step():
    # x' and z' from the plant and observer equations equal Acl [x; z]
    rng, A, B, C, D, K, _, red, _, _ = random_design(6)
    x, z = rng.normal(size=A.shape[0]), rng.normal(size=red.order)
    # u = -K x_hat with x_hat depending on y - D u = C x
    x_hat = red.state_estimate(C @ x, z)
    u = -K @ x_hat
    y = C @ x + D @ u
    assert_allclose(red.state_estimate(y, z, u), x_hat)
    xdot = A @ x + B @ u
    zdot = red.z_rate(z, y, u)
    Acl = reduced_closed_loop_matrix(A, B, K, red, 'state')
    assert_allclose(Acl @ np.concatenate([x, z]), np.concatenate([xdot, zdot]), atol=1e-9)


# ---------------------------------------------------------------- compensator


def test_compensator_transfer_function_is_seed_000_formula():
    K = controller_gain(SUB_A, SUB_B, [-0.3, -0.31, -0.32])
    L = observer_gain(SUB_A, SUB_C, [-0.6, -0.61, -0.62])
    tf = compensator_tf(SUB_A, SUB_B, SUB_C, K, L)
    for s in (0.1j, 1.0 + 0.5j, 3.0):
        expected = K @ np.linalg.solve(s * np.eye(3) - SUB_A + SUB_B @ K + L @ SUB_C, L)
        assert_allclose(np.squeeze(tf(s)), expected[0, 0], rtol=1e-9)
    assert_allclose(np.sort_complex(compensator_poles(SUB_A, SUB_B, SUB_C, K, L)),
                    np.sort_complex(np.linalg.eigvals(SUB_A - SUB_B @ K - L @ SUB_C)))


def test_compensator_with_feedthrough_uses_LDK():
    _, A, B, C, D, K, L, _, _, _ = random_design(2)
    Ac, Bc, Cc, Dc = compensator_matrices(A, B, C, K, L, D)
    assert_allclose(Ac, A - B @ K - L @ C + L @ D @ K)
    assert_allclose(Bc, L)
    assert_allclose(Cc, K)
    assert_allclose(Dc, 0.0)


@pytest.mark.parametrize('seed', range(6))
def test_plant_with_compensator_has_the_separated_poles(seed):
    _, A, B, C, D, K, L, red, ctrl, obs = random_design(seed)
    for observer, expected in ((L, np.concatenate([ctrl, obs])),
                               (red, np.concatenate([ctrl, red.poles]))):
        sys = compensator_ss(A, B, C, K, observer, D)
        assert isinstance(sys, control.StateSpace)
        M = interconnect(A, B, C, D, sys.A, sys.B, sys.C, sys.D)
        assert spectrum_match(M, expected)[0]


def test_discrete_compensator_has_the_sample_time():
    Ad, Bd = zoh_matrices(SUB_A, SUB_B, 0.1)
    K = controller_gain(Ad, Bd, np.exp(0.1 * np.array([-0.3, -0.31, -0.32])))
    L = observer_gain(Ad, SUB_C, np.exp(0.1 * np.array([-0.6, -0.61, -0.62])))
    sys = compensator_ss(Ad, Bd, SUB_C, K, L, dt=0.1)
    assert sys.dt == 0.1
    ok, _, _ = separation_check(Ad, Bd, SUB_C, K, L)
    assert ok


# ---------------------------------------------------------------- tracking


def test_tracking_residual_and_ok():
    x_d = np.array([0.0, 1.0, 0.0, 0.0])
    assert tracking_ok(CART_A, CART_B, x_d)
    assert not tracking_ok(CART_A, CART_B, [1.0, 0.0, 0.0, 0.0])    # theta_d = 1 rad
    assert_allclose(tracking_residual(CART_A, CART_B, [1.0, 0, 0, 0]), [0, 0, -10.78, 0.98])
    # discrete: a constant reference has A_d = I
    Ad, Bd = zoh_matrices(CART_A, CART_B, 0.01)
    assert tracking_ok(Ad, Bd, x_d, discrete=True)
    assert not tracking_ok(Ad, Bd, x_d, discrete=False)
    with pytest.raises(DimensionError, match='x_d has 3 elements; expected 4'):
        tracking_residual(CART_A, CART_B, [0, 1, 0])


# ---------------------------------------------------------------- warnings


def test_unstable_compensator_warning_example_518():
    K = controller_gain(CART_A, CART_B, [-7.853 + 3.2528j, -7.853 - 3.2528j,
                                         -7.853 + 7.853j, -7.853 - 7.853j])
    L = observer_gain(CART_A, CART_C, [-10 + 10j, -10 - 10j, -20 + 20j, -20 - 20j])
    msgs = design_warnings(CART_A, CART_B, CART_C, K, L)
    assert any('unstable compensator' in w and '428.9' in w for w in msgs)
    stable = observer_gain(CART_A, CART_C, [-1, -2, -3, -4])
    K_slow = controller_gain(CART_A, CART_B, [-0.1, -0.2, -0.3, -0.4])
    assert not any('unstable compensator' in w
                   for w in design_warnings(CART_A, CART_B, CART_C, K_slow, stable)) or \
        np.any(compensator_poles(CART_A, CART_B, CART_C, K_slow, stable).real > 0)


def test_open_loop_observer_of_unstable_plant_drifts():
    msgs = design_warnings(CART_A, CART_B, CART_C, None, np.zeros((4, 1)))
    assert any('open-loop observer drifts' in w for w in msgs)
    assert not design_warnings(-np.eye(2), np.ones((2, 1)), [[1.0, 0.0]], None,
                               np.zeros((2, 1)))


def test_noise_gain_warning_for_too_fast_poles():
    K = controller_gain(SUB_A, SUB_B, [-0.3, -0.31, -0.32])
    slowish = observer_gain(SUB_A, SUB_C, [-0.6, -0.61, -0.62])
    fast = observer_gain(SUB_A, SUB_C, [-300, -310, -320])
    kwargs = {'noise_std': [0.01], 'sample_time': 0.01, 'output_names': ['q']}
    assert not [w for w in design_warnings(SUB_A, SUB_B, SUB_C, K, slowish, **kwargs)
                if 'noise' in w]
    msgs = design_warnings(SUB_A, SUB_B, SUB_C, K, fast, **kwargs)
    assert any('amplifies the noise of q' in w for w in msgs)


def test_noise_gain_continuous_matches_the_sampled_observer():
    # sampled noise of variance s^2 every dt = white noise of intensity s^2 dt:
    # for dt small compared with the observer, both give the same output noise std
    L = observer_gain(SUB_A, SUB_C, [-2.0, -2.1, -2.2])
    dt, sigma = 0.001, 0.05
    ratio_c, P_c = observer_noise_gain(SUB_A, SUB_C, L, [sigma], dt)
    Ad, _ = zoh_matrices(SUB_A, SUB_B, dt)
    Ld = observer_gain(Ad, SUB_C, np.exp(dt * np.array([-2.0, -2.1, -2.2])))
    ratio_d, P_d = observer_noise_gain(Ad, SUB_C, Ld, [sigma], discrete=True)
    assert 0.0 < ratio_c[0] < 1.0
    assert_allclose(ratio_c, ratio_d, rtol=0.05)
    Phi = SUB_A - L @ SUB_C
    assert_allclose(Phi @ P_c + P_c @ Phi.T, -L @ L.T * sigma ** 2 * dt, atol=1e-14)
    assert_allclose(P_d, scipy.linalg.solve_discrete_lyapunov(Ad - Ld @ SUB_C,
                                                              Ld @ Ld.T * sigma ** 2))


# ---------------------------------------------------------------- vehicle design


def make_vehicle(A=SUB_A, B=SUB_B, C=SUB_C, D=None, observer=None, controller=None,
                 dt=None, states=('theta', 'w', 'q'), outputs=('q',), noise=(0.01,)):
    plant = Plant(A, B, C, D, dt, states, ('delta',), outputs)
    sensor = SensorSpec('imu', 'imu/data', 'sensor_msgs/msg/Imu',
                        tuple(f'f{i}' for i in range(len(outputs))), tuple(outputs),
                        np.array(noise, dtype=float))
    observer = observer or ObserverSpec('full', poles=np.array([-0.6, -0.61, -0.62]))
    controller = controller or ControllerSpec(poles=np.array([-0.3, -0.31, -0.32]))
    return Vehicle('sub', plant, (sensor,), observer, controller,
                   SimulatorSpec(100.0, np.zeros(plant.n)), description='test vehicle')


def test_design_vehicle_full():
    v = make_vehicle()
    d = design_vehicle(v)
    assert d.kind == 'full' and d.L.shape == (3, 1) and d.K.shape == (1, 3)
    assert_allclose(d.L, observer_gain(SUB_A, SUB_C, [-0.6, -0.61, -0.62]))
    assert d.separation_ok is True
    assert d.observability.observable and d.controllability.controllable
    assert len(d.closed_loop_poles) == 6 and len(d.compensator_poles) == 3
    assert d.noise_gain is not None and d.noise_gain[0] < 1.0
    assert d.warnings == ()
    data = to_json_dict(d)
    text = json.dumps(data)
    back = json.loads(text)
    for key in ('observable', 'detectable', 'observability_rank', 'L', 'K', 'observer_poles',
                'controller_poles', 'closed_loop_poles', 'separation_ok',
                'compensator_poles', 'warnings', 'unobservable_modes'):
        assert key in back, key
    assert back['L'] == [[float(x)] for x in d.L[:, 0]]
    assert all(len(z) == 2 for z in back['observer_poles'])
    assert sorted(round(z[0], 6) for z in back['observer_poles']) == [-0.62, -0.61, -0.6]
    report = format_report(d, v)
    for piece in ('Vehicle: sub', 'observable (rank 3 of 3)', 'theta', 'Separation principle',
                  'ok', 'Compensator D(s)', 'Warnings: none', '-0.8442'):
        assert piece in report, piece


def test_design_vehicle_reduced():
    C = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    v = make_vehicle(C=C, outputs=('theta', 'q'), noise=(0.01, 0.01),
                     observer=ObserverSpec('reduced', poles=np.array([-0.6])))
    d = design_vehicle(v)
    assert d.reduced is not None and d.L.shape == (1, 2)
    assert_allclose(d.observer_poles, [-0.6])
    assert d.separation_ok and len(d.closed_loop_poles) == 4
    data = json.loads(json.dumps(to_json_dict(d)))
    assert set(data['reduced']) >= {'F', 'G', 'H', 'L'}
    assert data['reduced']['rest'] == ['w']
    assert_allclose(data['reduced']['F'], [[-0.6]])
    assert 'estimates' in format_report(d, v)


def test_design_vehicle_open_loop_and_kalman():
    d = design_vehicle(make_vehicle(observer=ObserverSpec('open_loop')))
    assert_allclose(d.L, 0.0)
    assert_allclose(np.sort_complex(d.observer_poles), np.sort_complex(np.linalg.eigvals(SUB_A)))
    assert any('observer is slow' in w for w in d.warnings)
    cart = make_vehicle(A=CART_A, B=CART_B, C=CART_C, states=('theta', 'x', 'td', 'xd'),
                        outputs=('x',), observer=ObserverSpec('open_loop'),
                        controller=ControllerSpec(poles=np.array([-1.0, -2, -3, -4])))
    assert any('open-loop observer drifts' in w for w in design_vehicle(cart).warnings)
    kal = ObserverSpec('kalman', Qd=np.diag([1e-4, 1e-2, 1e-2]), Rd=np.array([[1e-4]]))
    v = make_vehicle(observer=kal)
    d = design_vehicle(v)
    assert d.P is not None
    # Rd is the covariance of each 10 ms sample, as the node's sampled filter uses it: the
    # design reported is the Kalman-Bucy filter that filter tends to, intensity Rd h
    h = v.sample_time
    assert_allclose(measurement_intensity(v), [[1e-4 * h]])
    assert_allclose(d.L, d.P @ SUB_C.T / (1e-4 * h), rtol=1e-9)
    assert 'P' in to_json_dict(d)


def test_design_vehicle_given_gains_and_lqr():
    L = observer_gain(SUB_A, SUB_C, [-1.0, -1.1, -1.2])
    K = controller_gain(SUB_A, SUB_B, [-0.3, -0.31, -0.32])
    d = design_vehicle(make_vehicle(observer=ObserverSpec('full', gain=L),
                                    controller=ControllerSpec(K=K)))
    assert_allclose(d.L, L)
    assert_allclose(d.K, K)
    with pytest.raises(DesignError, match='controller.K does not stabilize'):
        design_vehicle(make_vehicle(controller=ControllerSpec(K=np.zeros((1, 3)) + 100.0)))
    with pytest.raises(DesignError, match='observer.gain does not stabilize'):
        design_vehicle(make_vehicle(observer=ObserverSpec('full', gain=-L)))
    d = design_vehicle(make_vehicle(controller=ControllerSpec(lqr_Q=np.eye(3),
                                                              lqr_R=np.eye(1))))
    assert np.all(d.controller_poles.real < 0)
    d = design_vehicle(make_vehicle(controller=ControllerSpec()))
    assert d.K is None and d.separation_ok is None and d.compensator is None
    assert json.dumps(to_json_dict(d))
    assert 'Controller: none' in format_report(d)


def test_design_vehicle_example_515_refused():
    A = np.diag([2.0, -1.0, 5.0])
    B = np.array([[3.0], [0.0], [-1.0]])
    C = np.array([[1.0, 0.0, 0.0], [1.0, 2.0, 0.0]])
    D = np.array([[0.0], [1.0]])
    v = make_vehicle(A=A, B=B, C=C, D=D, states=('x1', 'x2', 'x3'), outputs=('y1', 'y2'),
                     noise=(0.1, 0.1), observer=ObserverSpec('full', poles=np.array([-3.0,
                                                                                     -4.0])),
                     controller=ControllerSpec(poles=np.array([-1.0, -2.0, -3.0])))
    with pytest.raises(NotDetectableError, match=r'eigenvalue 5 \(unstable\): x3'):
        design_vehicle(v)


def test_design_vehicle_bad_specs():
    with pytest.raises(DimensionError, match='observer.poles: poles has 2 poles; expected 3'):
        design_vehicle(make_vehicle(observer=ObserverSpec('full', poles=np.array([-1., -2]))))
    with pytest.raises(DesignError, match='observer.poles: pole 1 is in the closed right'):
        design_vehicle(make_vehicle(observer=ObserverSpec('full',
                                                          poles=np.array([1.0, -2, -3]))))
    with pytest.raises(DesignError, match='exactly one of observer.poles and observer.gain'):
        design_vehicle(make_vehicle(observer=ObserverSpec('full')))
    with pytest.raises(DesignError, match='needs observer.Qd and observer.Rd'):
        design_vehicle(make_vehicle(observer=ObserverSpec('kalman')))
    uncontrollable = make_vehicle(B=np.array([[0.0], [0.0], [0.0]]))
    with pytest.raises(DimensionError, match='controller.poles: poles has 3 poles; expected 0'):
        design_vehicle(uncontrollable)


def test_design_vehicle_detectable_plant_names_kept_mode():
    A = np.diag([-1.0, -2.0, -4.0]) + np.diag([1.0, 0.0], 1)
    C = np.array([[1.0, 0.0, 0.0]])
    B = np.array([[0.0], [1.0], [1.0]])
    v = make_vehicle(A=A, B=B, C=C, states=('a', 'b', 'c'), outputs=('y',),
                     observer=ObserverSpec('full', poles=np.array([-5.0, -6.0])),
                     controller=ControllerSpec(poles=np.array([-1.0, -2.0, -3.0])))
    d = design_vehicle(v)
    assert d.observability.detectable and not d.observability.observable
    assert d.observability.unobservable_modes == ('eigenvalue -4 (stable): c',)
    assert_allclose(np.sort(d.observer_poles.real), [-6.0, -5.0, -4.0])
    data = to_json_dict(d)
    assert data['unobservable_modes'] == ['eigenvalue -4 (stable): c']
    assert data['observable'] is False and data['detectable'] is True
    assert 'eigenvalue -4 (stable): c' in format_report(d, v)


def test_design_vehicle_discrete_plant():
    dt = 0.1
    Ad, Bd = zoh_matrices(SUB_A, SUB_B, dt)
    zo = np.exp(dt * np.array([-0.6, -0.61, -0.62]))
    zc = np.exp(dt * np.array([-0.3, -0.31, -0.32]))
    v = make_vehicle(A=Ad, B=Bd, dt=dt, observer=ObserverSpec('full', poles=zo),
                     controller=ControllerSpec(poles=zc))
    d = design_vehicle(v)
    assert d.discrete and d.separation_ok and d.compensator.dt == dt
    assert_allclose(np.sort(d.observer_poles.real), np.sort(zo), rtol=1e-9)
    assert not [w for w in d.warnings if 'slow' in w]
    assert 'z-plane' in format_report(d, v)
    # s-plane poles for a discrete plant are refused (outside the unit circle)
    with pytest.raises(DesignError, match='unit circle'):
        design_vehicle(make_vehicle(A=Ad, B=Bd, dt=dt,
                                    observer=ObserverSpec('full', poles=np.array([-2., -3,
                                                                                  -4]))))


def test_design_warnings_are_collected_not_raised():
    rng = np.random.default_rng(1)
    A = rng.normal(size=(12, 12))
    B = rng.normal(size=(12, 1))
    C = rng.normal(size=(1, 12))
    plant_states = tuple(f's{i}' for i in range(12))
    with pytest.warns(ObserverDesignWarning):
        K = controller_gain(A, B, -np.arange(1.0, 13.0) / 10.0)
    v = make_vehicle(A=A, B=B, C=C, states=plant_states, outputs=('y',),
                     observer=ObserverSpec('full', poles=-np.arange(1.0, 13.0)),
                     controller=ControllerSpec(K=K))
    with warnings.catch_warnings():
        warnings.simplefilter('error', ObserverDesignWarning)
        d = design_vehicle(v)
    assert any('relative error' in w for w in d.warnings)
