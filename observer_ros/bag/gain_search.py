# observer_ros.bag.gain_search: choose an observer's poles or Kalman weights from bags.
"""
Gain search: replay bags through a family of observers and score each.

The family is one parameter, a scale ``s`` of the vehicle's observer:

- ``poles``: the observer poles times s (continuous model; ``z**s`` for a discrete one):
  s > 1 is faster;
- ``kalman``: the Kalman process-noise covariance ``observer.Qd`` times s (only the
  ratio of Qd to Rd sets the gain): s > 1 trusts the measurements more.

Each bag is read once and replayed through every scale of a grid (:func:`evaluate_bag`
with one variant per scale); ``refine`` then narrows the best grid interval with
``scipy.optimize.minimize_scalar``. The metric of a bag is the RMS of the estimation
error norm against ``state/true`` when every bag has it (``error_rms``); otherwise, per
output, the residual RMS relative to that of the scale nearest 1, plus the fraction of
autocorrelation lags outside +-1.96/sqrt(N) (0.05 for white residuals), averaged over the
outputs. The search minimises the mean over the bags.

"""

from dataclasses import dataclass, field
import math
from typing import Dict, List

import numpy as np

from .errors import BagToolError
from .evaluate import evaluate_bag

__all__ = ['DEFAULT_SCALES', 'SearchResult', 'search_overrides', 'gain_search']

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

    def rows(self):
        """Return the table rows: scale, mean metric, then one per bag."""
        return [[s, self.mean[i]] + [v[i] for v in self.per_bag.values()]
                for i, s in enumerate(self.scales)]

    def to_dict(self):
        """Return JSON-ready data."""
        return {'kind': self.kind, 'metric': self.metric, 'scales': self.scales,
                'per_bag': self.per_bag, 'mean': self.mean, 'best': self.best,
                'overrides': {str(k): v for k, v in self.overrides.items()}}


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


def _bag_metric(result, names, scales, truth):
    if truth:
        return [result.variants[n].summary.get('error_rms', math.nan) for n in names]
    ref = names[int(np.argmin([abs(math.log(s)) for s in scales]))]
    out = []
    for n in names:
        terms = []
        for output, m in result.variants[n].outputs.items():
            base = result.variants[ref].outputs[output]['residual_rms']
            if m['samples'] and base and math.isfinite(base):
                terms.append(m['residual_rms'] / base + (m['acf_outside'] or 0.0))
        out.append(float(np.mean(terms)) if terms else math.nan)
    return out


def _scores(bags, vehicle, base, kind, scales, namespace, exact, progress=None):
    """Return ({bag: [metric per scale]}, truth) of one batch of scales."""
    names = tuple(f'scale_{i}' for i in range(len(scales)))
    variants = {n: search_overrides(base, kind, s) for n, s in zip(names, scales)}
    results = []
    for i, bag in enumerate(bags):
        if progress:
            progress('searching', i, len(bags))
        results.append(evaluate_bag(bag, vehicle, variants, namespace, exact=exact,
                                    include_live=False, include_design=False))
    if progress:
        progress('searching', len(bags), len(bags))
    truth = all(r.truth is not None for r in results)
    per_bag = {}
    for bag, r in zip(bags, results):
        key = str(bag)
        while key in per_bag:
            key += "'"
        per_bag[key] = _bag_metric(r, names, scales, truth)
    return per_bag, truth


def gain_search(bags, vehicle, kind, scales=DEFAULT_SCALES, namespace=None, exact=False,
                progress=None, refine=0):
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

    Returns
    -------
    result : SearchResult

    """
    from .evaluate import _load_vehicle
    base = _load_vehicle(vehicle)
    scales = sorted(float(s) for s in scales)
    if not scales or any(not (s > 0 and math.isfinite(s)) for s in scales):
        raise BagToolError(f'--grid: scales must be positive numbers; got {scales}')
    per_bag, truth = _scores(bags, vehicle, base, kind, scales, namespace, exact, progress)
    mean = np.nanmean(np.array(list(per_bag.values())), axis=0)
    i = int(np.nanargmin(mean)) if np.isfinite(mean).any() else -1
    if refine and 0 < i < len(scales) - 1:
        from scipy.optimize import minimize_scalar
        # the residual metric is relative to the scale nearest 1: score it alongside
        ref = min(scales, key=lambda s: abs(math.log(s)))
        extra = {}

        def cost(logs):
            s = float(math.exp(logs))
            got, _ = _scores(bags, vehicle, base, kind, [s, ref], namespace, exact)
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
        mean = np.nanmean(np.array(list(per_bag.values())), axis=0)
    best = scales[int(np.nanargmin(mean))] if np.isfinite(mean).any() else math.nan
    metric = 'error_rms (|x_hat - x_true| RMS)' if truth else \
        'residual RMS / that at scale ~1 + fraction of ACF lags outside'
    return SearchResult(kind, metric, scales, per_bag, [float(v) for v in mean], best,
                        {s: search_overrides(base, kind, s) for s in scales})
