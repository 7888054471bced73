# observer_ros.nodes.entry: the node executables' entry points, light to import.
"""
Entry points of the node executables (``ros2 run observer_ros observer``, ...).

Each installs the stop-signal handlers (:mod:`observer_ros.nodes.signals`) first and only
then imports its node's module (rclpy, numpy, scipy, python-control: seconds on a loaded
machine), so that a Ctrl-C at any moment of the start-up ends the process cleanly: at
once (status 0) while those modules are imported, as a node stops once it runs.
``python -m observer_ros.nodes.entry NODE ARGS...`` does the same (``observer-run``).

"""

import importlib
import logging
import os
import sys

from . import signals

__all__ = ['MODULES', 'run', 'plant_simulator', 'observer', 'compensator', 'recorder',
           'container']

# executable -> the module whose main() it runs
MODULES = {
    'plant_simulator': 'observer_ros.nodes.plant_simulator',
    'observer': 'observer_ros.nodes.observer_node',
    'observer_node': 'observer_ros.nodes.observer_node',
    'compensator': 'observer_ros.nodes.compensator',
    'recorder': 'observer_ros.nodes.recorder',
    'container': 'observer_ros.nodes.container',
}


def run(name, args=None):
    """Install the signal handlers, import the node's module, run its main(); the status."""
    signals.exit_while_importing(True)     # a stop now ends the process at once
    signals.install()
    try:
        module = importlib.import_module(MODULES[name])
        signals.exit_while_importing(False)
        code = module.main(args)
    finally:
        # the process only exits now: a signal must not kill it while the interpreter
        # finalises (which puts SIGINT and SIGTERM back to their defaults)
        signals.ignore()
    _exit_now(code)


def _exit_now(code):
    """
    End the process now: the nodes are destroyed, ROS shut down, every file closed.

    The interpreter's own teardown of numpy's, scipy's and python-control's modules is
    skipped: it took 1.5 to 2 s on a loaded 2-core host (0.07 s without them), and
    ``ros2 launch`` sends SIGTERM 5 s after SIGINT.
    """
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):   # a closed pipe: nothing more to say
            pass
    os._exit(code if isinstance(code, int) else int(code is not None))


def plant_simulator():
    """Run the plant simulator node."""
    return run('plant_simulator')


def observer():
    """Run the observer node."""
    return run('observer')


def compensator():
    """Run the compensator node."""
    return run('compensator')


def recorder():
    """Run the recorder node."""
    return run('recorder')


def container():
    """Run several nodes in one process."""
    return run('container')


if __name__ == '__main__':
    if len(sys.argv) < 2 or sys.argv[1] not in MODULES:
        print(f'usage: python -m observer_ros.nodes.entry {{{",".join(MODULES)}}} ARGS...',
              file=sys.stderr)
        raise SystemExit(2)
    name = sys.argv.pop(1)
    raise SystemExit(run(name))
