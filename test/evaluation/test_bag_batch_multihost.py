# test_bag_batch_multihost.py: observer-eval-batch across two hosts (network namespaces).
"""
observer-eval-batch on a Dask cluster across two hosts gives the serial numbers.

A Dask cluster across two "machines": the network namespaces of test_multihost.py
(10.200.X.1 and 10.200.X.2 on one veth link).

The scheduler and a worker run on host 1, a second worker on host 2, every one bound to
its host's address on the link (``--host``, ``--dashboard-address``): nothing of theirs
listens on another address. ``observer-eval-batch --scheduler`` on host 1 gives the numbers of the
serial run, and both workers ran jobs. Needs root and ``ip``; skipped otherwise.

"""

import csv
import json
from pathlib import Path
import subprocess
import sys

from netns import env, NET
from observer_ros.tools.run_closed_loop import stop_process
import pytest

pytestmark = pytest.mark.ros      # processes or DDS participants

ROOT = Path(__file__).resolve().parents[2]
SAMPLE = ROOT / 'bags' / 'samples' / 'submarine'
VEHICLE = ROOT / 'config' / 'submarine.yaml'
BIN = Path(sys.executable).parent
WAIT = 240.0


def _in(ns, *cmd):
    return ['ip', 'netns', 'exec', ns, *map(str, cmd)]


def _listening(ns):
    """Return the local addresses of the TCP sockets listening in a namespace."""
    out = subprocess.run(_in(ns, 'ss', '-ltnH'), capture_output=True, text=True,
                         check=True).stdout
    return [line.split()[3] for line in out.splitlines() if line.strip()]


def _rows(out):
    with open(out / 'results.csv') as f:
        return [{k: v for k, v in r.items() if k != 'seconds'} for r in csv.DictReader(f)]


def test_a_batch_across_two_hosts_gives_the_serial_numbers(hosts, tmp_path):
    ip1, ip2 = f'10.200.{NET}.1', f'10.200.{NET}.2'
    bags = tmp_path / 'bags'
    bags.mkdir()
    for i in range(4):
        (bags / f'sub{i}').symlink_to(SAMPLE, target_is_directory=True)
    args = [str(bags), '--vehicle', str(VEHICLE), '--variant',
            'slow:observer.poles:=[-0.1,-0.11,-0.12]', '--no-plots']
    procs, logs = [], []

    def start(ns, name, *cmd):
        log = open(tmp_path / f'{name}.log', 'w')
        logs.append(log)
        procs.append(subprocess.Popen(_in(ns, *cmd), stdout=log, stderr=subprocess.STDOUT,
                                      env=env()))
    address = f'tcp://{ip1}:8786'
    try:
        # as README.md says: --host and --dashboard-address on the private address (the
        # HTTP server of each serves Dask's health and metrics routes, the dashboard too
        # with bokeh; without an address it listens on every interface)
        start(hosts['sim'], 'scheduler', BIN / 'dask', 'scheduler', '--host', ip1,
              '--port', '8786', '--dashboard-address', f'{ip1}:8787')
        for ns, ip, name in ((hosts['sim'], ip1, 'worker1'), (hosts['est'], ip2, 'worker2')):
            start(ns, name, BIN / 'dask', 'worker', address, '--host', ip, '--nthreads', '1',
                  '--dashboard-address', f'{ip}:0', '--name', name)
        wait = ('from distributed import Client; '
                f'c = Client({address!r}, timeout="{WAIT:g}s"); '
                f'c.wait_for_workers(2, timeout={WAIT}); print("workers", len(c.nthreads()))')
        proc = subprocess.run(_in(hosts['sim'], sys.executable, '-c', wait), capture_output=True,
                              text=True, timeout=WAIT + 60, env=env())
        assert 'workers 2' in proc.stdout, proc.stderr[-2000:]
        # every port of the cluster is on the host's own address on the link
        for ns, ip in ((hosts['sim'], ip1), (hosts['est'], ip2)):
            ports = _listening(ns)
            assert ports, ns
            assert all(p.rsplit(':', 1)[0] == ip for p in ports), (ns, ports)
        out = tmp_path / 'out'
        proc = subprocess.run(_in(hosts['sim'], BIN / 'observer-eval-batch', *args, '--out',
                                  out, '--scheduler', address), capture_output=True,
                              text=True, timeout=WAIT, env=env())
        assert proc.returncode == 0, proc.stderr[-2000:]
        assert 'parallel efficiency' in proc.stdout and 'on 2 workers' in proc.stdout
        serial = tmp_path / 'serial'
        proc = subprocess.run([str(BIN / 'observer-eval-batch'), *args, '--out', str(serial),
                               '--serial'], capture_output=True, text=True, timeout=WAIT)
        assert proc.returncode == 0, proc.stderr[-2000:]
        assert _rows(out) == _rows(serial)
        assert len(_rows(out)) == 8
        # both hosts ran jobs: each worker's log of finished tasks
        ran = subprocess.run(_in(hosts['sim'], sys.executable, '-c', (
            'from distributed import Client; import json; '
            f'c = Client({address!r}); '
            'print(json.dumps(c.run(lambda dask_worker: sum(1 for e in dask_worker.state.log '
            'if "run_job" in str(e[0]) and e[2] == "memory"))))')),
            capture_output=True, text=True, timeout=WAIT, env=env())
        counts = json.loads(ran.stdout.strip().splitlines()[-1])
        assert len(counts) == 2 and all(v > 0 for v in counts.values()), counts
    finally:
        for proc in reversed(procs):
            stop_process(proc, timeout=30.0)
        for log in logs:
            log.close()
