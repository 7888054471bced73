# Tests of observer_ros.vehicle.schema: the one source of keys, bounds, units and the docs.
"""The schema: its docs table, the bounds the loader enforces, rates, plausibility, units."""

import math
from pathlib import Path
import re
import subprocess
import sys

from observer_ros.core.errors import VehicleFileError
from observer_ros.evaluation.report import format_table
from observer_ros.vehicle import (apply_overrides, KNOWN_KEYS, load_parameters, load_vehicle,
                                  parameter_schema, parameters_to_yaml, SENSOR_KEYS,
                                  vehicle_from_parameters, vehicle_to_parameters)
from observer_ros.vehicle.doc import render, SECTIONS
from observer_ros.vehicle.schema import (bound_problem, MAX_RATE_HZ, MAX_STATE_MAGNITUDE,
                                         NODE_KEYS, ros_range)
import pytest
import yaml

ROOT = Path(__file__).resolve().parents[2]
DOC = ROOT / 'docs' / 'vehicle_schema.md'
CONFIGS = sorted((ROOT / 'config').glob('*.yaml'))


def build(overrides, name='submarine'):
    """Load a config file with overrides (tools' key:=value strings or a dict)."""
    flat = load_parameters(ROOT / 'config' / f'{name}.yaml')
    return vehicle_from_parameters(apply_overrides(flat, overrides), source=f'{name}.yaml')


# -- the schema and the page ---------------------------------------------------------------

def test_parameter_schema_for_nodes():
    from rclpy.parameter import Parameter
    schema = parameter_schema(['gyro'])
    names = [p.name for p in schema]
    assert 'model.A' in names and 'sensors.gyro.noise_std' in names
    assert len(names) == len(set(names)) == len(KNOWN_KEYS) + len(SENSOR_KEYS)
    for name, kind, default, description in schema:
        assert kind in Parameter.Type.__members__
        assert description
        if default is not None:
            # rclpy infers the same type from the default: it can be declared with it.
            assert Parameter.Type.from_parameter_value(default).name == kind, name
    by_name = {p.name: p for p in schema}
    assert by_name['simulator.rate_hz'].default == 100.0
    assert by_name['sensors.gyro.timeout'].default == 0.5
    assert by_name['model.A'].default is None and 'required' in by_name['model.A'].description


def test_doc_tables_are_made_from_the_schema():
    """The page's tables are the schema's, to the character (regenerate: see the page)."""
    text = DOC.read_text()
    assert re.findall(r'<!-- schema: (\w+) -->', text) == list(SECTIONS)
    assert render(text) == text, ('docs/vehicle_schema.md differs from the schema: run '
                                  'python -m observer_ros.vehicle.doc docs/vehicle_schema.md')


_DOC_TYPES = {'string': 'STRING', 'string[]': 'STRING_ARRAY', 'double': 'DOUBLE',
              'double[]': 'DOUBLE_ARRAY', 'int': 'INTEGER', 'bool': 'BOOL'}
_ROW = re.compile(r'^\| `([a-z_<>.A-Z]+)` \| ([a-z\[\]]+) \| ([^|]*) \| ([^|]*) \| ([^|]*) \|',
                  re.M)


def _bound(text):
    """Read ``[a, b]``, ``(a, b]``, ``>= a``, ``> a`` from a range cell: (low, high, open)."""
    text = text.replace('each ', '')
    m = re.search(r'([\[(])([-+0-9.e]+), ([-+0-9.e]+)\]', text)
    if m:
        return float(m.group(2)), float(m.group(3)), m.group(1) == '('
    m = re.search(r'(>=?) ([-+0-9.e]+)', text)
    if m:
        return float(m.group(2)), None, m.group(1) == '>'
    return None, None, False


def test_doc_rows_say_what_the_loader_and_descriptors_use():
    """Read back independently: every key, type, default, unit and bound of the page."""
    documented = {key: cells for key, *cells in _ROW.findall(DOC.read_text())}
    code = dict(KNOWN_KEYS)
    code.update({f'sensors.<s>.{k}': spec for k, spec in SENSOR_KEYS.items()})
    code.update(NODE_KEYS)
    assert set(documented) == set(code)
    for key, (kind, default, unit, bound) in documented.items():
        spec = code[key]
        assert _DOC_TYPES[kind] == spec.param_type, key
        default = default.strip()
        if default == 'required':
            assert spec.required, key
        elif default == '—':
            assert not spec.required and spec.default is None, key
        else:
            assert yaml.safe_load(default.strip('`')) == spec.default, key
        assert unit.strip() == spec.unit, key
        low, high, is_open = _bound(bound)
        assert (low, high, is_open) == (spec.low, spec.high, spec.low_open), key


@pytest.mark.ros
def test_vehicle_package_does_not_import_rclpy():
    code = ('import sys, observer_ros.vehicle, observer_ros.vehicle.doc, observer_ros.sensors; '
            'assert "rclpy" not in sys.modules, "rclpy imported"; '
            'assert not any(m.startswith("sensor_msgs") for m in sys.modules)')
    subprocess.run([sys.executable, '-c', code], check=True)


# -- bounds --------------------------------------------------------------------------------

def _scalar_keys():
    keys = [(name, spec) for name, spec in KNOWN_KEYS.items() if spec.bounded and
            spec.param_type in ('DOUBLE', 'INTEGER') and name != 'model.sample_time']
    keys += [(f'sensors.gyro.{name}', spec) for name, spec in SENSOR_KEYS.items()
             if spec.bounded and spec.param_type in ('DOUBLE', 'INTEGER')]
    return keys


def _just_outside(spec):
    """Return values just outside a key's bound (the bound itself when it is open)."""
    integer = spec.param_type == 'INTEGER'
    out = []
    if spec.low is not None:
        out.append(spec.low if spec.low_open else
                   (int(spec.low) - 1 if integer else math.nextafter(spec.low, -math.inf)))
    if spec.high is not None:
        out.append(int(spec.high) + 1 if integer else math.nextafter(spec.high, math.inf))
    return out


@pytest.mark.parametrize('name, spec', _scalar_keys(), ids=lambda x: getattr(x, 'name', x))
def test_every_bound_is_enforced_by_the_loader(name, spec):
    for value in _just_outside(spec):
        with pytest.raises(VehicleFileError, match=re.escape(f'{name}: {value!r} ')):
            build({name: value})
    # the edges themselves are accepted where no rule about other keys applies
    if spec.low is not None and not spec.low_open and not spec.rule:
        low = int(spec.low) if spec.param_type == 'INTEGER' else float(spec.low)
        # a run of 0 s (until stopped) has at least one step at any rate
        build({name: low, 'simulator.duration': 0.0} if name == 'simulator.rate_hz' else
              {name: low})


def test_a_discrete_step_is_bounded_like_a_rate():
    over = {'model.time_domain': 'discrete', 'model.sample_time': 0.05,
            'simulator.rate_hz': None, 'observer.poles': [0.5, 0.6, 0.7],
            'controller.poles': [0.8, 0.85, 0.9]}
    build(over)
    with pytest.raises(VehicleFileError, match=r'model\.sample_time: 1e-05 is outside '
                       r'\[0\.0001, 1000\] s \(1/sample_time is the step rate; 10000 Hz'):
        build(dict(over, **{'model.sample_time': 1e-5}))


def test_rates_beyond_what_the_machine_can_do_are_refused_with_the_reason():
    with pytest.raises(VehicleFileError, match=r'simulator\.rate_hz: 1000000000\.0 is outside '
                       r"\[0\.001, 10000\] Hz \(10000 Hz: the fastest a node's timer fires"):
        build({'simulator.rate_hz': 1e9})
    build({'simulator.rate_hz': MAX_RATE_HZ})
    # realtime: the step timer runs at rate_hz x realtime_factor
    fast = {'simulator.rate_hz': 1000.0, 'simulator.mode': 'realtime'}
    build(dict(fast, **{'simulator.realtime_factor': 10.0}))
    with pytest.raises(VehicleFileError, match=r'simulator\.realtime_factor: 20 steps 1000 Hz '
                       r'at 20000 Hz of wall time, more than the 10000 Hz'):
        build(dict(fast, **{'simulator.realtime_factor': 20.0}))
    # lock-step has no step timer: the same factor is not a timer there
    build({'simulator.rate_hz': 1000.0, 'simulator.realtime_factor': 20.0})


@pytest.mark.parametrize('key', ['observer.rate_hz', 'observer.publish_rate_hz'])
def test_no_observer_timer_is_faster_than_the_fastest_sensor(key):
    build({key: 20.0})          # the submarine's gyro: 20 Hz
    with pytest.raises(VehicleFileError, match=re.escape(
            f'{key}: 40 Hz is faster than the fastest sensor (20 Hz: simulator.rate_hz / its '
            'rate_divider)')):
        build({key: 40.0})
    with pytest.raises(VehicleFileError, match=f'{re.escape(key)}: 20 Hz .* fastest sensor '
                       r'\(10 Hz'):
        build({key: 20.0, 'sensors.gyro.rate_divider': 2})


@pytest.mark.parametrize('key', ['observer.initial_estimate', 'simulator.initial_state',
                                 'controller.reference'])
def test_implausible_state_values_are_refused(key):
    with pytest.raises(VehicleFileError, match=re.escape(
            f'{key}: element 0: 1e+308 is outside [-1e+09, 1e+09] (a plausibility bound')):
        build({key: [1e308, 0.0, 0.0]})
    build({key: [-MAX_STATE_MAGNITUDE, 0.0, MAX_STATE_MAGNITUDE]})


def test_bound_problem_and_the_ros_range_of_an_open_bound():
    spec = NODE_KEYS['future_tolerance']
    assert bound_problem(spec, 0.0) == '0.0 is outside (0, 1e+09] s'
    assert bound_problem(spec, float('nan')) is not None
    assert bound_problem(spec, 5e-324) is None and bound_problem(spec, 1e9) is None
    assert ros_range(spec) == (5e-324, 1e9)
    assert ros_range(SENSOR_KEYS['rate_divider']) == (1, 2 ** 63 - 1)
    assert ros_range(KNOWN_KEYS['simulator.duration'])[1] == sys.float_info.max
    assert ros_range(KNOWN_KEYS['observer.initial_estimate']) is None     # arrays: none
    with pytest.raises(ValueError, match='open bound'):
        type(spec)('x', 'DOUBLE', '', low=1.0, low_open=True)


# -- units ---------------------------------------------------------------------------------

@pytest.mark.parametrize('path', CONFIGS, ids=lambda p: p.stem)
def test_every_shipped_file_states_its_units(path):
    v = load_vehicle(path)
    assert len(v.state_units) == v.plant.n and all(v.state_units)
    assert len(v.input_units) == v.plant.m and all(v.input_units)
    assert len(v.output_units) == v.plant.p and all(v.output_units)
    # every sensor field is SI
    assert set(v.output_units) <= {'rad', 'rad/s', 'm', 'm/s', 'm/s^2'}


def test_units_of_the_seeds_are_kept_and_stated():
    sub = load_vehicle(ROOT / 'config' / 'submarine.yaml')
    assert sub.state_units == ('rad', 'ft/s', 'rad/s') and sub.output_units == ('rad/s',)
    assert sub.unit('state', 'w') == 'ft/s'
    air = load_vehicle(ROOT / 'config' / 'aircraft_lateral.yaml')
    assert air.input_units == ('deg', 'deg') and air.unit('state', 'delta_a') == 'deg'


def test_a_unit_against_the_field_convention_is_refused():
    with pytest.raises(VehicleFileError, match=re.escape(
            'model.output_units: q is deg/s, but output q is read from sensor_msgs/msg/Imu '
            'angular_velocity.y (sensor gyro), which ROS gives in rad/s (REP 103)')):
        build({'model.output_units': ['deg/s'], 'model.state_units': ['rad', 'ft/s', 'deg/s']})
    with pytest.raises(VehicleFileError, match=re.escape(
            'model.state_units: q is deg/s, but output q is read from')):
        build({'model.state_units': ['rad', 'ft/s', 'deg/s']})
    with pytest.raises(VehicleFileError, match=re.escape(
            'model.output_units: q is rad/s but measures state q alone (its row of C), which '
            'is 1/s in model.state_units')):
        build({'model.state_units': ['rad', 'ft/s', '1/s'], 'model.output_units': ['rad/s']})
    with pytest.raises(VehicleFileError, match=r'model\.input_units: has 2 units; expected 1 '
                       r'\(one per input: delta\)'):
        build({'model.input_units': ['rad', 'rad']})


def test_units_round_trip_through_a_written_file(tmp_path):
    flat = vehicle_to_parameters(load_vehicle(ROOT / 'config' / 'submarine.yaml'))
    assert flat['model.state_units'] == ['rad', 'ft/s', 'rad/s']
    out = tmp_path / 'variant.yaml'
    out.write_text(parameters_to_yaml(flat))
    assert load_vehicle(out).state_units == ('rad', 'ft/s', 'rad/s')


def test_the_evaluation_report_shows_the_units(tmp_path):
    from bag_synth import simulate, write_bag
    from observer_ros.evaluation.evaluator import evaluate_bag
    vehicle = build({'simulator.duration': 2.0})
    bag = write_bag(tmp_path / 'bag', simulate(vehicle)['messages'])
    result = evaluate_bag(bag, vehicle)
    table = format_table(result)
    rows = [line.split() for line in table.splitlines()]
    assert ['variant', 'state', 'unit'] == rows[[r[:2] for r in rows].index(
        ['variant', 'state'])][:3]
    assert any(r[1:3] == ['w', 'ft/s'] for r in rows if len(r) > 2), table
    assert result.to_dict()['units']['state'] == {'theta': 'rad', 'w': 'ft/s', 'q': 'rad/s'}


def test_a_bare_n_is_false_as_ros_reads_it_and_written_files_quote_it(tmp_path):
    text = (ROOT / 'config' / 'cart_pendulum.yaml').read_text()
    bare = tmp_path / 'bare.yaml'
    bare.write_text(text.replace("input_units: ['N']", 'input_units: [N]'))
    with pytest.raises(VehicleFileError, match=r'model\.input_units: expected strings; got '
                       r'boolean False \(quote it\)'):
        load_vehicle(bare)
    flat = vehicle_to_parameters(load_vehicle(ROOT / 'config' / 'cart_pendulum.yaml'))
    out = tmp_path / 'written.yaml'
    out.write_text(parameters_to_yaml(flat))
    assert "input_units: ['N']" in out.read_text()
    assert load_vehicle(out).input_units == ('N',)


def test_written_files_have_no_yaml_aliases_and_keep_quoted_units():
    # one list object under two keys: a plain safe_dump writes an anchor and an alias
    shared = [1.0, 2.0]
    text = parameters_to_yaml({'observer.a': shared, 'observer.b': shared,
                               'model.input_units': ['N']})
    assert '&' not in text and '*' not in text.replace('/**:', ''), text
    assert "input_units: ['N']" in text
    assert yaml.safe_load(text)['/**']['ros__parameters']['observer']['b'] == shared
