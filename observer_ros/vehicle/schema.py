# observer_ros.vehicle.schema: every key of a vehicle file, its type, default and meaning.
"""
The vehicle schema: :data:`KNOWN_KEYS` and :data:`SENSOR_KEYS`.

Each key of a vehicle file is a :class:`KeySpec` (documented in docs/vehicle_schema.md);
:func:`known_keys` expands the per-sensor keys, :func:`parameter_schema` lists them as a
node declares them. No ROS imports: this module is used offline too.

"""

from dataclasses import dataclass
from typing import NamedTuple, Tuple

from ..core.spec import HISTORY_LENGTH, OBSERVER_TYPES, SENSOR_TYPES

__all__ = ['KeySpec', 'ParameterInfo', 'KNOWN_KEYS', 'SENSOR_KEYS', 'ROS_RESERVED_KEYS',
           'ROS_RESERVED_PREFIXES', 'known_keys', 'parameter_schema']

STRING = 'STRING'
STRING_ARRAY = 'STRING_ARRAY'
DOUBLE = 'DOUBLE'
DOUBLE_ARRAY = 'DOUBLE_ARRAY'
INTEGER = 'INTEGER'
BOOL = 'BOOL'


@dataclass(frozen=True)
class KeySpec:
    """
    One parameter of the vehicle schema.

    ``param_type`` is the name of the rclpy ``Parameter.Type`` member (``DOUBLE_ARRAY``,
    ...), so a node can declare it with ``Parameter.Type[spec.param_type]``. ``default``
    is None for a required parameter and for an optional one without a default.

    """

    name: str
    param_type: str
    description: str
    required: bool = False
    default: object = None
    choices: Tuple[str, ...] = ()
    minimum: object = None      # scalars: the least value (a node declares it as a range)


class ParameterInfo(NamedTuple):
    """A parameter as a node declares it: name, type, default (or None), description."""

    name: str
    param_type: str
    default: object
    description: str


def _keys(*specs):
    return {spec.name: spec for spec in specs}


KNOWN_KEYS = _keys(
    KeySpec('vehicle.name', STRING, 'short name (letters, digits, _ . -), used in bag and '
            'report names', required=True),
    KeySpec('vehicle.description', STRING, 'one line', default=''),
    KeySpec('vehicle.source', STRING, 'where the numbers come from (seed, paper)',
            default=''),
    KeySpec('model.time_domain', STRING, 'continuous or discrete', default='continuous',
            choices=('continuous', 'discrete')),
    KeySpec('model.sample_time', DOUBLE, 's; required (> 0) for a discrete model',
            minimum=0.0),
    KeySpec('model.states', STRING_ARRAY, 'state names (n)', required=True),
    KeySpec('model.inputs', STRING_ARRAY, 'input names (m)', required=True),
    KeySpec('model.outputs', STRING_ARRAY, 'output names (p)', required=True),
    KeySpec('model.A', DOUBLE_ARRAY, 'n x n, row-major', required=True),
    KeySpec('model.B', DOUBLE_ARRAY, 'n x m, row-major', required=True),
    KeySpec('model.C', DOUBLE_ARRAY, 'p x n, row-major', required=True),
    KeySpec('model.D', DOUBLE_ARRAY, 'p x m, row-major; default zeros'),
    KeySpec('sensors.names', STRING_ARRAY, 'the sensors; each has sensors.<name>.* keys',
            required=True),
    KeySpec('observer.type', STRING, 'full, reduced, open_loop or kalman', required=True,
            choices=OBSERVER_TYPES),
    KeySpec('observer.poles', DOUBLE_ARRAY, 'real parts of the observer poles'),
    KeySpec('observer.poles_imag', DOUBLE_ARRAY, 'imaginary parts; default all 0'),
    KeySpec('observer.gain', DOUBLE_ARRAY, 'L given directly: n x p (full) or '
            '(n-p) x p (reduced), row-major'),
    KeySpec('observer.method', STRING, 'pole placement: auto, place or acker',
            default='auto', choices=('auto', 'place', 'acker')),
    KeySpec('observer.Qd', DOUBLE_ARRAY, 'kalman: k x k process noise covariance; '
            'default diag(simulator.process_noise_std**2)'),
    KeySpec('observer.Rd', DOUBLE_ARRAY, 'kalman: p x p measurement noise covariance; '
            'default diag(noise_std**2) of the sensors'),
    KeySpec('observer.Bd', DOUBLE_ARRAY, 'kalman: n x k process noise input; '
            'default identity'),
    KeySpec('observer.initial_estimate', DOUBLE_ARRAY, 'x_hat(0) (n); default zeros'),
    KeySpec('observer.rate_hz', DOUBLE, 'Hz, prediction-only publish rate; default the '
            'simulator rate', minimum=0.0),
    KeySpec('observer.history_length', DOUBLE, 's, >= 0: late messages this much older '
            'than the estimate are used at their stamps (0: refused)', default=HISTORY_LENGTH,
            minimum=0.0),
    KeySpec('observer.publish_rate_hz', DOUBLE, 'Hz, > 0: also publish the estimate '
            'predicted to now at this rate (free-running); default off', minimum=0.0),
    KeySpec('controller.poles', DOUBLE_ARRAY, 'real parts of eig(A - B K) (n)'),
    KeySpec('controller.poles_imag', DOUBLE_ARRAY, 'imaginary parts; default all 0'),
    KeySpec('controller.K', DOUBLE_ARRAY, 'm x n, row-major'),
    KeySpec('controller.lqr_Q', DOUBLE_ARRAY, 'LQR state weight, n x n'),
    KeySpec('controller.lqr_R', DOUBLE_ARRAY, 'LQR input weight, m x m'),
    KeySpec('controller.reference', DOUBLE_ARRAY, 'x_d (n); default zeros'),
    KeySpec('controller.Kd', DOUBLE_ARRAY, 'feedforward, m x n; default zeros'),
    KeySpec('controller.u_min', DOUBLE_ARRAY, 'input lower limits (m); default none'),
    KeySpec('controller.u_max', DOUBLE_ARRAY, 'input upper limits (m); default none'),
    KeySpec('controller.safe_command', STRING, 'zero or hold', default='zero',
            choices=('zero', 'hold')),
    KeySpec('controller.stale_timeout', DOUBLE, 's, > 0', default=0.5, minimum=0.0),
    KeySpec('controller.predict_timeout', DOUBLE, 's, >= 0: predict-and-hold before the '
            'safe_command fallback', default=0.0, minimum=0.0),
    KeySpec('controller.delay_compensation', BOOL, 'realtime: predict a late estimate to '
            'when its command takes effect, and stamp the command with that time',
            default=False),
    KeySpec('simulator.rate_hz', DOUBLE, 'Hz, > 0; a discrete model runs at '
            '1/sample_time', default=100.0, minimum=0.0),
    KeySpec('simulator.initial_state', DOUBLE_ARRAY, 'x(0) (n); default zeros'),
    KeySpec('simulator.duration', DOUBLE, 's, >= 0; 0: the simulator node runs until '
            'stopped', default=10.0, minimum=0.0),
    KeySpec('simulator.seed', INTEGER, 'noise seed, >= 0', default=0, minimum=0),
    KeySpec('simulator.noise', BOOL, 'add the sensors noise_std', default=True),
    KeySpec('simulator.process_noise_std', DOUBLE_ARRAY, 'per state (n); default none'),
    KeySpec('simulator.mode', STRING, 'lockstep or realtime', default='lockstep',
            choices=('lockstep', 'realtime')),
    KeySpec('simulator.realtime_factor', DOUBLE, '> 0', default=1.0, minimum=0.0),
    KeySpec('simulator.command_timeout', DOUBLE, 's, > 0', default=2.0, minimum=0.0),
    KeySpec('simulator.publish_clock', BOOL, 'publish /clock (one vehicle per ROS graph)',
            default=True),
)

# Per-sensor keys: sensors.<s>.<key> for each <s> in sensors.names.
SENSOR_KEYS = _keys(
    KeySpec('topic', STRING, 'relative topic name', required=True),
    KeySpec('type', STRING, 'message type', required=True, choices=SENSOR_TYPES),
    KeySpec('fields', STRING_ARRAY, 'message fields read, one per output', required=True),
    KeySpec('outputs', STRING_ARRAY, 'the model outputs they are', required=True),
    KeySpec('noise_std', DOUBLE_ARRAY, 'noise standard deviation per field, >= 0',
            required=True),
    KeySpec('timeout', DOUBLE, 's, > 0', default=0.5, minimum=0.0),
    KeySpec('rate_divider', INTEGER, 'published every k-th simulator step, >= 1',
            default=1, minimum=1),
    KeySpec('frame_id', STRING, 'header.frame_id', default='base_link'),
)

# Parameters every ROS 2 node has; never vehicle keys, never warned about.
ROS_RESERVED_KEYS = ('use_sim_time', 'start_type_description_service')
ROS_RESERVED_PREFIXES = ('qos_overrides.',)


def known_keys(sensor_names=()):
    """
    Return the full schema for the given sensors.

    Parameters
    ----------
    sensor_names : sequence of str
        The entries of ``sensors.names``.

    Returns
    -------
    keys : dict
        Parameter name to :class:`KeySpec`, ``sensors.<s>.*`` expanded for each sensor.

    """
    keys = dict(KNOWN_KEYS)
    for sensor in sensor_names:
        for sub, spec in SENSOR_KEYS.items():
            name = f'sensors.{sensor}.{sub}'
            keys[name] = KeySpec(name, spec.param_type, spec.description, spec.required,
                                 spec.default, spec.choices, spec.minimum)
    return keys


def parameter_schema(sensor_names=()):
    """
    List the vehicle parameters as a node declares them.

    Parameters
    ----------
    sensor_names : sequence of str
        The entries of ``sensors.names`` (their ``sensors.<s>.*`` keys are included).

    Returns
    -------
    params : list of ParameterInfo
        ``(name, param_type, default, description)``; ``param_type`` names an rclpy
        ``Parameter.Type`` member; ``default`` is None where there is none (required
        parameters say so in the description).

    """
    out = []
    for spec in known_keys(sensor_names).values():
        text = spec.description + ('; required' if spec.required else '')
        out.append(ParameterInfo(spec.name, spec.param_type, spec.default, text))
    return out
