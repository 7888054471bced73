"""Tests of observer_ros.core.design: pole placement, LQR/Kalman, reduced-order observer."""

import warnings

import control
import numpy as np
from numpy.testing import assert_allclose
from observer_ros.core.analysis import is_controllable
from observer_ros.core.design import (
    controller_gain, kalman_gain, kalman_update_gain, lqr_gain, observer_gain,
    pole_placement_error, reduced_coordinates, reduced_order_observer)
from observer_ros.core.errors import (DesignError, DimensionError, NotControllableError,
                                      NotDetectableError, NotObservableError,
                                      ObserverDesignWarning, ObserverError)
from plants import GYRO_C, SUBMARINE_A, SUBMARINE_B
import pytest
from scipy.stats import ortho_group

A515 = np.diag([2.0, -1.0, 5.0])
C515 = np.array([[1.0, 0.0, 0.0], [1.0, 2.0, 0.0]])
A_CART = np.array([[0, 0, 1, 0], [0, 0, 0, 1], [10.78, 0, 0, 0], [-0.98, 0, 0, 0]], float)
B_CART = np.array([[0.0], [0.0], [-1.0], [1.0]])


def random_poles(rng, k):
    """Return k distinct stable poles, some in complex-conjugate pairs."""
    poles = []
    while len(poles) < k:
        if k - len(poles) >= 2 and rng.random() < 0.4:
            re, im = -rng.uniform(0.5, 4.0), rng.uniform(0.3, 3.0)
            poles += [complex(re, im), complex(re, -im)]
        else:
            poles.append(complex(-rng.uniform(0.5, 4.0), 0.0))
    return np.array(poles)


def random_system(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(2, 9))
    p = int(rng.integers(1, 4))
    m = int(rng.integers(1, 3))
    return rng, rng.normal(size=(n, n)), rng.normal(size=(n, m)), rng.normal(size=(p, n))


def random_unobservable(rng, n, p, unobs_eigs, m=1):
    """Return (A, B, C) whose unobservable subspace has the eigenvalues unobs_eigs."""
    k = len(unobs_eigs)
    r = n - k
    Abar = np.zeros((n, n))
    Abar[:r, :r] = rng.normal(size=(r, r))
    Abar[r:, :r] = rng.normal(size=(k, r))
    Abar[r:, r:] = np.diag(unobs_eigs)
    Cbar = np.zeros((p, n))
    Cbar[:, :r] = rng.normal(size=(p, r))
    T = ortho_group.rvs(n, random_state=rng)
    return T @ Abar @ T.T, rng.normal(size=(n, m)), Cbar @ T.T


# ---------------------------------------------------------------- full-order gains


@pytest.mark.filterwarnings('ignore:Convergence was not reached:UserWarning')
@pytest.mark.parametrize('seed', range(25))
def test_observer_gain_places_poles_and_agrees_with_place(seed):
    rng, A, _, C = random_system(seed)
    n = A.shape[0]
    poles = random_poles(rng, n)
    with warnings.catch_warnings():
        warnings.simplefilter('ignore', ObserverDesignWarning)
        L = observer_gain(A, C, poles)
    assert L.shape == (n, C.shape[0])
    assert pole_placement_error(A - L @ C, poles) < 1e-6
    Lp = control.place(A.T, C.T, poles).T
    if C.shape[0] == 1:
        # one output: the gain is unique, place and acker must agree
        assert_allclose(L, Lp, rtol=1e-5, atol=1e-7 * np.abs(Lp).max())
    else:
        assert_allclose(L, Lp, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize('seed', range(10))
def test_controller_gain_is_the_dual(seed):
    rng, A, B, _ = random_system(seed)
    poles = random_poles(rng, A.shape[0])
    with warnings.catch_warnings():
        warnings.simplefilter('ignore', ObserverDesignWarning)
        K = controller_gain(A, B, poles)
        L = observer_gain(A.T, B.T, poles)
    assert K.shape == (B.shape[1], A.shape[0])
    assert_allclose(K, L.T, rtol=1e-12, atol=1e-12)
    assert pole_placement_error(A - B @ K, poles) < 1e-6


def test_methods_give_the_same_single_output_gain():
    C = [[0.0, 1.0, 0.0, 0.0]]
    poles = [-10 + 10j, -10 - 10j, -20 + 20j, -20 - 20j]
    La = observer_gain(A_CART, C, poles, method='acker')
    Lp = observer_gain(A_CART, C, poles, method='place')
    assert_allclose(La, Lp, rtol=1e-10)
    with pytest.raises(DesignError, match="method is 'lqr'"):
        observer_gain(A_CART, C, poles, method='lqr')
    with pytest.raises(DesignError, match="'acker' needs a single output; there are 2"):
        observer_gain(A_CART, [[0, 1.0, 0, 0], [1.0, 0, 0, 0]], poles, method='acker')


def test_repeated_poles_single_output_use_acker():
    poles = [-2.0] * 4
    L = observer_gain(A_CART, [[0, 1.0, 0, 0]], poles)
    # a 4-fold eigenvalue is only defined to ~eps^(1/4); the characteristic
    # polynomial is the well-conditioned check
    assert_allclose(np.poly(A_CART - L @ np.array([[0, 1.0, 0, 0]])), np.poly(poles),
                    rtol=1e-9, atol=1e-9)
    with pytest.raises(DesignError, match="pole -2 is repeated 4 times; method 'place'"):
        observer_gain(A_CART, [[0, 1.0, 0, 0]], poles, method='place')


def test_repeated_poles_beyond_outputs_placed_by_a_rank_one_gain():
    C = np.array([[0, 1.0, 0, 0], [1.0, 0, 0, 0]])
    poles = [-3.0, -3.0, -3.0, -1.0]
    with warnings.catch_warnings():
        warnings.simplefilter('error', ObserverDesignWarning)
        L = observer_gain(A_CART, C, poles)
    # a rank-one gain L = l w^T (Ackermann on one combination w of the two outputs)
    assert np.linalg.matrix_rank(L) == 1
    assert pole_placement_error(A_CART - L @ C, poles) < 1e-9
    assert_allclose(np.poly(A_CART - L @ C), np.poly(poles), rtol=1e-9, atol=1e-9)
    L = observer_gain(A_CART, C, [-3.0, -3.0, -1.0, -2.0])      # twice: place itself
    assert pole_placement_error(A_CART - L @ C, [-3, -3, -1, -2]) < 1e-8
    with pytest.raises(DesignError, match="pole -3 is repeated 3 times; method 'place' allows "
                                          'at most 2'):
        observer_gain(A_CART, C, poles, method='place')


def test_four_fold_controller_pole_with_two_inputs():
    B = np.array([[0.0, 0.0], [0.0, 0.0], [-1.0, 1.0], [1.0, 0.0]])
    for poles in ([-2.0] * 4, [-1 - 1j, -1 + 1j, -1 - 1j, -1 + 1j]):
        K = controller_gain(A_CART, B, poles)
        assert pole_placement_error(A_CART - B @ K, poles) < 1e-9
        assert_allclose(np.poly(A_CART - B @ K), np.poly(poles), atol=1e-8)


def test_cyclic_design_when_no_input_combination_is_controllable():
    # eigenvalue 1 of geometric multiplicity 2: no single b = B g makes (A, b) controllable
    A = np.diag([1.0, 1.0, 2.0])
    B = np.array([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
    for g in (np.array([1.0, 0.0]), np.array([0.3, -0.7])):
        assert not is_controllable(A, (B @ g).reshape(3, 1))
    K = controller_gain(A, B, [-1.0, -1.0, -1.0])
    assert_allclose(np.poly(A - B @ K), np.poly([-1.0, -1.0, -1.0]), atol=1e-9)


def test_ill_conditioned_placement_warns():
    rng = np.random.default_rng(1)
    A = rng.normal(size=(12, 12))
    C = rng.normal(size=(1, 12))
    with pytest.warns(ObserverDesignWarning, match='relative error'):
        observer_gain(A, C, -np.arange(1.0, 13.0))


def test_acker_losing_digits_warns():
    rng = np.random.default_rng(0)
    A = rng.normal(size=(7, 7)) * np.logspace(0, 2, 7)[None, :]
    C = rng.normal(size=(1, 7))
    poles = -np.arange(1.0, 8.0)
    with pytest.warns(ObserverDesignWarning) as record:
        observer_gain(A, C, poles, method='acker')
    messages = [str(w.message) for w in record]
    assert any("'acker'" in msg and 'loses digits' in msg for msg in messages)
    assert any('relative error' in msg and 'by acker' in msg for msg in messages)
    with warnings.catch_warnings():
        warnings.simplefilter('error', ObserverDesignWarning)
        L = observer_gain(A, C, poles)   # auto picks place (~1e-7 off): no warning
    assert pole_placement_error(A - L @ C, poles) < 1e-6


def test_no_warning_for_a_well_conditioned_design():
    with warnings.catch_warnings():
        warnings.simplefilter('error', ObserverDesignWarning)
        observer_gain(A_CART, [[0, 1.0, 0, 0]], [-1, -2, -3, -4])


# ---------------------------------------------------------------- unobservable plants


@pytest.mark.parametrize('seed', range(10))
def test_detectable_plant_keeps_unobservable_eigenvalues(seed):
    rng = np.random.default_rng(50 + seed)
    n = int(rng.integers(3, 8))
    k = int(rng.integers(1, n - 1))
    p = int(rng.integers(1, 3))
    unobs = -rng.uniform(0.5, 3.0, k)
    A, _, C = random_unobservable(rng, n, p, unobs)
    poles = random_poles(rng, n - k)
    with warnings.catch_warnings():
        warnings.simplefilter('ignore', ObserverDesignWarning)
        L = observer_gain(A, C, poles)
    assert pole_placement_error(A - L @ C, np.concatenate([poles, unobs])) < 1e-6
    with pytest.raises(DimensionError, match=f'expected {n - k}: .* rank {n - k} of {n}'):
        observer_gain(A, C, random_poles(rng, n))


@pytest.mark.parametrize('seed', range(5))
def test_undetectable_plant_refused(seed):
    rng = np.random.default_rng(80 + seed)
    n = int(rng.integers(3, 7))
    A, _, C = random_unobservable(rng, n, 1, [-1.0, 0.7])
    names = [f's{i}' for i in range(n)]
    with pytest.raises(NotDetectableError, match='eigenvalue 0.7 \\(unstable\\)'):
        observer_gain(A, C, random_poles(rng, n - 2), state_names=names)


def test_example_515_refused_naming_x3_and_5():
    with pytest.raises(NotDetectableError, match='eigenvalue 5 \\(unstable\\): x3'):
        observer_gain(A515, C515, [-1.0, -2.0])
    # NotDetectableError is a NotObservableError and a ValueError
    with pytest.raises(NotObservableError):
        observer_gain(A515, C515, [-1.0, -2.0, -3.0])


def test_discrete_detectability_uses_unit_circle():
    A = np.diag([0.5, 1.5])
    C = [[0.0, 1.0]]
    L = observer_gain(A, C, [0.2], discrete=True)         # unobservable 0.5 is kept
    assert_allclose(np.sort(np.linalg.eigvals(A - L @ np.array(C)).real), [0.2, 0.5])
    with pytest.raises(NotDetectableError):
        observer_gain(A, C, [-0.2])                          # continuous: 0.5 is unstable


def test_uncontrollable_plant():
    B = np.array([[3.0], [0.0], [-1.0]])                     # x2 not moved by u
    # the observer's rule: one pole per controllable mode, a DimensionError
    # that names the count and the kept mode
    with pytest.raises(DimensionError, match='expected 2.*eigenvalue -1 \\(stable\\): x2'):
        controller_gain(A515, B, [-1.0, -2.0, -3.0])
    K = controller_gain(A515, B, [-2.0, -3.0])               # stabilizable: keep -1
    assert_allclose(np.sort(np.linalg.eigvals(A515 - B @ K).real), [-3.0, -2.0, -1.0],
                    atol=1e-9)
    with pytest.raises(NotControllableError, match='not stabilizable.*eigenvalue 3'):
        controller_gain(np.diag([2.0, 3.0]), [[1.0], [0.0]], [-1.0])


# ---------------------------------------------------------------- bad inputs


def test_bad_shapes_and_poles():
    A = np.eye(3)
    with pytest.raises(DimensionError, match='C has 2 columns; expected 3'):
        observer_gain(A, np.ones((1, 2)), [-1, -2, -3])
    with pytest.raises(DimensionError, match='B has 2 rows; expected 3'):
        controller_gain(A, np.ones((2, 1)), [-1, -2, -3])
    with pytest.raises(DimensionError, match='poles has 2 poles; expected 4 \\(one per state'):
        observer_gain(A_CART, [[0, 1.0, 0, 0]], [-1, -2])
    with pytest.raises(ObserverError, match='conjugate'):
        observer_gain(A_CART, [[0, 1.0, 0, 0]], [-1 + 1j, -1 + 1j, -2, -3])
    with pytest.raises(DimensionError, match='poles is not a list of numbers'):
        observer_gain(A_CART, [[0, 1.0, 0, 0]], ['a', -1, -2, -3])


# ---------------------------------------------------------------- LQR and Kalman


def test_lqr_gain_matches_control_and_solves_the_riccati_equation():
    Q = np.diag([10.0, 1.0, 1.0, 1.0])
    R = np.array([[0.1]])
    K, S, E = lqr_gain(A_CART, B_CART, Q, R)
    Kc, _, _ = control.lqr(A_CART, B_CART, Q, R)
    assert_allclose(K, Kc)
    res = A_CART.T @ S + S @ A_CART - S @ B_CART @ np.linalg.solve(R, B_CART.T) @ S + Q
    assert np.abs(res).max() < 1e-8 * np.abs(S).max()
    assert_allclose(np.sort_complex(E), np.sort_complex(np.linalg.eigvals(A_CART - B_CART @ K)))
    with pytest.raises(DimensionError, match='Q has 3 rows; expected 4'):
        lqr_gain(A_CART, B_CART, np.eye(3), R)
    with pytest.raises(DesignError, match='R must be positive definite'):
        lqr_gain(A_CART, B_CART, Q, [[0.0]])
    with pytest.raises(DesignError, match='Q is not symmetric'):
        lqr_gain(A_CART, B_CART, Q + np.triu(np.ones((4, 4)), 1), R)


def test_dlqr_path():
    Ad = np.array([[1.0, 0.1], [0.0, 1.0]])
    Bd = np.array([[0.005], [0.1]])
    K, S, E = lqr_gain(Ad, Bd, np.eye(2), [[1.0]], discrete=True)
    assert_allclose(K, control.dlqr(Ad, Bd, np.eye(2), [[1.0]])[0])
    assert np.all(np.abs(E) < 1)


def test_kalman_bucy_gain_is_P_Ct_Rinv_with_P_from_the_are():
    A, C, Bd = np.array(SUBMARINE_A), np.array(GYRO_C), np.array(SUBMARINE_B)
    Qd = np.array([[4.0]])
    Rd = np.array([[1e-4]])
    L, P, E = kalman_gain(A, C, Qd, Rd, Bd)
    assert_allclose(L, P @ C.T @ np.linalg.inv(Rd), rtol=1e-10)
    res = A @ P + P @ A.T + Bd @ Qd @ Bd.T - P @ C.T @ np.linalg.solve(Rd, C) @ P
    assert np.abs(res).max() < 1e-9 * max(1.0, np.abs(P).max())
    assert np.all(np.linalg.eigvalsh(P) > -1e-12)
    assert np.all(E.real < 0)
    assert_allclose(np.sort_complex(E), np.sort_complex(np.linalg.eigvals(A - L @ C)))


def test_discrete_kalman_gain_is_the_predictor_gain():
    Ad = np.array([[1.0, 0.1], [0.0, 0.95]])
    C = np.array([[1.0, 0.0]])
    Qd = np.diag([1e-4, 1e-3])
    Rd = np.array([[0.01]])
    L, P, E = kalman_gain(Ad, C, Qd, Rd, discrete=True)
    M = kalman_update_gain(P, C, Rd)
    assert_allclose(M, P @ C.T / (C @ P @ C.T + Rd))
    assert_allclose(L, Ad @ M, rtol=1e-10)
    # P is the a-priori covariance: the DARE of the predictor
    res = Ad @ P @ Ad.T - Ad @ P @ C.T @ np.linalg.solve(C @ P @ C.T + Rd, C @ P @ Ad.T) \
        + Qd - P
    assert np.abs(res).max() < 1e-12
    assert np.all(np.abs(E) < 1)


def test_kalman_bad_inputs():
    A = np.eye(2) * -1.0
    C = np.array([[1.0, 0.0]])
    with pytest.raises(DimensionError, match='Rd has 2 rows; expected 1'):
        kalman_gain(A, C, np.eye(2), np.eye(2))
    with pytest.raises(DimensionError, match='Qd has 2 rows; expected 1'):
        kalman_gain(A, C, np.eye(2), [[1.0]], Bd=[[1.0], [0.0]])
    with pytest.raises(DesignError, match='Rd must be positive definite'):
        kalman_gain(A, C, np.eye(2), [[-1.0]])
    with pytest.raises(NotDetectableError, match='eigenvalue 5 \\(unstable\\): x3'):
        kalman_gain(A515, C515, np.eye(3), np.eye(2))


# ---------------------------------------------------------------- reduced order


def test_reduced_coordinates_cart():
    T, Tinv, rest = reduced_coordinates([[0, 1.0, 0, 0]])
    assert rest == [0, 2, 3]
    assert_allclose(T @ Tinv, np.eye(4))
    with pytest.raises(DesignError, match='full row rank'):
        reduced_coordinates([[1.0, 0, 0], [2.0, 0, 0]])


def _check_reduced(A, B, C, D, design, rng):
    """Check the three annihilation conditions and e2' = F e2 for arbitrary x, z, u."""
    p = design.p
    assert_allclose(design.A22 - design.L @ design.A12 - design.F, 0.0, atol=1e-9)
    assert_allclose(design.B2 - design.L @ design.B1 - design.H, 0.0, atol=1e-9)
    assert_allclose(design.A21 - design.L @ design.A11 + design.F @ design.L - design.G, 0.0,
                    atol=1e-9 * max(1.0, np.abs(design.G).max()))
    assert_allclose(design.T @ A @ design.Tinv,
                    np.block([[design.A11, design.A12], [design.A21, design.A22]]))
    assert_allclose(design.T[:p], C)
    # error dynamics from the plant and observer equations directly
    n, m = B.shape
    for _ in range(3):
        x, u, z = rng.normal(size=n), rng.normal(size=m), rng.normal(size=design.order)
        y = C @ x + D @ u
        x_hat = design.state_estimate(y, z, u)
        e2 = (design.T @ (x - x_hat))[p:]
        assert_allclose((design.T @ (x - x_hat))[:p], 0.0, atol=1e-9)   # y is exact
        xdot = A @ x + B @ u
        # d/dt x_hat2 = L d/dt(y - D u) + z' with y - D u = C x
        e2dot = (design.T @ xdot)[p:] - design.L @ (C @ xdot) - design.z_rate(z, y, u)
        assert_allclose(e2dot, design.F @ e2, rtol=1e-8,
                        atol=1e-8 * max(1.0, np.abs(e2dot).max()))


@pytest.mark.parametrize('seed', range(15))
def test_reduced_order_observer_random(seed):
    rng, A, B, C = random_system(200 + seed)
    n, p = A.shape[0], C.shape[0]
    if p >= n:
        C = C[:n - 1]
        p = n - 1
    D = rng.normal(size=(p, B.shape[1]))
    poles = random_poles(rng, n - p)
    with warnings.catch_warnings():
        warnings.simplefilter('ignore', ObserverDesignWarning)
        design = reduced_order_observer(A, B, C, D, poles=poles)
    assert design.L.shape == (n - p, p)
    assert pole_placement_error(design.F, poles) < 1e-6
    _check_reduced(A, B, C, D, design, rng)
    x = rng.normal(size=n)
    u = rng.normal(size=B.shape[1])
    y = C @ x + D @ u
    assert_allclose(design.state_estimate(y, design.z_from_estimate(x, y, u), u), x,
                    atol=1e-9 * max(1.0, np.abs(x).max()) * max(1.0, np.abs(design.L).max()))


def test_reduced_order_observer_with_given_gain_and_errors():
    C = [[0, 1.0, 0, 0]]
    L = np.array([[1.0], [2.0], [3.0]])
    d = reduced_order_observer(A_CART, B_CART, C, gain=L)
    assert_allclose(d.L, L)
    assert_allclose(d.F, d.A22 - L @ d.A12)
    with pytest.raises(DesignError, match='exactly one of poles and gain'):
        reduced_order_observer(A_CART, B_CART, C)
    with pytest.raises(DimensionError, match='gain has 4 rows; expected 3'):
        reduced_order_observer(A_CART, B_CART, C, gain=np.ones((4, 1)))
    with pytest.raises(DimensionError, match='reduced-order observer: poles has 4 poles; '
                                             'expected 3'):
        reduced_order_observer(A_CART, B_CART, C, poles=[-1, -2, -3, -4])
    with pytest.raises(DimensionError, match='y has 2 elements; expected 1'):
        d.state_estimate([1.0, 2.0], np.zeros(3))


def test_reduced_order_detectable_and_undetectable():
    B = np.ones((3, 1))
    C = np.array([[1.0, 0.0, 0.0]])
    # x2, x3 are unobservable but stable: nothing to place, F keeps -2 and -4
    d = reduced_order_observer(np.diag([-1.0, -2.0, -4.0]), B, C, poles=[],
                               state_names=['a', 'b', 'c'])
    assert_allclose(np.sort(d.poles.real), [-4.0, -2.0])
    with pytest.raises(DimensionError, match='expected 0'):
        reduced_order_observer(np.diag([-1.0, -2.0, -4.0]), B, C, poles=[-5.0])
    # one unobservable stable mode (c) kept, one observable mode placed
    A = np.array([[-1.0, 1.0, 0.0], [0.0, -2.0, 0.0], [0.0, 0.0, -4.0]])
    d = reduced_order_observer(A, B, C, poles=[-5.0])
    assert_allclose(np.sort(d.poles.real), [-5.0, -4.0])
    A2 = np.diag([-1.0, 0.5, -4.0])
    with pytest.raises(NotDetectableError, match='eigenvalue 0.5 \\(unstable\\): b'):
        reduced_order_observer(A2, B, C, poles=[], state_names=['a', 'b', 'c'])
