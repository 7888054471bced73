# observer_ros.bag.batch: observer-eval-batch, many bags x many variants as jobs (Dask).
"""
``observer-eval-batch``: evaluate many bags times many observer variants.

Each bag x variant is one job of :mod:`observer_ros.bag.jobs`, run on a local Dask
cluster (``--workers N``), on an existing one (``--scheduler ADDRESS`` or
``$DASK_SCHEDULER_ADDRESS``) or in this process (``--serial``). The output folder holds
one merged table (``results.csv``: one row per bag and variant), the summary across bags
(``summary.csv``), both with every number in ``results.json``, the printed table in
``results.txt`` and a plot of each bag's error (or residual) RMS per variant
(``error_rms.png``).

"""

import argparse
import csv
import json
import math
from pathlib import Path
import sys
import time
import warnings

from .errors import BagToolError
from .evaluate import _Progress, IN_MEMORY_HELP, parse_options
from .jobs import job_dict, make_jobs, run_jobs, SCHEDULER_ENV, summarize
from .report import text_table
from .results import jsonable
from ..core.errors import ObserverError

__all__ = ['find_bags', 'write_batch', 'format_batch', 'main']

_STORAGE = ('.mcap', '.db3')


def _is_bag(path):
    path = Path(path)
    if path.is_file():
        return path.suffix in _STORAGE
    return path.is_dir() and ((path / 'metadata.yaml').exists() or
                              any(p.suffix in _STORAGE for p in path.iterdir()))


def find_bags(paths):
    """
    Return the bags given: bag directories or files, or folders whose subfolders are bags.

    Raises
    ------
    BagToolError
        A path is missing, or a folder holds no bag.

    """
    out = []
    for p in map(Path, paths):
        if not p.exists():
            raise BagToolError(f'{p}: no such file or directory')
        if _is_bag(p):
            out.append(p)
            continue
        found = sorted(x for x in p.iterdir() if _is_bag(x)) if p.is_dir() else []
        if not found:
            raise BagToolError(f'{p}: neither a bag nor a folder of bags')
        out.extend(found)
    return out


def _fmt(v):
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return '-'
    return f'{v:.4g}' if isinstance(v, float) else str(v)


def _value(v):
    """Return a metric as a float (None, from JSON-ready data, as NaN)."""
    return math.nan if v is None else float(v)


def _residual_rms(row):
    return {k: _value(m.get('residual_rms')) for k, m in row['outputs'].items()}


def _metric(row):
    """Return the figure of merit of a row: error RMS against the truth, else residual RMS."""
    rms = _value(row['summary'].get('error_rms'))
    if math.isfinite(rms):
        return rms
    values = [v for v in _residual_rms(row).values() if math.isfinite(v)]
    return max(values) if values else math.nan


def _settling(row):
    """Return a row's settling time as text: ``never`` where the error never settles."""
    value = row['summary'].get('settling_time')
    if value is None and _value(row['summary'].get('error_rms')) > 0.0:
        return 'never'              # scored against the truth, settling inf (JSON None)
    return _fmt(value)


def format_batch(rows, summary):
    """Return the merged table and the summary as text."""
    body = [[r['bag'], r['variant'], r['observer_type'] or '-', r['estimates'],
             _fmt(r['summary'].get('error_rms')), _settling(r),
             ' '.join(f'{k}={_fmt(v)}' for k, v in _residual_rms(r).items()) or '-',
             r['error'] or ''] for r in rows]
    lines = [text_table(['bag', 'variant', 'observer', 'estimates', 'error_rms',
                         'settle[s]', 'residual_rms', 'error'], body), '',
             'across bags (error_rms: mean / median / max)']
    body = [[s['variant'], s['bags'], s['failed'], _fmt(s['error_rms']['mean']),
             _fmt(s['error_rms']['median']), _fmt(s['error_rms']['max'])] for s in summary]
    lines += ['', text_table(['variant', 'bags', 'failed', 'mean', 'median', 'max'], body)]
    return '\n'.join(lines)


def _plot(rows, path):
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    bags = list(dict.fromkeys(r['bag'] for r in rows))
    variants = list(dict.fromkeys(r['variant'] for r in rows))
    truth = any(math.isfinite(_value(r['summary'].get('error_rms'))) for r in rows)
    fig, ax = plt.subplots(figsize=(max(6.0, 1.2 * len(bags) + 3), 4.5))
    width = 0.8 / max(1, len(variants))
    for j, name in enumerate(variants):
        values = {r['bag']: _metric(r) for r in rows if r['variant'] == name}
        ax.bar([i + j * width for i in range(len(bags))],
               [values.get(b, math.nan) for b in bags], width, label=name)
    ax.set_xticks([i + 0.4 - width / 2 for i in range(len(bags))])
    ax.set_xticklabels([Path(b).name for b in bags], rotation=20, ha='right')
    ax.set_ylabel('error RMS against state/true' if truth else 'largest residual RMS')
    ax.set_title('per bag and variant')
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


_CSV = ['bag', 'variant', 'observer_type', 'estimates', 'overrides', 'seconds', 'error']
_SUMMARY = ['matched', 'error_rms', 'settling_time']


def write_batch(out, jobs, rows, summary, plots=True):
    """Write the merged table, the summary, the JSON and the plot to a new folder."""
    out = Path(out)
    out.mkdir(parents=True)
    states = list(dict.fromkeys(k for r in rows for k in r['states']))
    outputs = list(dict.fromkeys(k for r in rows for k in r['outputs']))
    with open(out / 'results.csv', 'w', newline='') as f:
        w = csv.writer(f)
        w.writerow(_CSV + _SUMMARY + [f'rmse.{s}' for s in states] +
                   [f'residual_rms.{o}' for o in outputs])
        for r in rows:
            w.writerow([' '.join(r[k]) if k == 'overrides' else r[k] for k in _CSV] +
                       [r['summary'].get(k) for k in _SUMMARY] +
                       [r['states'].get(s, {}).get('rmse') for s in states] +
                       [r['outputs'].get(o, {}).get('residual_rms') for o in outputs])
    with open(out / 'summary.csv', 'w', newline='') as f:
        w = csv.writer(f)
        w.writerow(['variant', 'bags', 'failed', 'metric', 'mean', 'median', 'min', 'max'])
        for s in summary:
            metrics = [('error_rms', s['error_rms']), ('settling_time', s['settling_time'])]
            metrics += [(f'rmse.{k}', v) for k, v in s['rmse'].items()]
            metrics += [(f'residual_rms.{k}', v) for k, v in s['residual_rms'].items()]
            for name, st in metrics:
                w.writerow([s['variant'], s['bags'], s['failed'], name, st['mean'],
                            st['median'], st['min'], st['max']])
    (out / 'results.json').write_text(json.dumps(jsonable(
        {'jobs': [job_dict(j) for j in jobs], 'rows': rows, 'summary': summary}), indent=1))
    (out / 'results.txt').write_text(format_batch(rows, summary) + '\n')
    files = ['results.csv', 'summary.csv', 'results.json', 'results.txt']
    if plots and rows:
        _plot(rows, out / 'error_rms.png')
        files.append('error_rms.png')
    return [out / f for f in files]


def _parser():
    parser = argparse.ArgumentParser(
        prog='observer-eval-batch',
        description="Evaluate many bags times many observer variants (observer-eval's "
                    'metrics), each bag x variant an independent job on Dask.',
        epilog='Variants as observer-eval --variant. The jobs run on a local Dask cluster '
               f'unless --scheduler (or ${SCHEDULER_ENV}) names an existing one, whose '
               'workers need observer_ros installed (not ROS) and the same paths to the '
               'bags and the vehicle file. exit status: 0 every job ran; 1 some jobs '
               'failed (their row says why); 2 bad arguments (one line "error: ...").')
    parser.add_argument('bags', nargs='+', help='bags, or folders holding bags')
    parser.add_argument('--vehicle', required=True, help='vehicle file of every bag')
    parser.add_argument('--variant', action='append', default=[],
                        metavar='NAME:KEY:=VALUE[,...]', help='an observer configuration')
    parser.add_argument('--out', required=True, help='output folder (must not exist)')
    parser.add_argument('--namespace', help="the vehicle's namespace in the bags")
    parser.add_argument('--tolerance', help='settling band, as observer-eval')
    parser.add_argument('--exact', action='store_true', help='no bulk replay')
    where = parser.add_mutually_exclusive_group()
    where.add_argument('--workers', type=int, metavar='N',
                       help='processes of the local Dask cluster (default: CPU count)')
    where.add_argument('--scheduler', metavar='ADDRESS',
                       help=f'an existing Dask scheduler (default ${SCHEDULER_ENV})')
    where.add_argument('--serial', action='store_true', help='run the jobs in this process')
    parser.add_argument('--in-memory', action='store_true', help=IN_MEMORY_HELP)
    parser.add_argument('--no-plots', action='store_true', help='do not write the plot')
    parser.add_argument('--progress', action='store_true',
                        help='show progress even when stderr is not a terminal')
    return parser


def main(argv=None):
    """Entry point of ``observer-eval-batch``; returns the exit status."""
    args = _parser().parse_args(argv)
    started = time.perf_counter()
    progress = _Progress(args.progress or sys.stderr.isatty(), sys.stderr)
    try:
        if args.workers is not None and args.workers < 1:
            raise BagToolError(f'--workers must be at least 1, not {args.workers}')
        variants = parse_options(args.variant, args.tolerance)
        if not Path(args.vehicle).is_file():
            raise BagToolError(f'--vehicle {args.vehicle}: no such file')
        out = Path(args.out)
        if out.exists():
            raise BagToolError(f'{out} exists; refusing to overwrite it')
        jobs = make_jobs(find_bags(args.bags), args.vehicle, variants, args.namespace,
                         args.tolerance, args.exact)
        with warnings.catch_warnings():
            warnings.simplefilter('ignore')
            rows = run_jobs(jobs, 'serial' if args.serial else 'dask', args.workers,
                            args.scheduler, lambda d, t: progress('jobs done', d, t),
                            spill=None if args.in_memory else True)
        progress.finish()
        summary = summarize(rows)
        files = write_batch(out, jobs, rows, summary, plots=not args.no_plots)
    except (ObserverError, OSError) as err:
        progress.finish()
        text = str(err).splitlines()[0] if str(err) else type(err).__name__
        print(f'error: {text}', file=sys.stderr)
        return 2
    print(format_batch(rows, summary))
    failed = [r for r in rows if r['error']]
    for r in failed:
        print(f'warning: {r["bag"]} {r["variant"]}: {r["error"]}', file=sys.stderr)
    print(f'\n{len(jobs)} jobs written to {out}/ ({", ".join(f.name for f in files)}) in '
          f'{time.perf_counter() - started:.1f} s')
    return 1 if failed else 0


if __name__ == '__main__':
    raise SystemExit(main())
