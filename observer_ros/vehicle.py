# observer_ros.vehicle: the one loader of vehicle files, for nodes and offline tools alike.
"""
Load and check a vehicle: a ROS 2 parameters file, or a node's parameters.

A vehicle file is an ordinary ROS 2 parameters file (``/**:`` then ``ros__parameters:``)
whose nested keys become dotted parameter names (``model.A``). Offline tools call
:func:`load_vehicle`; nodes pass their own parameters (plain Python values) to
:func:`vehicle_from_parameters`. Both end in the same checks, and every refusal is a
:class:`VehicleFileError` whose message starts with the offending parameter's name.
The schema is :data:`KNOWN_KEYS` and :data:`SENSOR_KEYS` (documented in
docs/vehicle_schema.md). No ROS imports: this module is used offline too.

"""

import array
from dataclasses import dataclass
import difflib
import math
import numbers
import re
from typing import NamedTuple, Tuple

import numpy as np
import yaml

from .core.errors import ObserverError, VehicleFileError
from .core.model import as_poles, Plant
from .core.spec import (ControllerSpec, HISTORY_LENGTH, OBSERVER_TYPES, ObserverSpec,
                        SENSOR_TYPES, SensorSpec, SimulatorSpec, Vehicle)
from .params_file import _yaml_load, flatten_parameters, load_parameters
from .sensors import (extract_measurement, fill_measurement, MeasurementError,
                      parse_field)

__all__ = ['KeySpec', 'ParameterInfo', 'KNOWN_KEYS', 'SENSOR_KEYS', 'ROS_RESERVED_KEYS',
           'known_keys', 'parameter_schema', 'load_vehicle', 'load_parameters',
           'vehicle_from_parameters', 'vehicle_to_parameters', 'apply_overrides',
           'parse_override', 'parameters_to_yaml', 'flatten_parameters',
           'MeasurementError', 'extract_measurement', 'fill_measurement', 'parse_field']

# -- the schema ---------------------------------------------------------------------------

STRING = 'STRING'
STRING_ARRAY = 'STRING_ARRAY'
DOUBLE = 'DOUBLE'
DOUBLE_ARRAY = 'DOUBLE_ARRAY'
INTEGER = 'INTEGER'
BOOL = 'BOOL'


@dataclass(frozen=True)
class KeySpec:
    """
    One parameter of the vehicle schema.

    ``param_type`` is the name of the rclpy ``Parameter.Type`` member (``DOUBLE_ARRAY``,
    ...), so a node can declare it with ``Parameter.Type[spec.param_type]``. ``default``
    is None for a required parameter and for an optional one without a default.

    """

    name: str
    param_type: str
    description: str
    required: bool = False
    default: object = None
    choices: Tuple[str, ...] = ()
    minimum: object = None      # scalars: the least value (a node declares it as a range)


class ParameterInfo(NamedTuple):
    """A parameter as a node declares it: name, type, default (or None), description."""

    name: str
    param_type: str
    default: object
    description: str


def _keys(*specs):
    return {spec.name: spec for spec in specs}


KNOWN_KEYS = _keys(
    KeySpec('vehicle.name', STRING, 'short name (letters, digits, _ . -), used in bag and '
            'report names', required=True),
    KeySpec('vehicle.description', STRING, 'one line', default=''),
    KeySpec('vehicle.source', STRING, 'where the numbers come from (seed, paper)',
            default=''),
    KeySpec('model.time_domain', STRING, 'continuous or discrete', default='continuous',
            choices=('continuous', 'discrete')),
    KeySpec('model.sample_time', DOUBLE, 's; required (> 0) for a discrete model',
            minimum=0.0),
    KeySpec('model.states', STRING_ARRAY, 'state names (n)', required=True),
    KeySpec('model.inputs', STRING_ARRAY, 'input names (m)', required=True),
    KeySpec('model.outputs', STRING_ARRAY, 'output names (p)', required=True),
    KeySpec('model.A', DOUBLE_ARRAY, 'n x n, row-major', required=True),
    KeySpec('model.B', DOUBLE_ARRAY, 'n x m, row-major', required=True),
    KeySpec('model.C', DOUBLE_ARRAY, 'p x n, row-major', required=True),
    KeySpec('model.D', DOUBLE_ARRAY, 'p x m, row-major; default zeros'),
    KeySpec('sensors.names', STRING_ARRAY, 'the sensors; each has sensors.<name>.* keys',
            required=True),
    KeySpec('observer.type', STRING, 'full, reduced, open_loop or kalman', required=True,
            choices=OBSERVER_TYPES),
    KeySpec('observer.poles', DOUBLE_ARRAY, 'real parts of the observer poles'),
    KeySpec('observer.poles_imag', DOUBLE_ARRAY, 'imaginary parts; default all 0'),
    KeySpec('observer.gain', DOUBLE_ARRAY, 'L given directly: n x p (full) or '
            '(n-p) x p (reduced), row-major'),
    KeySpec('observer.method', STRING, 'pole placement: auto, place or acker',
            default='auto', choices=('auto', 'place', 'acker')),
    KeySpec('observer.Qd', DOUBLE_ARRAY, 'kalman: k x k process noise covariance; '
            'default diag(simulator.process_noise_std**2)'),
    KeySpec('observer.Rd', DOUBLE_ARRAY, 'kalman: p x p measurement noise covariance; '
            'default diag(noise_std**2) of the sensors'),
    KeySpec('observer.Bd', DOUBLE_ARRAY, 'kalman: n x k process noise input; '
            'default identity'),
    KeySpec('observer.initial_estimate', DOUBLE_ARRAY, 'x_hat(0) (n); default zeros'),
    KeySpec('observer.rate_hz', DOUBLE, 'Hz, prediction-only publish rate; default the '
            'simulator rate', minimum=0.0),
    KeySpec('observer.history_length', DOUBLE, 's, >= 0: late messages this much older '
            'than the estimate are used at their stamps (0: refused)', default=HISTORY_LENGTH,
            minimum=0.0),
    KeySpec('observer.publish_rate_hz', DOUBLE, 'Hz, > 0: also publish the estimate '
            'predicted to now at this rate (free-running); default off', minimum=0.0),
    KeySpec('controller.poles', DOUBLE_ARRAY, 'real parts of eig(A - B K) (n)'),
    KeySpec('controller.poles_imag', DOUBLE_ARRAY, 'imaginary parts; default all 0'),
    KeySpec('controller.K', DOUBLE_ARRAY, 'm x n, row-major'),
    KeySpec('controller.lqr_Q', DOUBLE_ARRAY, 'LQR state weight, n x n'),
    KeySpec('controller.lqr_R', DOUBLE_ARRAY, 'LQR input weight, m x m'),
    KeySpec('controller.reference', DOUBLE_ARRAY, 'x_d (n); default zeros'),
    KeySpec('controller.Kd', DOUBLE_ARRAY, 'feedforward, m x n; default zeros'),
    KeySpec('controller.u_min', DOUBLE_ARRAY, 'input lower limits (m); default none'),
    KeySpec('controller.u_max', DOUBLE_ARRAY, 'input upper limits (m); default none'),
    KeySpec('controller.safe_command', STRING, 'zero or hold', default='zero',
            choices=('zero', 'hold')),
    KeySpec('controller.stale_timeout', DOUBLE, 's, > 0', default=0.5, minimum=0.0),
    KeySpec('controller.predict_timeout', DOUBLE, 's, >= 0: predict-and-hold before the '
            'safe_command fallback', default=0.0, minimum=0.0),
    KeySpec('controller.delay_compensation', BOOL, 'realtime: predict a late estimate to '
            'when its command takes effect, and stamp the command with that time',
            default=False),
    KeySpec('simulator.rate_hz', DOUBLE, 'Hz, > 0; a discrete model runs at '
            '1/sample_time', default=100.0, minimum=0.0),
    KeySpec('simulator.initial_state', DOUBLE_ARRAY, 'x(0) (n); default zeros'),
    KeySpec('simulator.duration', DOUBLE, 's, >= 0; 0: the simulator node runs until '
            'stopped', default=10.0, minimum=0.0),
    KeySpec('simulator.seed', INTEGER, 'noise seed, >= 0', default=0, minimum=0),
    KeySpec('simulator.noise', BOOL, 'add the sensors noise_std', default=True),
    KeySpec('simulator.process_noise_std', DOUBLE_ARRAY, 'per state (n); default none'),
    KeySpec('simulator.mode', STRING, 'lockstep or realtime', default='lockstep',
            choices=('lockstep', 'realtime')),
    KeySpec('simulator.realtime_factor', DOUBLE, '> 0', default=1.0, minimum=0.0),
    KeySpec('simulator.command_timeout', DOUBLE, 's, > 0', default=2.0, minimum=0.0),
    KeySpec('simulator.publish_clock', BOOL, 'publish /clock (one vehicle per ROS graph)',
            default=True),
)

# Per-sensor keys: sensors.<s>.<key> for each <s> in sensors.names.
SENSOR_KEYS = _keys(
    KeySpec('topic', STRING, 'relative topic name', required=True),
    KeySpec('type', STRING, 'message type', required=True, choices=SENSOR_TYPES),
    KeySpec('fields', STRING_ARRAY, 'message fields read, one per output', required=True),
    KeySpec('outputs', STRING_ARRAY, 'the model outputs they are', required=True),
    KeySpec('noise_std', DOUBLE_ARRAY, 'noise standard deviation per field, >= 0',
            required=True),
    KeySpec('timeout', DOUBLE, 's, > 0', default=0.5, minimum=0.0),
    KeySpec('rate_divider', INTEGER, 'published every k-th simulator step, >= 1',
            default=1, minimum=1),
    KeySpec('frame_id', STRING, 'header.frame_id', default='base_link'),
)

# Parameters every ROS 2 node has; never vehicle keys, never warned about.
ROS_RESERVED_KEYS = ('use_sim_time', 'start_type_description_service')
_ROS_RESERVED_PREFIXES = ('qos_overrides.',)


def known_keys(sensor_names=()):
    """
    Return the full schema for the given sensors.

    Parameters
    ----------
    sensor_names : sequence of str
        The entries of ``sensors.names``.

    Returns
    -------
    keys : dict
        Parameter name to :class:`KeySpec`, ``sensors.<s>.*`` expanded for each sensor.

    """
    keys = dict(KNOWN_KEYS)
    for sensor in sensor_names:
        for sub, spec in SENSOR_KEYS.items():
            name = f'sensors.{sensor}.{sub}'
            keys[name] = KeySpec(name, spec.param_type, spec.description, spec.required,
                                 spec.default, spec.choices, spec.minimum)
    return keys


def parameter_schema(sensor_names=()):
    """
    List the vehicle parameters as a node declares them.

    Parameters
    ----------
    sensor_names : sequence of str
        The entries of ``sensors.names`` (their ``sensors.<s>.*`` keys are included).

    Returns
    -------
    params : list of ParameterInfo
        ``(name, param_type, default, description)``; ``param_type`` names an rclpy
        ``Parameter.Type`` member; ``default`` is None where there is none (required
        parameters say so in the description).

    """
    out = []
    for spec in known_keys(sensor_names).values():
        text = spec.description + ('; required' if spec.required else '')
        out.append(ParameterInfo(spec.name, spec.param_type, spec.default, text))
    return out


def load_vehicle(path, node_name=None, overrides=None, extra_keys=()):
    """
    Load and check a vehicle file.

    Parameters
    ----------
    path : str or path-like
        A ROS 2 parameters file (``config/submarine.yaml``).
    node_name : str, optional
        Also merge the section of this node over ``/**`` (see :func:`load_parameters`).
    overrides : dict or list of str, optional
        Applied after reading, as by :func:`apply_overrides` (``["observer.type:=kalman"]``).
    extra_keys : sequence of str
        Further parameter names that are not warned about (a node's own parameters).

    Returns
    -------
    vehicle : Vehicle
        With ``warnings`` for unknown or unused keys.

    Raises
    ------
    VehicleFileError
        The file cannot be read or is invalid; the message names the file and field.

    """
    flat = load_parameters(path, node_name)
    if overrides:
        flat = apply_overrides(flat, overrides)
    return vehicle_from_parameters(flat, source=str(path), extra_keys=extra_keys)


# -- overrides and writing ----------------------------------------------------------------

def parse_override(text):
    """
    Parse one ``key:=value`` override (the value is YAML, as on a ROS command line).

    Returns
    -------
    key, value : str, object
        ``value`` is None for ``key:=null`` (remove the key).

    """
    if not isinstance(text, str) or ':=' not in text:
        raise VehicleFileError(f'override {text!r}: expected key:=value')
    key, _, value = text.partition(':=')
    key = key.strip()
    if not key:
        raise VehicleFileError(f'override {text!r}: empty parameter name')
    return key, _yaml_load(value, f'override {key}')


def apply_overrides(flat, overrides):
    """
    Return a copy of a flat parameter dict with overrides applied.

    Parameters
    ----------
    flat : dict
        Dotted parameter names to values.
    overrides : dict or sequence of str
        A dict of values, or ``"key:=value"`` strings whose values are parsed as YAML
        (``"observer.type:=kalman"``, ``"observer.poles:=[-1.0, -2.0]"``). A mapping
        value is flattened under its key; a null value removes the key.

    Returns
    -------
    flat : dict
        A new dict; the input is not changed.

    """
    if isinstance(overrides, dict):
        items = list(overrides.items())
    elif isinstance(overrides, str):
        items = [parse_override(overrides)]
    else:
        items = [parse_override(text) for text in overrides]
    out = dict(flat)
    for key, value in items:
        if not isinstance(key, str) or not key:
            raise VehicleFileError(f'override key {key!r} is not a parameter name')
        if isinstance(value, dict):
            value = flatten_parameters(value, key, where=f'override {key}')
            for name in [k for k in out if k == key or k.startswith(key + '.')]:
                del out[name]
            out.update(value)
        elif value is None:
            out.pop(key, None)
        else:
            out[key] = value
    return out


def parameters_to_yaml(flat, node_key='/**'):
    """
    Write a flat parameter dict as a ROS 2 parameters file.

    Parameters
    ----------
    flat : dict
        Dotted names to plain values (as :func:`vehicle_to_parameters` gives).
    node_key : str
        The section key; ``/**`` applies to every node.

    Returns
    -------
    text : str
        YAML for ``--params-file`` and :func:`load_vehicle`.

    """
    tree = {}
    for name, value in flat.items():
        node = tree
        parts = name.split('.')
        for part in parts[:-1]:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise VehicleFileError(f'{name}: its prefix is also a parameter')
        if parts[-1] in node and isinstance(node[parts[-1]], dict):
            raise VehicleFileError(f'{name}: is also a prefix of other parameters')
        node[parts[-1]] = value
    return yaml.safe_dump({node_key: {'ros__parameters': tree}}, sort_keys=False,
                          default_flow_style=None, width=99)


# -- checking -----------------------------------------------------------------------------

_NAME_RE = re.compile(r'^[A-Za-z0-9_.-]+$')
_SENSOR_NAME_RE = re.compile(r'^[A-Za-z_][A-Za-z0-9_]*$')
_TOPIC_TOKEN_RE = re.compile(r'^(?:[A-Za-z_][A-Za-z0-9_]*|\{[A-Za-z_]+\})$')


def _preview(values, limit=4):
    shown = ', '.join(repr(v) for v in values[:limit])
    return f'[{shown}, ...]' if len(values) > limit else f'[{shown}]'


def _is_bool(value):
    return isinstance(value, (bool, np.bool_))


def _is_int(value):
    return isinstance(value, numbers.Integral) and not _is_bool(value)


def _is_real(value):
    return isinstance(value, numbers.Real) and not _is_bool(value)


def _as_list(value):
    """Return value as a list if it is a sequence parameter value, else None."""
    if isinstance(value, (list, tuple)):
        return list(value)
    if isinstance(value, array.array):
        return value.tolist()
    if isinstance(value, np.ndarray) and value.ndim == 1:
        return value.tolist()
    return None


def _describe(value):
    if isinstance(value, str):
        return f'string {_short(value)}'
    if _is_bool(value):
        return f'boolean {value!r}'
    return f'{type(value).__name__} {_short(value)}'


def _short(value, limit=60):
    text = repr(value)
    return text if len(text) <= limit else text[:limit - 3] + '...'


class _Checker:
    """Reads typed values from a flat dict; every refusal names the parameter."""

    def __init__(self, flat, source):
        self.flat = flat
        self.prefix = f'{source}: ' if source else ''

    def fail(self, key, message):
        raise VehicleFileError(f'{self.prefix}{key}: {message}')

    def given(self, key):
        return key in self.flat

    def _raw(self, key, spec, required):
        if key in self.flat:
            return self.flat[key], True
        if required:
            self.fail(key, 'missing (required)')
        return (spec.default if spec is not None else None), False

    def string(self, key, spec=None, required=None, allow_empty=False):
        spec = spec or KNOWN_KEYS.get(key)
        required = spec.required if required is None else required
        value, given = self._raw(key, spec, required)
        if not given:
            return value
        if not isinstance(value, str):
            self.fail(key, f'expected a string; got {_describe(value)}')
        if spec is not None and spec.choices and value not in spec.choices:
            self.fail(key, f'{value!r} is not one of {list(spec.choices)}')
        if not value and not allow_empty:
            self.fail(key, 'empty string')
        return value

    def string_array(self, key, spec=None, required=None, unique=True):
        spec = spec or KNOWN_KEYS.get(key)
        required = spec.required if required is None else required
        value, given = self._raw(key, spec, required)
        if not given:
            return None
        items = _as_list(value)
        if items is None:
            self.fail(key, f'expected a list of strings; got {_describe(value)}')
        if not items:
            self.fail(key, 'empty list')
        for item in items:
            if not isinstance(item, str):
                hint = ' (quote it)' if _is_bool(item) or item is None else ''
                self.fail(key, f'expected strings; got {_describe(item)}{hint}')
            if not item or item != item.strip():
                self.fail(key, f'name {item!r} is empty or has surrounding spaces')
        if unique:
            dup = [item for i, item in enumerate(items) if item in items[:i]]
            if dup:
                self.fail(key, f'duplicate name {dup[0]!r} in {items}')
        return tuple(items)

    def double_array(self, key, spec=None, required=None, allow_inf=False):
        """Return a list of floats, or None when the key is absent (or an empty list)."""
        spec = spec or KNOWN_KEYS.get(key)
        required = spec.required if required is None else required
        value, given = self._raw(key, spec, required)
        if not given:
            return None
        items = _as_list(value)
        if items is None:
            self.fail(key, f'expected a list of floats; got {_describe(value)}')
        if not items:
            if required:
                self.fail(key, 'empty list (required)')
            return None
        ints = [v for v in items if _is_int(v)]
        bad = [v for v in items if not _is_real(v)]
        if bad:
            self.fail(key, f'expected floats; got {_describe(bad[0])}')
        if ints:
            kind = 'integer array' if len(ints) == len(items) else \
                'mixed integer and float array'
            self.fail(key, f'{kind} {_preview(items)}; double arrays must be written as '
                      'floats (1.0, not 1)')
        out = [float(v) for v in items]
        for i, v in enumerate(out):
            if math.isnan(v) or (math.isinf(v) and not allow_inf):
                self.fail(key, f'element {i} is {v}; values must be finite')
        return out

    def double(self, key, spec=None, required=None, minimum=None, positive=False):
        spec = spec or KNOWN_KEYS.get(key)
        required = spec.required if required is None else required
        value, given = self._raw(key, spec, required)
        if not given:
            return value
        if _is_int(value):
            self.fail(key, f'integer {value!r}; doubles must be written as floats '
                      f'({value}.0, not {value})')
        if not _is_real(value):
            self.fail(key, f'expected a float; got {_describe(value)}')
        value = float(value)
        if not math.isfinite(value):
            self.fail(key, f'{value} is not finite')
        if positive and not value > 0.0:
            self.fail(key, f'{value} must be > 0')
        if minimum is not None and value < minimum:
            self.fail(key, f'{value} must be >= {minimum}')
        return value

    def integer(self, key, spec=None, required=None, minimum=None):
        spec = spec or KNOWN_KEYS.get(key)
        required = spec.required if required is None else required
        value, given = self._raw(key, spec, required)
        if not given:
            return value
        if not _is_int(value):
            self.fail(key, f'expected an integer; got {_describe(value)}')
        value = int(value)
        if minimum is not None and value < minimum:
            self.fail(key, f'{value} must be >= {minimum}')
        if value >= 2 ** 63:
            self.fail(key, f'{value} does not fit a 64-bit integer')
        return value

    def boolean(self, key, spec=None):
        spec = spec or KNOWN_KEYS.get(key)
        value, given = self._raw(key, spec, spec.required if spec else False)
        if not given:
            return value
        if not _is_bool(value):
            self.fail(key, f'expected true or false; got {_describe(value)}')
        return bool(value)

    def matrix(self, key, rows, cols, labels, required=None, values=None):
        """Row-major rows x cols matrix; labels = ('outputs', 'states') for the message."""
        if values is None:
            values = self.double_array(key, required=required)
        if values is None:
            return None
        if len(values) != rows * cols:
            self.fail(key, f'has {len(values)} values; expected {rows * cols} '
                      f'({labels[0]} x {labels[1]} = {rows}x{cols})')
        return np.array(values, dtype=float).reshape(rows, cols)

    def vector(self, key, size, label, allow_inf=False):
        values = self.double_array(key, allow_inf=allow_inf)
        if values is None:
            return None
        if len(values) != size:
            self.fail(key, f'has {len(values)} values; expected {size} ({label})')
        return np.array(values, dtype=float)

    def symmetric(self, key, M, definite):
        """
        Return M symmetrised, refusing one that is not symmetric positive (semi)definite.

        Symmetric to round-off (``|M - M^T| <= 1e-9 max(1, |M|)``) is made exactly
        symmetric, ``(M + M^T) / 2``: the Riccati solvers demand symmetry to the last bit.

        """
        if not np.all(np.isfinite(M)):
            self.fail(key, 'has values that are not finite (too large to square?)')
        scale = max(1.0, float(np.max(np.abs(M))))
        if np.max(np.abs(M - M.T)) > 1e-9 * scale:
            self.fail(key, 'must be symmetric')
        try:
            eig = np.linalg.eigvalsh(M / scale)
        except (np.linalg.LinAlgError, ValueError):
            self.fail(key, 'eigenvalues cannot be computed')
        if definite and not np.min(eig) > 1e-12:
            self.fail(key, f'must be positive definite (smallest eigenvalue '
                      f'{np.min(eig) * scale:.3g})')
        if not definite and np.min(eig) < -1e-9:
            self.fail(key, f'must be positive semidefinite (smallest eigenvalue '
                      f'{np.min(eig) * scale:.3g})')
        return (M + M.T) / 2.0

    def poles(self, prefix, count, exact, count_label, discrete):
        """Complex poles from <prefix>.poles and <prefix>.poles_imag, or None."""
        key, key_imag = f'{prefix}.poles', f'{prefix}.poles_imag'
        real = self.double_array(key)
        imag = self.double_array(key_imag)
        if real is None:
            if imag is not None:
                self.fail(key_imag, f'given without {key}')
            return None
        if imag is None:
            imag = [0.0] * len(real)
        if len(imag) != len(real):
            self.fail(key_imag, f'has {len(imag)} values; expected {len(real)} (one per '
                      f'pole in {key})')
        if exact and len(real) != count:
            self.fail(key, f'has {len(real)} poles; expected {count} ({count_label})')
        if not exact and len(real) > count:
            self.fail(key, f'has {len(real)} poles; expected at most {count} '
                      f'({count_label})')
        try:
            return as_poles(np.array(real) + 1j * np.array(imag), key, discrete=discrete)
        except ObserverError as err:
            text = str(err)
            text = text[len(key):].lstrip(': ') if text.startswith(key) else text
            self.fail(key, text)


def _warn_unloadable_strings(flat, warnings):
    """
    Warn about strings that `ros2 param load` of a dump would not give back.

    rclpy's parameter-file reader (parameter_dict_from_yaml_file, Jazzy) reads each value
    again as YAML: ``'a: b'`` becomes a mapping and the load ends in a TypeError, ``'1.0'``
    a double.
    """
    for name, value in sorted(flat.items()):
        for text in value if isinstance(value, (list, tuple)) else [value]:
            if not isinstance(text, str):
                continue
            try:
                same = yaml.safe_load(text) == text
            except yaml.parser.ParserError:     # rclpy keeps the text as it is
                same = True
            except yaml.YAMLError:
                same = False
            if not same:
                warnings.append(f'{name}: {_short(text)!r} would not survive `ros2 param '
                                'dump` then `ros2 param load` (rclpy reads it again as YAML: '
                                'avoid ": ", " #", and strings that look like numbers)')
                break


def _warn_unknown(flat, sensor_names, extra_keys, warnings):
    known = known_keys(sensor_names)
    candidates = list(known)
    for key in flat:
        if key in known or key in extra_keys or key in ROS_RESERVED_KEYS or \
                key.startswith(_ROS_RESERVED_PREFIXES):
            continue
        text = f'unknown key {key}'
        parts = key.split('.')
        if parts[0] == 'sensors' and len(parts) == 3 and parts[1] not in sensor_names \
                and parts[2] in SENSOR_KEYS:
            text += f" (sensor '{parts[1]}' is not in sensors.names {list(sensor_names)})"
        else:
            match = difflib.get_close_matches(key, candidates, n=1, cutoff=0.6)
            if match:
                text += f' (did you mean {match[0]}?)'
        warnings.append(text)


def _warn_unused(check, keys, reason, warnings):
    for key in keys:
        if key in check.flat:
            spec = KNOWN_KEYS.get(key)
            value = check.flat[key]
            if spec is not None and isinstance(value, str) and value == spec.default:
                continue
            warnings.append(f'{key} is not used {reason} (ignored)')


def vehicle_from_parameters(flat, source='', extra_keys=()):
    """
    Build and check a vehicle from flat parameters.

    Parameters
    ----------
    flat : mapping
        Dotted parameter names (``model.A``) to plain values: str, bool, int, float, or
        lists (also ``array.array`` and 1-D numpy arrays, as rclpy gives) of those. A
        value of None counts as absent (an unset ROS parameter).
    source : str
        Where the parameters come from (a file path, a node name); prefixed to errors.
    extra_keys : sequence of str
        Further names that are not warned about (a node's own parameters).
        ``use_sim_time`` and other ROS parameters are never warned about.

    Returns
    -------
    vehicle : Vehicle
        Checked for structure: shapes, types, names, sensors covering each output once,
        poles in conjugate pairs. Observability and controllability are the design's.

    Raises
    ------
    VehicleFileError
        The message starts with the source and the parameter name
        (``model.C: has 4 values; expected 3 (outputs x states = 1x3)``).

    """
    prefix = f'{source}: ' if source else ''
    try:
        items = list(flat.items())
    except AttributeError:
        raise VehicleFileError(f'{prefix}parameters must be a dict; got '
                               f'{type(flat).__name__}') from None
    for key, _ in items:
        if not isinstance(key, str) or not key:
            raise VehicleFileError(f'{prefix}parameter name {key!r} is not a string')
    flat = {key: value for key, value in items if value is not None}
    check = _Checker(flat, source)
    warnings = []

    sensor_names = check.string_array('sensors.names')
    for name in sensor_names:
        if not _SENSOR_NAME_RE.match(name) or name == 'names':
            check.fail('sensors.names', f'sensor name {name!r} must be letters, digits and _, '
                       "and not 'names' (it is part of parameter names)")
    _warn_unknown(flat, sensor_names, set(extra_keys), warnings)
    _warn_unloadable_strings(flat, warnings)

    # vehicle
    name = check.string('vehicle.name')
    if not _NAME_RE.match(name):
        check.fail('vehicle.name', f'{name!r} may hold only letters, digits, _ . and -')
    description = check.string('vehicle.description', allow_empty=True)
    source_text = check.string('vehicle.source', allow_empty=True)

    plant, discrete = _read_model(check, warnings)
    sensors = _read_sensors(check, plant, sensor_names)
    simulator = _read_simulator(check, plant, discrete)
    controller = _read_controller(check, plant, discrete)
    observer = _read_observer(check, plant, discrete, sensors, simulator, warnings)
    return Vehicle(name=name, plant=plant, sensors=sensors, observer=observer,
                   controller=controller, simulator=simulator, description=description,
                   source=source_text, warnings=tuple(warnings), origin=source)


def _read_model(check, warnings):
    domain = check.string('model.time_domain')
    discrete = domain == 'discrete'
    dt = None
    if discrete:
        dt = check.double('model.sample_time', required=True, positive=True)
    else:
        _warn_unused(check, ['model.sample_time'], 'by a continuous model', warnings)
    states = check.string_array('model.states')
    inputs = check.string_array('model.inputs')
    outputs = check.string_array('model.outputs')
    n, m, p = len(states), len(inputs), len(outputs)
    A = check.matrix('model.A', n, n, ('states', 'states'))
    B = check.matrix('model.B', n, m, ('states', 'inputs'))
    C = check.matrix('model.C', p, n, ('outputs', 'states'))
    D = check.matrix('model.D', p, m, ('outputs', 'inputs'))
    try:
        plant = Plant(A, B, C, D, dt, states, inputs, outputs)
    except ObserverError as err:   # pre-checked above; kept as a safety net
        check.fail('model', str(err))
    return plant, discrete


def _read_sensors(check, plant, sensor_names):
    specs = []
    owner = {}          # output -> sensor
    topics = {}         # topic -> sensor
    for sensor in sensor_names:
        key = f'sensors.{sensor}.'

        def spec(sub):
            return SENSOR_KEYS[sub]

        topic = check.string(key + 'topic', spec('topic'))
        if not _valid_topic(topic):
            check.fail(key + 'topic', f'{topic!r} is not a valid ROS topic name')
        if topic in topics:
            check.fail(key + 'topic', f'topic {topic!r} is already used by sensor '
                       f'{topics[topic]}')
        topics[topic] = sensor
        msg_type = check.string(key + 'type', spec('type'))
        fields = check.string_array(key + 'fields', spec('fields'))
        for field in fields:
            try:
                parse_field(msg_type, field)
            except VehicleFileError as err:
                check.fail(key + 'fields', str(err))
        outputs = check.string_array(key + 'outputs', spec('outputs'))
        if len(outputs) != len(fields):
            check.fail(key + 'outputs', f'has {len(outputs)} names; expected '
                       f'{len(fields)} (one per field in {key}fields)')
        for output in outputs:
            if output not in plant.output_names:
                check.fail(key + 'outputs', f'unknown output {output!r}; outputs are '
                           f'[{", ".join(plant.output_names)}]')
            if output in owner:
                check.fail(key + 'outputs', f'output {output!r} is already measured by '
                           f'sensor {owner[output]}; each output has exactly one sensor')
            owner[output] = sensor
        noise = check.double_array(key + 'noise_std', spec('noise_std'))
        if len(noise) != len(fields):
            check.fail(key + 'noise_std', f'has {len(noise)} values; expected '
                       f'{len(fields)} (one per field in {key}fields)')
        if min(noise) < 0.0:
            check.fail(key + 'noise_std', f'{min(noise)} is negative')
        timeout = check.double(key + 'timeout', spec('timeout'), positive=True)
        divider = check.integer(key + 'rate_divider', spec('rate_divider'), minimum=1)
        frame_id = check.string(key + 'frame_id', spec('frame_id'))
        specs.append(SensorSpec(name=sensor, topic=topic, msg_type=msg_type, fields=fields,
                                outputs=outputs, noise_std=np.array(noise), timeout=timeout,
                                rate_divider=divider, frame_id=frame_id))
    missing = [output for output in plant.output_names if output not in owner]
    if missing:
        check.fail('model.outputs', f'output {missing[0]!r} is measured by no sensor (list '
                   "it in one sensor's outputs)")
    return tuple(specs)


def _valid_topic(topic):
    """Check a topic name against the ROS 2 rules (tokens of [A-Za-z0-9_], ~/ or /)."""
    if topic.startswith('~/'):
        name = topic[2:]
    elif topic.startswith('/'):
        name = topic[1:]
    else:
        name = topic
    if not name or name.endswith('/'):
        return False
    return all(_TOPIC_TOKEN_RE.match(token) for token in name.split('/'))


def _read_simulator(check, plant, discrete):
    n = plant.n
    if discrete:
        rate = 1.0 / plant.dt if plant.dt > 1e-12 else math.inf
        if not math.isfinite(rate):
            check.fail('model.sample_time', f'{plant.dt} s is too small')
        if check.given('simulator.rate_hz'):
            given = check.double('simulator.rate_hz', positive=True)
            if abs(given - rate) > 1e-9 * rate:
                check.fail('simulator.rate_hz', f'{given} Hz does not match model.sample_time '
                           f'{plant.dt} s (a discrete model runs at 1/sample_time = '
                           f'{rate:g} Hz)')
    else:
        rate = check.double('simulator.rate_hz', positive=True)
    initial = check.vector('simulator.initial_state', n, 'states')
    duration = check.double('simulator.duration', minimum=0.0)
    if 0.0 < duration * rate < 1.0:
        check.fail('simulator.duration', f'{duration} s is shorter than one step '
                   f'(1/{rate:g} Hz)')
    seed = check.integer('simulator.seed', minimum=0)
    noise = check.boolean('simulator.noise')
    process = check.vector('simulator.process_noise_std', n, 'states')
    if process is not None and np.min(process) < 0.0:
        check.fail('simulator.process_noise_std', f'{np.min(process)} is negative')
    mode = check.string('simulator.mode')
    factor = check.double('simulator.realtime_factor', positive=True)
    timeout = check.double('simulator.command_timeout', positive=True)
    publish_clock = check.boolean('simulator.publish_clock')
    return SimulatorSpec(rate_hz=rate, initial_state=np.zeros(n) if initial is None else
                         initial, duration=duration, seed=seed, noise=noise,
                         process_noise_std=process, mode=mode, realtime_factor=factor,
                         command_timeout=timeout, publish_clock=publish_clock)


def _read_controller(check, plant, discrete):
    n, m = plant.n, plant.m
    options = [key for key in ('controller.poles', 'controller.K', 'controller.lqr_Q')
               if check.double_array(key) is not None]
    if check.given('controller.lqr_R') and check.double_array('controller.lqr_R') is not None \
            and 'controller.lqr_Q' not in options:
        check.fail('controller.lqr_Q', 'missing (required with controller.lqr_R)')
    if not options:
        check.fail('controller.poles', 'missing: give one of controller.poles, controller.K '
                   'or controller.lqr_Q with controller.lqr_R')
    if len(options) > 1:
        check.fail(options[1], f'give only one of controller.poles, controller.K and '
                   f'controller.lqr_Q/lqr_R (got {" and ".join(options)})')
    # the observer's rule: at most n here; the design asks for exactly one per
    # controllable mode (n for a controllable plant) and names the count
    poles = check.poles('controller', n, False, 'one per controllable mode', discrete)
    K = check.matrix('controller.K', m, n, ('inputs', 'states'))
    Q = R = None
    if options[0] == 'controller.lqr_Q':
        Q = check.matrix('controller.lqr_Q', n, n, ('states', 'states'))
        R = check.matrix('controller.lqr_R', m, m, ('inputs', 'inputs'), required=True)
        Q = check.symmetric('controller.lqr_Q', Q, definite=False)
        R = check.symmetric('controller.lqr_R', R, definite=True)
    reference = check.vector('controller.reference', n, 'states')
    Kd = check.matrix('controller.Kd', m, n, ('inputs', 'states'))
    u_min = check.vector('controller.u_min', m, 'inputs', allow_inf=True)
    u_max = check.vector('controller.u_max', m, 'inputs', allow_inf=True)
    if u_min is not None and u_max is not None:
        bad = np.nonzero(~(u_min < u_max))[0]
        if bad.size:
            i = int(bad[0])
            check.fail('controller.u_max', f'{plant.input_names[i]}: u_max {u_max[i]} is '
                       f'not above u_min {u_min[i]}')
    safe = check.string('controller.safe_command')
    stale = check.double('controller.stale_timeout', positive=True)
    predict = check.double('controller.predict_timeout', minimum=0.0)
    delay = check.boolean('controller.delay_compensation')
    return ControllerSpec(poles=poles, K=K, lqr_Q=Q, lqr_R=R, reference=reference, Kd=Kd,
                          u_min=u_min, u_max=u_max, safe_command=safe, stale_timeout=stale,
                          predict_timeout=predict, delay_compensation=delay)


def _read_observer(check, plant, discrete, sensors, simulator, warnings):
    n, p = plant.n, plant.p
    kind = check.string('observer.type')
    poles = gain = Qd = Rd = Bd = None
    method = KNOWN_KEYS['observer.method'].default
    design_keys = ['observer.poles', 'observer.poles_imag', 'observer.gain',
                   'observer.method']
    kalman_keys = ['observer.Qd', 'observer.Rd', 'observer.Bd']
    if kind in ('full', 'reduced'):
        _warn_unused(check, kalman_keys, f'by a {kind} observer', warnings)
        if kind == 'reduced' and p >= n:
            check.fail('observer.type', f'a reduced observer needs fewer outputs than '
                       f'states (p = {p}, n = {n})')
        method = check.string('observer.method')
        rows, label = (n, 'states') if kind == 'full' else (n - p, 'states - outputs')
        has_poles = check.double_array('observer.poles') is not None
        has_gain = check.double_array('observer.gain') is not None
        if has_poles and has_gain:
            check.fail('observer.gain', 'give either observer.poles or observer.gain, '
                       'not both')
        if not has_poles and not has_gain:
            check.fail('observer.poles', f'missing: a {kind} observer needs observer.poles '
                       'or observer.gain')
        if has_poles:
            what = 'n for a full observer' if kind == 'full' else \
                'n - p for a reduced observer'
            poles = check.poles('observer', rows, False, what, discrete)
        else:
            if check.given('observer.poles_imag'):
                check.fail('observer.poles_imag', 'given without observer.poles')
            gain = check.matrix('observer.gain', rows, p, (label, 'outputs'))
    elif kind == 'kalman':
        _warn_unused(check, design_keys, 'by a kalman observer', warnings)
        Bd = check.double_array('observer.Bd')
        if Bd is not None:
            if len(Bd) % n:
                check.fail('observer.Bd', f'has {len(Bd)} values; expected a multiple of '
                           f'{n} (states x k)')
            k = len(Bd) // n
            Bd = np.array(Bd).reshape(n, k)
        else:
            k = n
        if check.double_array('observer.Qd') is not None:
            Qd = check.matrix('observer.Qd', k, k, ('k', 'k') if Bd is not None else
                              ('states', 'states'))
        elif Bd is None and simulator.process_noise_std is not None and \
                np.all(simulator.process_noise_std > 0.0):
            Qd = np.diag(simulator.process_noise_std ** 2)
        else:
            check.fail('observer.Qd', 'missing: a kalman observer needs observer.Qd (the '
                       'default, diag(simulator.process_noise_std**2), needs all of them > 0 '
                       'and no observer.Bd)')
        Qd = check.symmetric('observer.Qd', Qd, definite=False)
        if check.double_array('observer.Rd') is not None:
            Rd = check.matrix('observer.Rd', p, p, ('outputs', 'outputs'))
        else:
            std = np.zeros(p)
            for sensor in sensors:
                std[list(plant.output_rows(sensor.outputs))] = sensor.noise_std
            if not np.all(std > 0.0):
                check.fail('observer.Rd', 'missing: a kalman observer needs observer.Rd '
                           '(the default, diag(noise_std**2) of the sensors, needs every '
                           'noise_std > 0)')
            Rd = np.diag(std ** 2)
        Rd = check.symmetric('observer.Rd', Rd, definite=True)
    else:   # open_loop
        _warn_unused(check, design_keys + kalman_keys, 'by an open_loop observer', warnings)
    initial = check.vector('observer.initial_estimate', n, 'states')
    rate = check.double('observer.rate_hz', positive=True)
    history = check.double('observer.history_length', minimum=0.0)
    publish_rate = check.double('observer.publish_rate_hz', positive=True)
    return ObserverSpec(kind=kind, poles=poles, gain=gain, method=method, Qd=Qd, Rd=Rd,
                        Bd=Bd, initial_estimate=initial, rate_hz=rate,
                        history_length=history, publish_rate_hz=publish_rate)


# -- writing ------------------------------------------------------------------------------

def _floats(values):
    return [float(v) for v in np.asarray(values, dtype=float).reshape(-1)]


def _put_poles(flat, prefix, poles):
    poles = np.asarray(poles, dtype=complex).reshape(-1)
    flat[f'{prefix}.poles'] = _floats(poles.real)
    if np.any(poles.imag != 0.0):
        flat[f'{prefix}.poles_imag'] = _floats(poles.imag)


def vehicle_to_parameters(vehicle):
    """
    Return the flat parameters that describe a vehicle (inverse of the loader).

    Parameters
    ----------
    vehicle : Vehicle
        The vehicle to describe.

    Returns
    -------
    flat : dict
        Dotted names to plain Python values (str, bool, int, lists of float or str):
        ``vehicle_from_parameters(vehicle_to_parameters(v))`` describes the same vehicle.
        Optional parameters that are unset are left out; defaults are written.

    """
    plant = vehicle.plant
    flat = {'vehicle.name': vehicle.name}
    if vehicle.description:
        flat['vehicle.description'] = vehicle.description
    if vehicle.source:
        flat['vehicle.source'] = vehicle.source
    if plant.is_discrete:
        flat['model.time_domain'] = 'discrete'
        flat['model.sample_time'] = float(plant.dt)
    else:
        flat['model.time_domain'] = 'continuous'
    flat['model.states'] = list(plant.state_names)
    flat['model.inputs'] = list(plant.input_names)
    flat['model.outputs'] = list(plant.output_names)
    for key in 'ABCD':
        flat[f'model.{key}'] = _floats(getattr(plant, key))
    flat['sensors.names'] = [s.name for s in vehicle.sensors]
    for s in vehicle.sensors:
        key = f'sensors.{s.name}.'
        flat[key + 'topic'] = s.topic
        flat[key + 'type'] = s.msg_type
        flat[key + 'fields'] = list(s.fields)
        flat[key + 'outputs'] = list(s.outputs)
        flat[key + 'noise_std'] = _floats(s.noise_std)
        flat[key + 'timeout'] = float(s.timeout)
        flat[key + 'rate_divider'] = int(s.rate_divider)
        flat[key + 'frame_id'] = s.frame_id
    o = vehicle.observer
    flat['observer.type'] = o.kind
    if o.poles is not None:
        _put_poles(flat, 'observer', o.poles)
    for key in ('gain', 'Qd', 'Rd', 'Bd', 'initial_estimate'):
        if getattr(o, key) is not None:
            flat[f'observer.{key}'] = _floats(getattr(o, key))
    if o.kind in ('full', 'reduced'):
        flat['observer.method'] = o.method
    if o.rate_hz is not None:
        flat['observer.rate_hz'] = float(o.rate_hz)
    flat['observer.history_length'] = float(o.history_length)
    if o.publish_rate_hz is not None:
        flat['observer.publish_rate_hz'] = float(o.publish_rate_hz)
    c = vehicle.controller
    if c.poles is not None:
        _put_poles(flat, 'controller', c.poles)
    for key in ('K', 'lqr_Q', 'lqr_R', 'reference', 'Kd', 'u_min', 'u_max'):
        if getattr(c, key) is not None:
            flat[f'controller.{key}'] = _floats(getattr(c, key))
    flat['controller.safe_command'] = c.safe_command
    flat['controller.stale_timeout'] = float(c.stale_timeout)
    flat['controller.predict_timeout'] = float(c.predict_timeout)
    flat['controller.delay_compensation'] = bool(c.delay_compensation)
    sim = vehicle.simulator
    if not plant.is_discrete:
        flat['simulator.rate_hz'] = float(sim.rate_hz)
    flat['simulator.initial_state'] = _floats(sim.initial_state)
    flat['simulator.duration'] = float(sim.duration)
    flat['simulator.seed'] = int(sim.seed)
    flat['simulator.noise'] = bool(sim.noise)
    if sim.process_noise_std is not None:
        flat['simulator.process_noise_std'] = _floats(sim.process_noise_std)
    flat['simulator.mode'] = sim.mode
    flat['simulator.realtime_factor'] = float(sim.realtime_factor)
    flat['simulator.command_timeout'] = float(sim.command_timeout)
    flat['simulator.publish_clock'] = bool(sim.publish_clock)
    return flat
