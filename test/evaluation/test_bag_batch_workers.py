# test/evaluation/test_bag_batch_workers.py: observer-eval-batch when its Dask workers die mid-run.
"""
observer-eval-batch on a real Dask cluster whose workers are killed mid-run.

A real ``dask scheduler`` and ``dask worker`` processes (no nanny, so a killed worker
stays dead), and ``observer-eval-batch`` run as a user runs it:

- one worker SIGKILLed after two jobs: the progress output says so, the other worker
  finishes every job, and the numbers are the serial run's;
- every worker SIGKILLed after two jobs: the run ends within ``--lost-timeout`` with one
  ``error:`` line, the finished results are on disk, and the printed resume command,
  run with a new worker, finishes only the jobs that were missing.

The jobs replay a 10 000-message Imu bag call by call (``--exact``), long enough for the
kills to land mid-run.

"""

import csv
import json
from pathlib import Path
import re
import shlex
import signal
import subprocess
import sys
import threading
import time

from observer_ros.tools.run_closed_loop import stop_process
import pytest
from ros_helpers import made_once

pytestmark = pytest.mark.ros      # processes or DDS participants

ROOT = Path(__file__).resolve().parents[2]
VEHICLE = ROOT / 'config' / 'submarine.yaml'
DASK = Path(sys.executable).parent / 'dask'
BATCH = Path(sys.executable).parent / 'observer-eval-batch'
BAGS = 4                     # copies (links) of the bag: 4 bags x 2 variants = 8 jobs
LOST_TIMEOUT = 15.0
WAIT = 900.0                 # s: a whole run on a loaded 2-core host


@pytest.fixture(scope='module')
def bags(tmp_path_factory):
    """Return a folder of BAGS links to one 10 000-message Imu bag (P3's generator)."""
    def generate(folder):
        sys.path.insert(0, str(ROOT / 'benchmarks'))
        import p3_replay
        (folder / 'p3').mkdir()
        bag = p3_replay.generate(10_000, data=folder / 'p3', log=lambda *a: None)
        (folder / 'bags').mkdir()
        for i in range(BAGS):
            (folder / 'bags' / f'b{i}').symlink_to(bag, target_is_directory=True)
    return made_once(tmp_path_factory, 'batch_workers_bags', generate) / 'bags'


class Cluster:
    """A dask scheduler on the loopback interface and its workers, each a process."""

    def __init__(self, tmp):
        self.file = tmp / 'scheduler.json'
        self.logs = tmp
        self.procs = []
        self.scheduler = self._start(
            'scheduler', ['scheduler', '--host', '127.0.0.1', '--port', '0',
                          '--no-dashboard', '--scheduler-file', str(self.file)])
        self.address = self._read_address(time.monotonic() + WAIT)
        self.workers = []

    def _read_address(self, deadline):
        # The scheduler writes its file in place: it can exist, empty or cut
        # short, before the write ends.
        while True:
            try:
                return json.loads(self.file.read_text())['address']
            except (FileNotFoundError, json.JSONDecodeError, KeyError):
                if time.monotonic() > deadline or self.scheduler.poll() is not None:
                    raise
            time.sleep(0.1)

    def _start(self, name, args):
        log = open(self.logs / f'{name}_{len(self.procs)}.log', 'w')
        proc = subprocess.Popen([str(DASK), *args], stdout=log, stderr=subprocess.STDOUT)
        self.procs.append(proc)
        return proc

    def add_workers(self, count):
        from distributed import Client
        for _ in range(count):
            self.workers.append(self._start('worker', [
                'worker', '--scheduler-file', str(self.file), '--nthreads', '1',
                '--no-nanny', '--host', '127.0.0.1', '--no-dashboard']))
        alive = sum(p.poll() is None for p in self.workers)
        with Client(self.address, timeout='60s') as client:
            client.wait_for_workers(alive, timeout=WAIT)

    def kill(self, worker):
        worker.send_signal(signal.SIGKILL)
        worker.wait(timeout=30)

    def close(self):
        for proc in reversed(self.procs):
            stop_process(proc, timeout=30.0)


@pytest.fixture
def cluster(tmp_path):
    c = Cluster(tmp_path)
    try:
        yield c
    finally:
        c.close()


class Batch:
    """observer-eval-batch as a process; its stderr collected (the bar has no newlines)."""

    def __init__(self, args):
        self.proc = subprocess.Popen([str(BATCH), *args], stdout=subprocess.PIPE,
                                     stderr=subprocess.PIPE, text=True)
        self.err = ''
        self.cond = threading.Condition()
        self.thread = threading.Thread(target=self._read, daemon=True)
        self.thread.start()

    def _read(self):
        while True:
            chunk = self.proc.stderr.read(1)
            if not chunk:
                break
            with self.cond:
                self.err += chunk
                self.cond.notify_all()

    def wait_for(self, pattern, timeout=WAIT):
        with self.cond:
            ok = self.cond.wait_for(lambda: re.search(pattern, self.err), timeout)
        assert ok, f'no {pattern!r} in {self.err[-2000:]!r}'

    def finish(self, timeout=WAIT):
        out = self.proc.stdout.read()
        code = self.proc.wait(timeout=timeout)
        self.thread.join(timeout=30)
        return code, out, self.err


def _args(bags, out, cluster, *extra):
    return [str(bags), '--vehicle', str(VEHICLE), '--variant',
            'slow:observer.poles:=[-0.1,-0.11,-0.12]', '--exact', '--out', str(out),
            '--scheduler', cluster.address, '--progress', '--no-plots',
            '--lost-timeout', str(LOST_TIMEOUT), *extra]


def _finished(out):
    return sorted((out / 'jobs').glob('*.json'))


def _wait_files(out, count, batch):
    deadline = time.monotonic() + WAIT
    while len(_finished(out)) < count:
        assert batch.proc.poll() is None, batch.err[-2000:]
        assert time.monotonic() < deadline, f'fewer than {count} jobs finished in time'
        time.sleep(0.05)


def _rows(out):
    with open(out / 'results.csv') as f:
        return [{k: v for k, v in r.items() if k != 'seconds'} for r in csv.DictReader(f)]


def test_one_worker_lost_is_said_and_the_other_finishes(bags, cluster, tmp_path):
    cluster.add_workers(2)
    out = tmp_path / 'out'
    batch = Batch(_args(bags, out, cluster))
    _wait_files(out, 2, batch)
    cluster.kill(cluster.workers[0])
    batch.wait_for(r'warning: lost worker tcp://127\.0\.0\.1:\d+: 1 left')
    code, stdout, err = batch.finish()
    assert code == 0, err[-2000:]
    assert len(_finished(out)) == 2 * BAGS
    assert 'parallel efficiency' in stdout
    assert not [line for line in err.splitlines() if line.startswith('error')]
    # the same numbers as in one process (one of the linked bags: its two jobs)
    one = tmp_path / 'one'
    one.mkdir()
    (one / 'b0').symlink_to((bags / 'b0').resolve(), target_is_directory=True)
    serial = tmp_path / 'serial'
    args = _args(one, serial, cluster)
    args[args.index('--scheduler'):args.index('--scheduler') + 2] = ['--serial']
    proc = subprocess.run([str(BATCH), *args], capture_output=True, text=True, timeout=WAIT)
    assert proc.returncode == 0, proc.stderr[-2000:]
    numbers = [{k: v for k, v in r.items() if k != 'bag'} for r in _rows(serial)]
    assert len(numbers) == 2
    for i in range(BAGS):
        got = [{k: v for k, v in r.items() if k != 'bag'} for r in _rows(out)[2 * i:2 * i + 2]]
        assert got == numbers, i


def test_every_worker_lost_ends_the_run_keeps_the_results_and_resumes(bags, cluster,
                                                                      tmp_path):
    cluster.add_workers(2)
    out = tmp_path / 'out'
    batch = Batch(_args(bags, out, cluster))
    _wait_files(out, 2, batch)
    for worker in cluster.workers:
        cluster.kill(worker)
    killed = time.monotonic()
    code, stdout, err = batch.finish()
    took = time.monotonic() - killed
    assert code == 3, err[-2000:]
    assert took < LOST_TIMEOUT + 90.0, took     # the timeout and its polling, not forever
    errors = [line for line in err.splitlines() if 'error:' in line]
    assert len(errors) == 1, err[-2000:]
    assert errors[0].split('\r')[-1].startswith('error: every worker lost'), errors
    assert 'no worker left' in err
    kept = len(_finished(out))
    assert 2 <= kept < 2 * BAGS
    assert f'{kept} finished results kept' in errors[0]
    resume = [line for line in err.splitlines() if line.startswith('resume with: ')]
    assert len(resume) == 1
    command = shlex.split(resume[0][len('resume with: '):])
    assert command[0] == 'observer-eval-batch' and command[-1] == '--resume'
    done_before = {p.name: p.stat().st_mtime_ns for p in _finished(out)}
    cluster.add_workers(1)
    proc = subprocess.run([str(BATCH), *command[1:]], capture_output=True, text=True,
                          timeout=WAIT)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert f'resuming: {kept} of {2 * BAGS} jobs already done' in proc.stderr
    assert len(_rows(out)) == 2 * BAGS
    # the finished jobs were not run again
    assert all((out / 'jobs' / name).stat().st_mtime_ns == mtime
               for name, mtime in done_before.items())
