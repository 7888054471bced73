# test_core_simulate: the exact plant simulator used by the tests and the simulator node.
"""Tests of observer_ros.core.simulate.PlantSimulator."""

import numpy as np
from numpy.testing import assert_allclose
from observer_ros.core.errors import DimensionError, ObserverError
from observer_ros.core.estimators import process_noise_covariance
from observer_ros.core.model import Plant
from observer_ros.core.simulate import PlantSimulator
from plants import submarine
import pytest
import scipy.integrate


def imu_pitch():
    return Plant([[-1.2, 1.0], [-4.0, -1.5]], [[-0.2], [-8.0]], [[0.0, 1.0], [-1.2, 0.0]],
                 [[0.0], [-0.2]])


def test_step_is_the_exact_solution_with_held_input():
    plant = submarine()
    sim = PlantSimulator(plant, x0=[0.5, 0.1, -0.2])
    x = np.array([0.5, 0.1, -0.2])
    rng = np.random.default_rng(0)
    dts = rng.uniform(0.01, 0.5, 8)
    for dt, u in zip(dts, rng.normal(size=8)):
        def f(_, xx, u=u):
            return plant.A @ xx + plant.B[:, 0] * u
        x = scipy.integrate.solve_ivp(f, (0.0, dt), x, rtol=1e-12, atol=1e-14).y[:, -1]
        assert_allclose(sim.step([u], dt), x, rtol=1e-9, atol=1e-12)
    assert sim.t == pytest.approx(np.sum(dts))


def test_time_and_held_input():
    sim = PlantSimulator(submarine(), t0=2.0)
    sim.step([0.3], 0.1)
    x1 = sim.step(None, 0.1)             # keeps u = 0.3
    assert sim.t == pytest.approx(2.2)
    assert_allclose(sim.u, [0.3])
    other = PlantSimulator(submarine(), t0=2.0)
    other.step([0.3], 0.2)
    assert_allclose(x1, other.x, rtol=1e-12, atol=1e-15)


def test_measure_uses_the_held_input_and_rows():
    plant = imu_pitch()
    sim = PlantSimulator(plant, x0=[0.2, -0.1])
    assert_allclose(sim.measure(), plant.C @ [0.2, -0.1])           # u = 0 so far
    sim.step([0.5], 0.05)
    y = sim.measure()
    assert_allclose(y, plant.C @ sim.x + plant.D @ [0.5])
    assert_allclose(sim.measure([1]), y[1:])
    with pytest.raises(DimensionError, match='out of range'):
        sim.measure([2])


def test_discrete_plant_steps_by_whole_samples():
    plant = submarine().discretize(0.1)
    a = PlantSimulator(plant, x0=[0.5, 0, 0])
    b = PlantSimulator(plant, x0=[0.5, 0, 0])
    a.step([0.2])
    a.step([0.2])
    b.step([0.2], 0.2)
    assert_allclose(a.x, b.x, rtol=1e-13)
    assert_allclose(a.x, plant.A @ (plant.A @ [0.5, 0, 0] + plant.B[:, 0] * 0.2)
                    + plant.B[:, 0] * 0.2, rtol=1e-13)
    with pytest.raises(ObserverError, match='not a whole number of samples'):
        a.step([0.0], 0.15)


def test_measurement_noise_statistics_and_seed():
    plant = imu_pitch()
    std = np.array([0.02, 0.5])
    sim = PlantSimulator(plant, seed=3, measurement_noise_std=std)
    ys = np.array([sim.measure() for _ in range(20000)])
    assert_allclose(ys.std(axis=0), std, rtol=0.03)
    assert np.all(np.abs(ys.mean(axis=0)) < 4 * std / np.sqrt(20000))
    again = PlantSimulator(plant, seed=3, measurement_noise_std=std)
    assert np.array_equal(again.measure(), ys[0])
    other = PlantSimulator(plant, seed=4, measurement_noise_std=std)
    assert not np.array_equal(other.measure(), ys[0])
    assert np.array_equal(sim.measure(noise=False), plant.C @ sim.x)


def test_process_noise_has_the_van_loan_covariance():
    plant = imu_pitch()
    wstd = np.array([0.3, 1.0])
    dt = 0.1
    sim = PlantSimulator(plant, rng=np.random.default_rng(5), process_noise_std=wstd)
    xs = []
    for _ in range(20000):
        sim.reset()
        xs.append(sim.step([0.0], dt))
    emp = np.cov(np.array(xs).T, bias=True)
    Qd = process_noise_covariance(plant.A, np.diag(wstd ** 2), dt)
    assert_allclose(np.diag(emp), np.diag(Qd), rtol=0.05)
    assert emp[0, 1] == pytest.approx(Qd[0, 1], abs=0.05 * np.sqrt(Qd[0, 0] * Qd[1, 1]))


def test_process_noise_is_an_intensity_independent_of_the_step():
    # Ten steps of 0.01 s add the same covariance as one step of 0.1 s.
    plant = imu_pitch()
    wstd = np.array([0.3, 1.0])
    fine = PlantSimulator(plant, seed=6, process_noise_std=wstd)
    coarse = PlantSimulator(plant, seed=7, process_noise_std=wstd)
    a, b = [], []
    for _ in range(8000):
        fine.reset()
        coarse.reset()
        for _ in range(10):
            fine.step([0.0], 0.01)
        a.append(fine.x)
        b.append(coarse.step([0.0], 0.1))
    assert_allclose(np.var(a, axis=0), np.var(b, axis=0), rtol=0.08)


def test_argument_errors():
    plant = submarine()
    with pytest.raises(DimensionError, match='x0 has 2 elements; expected 3'):
        PlantSimulator(plant, x0=[0.0, 1.0])
    with pytest.raises(DimensionError, match='measurement_noise_std has 2 elements; expected 1'):
        PlantSimulator(plant, measurement_noise_std=[0.1, 0.2])
    with pytest.raises(DimensionError, match='negative'):
        PlantSimulator(plant, process_noise_std=[0.1, -0.2, 0.0])
    sim = PlantSimulator(plant)
    with pytest.raises(ObserverError, match='dt is required'):
        sim.step([0.0])
    with pytest.raises(DimensionError, match='u has 2 elements; expected 1'):
        sim.step([0.0, 1.0], 0.1)
    with pytest.raises(ObserverError, match='positive'):
        sim.step([0.0], -0.1)


def test_reset():
    sim = PlantSimulator(submarine(), x0=[0.5, 0, 0], t0=1.0)
    sim.step([1.0], 0.3)
    sim.reset()
    assert_allclose(sim.x, [0.5, 0, 0])
    assert sim.t == 1.0
    assert_allclose(sim.u, [0.0])
    sim.reset([1.0, 2.0, 3.0], t0=0.0)
    assert_allclose(sim.x, [1.0, 2.0, 3.0])
    assert sim.t == 0.0


def test_process_noise_factor_is_the_exact_step_covariance():
    """The node simulator and PlantSimulator add w with Qd(dt) (continuous) or W (discrete)."""
    from observer_ros.core.simulate import process_noise_factor
    A = np.array([[0.0, 1.0], [-2.0, -0.5]])
    plant = Plant(A, np.array([[0.0], [1.0]]), np.eye(2), np.zeros((2, 1)))
    wstd = np.array([0.1, 0.3])
    for dt in (0.001, 0.05):
        S = process_noise_factor(plant, wstd, dt)
        Q = process_noise_covariance(A, np.diag(wstd ** 2), dt)
        assert_allclose(S @ S.T, Q, rtol=1e-10, atol=1e-15)
        # an intensity: the covariance of a step grows with the step, about W dt
        assert_allclose(np.diag(Q), wstd ** 2 * dt, rtol=0.1)
    discrete = Plant(0.9 * np.eye(2), np.array([[0.0], [1.0]]), np.eye(2), np.zeros((2, 1)),
                     dt=0.1)
    S = process_noise_factor(discrete, wstd, 0.1)
    assert_allclose(S @ S.T, np.diag(wstd ** 2), atol=1e-15)
    S2 = process_noise_factor(discrete, wstd, 0.2, samples=2)
    assert_allclose(S2 @ S2.T, np.diag(wstd ** 2) * (1 + 0.81), atol=1e-15)
