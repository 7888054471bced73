# observer_ros.vehicle: the vehicle file, described once: schema, checks, loading, writing.
"""
Load and check a vehicle: a ROS 2 parameters file, or a node's parameters.

A vehicle file is an ordinary ROS 2 parameters file (``/**:`` then ``ros__parameters:``)
whose nested keys become dotted parameter names (``model.A``). Offline tools call
:func:`load_vehicle`; nodes pass their own parameters (plain Python values) to
:func:`vehicle_from_parameters`. Both end in the same checks, and every refusal is a
:class:`VehicleFileError` whose message starts with the offending parameter's name.
No ROS imports: this package is used offline too.

- :mod:`.schema`: every key, its type, default and meaning (:data:`KNOWN_KEYS`,
  :data:`SENSOR_KEYS`; docs/vehicle_schema.md).
- :mod:`.checker`: typed reads that name the refused parameter; the loader's warnings.
- :mod:`.load`: :func:`load_vehicle`, :func:`vehicle_from_parameters`.
- :mod:`.overrides`: ``key:=value`` overrides; :mod:`.write`: the way back to a file.

"""

from .load import load_vehicle, vehicle_from_parameters
from .overrides import apply_overrides, parse_override
from .schema import (KeySpec, KNOWN_KEYS, known_keys, parameter_schema, ParameterInfo,
                     ROS_RESERVED_KEYS, SENSOR_KEYS)
from .write import parameters_to_yaml, vehicle_to_parameters
from ..params_file import flatten_parameters, load_parameters
from ..sensors import extract_measurement, fill_measurement, MeasurementError, parse_field

__all__ = ['KeySpec', 'ParameterInfo', 'KNOWN_KEYS', 'SENSOR_KEYS', 'ROS_RESERVED_KEYS',
           'known_keys', 'parameter_schema', 'load_vehicle', 'load_parameters',
           'vehicle_from_parameters', 'vehicle_to_parameters', 'apply_overrides',
           'parse_override', 'parameters_to_yaml', 'flatten_parameters',
           'MeasurementError', 'extract_measurement', 'fill_measurement', 'parse_field']
