# observer_ros.bag.tune: `observer-tune BAG... --vehicle V.yaml`: noise and gains from bags.
"""
Tune an observer from recorded data.

1. Noise covariances by autocovariance least squares (:mod:`observer_ros.bag.identify`,
   :mod:`observer_ros.core.als`): the bags' outputs and commands on their sample grid
   (:mod:`observer_ros.bag.sampled`), the innovations of a stable reference predictor
   (the vehicle's own observer), the transient dropped, autocovariances over ``--lags``
   lags (pooled over the bags), Q on the noise input's columns (``observer.Bd``,
   ``--states``, ``--input-noise`` or every state) and R; diagonal and
   non-negative, or ``--full`` (symmetric, projected to be positive semidefinite). A
   second pass repeats it with the Kalman predictor of the first pass's covariances as
   the reference (``--passes``; Rajamani & Rawlings 2009 recommend a reference close to
   the optimal filter).
2. Mehra's whiteness test of the innovations of the reference and of the Kalman filter
   designed from the identified covariances; a plot of the empirical autocovariances
   against the fitted ones, with +-2 sigma bands.
3. A gain search (:mod:`observer_ros.bag.gain_search`) over a scale of the Kalman weights
   (``--search kalman``, the default) or of the vehicle's observer poles (``--search
   poles``, also without identification: ``--no-als``).
4. A new vehicle file with the tuned observer (never overwriting), and the report beside
   the first bag (``<bag>_tune``): tune.txt, tune.json, search.csv, autocovariance.png,
   search.png.

"""

import argparse
from dataclasses import dataclass, field
import json
import math
from pathlib import Path
import sys
import time
from typing import List
import warnings

import numpy as np

from .errors import BagToolError
from .evaluate import _load_vehicle, _Progress, tool_error
from .gain_search import DEFAULT_SCALES, gain_search, search_overrides
from .identify import Identification, identify
from .metrics import WHITENESS_LAGS
from .outputs import check_output, prepare_output, seal_output
from .plots import plot_autocovariances, plot_search
from .report import csv_cell, fmt, text_table
from .results import jsonable
from .tuned_vehicle import OBSERVER_KEYS, write_tuned_vehicle
from ..core.als import DEFAULT_LAGS
from ..core.errors import ObserverError

__all__ = ['Identification', 'identify', 'TuneResult', 'tune', 'format_report', 'main']


def _tuned_observer(ident):
    """Return the tuned observer's keys and the source of each."""
    r = ident.result
    n, k = ident.G.shape
    src = (f'observer-tune: autocovariance least squares on {", ".join(ident.bags)} '
           f'({sum(ident.samples.values())} samples, dt {ident.dt:.6g} s, {r.lags} lags, '
           f'{len(ident.passes)} passes, reference {ident.reference}; '
           f'condition number {r.condition:.3g})')
    outputs = ', '.join(ident.vehicle.plant.output_names)
    what = 'intensity' if not ident.vehicle.plant.is_discrete else 'per-sample covariance'
    obs = {'observer.type': 'kalman', 'observer.Qd': list(np.ravel(r.Q)),
           'observer.Rd': list(np.ravel(r.R)), 'observer.Bd': list(np.ravel(ident.G))}
    sources = {
        'observer.type': 'observer-tune: Kalman filter from identified noise covariances',
        'observer.Qd': f"{what} of the process noise on Bd's columns "
                       f'({", ".join(ident.noise_names)}); {src}',
        'observer.Rd': f'measurement noise covariance of {outputs}; {src}',
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
    from .evaluate import _default_out
    out = _default_out(bag)
    return out.with_name(out.name[:-len('_eval')] + '_tune')


def tune(bags, vehicle_path, out, output=None, namespace=None, lags=DEFAULT_LAGS,
         full=False, states=None, burn=None, passes=2, als=True, search='auto',
         scales=DEFAULT_SCALES, use_search=False, force=False, plots=True, progress=None,
         input_noise=False, refine=0):
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
        The tuned vehicle file (default ``<out>/<vehicle>_tuned.yaml``); never
        overwritten.
    namespace, lags, full, states, burn, passes
        See :func:`identify`.
    als : bool
        Identify the noise covariances (else only the pole search runs).
    search : {'auto', 'kalman', 'poles', 'none'}
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

    Returns
    -------
    result : TuneResult

    """
    start = time.perf_counter()
    bags = [str(b) for b in bags]
    vehicle = _load_vehicle(vehicle_path)
    out = Path(out)
    if search == 'auto':
        search = 'kalman' if als else 'poles'
    if als and search == 'poles' and use_search:
        raise BagToolError('--use-search --search poles: the tuned file is a Kalman filter; '
                           'add --no-als to write the best poles')
    if not als and search in ('kalman', 'none'):
        raise BagToolError(f'--no-als --search {search}: nothing to tune (use --search poles)')
    output = Path(output) if output else out / f'{Path(vehicle_path).stem}_tuned.yaml'
    check_output(out, force, 'observer-tune')          # before the work, touching nothing
    if output.exists() or output.is_symlink():
        raise BagToolError(f'{output} exists; the tuned vehicle file is never overwritten '
                           '(give another --output)')
    if search == 'poles':
        search_overrides(vehicle, 'poles', 1.0)           # refuse early
    ident = identify(bags, vehicle, namespace, lags, full, states, burn, passes,
                     input_noise) \
        if als else None
    out = prepare_output(out, force, 'observer-tune')
    files = []
    tmp = None
    if ident is not None:
        observer, sources = _tuned_observer(ident)
        header = [f'{vehicle.name} with the observer tuned by observer-tune from '
                  f'{", ".join(bags)}', f'original: {vehicle_path}']
        if search == 'kalman':
            # the search scales the identified Kalman filter: a scratch file for it
            tmp = out / '.identified.yaml'
            if tmp.exists():
                tmp.unlink()
            write_tuned_vehicle(vehicle_path, tmp, observer, sources, header)
    sr = None
    if search != 'none':
        sr = gain_search(bags, tmp if search == 'kalman' else vehicle_path, search, scales,
                         namespace, progress=progress, refine=refine)
    replace = OBSERVER_KEYS
    if ident is None:           # only the poles change: the rest of the design stays
        replace = ('observer.poles', 'observer.poles_imag')
        observer = {}
        header = [f'{vehicle.name} with observer poles chosen by observer-tune from '
                  f'{", ".join(bags)}', f'original: {vehicle_path}']
        sources = {}
    if ident is None and not math.isfinite(sr.best):
        raise BagToolError('the gain search found no finite metric: no poles to write')
    if sr is not None and (use_search or ident is None) and math.isfinite(sr.best):
        best = _load_vehicle(tmp if search == 'kalman' else vehicle_path,
                             sr.overrides[sr.best])
        grid = ', '.join(f'{x:.4g}' for x in sr.scales)
        note = (f'observer-tune gain search ({search} scale {sr.best:g} of [{grid}], '
                f'metric {sr.metric}, on {", ".join(bags)})')
        if search == 'kalman':
            observer['observer.Qd'] = list(np.ravel(best.observer.Qd))
            sources['observer.Qd'] += f'; times {sr.best:g} by the {note}'
        else:
            p = np.asarray(best.observer.poles, dtype=complex)
            observer['observer.poles'] = list(p.real)
            observer['observer.poles_imag'] = list(p.imag)
            sources['observer.poles'] = note
            sources['observer.poles_imag'] = note
    vehicle_file = write_tuned_vehicle(vehicle_path, output, observer, sources, header,
                                       replace)
    if tmp is not None:
        tmp.unlink()
    result = TuneResult(ident, sr, vehicle_file)
    files += _write_report(result, out, plots)
    seal_output(out, 'observer-tune', files)       # the tuned vehicle file is not ours
    result.files = files + [vehicle_file]
    result.seconds = time.perf_counter() - start
    return result


def format_report(result):
    """Return the readable report (what ``observer-tune`` prints)."""
    lines = []
    ident = result.identification
    if ident is not None:
        r = ident.result
        lines += [f'noise identification (autocovariance least squares) of '
                  f'{ident.vehicle.name} on {len(ident.bags)} bag(s): '
                  f'{sum(ident.samples.values())} samples at dt {ident.dt:.6g} s, first '
                  f'{ident.burn} of each dropped, {r.lags} lags, '
                  f'{"full" if r.full else "diagonal"} covariances',
                  f'reference: {ident.reference}; condition number {fmt(r.condition)} '
                  f'(rank {r.rank} of {r.unknowns})', '']
        rows = []
        for i, p in enumerate(ident.passes):
            for j, name in enumerate(ident.noise_names):
                rows.append([i + 1, f'Qd {name}', fmt(p.Q[j, j])])
            for j, name in enumerate(ident.vehicle.plant.output_names):
                rows.append([i + 1, f'Rd {name}', fmt(p.R[j, j])])
        lines += [text_table(['pass', 'entry', 'value'], rows), '']
        rows = []
        for label, w in (('reference', ident.whiteness_before),
                         ('tuned kalman', ident.whiteness_after)):
            for name, m in w.items():
                rows.append([label, name, m['samples'], fmt(m['residual_rms']),
                             fmt(m['ljung_box_p'], 3), fmt(m['acf_outside'], 3),
                             {True: 'yes', False: 'no'}.get(m['white'], '-')])
        lines += [f'Mehra whiteness test of the innovations (lags 1..{WHITENESS_LAGS}; '
                  'white if at most 5% of the lags are outside +-1.96/sqrt(N))', '',
                  text_table(['filter', 'output', 'N', 'rms', 'LB_p', 'acf_out', 'white'],
                             rows), '']
    sr = result.search
    if sr is not None:
        names = list(sr.per_bag)
        head = ['scale', 'mean'] + [f'bag{i + 1}' for i in range(len(names))]
        rows = [[fmt(c) for c in row] for row in sr.rows()]
        lines += [f'gain search: {sr.kind} scale; metric {sr.metric}; best {fmt(sr.best)}',
                  ''] + [f'  bag{i + 1}: {n}' for i, n in enumerate(names)] + \
            ['', text_table(head, rows), '']
    lines.append(f'tuned vehicle file: {result.vehicle_file}')
    return '\n'.join(lines)


def _write_report(result, out, plots):
    files = []
    (out / 'tune.txt').write_text(format_report(result) + '\n')
    files.append(out / 'tune.txt')
    with open(out / 'tune.json', 'w') as f:
        json.dump(result.to_dict(), f, indent=2)
        f.write('\n')
    files.append(out / 'tune.json')
    sr = result.search
    if sr is not None:
        with open(out / 'search.csv', 'w') as f:
            f.write(','.join(['scale', 'mean'] + list(sr.per_bag)) + '\n')
            for row in sr.rows():
                f.write(','.join(csv_cell(float(c)) for c in row) + '\n')
        files.append(out / 'search.csv')
    if plots and result.identification is not None:
        ident = result.identification
        fits = [(f'pass {i + 1}: ' + (ident.reference if i == 0 else
                                      'Kalman filter of the previous pass'),
                 p.empirical, p.fitted, p.sigma) for i, p in enumerate(ident.passes)]
        files.append(plot_autocovariances(
            out / 'autocovariance.png', ident.vehicle.plant.output_names, fits,
            f'{ident.vehicle.name}: innovation autocovariances, empirical and fitted'))
    if plots and sr is not None:
        metrics = dict(sr.per_bag) if len(sr.per_bag) > 1 else {}
        metrics['mean'] = sr.mean
        files.append(plot_search(out / 'search.png', f'{sr.kind} scale', sr.scales,
                                 metrics, sr.metric, sr.best))
    return files


_EPILOG = """\
what it does:
  1. identifies the process noise (on observer.Bd's columns, --states, --input-noise, or
     every state) and the measurement noise covariances from the bags by
     autocovariance least squares (Odelson, Rajamani & Rawlings 2006), with the
     vehicle's own observer as the reference, then once more with the Kalman filter of
     the first estimate;
  2. Mehra's whiteness test of the innovations before (reference) and after (Kalman
     filter of the identified covariances);
  3. a gain search: the identified Kalman filter's Qd times each --grid scale (--search
     kalman) or the vehicle's observer poles times each scale (--search poles); metric:
     RMS estimation error against state/true when the bags have it, else residual RMS
     and whiteness;
  4. writes a NEW vehicle file with observer.type kalman, Qd, Rd, Bd (each number's
     source as a comment) and the report.

output (folder --out; default <first bag>_tune next to it; never overwritten without
--force): tune.txt (also on stdout), tune.json, search.csv, autocovariance.png,
search.png, and the tuned vehicle file (default <out>/<vehicle>_tuned.yaml, --output;
never overwritten). Compare it with the original:
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
                        '<out>/<vehicle>_tuned.yaml; never overwritten)')
    parser.add_argument('--namespace', help="the vehicle's namespace in the bags")
    parser.add_argument('--lags', type=int, default=DEFAULT_LAGS,
                        help=f'autocovariance lags (default {DEFAULT_LAGS})')
    parser.add_argument('--full', action='store_true',
                        help='full symmetric Qd and Rd (default diagonal, non-negative)')
    parser.add_argument('--states', help='process noise on these states, comma-separated '
                        '(default observer.Bd, else every state)')
    parser.add_argument('--input-noise', action='store_true',
                        help="process noise on the inputs (Bd = the model's B: a force "
                        'or torque disturbance)')
    parser.add_argument('--burn', type=int, help='samples dropped at the start of each bag '
                        "(default: the reference observer's transient)")
    parser.add_argument('--passes', type=int, default=2,
                        help='identification passes (default 2)')
    parser.add_argument('--no-als', action='store_true',
                        help='no noise identification (only --search poles)')
    parser.add_argument('--search', choices=['auto', 'kalman', 'poles', 'none'],
                        default='auto', help='gain search (default: kalman after the '
                        'identification, poles without it)')
    parser.add_argument('--grid', help='search scales, comma-separated (default '
                        f'{",".join(f"{s:g}" for s in DEFAULT_SCALES)})')
    parser.add_argument('--refine', type=int, default=0, metavar='N',
                        help='then up to N evaluations of scipy.optimize.minimize_scalar '
                        'around the best grid scale (default 0: the grid only)')
    parser.add_argument('--use-search', action='store_true',
                        help="write the search's best scale into the tuned file")
    parser.add_argument('--force', action='store_true',
                        help='replace an existing observer-tune report folder')
    parser.add_argument('--no-plots', action='store_true', help='do not write PNG plots')
    parser.add_argument('--progress', action='store_true',
                        help='show progress even when stderr is not a terminal')
    return parser


def _check_args(args):
    if args.lags < 1:
        raise BagToolError(f'--lags {args.lags}: must be at least 1')
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


def main(argv=None):
    """Entry point of ``observer-tune``; returns the exit status."""
    args = _parser().parse_args(argv)
    progress = _Progress(args.progress or sys.stderr.isatty())
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
                          args.input_noise, args.refine)
        progress.finish()
    except (ObserverError, OSError, KeyboardInterrupt) as err:
        return tool_error(progress, err)
    print(format_report(result))
    if result.identification is not None:
        for text in result.identification.warnings:
            print(f'warning: {text}', file=sys.stderr)
    print(f'\nwritten to {out}/ ({", ".join(f.name for f in result.files)}) in '
          f'{result.seconds:.1f} s')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
