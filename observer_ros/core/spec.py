# observer_ros.core.spec: what a vehicle file says, as plain data classes.
"""
Data classes describing a vehicle: plant, sensors, observer, controller, simulator.

They are filled by ``observer_ros.vehicle`` (from a parameter file or a node's
parameters) and consumed by the design, the estimators, the nodes and the tools.
No ROS imports here.

"""

from dataclasses import dataclass, field
from typing import Optional, Tuple

import numpy as np

from .model import Plant

__all__ = ['SensorSpec', 'ObserverSpec', 'ControllerSpec', 'SimulatorSpec', 'Vehicle',
           'OBSERVER_TYPES', 'SENSOR_TYPES', 'HISTORY_LENGTH']

OBSERVER_TYPES = ('full', 'reduced', 'open_loop', 'kalman')
SENSOR_TYPES = ('sensor_msgs/msg/Imu', 'sensor_msgs/msg/JointState', 'std_msgs/msg/Float64')

#: Default ``observer.history_length`` (s): longer than the latency of the slow sensors of
#: the vehicles here (40 ms), shorter than the node's clock-jump tolerance (0.5 s: a larger
#: step back is a clock restart). See estimators.history.
HISTORY_LENGTH = 0.25


@dataclass(frozen=True)
class SensorSpec:
    """One sensor topic: which message fields carry which model outputs."""

    name: str
    topic: str
    msg_type: str
    fields: Tuple[str, ...]
    outputs: Tuple[str, ...]
    noise_std: np.ndarray
    timeout: float = 0.5
    rate_divider: int = 1
    frame_id: str = 'base_link'


@dataclass(frozen=True)
class ObserverSpec:
    """The estimator: type and its design (poles, a gain, or Kalman covariances)."""

    kind: str                                # one of OBSERVER_TYPES
    poles: Optional[np.ndarray] = None       # complex; s-plane (continuous) or z-plane
    gain: Optional[np.ndarray] = None        # L, 2-D; n x p (full) or (n-p) x p (reduced)
    method: str = 'auto'                     # auto | place | acker
    Qd: Optional[np.ndarray] = None          # kalman: k x k
    Rd: Optional[np.ndarray] = None          # kalman: p x p
    Bd: Optional[np.ndarray] = None          # kalman: n x k (None: identity)
    initial_estimate: Optional[np.ndarray] = None   # n (None: zeros)
    rate_hz: Optional[float] = None
    history_length: float = HISTORY_LENGTH           # s, >= 0
    publish_rate_hz: Optional[float] = None          # Hz; None: no fixed-rate output


@dataclass(frozen=True)
class ControllerSpec:
    """The state feedback u = K (x_d - x_hat) - Kd x_d, with limits and a safe command."""

    poles: Optional[np.ndarray] = None       # complex
    K: Optional[np.ndarray] = None           # m x n
    lqr_Q: Optional[np.ndarray] = None       # n x n
    lqr_R: Optional[np.ndarray] = None       # m x m
    reference: Optional[np.ndarray] = None   # x_d, n (None: zeros)
    Kd: Optional[np.ndarray] = None          # m x n (None: zeros)
    u_min: Optional[np.ndarray] = None       # m
    u_max: Optional[np.ndarray] = None       # m
    safe_command: str = 'zero'               # zero | hold
    stale_timeout: float = 0.5
    predict_timeout: float = 0.0             # s of predict-and-hold before safe_command
    delay_compensation: bool = False         # realtime: predict to when u takes effect


@dataclass(frozen=True)
class SimulatorSpec:
    """How the plant simulator runs."""

    rate_hz: float
    initial_state: np.ndarray
    duration: float = 10.0
    seed: int = 0
    noise: bool = True
    process_noise_std: Optional[np.ndarray] = None
    mode: str = 'lockstep'                   # lockstep | realtime
    realtime_factor: float = 1.0
    command_timeout: float = 2.0
    publish_clock: bool = True               # one /clock per ROS graph


@dataclass(frozen=True)
class Vehicle:
    """Everything a vehicle file says."""

    name: str
    plant: Plant
    sensors: Tuple[SensorSpec, ...]
    observer: ObserverSpec
    controller: ControllerSpec
    simulator: SimulatorSpec
    description: str = ''
    source: str = ''
    base_frame: str = 'base_link'                   # frame_id of the state messages
    warnings: Tuple[str, ...] = field(default=())   # loader warnings (unknown keys, ...)
    origin: str = ''                                # the file or node it was read from
    # the unit of each state, input and output ('' where unstated): model.*_units
    state_units: Tuple[str, ...] = field(default=())
    input_units: Tuple[str, ...] = field(default=())
    output_units: Tuple[str, ...] = field(default=())

    def unit(self, kind, name):
        """Return the unit of a state, input or output by name ('' when unstated)."""
        names, units = {'state': (self.plant.state_names, self.state_units),
                        'input': (self.plant.input_names, self.input_units),
                        'output': (self.plant.output_names, self.output_units)}[kind]
        i = list(names).index(name)
        return units[i] if i < len(units) else ''

    @property
    def sample_time(self):
        """Return the simulator's step (the model's own for a discrete model)."""
        return self.plant.dt if self.plant.is_discrete else 1.0 / self.simulator.rate_hz
