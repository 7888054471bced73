# The descriptors the nodes declare their parameters with (no DDS: built from the schema).
"""Each parameter's ParameterDescriptor: the schema's description, read_only, range."""

from observer_ros.nodes.parameters import describe, READ_ONLY_SECTIONS
from observer_ros.vehicle import known_keys, load_parameters
import pytest
from ros_helpers import CONFIG


@pytest.mark.parametrize('path', sorted(CONFIG.glob('*.yaml')), ids=lambda p: p.name)
def test_every_vehicle_key_gets_the_schema_description(path):
    flat = load_parameters(path)
    schema = known_keys(flat['sensors.names'])
    for name, value in flat.items():
        descriptor = describe(name, value, schema)
        spec = schema[name]
        assert descriptor.description.startswith(spec.description), name
        assert descriptor.read_only == (name.split('.')[0] in READ_ONLY_SECTIONS), name


def test_what_cannot_change_while_running_is_read_only():
    schema = known_keys(['gyro'])
    for name in ('model.A', 'model.states', 'model.inputs', 'model.outputs', 'sensors.names',
                 'sensors.gyro.topic', 'vehicle.name', 'simulator.mode'):
        assert describe(name, 'x', schema).read_only, name
    for name in ('observer.poles', 'controller.poles', 'controller.stale_timeout'):
        assert not describe(name, [1.0], schema).read_only, name


def test_scalars_with_a_bound_get_a_range_of_their_type():
    schema = known_keys(['gyro'])
    rate = describe('simulator.rate_hz', 100.0, schema)
    assert rate.floating_point_range[0].from_value == 0.0
    assert not rate.integer_range
    divider = describe('sensors.gyro.rate_divider', 2, schema)
    assert divider.integer_range[0].from_value == 1 and divider.integer_range[0].step == 1
    # a value of another type (an integer written for a double): no range; the loader
    # refuses it with its own message
    assert not describe('simulator.rate_hz', 100, schema).floating_point_range


def test_unknown_keys_and_own_parameters_are_described():
    schema = known_keys([])
    assert 'not a key of the vehicle schema' in describe('observer.pole', [1.0],
                                                         schema).description
    own = describe('diagnostics_period', 1.0, schema, 's between reports')
    assert own.description == 's between reports' and not own.read_only
