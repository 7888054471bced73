# test/evaluation/test_bag_jobs.py: bag x variant jobs, serially and on a local Dask cluster.
"""
The job layer (observer_ros/evaluation/jobs.py) and observer-eval-batch (evaluation/batch.py).

A local Dask cluster of two worker processes runs the jobs of the three sample bags
times two configurations and gives the serial path's rows exactly; a job's numbers are
those of observer-eval for the same variant; the worker path imports no ROS.

"""

import contextlib
import csv
import io
import math
from pathlib import Path
import subprocess
import sys

from bag_cases import numbers
from observer_ros.bag.errors import BagToolError
from observer_ros.evaluation.batch import find_bags, main
from observer_ros.evaluation.evaluator import evaluate_bag
from observer_ros.evaluation.jobs import Job, make_jobs, run_job, run_jobs, summarize
import pytest

ROOT = Path(__file__).resolve().parents[2]
SAMPLES = ROOT / 'bags' / 'samples'
CONFIG = ROOT / 'config'
OPEN_LOOP = ['observer.type:=open_loop']


def _jobs():
    jobs = []
    for name in ('submarine', 'cart_pendulum', 'submarine_reduced'):
        jobs += make_jobs([SAMPLES / name], CONFIG / f'{name}.yaml', {'openloop': OPEN_LOOP})
    return jobs


@pytest.mark.ros
def test_a_local_dask_cluster_of_two_workers_gives_the_serial_numbers_exactly():
    jobs = _jobs()
    seen = []
    serial = run_jobs(jobs, 'serial', progress=lambda d, t: seen.append((d, t)))
    assert seen == [(i + 1, len(jobs)) for i in range(len(jobs))]
    assert all(r['error'] is None for r in serial), [r['error'] for r in serial]
    assert all(math.isfinite(r['summary']['error_rms']) and r['estimates'] > 100
               for r in serial)
    done = []
    on_dask = run_jobs(jobs, 'dask', workers=2, progress=lambda d, t: done.append(d))
    assert done == list(range(1, len(jobs) + 1))
    assert numbers(on_dask) == numbers(serial)
    # the design and the open loop differ (the rows are not all one number)
    assert serial[0]['summary']['error_rms'] != serial[1]['summary']['error_rms']


def test_a_jobs_numbers_are_observer_evals():
    bag, vehicle = SAMPLES / 'submarine', CONFIG / 'submarine.yaml'
    result = evaluate_bag(bag, vehicle, {'openloop': OPEN_LOOP}, include_live=False)
    for name, overrides in (('design', ()), ('openloop', tuple(OPEN_LOOP))):
        row = run_job(Job(str(bag), str(vehicle), name, overrides))
        vr = result.variants[name]
        assert row['error'] is None
        assert row['summary']['error_rms'] == vr.summary['error_rms']
        assert row['estimates'] == len(vr.replay)
        assert {k: m['rmse'] for k, m in row['states'].items()} == \
            {k: m['rmse'] for k, m in vr.states.items()}
        assert {k: m['residual_rms'] for k, m in row['outputs'].items()} == \
            {k: m['residual_rms'] for k, m in vr.outputs.items()}


@pytest.mark.ros
def test_the_worker_path_imports_no_ros():
    code = ('import sys; from observer_ros.evaluation.jobs import Job, run_job; '
            f'row = run_job(Job({str(SAMPLES / "submarine")!r}, '
            f'{str(CONFIG / "submarine.yaml")!r})); '
            'assert row["error"] is None, row; '
            'bad = [m for m in sys.modules if m.split(".")[0] in ("rclpy", "rosidl_runtime_py")]; '
            'print("ros modules:", bad)')
    proc = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                          timeout=300, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr
    assert 'ros modules: []' in proc.stdout


def test_a_failing_job_gives_a_row_and_the_others_run(tmp_path):
    jobs = make_jobs([SAMPLES / 'submarine', tmp_path / 'missing'], CONFIG / 'submarine.yaml')
    rows = run_jobs(jobs, 'serial')
    assert rows[0]['error'] is None
    assert 'missing' in rows[1]['error'] and 'no such file' in rows[1]['error']
    summary = summarize(rows)
    assert summary[0]['bags'] == 1 and summary[0]['failed'] == 1
    assert summary[0]['error_rms']['mean'] == rows[0]['summary']['error_rms']


def test_summary_across_bags():
    rows = run_jobs(make_jobs([SAMPLES / 'submarine'] * 2, CONFIG / 'submarine.yaml',
                              {'openloop': OPEN_LOOP}), 'serial')
    summary = {s['variant']: s for s in summarize(rows)}
    assert list(summary) == ['design', 'openloop']
    rms = [r['summary']['error_rms'] for r in rows if r['variant'] == 'openloop']
    assert summary['openloop']['bags'] == 2
    assert summary['openloop']['error_rms']['mean'] == pytest.approx(sum(rms) / 2)
    assert set(summary['design']['rmse']) == {'theta', 'w', 'q'}


def test_find_bags_takes_a_folder_of_bags(tmp_path):
    assert find_bags([SAMPLES]) == sorted(p for p in SAMPLES.iterdir() if p.is_dir())
    with pytest.raises(BagToolError, match='neither a bag nor a folder of bags'):
        find_bags([tmp_path])


def test_command_line_merged_table_summary_and_plot(tmp_path):
    out = tmp_path / 'out'
    buf, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(buf), contextlib.redirect_stderr(err):
        code = main([str(SAMPLES / 'submarine'), str(SAMPLES / 'cart_pendulum'),
                     '--vehicle', str(CONFIG / 'submarine.yaml'), '--variant',
                     'openloop:observer.type:=open_loop', '--out', str(out), '--serial',
                     '--progress'])
    # the cart's bag is not a submarine's: its jobs fail, the others are written
    assert code == 1
    assert 'jobs done' in err.getvalue() and '4/4' in err.getvalue()
    with open(out / 'results.csv') as f:
        rows = list(csv.DictReader(f))
    assert [(Path(r['bag']).name, r['variant']) for r in rows] == [
        ('submarine', 'design'), ('submarine', 'openloop'),
        ('cart_pendulum', 'design'), ('cart_pendulum', 'openloop')]
    assert float(rows[0]['error_rms']) > 0 and rows[2]['error']
    with open(out / 'summary.csv') as f:
        summary = list(csv.DictReader(f))
    assert {(s['variant'], s['bags'], s['failed']) for s in summary} == {
        ('design', '1', '1'), ('openloop', '1', '1')}
    assert (out / 'error_rms.png').stat().st_size > 1000
    assert 'across bags' in buf.getvalue()
    # the output folder is never overwritten
    with contextlib.redirect_stderr(io.StringIO()) as e2:
        assert main([str(SAMPLES / 'submarine'), '--vehicle', str(CONFIG / 'submarine.yaml'),
                     '--out', str(out), '--serial']) == 2
    assert e2.getvalue().startswith('error: ') and 'exists' in e2.getvalue()


@pytest.mark.ros
def test_jobs_run_on_an_existing_cluster_named_by_the_environment(monkeypatch):
    from distributed import LocalCluster
    from observer_ros.evaluation.jobs import SCHEDULER_ENV
    jobs = make_jobs([SAMPLES / 'submarine'], CONFIG / 'submarine.yaml',
                     {'openloop': OPEN_LOOP})
    serial = run_jobs(jobs, 'serial')
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True,
                      dashboard_address=None) as cluster:
        monkeypatch.setenv(SCHEDULER_ENV, cluster.scheduler_address)
        rows = run_jobs(jobs, 'dask')
        # the cluster is still there: run_jobs closed only its client
        assert cluster.scheduler_address
        again = run_jobs(jobs, 'dask', scheduler=cluster.scheduler_address)
    assert numbers(rows) == numbers(serial) == numbers(again)


@pytest.mark.ros
def test_a_local_cluster_listens_on_the_loopback_interface_only():
    import os
    import psutil
    from observer_ros.evaluation.jobs import connect, workers_of
    client, cluster = connect(workers=1)
    try:
        assert cluster.scheduler_address.startswith('tcp://127.0.0.1:')
        assert all(w.startswith('tcp://127.0.0.1:') for w in workers_of(client))
        pids = {os.getpid(), *client.run(os.getpid).values(), *client.run(os.getppid).values()}
        listening = [c for c in psutil.net_connections('inet') if c.pid in pids and
                     c.status == psutil.CONN_LISTEN]
        assert len(listening) >= 2             # the scheduler's and the worker's (+ nanny)
        assert {c.laddr.ip for c in listening} == {'127.0.0.1'}, listening
    finally:
        client.close()
        cluster.close()


def test_the_efficiency_line_says_when_serial_would_have_been_faster():
    from observer_ros.evaluation.batch import _efficiency
    rows = [{'cpu_seconds': 3.0}, {'cpu_seconds': 3.0}]
    line = _efficiency(rows, 4.0, 2)
    assert line.startswith('parallel efficiency 75%: speed-up 1.50x on 2 workers')
    assert 'serially' not in line
    slow = _efficiency(rows, 8.0, 2)
    assert 'speed-up 0.75x' in slow and 'running serially (--serial) would have been faster' \
        in slow
