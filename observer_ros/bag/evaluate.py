# observer_ros.bag.evaluate: `observer-eval BAG --vehicle V.yaml`: replay and compare.
"""
Offline evaluation of estimators on a recorded bag.

The recorded measurements and commands are replayed, at their recorded stamps and in bag
order, through one or more observer configurations with the same estimator code as the
observer node (:mod:`observer_ros.bag.replay`). The vehicle file's own design is always
the variant ``design``; ``--variant`` adds configurations that override the file; the
live estimate recorded on ``state/estimate`` is scored as the variant ``live``.

Against ``state/true`` (matched by stamp, interpolated where the stamps differ) each
variant gets, per state: RMSE, maximum absolute error, settling time (the time after
which the error stays within a tolerance: 2 % of the state's range in the true
trajectory unless ``--tolerance``) and the steady-state error spread and mean (over the
last 20 % of the run: the noise the observer lets through). Always, per output: the
residual RMS and its whiteness (normalised autocorrelation at lags 1..k, the Ljung-Box
statistic and its p-value, the fraction of lags outside +-1.96/sqrt(N)).

Python API: :func:`evaluate_bag` returns an :class:`EvalResult`;
:func:`write_results` writes the table, ``results.csv``, ``results.json``, PNG plots and
a results bag (``/eval/<variant>/state/estimate``, ``/eval/state/true``).

"""

import argparse
from dataclasses import dataclass, field
import json
import math
import os
from pathlib import Path
import re
import shutil
import sys
import time
from typing import Dict, List, Optional, Tuple
import warnings

import numpy as np

from .errors import BagToolError
from .reader import jazzy_typestore, read_recording
from .replay import CLOCK_JUMP_TOLERANCE, epochs_of, live_replay, replay
from ..core.compensator import design_vehicle
from ..core.errors import ObserverError

__all__ = ['DEFAULT_TOLERANCE', 'STEADY_FRACTION', 'WHITENESS_LAGS', 'VariantResult',
           'EvalResult', 'parse_variant', 'parse_tolerance', 'evaluate_bag',
           'write_results', 'format_table', 'main']

DEFAULT_TOLERANCE = 0.02        # fraction of each state's range in the true trajectory
STEADY_FRACTION = 0.2           # the last 20 % of the run is the steady state
WHITENESS_LAGS = 20             # autocorrelation lags 1..k of the residual
BAG_MAX_MESSAGES = 100_000      # per topic in the results bag (decimated beyond)
PLOT_MAX_POINTS = 5_000         # per line in the plots (decimated beyond)
RESERVED = ('design', 'live')
_NAME = re.compile(r'^[A-Za-z][A-Za-z0-9_]*$')


# ---------------------------------------------------------------------------------------
# Results
# ---------------------------------------------------------------------------------------

@dataclass
class VariantResult:
    """
    One configuration's replay and its metrics.

    ``states`` maps a state name to ``rmse``, ``max_abs_error``, ``settling_time`` (s;
    ``inf`` if the error is outside the tolerance at the end), ``ss_std``, ``ss_mean``
    and ``samples`` (matched with the truth); empty without ground truth. ``outputs`` maps
    an output name to ``samples``, ``residual_rms``, ``ljung_box_q``, ``ljung_box_p``,
    ``lags`` and ``acf_outside``. ``summary`` has ``error_rms`` (RMS of the error norm)
    and ``settling_time`` (the largest over the states).

    """

    name: str
    kind: str
    overrides: Tuple[str, ...]
    replay: object
    states: Dict[str, dict] = field(default_factory=dict)
    outputs: Dict[str, dict] = field(default_factory=dict)
    summary: Dict[str, object] = field(default_factory=dict)
    error: Optional[np.ndarray] = None       # (N, n) x_hat - x_true; NaN where unmatched

    @property
    def t(self):
        """Stamps of the estimates in seconds."""
        return self.replay.t

    @property
    def stamp_ns(self):
        """Stamps of the estimates in integer nanoseconds."""
        return self.replay.stamp_ns

    @property
    def x_hat(self):
        """Return the estimates, (N, n)."""
        return self.replay.x_hat

    @property
    def residual(self):
        """Return the residuals, (N, p), NaN for outputs a message did not carry."""
        return self.replay.residual


@dataclass
class EvalResult:
    """Everything :func:`evaluate_bag` computed."""

    bag_path: Path
    vehicle: object
    recording: object
    variants: Dict[str, VariantResult]
    truth: Optional[Tuple[np.ndarray, np.ndarray, np.ndarray]]   # stamp_ns, values, epoch
    tolerance: Dict[str, float]
    tolerance_rule: str
    warnings: List[str] = field(default_factory=list)
    seconds: float = 0.0

    @property
    def state_names(self):
        """Return the vehicle's state names."""
        return tuple(self.vehicle.plant.state_names)

    @property
    def output_names(self):
        """Return the vehicle's output names."""
        return tuple(self.vehicle.plant.output_names)

    @property
    def namespace(self):
        """Return the vehicle's namespace in the bag."""
        return self.recording.namespace

    def to_dict(self):
        """Return the results as JSON-ready data (inf and NaN as None)."""
        info = self.recording.info
        out = {
            'bag': str(self.bag_path),
            'storage': info.storage,
            'messages': info.message_count,
            'duration_s': (info.end_ns - info.start_ns) * 1e-9 if info.message_count else 0.0,
            'vehicle': self.vehicle.name,
            'namespace': self.namespace or '/',
            'topics': {k: v for k, v in vars(self.recording.topics).items()
                       if k != 'namespace'},
            'ground_truth': self.truth is not None,
            'tolerance': dict(self.tolerance),
            'tolerance_rule': self.tolerance_rule,
            'variants': {},
            'warnings': list(self.warnings),
        }
        for name, v in self.variants.items():
            out['variants'][name] = {
                'observer_type': v.kind,
                'overrides': list(v.overrides),
                'estimates': len(v.replay),
                'bulk_steps': int(getattr(v.replay, 'bulk_steps', 0)),
                'counts': dict(v.replay.counts),
                'summary': dict(v.summary),
                'states': v.states,
                'outputs': v.outputs,
            }
        return _jsonable(out)


def _jsonable(obj):
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        f = float(obj)
        return f if math.isfinite(f) else None
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, Path):
        return str(obj)
    return obj


# ---------------------------------------------------------------------------------------
# Arguments
# ---------------------------------------------------------------------------------------

def _split_top(text, sep=','):
    """Split at separators outside brackets and quotes."""
    parts, depth, quote, cur = [], 0, None, []
    for ch in text:
        if quote:
            quote = None if ch == quote else quote
        elif ch in '\'"':
            quote = ch
        elif ch in '[{(':
            depth += 1
        elif ch in ']})':
            depth -= 1
        elif ch == sep and depth == 0:
            parts.append(''.join(cur))
            cur = []
            continue
        cur.append(ch)
    parts.append(''.join(cur))
    return [p.strip() for p in parts if p.strip()]


def parse_variant(text):
    """
    Parse ``NAME:KEY:=VALUE[,KEY:=VALUE...]`` into ``(name, [overrides])``.

    Commas inside brackets belong to the value (``observer.poles:=[-1.0,-1.1,-1.2]``).

    Raises
    ------
    BagToolError
        Bad syntax, a bad or reserved name.

    """
    name, sep, rest = text.partition(':')
    name = name.strip()
    if not sep or rest.startswith('='):
        raise BagToolError(f'--variant {text!r}: expected NAME:KEY:=VALUE[,KEY:=VALUE...]')
    if not _NAME.match(name):
        raise BagToolError(f'--variant {text!r}: the name {name!r} must be a letter followed '
                           'by letters, digits or _ (it becomes a topic name)')
    if name in RESERVED:
        raise BagToolError(f'--variant {text!r}: {name!r} is reserved (the vehicle '
                           "file's own design is 'design', the recorded estimate is "
                           "'live')")
    overrides = _split_top(rest)
    bad = [o for o in overrides if ':=' not in o]
    if not overrides or bad:
        raise BagToolError(f'--variant {text!r}: expected KEY:=VALUE after the name; got '
                           f'{bad[0] if bad else "nothing"!r}')
    return name, overrides


def parse_tolerance(text):
    """
    Parse ``--tolerance``: ``5%`` (of each state's range) or an absolute number.

    Returns
    -------
    (fraction, absolute) : tuple
        One of them is None.

    """
    text = str(text).strip()
    try:
        if text.endswith('%'):
            value = float(text[:-1]) / 100.0
            if not value > 0:
                raise ValueError
            return value, None
        value = float(text)
        if not value > 0:
            raise ValueError
        return None, value
    except ValueError:
        raise BagToolError(f'--tolerance {text!r}: expected a positive number or a '
                           'percentage (5%)') from None


# ---------------------------------------------------------------------------------------
# Metrics
# ---------------------------------------------------------------------------------------

def _truth_at(truth, stamp_ns, epoch):
    """
    Return the true state at the estimates' stamps.

    Exact where a truth stamp matches, linear interpolation inside the epoch's truth
    otherwise, NaN outside.

    """
    t_ns, values, t_epoch = truth
    out = np.full((stamp_ns.size, values.shape[1]), np.nan)
    for e in np.unique(epoch):
        sel = np.flatnonzero(epoch == e)
        tsel = np.flatnonzero(t_epoch == e)
        if not tsel.size:
            continue
        order = np.argsort(t_ns[tsel], kind='stable')
        tn = t_ns[tsel][order]
        tv = values[tsel][order]
        ns = stamp_ns[sel]
        pos = np.clip(np.searchsorted(tn, ns), 0, tn.size - 1)
        exact = tn[pos] == ns
        out[sel[exact]] = tv[pos[exact]]
        rest = ~exact & (ns >= tn[0]) & (ns <= tn[-1])
        if rest.any():
            base = tn[0]
            x = (tn - base).astype(np.float64) * 1e-9
            q = (ns[rest] - base).astype(np.float64) * 1e-9
            for i in range(tv.shape[1]):
                out[sel[rest], i] = np.interp(q, x, tv[:, i])
    return out


def state_metrics(t, error, epoch, tolerance, steady_fraction=STEADY_FRACTION):
    """
    Per-state error metrics.

    Parameters
    ----------
    t : (N,) float
        Times (s) of the samples, increasing within each epoch.
    error : (N, n) float
        x_hat - x_true; rows with NaN are not matched and are left out.
    epoch : (N,) int
        Clock-jump epochs: settling is measured from each epoch's first sample.
    tolerance : (n,) float
        Settling band per state.
    steady_fraction : float
        The steady state is the last fraction of each epoch (by time).

    Returns
    -------
    metrics : list of dict
        One per state: samples, rmse, max_abs_error, settling_time, ss_std, ss_mean.

    """
    ok = np.all(np.isfinite(error), axis=1)
    t, error, epoch = t[ok], error[ok], epoch[ok]
    n = error.shape[1]
    out = []
    if not t.size:
        return [{'samples': 0, 'rmse': math.nan, 'max_abs_error': math.nan,
                 'settling_time': math.nan, 'ss_std': math.nan, 'ss_mean': math.nan}
                for _ in range(n)]
    settle = np.zeros(n)
    steady = np.zeros(t.size, dtype=bool)
    for e in np.unique(epoch):
        sel = np.flatnonzero(epoch == e)
        tau = t[sel] - t[sel[0]]
        steady[sel[tau >= (1.0 - steady_fraction) * tau[-1]]] = True
        outside = np.abs(error[sel]) > tolerance[None, :]
        for i in range(n):
            bad = np.flatnonzero(outside[:, i])
            if not bad.size:
                continue
            if bad[-1] == sel.size - 1:
                settle[i] = math.inf
            else:
                settle[i] = max(settle[i], tau[bad[-1] + 1])
    ss = error[steady]
    for i in range(n):
        e = error[:, i]
        out.append({
            'samples': int(e.size),
            'rmse': float(np.sqrt(np.mean(e * e))),
            'max_abs_error': float(np.max(np.abs(e))),
            'settling_time': float(settle[i]),
            'ss_std': float(np.std(ss[:, i])) if ss.shape[0] > 1 else math.nan,
            'ss_mean': float(np.mean(ss[:, i])) if ss.shape[0] else math.nan,
        })
    return out


def whiteness(r, lags=WHITENESS_LAGS):
    """
    Whiteness of a residual sequence.

    Parameters
    ----------
    r : (N,) float
        Residuals in order (non-finite entries are dropped).
    lags : int
        Largest lag k (reduced to N // 4 for short sequences).

    Returns
    -------
    stats : dict
        ``samples``, ``residual_rms``, ``lags``, ``acf`` (lags 1..k, normalised, mean
        removed), ``ljung_box_q`` = N (N + 2) sum rho_k^2 / (N - k), ``ljung_box_p`` (chi^2
        with k degrees of freedom: small means not white), ``acf_outside`` (fraction of
        lags with |rho_k| > 1.96 / sqrt(N); about 0.05 for white noise).

    """
    r = np.asarray(r, dtype=float)
    r = r[np.isfinite(r)]
    N = r.size
    out = {'samples': int(N), 'residual_rms': float(np.sqrt(np.mean(r * r))) if N else math.nan,
           'lags': 0, 'acf': [], 'ljung_box_q': math.nan, 'ljung_box_p': math.nan,
           'acf_outside': math.nan}
    k = min(int(lags), N // 4)
    if k < 1:
        return out
    d = r - r.mean()
    denom = float(d @ d)
    if denom <= 0.0 or not math.isfinite(denom):
        return out
    acf = np.array([float(d[:-j] @ d[j:]) / denom for j in range(1, k + 1)])
    q = float(N * (N + 2) * np.sum(acf ** 2 / (N - np.arange(1, k + 1))))
    from scipy.special import chdtrc      # chi-square survival function (light import)
    p = float(chdtrc(k, q))
    out.update(lags=k, acf=acf.tolist(), ljung_box_q=q, ljung_box_p=p,
               acf_outside=float(np.mean(np.abs(acf) > 1.96 / math.sqrt(N))))
    return out


def _tolerances(truth_values, names, fraction, absolute):
    tol = {}
    for i, name in enumerate(names):
        if absolute is not None:
            tol[name] = float(absolute)
            continue
        col = truth_values[:, i] if truth_values is not None else np.zeros(0)
        col = col[np.isfinite(col)]
        span = float(np.ptp(col)) if col.size else 0.0
        if span <= 0.0:
            span = float(np.max(np.abs(col))) if col.size else 0.0
        if span <= 0.0:
            span = 1.0
        tol[name] = fraction * span
    return tol


def _score(result, vr):
    """Fill a VariantResult's metrics."""
    rep = vr.replay
    plant = result.vehicle.plant
    if result.truth is not None and len(rep):
        x_true = _truth_at(result.truth, rep.stamp_ns, rep.epoch)
        vr.error = rep.x_hat - x_true
        tol = np.array([result.tolerance[s] for s in plant.state_names])
        metrics = state_metrics(rep.t, vr.error, rep.epoch, tol)
        vr.states = dict(zip(plant.state_names, metrics))
        ok = np.all(np.isfinite(vr.error), axis=1)
        norm2 = np.sum(vr.error[ok] ** 2, axis=1)
        vr.summary['matched'] = int(ok.sum())
        vr.summary['error_rms'] = float(np.sqrt(np.mean(norm2))) if ok.any() else math.nan
        settles = [m['settling_time'] for m in metrics]
        vr.summary['settling_time'] = float(max(settles)) if settles else math.nan
    for j, name in enumerate(plant.output_names):
        vr.outputs[name] = whiteness(rep.residual[:, j]) if len(rep) else whiteness([])


# ---------------------------------------------------------------------------------------
# Evaluation
# ---------------------------------------------------------------------------------------

def _load_vehicle(vehicle, overrides=()):
    from ..vehicle import (apply_overrides, load_vehicle, vehicle_from_parameters,
                           vehicle_to_parameters)
    if isinstance(vehicle, (str, os.PathLike)):
        return load_vehicle(vehicle, overrides=list(overrides) or None)
    if not overrides:
        return vehicle
    flat = apply_overrides(vehicle_to_parameters(vehicle), list(overrides))
    return vehicle_from_parameters(flat, source=f'vehicle {vehicle.name}')


def evaluate_bag(bag_path, vehicle, variants=None, namespace=None, tolerance=None,
                 exact=False, progress=None, clock_jump_tolerance=CLOCK_JUMP_TOLERANCE,
                 include_live=True):
    """
    Replay a bag through the vehicle's design and variants, and score them.

    Parameters
    ----------
    bag_path : str or Path
        Bag directory or ``.mcap`` / ``.db3`` file.
    vehicle : Vehicle or str or Path
        The vehicle (or its file). Its sensors say what to read from the bag.
    variants : dict, optional
        ``{name: ["observer.type:=kalman", "observer.Qd:=[...]", ...]}``: configurations
        that override the vehicle file. ``design`` (no overrides) always comes first.
    namespace : str, optional
        The vehicle's namespace in the bag; detected when None.
    tolerance : str or float, optional
        Settling band: ``"5%"`` of each state's range, or an absolute value; default 2 %.
    exact : bool
        Call the estimator for every message (no bulk replay; slower, bit-identical to
        the node).
    progress : callable, optional
        ``progress(stage, done, total)``.
    clock_jump_tolerance : float
        A stamp this many seconds before the estimate's time is a clock jump (reset).
    include_live : bool
        Score the recorded ``state/estimate`` as the variant ``live``.

    Returns
    -------
    result : EvalResult

    Raises
    ------
    BagToolError
        The bag cannot be read or does not match the vehicle.
    ObserverError
        The vehicle file or a variant is invalid.

    """
    start = time.perf_counter()
    base = _load_vehicle(vehicle)
    configs = {'design': (base, ())}
    for name, overrides in (variants or {}).items():
        if name in RESERVED or not _NAME.match(str(name)):
            raise BagToolError(f'variant name {name!r} is reserved or not a valid name')
        try:
            with warnings.catch_warnings():
                warnings.simplefilter('ignore')
                configs[name] = (_load_vehicle(vehicle, overrides), tuple(overrides))
        except ObserverError as err:
            raise type(err)(f'variant {name!r}: {err}') from None
    for name, (v, _) in configs.items():
        if tuple(v.plant.state_names) != tuple(base.plant.state_names):
            raise BagToolError(f'variant {name!r} has states {list(v.plant.state_names)}; '
                               f'the vehicle has {list(base.plant.state_names)}')
        try:   # every configuration's gains pass the design verification first
            with warnings.catch_warnings():
                warnings.simplefilter('ignore')
                design_vehicle(v)
        except ObserverError as err:
            raise type(err)(f'variant {name!r}: {err}') from None

    def stage(label):
        if progress is None:
            return None
        return lambda done, total: progress(label, done, total)

    recording = read_recording(bag_path, base, namespace, progress=stage('reading'))
    warnings_out = list(recording.warnings)
    truth = None
    if recording.truth is not None and recording.truth.valid.any():
        tr = recording.truth
        sel = np.flatnonzero(tr.valid)
        t_ns = tr.stamp_ns[sel]
        truth = (t_ns, tr.values[sel], epochs_of(t_ns, clock_jump_tolerance))
    if tolerance is None:
        fraction, absolute = DEFAULT_TOLERANCE, None
    elif isinstance(tolerance, str):
        fraction, absolute = parse_tolerance(tolerance)
    else:
        fraction, absolute = None, float(tolerance)
    rule = f"{fraction * 100:g}% of each state's range in the true trajectory" \
        if absolute is None else f'{absolute:g} (absolute)'
    tol = _tolerances(None if truth is None else truth[1], base.plant.state_names,
                      fraction, absolute)
    result = EvalResult(bag_path=Path(bag_path), vehicle=base, recording=recording,
                        variants={}, truth=truth, tolerance=tol, tolerance_rule=rule,
                        warnings=warnings_out)
    for name, (v, overrides) in configs.items():
        try:
            rep = replay(recording, v, name=name, overrides=overrides, exact=exact,
                         clock_jump_tolerance=clock_jump_tolerance,
                         progress=stage(f'replaying {name}'))
        except ObserverError as err:
            if isinstance(err, BagToolError):
                raise BagToolError(f'variant {name!r}: {err}') from None
            raise type(err)(f'variant {name!r}: {err}') from None
        for text in rep.warnings:
            warnings_out.append(f'{name}: {text}')
        if not len(rep):
            warnings_out.append(f'{name}: no measurement was accepted')
        result.variants[name] = VariantResult(name, v.observer.kind, overrides, rep)
    if include_live:
        live = live_replay(recording, base, clock_jump_tolerance)
        if live is not None:
            result.variants['live'] = VariantResult('live', 'recorded', (), live)
    for vr in result.variants.values():
        _score(result, vr)
    result.seconds = time.perf_counter() - start
    return result


# ---------------------------------------------------------------------------------------
# Output
# ---------------------------------------------------------------------------------------

def _fmt(value, digits=4):
    if value is None:
        return '-'
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    v = float(value)
    if math.isnan(v):
        return '-'
    if math.isinf(v):
        return 'never'
    if v == 0.0:
        return '0'
    if 1e-3 <= abs(v) < 1e5:
        return f'{v:.{digits}g}'
    return f'{v:.{digits - 1}e}'


def _table(header, rows):
    widths = [max(len(str(h)), *(len(str(r[i])) for r in rows)) if rows else len(str(h))
              for i, h in enumerate(header)]
    right = [i > 0 and all(_numeric(r[i]) for r in rows) for i in range(len(header))]

    def line(cells):
        return '  '.join(str(c).rjust(w) if r else str(c).ljust(w)
                         for c, w, r in zip(cells, widths, right)).rstrip()
    return '\n'.join([line(header), line(['-' * w for w in widths])] +
                     [line(r) for r in rows])


def _numeric(text):
    return bool(re.match(r'^[-+0-9.e]+$|^-$|^never$', str(text)))


def format_table(result):
    """Return the readable comparison (what ``observer-eval`` prints)."""
    info = result.recording.info
    dur = (info.end_ns - info.start_ns) * 1e-9 if info.message_count else 0.0
    lines = [f'bag {result.bag_path} ({info.storage}, {info.message_count} messages, '
             f'{dur:.1f} s); vehicle {result.vehicle.name}, namespace '
             f'{result.namespace or "/"}']
    rows = []
    for name, vr in result.variants.items():
        c = vr.replay.counts
        skipped = sum(v for k, v in c.items() if k not in ('measurements', 'commands',
                                                           'clock_jumps'))
        rows.append([name, vr.kind, len(vr.replay), c.get('commands', '-'),
                     c.get('clock_jumps', 0), skipped,
                     ' '.join(vr.overrides) if vr.overrides else '-'])
    lines += ['', _table(['variant', 'observer', 'estimates', 'commands', 'resets',
                          'skipped', 'overrides'], rows)]
    if result.truth is not None:
        tol = ', '.join(f'{k} {_fmt(v)}' for k, v in result.tolerance.items())
        lines += ['', f'errors against state/true ({result.truth[0].size} samples); '
                      f'settling band: {result.tolerance_rule} ({tol})']
        rows = []
        for name, vr in result.variants.items():
            for state, m in vr.states.items():
                rows.append([name, state, _fmt(m['rmse']), _fmt(m['max_abs_error']),
                             _fmt(m['settling_time']), _fmt(m['ss_std']),
                             _fmt(m['ss_mean'])])
        lines += ['', _table(['variant', 'state', 'rmse', 'max|err|', 'settle[s]',
                              'ss_std', 'ss_mean'], rows)]
    else:
        lines += ['', 'no state/true in the bag: residuals only']
    rows = []
    for name, vr in result.variants.items():
        for output, m in vr.outputs.items():
            if not m['samples']:
                continue
            rows.append([name, output, m['samples'], _fmt(m['residual_rms']),
                         _fmt(m['ljung_box_q']), _fmt(m['ljung_box_p'], 3),
                         _fmt(m['acf_outside'], 3)])
    if rows:
        lines += ['', 'residual whiteness (Ljung-Box over lags 1..'
                      f'{WHITENESS_LAGS}; p small = not white; acf_out ~0.05 if white)',
                  '', _table(['variant', 'output', 'N', 'rms', 'LB_Q', 'LB_p', 'acf_out'],
                             rows)]
    return '\n'.join(lines)


_CSV_COLUMNS = ['variant', 'observer', 'kind', 'name', 'samples', 'rmse', 'max_abs_error',
                'settling_time', 'ss_std', 'ss_mean', 'tolerance', 'residual_rms',
                'ljung_box_q', 'ljung_box_p', 'acf_outside']


def _csv_rows(result):
    rows = []
    for name, vr in result.variants.items():
        for state, m in vr.states.items():
            rows.append(dict(variant=name, observer=vr.kind, kind='state', name=state,
                             tolerance=result.tolerance.get(state), **m))
        for output, m in vr.outputs.items():
            rows.append({'variant': name, 'observer': vr.kind, 'kind': 'output', 'name': output,
                         'samples': m['samples'], 'residual_rms': m['residual_rms'],
                         'ljung_box_q': m['ljung_box_q'], 'ljung_box_p': m['ljung_box_p'],
                         'acf_outside': m['acf_outside']})
    return rows


def _csv_cell(v):
    if v is None:
        return ''
    if isinstance(v, (float, np.floating)):
        f = float(v)
        if math.isnan(f):
            return ''
        return 'inf' if math.isinf(f) else repr(f)
    return str(v)


def _prepare_out(out, force):
    out = Path(out)
    if out.exists():
        if not force:
            raise BagToolError(f'{out} exists; refusing to overwrite it (use --force or '
                               '--out DIR)')
        if not out.is_dir():
            raise BagToolError(f'{out} exists and is not a folder')
        if any(out.iterdir()) and not (out / 'results.json').exists():
            raise BagToolError(f'{out} exists and is not an observer-eval output folder '
                               '(no results.json); not deleting it even with --force')
        shutil.rmtree(out)
    out.mkdir(parents=True)
    return out


def write_results(result, out, force=False, plots=True, results_bag=True,
                  bag_max_messages=BAG_MAX_MESSAGES):
    """
    Write the evaluation to a new folder.

    Parameters
    ----------
    result : EvalResult
        The evaluation, from :func:`evaluate_bag`.
    out : str or Path
        The folder; it must not exist unless ``force`` (then an earlier observer-eval
        output there is replaced).
    force : bool
        Replace an earlier observer-eval output folder at ``out``.
    plots : bool
        Write ``states.png``, ``error_norm.png`` (with ground truth) and
        ``residuals.png``.
    results_bag : bool
        Write ``results_bag/`` (mcap): ``/eval/<variant>/state/estimate`` (JointState),
        ``/eval/<variant>/state/error`` and ``/eval/state/true`` when there is ground truth.
    bag_max_messages : int
        At most this many messages per topic in the results bag (evenly decimated).

    Returns
    -------
    files : list of Path

    Raises
    ------
    BagToolError
        The folder exists (without ``force``), or exists and is not an earlier output.

    """
    out = _prepare_out(out, force)
    files = []
    table = format_table(result)
    (out / 'results.txt').write_text(table + '\n')
    files.append(out / 'results.txt')
    with open(out / 'results.csv', 'w') as f:
        f.write(','.join(_CSV_COLUMNS) + '\n')
        for row in _csv_rows(result):
            f.write(','.join(_csv_cell(row.get(c)) for c in _CSV_COLUMNS) + '\n')
    files.append(out / 'results.csv')
    with open(out / 'results.json', 'w') as f:
        json.dump(result.to_dict(), f, indent=2)
        f.write('\n')
    files.append(out / 'results.json')
    if plots:
        files += _plots(result, out)
    if results_bag:
        files.append(_results_bag(result, out / 'results_bag', bag_max_messages))
    return files


def _decimate(n, limit):
    if n <= limit:
        return slice(None)
    return slice(None, None, int(math.ceil(n / limit)))


def _plots(result, out):
    import matplotlib
    matplotlib.use('Agg', force=True)
    import matplotlib.pyplot as plt

    files = []
    names = result.state_names
    t0 = _t0(result)
    colors = plt.rcParams['axes.prop_cycle'].by_key().get('color', ['C0'])
    fig, axes = plt.subplots(len(names), 1, sharex=True, squeeze=False,
                             figsize=(10, 2.2 * len(names) + 1))
    if result.truth is not None:
        t_ns, values, _ = result.truth
        d = _decimate(t_ns.size, PLOT_MAX_POINTS)
        for i, ax in enumerate(axes[:, 0]):
            ax.plot((t_ns[d] - t0) * 1e-9, values[d, i], color='k', lw=2.0, label='true')
    for c, (name, vr) in enumerate(result.variants.items()):
        rep = vr.replay
        d = _decimate(len(rep), PLOT_MAX_POINTS)
        style = {'ls': '--', 'lw': 1.2, 'color': '0.4'} if name == 'live' else \
            {'lw': 1.0, 'color': colors[c % len(colors)]}
        for i, ax in enumerate(axes[:, 0]):
            ax.plot((rep.stamp_ns[d] - t0) * 1e-9, rep.x_hat[d, i], label=name, **style)
    for i, ax in enumerate(axes[:, 0]):
        ax.set_ylabel(names[i])
        ax.grid(True, alpha=0.3)
    axes[0, 0].legend(loc='best', fontsize='small')
    axes[0, 0].set_title(f'{result.vehicle.name}: true and estimated states')
    axes[-1, 0].set_xlabel('time since the start of the bag [s]')
    fig.tight_layout()
    fig.savefig(out / 'states.png', dpi=100)
    plt.close(fig)
    files.append(out / 'states.png')
    if result.truth is not None:
        fig, ax = plt.subplots(figsize=(10, 4))
        for c, (name, vr) in enumerate(result.variants.items()):
            if vr.error is None:
                continue
            ok = np.all(np.isfinite(vr.error), axis=1)
            norm = np.linalg.norm(vr.error[ok], axis=1)
            ts = (vr.replay.stamp_ns[ok] - t0) * 1e-9
            d = _decimate(norm.size, PLOT_MAX_POINTS)
            style = {'ls': '--', 'color': '0.4'} if name == 'live' else \
                {'color': colors[c % len(colors)]}
            ax.semilogy(ts[d], np.maximum(norm[d], 1e-16), label=name, **style)
        ax.set_xlabel('time since the start of the bag [s]')
        ax.set_ylabel('|x_hat - x|')
        ax.set_title('estimation error norm')
        ax.grid(True, which='both', alpha=0.3)
        ax.legend(loc='best', fontsize='small')
        fig.tight_layout()
        fig.savefig(out / 'error_norm.png', dpi=100)
        plt.close(fig)
        files.append(out / 'error_norm.png')
    outputs = result.output_names
    fig, axes = plt.subplots(len(outputs), 1, sharex=True, squeeze=False,
                             figsize=(10, 2.2 * len(outputs) + 1))
    for c, (name, vr) in enumerate(result.variants.items()):
        rep = vr.replay
        for j, ax in enumerate(axes[:, 0]):
            ok = np.isfinite(rep.residual[:, j])
            if not ok.any():
                continue
            d = _decimate(int(ok.sum()), PLOT_MAX_POINTS)
            style = {'ls': '--', 'color': '0.4'} if name == 'live' else \
                {'color': colors[c % len(colors)]}
            ax.plot((rep.stamp_ns[ok][d] - t0) * 1e-9, rep.residual[ok, j][d], lw=0.8,
                    label=name, **style)
    for j, ax in enumerate(axes[:, 0]):
        ax.set_ylabel(f'residual {outputs[j]}')
        ax.grid(True, alpha=0.3)
    axes[0, 0].legend(loc='best', fontsize='small')
    axes[0, 0].set_title('residuals y - (C x_prior + D u)')
    axes[-1, 0].set_xlabel('time since the start of the bag [s]')
    fig.tight_layout()
    fig.savefig(out / 'residuals.png', dpi=100)
    plt.close(fig)
    files.append(out / 'residuals.png')
    return files


def _t0(result):
    starts = [int(vr.replay.stamp_ns.min()) for vr in result.variants.values()
              if len(vr.replay)]
    if result.truth is not None and result.truth[0].size:
        starts.append(int(result.truth[0].min()))
    return min(starts) if starts else 0


def _joint_state_bytes(names, stamp_ns, values):
    """Serialize JointState messages (name, position) for many stamps at once."""
    from .reader import _joint_state_layout   # the same layout rules as the decoder
    store = jazzy_typestore()
    js = store.types['sensor_msgs/msg/JointState']
    hdr = store.types['std_msgs/msg/Header']
    tm = store.types['builtin_interfaces/msg/Time']
    k = len(names)
    msg = js(header=hdr(stamp=tm(sec=0, nanosec=0), frame_id=''), name=list(names),
             position=np.zeros(k), velocity=np.zeros(0), effort=np.zeros(0))
    template = np.frombuffer(bytes(store.serialize_cdr(msg, js.__msgtype__)), np.uint8)
    _, arrays, _ = _joint_state_layout(template.tobytes())
    off, count = arrays['position']
    assert count == k
    N = stamp_ns.size
    rows = np.tile(template, (N, 1))
    rows[:, 4:8] = (stamp_ns // 1_000_000_000).astype('<i4').view(np.uint8).reshape(N, 4)
    rows[:, 8:12] = (stamp_ns % 1_000_000_000).astype('<u4').view(np.uint8).reshape(N, 4)
    rows[:, off:off + 8 * k] = np.ascontiguousarray(values, dtype='<f8').view(
        np.uint8).reshape(N, 8 * k)
    return rows


def _results_bag(result, path, limit):
    from rosbags.rosbag2 import StoragePlugin, Writer
    store = jazzy_typestore()
    js = 'sensor_msgs/msg/JointState'
    topics = []
    names = list(result.state_names)
    if result.truth is not None:
        t_ns, values, _ = result.truth
        topics.append(('/eval/state/true', t_ns, values, names))
    for name, vr in result.variants.items():
        rep = vr.replay
        topics.append((f'/eval/{name}/state/estimate', rep.stamp_ns, rep.x_hat, names))
        if vr.error is not None:
            ok = np.all(np.isfinite(vr.error), axis=1)
            topics.append((f'/eval/{name}/state/error', rep.stamp_ns[ok], vr.error[ok],
                           names))
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        for topic, ns, values, comp in topics:
            conn = writer.add_connection(topic, js, typestore=store)
            d = _decimate(ns.size, limit)
            ns, values = np.asarray(ns[d], dtype=np.int64), values[d]
            if not ns.size:
                continue
            rows = _joint_state_bytes(comp, ns, values)
            write = writer.write
            for stamp, row in zip(ns.tolist(), rows):
                write(conn, stamp, row.tobytes())
    return path


# ---------------------------------------------------------------------------------------
# Command line
# ---------------------------------------------------------------------------------------

class _Progress:
    """A one-line text progress bar on stderr."""

    def __init__(self, enabled, stream=sys.stderr):
        self.enabled = enabled
        self.stream = stream
        self.label = None
        self.last = 0.0

    def __call__(self, label, done, total):
        if not self.enabled:
            return
        now = time.monotonic()
        if label == self.label and now - self.last < 0.2 and done < total:
            return
        if label != self.label and self.label is not None:
            self.stream.write('\n')
        self.label, self.last = label, now
        if total:
            frac = min(1.0, done / total)
            bar = '#' * int(30 * frac) + '.' * (30 - int(30 * frac))
            text = f'\r{label:<20} [{bar}] {frac * 100:5.1f}% {done}/{total}'
        else:
            text = f'\r{label:<20} {done}'
        self.stream.write(text)
        self.stream.flush()

    def finish(self):
        if self.enabled and self.label is not None:
            self.stream.write('\n')
            self.stream.flush()
            self.label = None


_EPILOG = """\
variants:
  --variant NAME:KEY:=VALUE[,KEY:=VALUE...]   (repeatable; the same NAME adds overrides)
  KEY is a vehicle-file parameter (docs/vehicle_schema.md) and VALUE is YAML, as in a ROS
  -p override. Commas inside [...] belong to the value. Quote the whole argument.
    --variant 'slow:observer.poles:=[-0.1,-0.11,-0.12]'
    --variant 'kalman:observer.type:=kalman,observer.Rd:=[1.0e-6]'
    --variant 'kalman:observer.Qd:=[1.0e-4,0.0,0.0, 0.0,1.0e-4,0.0, 0.0,0.0,1.0e-4]'
                                                       (the same name: merged with the above)
    --variant 'openloop:observer.type:=open_loop'
  The vehicle file's own design is always the variant "design"; the estimate recorded on
  state/estimate is scored as "live".

output (folder --out; default <bag>_eval next to the bag directory, e.g. runs/sub1 ->
runs/sub1_eval, wherever the command is run from; never overwritten without --force):
  the table on stdout and in results.txt, results.csv, results.json, states.png,
  error_norm.png, residuals.png, and results_bag/ (mcap) with /eval/<variant>/state/estimate,
  /eval/<variant>/state/error and /eval/state/true for PlotJuggler or Foxglove.

exit status: 0 done; 2 the bag, the vehicle file or the arguments cannot be used (one line
'error: ...' on stderr).
"""


def _parser():
    parser = argparse.ArgumentParser(
        prog='observer-eval',
        description="Replay a bag's recorded measurements and commands through observer "
                    'configurations (the same estimator code as the observer node) and '
                    'compare them with the true state (state/true) or, without it, by '
                    'their residuals.',
        epilog=_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('bag', help='bag directory, or one .mcap or .db3 file')
    parser.add_argument('--vehicle', required=True, help='vehicle file (config/<name>.yaml)')
    parser.add_argument('--variant', action='append', default=[],
                        metavar='NAME:KEY:=VALUE[,...]',
                        help='an observer configuration to compare (see below)')
    parser.add_argument('--out', help='output folder (default: <bag>_eval next to the bag '
                        'directory)')
    parser.add_argument('--namespace', help="the vehicle's namespace in the bag, e.g. /sub1 "
                        '(default: detected from the sensor topics)')
    parser.add_argument('--tolerance', help="settling band: a percentage of each state's "
                        'range ("5%%") or an absolute value (default 2%%)')
    parser.add_argument('--force', action='store_true',
                        help='replace an existing output folder of observer-eval')
    parser.add_argument('--no-plots', action='store_true', help='do not write PNG plots')
    parser.add_argument('--no-bag', action='store_true', help='do not write the results bag')
    parser.add_argument('--bag-max', type=int, default=BAG_MAX_MESSAGES, metavar='N',
                        help='at most N messages per topic in the results bag '
                             f'(default {BAG_MAX_MESSAGES}; decimated beyond)')
    parser.add_argument('--exact', action='store_true',
                        help='call the estimator for every message (no bulk replay)')
    parser.add_argument('--progress', action='store_true',
                        help='show progress even when stderr is not a terminal')
    return parser


def _default_out(bag):
    """
    Return the default output folder: ``<bag>_eval`` next to the bag directory.

    For a storage file inside a bag directory (one with metadata.yaml) that directory is
    the bag; a bare ``.mcap``/``.db3`` file gets ``<stem>_eval`` next to it. The folder
    does not depend on the current directory.

    """
    bag = Path(bag)
    if bag.name in ('', '.', '..'):
        bag = bag.resolve()
    if bag.is_file():
        if not (bag.parent / 'metadata.yaml').is_file():
            return bag.with_name(f'{bag.stem or "bag"}_eval')
        bag = bag.parent
        if bag.name in ('', '.', '..'):
            bag = bag.resolve()
    return bag.parent / f'{bag.name or "bag"}_eval'


def main(argv=None):
    """Entry point of ``observer-eval``; returns the exit status."""
    args = _parser().parse_args(argv)
    started = time.perf_counter()
    progress = _Progress(args.progress or sys.stderr.isatty())
    try:
        variants = {}
        for text in args.variant:
            name, overrides = parse_variant(text)
            variants.setdefault(name, []).extend(overrides)
        if args.tolerance is not None:
            parse_tolerance(args.tolerance)
        if not Path(args.bag).exists():
            raise BagToolError(f'{args.bag}: no such file or directory')
        out = Path(args.out) if args.out else _default_out(args.bag)
        if out.exists() and not args.force:
            raise BagToolError(f'{out} exists; refusing to overwrite it (use --force or '
                               '--out DIR)')
        with warnings.catch_warnings():
            warnings.simplefilter('ignore')
            result = evaluate_bag(args.bag, args.vehicle, variants, args.namespace,
                                  args.tolerance, exact=args.exact, progress=progress)
            progress.finish()
            files = write_results(result, out, force=args.force, plots=not args.no_plots,
                                  results_bag=not args.no_bag, bag_max_messages=args.bag_max)
    except (ObserverError, OSError) as err:
        progress.finish()
        text = str(err).splitlines()[0] if str(err) else type(err).__name__
        print(f'error: {text}', file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        progress.finish()
        print('error: interrupted', file=sys.stderr)
        return 130
    print(format_table(result))
    for text in result.warnings:
        print(f'warning: {text}', file=sys.stderr)
    print(f'\nwritten to {out}/ ({", ".join(f.name for f in files)}) in '
          f'{time.perf_counter() - started:.1f} s')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
