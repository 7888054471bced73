# observer_ros.vehicle.write: a vehicle back to flat parameters and to a parameters file.
"""Write a vehicle as flat parameters (:func:`vehicle_to_parameters`) and as YAML."""

import numpy as np
import yaml

from ..core.errors import VehicleFileError
from ..params_file import ROS_BOOL_RE


class _Dumper(yaml.SafeDumper):
    """
    A safe dumper for ROS parameter files.

    It quotes a string ROS's parser would read as a boolean (``N``) and never writes a YAML
    alias (ROS's parser refuses them: "Will not support aliasing").
    """

    def ignore_aliases(self, data):
        return True


_Dumper.add_implicit_resolver('tag:yaml.org,2002:bool', ROS_BOOL_RE, list('yYnN'))

__all__ = ['parameters_to_yaml', 'vehicle_to_parameters']


def parameters_to_yaml(flat, node_key='/**'):
    """
    Write a flat parameter dict as a ROS 2 parameters file.

    Parameters
    ----------
    flat : dict
        Dotted names to plain values (as :func:`vehicle_to_parameters` gives).
    node_key : str
        The section key; ``/**`` applies to every node.

    Returns
    -------
    text : str
        YAML for ``--params-file`` and :func:`load_vehicle`.

    """
    tree = {}
    for name, value in flat.items():
        node = tree
        parts = name.split('.')
        for part in parts[:-1]:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise VehicleFileError(f'{name}: its prefix is also a parameter')
        if parts[-1] in node and isinstance(node[parts[-1]], dict):
            raise VehicleFileError(f'{name}: is also a prefix of other parameters')
        node[parts[-1]] = value
    return yaml.dump({node_key: {'ros__parameters': tree}}, Dumper=_Dumper, sort_keys=False,
                     default_flow_style=None, width=99)


def _floats(values):
    return [float(v) for v in np.asarray(values, dtype=float).reshape(-1)]


def _put_poles(flat, prefix, poles):
    poles = np.asarray(poles, dtype=complex).reshape(-1)
    flat[f'{prefix}.poles'] = _floats(poles.real)
    if np.any(poles.imag != 0.0):
        flat[f'{prefix}.poles_imag'] = _floats(poles.imag)


def vehicle_to_parameters(vehicle):
    """
    Return the flat parameters that describe a vehicle (inverse of the loader).

    Parameters
    ----------
    vehicle : Vehicle
        The vehicle to describe.

    Returns
    -------
    flat : dict
        Dotted names to plain Python values (str, bool, int, lists of float or str):
        ``vehicle_from_parameters(vehicle_to_parameters(v))`` describes the same vehicle.
        Optional parameters that are unset are left out; defaults are written.

    """
    plant = vehicle.plant
    flat = {'vehicle.name': vehicle.name}
    if vehicle.description:
        flat['vehicle.description'] = vehicle.description
    if vehicle.source:
        flat['vehicle.source'] = vehicle.source
    if vehicle.base_frame != 'base_link':
        flat['vehicle.base_frame'] = vehicle.base_frame
    if plant.is_discrete:
        flat['model.time_domain'] = 'discrete'
        flat['model.sample_time'] = float(plant.dt)
    else:
        flat['model.time_domain'] = 'continuous'
    flat['model.states'] = list(plant.state_names)
    flat['model.inputs'] = list(plant.input_names)
    flat['model.outputs'] = list(plant.output_names)
    for kind in ('state', 'input', 'output'):
        units = getattr(vehicle, f'{kind}_units')
        if units and all(units):
            flat[f'model.{kind}_units'] = list(units)
    for key in 'ABCD':
        flat[f'model.{key}'] = _floats(getattr(plant, key))
    flat['sensors.names'] = [s.name for s in vehicle.sensors]
    for s in vehicle.sensors:
        key = f'sensors.{s.name}.'
        flat[key + 'topic'] = s.topic
        flat[key + 'type'] = s.msg_type
        flat[key + 'fields'] = list(s.fields)
        flat[key + 'outputs'] = list(s.outputs)
        flat[key + 'noise_std'] = _floats(s.noise_std)
        flat[key + 'timeout'] = float(s.timeout)
        flat[key + 'rate_divider'] = int(s.rate_divider)
        flat[key + 'frame_id'] = s.frame_id
    o = vehicle.observer
    flat['observer.type'] = o.kind
    if o.poles is not None:
        _put_poles(flat, 'observer', o.poles)
    for key in ('gain', 'Qd', 'Rd', 'Bd', 'initial_estimate'):
        if getattr(o, key) is not None:
            flat[f'observer.{key}'] = _floats(getattr(o, key))
    if o.kind in ('full', 'reduced'):
        flat['observer.method'] = o.method
    if o.rate_hz is not None:
        flat['observer.rate_hz'] = float(o.rate_hz)
    flat['observer.history_length'] = float(o.history_length)
    if o.publish_rate_hz is not None:
        flat['observer.publish_rate_hz'] = float(o.publish_rate_hz)
    c = vehicle.controller
    if c.poles is not None:
        _put_poles(flat, 'controller', c.poles)
    for key in ('K', 'lqr_Q', 'lqr_R', 'reference', 'Kd', 'u_min', 'u_max'):
        if getattr(c, key) is not None:
            flat[f'controller.{key}'] = _floats(getattr(c, key))
    flat['controller.safe_command'] = c.safe_command
    flat['controller.stale_timeout'] = float(c.stale_timeout)
    flat['controller.predict_timeout'] = float(c.predict_timeout)
    flat['controller.delay_compensation'] = bool(c.delay_compensation)
    sim = vehicle.simulator
    if not plant.is_discrete:
        flat['simulator.rate_hz'] = float(sim.rate_hz)
    flat['simulator.initial_state'] = _floats(sim.initial_state)
    flat['simulator.duration'] = float(sim.duration)
    flat['simulator.seed'] = int(sim.seed)
    flat['simulator.noise'] = bool(sim.noise)
    if sim.process_noise_std is not None:
        flat['simulator.process_noise_std'] = _floats(sim.process_noise_std)
    flat['simulator.mode'] = sim.mode
    flat['simulator.realtime_factor'] = float(sim.realtime_factor)
    flat['simulator.command_timeout'] = float(sim.command_timeout)
    flat['simulator.publish_clock'] = bool(sim.publish_clock)
    return flat
