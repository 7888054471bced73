"""Tests of observer_ros.core.analysis: ranks, PBH, Gramians, decompositions, reports."""

import control
import numpy as np
from numpy.testing import assert_allclose
from observer_ros.core.analysis import (
    controllability_report, controllable_decomposition, ctrb,
    is_controllable, is_detectable, is_observable, is_stabilizable, numerical_rank,
    observability_report, observable_decomposition, obsv, pbh_test,
    pbh_test_controllability, rank_tolerance, uncontrollable_eigenvalues,
    unobservable_eigenvalues)
from observer_ros.core.errors import DimensionError, ObserverError
from observer_ros.core.gramians import controllability_gramian, observability_gramian
import pytest
import scipy.integrate
import scipy.linalg
from scipy.stats import ortho_group

# Example 5.15 (seed 002): x1' = 2 x1 + 3 u, x2' = -x2, x3' = 5 x3 - u,
# y1 = x1, y2 = 2 x2 + x1 + u.
A515 = np.diag([2.0, -1.0, 5.0])
B515 = np.array([[3.0], [0.0], [-1.0]])
C515 = np.array([[1.0, 0.0, 0.0], [1.0, 2.0, 0.0]])

# Inverted pendulum on a cart (seed 002), states [theta, x, thetadot, xdot].
A_CART = np.array([[0, 0, 1, 0], [0, 0, 0, 1], [10.78, 0, 0, 0], [-0.98, 0, 0, 0]], float)
CART_NAMES = ('theta', 'x', 'thetadot', 'xdot')


def random_unobservable(rng, n, p, n_unobs, unobs_eigs=None, m=1):
    """Random (A, B, C) with an n_unobs-dimensional unobservable subspace (orthogonal T)."""
    r = n - n_unobs
    Ao = rng.normal(size=(r, r))
    Au = np.diag(unobs_eigs) if unobs_eigs is not None else \
        np.diag(-rng.uniform(0.5, 3.0, n_unobs))
    Abar = np.zeros((n, n))
    Abar[:r, :r] = Ao
    Abar[r:, r:] = Au
    Abar[r:, :r] = rng.normal(size=(n_unobs, r))
    Cbar = np.zeros((p, n))
    Cbar[:, :r] = rng.normal(size=(p, r))
    T = ortho_group.rvs(n, random_state=rng)
    A = T @ Abar @ T.T
    C = Cbar @ T.T
    B = rng.normal(size=(n, m))
    return A, B, C, T


# ---------------------------------------------------------------- ranks


def test_obsv_ctrb_are_python_controls():
    rng = np.random.default_rng(0)
    A = rng.normal(size=(4, 4))
    B = rng.normal(size=(4, 2))
    C = rng.normal(size=(3, 4))
    assert_allclose(obsv(A, C), control.obsv(A, C))
    assert_allclose(ctrb(A, B), control.ctrb(A, B))
    assert obsv(A, C).shape == (12, 4)


def test_obsv_shape_errors_name_the_matrix():
    with pytest.raises(DimensionError, match='C has 3 columns; expected 2'):
        obsv(np.eye(2), np.ones((1, 3)))
    with pytest.raises(DimensionError, match='A is 2x3; expected a square matrix'):
        obsv(np.ones((2, 3)), np.ones((1, 3)))
    with pytest.raises(DimensionError, match='B has 3 rows; expected 2'):
        ctrb(np.eye(2), np.ones((3, 1)))


def test_numerical_rank_default_tolerance():
    U = ortho_group.rvs(5, random_state=1)
    V = ortho_group.rvs(5, random_state=2)
    s = np.array([1e3, 1.0, 1e-6, 1e-20, 0.0])
    M = U @ np.diag(s) @ V.T
    # default tol = 5 * eps * 1e3 ~ 1e-12: 1e-6 counts, 1e-20 does not
    assert numerical_rank(M) == 3
    assert rank_tolerance(M) == pytest.approx(5 * np.finfo(float).eps * 1e3, rel=1e-6)
    assert numerical_rank(M, tol=1e-3) == 2
    assert numerical_rank(np.zeros((3, 2))) == 0


# ---------------------------------------------------------------- PBH


def test_pbh_example_515_flags_eigenvalue_5():
    res = {r.eigenvalue.real: r for r in pbh_test(A515, C515)}
    assert set(res) == {2.0, -1.0, 5.0}
    assert res[5.0].rank == 2 and not res[5.0].passed and not res[5.0].stable
    assert res[2.0].passed and res[-1.0].passed
    assert res[-1.0].stable and not res[2.0].stable


def test_pbh_repeated_eigenvalue_single_output():
    # two identical decoupled modes cannot both be seen by one sensor
    res = pbh_test(-np.eye(2), [[1.0, 1.0]])
    assert len(res) == 1 and res[0].multiplicity == 2 and res[0].rank == 1
    assert not res[0].passed
    # a Jordan block observed at its head is observable
    res = pbh_test([[-1.0, 1.0], [0.0, -1.0]], [[1.0, 0.0]])
    assert len(res) == 1 and res[0].multiplicity == 2 and res[0].passed


def test_pbh_complex_pair_reported_once_and_discrete_stability():
    A = np.array([[0.5, 0.4], [-0.4, 0.5]])
    res = pbh_test(A, [[1.0, 0.0]], discrete=True)
    assert len(res) == 1 and res[0].eigenvalue.imag > 0
    assert res[0].stable          # |z| = 0.64 < 1
    assert not pbh_test(A, [[1.0, 0.0]])[0].stable   # Re s = 0.5 > 0


def test_pbh_controllability_is_dual():
    res = {r.eigenvalue.real: r.passed for r in pbh_test_controllability(A515, B515)}
    assert res == {2.0: True, -1.0: False, 5.0: True}


# ---------------------------------------------------------------- Gramians


def test_finite_horizon_gramian_matches_quadrature():
    rng = np.random.default_rng(3)
    A = rng.normal(size=(3, 3))
    C = rng.normal(size=(2, 3))
    t = 0.7
    W = observability_gramian(A, C, t)
    Wq = scipy.integrate.quad_vec(
        lambda s: scipy.linalg.expm(A.T * s) @ C.T @ C @ scipy.linalg.expm(A * s), 0, t,
        epsabs=1e-13, epsrel=1e-12)[0]
    assert_allclose(W, Wq, rtol=1e-9, atol=1e-12)
    assert_allclose(W, W.T)


def test_infinite_horizon_gramian_solves_lyapunov_and_is_the_limit():
    A = np.array([[-1.0, 2.0, 0.0], [0.0, -2.0, 1.0], [0.0, 0.0, -0.5]])
    C = np.array([[1.0, 0.0, 0.0]])
    W = observability_gramian(A, C)
    assert_allclose(A.T @ W + W @ A, -C.T @ C, atol=1e-12)
    assert np.all(np.linalg.eigvalsh(W) > 0)       # observable: positive definite
    assert_allclose(observability_gramian(A, C, 80.0), W, rtol=1e-9, atol=1e-12)


def test_infinite_horizon_gramian_refuses_unstable_A():
    with pytest.raises(ObserverError, match=r'stable A.*eigenvalue 5 \(unstable\)'):
        observability_gramian(A515, C515)
    with pytest.raises(ObserverError, match='stable A'):
        observability_gramian(np.diag([0.5, 1.5]), np.eye(2), discrete=True)


def test_discrete_gramian_sum_and_lyapunov():
    A = np.array([[0.5, 0.2], [0.0, -0.3]])
    C = np.array([[0.0, 1.0]])
    W3 = observability_gramian(A, C, 3, discrete=True)
    expected = sum(np.linalg.matrix_power(A.T, k) @ C.T @ C @ np.linalg.matrix_power(A, k)
                   for k in range(3))
    assert_allclose(W3, expected)
    W = observability_gramian(A, C, discrete=True)
    assert_allclose(A.T @ W @ A - W, -C.T @ C, atol=1e-14)
    with pytest.raises(ObserverError, match='whole number'):
        observability_gramian(A, C, 2.5, discrete=True)


def test_gramian_rank_detects_unobservability_and_duality():
    W = observability_gramian(A515, C515, 1.0)
    assert numerical_rank(W) == 2
    assert_allclose(W[2], 0.0, atol=1e-14)        # x3 never reaches the outputs
    Wc = controllability_gramian(A515, B515, 1.0)
    assert_allclose(Wc, observability_gramian(A515.T, B515.T, 1.0))
    assert numerical_rank(Wc) == 2


# ---------------------------------------------------------------- decompositions


def test_observable_decomposition_example_515():
    Abar, Bbar, Cbar, T, m = observable_decomposition(A515, B515, C515)
    assert m == 2
    assert_allclose(T.T @ T, np.eye(3), atol=1e-14)
    assert_allclose(Abar, T.T @ A515 @ T, atol=1e-14)
    assert_allclose(Abar[:2, 2], 0.0)
    assert_allclose(Cbar[:, 2], 0.0)
    assert_allclose(np.abs(T[:, 2]), [0, 0, 1], atol=1e-14)   # unobservable direction x3
    assert_allclose(Abar[2, 2], 5.0)
    assert_allclose(np.sort(unobservable_eigenvalues(A515, C515).real), [5.0])


@pytest.mark.parametrize('seed', range(6))
def test_observable_decomposition_random(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(3, 8))
    k = int(rng.integers(1, n - 1))
    p = int(rng.integers(1, 3))
    eigs = -rng.uniform(0.5, 3.0, k)
    A, B, C, _ = random_unobservable(rng, n, p, k, eigs)
    Abar, Bbar, Cbar, T, m = observable_decomposition(A, B, C)
    assert m == n - k
    assert m == numerical_rank(obsv(A, C), tol=1e-9 * np.linalg.norm(obsv(A, C), 2))
    assert_allclose(T @ Abar @ T.T, A, atol=1e-12)
    assert_allclose(T.T @ B, Bbar, atol=1e-12)
    assert_allclose(Abar[:m, m:], 0.0)
    assert_allclose(Cbar[:, m:], 0.0)
    assert_allclose(C @ T[:, m:], 0.0, atol=1e-12)
    assert is_observable(Abar[:m, :m], Cbar[:, :m])
    assert_allclose(np.sort(unobservable_eigenvalues(A, C).real), np.sort(eigs), atol=1e-10)
    # the transfer function only sees the observable part
    for s in (0.3 + 1.0j, 2.0):
        G = C @ np.linalg.solve(s * np.eye(n) - A, B)
        Go = Cbar[:, :m] @ np.linalg.solve(s * np.eye(m) - Abar[:m, :m], Bbar[:m])
        assert_allclose(G, Go, rtol=1e-9, atol=1e-12)


def test_controllable_decomposition_is_kalman_form():
    rng = np.random.default_rng(7)
    A, C_t, B_t, _ = random_unobservable(rng, 5, 2, 2, [-1.0, -2.0])
    A = A.T
    B = B_t.T                     # (A^T, C^T) dual of an unobservable pair: uncontrollable
    Abar, Bbar, Cbar, T, r = controllable_decomposition(A, B)
    assert r == 3
    assert_allclose(Abar[r:, :r], 0.0)
    assert_allclose(Bbar[r:], 0.0)
    assert_allclose(T @ Abar @ T.T, A, atol=1e-12)
    assert is_controllable(Abar[:r, :r], Bbar[:r])
    assert_allclose(np.sort(uncontrollable_eigenvalues(A, B).real), [-2.0, -1.0], atol=1e-10)


# ---------------------------------------------------------------- reports


def test_report_example_515_is_undetectable_and_names_x3():
    rep = observability_report(A515, C515)
    assert (rep.n, rep.rank, rep.observable, rep.detectable) == (3, 2, False, False)
    assert rep.unobservable_modes == ('eigenvalue 5 (unstable): x3',)
    assert rep.modes[0].states == ('x3',)
    assert 'NOT detectable' in rep.summary()


def test_report_detectable_when_unobservable_mode_is_stable():
    A = np.diag([2.0, -1.0, -5.0])
    rep = observability_report(A, C515, ['a', 'b', 'c'])
    assert not rep.observable and rep.detectable
    assert rep.unobservable_modes == ('eigenvalue -5 (stable): c',)
    assert is_detectable(A, C515) and not is_detectable(A515, C515)


def test_report_cart_measuring_theta_names_x_and_xdot():
    rep = observability_report(A_CART, [[1.0, 0, 0, 0]], CART_NAMES)
    assert rep.rank == 2 and not rep.detectable
    assert rep.unobservable_modes == (
        'eigenvalue 0 (multiplicity 2, marginally stable): x, xdot',)
    assert observability_report(A_CART, [[0, 1.0, 0, 0]], CART_NAMES).observable


def test_report_discrete_uses_unit_circle():
    A = np.diag([0.5, 1.2])
    C = [[0.0, 1.0]]
    assert observability_report(A, C, discrete=True).detectable       # |0.5| < 1
    assert not observability_report(A, C).detectable                  # Re 0.5 > 0
    rep = observability_report(np.diag([1.0, 0.3]), [[0.0, 1.0]], discrete=True)
    assert not rep.detectable and 'marginally stable' in rep.unobservable_modes[0]


def test_report_names_mixed_states_of_a_rotated_mode():
    # the unobservable mode lives on x1 - x2 (weights equal) and not on x3
    A = np.array([[-1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -3.0]])
    C = np.array([[1.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    rep = observability_report(A, C, ['u', 'v', 'w'])
    assert rep.rank == 2 and rep.detectable
    assert rep.modes[0].states == ('u', 'v')
    assert_allclose(rep.modes[0].weights, [1.0, 1.0, 0.0], atol=1e-12)


def test_controllability_report_example_515():
    rep = controllability_report(A515, B515)
    assert (rep.rank, rep.controllable, rep.stabilizable) == (2, False, True)
    assert rep.uncontrollable_modes == ('eigenvalue -1 (stable): x2',)
    assert is_stabilizable(A515, B515)
    assert not is_stabilizable(np.diag([1.0, 2.0]), [[1.0], [0.0]])


def test_report_state_names_length_checked():
    with pytest.raises(DimensionError, match='state_names has 2 names; expected 3'):
        observability_report(A515, C515, ['a', 'b'])


@pytest.mark.parametrize('seed', range(5))
def test_staircase_rank_agrees_with_obsv_rank_and_pbh(seed):
    rng = np.random.default_rng(100 + seed)
    n = int(rng.integers(2, 7))
    A = rng.normal(size=(n, n))
    C = rng.normal(size=(1, n))
    rep = observability_report(A, C)
    assert rep.observable and rep.rank == numerical_rank(obsv(A, C)) == n
    assert all(r.passed for r in rep.pbh)


@pytest.mark.ros
def test_core_package_exports_and_stays_ros_free():
    import importlib
    import pkgutil
    import subprocess
    import sys

    import observer_ros.core as core
    missing = [name for name in core.__all__ if not hasattr(core, name)]
    assert not missing
    for name in ('observability_report', 'observer_gain', 'design_vehicle', 'Plant',
                 'NotDetectableError', 'ObserverDesignWarning', 'Vehicle'):
        assert name in core.__all__
    # each exported name is the object a submodule exports under that name
    subs = [importlib.import_module(m.name)
            for m in pkgutil.walk_packages(core.__path__, 'observer_ros.core.')]
    for name in core.__all__:
        assert any(name in getattr(sub, '__all__', ())
                   and getattr(sub, name) is getattr(core, name) for sub in subs), name
    # every module of the core, imported in a fresh interpreter, imports no ROS
    code = ('import importlib, pkgutil, sys, observer_ros.core as core; '
            'names = [m.name for m in '
            'pkgutil.walk_packages(core.__path__, "observer_ros.core.")]; '
            'assert len(names) > 40, names; '
            '[importlib.import_module(name) for name in names]; '
            'bad = [m for m in sys.modules if m.split(".")[0] in ("rclpy", "rosbags")]; '
            'assert not bad, bad')
    subprocess.run([sys.executable, '-c', code], check=True)


@pytest.mark.ros
def test_core_package_imports_a_submodule_when_one_of_its_names_is_asked_for():
    import subprocess
    import sys

    code = ('import sys, observer_ros.core as core; '
            'loaded = [m for m in sys.modules if m.startswith("observer_ros.core.")]; '
            'assert loaded == ["observer_ros.core._lazy"], loaded; '
            'assert "scipy" not in sys.modules; '
            'from observer_ros.core import Plant; '
            'assert "observer_ros.core.model" in sys.modules; '
            'assert "observer_ros.core.vehicle_design" not in sys.modules; '
            'assert core.analysis.obsv is core.obsv; '
            'from observer_ros.core import *; '
            'assert callable(design_vehicle) and HISTORY_LENGTH == core.spec.HISTORY_LENGTH; '
            'assert not hasattr(core, "no_such_name")')
    subprocess.run([sys.executable, '-c', code], check=True)
    # the admission (read by the vehicle's schema) without the observers and their designs
    code = ('import sys, observer_ros.core.estimators.admission; '
            'assert "observer_ros.core.estimators.full_order" not in sys.modules; '
            'assert "observer_ros.core.design" not in sys.modules; '
            'from observer_ros.core.estimators import History, admission, placement; '
            'import observer_ros.core as core; '
            'assert core.History is History and "observer_ros.core.design" in sys.modules')
    subprocess.run([sys.executable, '-c', code], check=True)
