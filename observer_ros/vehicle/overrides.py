# observer_ros.vehicle.overrides: key:=value overrides of flat vehicle parameters.
"""Apply ``key:=value`` overrides (YAML values, as on a ROS command line) to parameters."""

from ..core.errors import VehicleFileError
from ..params_file import flatten_parameters, yaml_load

__all__ = ['parse_override', 'apply_overrides']


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
    return key, yaml_load(value, f'override {key}')


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
