# observer_ros.tools.robust_file: `observer-design --robust`: the redesign, written.
"""
The vehicle file of a robust redesign (``core/robust_design.py``).

The new file is the original's parameters (with any ``-p`` overrides) with the observer
(and, with ``--controller``, the controller's poles or gain) replaced; it is a ROS 2
parameters file under ``/**:``, double arrays as floats, no YAML aliases, written next to
the original as ``<name>_robust.yaml`` unless ``--out`` says otherwise, and never over an
existing file. Its first lines are comments: the command, the settling bound, the
fundamental limit of its outputs and every figure before and after.

"""

from pathlib import Path
import re
import textwrap

import numpy as np

from ..core.errors import ObserverError
from ..tuning.tuned_vehicle import OBSERVER_KEYS, write_tuned_vehicle

__all__ = ['default_output', 'write_robust_vehicle', 'figure_lines']

CONTROLLER_KEYS = ('controller.poles', 'controller.poles_imag', 'controller.K',
                   'controller.lqr_Q', 'controller.lqr_R')


def default_output(source):
    """``<dir>/<stem>_robust.yaml`` beside the source file."""
    source = Path(source)
    return source.with_name(f'{source.stem}_robust.yaml')


def _fmt(x, unit=''):
    if x is None:
        return '-'
    if isinstance(x, tuple):
        return f'{_fmt(x[0])} to {_fmt(x[1])}'
    if not np.isfinite(x):
        return 'inf'
    return f'{x:.3g}{unit}'


def figure_lines(result):
    """Return the before/after table (comments of the new file, lines of the report)."""
    b, a = result.before, result.after or {}
    rows = (('peak sensitivity Ms at the plant input', 'Ms', 1.0, ''),
            ('disk margin', 'disk_margin', 1.0, ''),
            ('gain margin (loop gains kept stable)', 'gain_margin', 1.0, ''),
            ('phase margin, deg', 'phase_margin_deg', 1.0, ''),
            ('delay margin, ms', 'delay_margin_s', 1e3, ''),
            ('settling (4 time constants), s', 'settling_s', 1.0, ''),
            ('transient growth of the observer error', 'observer_growth', 1.0, ''),
            ('transient growth of the closed loop', 'closed_loop_growth', 1.0, ''))

    def value(d, key, scale):
        x = d.get(key)
        if x is None:
            return None
        if isinstance(x, tuple):
            return tuple(float(v) * scale for v in x)
        return float(x) * scale

    width = max(len(r[0]) for r in rows)
    out = [f'{"":{width}}  {"before":>16}  {"after":>16}']
    for label, key, scale, unit in rows:
        out.append(f'{label:{width}}  {_fmt(value(b, key, scale), unit):>16}  '
                   f'{_fmt(value(a, key, scale), unit):>16}')
    return out


def _new_values(result, controller):
    v = result.vehicle
    o = v.observer
    values, sources = {}, {}
    if o.kind == 'kalman':
        values['observer.type'] = 'kalman'
        values['observer.Qd'] = [float(x) for x in np.asarray(o.Qd).reshape(-1)]
        values['observer.Rd'] = [float(x) for x in np.asarray(o.Rd).reshape(-1)]
        sources['observer.type'] = ('observer-design --robust: a Kalman filter, process noise '
                                    'q0 I + q B B^T (loop transfer recovery at the plant '
                                    "input), Rd the sensors' noise_std^2")
    else:
        values['observer.type'] = 'full'
        poles = np.asarray(o.poles, dtype=complex)
        values['observer.poles'] = [float(x) for x in poles.real]
        if np.any(poles.imag):
            values['observer.poles_imag'] = [float(x) for x in poles.imag]
        sources['observer.type'] = 'observer-design --robust: observer poles searched'
    if controller:
        c = v.controller
        if c.poles is not None:
            poles = np.asarray(c.poles, dtype=complex)
            values['controller.poles'] = [float(x) for x in poles.real]
            if np.any(poles.imag):
                values['controller.poles_imag'] = [float(x) for x in poles.imag]
            sources['controller.poles'] = ('observer-design --robust: LQR poles, refined for '
                                           'the smallest Ms')
        else:
            values['controller.K'] = [float(x) for x in np.asarray(c.K).reshape(-1)]
            sources['controller.K'] = 'observer-design --robust: LQR gain'
    return values, sources


def _name_of(out, original):
    """Return its file's stem (as every shipped file is named), else ``<name>_robust``."""
    stem = Path(out).stem
    if re.fullmatch(r'[A-Za-z0-9_.-]+', stem):
        return stem
    return f'{original}_robust'


def write_robust_vehicle(result, source, out, command, overrides=None, controller=False):
    """
    Write the robust redesign; return the path written.

    Parameters
    ----------
    result : RobustResult
        From :func:`~observer_ros.core.robust_design.robust_design` (with a vehicle).
    source : str or Path
        The original vehicle file.
    out : str or Path
        The new file; it must not exist.
    command : str
        The command line, for the header.
    overrides : dict, optional
        ``-p`` overrides (dotted key -> value) written into the new file too.
    controller : bool
        The controller was redesigned.

    Raises
    ------
    ObserverError
        The file exists, an override cannot be written, or the new file does not load.

    """
    values, sources = _new_values(result, controller)
    for key, value in (overrides or {}).items():
        if key in values:
            continue
        if isinstance(value, (list, tuple)) and not all(
                isinstance(x, (int, float)) and not isinstance(x, bool) for x in value):
            raise ObserverError(f'{key}: an override of a list of names cannot be written '
                                'into the robust file; edit the source file instead')
        values[key] = value
        sources[key] = 'overridden on the command line (-p)'
    text = (f'Written by: {command}. From {Path(source).name}: the design with the smallest '
            f'peak sensitivity Ms at the plant input, every closed-loop pole settling within '
            f'{result.settling_bound:.3g} s. {result.message}.')
    header = textwrap.wrap(text, 90) + ['Figures (core/design_review.py):'] + \
        figure_lines(result)
    values['vehicle.name'] = _name_of(out, result.vehicle.name)
    values['vehicle.description'] = (f'{Path(source).stem} redesigned for margin '
                                     '(observer-design --robust)')
    sources['vehicle.name'] = f'observer-design --robust from {Path(source).name}'
    replace = OBSERVER_KEYS + (CONTROLLER_KEYS if controller else ())
    return write_tuned_vehicle(source, out, values, sources, header, replace)
