# The descriptors the nodes declare their parameters with (no DDS peers: built from the schema).
"""Each parameter's ParameterDescriptor: the schema's description, read_only, range."""

import json
import subprocess
import sys

from observer_ros.nodes.checks import own_parameter_problem
from observer_ros.nodes.parameters import describe, READ_ONLY_SECTIONS
from observer_ros.vehicle import known_keys, load_parameters
from observer_ros.vehicle.schema import (interval_text, KNOWN_KEYS, NODE_KEYS, ros_range,
                                         SENSOR_KEYS)
import pytest
from ros_helpers import CONFIG, DOMAIN_ID, REPO, SUBMARINE, WAIT


@pytest.mark.parametrize('path', sorted(CONFIG.glob('*.yaml')), ids=lambda p: p.name)
def test_every_vehicle_key_gets_the_schema_description(path):
    flat = load_parameters(path)
    schema = known_keys(flat['sensors.names'])
    for name, value in flat.items():
        descriptor = describe(name, value, schema)
        spec = schema[name]
        assert descriptor.description.startswith(spec.description), name
        assert descriptor.read_only == spec.read_only, name
        assert spec.read_only == (name.split('.')[0] in READ_ONLY_SECTIONS or name in (
            'observer.rate_hz', 'observer.publish_rate_hz')), name


def test_what_cannot_change_while_running_is_read_only():
    schema = known_keys(['gyro'])
    for name in ('model.A', 'model.states', 'model.inputs', 'model.outputs', 'sensors.names',
                 'sensors.gyro.topic', 'vehicle.name', 'simulator.mode'):
        assert describe(name, 'x', schema).read_only, name
    for name in ('observer.poles', 'controller.poles', 'controller.stale_timeout'):
        assert not describe(name, [1.0], schema).read_only, name


def _bounded_scalars():
    schema = known_keys(['gyro'])
    specs = [spec for spec in list(schema.values()) + list(NODE_KEYS.values())
             if spec.bounded and spec.param_type in ('DOUBLE', 'INTEGER')]
    assert len(specs) >= 15
    return schema, specs


def test_every_bounded_scalar_gets_the_schemas_range():
    schema, specs = _bounded_scalars()
    for spec in specs:
        value = 1.0 if spec.param_type == 'DOUBLE' else 1
        d = describe(spec.name, value, schema)
        ranges = d.floating_point_range if spec.param_type == 'DOUBLE' else d.integer_range
        other = d.integer_range if spec.param_type == 'DOUBLE' else d.floating_point_range
        assert len(ranges) == 1 and not other, spec.name
        assert (ranges[0].from_value, ranges[0].to_value) == ros_range(spec), spec.name
        assert d.additional_constraints.startswith(interval_text(spec)), spec.name
        if spec.low_open:
            assert ranges[0].from_value == 5e-324 and 'ROS ranges are closed' in \
                d.additional_constraints
    rate = describe('simulator.rate_hz', 100.0, schema)
    assert (rate.floating_point_range[0].from_value, rate.floating_point_range[0].to_value) \
        == (0.001, 10000.0)
    assert rate.description.endswith('[Hz]')
    # a value of another type (an integer written for a double): no range; the loader
    # refuses it with its own message
    assert not describe('simulator.rate_hz', 100, schema).floating_point_range
    # arrays: no ROS range, the bound in words
    noise = describe('sensors.gyro.noise_std', [0.1], schema)
    assert not noise.floating_point_range and noise.additional_constraints == 'each >= 0'


def test_unknown_keys_and_own_parameters_are_described():
    schema = known_keys([])
    assert 'not a key of the vehicle schema' in describe('observer.pole', [1.0],
                                                         schema).description
    own = describe('diagnostics_period', 1.0, schema)
    assert own.description == NODE_KEYS['diagnostics_period'].description + ' [s]'
    assert not own.read_only
    # the simulator subscribes to the recorder's topics at start, or not at all
    assert describe('wait_for_recorder', True, schema).read_only
    assert own.floating_point_range[0].from_value == 0.01
    other = describe('flush_period', 1.0, schema, 's between flushes')
    assert other.description == 's between flushes' and not other.floating_point_range


def test_own_parameter_changes_are_judged_by_the_schema():
    class P:
        def __init__(self, name, value):
            self.name, self.value = name, value
    assert own_parameter_problem([P('future_tolerance', 0.0)]) == \
        'future_tolerance: 0.0 is outside (0, 1e+09] s'
    assert own_parameter_problem([P('command_lead_steps', 101)]) == \
        'command_lead_steps: 101 is outside [0, 100]'
    assert own_parameter_problem([P('exit_when_done', 1)]).startswith('exit_when_done: expected')
    assert own_parameter_problem([P('future_tolerance', 1e-300)]) is None


# In a process of its own (rclpy's default context): the descriptors applied by rclpy
# itself, and a run-time set of keys the file did not give.
SCRIPT = """
import json, sys, warnings
warnings.filterwarnings('ignore')
import rclpy
from rclpy.parameter import Parameter
from observer_ros.nodes.common import VehicleNode
rclpy.init(args=['--ros-args', '--params-file', sys.argv[1], '-r', '__ns:=/params_test'])
node = VehicleNode('observer', own_parameters=('future_tolerance', 'diagnostics_period'))
out = {}
for key, name, value in [
        ('open_zero', 'future_tolerance', 0.0), ('open_tiny', 'future_tolerance', 1e-300),
        ('open_negative', 'future_tolerance', -1.0), ('over', 'diagnostics_period', 4000.0),
        ('absent', 'observer.history_length', 0.1),
        ('again', 'observer.history_length', -0.1),
        ('timer_rate', 'observer.rate_hz', 10.0),
        ('initial_absent_huge', 'controller.reference', [1e308, 0.0, 0.0]),
        ('bogus', 'observer.bogus', 1.0),
        ('read_only_absent', 'simulator.process_noise_std', [0.1, 0.1, 0.1]),
        ('wrong_type', 'controller.predict_timeout', 2)]:
    r = node.set_parameters_atomically([Parameter(name, value=value)])
    out[key] = [r.successful, r.reason]
out['declared'] = node.has_parameter('observer.history_length')
out['value'] = node.get_parameter('observer.history_length').value
out['not_declared'] = [n for n in ('controller.reference', 'observer.bogus',
                                   'controller.predict_timeout', 'observer.rate_hz')
                       if node.has_parameter(n)]
print(json.dumps(out))
node.destroy_node()
rclpy.shutdown()
"""


@pytest.mark.ros
def test_rclpy_applies_the_ranges_and_keys_absent_from_the_file_can_be_set():
    env = dict(__import__('os').environ, ROS_DOMAIN_ID=str(DOMAIN_ID))
    result = subprocess.run([sys.executable, '-c', SCRIPT, str(SUBMARINE)], env=env,
                            capture_output=True, text=True, timeout=WAIT, cwd=REPO)
    assert result.returncode == 0, result.stderr[-3000:]
    out = json.loads(result.stdout.splitlines()[-1])
    # a bound that excludes 0, as ROS holds it (Min value 5e-324): 0 and below refused
    assert out['open_zero'][0] is False and 'out of range' in out['open_zero'][1]
    assert out['open_tiny'] == [True, '']
    assert out['open_negative'][0] is False and out['over'][0] is False
    # observer.history_length is not in the submarine's file: declared when set, and
    # checked as a change; the rate of a timer made at start is read-only
    assert out['absent'] == [True, ''] and out['declared'] and out['value'] == 0.1
    assert out['again'] == [False, 'Parameter observer.history_length out of range Min: 0.0, '
                            'Max: 3600.0, value: -0.1']
    assert out['timer_rate'][0] is False and out['timer_rate'][1].startswith(
        'observer.rate_hz: read-only (read once, at start)')
    ok, reason = out['initial_absent_huge']
    assert not ok and reason.startswith('node /params_test/observer: controller.reference: '
                                        'element 0: 1e+308 is outside [-1e+09, 1e+09]'), reason
    ok, reason = out['bogus']
    assert not ok and reason.startswith('observer.bogus: not a parameter of '
                                        '/params_test/observer'), reason
    ok, reason = out['read_only_absent']
    assert not ok and reason.startswith('simulator.process_noise_std: read-only'), reason
    ok, reason = out['wrong_type']
    assert not ok and 'controller.predict_timeout: integer 2' in reason, reason
    assert out['not_declared'] == []


def test_schema_keys_all_have_descriptions():
    for spec in list(KNOWN_KEYS.values()) + list(SENSOR_KEYS.values()) + \
            list(NODE_KEYS.values()):
        assert spec.description and not spec.description.endswith('.'), spec.name


READ_AS_ROS = """
import json, sys, warnings
warnings.filterwarnings('ignore')
import rclpy
out = {}
for path in sys.argv[1:]:
    rclpy.init(args=['--ros-args', '--params-file', path])
    node = rclpy.create_node('reader', automatically_declare_parameters_from_overrides=True)
    out[path] = {name: (list(p.value) if isinstance(p.value, (list, tuple)) or
                        type(p.value).__name__ == 'array' else p.value)
                 for name, p in node._parameters.items() if name != 'use_sim_time'}
    node.destroy_node()
    rclpy.shutdown()
print(json.dumps(out))
"""


@pytest.mark.ros
def test_ros_reads_every_shipped_file_as_the_loader_does():
    """Read every shipped file with ROS's own parser (rcl): the loader's values (bare N: false)."""
    env = dict(__import__('os').environ, ROS_DOMAIN_ID=str(DOMAIN_ID))
    paths = [str(p) for p in sorted(CONFIG.glob('*.yaml'))]
    result = subprocess.run([sys.executable, '-c', READ_AS_ROS, *paths], env=env,
                            capture_output=True, text=True, timeout=WAIT, cwd=REPO)
    assert result.returncode == 0, result.stderr[-3000:]
    by_ros = json.loads(result.stdout.splitlines()[-1])
    for path in paths:
        ours = {k: list(v) if isinstance(v, tuple) else v
                for k, v in load_parameters(path).items()}
        theirs = {k: v for k, v in by_ros[path].items() if k != 'start_type_description_service'}
        assert theirs == ours, path
