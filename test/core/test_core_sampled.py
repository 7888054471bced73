# test/core/test_core_sampled.py: the sampled gains the loop runs are verified.
"""
Per-step gains pass the achieved-pole check; design_vehicle checks them at the sensor rates.

Covers the gap left by core/verify.py: the observer node corrects with gains designed per
sampled step and set of outputs (core/estimators), which must be verified too, and with
sensors at different rates the product of the per-step error maps must be stable.

"""

import re
import warnings

import late_sensors
import numpy as np
from numpy.testing import assert_allclose
from observer_ros.core.design import observer_gain
from observer_ros.core.errors import DesignVerificationError
from observer_ros.core.estimators import FullOrderEstimator, make_estimator, placement
from observer_ros.core.estimators.sampled import check_sampled_observer, sensor_pattern
from observer_ros.core.model import Plant
from observer_ros.core.spec import (ControllerSpec, ObserverSpec, SensorSpec, SimulatorSpec,
                                    Vehicle)
from observer_ros.core.vehicle_design import design_vehicle
from observer_ros.core.vehicle_report import to_json_dict
from observer_ros.core.verify import verify_placement
from observer_ros.vehicle import load_vehicle
import pytest

# A random 14-state plant with one output whose continuous observer design passes
# core/verify.py, while the gain of every sampled step (z = exp(s h), clustered near 1)
# lands a pole outside the unit circle: it passed observer-design and blew up in the loop.
N14, SEED14 = 14, 2
POLES14 = -np.linspace(1.0, 2.0, N14)


def _plant14():
    rng = np.random.default_rng(SEED14)
    A = rng.standard_normal((N14, N14))
    B = rng.standard_normal((N14, 1))
    C = rng.standard_normal((1, N14))
    return Plant(A, B, C, None, None, tuple(f'x{i}' for i in range(N14)), ('u',), ('y',))


def _vehicle14(rate_hz):
    plant = _plant14()
    sensor = SensorSpec('s', 'y', 'sensor_msgs/msg/JointState', ('position.y',), ('y',),
                        np.array([0.01]))
    return Vehicle('v14', plant, (sensor,), ObserverSpec('full', poles=POLES14),
                   ControllerSpec(), SimulatorSpec(rate_hz, np.zeros(N14)))


def test_a_sampled_gain_that_fails_verification_refuses_the_vehicle():
    plant = _plant14()
    with warnings.catch_warnings():
        warnings.simplefilter('ignore')
        # the continuous design alone passes core/verify.py ...
        L = observer_gain(plant.A, plant.C, POLES14)
        norm = np.linalg.norm(plant.A, 2) + np.linalg.norm(L, 2) * np.linalg.norm(plant.C, 2)
        assert verify_placement(plant.A - L @ plant.C, POLES14, 'observer.poles',
                                norm).within_bound
        # ... the sampled gain the loop would run does not: the vehicle is refused
        with pytest.raises(DesignVerificationError) as err:
            design_vehicle(_vehicle14(100.0))
    msg = str(err.value)
    assert '\n' not in msg
    assert msg.startswith("observer.poles at the sampled step h = 0.01 s with outputs ['y']")
    # where the pole lands depends on the BLAS's rounding in this ill-conditioned
    # placement (1.08776 on one host, 1.05416 on another): outside the unit circle on both
    landed = re.search(r'lands at ([0-9.]+) \(unstable', msg)
    assert landed and float(landed.group(1)) > 1.0 and 'Kalman' in msg, msg


def test_a_refused_step_gain_is_never_used_at_run_time():
    with warnings.catch_warnings():
        warnings.simplefilter('ignore')
        est = FullOrderEstimator(_plant14(), poles=POLES14, x0=np.full(N14, 0.1))
        rng = np.random.default_rng(0)
        est.correct(0.0, [0.3], (0,))
        for k in range(1, 6):
            t = k * 1e-2
            before = est.predict(t)
            est.correct(t, [rng.standard_normal()], (0,))
            # prediction only: the correction with the refused gain is skipped
            assert_allclose(est.x_hat, before, rtol=0.0, atol=0.0)
        assert est.unverified_corrections == 5
        (_, rows), reason = next(iter(est.gain_failures.items()))
        assert rows == (0,) and 'observer.poles at the sampled step' in reason
        with pytest.raises(DesignVerificationError, match='does not place pole'):
            est.error_matrix(1e-2)
        with pytest.raises(DesignVerificationError):
            est.correction_gain(1e-2)


def test_every_step_gain_is_verified(tmp_path):
    calls = []
    real = placement.verify_placement

    def spy(M, requested, field, perturbation, discrete=False):
        calls.append(field)
        return real(M, requested, field, perturbation, discrete)

    veh = late_sensors.vehicle(tmp_path, 'full')
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(placement, 'verify_placement', spy)
        est = make_estimator(veh.plant, veh.observer)
        F = est.error_matrix(0.01, (0,))
        est.error_matrix(0.01, (0,))          # cached: not designed again
        est.error_matrix(0.05, (0, 1))
    at = 'observer.poles at the sampled step h = {} s with outputs {}'
    assert calls == [at.format(0.01, ['q']), at.format(0.05, ['q', 'theta'])]
    assert_allclose(np.sort(np.abs(np.linalg.eigvals(F))),
                    np.exp(np.array([-0.8, -0.7, -0.6]) * 0.01), rtol=1e-9)


def test_several_outputs_place_poles_once(monkeypatch):
    # the quick path's place_poles gain is python-control's place: not computed twice
    rng = np.random.default_rng(1)
    A, C = rng.standard_normal((6, 6)), rng.standard_normal((2, 6))
    z = np.exp(-np.linspace(1.0, 3.0, 6) * 0.01)
    calls = []
    real = placement._place_poles
    monkeypatch.setattr(placement, '_place_poles', lambda *a: calls.append(1) or real(*a))
    monkeypatch.setattr(placement, 'QUICK_PLACE_TOL', 0.0)   # never "accurate"

    def no_full_design(*args, **kwargs):
        raise AssertionError('observer_gain called')

    monkeypatch.setattr(placement, 'observer_gain', no_full_design)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter('always')
        M = placement.place(A, C, z, 'auto')
    # scipy's Tits-Yang stops here without converging: its warning is not passed on
    assert not [w for w in caught if 'Convergence' in str(w.message)]
    assert len(calls) == 1
    assert_allclose(np.sort(np.linalg.eigvals(A - M @ C).real), np.sort(z), atol=1e-9)


# ---------------------------------------------------------------- multi-rate sensors


def _two_sensor(tmp_path, poles):
    path = late_sensors.write_vehicle(tmp_path, 'full', design=f'poles: {poles}')
    return load_vehicle(path)


def _final_theta_error(veh, seconds=30.0):
    msgs, truth = late_sensors.messages(veh, steps=int(seconds * 100), commands=False)
    est = make_estimator(veh.plant, veh.observer)
    for kind, ns, _, value in late_sensors.stamp_order(msgs):
        if kind != 'u':
            est.correct(ns * 1e-9, [value], (0,) if kind == 'gyro' else (1,))
    return abs(est.x_hat[0] - truth[-1][1][0])


def test_sensor_pattern_of_the_two_sensor_submarine(tmp_path):
    veh = late_sensors.vehicle(tmp_path, 'full')
    steps, events = sensor_pattern(veh)
    assert steps == 5
    pattern = [(j, rows) for j, rows, _ in events]
    assert pattern == [(1, (0,)), (2, (0,)), (3, (0,)), (4, (0,)), (5, (0, 1))]
    assert events[-1][2] == ('gyro', 'pitch')


def test_multi_rate_observer_whose_period_map_grows_is_refused(tmp_path):
    veh = _two_sensor(tmp_path, '[-2.0, -2.1, -2.2]')
    with pytest.raises(DesignVerificationError) as err:
        design_vehicle(veh)
    msg = str(err.value)
    assert '\n' not in msg
    assert msg.startswith('observer.poles: with sensors gyro (100 Hz), pitch (20 Hz)')
    assert 'spectral radius 1.02 ' in msg and 'observer.type: kalman' in msg
    # the refusal is right: run in stamp order, the same observer diverges (the initial
    # theta error is 0.5) ...
    assert _final_theta_error(veh) > 50.0
    # ... while on the gyro alone (one rate) the same poles are accepted
    gyro_only = late_sensors.VEHICLE_YAML.replace('names: [gyro, pitch]', 'names: [gyro]') \
        .replace('outputs: [q, theta]', 'outputs: [q]') \
        .replace('C: [0.0, 0.0, 1.0, 1.0, 0.0, 0.0]', 'C: [0.0, 0.0, 1.0]')
    path = tmp_path / 'gyro_only.yaml'
    path.write_text(gyro_only.format(observer_type='full', pitch_noise=0.01,
                                     observer_design='poles: [-2.0, -2.1, -2.2]'))
    one = design_vehicle(load_vehicle(path))
    assert one.sampled.sensors == ('gyro',)
    assert one.sampled.spectral_radius == pytest.approx(np.exp(-2.0 * 0.01), rel=1e-9)


def test_what_the_refusal_offers_works(tmp_path):
    # Kalman (any pattern) and slower poles are accepted and converge in the same run
    kalman = late_sensors.vehicle(tmp_path, 'kalman')
    assert design_vehicle(kalman).sampled is None
    assert _final_theta_error(kalman) < 0.05
    slow = late_sensors.vehicle(tmp_path, 'full')
    design = design_vehicle(slow)
    check = design.sampled
    assert check.spectral_radius == pytest.approx(0.9835, abs=1e-3)
    assert [c[1] for c in check.corrections] == [('q',)] * 4 + [('q', 'theta')]
    assert not any('sampled observer' in w for w in design.warnings)
    assert to_json_dict(design)['placement']['sampled']['spectral_radius'] == \
        check.spectral_radius
    assert _final_theta_error(slow) < 0.05


def test_a_slow_multi_rate_period_map_is_a_warning(tmp_path):
    veh = _two_sensor(tmp_path, '[-1.0, -1.1, -1.2]')
    check, messages = check_sampled_observer(veh)
    assert check.spectral_radius < 1.0
    assert len(messages) == 1
    assert 'decays at 0.278/s' in messages[0] and 'designed 1/s' in messages[0]
    assert messages[0] in design_vehicle(veh).warnings
