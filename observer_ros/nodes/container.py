# observer_ros.nodes.container: several of the package's nodes in one process.
"""
Run several of the package's nodes in one process, spun by one executor.

``ros2 run observer_ros container observer compensator --ros-args --params-file
config/submarine.yaml`` starts the observer and the compensator in one process: the
rclpy counterpart of a component container (rclpy has no component loading). The nodes
are the same classes as their own executables, with the same parameters (a ``/**:``
file applies to each; ``-r __ns:=/sub1`` moves them all), and talk to each other over
the same topics: DDS delivers between them inside the process, without a socket, and
no second Python interpreter competes for the cores. For a fast loop on a small
machine this halves the round trip (benchmarks/README.md, P2).

The recorder is not offered here: it must close its bag on a signal after draining
what DDS delivered, which needs a process of its own.

"""

import importlib
import sys

from .command_line import usage
from .runner import run_nodes

__all__ = ['NODES', 'main']

# executable name -> (module, class)
NODES = {
    'plant_simulator': ('observer_ros.nodes.plant_simulator', 'PlantSimulatorNode'),
    'observer': ('observer_ros.nodes.observer_node', 'ObserverNode'),
    'compensator': ('observer_ros.nodes.compensator', 'CompensatorNode'),
}

USAGE = (f'usage: container NODE [NODE ...] [--ros-args ...]\n'
         f'  NODE: one of {", ".join(NODES)} (each at most once)')


def _node_names(argv):
    """Split the argv into the node names (before --ros-args) and the rest."""
    names, rest = [], []
    for i, arg in enumerate(argv):
        if arg.startswith('-'):
            rest = argv[i:]
            break
        names.append(arg)
    return names, rest


def main(args=None):
    """Run the nodes named on the command line in one process; return the exit status."""
    argv = list(sys.argv[1:] if args is None else args)
    names, ros_argv = _node_names(argv)
    if names and names[0] in ('-h', '--help') or not names and set(argv) & {'-h', '--help'}:
        print(f'{USAGE}\n\n{usage("container NODE [NODE ...]", __name__, __doc__)}')
        return 0
    if not names:
        print(f'error: container: no node named\n{USAGE}', file=sys.stderr)
        return 2
    unknown = [n for n in names if n not in NODES]
    if unknown or len(set(names)) != len(names):
        what = f'unknown node(s) {unknown}' if unknown else 'a node named twice'
        print(f'error: container: {what}\n{USAGE}', file=sys.stderr)
        return 2
    classes = [getattr(importlib.import_module(NODES[n][0]), NODES[n][1]) for n in names]
    return run_nodes(classes, ['container'] + ros_argv, names)


if __name__ == '__main__':
    raise SystemExit(main())
