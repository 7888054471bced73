# observer_ros.vehicle.schema: every key of a vehicle file: type, default, unit, bound, meaning.
"""
The vehicle schema, the one source of every key, type, default, unit, bound and meaning.

:data:`KNOWN_KEYS` and :data:`SENSOR_KEYS` describe the vehicle file, :data:`NODE_KEYS`
the nodes' own parameters. The loader (:mod:`.checker`, :mod:`.load`), the ROS
``ParameterDescriptor`` of every parameter (``nodes/parameters.py``: description, range,
read-only) and the tables of docs/vehicle_schema.md (:mod:`.doc`) are all made from them.

Bounds are intervals in the key's unit: ``low``/``high`` (None: unbounded), ``low_open``
for a bound that excludes its value (``> 0``). ROS ranges are closed, so an open bound at
0 is given to ROS as the least positive double, 5e-324 (:func:`ros_range`): rclpy then
refuses 0 and every negative value and admits every positive one, as the loader does.
An open bound is allowed only at 0 (rclpy admits values within a relative 1e-6 of an
edge, which only at 0 is exactly the edge). An array's bound holds for each element.
No ROS imports: this module is used offline too.

"""

from dataclasses import dataclass, replace
import math
from typing import NamedTuple, Optional, Tuple

from ..core.estimators.admission import (CLOCK_JUMP_AGREEMENT, CLOCK_JUMP_TOLERANCE,
                                         FUTURE_TOLERANCE)
from ..core.spec import HISTORY_LENGTH, OBSERVER_TYPES, SENSOR_TYPES

__all__ = ['KeySpec', 'ParameterInfo', 'KNOWN_KEYS', 'SENSOR_KEYS', 'NODE_KEYS',
           'ROS_RESERVED_KEYS', 'ROS_RESERVED_PREFIXES', 'READ_ONLY_SECTIONS',
           'MAX_RATE_HZ', 'MIN_RATE_HZ', 'MAX_STATE_MAGNITUDE', 'known_keys',
           'parameter_schema', 'interval_text', 'bound_problem', 'ros_range', 'INT64_MAX']

STRING = 'STRING'
STRING_ARRAY = 'STRING_ARRAY'
DOUBLE = 'DOUBLE'
DOUBLE_ARRAY = 'DOUBLE_ARRAY'
INTEGER = 'INTEGER'
BOOL = 'BOOL'

INT64_MAX = 2 ** 63 - 1

#: Hz: the fastest a rate in a vehicle file may be (a simulator step, a sensor, a published
#: stream, a timer). An empty rclpy timer asked for 100 kHz fires at 9.9 kHz on these
#: machines; a node's real step costs far more (benchmarks/README.md, P2: about 1 kHz held).
MAX_RATE_HZ = 10_000.0
#: Hz: the slowest (a period of 1000 s).
MIN_RATE_HZ = 0.001
#: s: the shortest timeout (a silence is watched at a tenth of it: a period of 1/MAX_RATE_HZ).
MIN_TIMEOUT = 10.0 / MAX_RATE_HZ
#: s: the longest timeout, tolerance or period.
MAX_TIMEOUT = 3600.0
#: The largest magnitude of a state value written in a file (initial state and estimate,
#: reference), in the state's unit: a plausibility bound. Squares and products with gains
#: of such values (1e18 and beyond) stay far from overflow (1.8e308).
MAX_STATE_MAGNITUDE = 1e9

_RATE_WHY = f"{MAX_RATE_HZ:g} Hz: the fastest a node's timer fires here"
_TIMEOUT_WHY = f'a silence is watched at a tenth of the timeout, at most {MAX_RATE_HZ:g} Hz'
_STATE_WHY = 'a plausibility bound: docs/vehicle_schema.md, Limits'
_FASTEST = "and at most the fastest sensor's rate (simulator.rate_hz / its rate_divider)"

# Vehicle sections a node reads once, at start: changing them at run time would have no
# effect (or leave the node inconsistent), so they are read-only.
READ_ONLY_SECTIONS = ('vehicle', 'model', 'sensors', 'simulator')


@dataclass(frozen=True)
class KeySpec:
    """
    One parameter of the schema.

    ``param_type`` is the name of the rclpy ``Parameter.Type`` member (``DOUBLE_ARRAY``,
    ...), so a node can declare it with ``Parameter.Type[spec.param_type]``. ``default``
    is None for a required parameter and for an optional one without a default.
    ``low``/``high`` bound a number (each element of an array) in ``unit``; ``why`` is
    said with a refusal; ``rule`` states a bound that involves other keys (the loader
    checks it); ``details`` is the rest of the meaning, for the docs.

    """

    name: str
    param_type: str
    description: str
    required: bool = False
    default: object = None
    choices: Tuple[str, ...] = ()
    unit: str = ''
    low: Optional[float] = None
    high: Optional[float] = None
    low_open: bool = False
    why: str = ''
    rule: str = ''
    details: str = ''
    read_once: bool = False     # read at start only (a timer's rate), whatever its section

    def __post_init__(self):
        """Refuse an open bound other than at 0 (ROS could not hold it: module doc)."""
        if self.low_open and self.low != 0:
            raise ValueError(f'{self.name}: an open bound is allowed only at 0')

    @property
    def read_only(self):
        """Return True for a key a node reads once, at start (its section, or its own)."""
        return self.read_once or self.name.split('.', 1)[0] in READ_ONLY_SECTIONS

    @property
    def bounded(self):
        """Return True when the key has a numeric bound."""
        return self.low is not None or self.high is not None


class ParameterInfo(NamedTuple):
    """A parameter as a node declares it: name, type, default (or None), description."""

    name: str
    param_type: str
    default: object
    description: str


def _keys(*specs):
    return {spec.name: spec for spec in specs}


def _rate(name, description, **more):
    return KeySpec(name, DOUBLE, description, unit='Hz', low=MIN_RATE_HZ, high=MAX_RATE_HZ,
                   why=_RATE_WHY, **more)


def _timeout(name, description, **more):
    return KeySpec(name, DOUBLE, description, unit='s', low=MIN_TIMEOUT, high=MAX_TIMEOUT,
                   why=_TIMEOUT_WHY, **more)


def _state_values(name, description, **more):
    return KeySpec(name, DOUBLE_ARRAY, description, low=-MAX_STATE_MAGNITUDE,
                   high=MAX_STATE_MAGNITUDE, why=_STATE_WHY, unit='state units', **more)


KNOWN_KEYS = _keys(
    KeySpec('vehicle.name', STRING, 'short name (letters, digits, _ . -), used in bag and '
            'report names', required=True),
    KeySpec('vehicle.description', STRING, 'one line', default=''),
    KeySpec('vehicle.source', STRING, 'where the numbers come from (seed, paper)',
            default=''),
    KeySpec('vehicle.base_frame', STRING, 'the body frame the states are in: '
            'header.frame_id of state/estimate and state/true (REP 105)', default='base_link'),
    KeySpec('model.time_domain', STRING, 'continuous or discrete', default='continuous',
            choices=('continuous', 'discrete')),
    KeySpec('model.sample_time', DOUBLE, 'the step of a discrete model; required for '
            'discrete', unit='s', low=1.0 / MAX_RATE_HZ, high=1.0 / MIN_RATE_HZ,
            why=f'1/sample_time is the step rate; {_RATE_WHY}',
            details='a warning for `continuous`'),
    KeySpec('model.states', STRING_ARRAY, 'state names (n), unique', required=True,
            details='e.g. `[theta, w, q]`'),
    KeySpec('model.inputs', STRING_ARRAY, 'input names (m)', required=True,
            details='e.g. `[delta]`'),
    KeySpec('model.outputs', STRING_ARRAY, 'output names (p)', required=True,
            details='e.g. `[q]`'),
    KeySpec('model.state_units', STRING_ARRAY, 'the unit of each state (n), as written in '
            'the reports', details='e.g. `[rad, ft/s, rad/s]`; unstated when absent. A state '
            "that an output measures alone (its row of C selects it, D's row 0) has that "
            "output's unit"),
    KeySpec('model.input_units', STRING_ARRAY, 'the unit of each input (m)',
            details='e.g. `[deg, deg]`; unstated when absent'),
    KeySpec('model.output_units', STRING_ARRAY, 'the unit of each output (p)',
            details="when absent, each output's unit comes from the state it measures "
            "alone or from its message field's ROS convention (REP 103: an Imu's "
            '`angular_velocity` is rad/s, `linear_acceleration` m/s^2); a unit that '
            'contradicts the convention of the field it is read from is refused'),
    KeySpec('model.A', DOUBLE_ARRAY, 'n x n, row-major', required=True),
    KeySpec('model.B', DOUBLE_ARRAY, 'n x m, row-major', required=True),
    KeySpec('model.C', DOUBLE_ARRAY, 'p x n, row-major', required=True),
    KeySpec('model.D', DOUBLE_ARRAY, 'p x m, row-major; zeros when absent',
            details="an IMU's a_N has D != 0"),
    KeySpec('sensors.names', STRING_ARRAY, 'the sensors; each has sensors.<name>.* keys',
            required=True, details='e.g. `[gyro]`; letters, digits and `_`'),
    KeySpec('observer.type', STRING, 'full, reduced, open_loop or kalman', required=True,
            choices=OBSERVER_TYPES),
    KeySpec('observer.poles', DOUBLE_ARRAY, 'real parts of the observer poles',
            details='s-plane for a continuous model, z-plane for a discrete one: n for '
            '`full`, n-p for `reduced`. The gains of the sampled steps the observer runs '
            "(simulator step x each sensor's `rate_divider`) are designed and verified "
            'too, and with sensors at different rates the error map over one period of '
            'their pattern must be stable: otherwise the design is refused (Kalman handles '
            'any pattern)'),
    KeySpec('observer.poles_imag', DOUBLE_ARRAY, 'imaginary parts; all 0 when absent',
            details='same length as `poles`; complex poles in conjugate pairs'),
    KeySpec('observer.gain', DOUBLE_ARRAY, 'L given directly: n x p (full) or '
            '(n-p) x p (reduced), row-major',
            details='instead of poles; continuous-time for a continuous model'),
    KeySpec('observer.method', STRING, 'pole placement: auto, place or acker',
            default='auto', choices=('auto', 'place', 'acker'),
            details='`auto`: acker for one output where it is well conditioned, else place'),
    KeySpec('observer.Qd', DOUBLE_ARRAY, 'kalman: k x k process noise covariance',
            details='an intensity for a continuous model; when absent, '
            'diag(`simulator.process_noise_std`^2) if that is given, all > 0, and `Bd` is '
            'absent'),
    KeySpec('observer.Rd', DOUBLE_ARRAY, 'kalman: p x p measurement noise covariance',
            details='positive definite; when absent, diag(`noise_std`^2) of the sensors in '
            'output order (all must be > 0)'),
    KeySpec('observer.Bd', DOUBLE_ARRAY, 'kalman: n x k process noise input',
            details='row-major (k from its length); identity (k = n) when absent'),
    _state_values('observer.initial_estimate', 'x_hat(0) (n); zeros when absent'),
    _rate('observer.rate_hz', 'rate of the prediction published while every sensor is '
          'silent; the simulator rate when absent', rule=_FASTEST, read_once=True,
          details="from a sensor's `timeout` plus at most a tenth of it; read-only: the "
          'rate of a timer made at start'),
    KeySpec('observer.history_length', DOUBLE, 'late messages this much older than the '
            'estimate are used at their stamps (0: refused)', default=HISTORY_LENGTH,
            unit='s', low=0.0, high=MAX_TIMEOUT,
            details='the estimate is rewound to the stamp and the later messages applied '
            'again, once; older ones are skipped (`out_of_order`). Keep it below the '
            "observer's `clock_jump_tolerance` (0.5 s)"),
    _rate('observer.publish_rate_hz', 'free-running: also publish the estimate predicted '
          'to now at this rate; off when absent', rule=_FASTEST, read_once=True,
          details='besides the answer to each measurement (lock-step keeps one answer per '
          'measurement); read-only: the rate of a timer made at start'),
    KeySpec('controller.poles', DOUBLE_ARRAY, 'real parts of eig(A - B K) (n)',
            details='stable: n of them, or for a stabilizable but uncontrollable plant one '
            'per controllable mode (the rank; the uncontrollable eigenvalues are kept), the '
            'same rule as `observer.poles`; the design is refused when the gain does not '
            'achieve them (see `core/verify.py`)'),
    KeySpec('controller.poles_imag', DOUBLE_ARRAY, 'imaginary parts; all 0 when absent',
            details='conjugate pairs'),
    KeySpec('controller.K', DOUBLE_ARRAY, 'm x n, row-major', details='K given directly'),
    KeySpec('controller.lqr_Q', DOUBLE_ARRAY, 'LQR state weight, n x n',
            details='symmetric positive semidefinite'),
    KeySpec('controller.lqr_R', DOUBLE_ARRAY, 'LQR input weight, m x m',
            details='symmetric positive definite; required with `lqr_Q`'),
    _state_values('controller.reference', 'x_d (n); zeros when absent'),
    KeySpec('controller.Kd', DOUBLE_ARRAY, 'feedforward, m x n; zeros when absent',
            details='u = K(x_d - x_hat) - Kd x_d (seed 002)'),
    KeySpec('controller.u_min', DOUBLE_ARRAY, 'input lower limits (m); unlimited when '
            'absent', unit='input units', details='may be `-.inf`'),
    KeySpec('controller.u_max', DOUBLE_ARRAY, 'input upper limits (m); unlimited when '
            'absent', unit='input units', details='each above `u_min`; may be `.inf`'),
    KeySpec('controller.safe_command', STRING, 'zero or hold', default='zero',
            choices=('zero', 'hold'),
            details='the command when x_hat is stale, not finite or diverging (after '
            '`predict_timeout`); `hold`: the last command sent'),
    _timeout('controller.stale_timeout', 'x_hat older than this is stale', default=0.5),
    KeySpec('controller.predict_timeout', DOUBLE, 'predict-and-hold before the '
            'safe_command fallback', default=0.0, unit='s', low=0.0, high=MAX_TIMEOUT,
            details='while x_hat is stale or diverging, the compensator first keeps the loop '
            "closed on the model's prediction from the last trusted x_hat for this long, "
            'then sends `safe_command`. `0`: `safe_command` at once. For an unstable plant '
            '(the cart) give a few seconds: a zero command lets the pendulum fall'),
    KeySpec('controller.delay_compensation', BOOL, 'realtime: predict a late estimate to '
            'when its command takes effect, and stamp the command with that time',
            default=False,
            details="lock-step has no latency. The plant's time is read from the newest "
            "stamp on the vehicle's sensor topics, plus the compensator's "
            '`command_lead_steps`; the simulator applies a command from its stamp. For a '
            "loop with almost no delay margin: the cart's goes unstable with 0.58 ms of "
            'unmodelled delay (`core/delay_compensation.py`, docs/reliability.md)'),
    _rate('simulator.rate_hz', 'step rate; a discrete model runs at 1/sample_time',
          default=100.0,
          details='for a discrete model this key may be left out, and if given must equal '
          '1/`sample_time`'),
    _state_values('simulator.initial_state', 'x(0) (n); zeros when absent'),
    KeySpec('simulator.duration', DOUBLE, 'simulated time of a run; 0: the simulator node '
            'runs until stopped', default=10.0, unit='s', low=0.0,
            rule='at least one step',
            details='`observer-run` refuses 0. When a run ends, the simulator logs `run '
            'complete` and exits 0; the observer and compensator then report stale data on '
            '/diagnostics'),
    KeySpec('simulator.seed', INTEGER, 'noise seed', default=0, low=0),
    KeySpec('simulator.noise', BOOL, "add the sensors' noise_std", default=True),
    KeySpec('simulator.process_noise_std', DOUBLE_ARRAY, 'process noise per state (n); '
            'none when absent', low=0.0,
            details='continuous model: the square root of the diagonal intensity of w (per '
            'sqrt(s)), so each step adds the exact covariance Qd(dt) whatever the rate (what '
            "`observer.Qd`'s default and observer-tune read); discrete model: the standard "
            'deviation per sample'),
    KeySpec('simulator.mode', STRING, 'lockstep or realtime', default='lockstep',
            choices=('lockstep', 'realtime')),
    KeySpec('simulator.realtime_factor', DOUBLE, 'realtime speed', default=1.0,
            low=0.001, high=1000.0, rule=f'rate_hz x realtime_factor at most {MAX_RATE_HZ:g}'
            ' Hz'),
    _timeout('simulator.command_timeout', 'lockstep: wall time to wait for a command before '
             'reporting it', default=2.0,
             details='the simulator keeps waiting: it never advances without the answer'),
    KeySpec('simulator.publish_clock', BOOL, 'publish /clock (one vehicle per ROS graph)',
            default=True,
            details='absolute: one clock per ROS graph. With several vehicles in one graph '
            'only the one that owns time publishes it: `publish_clock:=false` in '
            '`closed_loop.launch.py`, `--no-clock` in `observer-run`'),
)

# Per-sensor keys: sensors.<s>.<key> for each <s> in sensors.names.
SENSOR_KEYS = _keys(
    KeySpec('topic', STRING, 'relative topic name', required=True,
            details='namespaced with the node, e.g. `imu/data`'),
    KeySpec('type', STRING, 'message type', required=True, choices=SENSOR_TYPES),
    KeySpec('fields', STRING_ARRAY, 'message fields read, one per output', required=True,
            details='see below'),
    KeySpec('outputs', STRING_ARRAY, 'the model outputs they are', required=True,
            details='same length as `fields`'),
    KeySpec('noise_std', DOUBLE_ARRAY, 'noise standard deviation per field', required=True,
            low=0.0, unit='output units',
            details='simulator noise; Imu covariance; default Kalman `Rd`'),
    _timeout('timeout', 'silence after which the observer predicts only and warns',
             default=0.5),
    KeySpec('rate_divider', INTEGER, 'published every k-th simulator step', default=1, low=1),
    KeySpec('frame_id', STRING, 'header.frame_id', default='base_link'),
)

# The nodes' own parameters (not in a vehicle file; given with -p or a node section).
NODE_KEYS = _keys(
    KeySpec('clock_jump_tolerance', DOUBLE, 'a stamp this far behind the newest is far back: '
            'skipped unless clock_jump_agreement such stamps come in a row (a clock jump: '
            'the observer resets; the compensator resets its plant time, standby and safe '
            'command, or on estimates its loop)', default=CLOCK_JUMP_TOLERANCE, unit='s', low=0.0,
            low_open=True, high=MAX_TIMEOUT, details='nodes: observer, compensator'),
    KeySpec('clock_jump_agreement', INTEGER, 'measurements (or estimates) in a row stamped '
            'more than clock_jump_tolerance behind the newest that make a clock jump; fewer '
            'are outliers, skipped (far_back_stamps, far_back_estimates)',
            default=CLOCK_JUMP_AGREEMENT, low=1, high=1000,
            details='nodes: observer, compensator'),
    KeySpec('future_tolerance', DOUBLE, 'a stamp this far ahead of the clock is refused',
            default=FUTURE_TOLERANCE, unit='s', low=0.0, low_open=True, high=1e9,
            details='nodes: observer'),
    KeySpec('diagnostics_period', DOUBLE, 'wall time between /diagnostics reports',
            default=1.0, unit='s', low=0.01, high=MAX_TIMEOUT,
            details='nodes: observer, compensator, plant_simulator'),
    KeySpec('start_time', DOUBLE, 'simulated time of step 0 (a zero stamp reads as unset)',
            default=1.0, unit='s', low=0.0, low_open=True, high=1e9,
            details='nodes: plant_simulator'),
    KeySpec('wait_for_subscribers', INTEGER, 'lockstep: matched readers of each sensor to '
            'wait for', default=1, low=0, high=1000, details='nodes: plant_simulator'),
    KeySpec('wait_for_recorder', BOOL, 'lockstep: start once recorder/ready is true, step '
            'on from step 0 once recorder/heard lists its estimate and command, and step at '
            'most 5 steps past the newest true state the recorder wrote (recorder/progress)',
            default=False, details='nodes: plant_simulator', read_once=True),
    KeySpec('exit_when_done', BOOL, 'exit (status 0) when simulator.duration is over',
            default=True, details='nodes: plant_simulator'),
    KeySpec('publish_array', BOOL, 'also publish control/u_array, a Float64MultiArray '
            '(ros2_control)', default=False, details='nodes: compensator'),
    KeySpec('command_lead_steps', INTEGER, 'controller.delay_compensation: steps a command '
            "is stamped ahead of the plant's time (its way to the plant)", default=3, low=0,
            high=100, details='nodes: compensator'),
    KeySpec('autostart', BOOL, 'configure and activate at start (false: the node waits '
            'unconfigured for `ros2 lifecycle set` or a launch file)', default=True,
            details='nodes: observer, compensator'),
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
            keys[name] = replace(spec, name=name)
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


def _num(value):
    return f'{value:g}'


def interval_text(spec, unit=True, each=True):
    """
    Return a key's bound as text: ``[0.001, 10000] Hz``, ``(0, 3600] s``, ``>= 1``.

    Empty for a key without a bound; an array's bound is prefixed with ``each``.
    """
    low, high = spec.low, spec.high
    if low is None and high is None:
        return ''
    if high is None:
        text = f'{">" if spec.low_open else ">="} {_num(low)}'
    elif low is None:
        text = f'<= {_num(high)}'
    else:
        text = f'{"(" if spec.low_open else "["}{_num(low)}, {_num(high)}]'
    if unit and spec.unit and not spec.unit.endswith('units'):
        text += f' {spec.unit}'
    return ('each ' + text) if each and spec.param_type.endswith('_ARRAY') else text


def bound_problem(spec, value):
    """
    Return why a number is outside its key's bound, or None.

    Parameters
    ----------
    spec : KeySpec
        The key.
    value : float or int
        One value (an element of an array).

    Returns
    -------
    str or None
        ``1e+09 is outside [0.001, 10000] Hz (at most 10000 Hz, ...)``, without the key.

    """
    low, high = spec.low, spec.high
    if isinstance(value, float) and math.isnan(value):
        inside = False
    else:
        inside = (low is None or value > low or (value == low and not spec.low_open)) and \
            (high is None or value <= high)
    if inside:
        return None
    text = f'{value!r} is outside {interval_text(spec, each=False)}'
    if low is not None and high is None:
        text = f'{value!r} must be {interval_text(spec, each=False)}'
    return text + (f' ({spec.why})' if spec.why else '')


def ros_range(spec):
    """
    Return the closed interval ``(from_value, to_value)`` a ROS descriptor gives a key.

    None for a key without a bound and for arrays (ROS ranges hold scalars only). An open
    bound at 0 becomes the least positive double (module doc); a missing bound the
    largest value of the type.
    """
    if not spec.bounded or spec.param_type not in (DOUBLE, INTEGER):
        return None
    if spec.param_type == INTEGER:
        low = -INT64_MAX - 1 if spec.low is None else int(spec.low) + int(spec.low_open)
        high = INT64_MAX if spec.high is None else int(spec.high)
        return low, high
    big = 1.7976931348623157e308
    if spec.low is None:
        low = -big
    else:
        low = math.nextafter(float(spec.low), math.inf) if spec.low_open else float(spec.low)
    return low, big if spec.high is None else float(spec.high)
