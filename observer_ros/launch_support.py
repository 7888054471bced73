# observer_ros.launch_support: what the package's launch files share (no launch import).
"""
Helpers of launch/*.launch.py: find a vehicle file, read remaps, the nodes' parameters.

Kept in the package (not in the launch files) so that they are tested like the rest and
both launch files use the same rules. Imports neither ``launch`` nor ``rclpy``.

"""

import os
from pathlib import Path

from .core.errors import ObserverError
from .params_file import regular_file
from .ros_names import check_namespace, check_topic_name

__all__ = ['namespace_argument', 'vehicle_file', 'check_vehicle', 'parse_remaps', 'as_bool']

PACKAGE = 'observer_ros'


def vehicle_file(vehicle, share=None):
    """
    Return the vehicle file that ``vehicle`` names.

    Parameters
    ----------
    vehicle : str
        A file (``~/robots/sub.yaml``, anything with a ``/`` or ending in ``.yaml``) or
        the name of one of the package's vehicles (``submarine``: ``config/submarine.yaml``
        under the package's share directory).
    share : str or Path, optional
        The package's share directory (default: from ament_index).

    Returns
    -------
    str
        An absolute path to an existing regular file: the file, or for a pipe
        (``vehicle:=<(cat v.yaml)``) a copy of its text that the launch's nodes can each
        read (deleted when the launch exits).

    Raises
    ------
    ObserverError
        The file does not exist; for a name, the package's vehicles are listed.

    """
    vehicle = vehicle.strip()
    if not vehicle:
        raise ObserverError('vehicle: empty; give a vehicle name (submarine) or a file')
    if '/' in vehicle or vehicle.endswith(('.yaml', '.yml')):
        # not resolved: /dev/fd/63 (<(cat v.yaml)) resolves to a name that is no file
        path = Path(os.path.abspath(os.path.expanduser(vehicle)))
        if not path.exists():
            raise ObserverError(f'vehicle: {vehicle}: no such file')
        # a pipe is read once, here; every node reads the regular copy. A folder or a
        # device is refused unopened, naming what it is
        return str(regular_file(path))
    if share is None:
        from ament_index_python.packages import get_package_share_directory
        share = get_package_share_directory(PACKAGE)
    config = Path(share) / 'config'
    path = config / f'{vehicle}.yaml'
    if not path.is_file():
        known = sorted(p.stem for p in config.glob('*.yaml'))
        raise ObserverError(f"vehicle: {vehicle!r} is not one of the package's vehicles "
                            f'{known} nor a file')
    return str(path)


def check_vehicle(path, overrides=()):
    """
    Load and design the vehicle of a launch before any node starts; return it.

    A file the nodes could not use stops the launch with one error naming the field
    (``ros2 launch`` exits 1), rather than each node exiting with the same error.

    Parameters
    ----------
    path : str
        The vehicle file (:func:`vehicle_file`).
    overrides : sequence of str
        ``name:=value`` parameters the launch gives the nodes (``simulator.mode:=lockstep``).

    Raises
    ------
    ObserverError
        The file, an override or the design refused, naming the field.

    """
    from .core.vehicle_design import design_vehicle
    from .vehicle import load_vehicle
    vehicle = load_vehicle(path, overrides=list(overrides))
    design_vehicle(vehicle)
    return vehicle


def parse_remaps(text):
    """
    Read ``from:=to`` remaps separated by commas or spaces.

    Parameters
    ----------
    text : str
        For example ``imu/data:=/robot/imu,control/u:=/robot/cmd``.

    Returns
    -------
    list of tuple
        ``[(from, to), ...]``, as launch_ros's ``remappings`` takes them.

    """
    remaps = []
    for item in text.replace(',', ' ').split():
        source, sep, target = item.partition(':=')
        if not sep or not source or not target:
            raise ObserverError(f'remaps: {item!r} is not FROM:=TO')
        for name in (source, target):
            check_topic_name(name, 'remaps:')
        remaps.append((source, target))
    return remaps


def namespace_argument(text):
    """
    Return a launch file's ``namespace`` argument checked by ROS's rules ('' for none).

    ``sub2`` becomes ``/sub2``; a namespace rcl would refuse (``/véhicule_1``) is refused
    here, before any node starts, in one line naming the character.
    """
    return check_namespace(text, 'namespace:=') if text else ''


def as_bool(text, name):
    """Return a launch argument's ``true``/``false`` as a bool; refuse anything else."""
    value = str(text).strip().lower()
    if value in ('true', '1', 'yes'):
        return True
    if value in ('false', '0', 'no'):
        return False
    raise ObserverError(f'{name}: {text!r} is not true or false')
