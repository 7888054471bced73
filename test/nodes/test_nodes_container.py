# The container executable and the executor choice (the nodes' own behaviour is tested
# through test_nodes_closed_loop, which runs the container too).
"""``container NODE ...``: argument errors, a bad vehicle file; OBSERVER_ROS_EXECUTOR; Ctrl-C."""

import signal
import subprocess
import sys

from observer_ros.core.errors import ObserverError
from observer_ros.nodes import signals
from observer_ros.nodes.runner import make_executor
import pytest
from ros_helpers import CONFIG, ros_env


def _container(*args, timeout=60):
    return subprocess.run([sys.executable, '-W', 'ignore::DeprecationWarning', '-m',
                           'observer_ros.nodes.container', *args], capture_output=True,
                          text=True, timeout=timeout, env=ros_env())


@pytest.mark.ros
def test_unknown_or_repeated_node_is_refused_with_the_usage():
    for args, what in ((['observer', 'recorder'], "unknown node(s) ['recorder']"),
                       (['observer', 'observer'], 'a node named twice')):
        result = _container(*args)
        assert result.returncode == 2
        assert what in result.stderr and 'usage: container NODE' in result.stderr


@pytest.mark.ros
def test_no_node_prints_the_usage():
    result = _container('--ros-args')
    assert result.returncode == 2 and 'usage: container NODE' in result.stderr


@pytest.mark.ros
def test_bad_vehicle_file_stops_the_container_naming_the_field():
    result = _container('observer', 'compensator', '--ros-args', '--params-file',
                        str(CONFIG / 'submarine.yaml'), '-p', 'model.A:=[1.0]')
    assert result.returncode == 2
    assert 'error: ' in result.stderr and 'model.A' in result.stderr
    assert 'Traceback' not in result.stderr + result.stdout


def test_unknown_executor_is_refused_naming_the_variable(monkeypatch):
    monkeypatch.setenv('OBSERVER_ROS_EXECUTOR', 'multi')
    with pytest.raises(ObserverError, match='OBSERVER_ROS_EXECUTOR'):
        make_executor()


def test_stop_signals_are_recorded_never_raised():
    """Ctrl-C signals the group and ros2 launch signals again: each only asks for a stop."""
    old = {sig: signal.getsignal(sig) for sig in signals.STOP_SIGNALS}
    try:
        signals.install()
        assert not signals.requested()
        for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGINT):
            signal.raise_signal(sig)    # nothing raised, whatever runs at that moment
        assert signals.requested()
        assert signals.RECEIVED == [signal.SIGINT, signal.SIGTERM, signal.SIGINT]
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)
        signals.RECEIVED.clear()


@pytest.mark.ros
@pytest.mark.parametrize('when', ['during', 'before'])
def test_a_stop_while_the_modules_import_ends_the_process_at_once(when):
    """Nothing is open while a node's modules import: a stop signal exits with status 0."""
    # 'before': received while blocked (observer-run starts nodes so), taken at install
    signal_first = 'os.kill(os.getpid(), signal.SIGINT); ' if when == 'before' else ''
    script = (
        'import os, signal\n'
        'from observer_ros.nodes import signals\n'
        'signal.pthread_sigmask(signal.SIG_BLOCK, signals.STOP_SIGNALS)\n'
        f'{signal_first}signals.exit_while_importing(True)\n'
        'signals.install()\n'
        'os.kill(os.getpid(), signal.SIGTERM)\n'
        'import numpy, scipy.linalg\n'      # a stand-in for the node's imports
        'print("imported")\n')
    result = subprocess.run([sys.executable, '-c', script], capture_output=True, text=True,
                            timeout=120)
    assert result.returncode == 0, result.stdout + result.stderr
    assert 'imported' not in result.stdout and not result.stderr, result.stdout + result.stderr
