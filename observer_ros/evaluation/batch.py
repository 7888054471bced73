# observer_ros.evaluation.batch: observer-eval-batch, many bags x many variants as jobs (Dask).
"""
``observer-eval-batch``: evaluate many bags times many observer variants.

Each bag x variant is one job of :mod:`observer_ros.evaluation.jobs`, run on a local Dask
cluster (``--workers N``), on an existing one (``--scheduler ADDRESS`` or
``$DASK_SCHEDULER_ADDRESS``) or in this process (``--serial``). The output folder holds
one merged table (``results.csv``: one row per bag and variant), the summary across bags
(``summary.csv``), both with every number in ``results.json``, the printed table in
``results.txt`` and a plot of each bag's error (or residual) RMS per variant
(``error_rms.png``).

Every job's row is written to ``jobs/`` in the output folder as soon as the job
finishes (``batch.json`` lists the jobs), so nothing finished is lost: a run that loses
every worker for ``--lost-timeout`` seconds, or is interrupted, ends with one ``error:``
line and the command that finishes it (``--resume``: the jobs already in ``jobs/`` are
skipped). A worker lost or joining is said as it happens. A local cluster listens on the
loopback interface only. At the end the measured parallel efficiency is printed (the
jobs' CPU time over the wall time, per worker), and a local cluster of more workers than
free cores is warned about before it starts.

"""

import argparse
import csv
import json
import math
import os
from pathlib import Path
import shlex
import sys
import time
import warnings

from .cli import IN_MEMORY_HELP, Progress, tool_error
from .evaluator import parse_options
from .jobs import (connect, job_dict, LOST_TIMEOUT, make_jobs, run_jobs, SCHEDULER_ENV,
                   summarize, workers_of, WorkersLost)
from .report import text_table
from .results import jsonable
from ..bag.errors import BagToolError
from ..core.errors import ObserverError, quiet_on_closed_pipe
from ..params_file import regular_file

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
    from .plots import pyplot, save_figure
    plt = pyplot()
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
    return save_figure(fig, path)


_CSV = ['bag', 'variant', 'observer_type', 'estimates', 'overrides', 'seconds', 'error']
_SUMMARY = ['matched', 'error_rms', 'settling_time']


_MANIFEST = 'batch.json'        # the jobs of a batch's output folder (for --resume)
_FINISHED = 'jobs'              # one JSON row per finished job, written as it finishes


def _row_file(out, i):
    return Path(out) / _FINISHED / f'{i:06d}.json'


def start_output(out, jobs, resume):
    """
    Prepare the output folder; return the rows of the jobs already finished there.

    A new folder gets the manifest (every job) and an empty ``jobs/``; with ``resume``
    the folder must hold the manifest of the same jobs, and the rows in ``jobs/`` of the
    jobs that match are returned ``{index: row}`` (the others run again).

    """
    out = Path(out)
    wanted = json.loads(json.dumps([job_dict(j) for j in jobs]))     # as read back
    if not resume:
        if out.exists():
            raise BagToolError(f'{out} exists; refusing to overwrite it (--resume to finish '
                               'the batch that wrote it)')
        (out / _FINISHED).mkdir(parents=True)
        _write_json(out / _MANIFEST, {'jobs': wanted})
        return {}
    try:
        manifest = json.loads((out / _MANIFEST).read_text())
    except (OSError, ValueError):
        raise BagToolError(f'--resume: {out} holds no observer-eval-batch run '
                           f'({_MANIFEST} missing or unreadable)') from None
    if manifest.get('jobs') != wanted:
        raise BagToolError(f'--resume: the jobs differ from those of the run in {out} '
                           '(give the same bags, vehicle, variants and options)')
    (out / _FINISHED).mkdir(exist_ok=True)
    done = {}
    for i, job in enumerate(wanted):
        try:
            row = json.loads(_row_file(out, i).read_text())
        except (OSError, ValueError):
            continue
        if row.get('job') == job:
            done[i] = row['row']
    return done


def _write_json(path, data):
    """Write JSON to a file atomically (a file written whole, or not at all)."""
    tmp = path.with_name(path.name + '.tmp')
    tmp.write_text(json.dumps(data))
    os.replace(tmp, path)


def write_batch(out, jobs, rows, summary, plots=True):
    """Write the merged table, the summary, the JSON and the plot to the folder."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
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
               'bags and the vehicle file. Each finished job is written to OUT/jobs/ at '
               'once. exit status: 0 every job ran; 1 some jobs failed (their row says '
               'why); 2 bad arguments (one line "error: ..."); 3 every worker lost for '
               '--lost-timeout s, 130 interrupted (one line "error: ...", the finished '
               'results kept, then the command to resume).')
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
    parser.add_argument('--resume', action='store_true',
                        help='finish the run that wrote --out: skip the jobs whose results '
                             'are there (after lost workers or Ctrl-C)')
    parser.add_argument('--lost-timeout', type=float, default=LOST_TIMEOUT, metavar='S',
                        help='end the run when the cluster has had no worker for S seconds '
                             f'(default {LOST_TIMEOUT:g}); the finished results are kept')
    parser.add_argument('--dashboard', nargs='?', const='127.0.0.1:8787', metavar='HOST:PORT',
                        help="the local cluster's Dask dashboard (needs bokeh: the "
                             "'dashboard' extra; default 127.0.0.1:8787)")
    parser.add_argument('--in-memory', action='store_true', help=IN_MEMORY_HELP)
    parser.add_argument('--no-plots', action='store_true', help='do not write the plot')
    parser.add_argument('--progress', action='store_true',
                        help='show progress even when stderr is not a terminal')
    return parser


def _free_cores():
    """Return (CPU count, 1-minute load average, cores free of it)."""
    cores = os.cpu_count() or 1
    try:
        load = os.getloadavg()[0]
    except OSError:
        load = 0.0
    return cores, load, max(0.0, cores - load)


def _efficiency(rows, wall, workers):
    """Return the line on the measured speed-up, and whether serial would have been faster."""
    cpu = sum(r.get('cpu_seconds') or 0.0 for r in rows)
    if not rows or wall <= 0.0 or not workers:
        return None
    speedup = cpu / wall
    line = (f'parallel efficiency {speedup / workers:.0%}: speed-up {speedup:.2f}x on '
            f'{workers} workers (the jobs took {cpu:.1f} s of CPU, done in {wall:.1f} s)')
    if speedup < 1.0:
        line += '; running serially (--serial) would have been faster'
    return line


@quiet_on_closed_pipe
def main(argv=None):
    """Entry point of ``observer-eval-batch``; returns the exit status."""
    argv = sys.argv[1:] if argv is None else list(argv)
    args = _parser().parse_args(argv)
    started = time.perf_counter()
    progress = Progress(args.progress or sys.stderr.isatty(), sys.stderr)

    def say(text):                       # on its own line, the progress bar after it
        progress.finish()
        print(f'warning: {text}', file=sys.stderr, flush=True)
    out = Path(args.out)
    done = {}
    try:
        if args.workers is not None and args.workers < 1:
            raise BagToolError(f'--workers must be at least 1, not {args.workers}')
        if not args.lost_timeout > 0:
            raise BagToolError(f'--lost-timeout must be positive, not {args.lost_timeout:g}')
        variants = parse_options(args.variant, args.tolerance)
        # a pipe (<(cat v.yaml)) is read once: the jobs (other processes) read a copy
        args.vehicle = str(regular_file(args.vehicle))
        jobs = make_jobs(find_bags(args.bags), args.vehicle, variants, args.namespace,
                         args.tolerance, args.exact)
        done = start_output(out, jobs, args.resume)
        todo = [i for i in range(len(jobs)) if i not in done]
        if done:
            print(f'resuming: {len(done)} of {len(jobs)} jobs already done in {out}/',
                  file=sys.stderr)

        def finished(k, row):           # k: index among todo
            _write_json(_row_file(out, todo[k]), {'job': job_dict(jobs[todo[k]]),
                                                  'row': row})
        client = cluster = None
        workers = 1
        if not args.serial and todo:
            with warnings.catch_warnings():
                warnings.simplefilter('ignore')
                client, cluster = connect(args.workers, args.scheduler, len(todo),
                                          dashboard=args.dashboard)
            workers = len(workers_of(client)) or 1
            if cluster is not None:
                cores, load, free = _free_cores()
                if workers > max(1.0, free):
                    say(f'{workers} workers on {cores} cores with about {free:.1f} free '
                        f'(load average {load:.2f}): running serially (--serial) would '
                        'likely be faster')
        run_started = time.perf_counter()
        try:
            with warnings.catch_warnings():
                warnings.simplefilter('ignore')
                ran = run_jobs([jobs[i] for i in todo], 'serial' if args.serial else 'dask',
                               progress=lambda d, t: progress('jobs done', len(done) + d,
                                                              len(jobs)),
                               spill=None if args.in_memory else True, on_row=finished,
                               on_event=say, lost_timeout=args.lost_timeout, client=client)
        finally:
            if client is not None:
                client.close()
            if cluster is not None:
                cluster.close()
        wall = time.perf_counter() - run_started
        progress.finish()
        rows = [None] * len(jobs)
        for i, row in done.items():
            rows[i] = row
        for i, row in zip(todo, ran):
            rows[i] = row
        summary = summarize(rows)
        files = write_batch(out, jobs, rows, summary, plots=not args.no_plots)
    except (WorkersLost, KeyboardInterrupt) as err:
        progress.finish()
        kept = len(list((out / _FINISHED).glob('*.json'))) if (out / _FINISHED).is_dir() \
            else 0
        why = 'interrupted' if isinstance(err, KeyboardInterrupt) else str(err)
        print(f'error: {why}; {kept} finished results kept in {out}/{_FINISHED}/',
              file=sys.stderr)
        again = argv if '--resume' in argv else argv + ['--resume']
        print(f'resume with: observer-eval-batch {shlex.join(again)}', file=sys.stderr)
        return 130 if isinstance(err, KeyboardInterrupt) else 3
    except (ObserverError, OSError) as err:
        return tool_error(progress, err)
    print(format_batch(rows, summary))
    failed = [r for r in rows if r['error']]
    for r in failed:
        print(f'warning: {r["bag"]} {r["variant"]}: {r["error"]}', file=sys.stderr)
    line = None if args.serial else _efficiency([rows[i] for i in todo], wall, workers)
    if line:
        print(f'\n{line}')
    print(f'\n{len(jobs)} jobs written to {out}/ ({", ".join(f.name for f in files)}) in '
          f'{time.perf_counter() - started:.1f} s')
    return 1 if failed else 0


if __name__ == '__main__':
    raise SystemExit(main())
