# observer_ros.tuning.pole_search: choose each observer pole from bags (scipy.optimize).
"""
Per-pole search: every observer pole its own parameter, chosen by scipy.optimize.

The common-scale search (:func:`~observer_ros.tuning.gain_search.gain_search` of the poles)
runs first; from the vehicle's poles times its best scale, Nelder-Mead
(``scipy.optimize.minimize``) moves each pole on its own: a real pole is one parameter,
a conjugate pair two (its real part and ``|imag|``, so the pair stays a pair). In the
s-plane (a discrete vehicle's z-plane poles through ``s = log(z) / dt``) a pole's real
part is ``-(margin + exp(a))``, so every pole stays stable with a margin of
:data:`MARGIN` times the slowest starting pole's ``|Re s|``; ``|imag| = exp(b)``. Each
evaluation replays every bag through the candidate observer and scores it with the gain
search's metric (:func:`~observer_ros.tuning.gain_search.score_variants`: RMS estimation
error against ``state/true``, else residuals and whiteness relative to the vehicle's own
poles), the mean over the bags; a candidate whose observer cannot be designed scores
inf. The best evaluation (the start included, so never worse than the common scale's
best) is the answer.

"""

from dataclasses import dataclass, field
import math
from typing import Dict, List

import numpy as np

from .gain_search import (bag_keys, DEFAULT_SCALES, gain_search, metric_name,
                          score_variants)
from ..bag.errors import BagToolError
from ..core.errors import ObserverError

__all__ = ['MARGIN', 'DEFAULT_EVALUATIONS', 'PoleSet', 'pole_set', 'PoleSearchResult',
           'pole_search']

#: Stability margin: no pole slower than this fraction of the slowest starting pole.
MARGIN = 0.05
#: Candidate observers scored by the optimizer (each a replay of every bag).
DEFAULT_EVALUATIONS = 40


def _floats(values):
    return '[' + ', '.join(repr(float(v)) for v in values) + ']'


@dataclass
class PoleSet:
    """A vehicle's observer poles as search parameters (see the module)."""

    discrete: bool
    dt: float
    margin: float                 # in the s-plane, > 0
    kinds: List[str]              # per group: 'real' or 'pair'
    start: np.ndarray             # the parameters of the poles given to pole_set

    def poles(self, theta):
        """Return the poles of parameters ``theta`` (z-plane for a discrete vehicle)."""
        out, i = [], 0
        for kind in self.kinds:
            re = -(self.margin + math.exp(theta[i]))
            if kind == 'real':
                out.append(complex(re, 0.0))
                i += 1
            else:
                im = math.exp(theta[i + 1])
                out += [complex(re, im), complex(re, -im)]
                i += 2
        s = np.array(out, dtype=complex)
        return np.exp(s * self.dt) if self.discrete else s

    def overrides(self, theta):
        """Return the ``KEY:=VALUE`` overrides of the poles of ``theta``."""
        p = self.poles(theta)
        return [f'observer.poles:={_floats(p.real)}', f'observer.poles_imag:={_floats(p.imag)}']


def pole_set(vehicle, scale=1.0):
    """
    Return the vehicle's observer poles times ``scale`` as a :class:`PoleSet`.

    Raises
    ------
    BagToolError
        The observer has no poles; (A, C) is not observable (an unobservable mode's
        pole cannot be moved); a complex pole without its conjugate (``observer.poles_imag``);
        a discrete pole on the non-positive real axis (no s-plane equivalent); a pole
        not stable.

    """
    from ..core.analysis import is_observable
    obs, plant = vehicle.observer, vehicle.plant
    if obs.poles is None:
        raise BagToolError(f'--search each-pole: the {obs.kind} observer of {vehicle.name} '
                           'has no poles (give observer.poles)')
    if not is_observable(plant.A, plant.C):
        raise BagToolError(f'--search each-pole: the model of {vehicle.name} is not '
                           'observable from its outputs: the poles of its unobservable '
                           'modes cannot be moved (use --search poles)')
    p = np.asarray(obs.poles, dtype=complex)
    dt = float(vehicle.sample_time) if plant.is_discrete else 1.0
    if plant.is_discrete:
        bad = [z for z in p if abs(z.imag) <= 1e-12 and z.real <= 0.0]
        if bad:
            raise BagToolError(f'observer.poles: the discrete pole {bad[0].real:g} is on the '
                               'non-positive real axis (no s-plane pole gives it): '
                               '--search each-pole cannot move it')
        p = np.log(p) / dt
    p = p * float(scale)
    if np.any(p.real >= 0.0):
        raise BagToolError(f'observer.poles: {p[p.real >= 0.0][0]:g} is not stable')
    tol = 1e-9 * max(1.0, float(np.max(np.abs(p))))
    upper = [z for z in p if z.imag > tol]
    lower = [z for z in p if z.imag < -tol]
    for z in upper:
        if not any(abs(w - z.conjugate()) <= tol for w in lower):
            raise BagToolError(f'observer.poles_imag: the pole {z:g} has no conjugate '
                               '(complex poles come in pairs)')
    if len(upper) != len(lower):
        raise BagToolError('observer.poles_imag: the complex poles are not in conjugate pairs')
    margin = MARGIN * float(np.min(-p.real))
    kinds, theta = [], []
    for z in sorted(p, key=lambda z: (z.real, z.imag)):
        if z.imag < -tol:
            continue
        a = math.log(max(-z.real - margin, 1e-12 * margin))
        if z.imag > tol:
            kinds.append('pair')
            theta += [a, math.log(z.imag)]
        else:
            kinds.append('real')
            theta.append(a)
    return PoleSet(bool(plant.is_discrete), dt, margin, kinds, np.array(theta))


@dataclass
class PoleSearchResult:
    """A per-pole search: the common-scale grid, then every optimizer evaluation."""

    kind: str
    metric: str
    grid: object                           # SearchResult of the common scale
    start_scale: float
    bags: List[str]
    poles: List[List[complex]]             # per evaluation
    per_bag: Dict[str, List[float]]        # per bag, per evaluation
    mean: List[float]
    best: int                              # the best evaluation's index
    best_poles: List[complex] = field(default_factory=list)

    @property
    def best_metric(self):
        """Return the best evaluation's metric (mean over the bags)."""
        return self.mean[self.best]

    def rows(self):
        """Return the table rows: evaluation, mean metric, one per bag, the poles."""
        return [[i, self.mean[i]] + [v[i] for v in self.per_bag.values()] +
                [' '.join(_pole_text(z) for z in p)] for i, p in enumerate(self.poles)]

    def to_dict(self):
        """Return JSON-ready data."""
        return {'kind': self.kind, 'metric': self.metric, 'grid': self.grid.to_dict(),
                'start_scale': self.start_scale,
                'poles': [[[z.real, z.imag] for z in p] for p in self.poles],
                'per_bag': self.per_bag, 'mean': self.mean, 'best': self.best,
                'best_metric': self.best_metric,
                'best_poles': [[z.real, z.imag] for z in self.best_poles]}


def _pole_text(z):
    return f'{z.real:.5g}' if z.imag == 0 else f'{z.real:.5g}{z.imag:+.5g}j'


def pole_search(bags, vehicle, scales=DEFAULT_SCALES, namespace=None, exact=False,
                progress=None, evaluations=DEFAULT_EVALUATIONS, refine=0, dask=None,
                spill=True):
    """
    Search each observer pole (see the module) on one or many bags.

    Parameters
    ----------
    bags : sequence of str or Path
        The bags.
    vehicle : str or Path or Vehicle
        The vehicle (file) whose observer poles are searched.
    scales, namespace, exact, progress, refine, dask, spill
        The common-scale search's (:func:`~observer_ros.tuning.gain_search.gain_search`;
        the optimizer's evaluations, one after the other, run in this process).
    evaluations : int
        Most candidate observers scored (>= 1; the first is the start).

    Returns
    -------
    result : PoleSearchResult

    """
    from scipy.optimize import minimize
    from ..evaluation.cli import resolve_vehicle
    base = resolve_vehicle(vehicle)
    pole_set(base)                                       # refuse before any replay
    if int(evaluations) < 1:
        raise BagToolError(f'--evaluations {evaluations}: must be at least 1')
    grid = gain_search(bags, vehicle, 'poles', scales, namespace, exact, progress, refine,
                       dask, spill)
    if not math.isfinite(grid.best):
        raise BagToolError('the common-scale search found no finite metric: no poles '
                           'to start from')
    space = pole_set(base, grid.best)
    # the residual metric is relative to the vehicle's own poles: scored alongside
    own = pole_set(base).overrides(pole_set(base).start)
    poles, per_bag, mean, seen = [], {k: [] for k in bag_keys(bags)}, [], {}
    truth = [True]

    def cost(theta):
        key = tuple(np.round(theta, 12))
        if key in seen:                   # Nelder-Mead scores its start again
            return seen[key]
        try:
            got, truth[0] = score_variants(bags, vehicle, [space.overrides(theta), own], 1,
                                           namespace, exact, spill=spill)
            values = {k: float(v[0]) for k, v in got.items()}
        except ObserverError:            # a candidate that cannot be designed
            values = {k: math.inf for k in per_bag}
        for k, v in values.items():
            per_bag[k].append(v)
        poles.append(list(space.poles(theta)))
        m = float(np.mean(list(values.values())))
        mean.append(m if math.isfinite(m) else math.inf)
        seen[key] = mean[-1]
        if progress:
            progress('searching each pole', len(mean), int(evaluations))
        return mean[-1]

    start = cost(space.start)
    fatol = 1e-6 * abs(start) if math.isfinite(start) else 0.0
    minimize(cost, space.start, method='Nelder-Mead',
             options={'maxfev': int(evaluations), 'xatol': 1e-3, 'fatol': fatol})
    best = int(np.argmin(mean))
    return PoleSearchResult('each-pole', metric_name(truth[0]), grid, float(grid.best),
                            [str(b) for b in bags], poles, per_bag, mean, best, poles[best])
