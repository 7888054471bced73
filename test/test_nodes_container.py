# The container executable and the executor choice (the nodes' own behaviour is tested
# through test_nodes_closed_loop, which runs the container too).
"""``container NODE ...``: argument errors, a bad vehicle file; OBSERVER_ROS_EXECUTOR; Ctrl-C."""

import signal
import subprocess
import sys

from observer_ros.core.errors import ObserverError
from observer_ros.nodes import common
from observer_ros.nodes.common import make_executor
import pytest
from ros_helpers import CONFIG, ros_env


def _container(*args, timeout=60):
    return subprocess.run([sys.executable, '-W', 'ignore::DeprecationWarning', '-m',
                           'observer_ros.nodes.container', *args], capture_output=True,
                          text=True, timeout=timeout, env=ros_env())


def test_unknown_or_repeated_node_is_refused_with_the_usage():
    for args, what in ((['observer', 'recorder'], "unknown node(s) ['recorder']"),
                       (['observer', 'observer'], 'a node named twice')):
        result = _container(*args)
        assert result.returncode == 2
        assert what in result.stderr and 'usage: container NODE' in result.stderr


def test_no_node_prints_the_usage():
    result = _container('--ros-args')
    assert result.returncode == 2 and 'usage: container NODE' in result.stderr


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


def test_only_the_first_sigint_interrupts_a_node_process():
    """Ctrl-C signals the group and ros2 launch signals again: one KeyboardInterrupt."""
    old = signal.getsignal(signal.SIGINT)
    try:
        common._interrupt_once()
        with pytest.raises(KeyboardInterrupt):
            signal.raise_signal(signal.SIGINT)
        for _ in range(3):      # while the first is handled: ignored, no second exception
            signal.raise_signal(signal.SIGINT)
    finally:
        signal.signal(signal.SIGINT, old)
