# observer_ros.core.design_review: margins, transients and limits of a designed vehicle.
"""
The robustness review of a :class:`~observer_ros.core.vehicle_design.VehicleDesign`.

``design_vehicle`` designs and verifies the gains (fast: nodes and offline tools call it
at start-up); :func:`review_design` adds what ``observer-design`` reports about them,
each figure with the threshold above (below) which it is a warning:

- pole sensitivity of the closed loop (of the observer error without a controller):
  eigenvalue condition numbers and how far one rounding of the matrix moves each pole
  (``core/conditioning.py``; warned above ``POLE_CONDITION_WARN``, 1e4);
- transient growth ``sup ||e^{M t}||`` of the observer error and of the closed loop
  (warned above ``TRANSIENT_GROWTH_WARN``, 100);
- gain, phase and delay margins, peak sensitivity and disk margin with the loop broken at
  the plant input and at its output (``core/margins.py``; warned below 2x (6 dB), 30 deg,
  two sample periods; Ms above 2);
- the sampled observer at the sensors' rates: the decay rate and the growth of its error
  map over one period of the sensor pattern against the designed ones (warned when it
  decays slower than :data:`SAMPLED_DECAY_WARN` of the design, or grows more than
  :data:`SAMPLED_GROWTH_WARN` times as much);
- the fundamental limit of the plant with its outputs (``core/limits.py``): the smallest
  Ms any controller can reach, and whether the sensor set is the obstacle.

Warnings the libraries raise while these are computed are caught and said here in words.

"""

from dataclasses import dataclass, field
import math
from typing import Optional, Tuple
import warnings

import numpy as np

from ._lazy import control
from .analysis import format_complex
from .closed_loop import closed_loop_matrix, reduced_closed_loop_matrix
from .conditioning import (POLE_CONDITION_WARN, pole_sensitivity, PoleSensitivity,
                           transient_growth, TRANSIENT_GROWTH_WARN)
from .limits import fundamental_limit, FundamentalLimit
from .margins import loop_margins, LoopMargins, margin_warnings, PEAK_SENSITIVITY_WARN

__all__ = ['DesignReview', 'review_design', 'SAMPLED_DECAY_WARN', 'SAMPLED_GROWTH_WARN']

#: The sampled observer is warned about when its error decays slower than this fraction
#: of the designed rate.
SAMPLED_DECAY_WARN = 0.8

#: ... or when its error map over one period grows more than this many times the
#: designed observer's transient growth.
SAMPLED_GROWTH_WARN = 2.0


@dataclass(frozen=True)
class DesignReview:
    """The figures of :func:`review_design` and the warnings they raise."""

    sensitivity: Optional[PoleSensitivity]
    sensitivity_of: str
    observer_growth: Optional[Tuple[float, float]]
    closed_loop_growth: Optional[Tuple[float, float]]
    margins: Tuple[LoopMargins, ...]
    sampled_growth: Optional[float]
    limit: Optional[FundamentalLimit]
    warnings: Tuple[str, ...] = field(default=())

    def to_json(self):
        """Return a JSON-serialisable dict."""
        def growth(g):
            return None if g is None else {'growth': _num(g[0]), 'at': _num(g[1])}
        return {'pole_sensitivity': None if self.sensitivity is None else
                dict(self.sensitivity.to_json(), of=self.sensitivity_of),
                'observer_growth': growth(self.observer_growth),
                'closed_loop_growth': growth(self.closed_loop_growth),
                'margins': [m.to_json() for m in self.margins],
                'sampled_growth': _num(self.sampled_growth),
                'fundamental_limit': None if self.limit is None else self.limit.to_json(),
                'warnings': list(self.warnings)}

    def lines(self, design, sample_time):
        """Return the text of the review, as ``vehicle_report.format_report`` prints it."""
        out = ['Robustness (each figure is a warning past the threshold in brackets):']
        s = self.sensitivity
        if s is not None and s.poles.size:
            out.append(
                f' pole sensitivity ({self.sensitivity_of}): condition numbers up to '
                f'{s.max_condition:.3g} (pole {format_complex(s.poles[s.worst], 5)}), '
                f'cond(V) {s.eigenvector_condition:.3g} [> {POLE_CONDITION_WARN:g}]; one '
                f'rounding of the matrix moves that pole by {s.rounding_move[s.worst]:.2g} '
                f'(relative {s.relative_move:.2g}), a model error of relative size d by '
                f'about d/eps times that')
        for label, g in (('observer error', self.observer_growth),
                         ('closed loop', self.closed_loop_growth)):
            if g is not None:
                unit = 'steps' if design.discrete else 's'
                at = '' if not (np.isfinite(g[1]) and g[0] > 1.0) else f' at {g[1]:.3g} {unit}'
                out.append(f' transient growth of the {label}: sup ||e^(M t)|| = '
                           f'{g[0]:.3g}{at} [> {TRANSIENT_GROWTH_WARN:g}]')
        for m in self.margins:
            lo, hi = m.disk_gain
            out.append(f' loop broken at the {m.where}: stable for loop gains '
                       f'{_gain(m.gain_low)} to {_gain(m.gain_high)} [< 2x], phase margin '
                       f'{_deg(m.phase)}' + (f' (at {m.phase_frequency:.3g} rad/s)'
                                             if np.isfinite(m.phase) else '') + ' [< 30 deg]')
            if np.isfinite(m.delay):
                out.append(f'   Delay margin at the {m.where}: {m.delay * 1e3:.3g} ms (at '
                           f'{m.delay_frequency:.3g} rad/s), {m.delay / sample_time:.3g} '
                           f'samples [< 2]')
                if m.delay < sample_time and m.side == 'input':
                    out.append(f'   less than one sample ({sample_time * 1e3:g} ms): a realtime '
                               'loop needs controller.delay_compensation (a command that '
                               'misses its step destabilises it), or a design with margin '
                               '(observer-design --robust)')
            else:
                out.append(f'   Delay margin at the {m.where}: no gain crossover (none needed)')
            last = m is self.margins[-1] or self.margins[self.margins.index(m) + 1].side != \
                m.side
            if last and not np.isfinite(m.peak_sensitivity):
                out.append(f'   peak sensitivity at the plant {m.side}: not stated (more '
                           f'{m.side}s than the loop has rank; the loop-at-a-time figures '
                           'above)')
            elif last:
                whole = '' if m.siso else ' (the whole loop; its disk margin the unstructured ' \
                    'bound)'
                out.append(f'   peak sensitivity at the plant {m.side}{whole}: Ms '
                           f'{m.peak_sensitivity:.3g} (at {m.peak_frequency:.3g} rad/s) '
                           f'[> {PEAK_SENSITIVITY_WARN:g}], disk margin {m.disk:.3g}: gain '
                           f'{lo:.4g} to {_gain(hi)}, phase +-{m.disk_phase:.3g} deg')
        sc = design.sampled
        if sc is not None and len({o for _, o in sc.corrections}) > 1:
            designed = self.observer_growth[0] if self.observer_growth else math.nan
            out.append(" sampled observer at the sensors' rates: decays at "
                       f'{_rate(sc.decay_rate)} against the designed {_rate(sc.designed_rate)} '
                       f'[< {SAMPLED_DECAY_WARN:g}x], its error grows by '
                       f'{_num3(self.sampled_growth)} against the designed {designed:.3g} '
                       f'[> {SAMPLED_GROWTH_WARN:g}x]')
        if self.limit is not None:
            out.extend(' ' + line for line in self.limit.lines())
        return out


def _num(x):
    return None if x is None or not np.isfinite(x) else float(x)


def _num3(x):
    return '-' if x is None else f'{x:.3g}'


def _gain(g):
    return 'inf' if not np.isfinite(g) else f'{g:.4g}'


def _deg(x):
    return 'inf (no gain crossover)' if not np.isfinite(x) else f'{x:.3g} deg'


def _rate(r):
    return 'deadbeat' if r == -math.inf else f'{-r:.3g}/s'


def _loop_matrices(design, vehicle):
    plant = vehicle.plant
    A, B, C, D = plant.A, plant.B, plant.C, plant.D
    error = design.reduced.F if design.reduced is not None else A - design.L @ C
    if design.K is None:
        return error, None
    if design.reduced is not None:
        return error, reduced_closed_loop_matrix(A, B, design.K, design.reduced, 'state')
    return error, closed_loop_matrix(A, B, C, design.K, design.L, D)


def _sampled_growth(sc):
    if sc is None or sc.period_map is None:
        return None
    return transient_growth(sc.period_map, discrete=True)[0]


def _guarded(notes, what, fn, *args):
    """Return fn(*args), or None with a note saying what could not be computed."""
    try:
        return fn(*args)
    except (ValueError, ArithmeticError, np.linalg.LinAlgError, TypeError) as err:
        notes.append(f'{what} could not be computed ({type(err).__name__}: '
                     f'{str(err).splitlines()[0][:100] if str(err) else "no message"}); '
                     'it is left out')
        return None


def _margins(design, plant):
    P = control.ss(plant.A, plant.B, plant.C, plant.D, plant.dt or 0)
    margins = loop_margins(P, design.compensator, 'input', plant.input_names, plant.dt)
    if plant.m != 1 or plant.p != 1:     # one input and one output: the same loop
        margins += loop_margins(P, design.compensator, 'output', plant.output_names,
                                plant.dt)
    return tuple(margins)


def review_design(design, vehicle):
    """
    Review a design's robustness: see the module docstring.

    Parameters
    ----------
    design : VehicleDesign
        From :func:`~observer_ros.core.vehicle_design.design_vehicle`.
    vehicle : observer_ros.core.spec.Vehicle
        The vehicle it was designed for.

    Returns
    -------
    DesignReview

    """
    plant = vehicle.plant
    discrete = design.discrete
    dt = vehicle.sample_time
    notes = []
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter('always')
        error, loop = _loop_matrices(design, vehicle)
        matrix = loop if loop is not None else error
        of = 'closed loop [x; x_hat]' if loop is not None else 'observer error'
        if design.reduced is not None and loop is not None:
            of = 'closed loop [x; z]'
        sens = _guarded(notes, 'the pole sensitivity', pole_sensitivity, matrix)
        obs_growth = _guarded(notes, "the observer error's transient growth",
                              transient_growth, error, discrete) if error.size else None
        cl_growth = _guarded(notes, "the closed loop's transient growth", transient_growth,
                             loop, discrete) if loop is not None else None
        margins = ()
        if design.compensator is not None:
            margins = _guarded(notes, 'the loop margins', _margins, design, plant) or ()
        sampled_growth = _guarded(notes, "the sampled observer's growth", _sampled_growth,
                                  design.sampled)
        limit = _guarded(notes, 'the fundamental limit', fundamental_limit, plant.A, plant.B,
                         plant.C, plant.D, discrete, plant.dt, plant.output_names,
                         plant.state_names)
    for w in caught:
        if not issubclass(w.category, DeprecationWarning):
            text = (f'a numerical warning was raised while reviewing the design '
                    f'({w.category.__name__}: {str(w.message).splitlines()[0][:100]}); '
                    'the figures above may be less accurate than shown')
            if text not in notes:
                notes.append(text)
    out = []
    if sens is not None and sens.warn:
        out.append(
            f'pole sensitivity: the {of} has eigenvalue condition numbers up to '
            f'{sens.max_condition:.3g} and cond(V) {sens.eigenvector_condition:.3g} (above '
            f'{POLE_CONDITION_WARN:g}): one rounding moves pole '
            f'{format_complex(sens.poles[sens.worst], 5)} by {sens.rounding_move[sens.worst]:.2g}'
            f', a model error of 1e-6 by about '
            f'{sens.rounding_move[sens.worst] * 1e-6 / np.finfo(float).eps:.2g}'
            '; spread the poles apart or use an LQR/Kalman design')
    for label, g in (('observer error', obs_growth), ('closed loop', cl_growth)):
        if g is not None and g[0] > TRANSIENT_GROWTH_WARN:
            out.append(f'transient growth: the {label} can grow {g[0]:.3g} times its initial '
                       f'size before it decays (sup ||e^(M t)||, above '
                       f'{TRANSIENT_GROWTH_WARN:g}): its matrix is far from normal (poles far '
                       "from the plant's, or clustered)")
    out.extend(margin_warnings(margins, dt))
    sc = design.sampled
    if sc is not None and len({o for _, o in sc.corrections}) > 1 and \
            np.isfinite(sc.designed_rate) and sc.designed_rate < 0.0:
        if sc.decay_rate > SAMPLED_DECAY_WARN * sc.designed_rate:
            out.append('sampled observer: with the sensors at their rates the error decays '
                       f'at {_rate(sc.decay_rate)}, {sc.decay_rate / sc.designed_rate:.0%} of '
                       f'the designed {_rate(sc.designed_rate)} (below '
                       f'{SAMPLED_DECAY_WARN:.0%})')
        if obs_growth is not None and sampled_growth is not None and \
                sampled_growth > SAMPLED_GROWTH_WARN * max(obs_growth[0], 1.0):
            out.append(f'sampled observer: over the periods of the sensor pattern its error '
                       f'grows by {sampled_growth:.3g} before it decays, against '
                       f'{obs_growth[0]:.3g} designed')
    if limit is not None and limit.ms_bound > PEAK_SENSITIVITY_WARN:
        if math.isfinite(limit.ms_bound):
            what = (f'no controller with outputs {list(limit.outputs)} reaches a peak '
                    f'sensitivity below {limit.ms_bound:.3g} (unstable pole and '
                    'non-minimum-phase zero)')
        else:
            what = f'no controller stabilises the plant with outputs {list(limit.outputs)}'
        if limit.sensor_obstacle and limit.better_with:
            what += (f': the sensor set is the obstacle; measuring {limit.better_with} as '
                     f'well lowers the bound to {limit.better_bound:.3g}')
        out.append(what)
    out.extend(notes)
    return DesignReview(sens, of, obs_growth, cl_growth, margins, sampled_growth, limit,
                        tuple(out))
