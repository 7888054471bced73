"""Every design is verified before it is used: findings, rule, property tests."""

import json
from pathlib import Path
import warnings

import control
from hypothesis import given, HealthCheck, settings, strategies as st
import numpy as np
from numpy.testing import assert_allclose
from observer_ros.core import pole_placement
from observer_ros.core.analysis import observability_report
from observer_ros.core.design import kalman_gain, kalman_update_gain
from observer_ros.core.errors import (DesignVerificationError, DimensionError, ObserverError,
                                      VehicleFileError)
from observer_ros.core.model import Plant
from observer_ros.core.spec import (ControllerSpec, ObserverSpec, SensorSpec, SimulatorSpec,
                                    Vehicle)
from observer_ros.core.vehicle_design import design_vehicle, measurement_intensity
from observer_ros.core.vehicle_report import to_json_dict
from observer_ros.core.verify import eigenvalue_bounds, stability_status, unstable_eigenvalues
from observer_ros.tools import design_report
from observer_ros.vehicle import load_vehicle, parameters_to_yaml, vehicle_to_parameters
import pytest

SUBMARINE = str(Path(__file__).resolve().parents[2] / 'config' / 'submarine.yaml')


def vehicle(A, B, C, observer, controller, dt=None):
    A, B, C = (np.atleast_2d(np.asarray(M, dtype=float)) for M in (A, B, C))
    n, m, p = A.shape[0], B.shape[1], C.shape[0]
    plant = Plant(A, B, C, None, dt, tuple(f'x{i + 1}' for i in range(n)),
                  tuple(f'u{i + 1}' for i in range(m)), tuple(f'y{i + 1}' for i in range(p)))
    sensors = tuple(SensorSpec(f's{i}', f's{i}/data', 'std_msgs/msg/Float64', ('data',),
                               (plant.output_names[i],), np.array([0.01]))
                    for i in range(p))
    return Vehicle('random', plant, sensors, observer, controller,
                   SimulatorSpec(100.0, np.zeros(n)))


def random_plant(n, m, p, seed):
    rng = np.random.default_rng(seed)
    return (rng.standard_normal((n, n)) / np.sqrt(n), rng.standard_normal((n, m)),
            rng.standard_normal((p, n)))


def design_quietly(v):
    with warnings.catch_warnings():
        warnings.simplefilter('ignore')
        return design_vehicle(v)


def run_tool(tmp_path, capsys, v, *extra):
    path = tmp_path / 'vehicle.yaml'
    path.write_text(parameters_to_yaml(vehicle_to_parameters(v)))
    rc = design_report.main([str(path), *extra])
    out, err = capsys.readouterr()
    return rc, out, err


# ---------------------------------------------------------------- finding 1


def test_finding1_unstable_controller_placement_refused(tmp_path, capsys):
    A, B, C = random_plant(20, 1, 1, 0)
    v = vehicle(A, B, C, ObserverSpec('open_loop'),
                ControllerSpec(poles=-1.0 - 0.1 * np.arange(20)))
    with pytest.raises(DesignVerificationError, match=r'^controller\.poles: .*lands at '
                       r'[0-9.]+ \(unstable.*LQR'):
        design_quietly(v)
    rc, out, err = run_tool(tmp_path, capsys, v, '--json')
    assert rc == 2 and out == ''
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith('error: controller.poles: ')


def test_finding1_observer_placement_refused():
    A, B, C = random_plant(14, 1, 1, 0)
    v = vehicle(A, B, C, ObserverSpec('full', poles=-1.0 - 0.05 * np.arange(14)),
                ControllerSpec())
    with pytest.raises(DesignVerificationError, match=r'^observer\.poles: .*Kalman'):
        design_quietly(v)


def test_given_gains_use_the_same_rule():
    A = np.array([[0.0, 1.0], [0.0, 0.0]])
    B = np.array([[0.0], [1.0]])
    C = np.array([[1.0, 0.0]])
    v = vehicle(A, B, C, ObserverSpec('full', gain=np.array([[1.0], [0.0]])),
                ControllerSpec())
    with pytest.raises(DesignVerificationError, match='observer.gain does not stabilize'):
        design_quietly(v)
    v = vehicle(A, B, C, ObserverSpec('open_loop'), ControllerSpec(K=np.array([[1.0, 0.0]])))
    with pytest.raises(DesignVerificationError, match=r'controller\.K .*marginally stable'):
        design_quietly(v)


# ---------------------------------------------------------------- finding 2


def test_finding2_kalman_with_noise_input_matrix():
    A, B, C = random_plant(4, 1, 2, 3)
    A = A - 2.0 * np.eye(4)
    Bd = np.random.default_rng(4).standard_normal((4, 2))
    Qd = np.array([[2.0, 0.3], [0.3 + 1e-13, 1.0]])        # asymmetric by round-off
    Rd = np.diag([0.01, 0.02])
    v = vehicle(A, B, C, ObserverSpec('kalman', Qd=Qd, Rd=Rd, Bd=Bd), ControllerSpec())
    d = design_quietly(v)
    Qn = Bd @ ((Qd + Qd.T) / 2) @ Bd.T
    # Rd per sample: the continuous design sees the intensity Rd h (vehicle_design)
    L_ref, P_ref, _ = control.lqe(A, np.eye(4), C, (Qn + Qn.T) / 2, Rd * v.sample_time)
    assert_allclose(d.L, L_ref, rtol=1e-9, atol=1e-12)
    assert_allclose(d.P, P_ref, rtol=1e-9, atol=1e-12)


def test_finding2_loader_symmetrises_or_names_the_field():
    def load(qd):
        return load_vehicle(SUBMARINE, overrides=[
            'observer.type:=kalman', 'observer.poles:=null', f'observer.Qd:={qd}',
            'observer.Rd:=[1e-06]'])
    v = load('[1.0, 0.2, 0.0, 0.20000000000001, 1.0, 0.0, 0.0, 0.0, 1.0]')
    assert np.array_equal(v.observer.Qd, v.observer.Qd.T)
    design_quietly(v)
    with pytest.raises(VehicleFileError, match=r'observer\.Qd: must be symmetric'):
        load('[1.0, 0.2, 0.0, 0.3, 1.0, 0.0, 0.0, 0.0, 1.0]')


# ---------------------------------------------------------------- finding 3


def test_finding3_controller_poles_on_a_stabilizable_plant():
    A = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
    B = np.array([[0.0], [1.0], [0.0]])                   # x3 (-1) not controllable
    C = np.array([[1.0, 0.0, 1.0]])
    obs = ObserverSpec('full', poles=np.array([-4.0, -5.0, -6.0]))
    d = design_quietly(vehicle(A, B, C, obs, ControllerSpec(poles=np.array([-2.0, -3.0]))))
    assert_allclose(np.sort(d.controller_poles.real), [-3.0, -2.0, -1.0], atol=1e-9)
    assert d.controller_placement.max_error < 1e-9
    with pytest.raises(DimensionError, match=r'controller\.poles: poles has 3 poles; '
                       r'expected 2.*eigenvalue -1 \(stable\): x3'):
        design_quietly(vehicle(A, B, C, obs, ControllerSpec(poles=np.array([-2.0, -3, -4]))))


# ---------------------------------------------------------------- finding 4


def test_finding4_stability_is_relative_to_each_eigenvalue():
    A = np.diag([-1e6, -5e-4])
    rep = observability_report(A, [[1.0, 0.0]])
    assert rep.detectable and rep.modes[0].status == 'stable'
    assert unstable_eigenvalues(A) == []
    lam, b = eigenvalue_bounds(A)
    assert np.all(b < 1e-8)
    # an integrator computed as +-1e-17 stays marginal
    lam, b = eigenvalue_bounds([[0.0, 1.0], [0.0, -1.0]])
    assert stability_status(-1e-17, b[np.argmin(np.abs(lam))]) == 'marginally stable'
    assert stability_status(1e-3, 1e-9) == 'unstable'


def test_finding4_slow_observer_pole_one_verdict():
    A = np.array([[0.0, 1.0], [0.0, 0.0]])
    B = np.array([[0.0], [1.0]])
    C = np.array([[1.0, 0.0]])
    d = design_quietly(vehicle(A, B, C, ObserverSpec('full', poles=np.array([-1e-12, -1.0])),
                               ControllerSpec()))
    assert not any('not stable' in w for w in d.warnings)
    assert d.observer_placement.within_bound


# ---------------------------------------------------------------- finding 5


def test_finding5_closed_loop_poles_are_the_union():
    A, B, C = random_plant(5, 1, 1, 7)
    ctrl = np.array([-1.0, -1.5, -2.0, -2.5, -3.0])
    obs = ctrl * 3.0
    d = design_quietly(vehicle(A, B, C, ObserverSpec('full', poles=obs),
                               ControllerSpec(poles=ctrl)))
    assert_allclose(np.sort(d.closed_loop_poles.real), np.sort(np.concatenate([ctrl, obs])),
                    atol=1e-9)
    data = json.loads(json.dumps(to_json_dict(d)))
    assert data['separation_ok'] is True
    assert 0.0 <= data['separation_error'] <= data['separation_allowed']
    assert data['placement']['controller']['max_error'] < 1e-9


# ---------------------------------------------------------------- property-based


def _poles(draw, k, discrete, complex_ok):
    mags = draw(st.lists(st.floats(0.3, 0.9) if discrete else st.floats(0.5, 6.0),
                         min_size=k, max_size=k, unique=True))
    p = [m if discrete else -m for m in mags]
    if complex_ok and k >= 2 and draw(st.booleans()):
        im = draw(st.floats(0.05, 0.3) if discrete else st.floats(0.2, 3.0))
        p[0], p[1] = complex(p[0], im), complex(p[0], -im)
    return np.array(p, dtype=complex)


@st.composite
def systems(draw):
    n = draw(st.integers(2, 12))
    m = draw(st.integers(1, 3))
    p = draw(st.integers(1, 3))
    discrete = draw(st.booleans())
    seed = draw(st.integers(0, 2 ** 31))
    A, B, C = random_plant(n, m, p, seed)
    if discrete:
        A = A * 0.9 / max(1.0, np.max(np.abs(np.linalg.eigvals(A))))
    kind = draw(st.sampled_from(['full', 'reduced', 'kalman']))
    if kind == 'reduced' and p >= n:
        kind = 'full'
    k = n - p if kind == 'reduced' else n
    obs = ObserverSpec(kind, Qd=np.eye(n), Rd=0.01 * np.eye(p)) if kind == 'kalman' else \
        ObserverSpec(kind, poles=_poles(draw, k, discrete, True))
    ctrl = ControllerSpec(poles=_poles(draw, n, discrete, True))
    return vehicle(A, B, C, obs, ctrl, 0.1 if discrete else None)


def _achieved_ok(poles, discrete):
    poles = np.array([complex(*z) for z in poles])
    return bool(np.all(np.abs(poles) < 1.0)) if discrete else bool(np.all(poles.real < 0))


# The claim holds for any gain the design accepts, however long the robust placement
# searched: capped at 60 iterations (twice python-control's 30, so that the longer search
# stays a candidate of its own), multi-input plants of 7-12 states no longer run it to its
# 300-iteration limit (at that limit the search is 85 % of this test's time).
PROPERTY_ROBUST_MAXITER = 60


@pytest.fixture
def capped_robust_search(monkeypatch):
    monkeypatch.setattr(pole_placement, 'ROBUST_MAXITER', PROPERTY_ROBUST_MAXITER)


@settings(max_examples=30, deadline=None, suppress_health_check=list(HealthCheck))
@given(systems())
def test_property_every_accepted_design_is_verified(capped_robust_search, v):
    try:
        d = design_quietly(v)
    except ObserverError as err:
        text = str(err)
        assert '\n' not in text
        assert text.startswith(('controller.poles', 'observer.poles', '(A, ', 'the plant',
                                'the Kalman', 'reduced-order')), text
        return
    data = json.loads(json.dumps(to_json_dict(d)))
    discrete = v.plant.is_discrete
    A, B, C = v.plant.A, v.plant.B, v.plant.C
    K = np.array(data['K'])
    assert _achieved_ok([[z.real, z.imag] for z in np.linalg.eigvals(A - B @ K)], discrete)
    assert _achieved_ok(data['observer_poles'], discrete)
    for side in ('controller', 'observer'):
        rec = data['placement'][side]
        if rec is not None:
            assert rec['within_bound'] and rec['max_error'] <= rec['bound_at_worst']
    ctrl = data['placement']['controller']
    if data['controllable']:   # recompute: every achieved pole within the stated bound
        got = np.linalg.eigvals(A - B @ K)
        want = v.controller.poles
        off = max(np.min(np.abs(got - w)) for w in want)
        assert off <= ctrl['bound_at_worst'] * (1 + 1e-6) + 1e-12
    if v.observer.kind == 'kalman':
        Rd = v.observer.Rd
        if discrete:
            L_ref, P_ref, _ = control.dlqe(A, np.eye(A.shape[0]), C, v.observer.Qd, Rd)
            M = kalman_update_gain(d.P, C, Rd)
            assert_allclose(A @ M, L_ref, rtol=1e-9, atol=1e-9)     # predictor = A M
        else:
            L_ref, P_ref, _ = control.lqe(A, np.eye(A.shape[0]), C, v.observer.Qd,
                                          measurement_intensity(v))
        assert_allclose(d.L, L_ref, rtol=1e-9, atol=1e-9)
    n = A.shape[0]
    observer_order = d.L.shape[0] if d.reduced is not None else n
    assert len(d.closed_loop_poles) == n + observer_order


def test_kalman_gain_filter_convention_matches_dlqe():
    A, B, C = random_plant(5, 1, 2, 11)
    A = 0.8 * A / np.max(np.abs(np.linalg.eigvals(A)))
    Qd, Rd = np.eye(5), 0.1 * np.eye(2)
    L, P, _ = kalman_gain(A, C, Qd, Rd, discrete=True)
    L_ref, P_ref, _ = control.dlqe(A, np.eye(5), C, Qd, Rd)
    M = kalman_update_gain(P, C, Rd)
    assert_allclose(A @ M, L_ref, rtol=1e-9, atol=1e-12)
    assert_allclose(P, P_ref, rtol=1e-9, atol=1e-12)


# ---------------------------------------------------------------- --sensors


def _cart_two_sensors():
    cart = load_vehicle(str(Path(SUBMARINE).parent / 'cart_pendulum.yaml'))
    A, B = cart.plant.A, cart.plant.B
    C = np.array([[0.0, 1.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]])      # x, theta
    plant = Plant(A, B, C, None, None, cart.plant.state_names, cart.plant.input_names,
                  ('x', 'theta'))
    sensors = tuple(SensorSpec(f's_{o}', f'{o}/data', 'std_msgs/msg/Float64', ('data',), (o,),
                               np.array([1e-3])) for o in ('x', 'theta'))
    sim = SimulatorSpec(100.0, np.zeros(4), process_noise_std=np.full(4, 1e-4))
    return Vehicle('cart2', plant, sensors, ObserverSpec('full', poles=-np.arange(2.0, 6.0)),
                   ControllerSpec(K=np.zeros((1, 4))), sim)


def test_sensors_cart_pendulum_x_suffices_theta_does_not(tmp_path, capsys):
    from observer_ros.core.sensor_subsets import sensor_subsets
    v = _cart_two_sensors()
    subsets = sensor_subsets(v)
    by = {s.outputs: s for s in subsets}
    # observable first, then by the least Ms any controller reaches: with x alone the
    # unstable pole 3.28 and the zero 3.13 force Ms >= 42; theta as well removes the zero
    assert [s.outputs for s in subsets[:2]] == [('x', 'theta'), ('x',)]
    assert by[('x', 'theta')].ms_bound == 1.0 and 41.5 < by[('x',)].ms_bound < 42.5
    assert by[('x',)].observable and by[('x', 'theta')].observable
    assert not by[('theta',)].observable and not by[('theta',)].detectable
    assert any('x' in m for m in by[('theta',)].unobservable_modes)
    assert by[('theta',)].variance is None
    both, alone = by[('x', 'theta')].variance, by[('x',)].variance
    assert np.all(both > 0) and np.all(both <= alone * (1 + 1e-9))   # a sensor more helps
    rc, out, err = run_tool(tmp_path, capsys, v, '--sensors', '--json')
    assert rc == 0, err
    data = json.loads(out)['sensor_subsets']
    assert data[0]['outputs'] == ['x', 'theta'] and data[0]['observable']
    assert data[1]['outputs'] == ['x'] and round(data[1]['ms_bound']) == 42
    assert set(data[1]['kalman_error_variance']) == set(v.plant.state_names)


def test_sensors_example_515_names_the_unobservable_mode(tmp_path, capsys):
    from observer_ros.core.sensor_subsets import sensor_subsets
    # seed 002 Example 5.15: x1' = 2 x1 + 3 u, x2' = -x2, x3' = 5 x3 - u, y = x1 + x2
    A = np.diag([2.0, -1.0, 5.0])
    B = np.array([[3.0], [0.0], [-1.0]])
    C = np.array([[1.0, 1.0, 0.0]])
    v = vehicle(A, B, C, ObserverSpec('open_loop'), ControllerSpec(K=np.zeros((1, 3))))
    (only,) = sensor_subsets(v)
    assert not only.observable and not only.detectable and only.rank == 2
    assert len(only.unobservable_modes) == 1 and 'eigenvalue 5 (unstable): x3' in \
        only.unobservable_modes[0]
    rc, out, _ = run_tool(tmp_path, capsys, v, '--sensors')
    assert rc == 0 and 'NOT detectable' in out and 'eigenvalue 5 (unstable): x3' in out
