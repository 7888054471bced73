# The loop split across two "machines": network namespaces joined by a veth pair.
"""
The simulator on one host, the observer and the compensator on another (reliability issue).

Two network namespaces joined by a veth pair stand for two machines on one Ethernet
segment (10.200.X.1/24 and 10.200.X.2/24). DDS discovers over the veth by multicast, as
on a LAN. Fast DDS is limited to UDPv4 (``FASTDDS_BUILTIN_TRANSPORTS=UDPv4``): two machines
share no memory, and this way the veth is the only path between the hosts, so cutting it
cuts them apart. A probe runs in the observer's namespace (this file, run as a script) and
prints what it sees as JSON lines. Needs root and ``ip``; skipped otherwise.

"""

import json
import os
from pathlib import Path
import signal
import subprocess
import sys
import threading

from netns import env, ip, VETH_SIM
import numpy as np
from observer_ros.tools.run_closed_loop import node_command, stop_process
import pytest
from ros_helpers import CONFIG, WAIT

pytestmark = [pytest.mark.ros,       # processes or DDS participants
              pytest.mark.realtime]  # realtime closed loops or rates: one at a time

VEHICLE = CONFIG / 'submarine.yaml'
TEST = Path(__file__).resolve().parents[1]       # test/: the helper modules
SIM = ['simulator.mode:=realtime', 'simulator.realtime_factor:=2.0',
       'simulator.noise:=false', 'simulator.duration:=3000.0']
CLIENT = SIM + ['use_sim_time:=true']


class Watch:
    """The probe's JSON lines, collected by a thread; waits are woken by each line."""

    def __init__(self, ns, log_path):
        self.cond = threading.Condition()
        self.true, self.estimates, self.diagnostics = {}, [], []
        self.log = open(log_path, 'w')
        # the probe is this file run as a script: test/'s helper modules on its path
        path = os.pathsep.join(filter(None, [str(TEST), os.environ.get('PYTHONPATH')]))
        self.proc = subprocess.Popen(
            ['ip', 'netns', 'exec', ns, sys.executable, '-W', 'ignore', __file__, '--probe'],
            stdout=subprocess.PIPE, stderr=self.log, text=True, env=dict(env(), PYTHONPATH=path))
        self.thread = threading.Thread(target=self._read, daemon=True)
        self.thread.start()

    def _read(self):
        for line in self.proc.stdout:
            try:
                item = json.loads(line)
            except ValueError:
                continue
            with self.cond:
                if item['k'] == 'true':
                    self.true[item['t']] = np.array(item['x'])
                elif item['k'] == 'est':
                    self.estimates.append((item['t'], np.array(item['x'])))
                else:
                    self.diagnostics.append((item['name'], item['level'], item['message']))
                self.cond.notify_all()

    def wait(self, predicate, what, timeout=WAIT):
        with self.cond:
            if not self.cond.wait_for(predicate, timeout):
                raise AssertionError(f'timed out after {timeout} s waiting for {what}')

    def errors_since(self, index):
        return [float(np.linalg.norm(self.true[t] - x)) for t, x in self.estimates[index:]
                if t in self.true]

    def status(self, node, since=0):
        for name, level, message in reversed(self.diagnostics[since:]):
            if name.endswith('/' + node):
                return level, message
        return None

    def close(self):
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self.thread.join(timeout=5)
        self.log.close()


def _start(ns, node, params, log_dir):
    log = open(log_dir / f'{node}.log', 'w')
    proc = subprocess.Popen(['ip', 'netns', 'exec', ns, *node_command(node, VEHICLE, *params)],
                            stdout=log, stderr=subprocess.STDOUT, env=env())
    return proc, log


def _stop(proc, log):
    stop_process(proc)
    log.close()


OK, WARN, ERROR = 0, 1, 2


def test_loop_across_two_hosts_survives_a_cut_link(hosts, tmp_path):
    procs = {}
    watch = None
    try:
        procs['observer'] = _start(hosts['est'], 'observer_node', CLIENT, tmp_path)
        procs['compensator'] = _start(hosts['est'], 'compensator', CLIENT, tmp_path)
        watch = Watch(hosts['est'], tmp_path / 'probe.log')
        procs['simulator'] = _start(hosts['sim'], 'plant_simulator', SIM, tmp_path)

        # the loop closes across the link: the estimate (on host 2) converges to the true
        # state (from host 1), and the compensator's commands drive the plant to zero
        watch.wait(lambda: watch.errors_since(0), 'estimates and true states across hosts')
        watch.wait(lambda: (s := watch.status('compensator')) and s[0] == OK,
                   'the compensator closing the loop')
        watch.wait(lambda: any(e < 1e-2 for e in watch.errors_since(0)),
                   'the estimate converging across the link')
        watch.wait(lambda: np.linalg.norm(watch.true[max(watch.true)]) < 0.25,
                   'the plant on host 1 driven towards zero from host 2')

        # cut the link: nothing arrives on host 2; the observer reports that it only
        # predicts (WARN), the compensator that its estimate is stale (ERROR)
        ip('-n', hosts['sim'], 'link', 'set', VETH_SIM, 'down')
        n_diag = len(watch.diagnostics)
        watch.wait(lambda: (s := watch.status('observer', n_diag)) and s[0] == WARN
                   and 'predicting only' in s[1], 'the observer reporting predicting only')
        # counted once the observer has had nothing for its sensor timeout: what was under
        # way when the link went down has arrived by then, even at a loaded probe's pace
        n_true = len(watch.true)
        watch.wait(lambda: (s := watch.status('compensator', n_diag)) and s[0] == ERROR,
                   'the compensator reporting a stale estimate')
        n_diag = len(watch.diagnostics)
        watch.wait(lambda: watch.status('observer', n_diag), 'one more observer report')
        assert 'stale' in watch.status('compensator')[1]
        assert len(watch.true) <= n_true + 1            # (one may have been under way)
        for name, (proc, _) in procs.items():
            assert proc.poll() is None, f'{name} exited during the cut'

        # the link returns: data flows again, both report OK, the estimate converges again
        ip('-n', hosts['sim'], 'link', 'set', VETH_SIM, 'up')
        n_diag, n_est = len(watch.diagnostics), len(watch.estimates)
        watch.wait(lambda: (s := watch.status('observer', n_diag)) and s[0] == OK,
                   'the observer estimating again')
        watch.wait(lambda: (s := watch.status('compensator', n_diag)) and s[0] == OK,
                   'the compensator closing the loop again')
        watch.wait(lambda: len(watch.true) > n_true + 20, 'true states across the link again')
        watch.wait(lambda: (e := watch.errors_since(n_est)) and any(x < 1e-2 for x in e[5:]),
                   'the estimate converged again after the cut')
    finally:
        for name in ('simulator', 'observer', 'compensator'):
            if name in procs:
                _stop(*procs[name])
        if watch is not None:
            watch.close()


# -------------------------------------------------------------------- the probe (host 2)
def _probe_main():
    """Print state/true, state/estimate and /diagnostics as JSON lines until SIGINT."""
    import warnings
    warnings.filterwarnings('ignore', category=DeprecationWarning)
    import rclpy
    from rclpy.executors import ExternalShutdownException
    from diagnostic_msgs.msg import DiagnosticArray
    from sensor_msgs.msg import JointState
    from observer_ros.nodes.common import STATE_QOS
    from observer_ros.timeutil import stamp_to_ns

    def vector(kind):
        def callback(msg):
            print(json.dumps({'k': kind, 't': stamp_to_ns(msg.header.stamp),
                              'x': list(msg.position)}), flush=True)
        return callback

    def diagnostics(msg):
        for s in msg.status:
            level = s.level if isinstance(s.level, int) else int.from_bytes(s.level, 'little')
            print(json.dumps({'k': 'diag', 'name': s.name, 'level': level,
                              'message': s.message}), flush=True)

    rclpy.init()
    node = rclpy.create_node('multihost_probe')
    node.create_subscription(JointState, 'state/true', vector('true'), STATE_QOS)
    node.create_subscription(JointState, 'state/estimate', vector('est'), STATE_QOS)
    node.create_subscription(DiagnosticArray, '/diagnostics', diagnostics, 100)
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__' and '--probe' in sys.argv:
    _probe_main()
