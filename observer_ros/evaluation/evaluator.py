# observer_ros.evaluation.evaluator: a bag replayed through observer variants, and scored.
"""
Offline evaluation of estimators on a recorded bag.

The recorded measurements and commands are replayed, at their recorded stamps and in bag
order, through one or more observer configurations with the same estimator code as the
observer node (:mod:`observer_ros.replay.replay`). The vehicle file's own design is always
the variant ``design``; ``--variant`` adds configurations that override the file; the
live estimate recorded on ``state/estimate`` is scored as the variant ``live``.

Against ``state/true`` (matched by stamp, interpolated where the stamps differ) each
variant gets, per state: RMSE, maximum absolute error, settling time (the time after
which the error stays within a tolerance: 2 % of the state's range in the true
trajectory unless ``--tolerance``; ``never`` when it still leaves the band in the steady
state) and the steady-state error spread and mean (over the last 20 % of the run: the
noise the observer lets through). Always, per output: the
residual RMS and its whiteness (normalised autocorrelation at lags 1..k, the Ljung-Box
statistic and its p-value, the fraction of lags outside +-1.96/sqrt(N)).

Python API: :func:`evaluate_bag` returns an :class:`EvalResult`;
:func:`write_results` (:mod:`observer_ros.evaluation.report`) writes the table, ``results.csv``,
``results.json``, PNG plots (:mod:`observer_ros.evaluation.plots`) and a results bag
(``/eval/<variant>/state/estimate``, ``/eval/state/true``). :func:`evaluate_job` is one
job, one bag x one variant, with a plain picklable :class:`JobResult` (no arrays, no
open files): the unit to run serially or on many workers. The metrics are in
:mod:`observer_ros.evaluation.metrics`.

"""
from dataclasses import dataclass, field
import os
from pathlib import Path
import re
import time
from typing import Dict, Tuple
import warnings

import numpy as np

from .cli import resolve_vehicle
from .metrics import (DEFAULT_TOLERANCE, score_variant, STEADY_FRACTION, tolerances,
                      whiteness, WHITENESS_LAGS)
from .report import format_table, write_results
from .results import EvalResult, jsonable, ScoredReplay, VariantResult
from ..bag.errors import BagToolError
from ..bag.reader import read_recording
from ..bag.spill import blocks, count_true, is_spilled, Sink
from ..core.errors import ObserverError
from ..core.vehicle_design import design_vehicle
from ..replay.events import epoch_cuts, epochs_from_cuts
from ..replay.replay import (CLOCK_JUMP_AGREEMENT, CLOCK_JUMP_TOLERANCE, epochs_of,
                             live_replay, replay)

__all__ = ['DEFAULT_TOLERANCE', 'STEADY_FRACTION', 'WHITENESS_LAGS', 'VariantResult',
           'EvalResult', 'JobResult', 'parse_variant', 'parse_compare', 'parse_tolerance',
           'evaluate_bag',
           'evaluate_job', 'write_results', 'format_table', 'whiteness']

RESERVED = ('design', 'live')
_NAME = re.compile(r'^[A-Za-z][A-Za-z0-9_]*$')


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


def parse_options(variant_texts, tolerance):
    """
    Check the ``--variant`` and ``--tolerance`` options of a command line.

    Returns ``{name: [overrides]}`` (the same name repeated merges its overrides); raises
    BagToolError on a bad one (:func:`parse_variant`, :func:`parse_tolerance`).

    """
    variants = {}
    for text in variant_texts:
        name, overrides = parse_variant(text)
        variants.setdefault(name, []).extend(overrides)
    if tolerance is not None:
        parse_tolerance(tolerance)
    return variants


def parse_compare(text):
    """
    Parse ``--compare [NAME=]FILE`` into ``(name, file)``.

    Without NAME the file name's stem, other characters than letters, digits and _
    replaced by _, is the name.

    """
    name, sep, path = str(text).partition('=')
    if not sep:
        path = name
        name = re.sub(r'[^A-Za-z0-9_]', '_', Path(path).stem)
        if not name[:1].isalpha():
            name = 'v' + name
    if not path:
        raise BagToolError(f'--compare {text!r}: expected [NAME=]FILE')
    if not _NAME.match(name) or name in RESERVED:
        raise BagToolError(f'--compare {text!r}: the name {name!r} must be a letter '
                           'followed by letters, digits or _, and not design or live')
    # a pipe (--compare <(cat V_tuned.yaml)) is read as the --vehicle file is; a folder or a
    # device is refused by the loader (params_file.read_text), naming what it is
    if not os.path.exists(path):
        raise BagToolError(f'--compare {text!r}: {path}: no such file')
    return name, path


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
# Evaluation
# ---------------------------------------------------------------------------------------

def evaluate_bag(bag_path, vehicle, variants=None, namespace=None, tolerance=None,
                 exact=False, progress=None, clock_jump_tolerance=CLOCK_JUMP_TOLERANCE,
                 include_live=True, include_design=True, compare=None, spill=None,
                 keep_rows=True, health=True, clock_jump_agreement=CLOCK_JUMP_AGREEMENT,
                 states=True, recording=None):
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
        A stamp this many seconds before the newest is far back: a clock jump (reset)
        when ``clock_jump_agreement`` of them come in a row (the observer node's rule).
    include_live : bool
        Score the recorded ``state/estimate`` as the variant ``live``.
    include_design : bool
        Replay the vehicle file's own design as the variant ``design`` (when False, only
        ``variants`` are replayed; with no variants the design is replayed anyway).
    compare : dict, optional
        ``{name: vehicle file}``: other vehicle files replayed as variants (e.g. a
        tuned file against the original); same states, inputs and sensors as
        ``vehicle``.
    spill : True or path, optional
        Keep each replay's rows in temporary files (:func:`~observer_ros.replay.replay.replay`'s
        ``spill``): memory does not grow with them; every figure is the same.
    keep_rows : bool
        Keep each variant's rows (and errors) for the plots and the results bag. When
        False each variant is scored as soon as its replay ends and its rows are dropped
        (its ``replay`` becomes a :class:`~observer_ros.evaluation.results.ScoredReplay`): the
        memory of a search does not grow with the number of variants. Either way every
        variant is scored right after its replay, with the same figures.
    health : bool
        Judge each sensor's innovation health (``VariantResult.sensors``); a gain
        search, whose metric does not use it, turns it off.
    clock_jump_agreement : int
        Far-back measurements in a row that make a clock jump (the observer node's
        parameter).
    states : bool
        Score each state against the truth (``VariantResult.states``, the summary's
        ``settling_time``); a gain search, whose metric is the error norm's RMS, turns
        it off (the error is then computed once per row, for that RMS).
    recording : Recording, optional
        The bag already read (:func:`~observer_ros.bag.reader.read_recording` of this
        bag with ``vehicle``'s sensors and ``namespace``): not read again. Its columns
        stay where they are (in memory: ``spill`` then applies to the replays' rows).

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
    base = resolve_vehicle(vehicle)
    configs = {'design': (base, ())} if include_design or not (variants or compare) \
        else {}
    for name, path in (compare or {}).items():
        if name in RESERVED or not _NAME.match(str(name)) or name in (variants or {}):
            raise BagToolError(f'--compare {name}={path}: the name {name!r} is reserved, '
                               'not a valid name or already a variant')
        other = resolve_vehicle(path)
        same = [k for k in ('state_names', 'input_names', 'output_names')
                if tuple(getattr(other.plant, k)) != tuple(getattr(base.plant, k))]
        if not same and [(x.name, x.topic, tuple(x.outputs)) for x in other.sensors] != \
                [(x.name, x.topic, tuple(x.outputs)) for x in base.sensors]:
            same = ['sensors']
        if same:
            raise BagToolError(f'--compare {path}: its {same[0].replace("_", " ")} differ '
                               f'from those of {base.name}')
        configs[name] = (other, (f'file {path}',))
    for name, overrides in (variants or {}).items():
        if name in RESERVED or not _NAME.match(str(name)):
            raise BagToolError(f'variant name {name!r} is reserved or not a valid name')
        try:
            with warnings.catch_warnings():
                warnings.simplefilter('ignore')
                configs[name] = (resolve_vehicle(vehicle, overrides), tuple(overrides))
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

    if recording is None:
        recording = read_recording(bag_path, base, namespace, progress=stage('reading'),
                                   spill=spill)
    warnings_out = list(recording.warnings)
    truth = _truth(recording.truth, clock_jump_tolerance, spill)
    if tolerance is None:
        fraction, absolute = DEFAULT_TOLERANCE, None
    elif isinstance(tolerance, str):
        fraction, absolute = parse_tolerance(tolerance)
    else:
        fraction, absolute = None, float(tolerance)
    rule = f"{fraction * 100:g}% of each state's range in the true trajectory" \
        if absolute is None else f'{absolute:g} (absolute)'
    tol = tolerances(None if truth is None else truth[1], base.plant.state_names,
                     fraction, absolute)
    result = EvalResult(bag_path=Path(bag_path), vehicle=base, recording=recording,
                        variants={}, truth=truth, tolerance=tol, tolerance_rule=rule,
                        warnings=warnings_out)
    for name, (v, overrides) in configs.items():
        try:
            rep = replay(recording, v, name=name, overrides=overrides, exact=exact,
                         clock_jump_tolerance=clock_jump_tolerance,
                         clock_jump_agreement=clock_jump_agreement,
                         progress=stage(f'replaying {name}'), spill=spill)
        except ObserverError as err:
            if isinstance(err, BagToolError):
                raise BagToolError(f'variant {name!r}: {err}') from None
            raise type(err)(f'variant {name!r}: {err}') from None
        for text in rep.warnings:
            warnings_out.append(f'{name}: {text}')
        if not len(rep):
            warnings_out.append(f'{name}: no measurement was accepted')
        _scored(result, VariantResult(name, v.observer.kind, overrides, rep), keep_rows,
                health, states)
        del rep
    if include_live:
        live = live_replay(recording, base, clock_jump_tolerance, spill=spill)
        if live is not None:
            _scored(result, VariantResult('live', 'recorded', (), live), keep_rows, health,
                    states)
    result.seconds = time.perf_counter() - start
    return result


def _truth(tr, tolerance, spill):
    """
    Return the truth's valid rows as (stamps, values, epochs), or None when it has none.

    With ``spill`` the columns of a spilled stream stay in temporary files: the
    stream's own when every message is valid, else the valid rows copied a block at a
    time.

    """
    if tr is None or not count_true(tr.valid):
        return None
    if spill is None or not is_spilled(tr.stamp_ns):     # a recording read in memory
        sel = np.flatnonzero(tr.valid)
        t_ns = tr.stamp_ns[sel]
        return t_ns, tr.values[sel], epochs_of(t_ns, tolerance)
    t_ns, values = tr.stamp_ns, tr.values
    if count_true(tr.valid) < len(tr):
        t_ns = Sink(np.int64, (), 0, spill)
        values = Sink(np.float64, tr.values.shape[1:], 0, spill)
        for lo, ok in blocks(tr.valid):
            sel = np.flatnonzero(ok) + lo
            t_ns.append(tr.stamp_ns[sel])
            values.append(tr.values[sel])
        t_ns, values = t_ns.result(), values.result()
    return t_ns, values, epochs_from_cuts(epoch_cuts(t_ns, tolerance), len(t_ns), spill)


def _scored(result, vr, keep_rows, health=True, states=True):
    """Score a variant and add it to the result; without ``keep_rows``, drop its rows."""
    score_variant(result, vr, health, states)
    if not keep_rows:
        vr.replay, vr.error, vr.matched = ScoredReplay.of(vr.replay), None, None
    result.variants[vr.name] = vr


@dataclass
class JobResult:
    """
    One job's result: one bag replayed through one variant, as plain data.

    Everything is built-in Python values (str, int, float, dict, list), so the result
    pickles and crosses process and machine boundaries; ``to_dict()`` is JSON-ready.

    """

    bag: str
    vehicle: str
    variant: str
    observer_type: str
    overrides: Tuple[str, ...]
    estimates: int
    counts: Dict[str, int]
    summary: Dict[str, object]
    states: Dict[str, dict]
    outputs: Dict[str, dict]
    ground_truth: bool
    warnings: Tuple[str, ...] = field(default_factory=tuple)
    seconds: float = 0.0

    def to_dict(self):
        """Return the result as JSON-ready data (inf and NaN as None)."""
        return jsonable(dict(vars(self)))


def evaluate_job(bag_path, vehicle, variant='design', overrides=(), namespace=None,
                 tolerance=None, exact=False, clock_jump_tolerance=CLOCK_JUMP_TOLERANCE,
                 spill=None):
    """
    Evaluate one bag with one observer configuration (one job).

    Parameters
    ----------
    bag_path : str or Path
        Bag directory or ``.mcap`` / ``.db3`` file.
    vehicle : str or Path or Vehicle
        The vehicle file (a path pickles best) or a loaded vehicle.
    variant : str
        The job's variant name: ``design`` (the file as it is, ``overrides`` must be
        empty), ``live`` (the recorded estimate) or a variant name.
    overrides : sequence of str
        ``KEY:=VALUE`` overrides of the vehicle file for the variant.
    namespace, tolerance, exact, clock_jump_tolerance, spill
        As in :func:`evaluate_bag` (the rows are dropped once scored).

    Returns
    -------
    result : JobResult
        Metrics equal to those :func:`evaluate_bag` gives the same variant.

    Raises
    ------
    BagToolError
        The bag cannot be read, does not match the vehicle, or has no recorded estimate
        for ``live``.
    ObserverError
        The vehicle file or the overrides are invalid.

    """
    overrides = tuple(overrides)
    if variant in RESERVED and overrides:
        raise BagToolError(f'variant {variant!r} takes no overrides')
    live = variant == 'live'
    variants = {} if variant in RESERVED else {variant: list(overrides)}
    res = evaluate_bag(bag_path, vehicle, variants, namespace, tolerance, exact=exact,
                       clock_jump_tolerance=clock_jump_tolerance, include_live=live,
                       include_design=variant == 'design', spill=spill, keep_rows=False)
    if variant not in res.variants:
        raise BagToolError(f'{bag_path}: no recorded state/estimate to score as '
                           f'{variant!r}')
    vr = res.variants[variant]
    return JobResult(
        bag=str(bag_path), vehicle=str(getattr(vehicle, 'name', vehicle)), variant=variant,
        observer_type=vr.kind, overrides=overrides, estimates=len(vr.replay),
        counts={str(k): int(v) for k, v in vr.replay.counts.items()},
        summary=jsonable(vr.summary), states=jsonable(vr.states),
        outputs=jsonable(vr.outputs), ground_truth=res.truth is not None,
        warnings=tuple(res.warnings), seconds=res.seconds)
