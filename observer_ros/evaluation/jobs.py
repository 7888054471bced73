# observer_ros.evaluation.jobs: bag x variant evaluations as independent jobs, serially or on Dask.
"""
The job layer: one job is one bag replayed through one observer configuration.

A :class:`Job` names a bag, a vehicle file, a variant (its overrides of the vehicle file)
and the evaluation's options; :func:`run_job` evaluates it with the code of
``observer-eval`` (:func:`observer_ros.evaluation.evaluator.evaluate_bag` on the vehicle with the
variant's overrides applied) and returns one row of plain data (numbers, strings), so a
job can run in any process: it reads the bag with rosbags and imports no ROS.

:func:`run_jobs` runs a list of jobs and returns their rows in the jobs' order:

- ``serial``: one after the other in this process;
- Dask (``dask.distributed``): each job a task on a cluster, a local one of ``workers``
  processes by default, or the existing cluster whose scheduler is at ``scheduler``
  (``tcp://host:8786``; default ``$DASK_SCHEDULER_ADDRESS``). Its workers need
  observer_ros and its Python dependencies (not ROS) and must see the bags and vehicle
  files at the same paths.

A job that fails (a bag that cannot be read, an invalid variant) gives a row with
``error`` set; the other jobs still run. :func:`summarize` merges the rows of a variant
across bags.

"""

from dataclasses import asdict, dataclass
import logging
import math
import os
import time
from typing import Optional, Tuple

import numpy as np

from ..bag.errors import BagToolError

__all__ = ['Job', 'make_jobs', 'run_job', 'run_jobs', 'connect', 'summarize', 'job_dict',
           'workers_of', 'WorkersLost', 'SCHEDULER_ENV', 'LOST_TIMEOUT']

SCHEDULER_ENV = 'DASK_SCHEDULER_ADDRESS'
LOCAL_HOST = '127.0.0.1'        # a local cluster listens on the loopback interface only
LOST_TIMEOUT = 60.0             # s without any worker before a Dask run gives up
POLL_SECONDS = 0.5              # s between looks at the cluster's workers


@dataclass(frozen=True)
class Job:
    """One bag through one configuration (all fields plain, so a job pickles anywhere)."""

    bag: str
    vehicle: str
    variant: str = 'design'
    overrides: Tuple[str, ...] = ()
    namespace: Optional[str] = None
    tolerance: Optional[str] = None
    exact: bool = False


def make_jobs(bags, vehicle, variants=None, namespace=None, tolerance=None, exact=False):
    """
    Return the jobs of every bag times the design and every variant.

    Parameters
    ----------
    bags : iterable of str or Path
        The bags (each a bag directory or a storage file).
    vehicle : str or Path
        The vehicle file, for every bag.
    variants : dict, optional
        ``{name: [override, ...]}`` as ``observer-eval --variant``; ``design`` (the file's
        own observer) always comes first.
    namespace, tolerance, exact
        As :func:`~observer_ros.evaluation.evaluator.evaluate_bag`'s.

    """
    configs = [('design', ())] + [(name, tuple(ov)) for name, ov in (variants or {}).items()]
    return [Job(str(bag), str(vehicle), name, ov, namespace, tolerance, bool(exact))
            for bag in bags for name, ov in configs]


def run_job(job, spill=True):
    """
    Evaluate one job; return its row (plain data).

    ``spill`` is :func:`~observer_ros.evaluation.evaluator.evaluate_bag`'s: True (default) keeps
    the replay's rows in temporary files (in the worker's TMPDIR) while it runs, None in
    memory; the rows are dropped once scored, so the row is the same either way.

    The row is :meth:`JobResult.to_dict() <observer_ros.evaluation.evaluator.JobResult>` of
    :func:`~observer_ros.evaluation.evaluator.evaluate_job` (``bag``, ``variant``,
    ``observer_type``, ``estimates``, ``summary`` with ``error_rms`` and
    ``settling_time``, ``states`` and ``outputs`` with their metrics, ``warnings``,
    ``seconds``; inf and NaN as None) with ``error``: None, or why the job failed, in
    one line (then the metrics are empty).

    """
    import warnings
    from .evaluator import evaluate_job
    from ..core.errors import error_text, ObserverError
    start = time.perf_counter()
    cpu = time.process_time()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter('ignore')
            result = evaluate_job(job.bag, job.vehicle, job.variant, job.overrides,
                                  job.namespace, job.tolerance, job.exact, spill=spill)
    except (ObserverError, OSError) as err:
        text = error_text(err)
        return {'bag': job.bag, 'vehicle': job.vehicle, 'variant': job.variant,
                'observer_type': None, 'overrides': list(job.overrides), 'estimates': 0,
                'counts': {}, 'summary': {}, 'states': {}, 'outputs': {},
                'ground_truth': False, 'warnings': [],
                'seconds': time.perf_counter() - start,
                'cpu_seconds': time.process_time() - cpu, 'error': text}
    row = result.to_dict()
    row['cpu_seconds'] = time.process_time() - cpu
    row['error'] = None
    return row


class WorkersLost(BagToolError):
    """Every worker of the cluster was gone for longer than the timeout; ``rows`` so far."""

    def __init__(self, message, rows):
        super().__init__(message)
        self.rows = rows


def run_jobs(jobs, backend='dask', workers=None, scheduler=None, progress=None, spill=True,
             on_row=None, on_event=None, lost_timeout=LOST_TIMEOUT, client=None):
    """
    Run jobs; return their rows in the jobs' order.

    Parameters
    ----------
    jobs : list of Job
        The jobs (:func:`make_jobs`).
    backend : {'dask', 'serial'}
        Where they run.
    workers : int, optional
        Worker processes of the local Dask cluster (default: the CPU count, at most the
        number of jobs). Ignored with a scheduler.
    scheduler : str, optional
        Address of an existing Dask scheduler; default ``$DASK_SCHEDULER_ADDRESS``; when
        neither is set, a local cluster is started and stopped.
    progress : callable, optional
        ``progress(done, total)`` after each finished job.
    spill : True or path or None
        Every job's :func:`run_job` ``spill`` (None: the rows in memory).
    on_row : callable, optional
        ``on_row(index, row)`` as soon as each job has finished (to write it at once).
    on_event : callable, optional
        ``on_event(text)``: a worker lost or back (Dask), said as it happens.
    lost_timeout : float
        Dask: seconds without any worker after which the run ends with
        :class:`WorkersLost` (its ``rows``: None for the jobs not finished).
    client : distributed.Client, optional
        Run on this client (from :func:`connect`; left open) instead of connecting.

    A job whose worker died under it is given to another worker by Dask; one that
    killed its workers three times (Dask's ``KilledWorker``) gets a row with ``error``
    and ``lost: True`` (not finished: not passed to ``on_row``).

    """
    jobs = list(jobs)
    if backend == 'serial':
        rows = []
        for i, job in enumerate(jobs):
            rows.append(run_job(job, spill))
            if on_row is not None:
                on_row(i, rows[-1])
            if progress is not None:
                progress(i + 1, len(jobs))
        return rows
    if backend != 'dask':
        raise ValueError(f'backend must be "dask" or "serial", not {backend!r}')
    if client is not None:
        return _run_dask(client, jobs, progress, spill, on_row, on_event, lost_timeout)
    client, cluster = connect(workers, scheduler, len(jobs))
    try:
        return _run_dask(client, jobs, progress, spill, on_row, on_event, lost_timeout)
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def connect(workers=None, scheduler=None, jobs=1, host=LOCAL_HOST, dashboard=None):
    """
    Return ``(client, cluster)``: a client of the scheduler, or of a new local cluster.

    ``scheduler`` (default ``$DASK_SCHEDULER_ADDRESS``) names an existing cluster
    (``cluster`` is then None); otherwise a local cluster of ``workers`` processes (default:
    the CPU count, at most ``jobs``), one thread each, whose scheduler and workers listen
    on ``host`` only (the loopback interface by default: nothing reachable from the
    network), with the Dask dashboard at ``dashboard`` (``HOST:PORT``; it needs bokeh,
    the ``dashboard`` extra) or none.

    """
    try:
        from distributed import Client, LocalCluster
    except ImportError:
        raise BagToolError('Dask is not installed (`pip install dask distributed`); or run '
                           'the jobs serially (--serial)') from None
    # Dask's own log lines (a local cluster's workers killed at its close under load,
    # ...) are not the user's business: the caller says what concerns the run
    logging.getLogger('distributed').setLevel(logging.ERROR)
    scheduler = scheduler or os.environ.get(SCHEDULER_ENV) or None
    if scheduler is not None:
        try:
            return Client(scheduler, timeout='30s'), None
        except (OSError, TimeoutError) as err:
            raise BagToolError(f'cannot reach the Dask scheduler at {scheduler}: '
                               f'{str(err).splitlines()[0] if str(err) else err}') from None
    if dashboard is not None:
        try:
            import bokeh  # noqa: F401
        except ImportError:
            raise BagToolError('--dashboard needs bokeh: pip install "observer_ros[dashboard]" '
                               '(or pip install "bokeh>=3.1")') from None
    n = workers or min(os.cpu_count() or 1, max(1, jobs))
    # without a dashboard the scheduler's HTTP server (health, metrics) still runs: on
    # the same host and a free port (Dask's default takes 8787, and says so when taken)
    cluster = LocalCluster(n_workers=int(n), threads_per_worker=1, processes=True,
                           host=host, dashboard_address=dashboard or f'{host}:0')
    return Client(cluster), cluster


def workers_of(client):
    """Return the addresses of the scheduler's workers now (asked, not a cached view)."""
    return set(client.run_on_scheduler(_worker_addresses))


def _worker_addresses(dask_scheduler=None):
    return list(dask_scheduler.workers)


def _run_dask(client, jobs, progress, spill, on_row, on_event, lost_timeout):
    from distributed import wait
    from distributed.scheduler import KilledWorker
    futures = {client.submit(run_job, job, spill, pure=False): i
               for i, job in enumerate(jobs)}
    rows = [None] * len(jobs)
    done = 0
    pending = set(futures)
    known = workers_of(client)
    alone_since = None if known else time.monotonic()
    while pending:
        try:
            finished, pending = wait(pending, timeout=POLL_SECONDS,
                                     return_when='FIRST_COMPLETED')
        except TimeoutError:                    # none finished in the poll's time
            finished = ()
        for future in finished:
            i = futures[future]
            try:
                rows[i] = future.result()
            except KilledWorker:
                rows[i] = _lost_row(jobs[i])
            else:
                if on_row is not None:
                    on_row(i, rows[i])
            done += 1
            if progress is not None:
                progress(done, len(jobs))
        if not pending:
            break
        now = workers_of(client)
        for gone in sorted(known - now):
            _say(on_event, f'lost worker {gone}: {len(now)} left, {done}/{len(jobs)} jobs '
                           'done (its jobs go to the others)' if now else
                           f'lost worker {gone}: no worker left, {done}/{len(jobs)} jobs '
                           f'done; waiting {lost_timeout:g} s for one')
        for new in sorted(now - known):
            _say(on_event, f'worker {new} joined: {len(now)} now')
        known = now
        if now:
            alone_since = None
        elif alone_since is None:
            alone_since = time.monotonic()
        elif time.monotonic() - alone_since > lost_timeout:
            for future in pending:
                future.cancel()
            raise WorkersLost(f'every worker lost: none for {lost_timeout:g} s, {done} of '
                              f'{len(jobs)} jobs done', rows)
    return rows


def _say(on_event, text):
    if on_event is not None:
        on_event(text)


def _lost_row(job):
    """Return the row of a job Dask gave up on (it killed its workers): not finished."""
    return {'bag': job.bag, 'vehicle': job.vehicle, 'variant': job.variant,
            'observer_type': None, 'overrides': list(job.overrides), 'estimates': 0,
            'counts': {}, 'summary': {}, 'states': {}, 'outputs': {}, 'ground_truth': False,
            'warnings': [], 'seconds': 0.0, 'cpu_seconds': 0.0, 'lost': True,
            'error': 'its worker died each time it ran (Dask KilledWorker); run again with '
                     '--resume'}


def _stats(values):
    v = np.array([x for x in values if x is not None and math.isfinite(x)], dtype=float)
    if not v.size:
        return {'mean': None, 'median': None, 'min': None, 'max': None}
    return {'mean': float(v.mean()), 'median': float(np.median(v)), 'min': float(v.min()),
            'max': float(v.max())}


def summarize(rows):
    """
    Return the rows merged per variant across bags (in the variants' first order).

    Each summary has ``variant``, ``bags`` (evaluated), ``failed``, and the ``mean``,
    ``median``, ``min`` and ``max`` across bags (None without a finite value) of
    ``error_rms``, ``settling_time``, each state's ``rmse`` and each output's
    ``residual_rms``.

    """
    by_variant = {}
    for row in rows:
        by_variant.setdefault(row['variant'], []).append(row)
    out = []
    for name, group in by_variant.items():
        ok = [r for r in group if r['error'] is None]
        summary = {'variant': name, 'bags': len(ok), 'failed': len(group) - len(ok)}
        for key in ('error_rms', 'settling_time'):
            summary[key] = _stats(r['summary'].get(key) for r in ok)
        for key, part in (('rmse', 'states'), ('residual_rms', 'outputs')):
            names = list(dict.fromkeys(k for r in ok for k in r[part]))
            summary[key] = {k: _stats(r[part].get(k, {}).get(key) for r in ok)
                            for k in names}
        out.append(summary)
    return out


def job_dict(job):
    """Return a job as a dict (for the JSON report)."""
    return asdict(job)
