# test_core_innovation: per-sensor NIS and whiteness of the residuals.
"""Tests of observer_ros.core.innovation against scipy and on a faulty sensor."""

import late_sensors
import numpy as np
from numpy.testing import assert_allclose
from observer_ros.core.estimators import make_estimator
from observer_ros.core.innovation import (InnovationMonitor, ljung_box, nis_bounds,
                                          sequence_health, whiten)
from observer_ros.evaluation.evaluator import whiteness
from observer_ros.timeutil import ns_to_sec
import pytest
import scipy.stats


def test_whiten_gives_the_nis():
    rng = np.random.default_rng(0)
    M = rng.normal(size=(3, 3))
    S = M @ M.T + 0.1 * np.eye(3)
    r = rng.normal(size=3)
    e = whiten(r, S)
    assert e @ e == pytest.approx(r @ np.linalg.solve(S, r), rel=1e-12)


def test_nis_bounds_are_the_chi_square_quantiles():
    low, high = nis_bounds(50, 2, alpha=1e-3)
    assert low == pytest.approx(scipy.stats.chi2.ppf(5e-4, 100) / 50, rel=1e-9)
    assert high == pytest.approx(scipy.stats.chi2.ppf(1 - 5e-4, 100) / 50, rel=1e-9)


def test_ljung_box_agrees_with_the_evaluation():
    x = np.random.default_rng(1).normal(size=400)
    x[1:] += 0.5 * x[:-1]                       # correlated
    q, p = ljung_box(x, lags=20)
    ref = whiteness(x, lags=20)                 # one formula: the evaluation calls ours
    assert q == pytest.approx(ref['ljung_box_q'], rel=1e-12)
    assert p == pytest.approx(ref['ljung_box_p'], rel=1e-9, abs=1e-300)
    # against the textbook statistic: numpy's correlation and scipy's chi-square
    d = x - x.mean()
    full = np.correlate(d, d, mode='full')[d.size - 1:]
    rho = full[1:21] / full[0]
    assert_allclose(ref['acf'], rho, rtol=1e-12)
    want = 400 * 402 * np.sum(rho ** 2 / (400 - np.arange(1, 21)))
    assert q == pytest.approx(want, rel=1e-12)
    assert p == pytest.approx(scipy.stats.chi2.sf(want, 20), rel=1e-9, abs=1e-300)
    assert p < 1e-3
    _, p_white = ljung_box(np.random.default_rng(2).normal(size=400), lags=20)
    assert p_white > 1e-3


def _run(tmp_path, faults=None, pitch_noise=late_sensors.PITCH_NOISE):
    """Kalman on the two-sensor submarine: feed the monitor each sensor's residual."""
    veh = late_sensors.vehicle(tmp_path, 'kalman', pitch_noise)
    msgs, _ = late_sensors.messages(veh, steps=2000, process_noise=True, seed=3, faults=faults)
    est = make_estimator(veh.plant, veh.observer)
    monitor = InnovationMonitor([(s.name, s.noise_std) for s in veh.sensors], kalman=True)
    E = {'gyro': [], 'pitch': []}
    for kind, ns, _, value in late_sensors.stamp_order(msgs):
        if kind == 'u':
            est.set_input(ns_to_sec(ns), [value])
            continue
        est.correct(ns_to_sec(ns), [value], (0,) if kind == 'gyro' else (1,))
        S = est.innovation_covariance
        monitor.add(kind, est.residual, S)
        if S is not None:
            E[kind].append(whiten(est.residual, S))
    return monitor, E


def test_a_consistent_kalman_filter_is_reported_consistent(tmp_path):
    monitor, E = _run(tmp_path)
    for health in monitor.report():
        assert health.consistent, health.problem
        assert health.nis_low <= health.nis_mean <= health.nis_high
    for name in ('gyro', 'pitch'):
        # NIS averages 1 per output after the initial transient
        nis = np.sum(np.array(E[name][100:]) ** 2, axis=1)
        assert 0.8 < nis.mean() < 1.25, (name, nis.mean())
        # as the evaluation judges it: only the first window (the transient) may be off
        assert sequence_health(name, np.array(E[name]), True)['windows_inconsistent'] <= 1


def _judged(tmp_path, faults):
    monitor, E = _run(tmp_path, faults=faults)
    return ({h.name: h for h in monitor.report()},
            {k: sequence_health(k, np.array(v), True) for k, v in E.items()})


def test_a_pitch_bias_is_named(tmp_path):
    # 0.1 rad (10 sigma) from step 1000 on: the windows after it are inconsistent (the
    # filter then absorbs the offset into theta); the gyro stays consistent
    _, figures = _judged(tmp_path, {'pitch': (1.0, 0.1, 1000)})
    assert figures['pitch']['windows_inconsistent'] >= 3
    assert figures['pitch']['problem'].startswith('pitch: residuals too large')
    assert figures['gyro']['windows_inconsistent'] == 0


def test_a_flipped_pitch_axis_is_named(tmp_path):
    health, figures = _judged(tmp_path, {'pitch': (-1.0, 0.0, 1000)})
    assert not health['pitch'].consistent
    assert health['pitch'].problem.startswith('pitch: ')
    assert health['gyro'].consistent
    assert figures['gyro']['windows_inconsistent'] == 0


def test_other_observers_use_the_sensor_noise():
    monitor = InnovationMonitor([('gyro', [0.1])], kalman=False, window=10)
    for _ in range(10):
        monitor.add('gyro', [0.2])                      # NIS 4: under 10 x the bound
    assert monitor.health('gyro').consistent
    assert_allclose(monitor.health('gyro').nis_mean, 4.0)
    for _ in range(10):
        monitor.add('gyro', [2.0])                      # NIS 400
    h = monitor.health('gyro')
    assert not h.consistent and 'gyro: residuals too large' in h.problem
    # a zero noise_std cannot whiten: nothing is counted
    quiet = InnovationMonitor([('enc', [0.0])], kalman=False, window=10)
    quiet.add('enc', [1.0])
    assert quiet.health('enc').samples == 0


def test_one_output_is_whitened_as_by_cholesky():
    # a single output skips the Cholesky factorisation (per message in the node): the
    # same figures as whiten(); a non-positive S is not counted, as whiten() refuses it
    rng = np.random.default_rng(5)
    fast = InnovationMonitor([('gyro', [0.1])], kalman=True, window=10)
    E = []
    for _ in range(10):
        r, S = rng.normal(size=1), np.array([[rng.uniform(0.5, 2.0)]])
        fast.add('gyro', r, S)
        E.append(whiten(r, S))
    fast.add('gyro', [1.0], np.array([[0.0]]))
    fast.add('gyro', [1.0], np.array([[-1.0]]))
    h = fast.health('gyro')
    assert h.samples == 10
    assert h.nis_mean == pytest.approx(float(np.mean(np.sum(np.array(E) ** 2, axis=1))),
                                       rel=1e-12)
