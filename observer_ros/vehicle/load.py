# observer_ros.vehicle.load: the one loader of vehicle files, for nodes and offline tools alike.
"""
Load and check a vehicle: a ROS 2 parameters file, or a node's parameters.

Offline tools call :func:`load_vehicle`; nodes pass their own parameters (plain Python
values) to :func:`vehicle_from_parameters`. Both end in the same checks, and every
refusal is a :class:`VehicleFileError` whose message starts with the offending
parameter's name. No ROS imports: this module is used offline too.

"""

import re

import numpy as np

from .checker import Checker, warn_unknown, warn_unloadable_strings, warn_unused
from .overrides import apply_overrides
from .schema import KNOWN_KEYS, MAX_RATE_HZ, SENSOR_KEYS
from .units import read_units
from ..core.errors import ObserverError, VehicleFileError
from ..core.model import Plant
from ..core.spec import ControllerSpec, ObserverSpec, SensorSpec, SimulatorSpec, Vehicle
from ..params_file import load_parameters
from ..sensors import parse_field

__all__ = ['load_vehicle', 'vehicle_from_parameters']

_NAME_RE = re.compile(r'^[A-Za-z0-9_.-]+$')
_SENSOR_NAME_RE = re.compile(r'^[A-Za-z_][A-Za-z0-9_]*$')
_TOPIC_TOKEN_RE = re.compile(r'^(?:[A-Za-z_][A-Za-z0-9_]*|\{[A-Za-z_]+\})$')


def load_vehicle(path, node_name=None, overrides=None, extra_keys=()):
    """
    Load and check a vehicle file.

    Parameters
    ----------
    path : str or path-like
        A ROS 2 parameters file (``config/submarine.yaml``).
    node_name : str, optional
        Also merge the section of this node over ``/**`` (see :func:`load_parameters`).
    overrides : dict or list of str, optional
        Applied after reading, as by :func:`apply_overrides` (``["observer.type:=kalman"]``).
    extra_keys : sequence of str
        Further parameter names that are not warned about (a node's own parameters).

    Returns
    -------
    vehicle : Vehicle
        With ``warnings`` for unknown or unused keys.

    Raises
    ------
    VehicleFileError
        The file cannot be read or is invalid; the message names the file and field.

    """
    flat = load_parameters(path, node_name)
    if overrides:
        flat = apply_overrides(flat, overrides)
    return vehicle_from_parameters(flat, source=str(path), extra_keys=extra_keys)


def vehicle_from_parameters(flat, source='', extra_keys=()):
    """
    Build and check a vehicle from flat parameters.

    Parameters
    ----------
    flat : mapping
        Dotted parameter names (``model.A``) to plain values: str, bool, int, float, or
        lists (also ``array.array`` and 1-D numpy arrays, as rclpy gives) of those. A
        value of None counts as absent (an unset ROS parameter).
    source : str
        Where the parameters come from (a file path, a node name); prefixed to errors.
    extra_keys : sequence of str
        Further names that are not warned about (a node's own parameters).
        ``use_sim_time`` and other ROS parameters are never warned about.

    Returns
    -------
    vehicle : Vehicle
        Checked for structure: shapes, types, names, sensors covering each output once,
        poles in conjugate pairs. Observability and controllability are the design's.

    Raises
    ------
    VehicleFileError
        The message starts with the source and the parameter name
        (``model.C: has 4 values; expected 3 (outputs x states = 1x3)``).

    """
    prefix = f'{source}: ' if source else ''
    try:
        items = list(flat.items())
    except AttributeError:
        raise VehicleFileError(f'{prefix}parameters must be a dict; got '
                               f'{type(flat).__name__}') from None
    for key, _ in items:
        if not isinstance(key, str) or not key:
            raise VehicleFileError(f'{prefix}parameter name {key!r} is not a string')
    flat = {key: value for key, value in items if value is not None}
    check = Checker(flat, source)
    warnings = []

    sensor_names = check.string_array('sensors.names')
    for name in sensor_names:
        if not _SENSOR_NAME_RE.match(name) or name == 'names':
            check.fail('sensors.names', f'sensor name {name!r} must be letters, digits and _, '
                       "and not 'names' (it is part of parameter names)")
    warn_unknown(flat, sensor_names, set(extra_keys), warnings)
    warn_unloadable_strings(flat, warnings)

    # vehicle
    name = check.string('vehicle.name')
    if not _NAME_RE.match(name):
        check.fail('vehicle.name', f'{name!r} may hold only letters, digits, _ . and -')
    description = check.string('vehicle.description', allow_empty=True)
    source_text = check.string('vehicle.source', allow_empty=True)
    base_frame = check.string('vehicle.base_frame')

    plant, discrete = _read_model(check, warnings)
    sensors = _read_sensors(check, plant, sensor_names)
    simulator = _read_simulator(check, plant, discrete)
    controller = _read_controller(check, plant, discrete)
    observer = _read_observer(check, plant, discrete, sensors, simulator, warnings)
    state_units, input_units, output_units = read_units(check, plant, sensors)
    return Vehicle(name=name, plant=plant, sensors=sensors, observer=observer,
                   controller=controller, simulator=simulator, description=description,
                   source=source_text, base_frame=base_frame, warnings=tuple(warnings),
                   origin=source,
                   state_units=state_units, input_units=input_units,
                   output_units=output_units)


def _read_model(check, warnings):
    domain = check.string('model.time_domain')
    discrete = domain == 'discrete'
    dt = None
    if discrete:
        dt = check.double('model.sample_time', required=True)
    else:
        warn_unused(check, ['model.sample_time'], 'by a continuous model', warnings)
    states = check.string_array('model.states')
    inputs = check.string_array('model.inputs')
    outputs = check.string_array('model.outputs')
    n, m, p = len(states), len(inputs), len(outputs)
    A = check.matrix('model.A', n, n, ('states', 'states'))
    B = check.matrix('model.B', n, m, ('states', 'inputs'))
    C = check.matrix('model.C', p, n, ('outputs', 'states'))
    D = check.matrix('model.D', p, m, ('outputs', 'inputs'))
    try:
        plant = Plant(A, B, C, D, dt, states, inputs, outputs)
    except ObserverError as err:   # pre-checked above; kept as a safety net
        check.fail('model', str(err))
    return plant, discrete


def _read_sensors(check, plant, sensor_names):
    specs = []
    owner = {}          # output -> sensor
    topics = {}         # topic -> sensor
    for sensor in sensor_names:
        key = f'sensors.{sensor}.'

        def spec(sub):
            return SENSOR_KEYS[sub]

        topic = check.string(key + 'topic', spec('topic'))
        if not _valid_topic(topic):
            check.fail(key + 'topic', f'{topic!r} is not a valid ROS topic name')
        if topic in topics:
            check.fail(key + 'topic', f'topic {topic!r} is already used by sensor '
                       f'{topics[topic]}')
        topics[topic] = sensor
        msg_type = check.string(key + 'type', spec('type'))
        fields = check.string_array(key + 'fields', spec('fields'))
        for field in fields:
            try:
                parse_field(msg_type, field)
            except VehicleFileError as err:
                check.fail(key + 'fields', str(err))
        outputs = check.string_array(key + 'outputs', spec('outputs'))
        if len(outputs) != len(fields):
            check.fail(key + 'outputs', f'has {len(outputs)} names; expected '
                       f'{len(fields)} (one per field in {key}fields)')
        for output in outputs:
            if output not in plant.output_names:
                check.fail(key + 'outputs', f'unknown output {output!r}; outputs are '
                           f'[{", ".join(plant.output_names)}]')
            if output in owner:
                check.fail(key + 'outputs', f'output {output!r} is already measured by '
                           f'sensor {owner[output]}; each output has exactly one sensor')
            owner[output] = sensor
        noise = check.double_array(key + 'noise_std', spec('noise_std'))
        if len(noise) != len(fields):
            check.fail(key + 'noise_std', f'has {len(noise)} values; expected '
                       f'{len(fields)} (one per field in {key}fields)')
        timeout = check.double(key + 'timeout', spec('timeout'))
        divider = check.integer(key + 'rate_divider', spec('rate_divider'))
        frame_id = check.string(key + 'frame_id', spec('frame_id'))
        specs.append(SensorSpec(name=sensor, topic=topic, msg_type=msg_type, fields=fields,
                                outputs=outputs, noise_std=np.array(noise), timeout=timeout,
                                rate_divider=divider, frame_id=frame_id))
    missing = [output for output in plant.output_names if output not in owner]
    if missing:
        check.fail('model.outputs', f'output {missing[0]!r} is measured by no sensor (list '
                   "it in one sensor's outputs)")
    return tuple(specs)


def _valid_topic(topic):
    """Check a topic name against the ROS 2 rules (tokens of [A-Za-z0-9_], ~/ or /)."""
    if topic.startswith('~/'):
        name = topic[2:]
    elif topic.startswith('/'):
        name = topic[1:]
    else:
        name = topic
    if not name or name.endswith('/'):
        return False
    return all(_TOPIC_TOKEN_RE.match(token) for token in name.split('/'))


def _read_simulator(check, plant, discrete):
    n = plant.n
    if discrete:
        rate = 1.0 / plant.dt      # model.sample_time is within its bound
        if check.given('simulator.rate_hz'):
            given = check.double('simulator.rate_hz')
            if abs(given - rate) > 1e-9 * rate:
                check.fail('simulator.rate_hz', f'{given} Hz does not match model.sample_time '
                           f'{plant.dt} s (a discrete model runs at 1/sample_time = '
                           f'{rate:g} Hz)')
    else:
        rate = check.double('simulator.rate_hz')
    initial = check.vector('simulator.initial_state', n, 'states')
    duration = check.double('simulator.duration')
    if 0.0 < duration * rate < 1.0:
        check.fail('simulator.duration', f'{duration} s is shorter than one step '
                   f'(1/{rate:g} Hz)')
    seed = check.integer('simulator.seed')
    noise = check.boolean('simulator.noise')
    process = check.vector('simulator.process_noise_std', n, 'states')
    mode = check.string('simulator.mode')
    factor = check.double('simulator.realtime_factor')
    if mode == 'realtime' and rate * factor > MAX_RATE_HZ:
        check.fail('simulator.realtime_factor', f'{factor:g} steps {rate:g} Hz at '
                   f'{rate * factor:g} Hz of wall time, more than the {MAX_RATE_HZ:g} Hz a '
                   "node's timer can do here")
    timeout = check.double('simulator.command_timeout')
    publish_clock = check.boolean('simulator.publish_clock')
    return SimulatorSpec(rate_hz=rate, initial_state=np.zeros(n) if initial is None else
                         initial, duration=duration, seed=seed, noise=noise,
                         process_noise_std=process, mode=mode, realtime_factor=factor,
                         command_timeout=timeout, publish_clock=publish_clock)


def _read_controller(check, plant, discrete):
    n, m = plant.n, plant.m
    options = [key for key in ('controller.poles', 'controller.K', 'controller.lqr_Q')
               if check.double_array(key) is not None]
    if check.given('controller.lqr_R') and check.double_array('controller.lqr_R') is not None \
            and 'controller.lqr_Q' not in options:
        check.fail('controller.lqr_Q', 'missing (required with controller.lqr_R)')
    if not options:
        check.fail('controller.poles', 'missing: give one of controller.poles, controller.K '
                   'or controller.lqr_Q with controller.lqr_R')
    if len(options) > 1:
        check.fail(options[1], f'give only one of controller.poles, controller.K and '
                   f'controller.lqr_Q/lqr_R (got {" and ".join(options)})')
    # the observer's rule: at most n here; the design asks for exactly one per
    # controllable mode (n for a controllable plant) and names the count
    poles = check.poles('controller', n, False, 'one per controllable mode', discrete)
    K = check.matrix('controller.K', m, n, ('inputs', 'states'))
    Q = R = None
    if options[0] == 'controller.lqr_Q':
        Q = check.matrix('controller.lqr_Q', n, n, ('states', 'states'))
        R = check.matrix('controller.lqr_R', m, m, ('inputs', 'inputs'), required=True)
        Q = check.symmetric('controller.lqr_Q', Q, definite=False)
        R = check.symmetric('controller.lqr_R', R, definite=True)
    reference = check.vector('controller.reference', n, 'states')
    Kd = check.matrix('controller.Kd', m, n, ('inputs', 'states'))
    u_min = check.vector('controller.u_min', m, 'inputs', allow_inf=True)
    u_max = check.vector('controller.u_max', m, 'inputs', allow_inf=True)
    if u_min is not None and u_max is not None:
        bad = np.nonzero(~(u_min < u_max))[0]
        if bad.size:
            i = int(bad[0])
            check.fail('controller.u_max', f'{plant.input_names[i]}: u_max {u_max[i]} is '
                       f'not above u_min {u_min[i]}')
    safe = check.string('controller.safe_command')
    stale = check.double('controller.stale_timeout')
    predict = check.double('controller.predict_timeout')
    delay = check.boolean('controller.delay_compensation')
    return ControllerSpec(poles=poles, K=K, lqr_Q=Q, lqr_R=R, reference=reference, Kd=Kd,
                          u_min=u_min, u_max=u_max, safe_command=safe, stale_timeout=stale,
                          predict_timeout=predict, delay_compensation=delay)


def _read_observer(check, plant, discrete, sensors, simulator, warnings):
    n, p = plant.n, plant.p
    kind = check.string('observer.type')
    poles = gain = Qd = Rd = Bd = None
    method = KNOWN_KEYS['observer.method'].default
    design_keys = ['observer.poles', 'observer.poles_imag', 'observer.gain',
                   'observer.method']
    kalman_keys = ['observer.Qd', 'observer.Rd', 'observer.Bd']
    if kind in ('full', 'reduced'):
        warn_unused(check, kalman_keys, f'by a {kind} observer', warnings)
        if kind == 'reduced' and p >= n:
            check.fail('observer.type', f'a reduced observer needs fewer outputs than '
                       f'states (p = {p}, n = {n})')
        method = check.string('observer.method')
        rows, label = (n, 'states') if kind == 'full' else (n - p, 'states - outputs')
        has_poles = check.double_array('observer.poles') is not None
        has_gain = check.double_array('observer.gain') is not None
        if has_poles and has_gain:
            check.fail('observer.gain', 'give either observer.poles or observer.gain, '
                       'not both')
        if not has_poles and not has_gain:
            check.fail('observer.poles', f'missing: a {kind} observer needs observer.poles '
                       'or observer.gain')
        if has_poles:
            what = 'n for a full observer' if kind == 'full' else \
                'n - p for a reduced observer'
            poles = check.poles('observer', rows, False, what, discrete)
        else:
            if check.given('observer.poles_imag'):
                check.fail('observer.poles_imag', 'given without observer.poles')
            gain = check.matrix('observer.gain', rows, p, (label, 'outputs'))
    elif kind == 'kalman':
        warn_unused(check, design_keys, 'by a kalman observer', warnings)
        Bd = check.double_array('observer.Bd')
        if Bd is not None:
            if len(Bd) % n:
                check.fail('observer.Bd', f'has {len(Bd)} values; expected a multiple of '
                           f'{n} (states x k)')
            k = len(Bd) // n
            Bd = np.array(Bd).reshape(n, k)
        else:
            k = n
        if check.double_array('observer.Qd') is not None:
            Qd = check.matrix('observer.Qd', k, k, ('k', 'k') if Bd is not None else
                              ('states', 'states'))
        elif Bd is None and simulator.process_noise_std is not None and \
                np.all(simulator.process_noise_std > 0.0):
            Qd = np.diag(simulator.process_noise_std ** 2)
        else:
            check.fail('observer.Qd', 'missing: a kalman observer needs observer.Qd (the '
                       'default, diag(simulator.process_noise_std**2), needs all of them > 0 '
                       'and no observer.Bd)')
        Qd = check.symmetric('observer.Qd', Qd, definite=False)
        if check.double_array('observer.Rd') is not None:
            Rd = check.matrix('observer.Rd', p, p, ('outputs', 'outputs'))
        else:
            std = np.zeros(p)
            for sensor in sensors:
                std[list(plant.output_rows(sensor.outputs))] = sensor.noise_std
            if not np.all(std > 0.0):
                check.fail('observer.Rd', 'missing: a kalman observer needs observer.Rd '
                           '(the default, diag(noise_std**2) of the sensors, needs every '
                           'noise_std > 0)')
            Rd = np.diag(std ** 2)
        Rd = check.symmetric('observer.Rd', Rd, definite=True)
    else:   # open_loop
        warn_unused(check, design_keys + kalman_keys, 'by an open_loop observer', warnings)
    initial = check.vector('observer.initial_estimate', n, 'states')
    rate = check.double('observer.rate_hz')
    history = check.double('observer.history_length')
    publish_rate = check.double('observer.publish_rate_hz')
    fastest = max(simulator.rate_hz / s.rate_divider for s in sensors)
    for key, value in (('observer.rate_hz', rate), ('observer.publish_rate_hz', publish_rate)):
        if value is not None and value > fastest * (1.0 + 1e-12):
            check.fail(key, f'{value:g} Hz is faster than the fastest sensor ({fastest:g} Hz: '
                       'simulator.rate_hz / its rate_divider); a timer faster than the data '
                       'adds no information')
    return ObserverSpec(kind=kind, poles=poles, gain=gain, method=method, Qd=Qd, Rd=Rd,
                        Bd=Bd, initial_estimate=initial, rate_hz=rate,
                        history_length=history, publish_rate_hz=publish_rate)
