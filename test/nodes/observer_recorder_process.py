# test/nodes/observer_recorder_process.py: the observer and the recorder in one process.
"""
Run the observer node and the recorder in one process, spun by one executor.

A test's helper (``python test/nodes/observer_recorder_process.py --ros-args --params-file
VEHICLE -p output:=BAG ...``): both nodes share the process's DDS participant, so each
message reaches the two readers together and the bag holds the messages in the order the
observer took them. A recorder in a process of its own receives from each publisher on
its own schedule (on a loaded 2-core machine a reliable command reached it 0.4 s after it
reached the observer). SIGINT or SIGTERM stops the process; the bag is closed.

"""

import sys

from observer_ros.nodes.observer_node import ObserverNode
from observer_ros.nodes.recorder import RecorderNode
from observer_ros.nodes.runner import run_nodes


if __name__ == '__main__':
    raise SystemExit(run_nodes([ObserverNode, RecorderNode], sys.argv,
                               ['observer', 'recorder']))
