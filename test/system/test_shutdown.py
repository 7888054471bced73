# Stopping a running closed loop: Ctrl-C (SIGINT) or SIGTERM at a random moment.
"""
``observer-run`` stopped by a signal to its process group, as a terminal's Ctrl-C does.

Every node exits 0 and logs neither a FATAL line nor a traceback; ``observer-run`` says so
and exits 130. The moments are random: while the nodes start (imports, the design, DDS
discovery) and while the loop runs. ``OBSERVER_ROS_SIGNAL_TRIES`` sets the number of tries
(default 2: one in each phase, the second a SIGTERM; ``OBSERVER_ROS_SIGNAL_TRIES=50`` is the
on-demand bar of docs/reliability.md); test_ros2cli.py does the same through ``ros2 launch``.
"""

import os
from pathlib import Path
import random
import signal
import subprocess
import time

import pytest
from ros_helpers import CONFIG, ros_env, RUN_SEED, WAIT

pytestmark = pytest.mark.ros      # processes or DDS participants

TRIES = int(os.environ.get('OBSERVER_ROS_SIGNAL_TRIES', '2'))
NODES = ('plant_simulator', 'observer_node', 'compensator', 'recorder')
BAD = ('Traceback', 'FATAL', 'Exception in')


def _wait_for_text(path, text, proc):
    """Wait until a log file shows `text` (polling a file; the run is not timed)."""
    deadline = time.monotonic() + WAIT
    while time.monotonic() < deadline and proc.poll() is None:
        if path.exists() and text in path.read_text():
            return True
        time.sleep(0.1)
    return False


def _signal_group(proc, sig):
    os.killpg(proc.pid, sig)
    try:
        return proc.wait(timeout=WAIT)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
        raise AssertionError('observer-run did not stop within the deadline') from None


def _moments(tries, seed):
    """Return (signal, phase, delay) per try: half while starting, half while running."""
    rng = random.Random(seed)
    # every fourth try from the second a SIGTERM (a service manager's stop), while running
    return [(signal.SIGTERM if i % 4 == 1 else signal.SIGINT,
             'started' if i % 2 == 0 else 'running', rng.uniform(0.0, 3.0))
            for i in range(tries)]


@pytest.mark.parametrize('sig, phase, delay', _moments(TRIES, RUN_SEED))
def test_observer_run_stops_cleanly_on_a_signal(tmp_path, sig, phase, delay):
    bag = tmp_path / 'run'
    logs = Path(str(bag) + '_logs')
    out = open(tmp_path / 'observer-run.log', 'w')
    proc = subprocess.Popen(
        [str(Path(os.sys.executable).parent / 'observer-run'), str(CONFIG / 'submarine.yaml'),
         '--out', str(bag), '-p', 'simulator.duration:=600.0'],
        stdout=out, stderr=subprocess.STDOUT, env=ros_env(), start_new_session=True)
    try:
        # started: the four processes exist (the simulator is the last one started);
        # running: the simulator steps in lock-step
        path, text = (logs / 'plant_simulator.log', '') if phase == 'started' else \
            (logs / 'plant_simulator.log', 'lockstep run of')
        assert _wait_for_text(path, text, proc), (tmp_path / 'observer-run.log').read_text()
        time.sleep(delay)       # the random moment (nothing waits on it)
        code = _signal_group(proc, sig)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        out.close()
    said = (tmp_path / 'observer-run.log').read_text()
    statuses = ', '.join(f'{name} 0' for name in NODES)
    assert code == 130 and f'node exit statuses: {statuses}' in said, said
    for name in NODES:
        log = (logs / f'{name}.log').read_text()
        assert not any(bad in log for bad in BAD), f'{name}:\n{log}'
