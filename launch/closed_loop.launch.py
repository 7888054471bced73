# Closed loop of one vehicle: plant_simulator, observer, compensator (and the recorder).
"""
Launch one vehicle's closed loop.

ros2 launch observer_ros closed_loop.launch.py vehicle:=submarine mode:=realtime
ros2 launch observer_ros closed_loop.launch.py vehicle:=submarine namespace:=sub2 \\
    publish_clock:=false          # a second vehicle: the first one owns /clock

Arguments: vehicle (a name from the package's config/ or a file), mode (lockstep or
realtime), namespace, record (true: the recorder writes a bag to `bag`), publish_clock (this
vehicle's simulator publishes /clock; one per ROS graph), use_sim_time, duration (0: the
simulator runs until stopped), autostart (false: the observer and the compensator wait
unconfigured for `ros2 lifecycle set`).

The vehicle file is loaded and designed before anything starts. The observer, then the
compensator, are configured and activated in order (managed nodes); the simulator starts
once both are active. When the simulator completes its run the launch shuts down; a node
that exits with a status other than 0 stops the launch with an error (exit status 1).
Ctrl-C stops every node (each exits 0).
"""

from datetime import datetime

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node
from observer_ros.launch_lifecycle import BringUp, exit_handlers, node_path
from observer_ros.launch_support import (as_bool, check_vehicle, namespace_argument,
                                        vehicle_file)

ARGUMENTS = (
    ('vehicle', 'submarine', "a vehicle of the package's config/ (submarine, pitch_imu, ...) "
     'or a vehicle file'),
    ('mode', 'realtime', 'lockstep (reproducible, waits for each command) or realtime'),
    ('namespace', '', 'namespace of every node and topic of this vehicle (sub2)'),
    ('record', 'false', 'true: run the recorder, writing the bag `bag`'),
    ('bag', '', 'bag directory to create (default bags/runs/<vehicle>_<time>)'),
    ('publish_clock', 'true', 'the simulator publishes /clock: true for exactly one '
     'vehicle of a ROS graph'),
    ('use_sim_time', 'true', 'the observer, compensator and recorder follow /clock'),
    ('duration', '', "s of simulated time (default: the vehicle file's); 0: until Ctrl-C"),
    ('autostart', 'true', 'configure and activate the observer and the compensator in order '
     '(false: they wait unconfigured for `ros2 lifecycle set`; the simulator starts once '
     'both are active)'),
)


def _nodes(context):
    def arg(name):
        return LaunchConfiguration(name).perform(context)

    path = vehicle_file(arg('vehicle'))
    mode = arg('mode')
    if mode not in ('lockstep', 'realtime'):
        raise ValueError(f'mode: {mode!r} is not lockstep or realtime')
    record = as_bool(arg('record'), 'record')
    sim_time = as_bool(arg('use_sim_time'), 'use_sim_time')
    autostart = as_bool(arg('autostart'), 'autostart')
    namespace = namespace_argument(arg('namespace'))
    common = {'simulator.mode': mode}
    simulator = dict(common, **{
        'simulator.publish_clock': as_bool(arg('publish_clock'), 'publish_clock')})
    if arg('duration'):
        simulator['simulator.duration'] = float(arg('duration'))
    vehicle = check_vehicle(path, [f'{k}:={v}' for k, v in simulator.items()])
    peers = dict(common, use_sim_time=sim_time)
    managed = dict(peers, autostart=False)      # brought up here, in order
    nodes = [Node(package='observer_ros', executable=name, name=name, namespace=namespace,
                  parameters=[path, managed], output='screen')
             for name in ('observer', 'compensator')]
    if record:
        bag = arg('bag') or datetime.now().strftime(f'bags/runs/{vehicle.name}_%Y%m%d_%H%M%S')
        nodes.append(Node(package='observer_ros', executable='recorder', namespace=namespace,
                          parameters=[path, dict(peers, output=bag)], output='screen'))
        if mode == 'lockstep':      # start once the recorder reads every sensor too
            simulator.update(wait_for_subscribers=2, wait_for_recorder=True)
    sim = Node(package='observer_ros', executable='plant_simulator', namespace=namespace,
               parameters=[path, simulator], output='screen')
    bring_up = BringUp([node_path(namespace, 'observer'), node_path(namespace, 'compensator')],
                       autostart=autostart, then=[sim])
    return nodes + [bring_up] + exit_handlers(nodes + [sim], simulator=sim)


def generate_launch_description():
    """Return the closed loop of one vehicle."""
    return LaunchDescription(
        [DeclareLaunchArgument(name, default_value=default, description=text)
         for name, default, text in ARGUMENTS] + [OpaqueFunction(function=_nodes)])
