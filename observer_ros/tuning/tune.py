# observer_ros.tuning.tune: `observer-tune BAG... --vehicle V.yaml`: noise and gains from bags.
"""
Tune an observer from recorded data.

1. Noise covariances by autocovariance least squares (:mod:`observer_ros.tuning.identify`,
   :mod:`observer_ros.core.als`): the bags' outputs and commands at their stamps
   (:mod:`observer_ros.tuning.sampled`; outputs missing at some samples and jittered stamps
   included), the innovations of a stable reference predictor (the vehicle's own
   observer) run at the actual stamps, the transient dropped, autocovariances over
   ``--lags`` lags (chosen from the plant by default; pooled over the bags), Q on the
   noise input's columns (``observer.Bd``, ``--states``, ``--input-noise`` or every
   state) and R by weighted least squares, with a standard error for each entry;
   diagonal and non-negative, or ``--full`` (symmetric, projected to be positive
   semidefinite). Each later pass (``--passes``, 3 by default) repeats it with the
   Kalman predictor of the previous pass's covariances as the reference (Rajamani &
   Rawlings 2009 recommend a reference close to the optimal filter).
2. The whiteness of the innovations of the reference and of the Kalman filter designed
   from the identified covariances (:mod:`observer_ros.core.whiteness`, the test of the
   node and ``observer-eval``); a plot of the empirical autocovariances against the
   fitted ones, with +-2 sigma bands.
3. A gain search (:mod:`observer_ros.tuning.gain_search`) over a scale of the Kalman weights
   (``--search kalman``, the default) or of the vehicle's observer poles (``--search
   poles``, also without identification: ``--no-als``), or of each pole
   (``--search each-pole``, :mod:`observer_ros.tuning.pole_search`: the common scale, then
   scipy.optimize on every pole, conjugate pairs kept). Over many bags the metric is
   the mean of the per-bag metrics; the tables give each bag's.
4. A new vehicle file with the tuned observer (never overwriting), and the report beside
   the first bag (``<bag>_tune``): tune.txt, tune.json, search.csv, autocovariance.png,
   search.png (and pole_search.csv, pole_search.png of ``--search each-pole``).

"""

import argparse
from dataclasses import dataclass, field
import math
from pathlib import Path
import sys
import time
from typing import List
import warnings

import numpy as np

from .gain_search import DEFAULT_SCALES, gain_search, search_overrides
from .identify import Identification, identify, PASSES
from .pole_search import DEFAULT_EVALUATIONS, pole_search, pole_set
from .report import format_report, write_report
from .tuned_vehicle import OBSERVER_KEYS, write_tuned_vehicle
from ..bag.errors import BagToolError
from ..core.als import DEFAULT_LAGS
from ..core.errors import ObserverError, quiet_on_closed_pipe
from ..evaluation.cli import (default_out as tool_default_out, IN_MEMORY_HELP, Progress,
                              resolve_vehicle, stop_on_sigterm, tool_done, tool_error)
from ..evaluation.results import jsonable
from ..outputs.folders import check_output
from ..outputs.staging import StagedOutput

__all__ = ['Identification', 'identify', 'TuneResult', 'tune', 'format_report', 'main']


def _tuned_observer(ident):
    """Return the tuned observer's keys and the source of each."""
    r = ident.result
    n, k = ident.G.shape
    src = (f'observer-tune: autocovariance least squares on {", ".join(ident.bags)} '
           f'({sum(ident.samples.values())} samples, median dt {ident.dt:.6g} s, {r.lags} lags, '
           f'{len(ident.passes)} passes, reference {ident.reference}; '
           f'condition number {r.condition:.3g})')
    outputs = ', '.join(ident.vehicle.plant.output_names)
    what = 'intensity' if not ident.vehicle.plant.is_discrete else 'per-sample covariance'
    std = {'Q': [], 'R': []}
    for kind, name, value, sd in r.entries():
        std[kind].append(f'{name} {value:.4g} +- {sd:.2g}')
    Q = ident.file_Q
    choice = ident.choice
    if choice is not None:
        chosen = [f'{ident.noise_names[i]} {Q[i, i]:.4g} (in {lo:.2g} .. {hi:.2g})'
                  for i, lo, hi in zip(choice.entries, choice.low, choice.high)]
        std['Q'].append('; not determined by these data (+-2 sigma reaching zero), so given '
                        'the value in their +-2 sigma whose filter loses least at worst '
                        '(predicted RMS error at most '
                        f'{choice.worst:.3f} times the filter that knew the true value): '
                        f'{", ".join(chosen)}')
    raised = [f'{name} {Q[i, i]:.4g}' for i, name in enumerate(ident.noise_names)
              if Q[i, i] != r.Q[i, i] and (choice is None or i not in choice.entries)]
    if raised:
        std['Q'].append('; not told from zero by these data, so given half their standard '
                        'error (a filter given zero stops following that noise): '
                        f'{", ".join(raised)}')
    obs = {'observer.type': 'kalman', 'observer.Qd': list(np.ravel(Q)),
           'observer.Rd': list(np.ravel(r.R)), 'observer.Bd': list(np.ravel(ident.G))}
    sources = {
        'observer.type': 'observer-tune: Kalman filter from identified noise covariances',
        'observer.Qd': f"{what} of the process noise on Bd's columns "
                       f'({", ".join(ident.noise_names)}); {src}\n'
                       f'standard errors (1 sigma): {", ".join(std["Q"])}',
        'observer.Rd': f'measurement noise covariance of {outputs}; {src}\n'
                       f'standard errors (1 sigma): {", ".join(std["R"])}',
        'observer.Bd': f'process noise input ({n}x{k}): '
                       f'{", ".join(ident.noise_names)} (observer-tune)',
    }
    return obs, sources


@dataclass
class TuneResult:
    """Everything :func:`tune` did."""

    identification: object          # Identification, or None with --no-als
    search: object                  # SearchResult, or None
    vehicle_file: Path
    files: List[Path] = field(default_factory=list)
    seconds: float = 0.0

    def to_dict(self):
        """Return JSON-ready data."""
        return jsonable({
            'identification': None if self.identification is None
            else self.identification.to_dict(),
            'search': None if self.search is None else self.search.to_dict(),
            'vehicle_file': str(self.vehicle_file), 'seconds': self.seconds})


def default_out(bag):
    """Return the default report folder: ``<bag>_tune`` next to the bag directory."""
    return tool_default_out(bag, '_tune')


def tune(bags, vehicle_path, out, output=None, namespace=None, lags=DEFAULT_LAGS,
         full=False, states=None, burn=None, passes=PASSES, als=True, search='auto',
         scales=DEFAULT_SCALES, use_search=False, force=False, plots=True, progress=None,
         input_noise=False, refine=0, evaluations=DEFAULT_EVALUATIONS, dask=None,
         spill=True):
    """
    Identify, search and write the tuned vehicle file and the report (see the module).

    Parameters
    ----------
    bags : sequence of str or Path
        The bags.
    vehicle_path : str or Path
        The vehicle file (never modified).
    out : str or Path
        The report folder (new, or an earlier observer-tune report with ``force``).
    output : str or Path, optional
        The tuned vehicle file (default ``<out>/<vehicle>_tuned.yaml``, part of the output:
        replaced with ``force`` while unchanged); elsewhere, never overwritten.
    namespace, lags, full, states, burn, passes
        See :func:`identify`.
    als : bool
        Identify the noise covariances (else only the pole search runs).
    search : {'auto', 'kalman', 'poles', 'each-pole', 'none'}
        The gain search (``auto``: kalman after identification, else poles).
    scales : sequence of float
        The search grid.
    use_search : bool
        Write the search's best scale into the tuned file (default: the identified
        covariances as they are; with ``search='poles'`` and no identification the
        best poles are written anyway).
    force : bool
        Replace an earlier report folder.
    plots : bool
        Write the PNGs.
    progress : callable, optional
        ``progress(label, done, total)``.
    input_noise : bool
        See :func:`identify`.
    refine : int
        Evaluations of scipy.optimize.minimize_scalar after the grid (0: none).
    evaluations : int
        ``each-pole``: most observers scored by scipy.optimize.minimize.
    dask : dict, optional
        ``{'workers': N, 'scheduler': ADDRESS}``: the search grid's bag x scale
        evaluations as jobs on Dask (:mod:`observer_ros.evaluation.jobs`), same numbers.
    spill : True or path or None
        The search's replays' rows in temporary files (default) or in memory (None); each
        variant's rows are dropped once it is scored.

    Returns
    -------
    result : TuneResult

    """
    start = time.perf_counter()
    bags = [str(b) for b in bags]
    vehicle = resolve_vehicle(vehicle_path)
    out = Path(out)
    if search == 'auto':
        search = 'kalman' if als else 'poles'
    if als and search in ('poles', 'each-pole') and use_search:
        raise BagToolError(f'--use-search --search {search}: the tuned file is a Kalman '
                           'filter; add --no-als to write the best poles')
    if not als and search in ('kalman', 'none'):
        raise BagToolError(f'--no-als --search {search}: nothing to tune (use --search poles '
                           'or each-pole)')
    output = Path(output) if output else out / f'{Path(vehicle_path).stem}_tuned.yaml'
    owned = check_output(out, force, 'observer-tune')  # before the work, touching nothing
    # in the folder, the tuned file is the tool's (replaced with --force while unchanged)
    inside = output.parent == out
    if (output.exists() or output.is_symlink()) and not (inside and output.name in owned):
        raise BagToolError(f'{output} exists and was not written by this output of '
                           'observer-tune; never overwritten (give another --output)')
    if search == 'poles':
        search_overrides(vehicle, 'poles', 1.0)           # refuse early
    if search == 'each-pole':
        pole_set(vehicle)
    # a gain search in this process replays the bags identification read (not read again)
    shared = {} if search in ('kalman', 'poles') and dask is None else None
    ident = identify(bags, vehicle, namespace, lags, full, states, burn, passes,
                     input_noise, recordings=shared) \
        if als else None
    with StagedOutput(out, force, 'observer-tune') as staged:
        # written aside and put in place whole at the end (outputs/staging.py): an interrupted
        # tune leaves the earlier output, and a rerun with --force finds it unchanged
        stage = staged.path
        files = []
        tmp = None
        if ident is not None:
            observer, sources = _tuned_observer(ident)
            header = [f'{vehicle.name} with the observer tuned by observer-tune from '
                      f'{", ".join(bags)}', f'original: {vehicle_path}']
            if search == 'kalman':
                # the search scales the identified Kalman filter: a scratch file for it
                tmp = stage / '.identified.yaml'
                if tmp.exists():
                    tmp.unlink()
                write_tuned_vehicle(vehicle_path, tmp, observer, sources, header)
        sr = None
        if search == 'each-pole':
            sr = pole_search(bags, vehicle_path, scales, namespace, progress=progress,
                             evaluations=evaluations, refine=refine, dask=dask, spill=spill)
        elif search != 'none':
            # kalman: scored on the identified model first, the scales around its best
            # replayed
            sr = gain_search(bags, tmp if search == 'kalman' else vehicle_path, search, scales,
                             namespace, progress=progress, refine=refine, dask=dask,
                             spill=spill, model=ident if search == 'kalman' else None,
                             recordings=shared)
            shared = None
        replace = OBSERVER_KEYS
        if ident is None:           # only the poles change: the rest of the design stays
            replace = ('observer.poles', 'observer.poles_imag')
            observer = {}
            header = [f'{vehicle.name} with observer poles chosen by observer-tune from '
                      f'{", ".join(bags)}', f'original: {vehicle_path}']
            sources = {}
        if ident is None and not math.isfinite(_best_metric(sr)):
            raise BagToolError('the gain search found no finite metric: no poles to write')
        if search == 'each-pole' and ident is None:
            _write_poles(observer, sources, sr.best_poles, _pole_note(sr, bags))
        elif sr is not None and (use_search or ident is None) and math.isfinite(sr.best):
            best = resolve_vehicle(tmp if search == 'kalman' else vehicle_path,
                                   sr.overrides[sr.best])
            grid = ', '.join(f'{x:.4g}' for x in sr.scales)
            note = (f'observer-tune gain search ({search} scale {sr.best:g} of [{grid}], '
                    f'metric {sr.metric}, on {", ".join(bags)})')
            if search == 'kalman':
                observer['observer.Qd'] = list(np.ravel(best.observer.Qd))
                sources['observer.Qd'] += f'; times {sr.best:g} by the {note}'
            else:
                _write_poles(observer, sources, best.observer.poles, note)
        written = write_tuned_vehicle(vehicle_path, stage / output.name if inside else output,
                                      observer, sources, header, replace)
        if tmp is not None:
            tmp.unlink()
        result = TuneResult(ident, sr, output)
        files += write_report(result, stage, plots)
        files = staged.commit(files + ([written] if inside else []))
    result.files = files if inside else files + [output]
    result.seconds = time.perf_counter() - start
    return result


def _best_metric(sr):
    """Return the best mean metric of a search."""
    return sr.best_metric if hasattr(sr, 'best_metric') else \
        min(sr.mean, key=lambda m: m if math.isfinite(m) else math.inf)


def _write_poles(observer, sources, poles, note):
    p = np.asarray(poles, dtype=complex)
    observer['observer.poles'] = [float(x) for x in p.real]
    observer['observer.poles_imag'] = [float(x) for x in p.imag]
    sources['observer.poles'] = note
    sources['observer.poles_imag'] = note


def _pole_note(sr, bags):
    return (f'observer-tune per-pole search (scipy.optimize Nelder-Mead from the poles '
            f'times {sr.start_scale:g}, the best common scale; evaluation {sr.best} of '
            f'{len(sr.mean)}, metric {sr.metric} {sr.best_metric:.6g} against '
            f'{_best_metric(sr.grid):.6g} at the best common scale; mean over '
            f'{", ".join(bags)})')


_EPILOG = """\
what it does:
  1. identifies the process noise (on observer.Bd's columns, --states, --input-noise, or
     every state) and the measurement noise covariances from the bags by
     autocovariance least squares (Odelson, Rajamani & Rawlings 2006; weighted as
     Rajamani & Rawlings 2009), with the vehicle's own observer as the reference, then
     twice more with the Kalman filter of the previous estimate (--passes); messages
     lost and jittered stamps are taken as they are (the filter and its model at the
     actual stamps); each entry comes with its standard error, and a warning names the
     entries the data do not determine, with the remedies;
  2. the whiteness of the innovations before (reference) and after (Kalman filter of
     the identified covariances), by the test of the node and observer-eval;
  3. a gain search: the identified Kalman filter's Qd times each --grid scale (--search
     kalman) or the vehicle's observer poles times each scale (--search poles), or
     each pole (--search each-pole: the scale grid, then scipy.optimize Nelder-Mead on
     every real pole and every conjugate pair's real part and |imag|, kept stable, at
     most --evaluations observers); metric: RMS estimation error against state/true
     when the bags have it, else residual RMS and whiteness; over many bags, the mean
     of the per-bag metrics (each bag's in the tables);
  4. writes a NEW vehicle file with observer.type kalman, Qd, Rd, Bd (each number's
     source as a comment) and the report.

output (folder --out; default <first bag>_tune next to it; never overwritten without
--force): tune.txt (also on stdout), tune.json, search.csv, autocovariance.png,
search.png (and pole_search.csv, pole_search.png of --search each-pole), and the tuned
vehicle file (default <out>/<vehicle>_tuned.yaml, replaced by --force while unchanged;
--output elsewhere, never overwritten). The folder is written aside and put in place
whole: an interrupted tune leaves the earlier one.
Compare it with the original:
  observer-eval BAG --vehicle V.yaml --compare <out>/V_tuned.yaml

exit status: 0 done; 2 the bags, the vehicle file or the arguments cannot be used, or
the noise is not identifiable (one line 'error: ...' on stderr).
"""


def _parser():
    parser = argparse.ArgumentParser(
        prog='observer-tune',
        description='Choose an observer from recorded data: noise covariances by '
                    'autocovariance least squares, a gain search, and a new vehicle file.',
        epilog=_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('bags', nargs='+', help='bag directories or .mcap/.db3 files')
    parser.add_argument('--vehicle', required=True, help='vehicle file (config/<name>.yaml)')
    parser.add_argument('--out', help='report folder (default: <first bag>_tune)')
    parser.add_argument('--output', help='the tuned vehicle file (default: '
                        '<out>/<vehicle>_tuned.yaml; elsewhere never overwritten)')
    parser.add_argument('--namespace', help="the vehicle's namespace in the bags")
    parser.add_argument('--lags', type=int, default=DEFAULT_LAGS,
                        help='autocovariance lags (default: chosen from the plant, enough '
                        'for the slowest mode the noise excites to decay)')
    parser.add_argument('--full', action='store_true',
                        help='full symmetric Qd and Rd (default diagonal, non-negative)')
    parser.add_argument('--states', help='process noise on these states, comma-separated '
                        '(default observer.Bd, else every state)')
    parser.add_argument('--input-noise', action='store_true',
                        help="process noise on the inputs (Bd = the model's B: a force "
                        'or torque disturbance)')
    parser.add_argument('--burn', type=int, help='samples dropped at the start of each bag '
                        "(default: the reference observer's transient)")
    parser.add_argument('--passes', type=int, default=PASSES,
                        help=f'identification passes (default {PASSES})')
    parser.add_argument('--no-als', action='store_true',
                        help='no noise identification (only --search poles)')
    parser.add_argument('--search', choices=['auto', 'kalman', 'poles', 'each-pole', 'none'],
                        default='auto', help='gain search (default: kalman after the '
                        'identification, poles without it; each-pole: every pole on its '
                        'own, after the poles grid)')
    parser.add_argument('--evaluations', type=int, default=DEFAULT_EVALUATIONS, metavar='N',
                        help='--search each-pole: most observers scored by '
                        f'scipy.optimize (default {DEFAULT_EVALUATIONS})')
    parser.add_argument('--grid', help='search scales, comma-separated (default '
                        f'{",".join(f"{s:g}" for s in DEFAULT_SCALES)})')
    parser.add_argument('--refine', type=int, default=0, metavar='N',
                        help='then up to N evaluations of scipy.optimize.minimize_scalar '
                        'around the best grid scale (default 0: the grid only)')
    where = parser.add_mutually_exclusive_group()
    where.add_argument('--workers', type=int, metavar='N',
                       help="the search grid's bag x scale evaluations as jobs on a local "
                       'Dask cluster of N processes (default: in this process)')
    where.add_argument('--scheduler', metavar='ADDRESS',
                       help='... on an existing Dask cluster (its workers need observer_ros '
                       'and the same paths to the bags and the vehicle file)')
    parser.add_argument('--in-memory', action='store_true', help=IN_MEMORY_HELP)
    parser.add_argument('--use-search', action='store_true',
                        help="write the search's best scale into the tuned file")
    parser.add_argument('--force', action='store_true',
                        help='replace an existing observer-tune report folder')
    parser.add_argument('--no-plots', action='store_true', help='do not write PNG plots')
    parser.add_argument('--progress', action='store_true',
                        help='show progress even when stderr is not a terminal')
    return parser


def _check_args(args):
    if args.lags is not None and args.lags < 1:
        raise BagToolError(f'--lags {args.lags}: must be at least 1')
    if args.workers is not None and args.workers < 1:
        raise BagToolError(f'--workers {args.workers}: must be at least 1')
    if args.evaluations < 1:
        raise BagToolError(f'--evaluations {args.evaluations}: must be at least 1')
    if args.refine < 0:
        raise BagToolError(f'--refine {args.refine}: must be >= 0')
    if args.passes < 1:
        raise BagToolError(f'--passes {args.passes}: must be at least 1')
    if args.burn is not None and args.burn < 0:
        raise BagToolError(f'--burn {args.burn}: must be >= 0')
    scales = DEFAULT_SCALES
    if args.grid:
        try:
            scales = [float(s) for s in args.grid.split(',') if s.strip()]
        except ValueError:
            raise BagToolError(f'--grid {args.grid!r}: expected numbers separated by '
                               'commas') from None
    for bag in args.bags:
        if not Path(bag).exists():
            raise BagToolError(f'{bag}: no such file or directory')
    states = [s.strip() for s in args.states.split(',') if s.strip()] if args.states \
        else None
    return scales, states


def _dask(args):
    if args.workers is None and args.scheduler is None:
        return None
    return {'workers': args.workers, 'scheduler': args.scheduler}


@quiet_on_closed_pipe
def main(argv=None):
    """Entry point of ``observer-tune``; returns the exit status."""
    args = _parser().parse_args(argv)
    stop_on_sigterm()
    progress = Progress(args.progress or sys.stderr.isatty())
    try:
        scales, states = _check_args(args)
        out = Path(args.out) if args.out else default_out(args.bags[0])
        check_output(out, args.force, 'observer-tune')
        with warnings.catch_warnings():
            warnings.simplefilter('ignore')
            result = tune(args.bags, args.vehicle, out, args.output, args.namespace,
                          args.lags, args.full, states, args.burn, args.passes,
                          not args.no_als, args.search, scales, args.use_search,
                          args.force, not args.no_plots, progress,
                          args.input_noise, args.refine, args.evaluations,
                          _dask(args), None if args.in_memory else True)
        progress.finish()
    except (ObserverError, OSError, KeyboardInterrupt) as err:
        return tool_error(progress, err)
    found = result.identification
    return tool_done(format_report(result), found.warnings if found is not None else (), out,
                     result.files, result.seconds)


if __name__ == '__main__':
    raise SystemExit(main())
