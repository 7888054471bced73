# Tests of observer_ros.vehicle (the vehicle-file loader) and observer_ros.sensors.
"""Vehicle files: loading, checking, round trips, overrides, sensor field mapping."""

import array
import math
from pathlib import Path
import types

from hypothesis import given, HealthCheck, settings, strategies as st
import numpy as np
from numpy.testing import assert_allclose
from observer_ros.core.errors import ObserverError, VehicleFileError
from observer_ros.core.spec import SensorSpec
from observer_ros.sensors import (extract_measurement, fill_measurement, MeasurementError,
                                  parse_field)
from observer_ros.vehicle import (apply_overrides, KNOWN_KEYS, load_parameters,
                                  load_vehicle, parameters_to_yaml,
                                  SENSOR_KEYS, vehicle_from_parameters,
                                  vehicle_to_parameters)
from plants import GYRO_C, SUBMARINE_A, SUBMARINE_B
import pytest

ROOT = Path(__file__).resolve().parents[2]
CONFIGS = sorted((ROOT / 'config').glob('*.yaml'))
SUBMARINE = ROOT / 'config' / 'submarine.yaml'


def base(name='submarine'):
    """Flat parameters of one of the config files."""
    return load_parameters(ROOT / 'config' / f'{name}.yaml')


def build(overrides, name='submarine'):
    """Load a config file with overrides (tools' key:=value strings or a dict)."""
    return vehicle_from_parameters(apply_overrides(base(name), overrides),
                                   source=f'{name}.yaml')


# -- the config files ---------------------------------------------------------------------

def test_config_files_exist():
    names = {path.stem for path in CONFIGS}
    assert {'submarine', 'submarine_reduced', 'cart_pendulum', 'cart_pendulum_reduced',
            'pitch_imu', 'aircraft_lateral'} <= names


@pytest.mark.parametrize('path', CONFIGS, ids=lambda p: p.stem)
def test_config_loads_without_warnings(path):
    vehicle = load_vehicle(path)
    assert vehicle.warnings == ()
    assert vehicle.name == path.stem
    assert vehicle.origin == str(path)
    assert vehicle.source   # every file says where its numbers come from
    covered = [out for s in vehicle.sensors for out in s.outputs]
    assert sorted(covered) == sorted(vehicle.plant.output_names)


@pytest.mark.parametrize('path', CONFIGS, ids=lambda p: p.stem)
def test_config_doubles_are_written_as_floats(path):
    """A ROS node would refuse an integer where a double is declared; so do we."""
    flat = load_parameters(path)
    for key, value in flat.items():
        spec = KNOWN_KEYS.get(key) or SENSOR_KEYS.get(key.split('.')[-1])
        if spec is not None and spec.param_type == 'DOUBLE_ARRAY':
            assert all(isinstance(v, float) for v in value), key


def test_submarine_numbers():
    v = load_vehicle(SUBMARINE)
    p = v.plant
    assert p.state_names == ('theta', 'w', 'q')
    assert_allclose(p.A, SUBMARINE_A)
    assert_allclose(p.B, SUBMARINE_B)
    assert_allclose(p.C, GYRO_C)
    assert_allclose(p.D, [[0.0]])
    gyro, = v.sensors
    assert (gyro.msg_type, gyro.fields, gyro.outputs) == (
        'sensor_msgs/msg/Imu', ('angular_velocity.y',), ('q',))
    assert v.observer.kind == 'full'
    assert_allclose(np.sort(v.observer.poles.real), [-0.62, -0.61, -0.6])
    assert_allclose(v.controller.poles.real, [-0.3, -0.31, -0.32])
    assert_allclose(v.simulator.initial_state, [math.radians(30.0), 0.0, 0.0])
    assert v.simulator.rate_hz == 20.0 and v.simulator.duration == 30.0
    assert v.sample_time == 0.05


def test_cart_pendulum_numbers():
    v = load_vehicle(ROOT / 'config' / 'cart_pendulum.yaml')
    poles = np.sort_complex(v.observer.poles)
    assert_allclose(poles, np.sort_complex([-10 + 10j, -10 - 10j, -20 + 20j, -20 - 20j]))
    assert_allclose(v.controller.reference, [0, 1, 0, 0])
    assert_allclose(v.controller.Kd, np.zeros((1, 4)))
    reduced = load_vehicle(ROOT / 'config' / 'cart_pendulum_reduced.yaml')
    assert reduced.observer.kind == 'reduced'
    assert_allclose(np.sort_complex(reduced.observer.poles),
                    np.sort_complex([-20, -20 + 20j, -20 - 20j]))


def test_pitch_imu_has_feedthrough_and_aircraft_is_kalman():
    pitch = load_vehicle(ROOT / 'config' / 'pitch_imu.yaml')
    assert pitch.plant.D[1, 0] != 0.0
    imu, = pitch.sensors
    assert imu.fields == ('angular_velocity.y', 'linear_acceleration.z')
    air = load_vehicle(ROOT / 'config' / 'aircraft_lateral.yaml')
    assert air.observer.kind == 'kalman'
    # Rd defaults to the sensors' noise_std**2, in the order of model.outputs.
    assert_allclose(np.diag(air.observer.Rd), [0.001 ** 2, 0.002 ** 2, 0.002 ** 2])
    assert air.controller.lqr_Q.shape == (7, 7) and air.controller.lqr_R.shape == (2, 2)


def test_base_frame_is_read_with_its_default():
    # the frame of the state messages: the submarine's FRD body, base_link where unstated
    assert load_vehicle(SUBMARINE).base_frame == 'base_link_frd'
    assert load_vehicle(ROOT / 'config' / 'cart_pendulum.yaml').base_frame == 'base_link'
    assert build({'vehicle.base_frame': 'hull'}).base_frame == 'hull'
    assert vehicle_to_parameters(build({'vehicle.base_frame': 'hull'}))[
        'vehicle.base_frame'] == 'hull'
    with pytest.raises(VehicleFileError, match='vehicle.base_frame'):
        build({'vehicle.base_frame': ''})


# -- round trips --------------------------------------------------------------------------

@pytest.mark.parametrize('path', CONFIGS, ids=lambda p: p.stem)
def test_round_trip_through_parameters(path):
    vehicle = load_vehicle(path)
    flat = vehicle_to_parameters(vehicle)
    again = vehicle_from_parameters(flat)
    assert vehicle_to_parameters(again) == flat
    assert again.warnings == ()
    for value in flat.values():   # plain Python values, as ROS parameters are
        assert isinstance(value, (str, bool, int, float, list))


@pytest.mark.parametrize('path', CONFIGS, ids=lambda p: p.stem)
def test_round_trip_through_yaml(path, tmp_path):
    flat = vehicle_to_parameters(load_vehicle(path))
    out = tmp_path / 'variant.yaml'
    out.write_text(parameters_to_yaml(flat))
    assert vehicle_to_parameters(load_vehicle(out)) == flat


def test_parameters_from_rclpy_containers():
    """Nodes may hand over array.array / numpy arrays; they read like lists."""
    flat = base()
    flat['model.A'] = array.array('d', flat['model.A'])
    flat['model.C'] = np.array(flat['model.C'])
    flat['observer.poles'] = tuple(flat['observer.poles'])
    flat['sensors.gyro.timeout'] = np.float64(0.25)
    flat['use_sim_time'] = True      # every node has it: never a warning
    flat['qos_overrides./clock.subscription.depth'] = 1
    v = vehicle_from_parameters(flat)
    assert v.warnings == ()
    assert v.sensors[0].timeout == 0.25
    with pytest.raises(VehicleFileError, match=r'model\.A: integer array'):
        vehicle_from_parameters(dict(flat, **{'model.A': array.array('q', [0] * 9)}))


def test_none_values_count_as_absent():
    v = build({'observer.initial_estimate': None, 'simulator.duration': None})
    assert v.observer.initial_estimate is None
    assert v.simulator.duration == KNOWN_KEYS['simulator.duration'].default


# -- errors: each names its field -----------------------------------------------------------

ERRORS = [
    # shapes and types
    (['model.C:=[0.0, 0.0, 1.0, 0.0]'],
     r'model\.C: has 4 values; expected 3 \(outputs x states = 1x3\)'),
    (['model.A:=[0, 1, 0, 0, 0, 0, 0, 0, 1]'],
     r'model\.A: integer array \[0, 1, .*\]; double arrays must be written as floats'),
    (['model.A:=[0.0, 1, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]'],
     r'model\.A: mixed integer and float array'),
    (['model.A:=[1.0, 2.0, 3.0, 4.0]'], r'model\.A: has 4 values; expected 9 \(states x '
     r'states = 3x3\)'),
    (['model.B:=[0.0, 1.0]'], r'model\.B: has 2 values; expected 3'),
    (['model.D:=[0.0, 0.0]'], r'model\.D: has 2 values; expected 1'),
    (['model.A:=[.nan, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]'], r'model\.A: element 0 is nan'),
    (['model.A:=not a matrix'], r'model\.A: expected a list of floats'),
    (['model.states:=[theta, w, theta]'], r"model\.states: duplicate name 'theta'"),
    (['model.states:=[theta, true, q]'], r'model\.states: expected strings; got boolean'),
    (['model.time_domain:=hybrid'], r"model\.time_domain: 'hybrid' is not one of"),
    (['model.time_domain:=discrete'], r'model\.sample_time: missing \(required\)'),
    (['simulator.duration:=30'], r'simulator\.duration: integer 30; doubles must be written '
     r'as floats \(30\.0, not 30\)'),
    (['simulator.seed:=1.5'], r'simulator\.seed: expected an integer'),
    (['simulator.noise:=1'], r'simulator\.noise: expected true or false'),
    (['vehicle.name:=my sub'], r'vehicle\.name: .* only letters'),
    # missing keys
    (['vehicle.name:=null'], r'vehicle\.name: missing \(required\)'),
    (['model.A:=null'], r'model\.A: missing \(required\)'),
    (['sensors.names:=null'], r'sensors\.names: missing \(required\)'),
    (['sensors.gyro.topic:=null'], r'sensors\.gyro\.topic: missing \(required\)'),
    (['sensors.gyro.noise_std:=null'], r'sensors\.gyro\.noise_std: missing'),
    (['observer.type:=null'], r'observer\.type: missing \(required\)'),
    (['observer.poles:=null'], r'observer\.poles: missing: a full observer needs'),
    (['controller.poles:=null'], r'controller\.poles: missing: give one of'),
    # enums
    (['observer.type:=luenberger'], r"observer\.type: 'luenberger' is not one of \['full', "),
    (['observer.method:=magic'], r"observer\.method: 'magic' is not one of"),
    (['controller.safe_command:=panic'], r'controller\.safe_command:'),
    (['simulator.mode:=fast'], r'simulator\.mode:'),
    (['sensors.gyro.type:=sensor_msgs/msg/Imu2'], r'sensors\.gyro\.type:'),
    # poles and gains
    (['observer.gain:=[1.0, 2.0, 3.0]'], r'observer\.gain: give either observer\.poles or '
     r'observer\.gain, not both'),
    (['observer.poles_imag:=[1.0, -1.0]'], r'observer\.poles_imag: has 2 values; expected 3'),
    (['observer.poles_imag:=[1.0, 0.0, 0.0]'],
     r'observer\.poles: pole -0\.6\+1j has no complex-conjugate partner'),
    (['observer.poles:=[0.6, -0.61, -0.62]'], r'observer\.poles: pole 0\.6 is in the closed '
     r'right half plane'),
    (['observer.poles:=[-1.0, -2.0, -3.0, -4.0]'], r'observer\.poles: has 4 poles; expected '
     r'at most 3'),
    (['observer.poles:=null', 'observer.gain:=[1.0, 2.0]'],
     r'observer\.gain: has 2 values; expected 3 \(states x outputs = 3x1\)'),
    (['observer.poles:=null', 'observer.poles_imag:=[0.0]', 'observer.gain:=[1.0, 2.0, 3.0]'],
     r'observer\.poles_imag: given without observer\.poles'),
    (['controller.poles:=[-1.0, -2.0, -3.0, -4.0]'], r'controller\.poles: has 4 poles; '
     r'expected at most 3'),
    (['controller.poles_imag:=[0.5, 0.0, 0.0]'], r'controller\.poles: pole .*conjugate'),
    (['controller.K:=[1.0, 2.0, 3.0]'], r'controller\.K: give only one of'),
    (['controller.poles:=null', 'controller.K:=[1.0, 2.0]'], r'controller\.K: has 2 values; '
     r'expected 3 \(inputs x states = 1x3\)'),
    (['controller.poles:=null', 'controller.lqr_Q:=[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, '
      '1.0]'], r'controller\.lqr_R: missing \(required\)'),
    (['controller.lqr_R:=[1.0]', 'controller.poles:=null'],
     r'controller\.lqr_Q: missing \(required with controller\.lqr_R\)'),
    (['controller.poles:=null', 'controller.lqr_Q:=[1.0, 2.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, '
      '1.0]', 'controller.lqr_R:=[1.0]'], r'controller\.lqr_Q: must be symmetric'),
    (['controller.poles:=null', 'controller.lqr_Q:=[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, '
      '1.0]', 'controller.lqr_R:=[0.0]'], r'controller\.lqr_R: must be positive definite'),
    (['controller.u_min:=[1.0]', 'controller.u_max:=[1.0]'], r'controller\.u_max: delta: '
     r'u_max 1\.0 is not above u_min'),
    (['controller.reference:=[0.0, 1.0]'], r'controller\.reference: has 2 values; expected 3'),
    # sensors
    (['sensors.gyro.outputs:=[qq]'], r"sensors\.gyro\.outputs: unknown output 'qq'; outputs "
     r'are \[q\]'),
    (['sensors.gyro.outputs:=[q, q]'], r'sensors\.gyro\.outputs: duplicate name'),
    (['sensors.gyro.fields:=[angular_velocity.q]'], r'sensors\.gyro\.fields: '
     r"'angular_velocity\.q' is not a field of sensor_msgs/msg/Imu"),
    (['sensors.gyro.type:=std_msgs/msg/Float64'], r'sensors\.gyro\.fields: '
     r"'angular_velocity\.y' is not a field of std_msgs/msg/Float64; fields are data"),
    (['sensors.gyro.type:=sensor_msgs/msg/JointState', 'sensors.gyro.fields:=[position]'],
     r"sensors\.gyro\.fields: 'position' is not a field of sensor_msgs/msg/JointState"),
    (['sensors.gyro.noise_std:=[0.1, 0.2]'], r'sensors\.gyro\.noise_std: has 2 values; '
     r'expected 1'),
    (['sensors.gyro.noise_std:=[-0.1]'], r'sensors\.gyro\.noise_std: element 0: -0\.1 must '
     r'be >= 0'),
    (['sensors.gyro.timeout:=-1.0'], r'sensors\.gyro\.timeout: -1\.0 is outside \[0\.001, '
     r'3600\] s \(a silence is watched at a tenth of the timeout, at most 10000 Hz\)'),
    (['sensors.gyro.rate_divider:=0'], r'sensors\.gyro\.rate_divider: 0 must be >= 1'),
    (['sensors.gyro.topic:=imu data'], r"sensors\.gyro\.topic: 'imu data' is not a valid"),
    (['sensors.gyro.topic:=imu//data'], r'sensors\.gyro\.topic:'),
    (['sensors.names:=[gyro, 2nd]'], r"sensors\.names: sensor name '2nd'"),
    (['sensors.names:=[gyro, names]'], r"sensors\.names: sensor name 'names'"),
    (['model.outputs:=[q, theta]', 'model.C:=[0.0, 0.0, 1.0, 1.0, 0.0, 0.0]'],
     r"model\.outputs: output 'theta' is measured by no sensor"),
    # timeouts and rates
    (['simulator.rate_hz:=-20.0'], r'simulator\.rate_hz: -20\.0 is outside \[0\.001, 10000\] Hz'),
    (['simulator.rate_hz:=0.0'], r'simulator\.rate_hz: 0\.0 is outside \[0\.001, 10000\] Hz'),
    (['simulator.duration:=0.01'], r'simulator\.duration: 0\.01 s is shorter than one step'),
    (['simulator.command_timeout:=-2.0'], r'simulator\.command_timeout:'),
    (['simulator.realtime_factor:=0.0'], r'simulator\.realtime_factor:'),
    (['simulator.seed:=-1'], r'simulator\.seed: -1 must be >= 0'),
    (['controller.stale_timeout:=-0.5'], r'controller\.stale_timeout:'),
    (['observer.rate_hz:=-1.0'], r'observer\.rate_hz:'),
    (['simulator.initial_state:=[0.0, 0.0]'], r'simulator\.initial_state: has 2 values; '
     r'expected 3'),
    (['observer.initial_estimate:=[0.0]'], r'observer\.initial_estimate: has 1 values'),
    (['simulator.process_noise_std:=[0.1, -0.1, 0.0]'], r'simulator\.process_noise_std:'),
    # kalman
    (['observer.type:=kalman'], r'observer\.Qd: missing: a kalman observer needs'),
    (['observer.type:=kalman', 'observer.Qd:=[1.0, 0.0, 0.0, 1.0]'],
     r'observer\.Qd: has 4 values; expected 9 \(states x states = 3x3\)'),
    (['observer.type:=kalman', 'observer.Bd:=[1.0, 0.0]', 'observer.Qd:=[1.0]'],
     r'observer\.Bd: has 2 values; expected a multiple of 3'),
    (['observer.type:=kalman', 'observer.Bd:=[1.0, 0.0, 0.0]', 'observer.Qd:=[1.0, 0.0]'],
     r'observer\.Qd: has 2 values; expected 1 \(k x k = 1x1\)'),
    (['observer.type:=kalman', 'observer.Bd:=[1.0, 0.0, 0.0]', 'observer.Qd:=[-1.0]'],
     r'observer\.Qd: must be positive semidefinite'),
    (['observer.type:=kalman', 'observer.Qd:=[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]',
      'sensors.gyro.noise_std:=[0.0]'], r'observer\.Rd: missing: a kalman observer needs'),
    (['observer.type:=kalman', 'observer.Qd:=[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]',
      'observer.Rd:=[0.0]'], r'observer\.Rd: must be positive definite'),
]


@pytest.mark.parametrize('overrides, match', ERRORS, ids=[m[:40] for _, m in ERRORS])
def test_error_names_the_field(overrides, match):
    with pytest.raises(VehicleFileError, match=match) as info:
        build(overrides)
    assert str(info.value).startswith('submarine.yaml: ')
    assert isinstance(info.value, ValueError)   # VehicleFileError is a ValueError


def test_output_covered_by_two_sensors():
    flat = apply_overrides(base(), {
        'sensors.names': ['gyro', 'gyro2'], 'sensors.gyro2.topic': 'imu2/data',
        'sensors.gyro2.type': 'std_msgs/msg/Float64', 'sensors.gyro2.fields': ['data'],
        'sensors.gyro2.outputs': ['q'], 'sensors.gyro2.noise_std': [0.1]})
    with pytest.raises(VehicleFileError, match=r"sensors\.gyro2\.outputs: output 'q' is "
                       r'already measured by sensor gyro'):
        vehicle_from_parameters(flat)
    flat['sensors.gyro2.outputs'] = ['theta']
    flat['model.outputs'] = ['q', 'theta']
    flat['model.C'] = [0.0, 0.0, 1.0, 1.0, 0.0, 0.0]
    flat['sensors.gyro2.topic'] = 'imu/data'
    with pytest.raises(VehicleFileError, match=r"sensors\.gyro2\.topic: topic 'imu/data' is "
                       r'already used by sensor gyro'):
        vehicle_from_parameters(flat)
    flat['sensors.gyro2.topic'] = 'attitude/pitch'
    v = vehicle_from_parameters(flat)
    assert [s.outputs for s in v.sensors] == [('q',), ('theta',)]


def test_reduced_observer_structure():
    with pytest.raises(VehicleFileError, match=r'observer\.poles: has 3 poles; expected at '
                       r'most 2 \(n - p for a reduced observer\)'):
        build(['observer.type:=reduced'])
    flat = base('submarine_reduced')
    flat['observer.poles'] = [-0.6, -0.7]
    with pytest.raises(VehicleFileError, match=r'observer\.poles: has 2 poles; expected at '
                       r'most 1'):
        vehicle_from_parameters(flat)
    flat = base('pitch_imu')   # p = n = 2: nothing left to estimate
    flat['observer.type'] = 'reduced'
    with pytest.raises(VehicleFileError, match=r'observer\.type: a reduced observer needs '
                       r'fewer outputs than states'):
        vehicle_from_parameters(flat)
    v = build(['observer.type:=reduced', 'observer.poles:=null',
               'observer.gain:=[1.0, 2.0]'])
    assert v.observer.gain.shape == (2, 1)


def test_discrete_model():
    over = ['model.time_domain:=discrete', 'model.sample_time:=0.05',
            'observer.poles:=[0.5, 0.6, 0.7]', 'controller.poles:=[0.8, 0.85, 0.9]',
            'simulator.rate_hz:=null']
    v = build(over)
    assert v.plant.is_discrete and v.sample_time == 0.05
    assert v.simulator.rate_hz == pytest.approx(20.0)
    assert vehicle_to_parameters(vehicle_from_parameters(vehicle_to_parameters(v))) == \
        vehicle_to_parameters(v)
    with pytest.raises(VehicleFileError, match=r'simulator\.rate_hz: 10\.0 Hz does not match '
                       r'model\.sample_time'):
        build(over + ['simulator.rate_hz:=10.0'])
    with pytest.raises(VehicleFileError, match=r'observer\.poles: pole 1\.5 is on or outside '
                       r'the unit circle'):
        build(over + ['observer.poles:=[1.5, 0.6, 0.7]'])
    with pytest.raises(VehicleFileError,
                       match=r'model\.sample_time: -0\.05 is outside \[0\.0001, 1000\] s'):
        build(over + ['model.sample_time:=-0.05'])


def test_kalman_defaults_and_unused_keys():
    v = build(['observer.type:=kalman', 'simulator.process_noise_std:=[0.01, 0.02, 0.03]'])
    assert_allclose(v.observer.Qd, np.diag([1e-4, 4e-4, 9e-4]))
    assert_allclose(v.observer.Rd, [[1e-6]])
    assert v.observer.poles is None
    assert v.warnings == ('observer.poles is not used by a kalman observer (ignored)',)
    v = build(['observer.type:=open_loop'])
    assert v.warnings == ('observer.poles is not used by an open_loop observer (ignored)',)
    v = build(['observer.Qd:=[1.0]'])
    assert v.warnings == ('observer.Qd is not used by a full observer (ignored)',)
    v = build(['model.sample_time:=0.1'])
    assert v.warnings == ('model.sample_time is not used by a continuous model (ignored)',)


def test_controller_options():
    v = build(['controller.poles:=null',
               'controller.lqr_Q:=[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]',
               'controller.lqr_R:=[1.0]', 'controller.u_min:=[-.inf]',
               'controller.u_max:=[0.5]'])
    assert v.controller.poles is None and v.controller.lqr_R.shape == (1, 1)
    assert v.controller.u_min[0] == -np.inf
    v = build(['controller.poles:=null', 'controller.K:=[1.0, 2.0, 3.0]'])
    assert_allclose(v.controller.K, [[1.0, 2.0, 3.0]])


# -- unknown keys ----------------------------------------------------------------------------

def test_unknown_key_warning_suggests_nearest():
    v = build(['observer.pole:=[-1.0]'])
    assert v.warnings == ('unknown key observer.pole (did you mean observer.poles?)',)
    v = build(['sensors.gyro.nosie_std:=[0.1]', 'simulatr.seed:=3'])
    assert 'unknown key sensors.gyro.nosie_std (did you mean sensors.gyro.noise_std?)' in \
        v.warnings
    assert 'unknown key simulatr.seed (did you mean simulator.seed?)' in v.warnings
    v = build(['sensors.imu.topic:=imu'])
    assert v.warnings == ("unknown key sensors.imu.topic (sensor 'imu' is not in "
                          "sensors.names ['gyro'])",)
    v = build(['completely.unrelated:=1'])
    assert v.warnings == ('unknown key completely.unrelated',)
    flat = dict(base(), own_setting=1.0)
    assert vehicle_from_parameters(flat, extra_keys=['own_setting']).warnings == ()


# -- the file and its sections -----------------------------------------------------------------

def _write(tmp_path, text, name='v.yaml'):
    path = tmp_path / name
    path.write_text(text)
    return path


def test_node_name_sections_merge_over_wildcard(tmp_path):
    text = SUBMARINE.read_text() + (
        '/observer:\n  ros__parameters:\n    observer:\n      poles: [-1.0, -1.1, -1.2]\n'
        '/**/compensator:\n  ros__parameters:\n    controller:\n'
        '      poles: [-0.5, -0.51, -0.52]\n'
        '/other:\n  ros__parameters:\n    vehicle:\n      name: other\n')
    path = _write(tmp_path, text)
    plain = load_vehicle(path)
    assert_allclose(np.sort(plain.observer.poles.real), [-0.62, -0.61, -0.6])
    obs = load_vehicle(path, node_name='observer')
    assert_allclose(np.sort(obs.observer.poles.real), [-1.2, -1.1, -1.0])
    assert_allclose(obs.controller.poles.real, [-0.3, -0.31, -0.32])
    comp = load_vehicle(path, node_name='/sub1/compensator')
    assert_allclose(comp.controller.poles.real, [-0.5, -0.51, -0.52])
    assert_allclose(np.sort(comp.observer.poles.real), [-0.62, -0.61, -0.6])
    assert load_vehicle(path, node_name='/sub1/observer').observer.poles.real.min() == -0.62
    assert load_vehicle(path, node_name='other').name == 'other'


def test_node_section_without_wildcard(tmp_path):
    text = SUBMARINE.read_text().replace('/**:', 'observer:', 1)
    path = _write(tmp_path, text)
    with pytest.raises(VehicleFileError, match=r"no section applies to '/\*\*'"):
        load_vehicle(path)
    assert load_vehicle(path, node_name='observer').name == 'submarine'
    with pytest.raises(VehicleFileError, match=r'no section applies to node /plant'):
        load_vehicle(path, node_name='plant')


@pytest.mark.parametrize('text, match', [
    ('model: {A: [1.0]}\n', r"section 'model' must hold exactly one key, 'ros__parameters'"),
    ('[1, 2]\n', 'not a ROS 2 parameters file'),
    ('', 'not a ROS 2 parameters file'),
    ('/**:\n  ros__parameters:\n    a: [1.0\n', 'not valid YAML'),
    ('/**:\n  ros__parameters:\n    a: 1.0\n    a: 2.0\n', "duplicate key 'a'"),
    ('/**:\n  ros__parameters:\n    model: {}\n', 'model is an empty mapping'),
    ('/**:\n  ros__parameters:\n    1: 2.0\n', 'key 1 under the top is not a parameter name'),
])
def test_bad_files(tmp_path, text, match):
    with pytest.raises(VehicleFileError, match=match):
        load_vehicle(_write(tmp_path, text))


def test_missing_file_is_a_vehicle_error(tmp_path):
    with pytest.raises(VehicleFileError, match='cannot read'):
        load_vehicle(tmp_path / 'nope.yaml')


def test_exponent_floats_read_as_floats(tmp_path):
    """ROS reads 1e-3 as a double; plain PyYAML would give a string."""
    text = SUBMARINE.read_text().replace('noise_std: [0.001]', 'noise_std: [1e-3]')
    assert 'noise_std: [1e-3]' in text
    v = load_vehicle(_write(tmp_path, text))
    assert v.sensors[0].noise_std[0] == 1e-3


# -- overrides ------------------------------------------------------------------------------------

def test_overrides():
    flat = base()
    out = apply_overrides(flat, ['observer.type:=kalman', 'observer.poles:=null',
                                 'observer.Qd:=[1.0e-4, 0.0, 0.0, 0.0, 1e-4, 0.0, 0.0, 0.0, '
                                 '1.0e-4]', 'vehicle.name:=sub_kalman'])
    assert 'observer.poles' in flat and 'observer.poles' not in out   # input unchanged
    assert out['observer.type'] == 'kalman' and out['vehicle.name'] == 'sub_kalman'
    assert out['observer.Qd'][4] == 1e-4
    v = vehicle_from_parameters(out)
    assert v.observer.kind == 'kalman' and v.warnings == ()
    out = apply_overrides(flat, {'simulator.seed': 3, 'simulator.noise': False})
    assert (out['simulator.seed'], out['simulator.noise']) == (3, False)
    out = apply_overrides(flat, 'simulator.duration:=5.0')
    assert out['simulator.duration'] == 5.0
    # A mapping value replaces the whole subtree.
    out = apply_overrides(flat, ['observer:={type: open_loop}'])
    assert out['observer.type'] == 'open_loop' and 'observer.poles' not in out
    assert vehicle_from_parameters(out).observer.kind == 'open_loop'
    # load_vehicle takes the same overrides.
    v = load_vehicle(SUBMARINE, overrides=['controller.poles:=[-0.4, -0.41, -0.42]'])
    assert_allclose(v.controller.poles.real, [-0.4, -0.41, -0.42])


@pytest.mark.parametrize('bad', ['observer.type=kalman', ':=1.0', 'a:=[1.0', 3])
def test_bad_overrides(bad):
    with pytest.raises(VehicleFileError, match='override'):
        apply_overrides(base(), [bad])


def test_override_int_is_refused_like_ros():
    with pytest.raises(VehicleFileError, match=r'simulator\.rate_hz: integer 50'):
        build(['simulator.rate_hz:=50'])


# -- sensor fields and messages -------------------------------------------------------------------

def _sensor(msg_type, fields, outputs, noise, topic='sensor/topic', name='s'):
    return SensorSpec(name=name, topic=topic, msg_type=msg_type, fields=tuple(fields),
                      outputs=tuple(outputs), noise_std=np.array(noise, dtype=float),
                      frame_id='base_link_frd')


IMU = 'sensor_msgs/msg/Imu'
JS = 'sensor_msgs/msg/JointState'
F64 = 'std_msgs/msg/Float64'


def test_parse_field():
    assert parse_field(IMU, 'angular_velocity.y').path == ('angular_velocity', 'y')
    acc = parse_field(JS, 'velocity.pitch')
    assert (acc.path, acc.joint) == (('velocity',), 'pitch')
    assert parse_field(JS, 'position.a.b').joint == 'a.b'
    assert parse_field(F64, 'data').path == ('data',)
    for msg_type, field in [(IMU, 'orientation.x'), (IMU, 'angular_velocity'), (F64, 'value'),
                            (JS, 'position.'), (JS, 'name.cart'), ('geometry_msgs/Twist', 'x')]:
        with pytest.raises(VehicleFileError):
            parse_field(msg_type, field)


def _ns_imu():
    vec = types.SimpleNamespace
    return vec(header=vec(frame_id='', stamp=None), orientation=vec(x=0.0, y=0.0, z=0.0, w=1.0),
               angular_velocity=vec(x=0.0, y=0.0, z=0.0),
               linear_acceleration=vec(x=0.0, y=0.0, z=0.0),
               orientation_covariance=[0.0] * 9, angular_velocity_covariance=[0.0] * 9,
               linear_acceleration_covariance=[0.0] * 9)


def _ns_joint_state():
    return types.SimpleNamespace(header=types.SimpleNamespace(frame_id=''), name=[],
                                 position=[], velocity=[], effort=[])


def _rclpy_classes():
    from sensor_msgs.msg import Imu, JointState
    from std_msgs.msg import Float64
    return Imu, JointState, Float64


def _rosbags_factories():
    from rosbags.typesys import get_typestore, Stores
    ts = get_typestore(Stores.ROS2_JAZZY)
    T = ts.types

    def header():
        return T['std_msgs/msg/Header'](
            stamp=T['builtin_interfaces/msg/Time'](sec=1, nanosec=0), frame_id='')

    def vec():
        return T['geometry_msgs/msg/Vector3'](x=0.0, y=0.0, z=0.0)

    def imu():
        return T[IMU](header=header(),
                      orientation=T['geometry_msgs/msg/Quaternion'](x=0.0, y=0.0, z=0.0, w=1.0),
                      orientation_covariance=np.zeros(9), angular_velocity=vec(),
                      angular_velocity_covariance=np.zeros(9), linear_acceleration=vec(),
                      linear_acceleration_covariance=np.zeros(9))

    def joint_state():
        empty = np.zeros(0)
        return T[JS](header=header(), name=[], position=empty, velocity=empty.copy(),
                     effort=empty.copy())

    def float64():
        return T[F64](data=0.0)
    return ts, imu, joint_state, float64


def _factories(flavour):
    """Message factories (imu, joint_state, float64) of one flavour."""
    if flavour == 'namespace':
        return _ns_imu, _ns_joint_state, lambda: types.SimpleNamespace(data=0.0)
    if flavour == 'rclpy':
        return _rclpy_classes()
    return _rosbags_factories()[1:]


FLAVOURS = ['namespace', 'rclpy', 'rosbags']


@pytest.mark.parametrize('flavour', FLAVOURS)
def test_imu_fill_and_extract(flavour):
    make_imu, _, _ = _factories(flavour)
    sensor = _sensor(IMU, ['angular_velocity.y', 'linear_acceleration.z'], ['q', 'a_N'],
                     [0.01, 0.5])
    msg = fill_measurement(make_imu(), sensor, [0.25, -9.5])
    assert msg.angular_velocity.y == 0.25 and msg.linear_acceleration.z == -9.5
    assert msg.header.frame_id == 'base_link_frd'
    assert_allclose(list(msg.angular_velocity_covariance), [0, 0, 0, 0, 1e-4, 0, 0, 0, 0])
    assert_allclose(list(msg.linear_acceleration_covariance), [0, 0, 0, 0, 0, 0, 0, 0, 0.25])
    assert list(msg.orientation_covariance)[0] == -1.0
    y = extract_measurement(msg, sensor)
    assert isinstance(y, np.ndarray) and y.dtype == float
    assert_allclose(y, [0.25, -9.5])
    # An unused block is "not provided" (REP 145): element 0 = -1.
    gyro = _sensor(IMU, ['angular_velocity.y'], ['q'], [0.001])
    msg = fill_measurement(make_imu(), gyro, [0.5])
    assert list(msg.linear_acceleration_covariance)[0] == -1.0
    assert_allclose(extract_measurement(msg, gyro), [0.5])


@pytest.mark.parametrize('flavour', FLAVOURS)
def test_joint_state_fill_and_extract(flavour):
    _, make_js, _ = _factories(flavour)
    sensor = _sensor(JS, ['position.pitch', 'velocity.pitch', 'position.cart'],
                     ['theta', 'q', 'x'], [0.1, 0.1, 0.1])
    msg = fill_measurement(make_js(), sensor, [0.1, 0.2, 0.3])
    assert list(msg.name) == ['pitch', 'cart']
    assert_allclose(list(msg.position), [0.1, 0.3])
    assert list(msg.velocity)[0] == 0.2 and math.isnan(list(msg.velocity)[1])
    assert len(msg.effort) == 0
    assert_allclose(extract_measurement(msg, sensor), [0.1, 0.2, 0.3])
    # Lookup is by name, not position in the arrays.
    msg.name = ['cart', 'pitch']
    assert_allclose(extract_measurement(msg, _sensor(JS, ['position.pitch'], ['t'], [0.1])),
                    [0.3])


@pytest.mark.parametrize('flavour', FLAVOURS)
def test_float64_fill_and_extract(flavour):
    _, _, make_f64 = _factories(flavour)
    sensor = _sensor(F64, ['data'], ['beta'], [0.002])
    msg = fill_measurement(make_f64(), sensor, [0.0175])
    assert msg.data == 0.0175
    assert_allclose(extract_measurement(msg, sensor), [0.0175])


@pytest.mark.parametrize('flavour', FLAVOURS)
def test_measurement_errors(flavour):
    make_imu, make_js, make_f64 = _factories(flavour)
    enc = _sensor(JS, ['position.cart'], ['x'], [1e-5], topic='joint_states')
    msg = fill_measurement(make_js(), _sensor(JS, ['position.wheel'], ['x'], [0.1]), [1.0])
    with pytest.raises(MeasurementError, match=r"joint_states: joint 'cart' is not in "
                       r"JointState\.name \['wheel'\]"):
        extract_measurement(msg, enc)
    msg = fill_measurement(make_js(), enc, [1.0])
    msg.name = ['other', 'cart']          # two names, one position
    with pytest.raises(MeasurementError, match=r"joint_states: joint 'cart': "
                       r'JointState\.position has 1 values for 2 names'):
        extract_measurement(msg, enc)
    msg = fill_measurement(make_js(), enc, [float('nan')])
    with pytest.raises(MeasurementError, match=r'joint_states: position\.cart is nan'):
        extract_measurement(msg, enc)
    gyro = _sensor(IMU, ['angular_velocity.y'], ['q'], [0.001], topic='imu/data')
    msg = fill_measurement(make_imu(), gyro, [float('inf')])
    with pytest.raises(MeasurementError, match=r'imu/data: angular_velocity\.y is inf'):
        extract_measurement(msg, gyro)
    with pytest.raises(MeasurementError, match=r'imu/data: message .* has no field '
                       r"'angular_velocity\.y'"):
        extract_measurement(make_f64(), gyro)
    with pytest.raises(MeasurementError, match='2 values for the 1 fields'):
        fill_measurement(make_imu(), gyro, [1.0, 2.0])
    # MeasurementError is an ObserverError and a ValueError, as nodes catch them.
    assert issubclass(MeasurementError, ObserverError)
    assert issubclass(MeasurementError, ValueError)


def test_rosbags_messages_serialize_after_fill():
    ts, make_imu, make_js, make_f64 = _rosbags_factories()
    cases = [(make_imu(), _sensor(IMU, ['angular_velocity.y'], ['q'], [0.01])),
             (make_js(), _sensor(JS, ['position.cart', 'velocity.cart'], ['x', 'v'],
                                 [0.1, 0.1])),
             (make_f64(), _sensor(F64, ['data'], ['b'], [0.1]))]
    for msg, sensor in cases:
        fill_measurement(msg, sensor, np.arange(len(sensor.fields)) + 0.5)
        raw = ts.serialize_cdr(msg, msg.__msgtype__)
        back = ts.deserialize_cdr(raw, msg.__msgtype__)
        assert_allclose(extract_measurement(back, sensor), np.arange(len(sensor.fields)) + 0.5)


def test_rclpy_messages_serialize_after_fill():
    from rclpy.serialization import deserialize_message, serialize_message
    Imu, JointState, Float64 = _rclpy_classes()
    cases = [(Imu, _sensor(IMU, ['linear_acceleration.z'], ['a'], [0.5])),
             (JointState, _sensor(JS, ['effort.motor'], ['f'], [0.1])),
             (Float64, _sensor(F64, ['data'], ['b'], [0.1]))]
    for cls, sensor in cases:
        msg = fill_measurement(cls(), sensor, [1.5])
        back = deserialize_message(serialize_message(msg), cls)
        assert_allclose(extract_measurement(back, sensor), [1.5])


@pytest.mark.parametrize('path', CONFIGS, ids=lambda p: p.stem)
def test_config_sensors_fill_and_extract(path):
    """Every sensor of every vehicle file round-trips through a real rclpy message."""
    classes = dict(zip((IMU, JS, F64), _rclpy_classes()))
    for sensor in load_vehicle(path).sensors:
        values = np.linspace(-1.0, 1.0, len(sensor.fields))
        msg = fill_measurement(classes[sensor.msg_type](), sensor, values)
        assert_allclose(extract_measurement(msg, sensor), values)


# -- fuzz ---------------------------------------------------------------------------------------

_BASES = [load_parameters(path) for path in CONFIGS]
_KEYS = sorted({key for flat in _BASES for key in flat} | set(KNOWN_KEYS))

_scalars = st.one_of(
    st.none(), st.booleans(), st.integers(min_value=-2 ** 70, max_value=2 ** 70),
    st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=12),
    st.binary(max_size=4), st.complex_numbers(max_magnitude=10.0))
_arrays = st.one_of(   # the containers rclpy and numpy code hand over
    st.lists(st.floats(allow_nan=True, allow_infinity=True), max_size=5).map(np.array),
    st.lists(st.integers(-5, 5), max_size=5).map(np.array),
    st.lists(st.floats(-10.0, 10.0), max_size=5).map(lambda v: array.array('d', v)),
    st.lists(st.integers(-5, 5), max_size=5).map(lambda v: array.array('q', v)),
    st.lists(st.booleans(), min_size=1, max_size=3).map(np.array),
    st.floats(-1.0, 1.0).map(lambda v: np.array([[v]])),
    st.sampled_from([np.float64(0.5), np.int64(3), np.bool_(True), np.float32(0.25)]))
_junk = st.recursive(
    st.one_of(_scalars, _arrays),
    lambda inner: st.one_of(st.lists(inner, max_size=6),
                            st.dictionaries(st.text(max_size=5), inner, max_size=3),
                            st.tuples(inner, inner)),
    max_leaves=12)
_float_lists = st.lists(st.floats(allow_nan=True, allow_infinity=True, width=64), max_size=12)


@st.composite
def _mutated(draw):
    flat = dict(draw(st.sampled_from(_BASES)))
    for _ in range(draw(st.integers(min_value=1, max_value=4))):
        keys = sorted(flat) or ['model.A']
        key = draw(st.sampled_from(keys))
        action = draw(st.sampled_from(
            ['drop', 'junk', 'floats', 'resize', 'nan', 'int', 'string', 'new_key',
             'other_key', 'choice']))
        if action == 'drop':
            flat.pop(key, None)
        elif action == 'junk':
            flat[key] = draw(_junk)
        elif action == 'floats':
            flat[key] = draw(_float_lists)
        elif action == 'resize' and isinstance(flat.get(key), list):
            n = draw(st.integers(min_value=0, max_value=len(flat[key]) + 3))
            flat[key] = (flat[key] * 2)[:n] if flat[key] else [0.5] * n
        elif action == 'nan' and isinstance(flat.get(key), list) and flat[key]:
            i = draw(st.integers(min_value=0, max_value=len(flat[key]) - 1))
            flat[key] = list(flat[key])
            flat[key][i] = draw(st.sampled_from([math.nan, math.inf, -math.inf, 1e308,
                                                 -1e308, 5e-324, 0.0]))
        elif action == 'int':
            flat[key] = draw(st.integers(min_value=-3, max_value=3))
        elif action == 'string':
            flat[key] = draw(st.sampled_from(['', 'q', 'theta', 'full', 'kalman', 'data',
                                              'sensor_msgs/msg/JointState', 'imu/data']))
        elif action == 'new_key':
            flat[draw(st.text(min_size=1, max_size=20))] = draw(_junk)
        elif action == 'other_key':
            flat[draw(st.sampled_from(_KEYS))] = draw(_junk)
        elif action == 'choice':
            flat['observer.type'] = draw(st.sampled_from(['full', 'reduced', 'open_loop',
                                                          'kalman']))
    return flat


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(_mutated())
def test_fuzz_only_vehicle_file_errors(flat):
    """Whatever the parameters, the loader returns a vehicle or raises VehicleFileError."""
    try:
        vehicle = vehicle_from_parameters(flat, source='fuzz')
    except VehicleFileError as err:
        assert str(err).startswith('fuzz: ')
        return
    # What loads also writes back and loads again to the same parameters.
    flat2 = vehicle_to_parameters(vehicle)
    assert vehicle_to_parameters(vehicle_from_parameters(flat2)) == flat2


@settings(max_examples=150, deadline=None)
@given(st.dictionaries(st.one_of(st.text(max_size=20), st.integers()), _junk, max_size=8))
def test_fuzz_arbitrary_dicts(flat):
    with pytest.raises(VehicleFileError):
        vehicle_from_parameters(flat)
