# observer_ros.tuning.tuned_vehicle: write a new vehicle file with a tuned observer.
"""
A new vehicle file: the original's parameters with the observer replaced.

The file is a ROS 2 parameters file under ``/**:`` (``parameters_to_yaml``): double
arrays written as floats, no YAML anchors or aliases, so both the project's loader and
``--params-file`` (rcl's parser) read it. Each changed key carries the source of its
numbers as a comment on the line before it. An existing file is never overwritten.

"""

from pathlib import Path

from ..bag.errors import BagToolError
from ..outputs.staging import write_new_file
from ..vehicle import load_parameters, load_vehicle, parameters_to_yaml

__all__ = ['OBSERVER_KEYS', 'tuned_parameters', 'write_tuned_vehicle']

#: Keys of the original observer design that a tuned one replaces.
OBSERVER_KEYS = ('observer.type', 'observer.poles', 'observer.poles_imag', 'observer.gain',
                 'observer.method', 'observer.Qd', 'observer.Rd', 'observer.Bd')


def _floats(values):
    return [float(v) for v in values]


def tuned_parameters(source, observer, replace=OBSERVER_KEYS):
    """
    Return the flat parameters of ``source`` (a vehicle file) with a new observer.

    Parameters
    ----------
    source : str or Path
        The original vehicle file.
    observer : dict
        New ``observer.*`` values (dotted keys); numbers in arrays become floats.
    replace : sequence of str
        The original's keys dropped first (default the whole observer design).

    """
    flat = load_parameters(source)
    flat = {k: v for k, v in flat.items() if k not in replace}
    for key, value in observer.items():
        flat[key] = _floats(value) if isinstance(value, (list, tuple)) else value
    return flat


def write_tuned_vehicle(source, path, observer, sources, header=(), replace=OBSERVER_KEYS):
    """
    Write a new vehicle file with a tuned observer; return its path.

    Parameters
    ----------
    source : str or Path
        The original vehicle file.
    path : str or Path
        The new file; it must not exist.
    observer : dict
        New ``observer.*`` values.
    sources : dict
        Key -> a comment saying where its numbers come from.
    header : sequence of str
        Comment lines at the top of the file.
    replace : sequence of str
        The original's keys dropped (see :func:`tuned_parameters`).

    Raises
    ------
    BagToolError
        The file exists, or the new parameters do not load as a vehicle.

    """
    path = Path(path)
    if path.exists() or path.is_symlink():
        raise BagToolError(f'{path} exists; the tuned vehicle file is never overwritten '
                           '(give another --output)')
    flat = tuned_parameters(source, observer, replace)
    text = parameters_to_yaml(flat)
    lines, stack = [], []            # (indent, key) of the mappings the line is in
    for line in text.splitlines():
        key = line.strip().split(':', 1)[0]
        indent = line[:len(line) - len(line.lstrip())]
        while stack and stack[-1][0] >= len(indent):
            stack.pop()
        full = '.'.join([k for _, k in stack[2:]] + [key])    # below /** and ros__parameters
        stack.append((len(indent), key))
        if full in sources:
            for part in str(sources[full]).splitlines():
                lines.append(f'{indent}# {part}')
        lines.append(line)
    body = '\n'.join([f'# {h}' for h in header] + lines) + '\n'
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        write_new_file(path, body)      # whole or not at all, never over another file
    except FileExistsError:
        raise BagToolError(f'{path} exists; the tuned vehicle file is never overwritten '
                           '(give another --output)') from None
    try:
        load_vehicle(path)
    except Exception as err:
        path.unlink()
        raise BagToolError(f'the tuned vehicle file does not load: {err}') from None
    return path
