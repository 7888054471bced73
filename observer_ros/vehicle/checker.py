# observer_ros.vehicle.checker: typed reads of flat parameters; every refusal names the key.
"""
Read typed values from flat parameters, and the loader's warnings.

:class:`Checker` reads strings, arrays, doubles, integers, booleans, matrices and poles
from a flat parameter dict and raises :class:`VehicleFileError` naming the parameter;
``warn_*`` collect what is not an error (unknown keys, unused keys, strings that
``ros2 param load`` would not give back).

"""

import array
import difflib
import math
import numbers

import numpy as np
import yaml

from .schema import bound_problem, INT64_MAX, KNOWN_KEYS, known_keys, ROS_RESERVED_KEYS, \
    ROS_RESERVED_PREFIXES, SENSOR_KEYS
from ..core.errors import ObserverError, VehicleFileError
from ..core.model import as_poles

__all__ = ['Checker', 'warn_unloadable_strings', 'warn_unknown', 'warn_unused']


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


class Checker:
    """Reads typed values from a flat dict; every refusal names the parameter."""

    def __init__(self, flat, source):
        self.flat = flat
        self.prefix = f'{source}: ' if source else ''

    def fail(self, key, message):
        raise VehicleFileError(f'{self.prefix}{key}: {message}')

    def given(self, key):
        return key in self.flat

    def _read(self, key, spec, required):
        """Return the key's spec, its value (the default when absent), and whether given."""
        spec = spec or KNOWN_KEYS.get(key)
        if spec is None:
            raise KeyError(f'{key} is not a key of the schema')
        if key in self.flat:
            return spec, self.flat[key], True
        if spec.required if required is None else required:
            self.fail(key, 'missing (required)')
        return spec, spec.default, False

    def string(self, key, spec=None, required=None, allow_empty=False):
        spec, value, given = self._read(key, spec, required)
        if not given:
            return value
        if not isinstance(value, str):
            self.fail(key, f'expected a string; got {_describe(value)}')
        if spec.choices and value not in spec.choices:
            self.fail(key, f'{value!r} is not one of {list(spec.choices)}')
        if not value and not allow_empty:
            self.fail(key, 'empty string')
        return value

    def string_array(self, key, spec=None, required=None, unique=True):
        spec, value, given = self._read(key, spec, required)
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

    def _bounded(self, key, spec, value, element=None):
        """Refuse a number outside its key's bound (the schema's), with the reason."""
        problem = bound_problem(spec, value)
        if problem is not None:
            self.fail(key, problem if element is None else f'element {element}: {problem}')

    def double_array(self, key, spec=None, required=None, allow_inf=False):
        """Return a list of floats, or None when the key is absent (or an empty list)."""
        spec, value, given = self._read(key, spec, required)
        if not given:
            return None
        items = _as_list(value)
        if items is None:
            self.fail(key, f'expected a list of floats; got {_describe(value)}')
        if not items:
            if spec.required if required is None else required:
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
            if spec.bounded:
                self._bounded(key, spec, v, i)
        return out

    def double(self, key, spec=None, required=None):
        """Return a finite float within the key's bound, or its default when absent."""
        spec, value, given = self._read(key, spec, required)
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
        self._bounded(key, spec, value)
        return value

    def integer(self, key, spec=None, required=None):
        """Return an integer within the key's bound, or its default when absent."""
        spec, value, given = self._read(key, spec, required)
        if not given:
            return value
        if not _is_int(value):
            self.fail(key, f'expected an integer; got {_describe(value)}')
        value = int(value)
        if not -INT64_MAX - 1 <= value <= INT64_MAX:
            self.fail(key, f'{value} does not fit a 64-bit integer')
        self._bounded(key, spec, value)
        return value

    def boolean(self, key, spec=None):
        spec, value, given = self._read(key, spec, None)
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


def warn_unloadable_strings(flat, warnings):
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


def warn_unknown(flat, sensor_names, extra_keys, warnings):
    known = known_keys(sensor_names)
    candidates = list(known)
    for key in flat:
        if key in known or key in extra_keys or key in ROS_RESERVED_KEYS or \
                key.startswith(ROS_RESERVED_PREFIXES):
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


def warn_unused(check, keys, reason, warnings):
    for key in keys:
        if key in check.flat:
            spec = KNOWN_KEYS.get(key)
            value = check.flat[key]
            if spec is not None and isinstance(value, str) and value == spec.default:
                continue
            warnings.append(f'{key} is not used {reason} (ignored)')
