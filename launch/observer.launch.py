# The observer alone, at a real robot's sensors (or a bag being played).
"""
Launch the observer for a real robot.

ros2 launch observer_ros observer.launch.py vehicle:=/path/robot.yaml \\
    remaps:="imu/data:=/robot/imu control/u:=/robot/cmd"

Arguments: vehicle (a name from the package's config/ or a file), namespace, remaps
(FROM:=TO pairs, separated by spaces or commas: the vehicle's sensor topics, control/u,
state/estimate, ...), use_sim_time (false on a robot; true when a bag is played with
--clock), autostart (false: the observer waits unconfigured for `ros2 lifecycle set`).
The observer runs free (simulator.mode realtime): it never waits for commands. The
vehicle file is loaded and designed before the node starts; the node is a managed node,
configured and activated by the launch; if it exits with a status other than 0 the launch
stops with an error (exit status 1).
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node
from observer_ros.launch_lifecycle import BringUp, exit_handlers, node_path
from observer_ros.launch_support import (as_bool, check_vehicle, namespace_argument,
                                        parse_remaps, vehicle_file)

ARGUMENTS = (
    ('vehicle', 'submarine', "a vehicle of the package's config/ or the robot's vehicle file"),
    ('namespace', '', 'namespace of the node and its relative topics'),
    ('remaps', '', 'FROM:=TO topic remaps, e.g. "imu/data:=/robot/imu control/u:=/cmd"'),
    ('use_sim_time', 'false', 'follow /clock (a played bag) instead of the system clock'),
    ('autostart', 'true', 'configure and activate the observer (false: it waits '
     'unconfigured for `ros2 lifecycle set`)'),
)


def _nodes(context):
    def arg(name):
        return LaunchConfiguration(name).perform(context)

    path = vehicle_file(arg('vehicle'))
    check_vehicle(path, ['simulator.mode:=realtime'])
    parameters = {'simulator.mode': 'realtime', 'autostart': False,
                  'use_sim_time': as_bool(arg('use_sim_time'), 'use_sim_time')}
    namespace = namespace_argument(arg('namespace'))
    observer = Node(package='observer_ros', executable='observer', name='observer',
                    namespace=namespace, parameters=[path, parameters],
                    remappings=parse_remaps(arg('remaps')), output='screen')
    return [observer, BringUp([node_path(namespace, 'observer')],
                              autostart=as_bool(arg('autostart'), 'autostart'))] + \
        exit_handlers([observer])


def generate_launch_description():
    """Return the observer node for a real robot."""
    return LaunchDescription(
        [DeclareLaunchArgument(name, default_value=default, description=text)
         for name, default, text in ARGUMENTS] + [OpaqueFunction(function=_nodes)])
