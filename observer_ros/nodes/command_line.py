# observer_ros.nodes.command_line: --help and the params files, before rclpy reads them.
"""
What a node does with its command line before ``rclpy.init``: ``--help``, params files.

``--help`` (or ``-h``) before ``--ros-args`` prints the usage, the params-file form and the
node's topics (its module's docstring), and exits 0. Each ``--params-file`` is read by the
package's loader first (observer_ros.params_file: size and array-length limits, no aliases,
UTF-8), so that a node refuses a file exactly as the offline tools do, as quickly, with one
``error:`` line and exit status 2, instead of rclpy's RCLError traceback. A pipe given as
a params file (process substitution) is read once and handed to rclpy as a regular copy;
a FIFO without a writer, a folder or a device is refused without waiting. The ``-p``
overrides and the ``-r`` remaps of the namespace or the node name are checked by ROS's
rules first too (observer_ros.ros_names), naming the argument and the character.

"""

import os
import sys

from ..core.errors import ObserverError
from ..params_file import check_parameters_file, regular_file
from ..ros_names import check_ros_arguments

__all__ = ['usage', 'params_files', 'check_command_line', 'regular_params_files',
           'program_name']

USAGE = """usage: ros2 run observer_ros {prog} --ros-args --params-file VEHICLE.yaml \\
           [-p NAME:=VALUE ...] [-r __ns:=/NAMESPACE] [-r FROM:=TO ...]
   or: python -m {module} --ros-args --params-file VEHICLE.yaml ...

VEHICLE.yaml is a vehicle file (config/submarine.yaml; installed under
$(ros2 pkg prefix observer_ros)/share/observer_ros/config/); its keys are described in
docs/vehicle_schema.md and by `ros2 param describe`. Launch files:
ros2 launch observer_ros closed_loop.launch.py vehicle:=submarine
"""


def usage(prog, module, doc):
    """Return the --help text of a node: usage, the params-file form, its topics."""
    return USAGE.format(prog=prog, module=module) + '\n' + (doc or '').strip() + '\n'


def params_files(argv):
    """Return the files a command line gives with ``--params-file``, in order."""
    return [argv[i + 1] for i, arg in enumerate(argv[:-1]) if arg == '--params-file']


def check_command_line(argv, prog, module, doc):
    """
    Handle ``--help`` and check the params files; return an exit status, or None to go on.

    Parameters
    ----------
    argv : list of str
        The arguments after the program name (ROS arguments included).
    prog, module : str
        The executable's name and its module (for the usage).
    doc : str
        The node's description (its module docstring: what it subscribes and publishes).

    """
    own = argv[:argv.index('--ros-args')] if '--ros-args' in argv else argv
    if '-h' in own or '--help' in own:
        print(usage(prog, module, doc))
        return 0
    try:
        check_ros_arguments(argv)
        for path in params_files(argv):
            check_parameters_file(path)
    except ObserverError as err:
        print(f'error: {err}', file=sys.stderr)
        return 2
    return None


def regular_params_files(argv):
    """
    Return ``argv`` with each ``--params-file`` that is a pipe replaced by a regular copy.

    A pipe (``--params-file <(cat v.yaml)``) is read once, by the package's loader
    (:func:`check_command_line`); rclpy then reads the copy. Call after
    :func:`check_command_line`.
    """
    out = list(argv)
    for i, arg in enumerate(out[:-1]):
        if arg == '--params-file':
            out[i + 1] = str(regular_file(out[i + 1]))
    return out


def program_name(default):
    """Return the executable's name (``observer``), or ``default`` under ``python -m``."""
    name = os.path.basename(sys.argv[0]) if sys.argv and sys.argv[0] else ''
    return default if not name or name.endswith('.py') or name == '-c' else name
