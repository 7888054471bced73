# observer_ros.tuning.gain_search: choose an observer's poles or Kalman weights from bags.
"""
Gain search: replay bags through a family of observers and score each.

The family is one parameter, a scale ``s`` of the vehicle's observer:

- ``poles``: the observer poles times s (continuous model; ``z**s`` for a discrete one):
  s > 1 is faster;
- ``kalman``: the Kalman process-noise covariance ``observer.Qd`` times s (only the
  ratio of Qd to Rd sets the gain): s > 1 trusts the measurements more.

Each bag is read once and replayed through every scale of a grid (:func:`evaluate_bag`
with one variant per scale, each scored as soon as it is replayed and its rows dropped,
spilled to temporary files while it runs unless ``spill`` is None: memory does not grow
with the number of scales); ``refine`` then narrows the best grid interval with
``scipy.optimize.minimize_scalar``. The metric of a bag is the RMS of the estimation
error norm against ``state/true`` when every bag has it (``error_rms``); otherwise, per
output, the residual RMS relative to that of the scale nearest 1, plus the fraction of
autocorrelation lags outside +-1.96/sqrt(N) (0.05 for white residuals), averaged over the
outputs. Over many bags the metric is the mean of the per-bag metrics (each bag's is
in the table); the search minimises it. The grid's bag x scale evaluations can run as
jobs on Dask (``dask``), with the numbers of this process.

"""

from dataclasses import dataclass, field
import math
from typing import Dict, List, Optional
import warnings

import numpy as np
import scipy.linalg

from ..bag.errors import BagToolError
from ..evaluation.evaluator import evaluate_bag

__all__ = ['DEFAULT_SCALES', 'SearchResult', 'search_overrides', 'score_variants',
           'bag_keys', 'gain_search', 'model_errors']

DEFAULT_SCALES = tuple(float(s) for s in np.round(np.geomspace(0.25, 4.0, 9), 4))


@dataclass
class SearchResult:
    """A gain search: the metric per scale and bag, and the best scale."""

    kind: str
    metric: str
    scales: List[float]
    per_bag: Dict[str, List[float]]
    mean: List[float]
    best: float
    overrides: Dict[float, List[str]] = field(default_factory=dict)
    # predicted metric of each scale on the identified model (``model_errors``), or None;
    # with it, only the scales around the model's best were replayed (NaN: not replayed)
    model: Optional[List[float]] = None

    def rows(self):
        """Return the table rows: scale, mean metric, then one per bag."""
        return [[s, self.mean[i]] + [v[i] for v in self.per_bag.values()]
                for i, s in enumerate(self.scales)]

    def to_dict(self):
        """Return JSON-ready data."""
        return {'kind': self.kind, 'metric': self.metric, 'scales': self.scales,
                'per_bag': self.per_bag, 'mean': self.mean, 'best': self.best,
                'overrides': {str(k): v for k, v in self.overrides.items()},
                'model': self.model}


def metric_name(truth):
    """Return the metric's description (with or without ``state/true`` in every bag)."""
    return 'error_rms (|x_hat - x_true| RMS)' if truth else \
        'residual RMS / that at scale ~1 + fraction of ACF lags outside'


def _floats(values):
    return '[' + ', '.join(repr(float(v)) for v in values) + ']'


def search_overrides(vehicle, kind, scale):
    """
    Return the ``KEY:=VALUE`` overrides of one scale of the vehicle's observer.

    Raises
    ------
    BagToolError
        ``poles`` for an observer without poles, ``kalman`` for one without Qd.

    """
    obs = vehicle.observer
    if kind == 'poles':
        if obs.poles is None:
            raise BagToolError(f'--search poles: the {obs.kind} observer of {vehicle.name} '
                               'has no poles (give observer.poles, or --search kalman)')
        p = np.asarray(obs.poles, dtype=complex)
        p = p ** scale if vehicle.plant.is_discrete else p * scale
        return [f'observer.poles:={_floats(p.real)}', f'observer.poles_imag:={_floats(p.imag)}']
    if kind == 'kalman':
        if obs.kind != 'kalman' or obs.Qd is None:
            raise BagToolError(f'--search kalman: the observer of {vehicle.name} is not a '
                               'Kalman filter with observer.Qd')
        return [f'observer.Qd:={_floats(np.ravel(obs.Qd) * scale)}']
    raise BagToolError(f'--search {kind!r}: expected poles or kalman')


def _number(v):
    return math.nan if v is None else float(v)


def _bag_metric(summaries, outputs, names, ref, truth):
    """
    Return the metric of each variant of one bag.

    ``summaries`` and ``outputs`` are each variant's summary and per-output metrics (by
    name; None for NaN, as the job rows have them), ``ref`` the residual metric's base.

    """
    if truth:
        return [_number(summaries[n].get('error_rms')) for n in names]
    out = []
    for n in names:
        terms = []
        for output, m in outputs[n].items():
            base = _number(outputs[ref][output]['residual_rms'])
            if m['samples'] and base and math.isfinite(base):
                outside = _number(m['acf_outside'])
                terms.append(_number(m['residual_rms']) / base +
                             (outside if math.isfinite(outside) else 0.0))
        out.append(float(np.mean(terms)) if terms else math.nan)
    return out


def score_variants(bags, vehicle, overrides, ref, namespace=None, exact=False,
                   progress=None, dask=None, spill=True, recordings=None):
    """
    Return ({bag: [metric per variant]}, truth) of observers given by their overrides.

    ``overrides`` is a list of ``KEY:=VALUE`` lists, ``ref`` the index of the one the
    residual metric is relative to (see the module). In this process every bag is read
    once; with ``dask`` (``{'workers': N, 'scheduler': ADDRESS}``, a vehicle file path)
    each bag x variant is a job of :mod:`observer_ros.evaluation.jobs` on a Dask cluster, with
    the same numbers. ``spill``: :func:`evaluate_bag`'s (True: the replay's rows in
    temporary files; None: in memory); each variant's rows are dropped once scored.
    Variants with the same overrides are one observer, replayed once (a Qd of zeros
    times every scale of a grid). The sensors' innovation health and the per-state
    metrics are not computed (the metric does not use them). ``recordings``:
    ``{str(bag): Recording}`` of bags already read (by :func:`~observer_ros.tuning.identify.
    identify`), replayed without reading them again.

    """
    # the same observer is replayed once: its overrides as text name it (a Qd of zeros
    # times any scale is one filter); the others take its scores
    unique = list(dict.fromkeys(tuple(o) for o in overrides))
    names = tuple(f'scale_{i}' for i in range(len(unique)))
    which = [unique.index(tuple(o)) for o in overrides]
    keys = bag_keys(bags)
    if dask is not None:
        per_bag, truth = _score_jobs(bags, vehicle, dict(zip(names, unique)),
                                     which[ref], namespace, exact, progress, dask, spill)
        return {k: [v[j] for j in which] for k, v in per_bag.items()}, truth
    per_bag, truth = {}, True
    for i, (key, bag) in enumerate(zip(keys, bags)):
        if progress:
            progress('searching', i, len(bags))
        r = evaluate_bag(bag, vehicle, dict(zip(names, map(list, unique))), namespace,
                         exact=exact, include_live=False, include_design=False, spill=spill,
                         keep_rows=False, health=False, states=False,
                         recording=(recordings or {}).get(str(bag)))
        truth = truth and r.truth is not None
        per_bag[key] = ({n: r.variants[n].summary for n in names},
                        {n: r.variants[n].outputs for n in names})
    if progress:
        progress('searching', len(bags), len(bags))
    out = {}
    for key, scored in per_bag.items():
        metric = _bag_metric(*scored, names, names[which[ref]], truth)
        out[key] = [metric[j] for j in which]
    return out, truth


def _score_jobs(bags, vehicle, variants, ref, namespace, exact, progress, dask, spill):
    from ..evaluation.jobs import Job, run_jobs
    names = tuple(variants)
    jobs = [Job(str(bag), str(vehicle), n, tuple(variants[n]), namespace, None, bool(exact))
            for bag in bags for n in names]
    rows = run_jobs(jobs, 'dask', dask.get('workers'), dask.get('scheduler'),
                    None if progress is None else lambda d, t: progress('search jobs', d, t),
                    spill=spill)
    failed = [r for r in rows if r['error']]
    if failed:
        raise BagToolError(f'{failed[0]["bag"]}: {failed[0]["error"]}')
    truth = all(r['ground_truth'] for r in rows)
    per_bag = {}
    for i, key in enumerate(bag_keys(bags)):
        part = rows[i * len(names):(i + 1) * len(names)]
        per_bag[key] = _bag_metric({r['variant']: r['summary'] for r in part},
                                   {r['variant']: r['outputs'] for r in part}, names,
                                   names[ref], truth)
    return per_bag, truth


def bag_keys(bags):
    """Return the bags' names in the tables (a bag given twice gets a prime)."""
    keys = []
    for bag in bags:
        key = str(bag)
        while key in keys:
            key += "'"
        keys.append(key)
    return keys


def _scores(bags, vehicle, base, kind, scales, namespace, exact, progress=None, dask=None,
            spill=True, recordings=None):
    """Return ({bag: [metric per scale]}, truth) of one batch of scales."""
    ref = int(np.argmin([abs(math.log(s)) for s in scales]))
    return score_variants(bags, vehicle, [search_overrides(base, kind, s) for s in scales],
                          ref, namespace, exact, progress, dask, spill, recordings)


def model_errors(Ad, C, Qk, R, scales, filter_Qk=None):
    """
    Return the steady-state RMS error of the Kalman filter of each scale, on a model.

    The filter of ``(s Qf, R)`` (``Qf`` is ``filter_Qk``, by default ``Qk``; steady-state
    gain of ``scipy.linalg.solve_discrete_are``) on the sampled model ``x+ = Ad x + w``,
    ``y = C x + v`` whose noises are ``(Qk, R)``: its error covariance solves a discrete
    Lyapunov equation (``scipy.linalg.solve_discrete_lyapunov``), and the RMS of the error
    norm is the square root of its trace after the correction. NaN where a scale has no
    steady state.

    """
    Ad, C, Qk, R = (np.atleast_2d(np.asarray(M, dtype=float)) for M in (Ad, C, Qk, R))
    Qf = Qk if filter_Qk is None else np.atleast_2d(np.asarray(filter_Qk, dtype=float))
    eye = np.eye(Ad.shape[0])
    out = []
    for s in scales:
        try:
            P = scipy.linalg.solve_discrete_are(Ad.T, C.T, s * Qf, R)
            K = np.linalg.solve(C @ P @ C.T + R, C @ P).T
            IKC = eye - K @ C
            KRK = K @ R @ K.T
            prior = scipy.linalg.solve_discrete_lyapunov(Ad @ IKC, Ad @ KRK @ Ad.T + Qk)
            post = IKC @ prior @ IKC.T + KRK
            value = math.sqrt(max(float(np.trace(post)), 0.0))
        except (ValueError, np.linalg.LinAlgError):
            value = math.nan
        out.append(value if math.isfinite(value) else math.nan)
    return out


def _identified_model(ident):
    """
    Return ``(Ad, C, Qk, R, noise_map)`` of an identification (its sampled model), or None.

    ``noise_map`` maps a process noise on the identification's columns to its per-step
    covariance.

    """
    try:
        from ..core.als import process_noise_map
        from .sampled import sampled_model
        plant = ident.vehicle.plant
        Ad, _ = sampled_model(ident.vehicle, ident.dt)
        r = ident.result
        F = process_noise_map(plant.A, ident.G, ident.dt, plant.is_discrete)
        return Ad, plant.C, r.Qk, r.R, F
    except (AttributeError, TypeError, ValueError):
        return None


def _model_first(bags, vehicle, base, scales, predicted, namespace, exact, progress, spill,
                 recordings=None):
    """
    Replay the model's best scale and its neighbours, then more until a minimum is bracketed.

    Returns ``(per_bag, truth)`` with NaN for the scales not replayed. Every batch of
    replays includes the scale nearest 1 (the residual metric's base).

    """
    ref = int(np.argmin([abs(math.log(s)) for s in scales]))
    start = int(np.nanargmin(predicted))
    per_bag, truth, done = None, True, set()
    batch = {i for i in (start - 1, start, start + 1) if 0 <= i < len(scales)}
    while batch:
        idx = sorted(batch | {ref})
        got, t = score_variants(bags, vehicle, [search_overrides(base, 'kalman', scales[i])
                                                for i in idx], idx.index(ref), namespace,
                                exact, progress, None, spill, recordings)
        truth = truth and t
        if per_bag is None:
            per_bag = {k: [math.nan] * len(scales) for k in got}
        for key, values in got.items():
            for i, v in zip(idx, values):
                per_bag[key][i] = v
        done |= set(idx)
        mean = np.array([np.nanmean([v[i] for v in per_bag.values()]) if i in done
                         else math.nan for i in range(len(scales))])
        if not np.isfinite(mean).any():
            break
        best = int(np.nanargmin(mean))
        batch = {i for i in (best - 1, best + 1) if 0 <= i < len(scales)} - done
    return per_bag, truth


def gain_search(bags, vehicle, kind, scales=DEFAULT_SCALES, namespace=None, exact=False,
                progress=None, refine=0, dask=None, spill=True, model=None, recordings=None):
    """
    Score a family of observers (see the module) on one or many bags.

    Parameters
    ----------
    bags : sequence of str or Path
        The bags.
    vehicle : str or Path or Vehicle
        The vehicle (file) whose observer is scaled.
    kind : {'poles', 'kalman'}
        What is scaled.
    scales : sequence of float
        The scales (> 0).
    namespace : str, optional
        The vehicle's namespace in the bags.
    exact : bool
        No bulk replay.
    progress : callable, optional
        ``progress(label, done, total)`` per bag.
    refine : int
        Then at most this many more evaluations of scipy.optimize.minimize_scalar
        (bounded, on log s) between the grid neighbours of the best grid scale (only
        when it is inside the grid); they join the table.
    dask : dict, optional
        ``{'workers': N, 'scheduler': ADDRESS}``: the grid's bag x scale evaluations as
        jobs on Dask (:mod:`observer_ros.evaluation.jobs`; ``vehicle`` must be a file); the
        refinement runs in this process.
    spill : True or path or None
        Each replay's rows in temporary files (True: in TMPDIR) or in memory (None);
        either way a scale's rows are dropped once it is scored (:func:`score_variants`).
    model : Identification, optional
        ``kalman``: score every scale on the identified model first (:func:`model_errors`)
        and replay only the model's best scale and its grid neighbours, then further
        neighbours until the best replayed scale has both replayed (or is at the grid's
        end); the others stay NaN. Without it (or with ``dask``) every scale is replayed.
    recordings : dict, optional
        ``{str(bag): Recording}``: bags already read (``identify``'s), not read again
        in this process.

    Returns
    -------
    result : SearchResult

    """
    from ..evaluation.cli import resolve_vehicle
    base = resolve_vehicle(vehicle)
    scales = sorted(float(s) for s in scales)
    if not scales or any(not (s > 0 and math.isfinite(s)) for s in scales):
        raise BagToolError(f'--grid: scales must be positive numbers; got {scales}')
    predicted = None
    parts = _identified_model(model) if model is not None and kind == 'kalman' and \
        dask is None else None
    if parts is not None:
        from .identify import FILE_FLOOR, filter_Q
        Qd = np.asarray(base.observer.Qd, float)
        # the file's Qd: the identified one, or the tuned file's (each variance the data
        # do not determine chosen in its +-2 sigma, or raised to half its standard
        # error); the model's noise is the identified one either way
        for filt in (np.asarray(model.result.Q, float), filter_Q(model.result, FILE_FLOOR),
                     getattr(model, 'tuned_Q', None)):
            if filt is None:
                continue
            if Qd.shape == filt.shape and np.any(filt) and np.allclose(Qd, filt):
                predicted = model_errors(*parts[:4], scales, filter_Qk=parts[4](filt))
                break
        if predicted is not None and not np.isfinite(predicted).any():
            predicted = None
    if predicted is not None:
        per_bag, truth = _model_first(bags, vehicle, base, scales, predicted, namespace,
                                      exact, progress, spill, recordings)
    else:
        per_bag, truth = _scores(bags, vehicle, base, kind, scales, namespace, exact,
                                 progress, dask, spill, recordings)
    with np.errstate(all='ignore'), warnings.catch_warnings():
        warnings.simplefilter('ignore', RuntimeWarning)     # a scale no bag replayed
        mean = np.nanmean(np.array(list(per_bag.values())), axis=0)
    i = int(np.nanargmin(mean)) if np.isfinite(mean).any() else -1
    if refine and 0 < i < len(scales) - 1:
        from scipy.optimize import minimize_scalar
        # the residual metric is relative to the scale nearest 1: score it alongside
        ref = min(scales, key=lambda s: abs(math.log(s)))
        extra = {}

        def cost(logs):
            s = float(math.exp(logs))
            got, _ = _scores(bags, vehicle, base, kind, [s, ref], namespace, exact,
                             spill=spill, recordings=recordings)
            extra[s] = {k: v[0] for k, v in got.items()}
            return float(np.nanmean(list(extra[s].values())))
        minimize_scalar(cost, bounds=(math.log(scales[i - 1]), math.log(scales[i + 1])),
                        method='bounded', options={'maxiter': int(refine), 'xatol': 0.01})
        for s, values in extra.items():
            if s in scales:
                continue
            k = int(np.searchsorted(scales, s))
            scales.insert(k, s)
            for key in per_bag:
                per_bag[key] = list(per_bag[key])
                per_bag[key].insert(k, values[key])
        with warnings.catch_warnings():
            warnings.simplefilter('ignore', RuntimeWarning)
            mean = np.nanmean(np.array(list(per_bag.values())), axis=0)
    best = scales[int(np.nanargmin(mean))] if np.isfinite(mean).any() else math.nan
    if predicted is not None and len(predicted) < len(scales):      # refined scales
        predicted = None
    return SearchResult(kind, metric_name(truth), scales, per_bag, [float(v) for v in mean],
                        best, {s: search_overrides(base, kind, s) for s in scales},
                        predicted)
