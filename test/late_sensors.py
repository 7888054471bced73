# test/late_sensors.py: the two-sensor submarine whose sensors have different latencies.
"""
The two-sensor submarine: a gyro and a pitch sensor of different rates and latencies.

A rate gyro (q, 100 Hz, 1 ms latency) and a pitch sensor (theta, 20 Hz, 40 ms latency),
for the node, bag replay and innovation tests.

:func:`messages` simulates it (exact ZOH, noisy sensors, a known input on ``control/u``
stamped like the gyro and received 2 ms later) and returns the messages with their stamp
and arrival times; the tests publish them or write them to a bag in either order.

"""

from pathlib import Path

import numpy as np
from observer_ros.core.estimators import process_noise_covariance
from observer_ros.core.model import zoh_matrices
from observer_ros.vehicle import load_vehicle

VEHICLE_YAML = """\
/**:
  ros__parameters:
    vehicle:
      name: submarine_two_sensors
      description: Submarine pitch with a gyro and a slower, later pitch sensor
    model:
      time_domain: continuous
      states: [theta, w, q]
      inputs: [delta]
      outputs: [q, theta]
      A: [0.0, 0.0, 1.0, 0.0135, -0.322, -0.7102, -0.036, 0.126, -0.7395]
      B: [0.0, 0.0322, -0.0857]
      C: [0.0, 0.0, 1.0, 1.0, 0.0, 0.0]
    sensors:
      names: [gyro, pitch]
      gyro:
        topic: imu/data
        type: sensor_msgs/msg/Imu
        fields: [angular_velocity.y]
        outputs: [q]
        noise_std: [0.001]
      pitch:
        topic: pitch
        type: sensor_msgs/msg/JointState
        fields: [position.theta]
        outputs: [theta]
        noise_std: [{pitch_noise}]
        rate_divider: 5
    observer:
      type: {observer_type}
      {observer_design}
    controller:
      poles: [-0.3, -0.31, -0.32]
    simulator:
      mode: realtime
      rate_hz: 100.0
      duration: 3.0
      initial_state: [0.5, 0.1, 0.0]
"""

#: Process noise intensity of the Kalman design (continuous, per state).
QD = np.diag([1.0e-6, 1.0e-4, 1.0e-4])

#: Full-order poles. Faster ones (-2, -2.1, -2.2) are refused: with the gyro at 100 Hz and
#: the pitch sensor at 20 Hz the product of the per-step error maps over 0.05 s has
#: spectral radius 1.02 (test_core_sampled.py); these give 0.983.
FULL_POLES = '[-0.6, -0.7, -0.8]'

DESIGNS = {
    'full': f'poles: {FULL_POLES}',
    'kalman': 'Qd: [' + ', '.join(f'{v:.1e}' for v in QD.reshape(-1)) + ']',
}

GYRO_LATENCY_NS = 1_000_000
GYRO_NOISE, PITCH_NOISE = 1e-3, 1e-2
PITCH_LATENCY_NS = 40_000_000
COMMAND_LATENCY_NS = 2_000_000


def write_vehicle(directory, observer_type='full', pitch_noise=PITCH_NOISE, design=None):
    """Write the vehicle file into a directory; return its path (design: observer keys)."""
    path = Path(directory) / f'submarine_two_sensors_{observer_type}.yaml'
    path.write_text(VEHICLE_YAML.format(observer_type=observer_type, pitch_noise=pitch_noise,
                                        observer_design=design or DESIGNS[observer_type]))
    return path


def vehicle(directory, observer_type='full', pitch_noise=PITCH_NOISE):
    """Write the vehicle file into ``directory`` and load it."""
    return load_vehicle(write_vehicle(directory, observer_type, pitch_noise))


def messages(veh, steps=300, t0_ns=100_000_000_000, seed=0, commands=True,
             process_noise=False, faults=None, qd=None):
    """
    Simulate the two-sensor submarine.

    Returns
    -------
    msgs : list of tuple
        ``(kind, stamp_ns, arrival_ns, value)`` with kind ``gyro``, ``pitch`` or ``u``,
        sorted by stamp.
    truth : list of tuple
        ``(stamp_ns, x)`` at every step.

    With ``process_noise`` the plant is driven by the process noise the Kalman design
    assumes (:data:`QD`, or ``qd``, exactly sampled). ``faults`` maps a sensor to
    ``(sign, bias, onset)``: from step ``onset`` on its readings become
    ``sign * reading + bias`` (a flipped axis, a bias).

    """
    rng = np.random.default_rng(seed)
    plant = veh.plant
    dt_ns = 10_000_000
    Ad, Bd = zoh_matrices(plant.A, plant.B, dt_ns * 1e-9)
    Qk = process_noise_covariance(plant.A, QD if qd is None else qd, dt_ns * 1e-9)
    W = np.linalg.cholesky(Qk + 1e-18 * np.eye(plant.n))
    x = np.array(veh.simulator.initial_state, dtype=float)
    pitch_noise = float(veh.sensors[1].noise_std[0])
    msgs, truth = [], []
    for k in range(steps):
        ns = t0_ns + k * dt_ns
        t = ns * 1e-9
        u = 0.05 * np.sin(0.7 * t) if commands else 0.0
        truth.append((ns, x.copy()))
        msgs.append(('gyro', ns, ns + GYRO_LATENCY_NS,
                     _fault(faults, 'gyro', x[2] + rng.normal(0.0, GYRO_NOISE), k)))
        if k % 5 == 0:
            msgs.append(('pitch', ns, ns + PITCH_LATENCY_NS,
                         _fault(faults, 'pitch', x[0] + rng.normal(0.0, pitch_noise), k)))
        if commands:
            msgs.append(('u', ns, ns + COMMAND_LATENCY_NS, u))
        x = Ad @ x + Bd @ np.array([u])
        if process_noise:
            x = x + W @ rng.standard_normal(plant.n)
    return msgs, truth


def _fault(faults, name, value, k):
    sign, bias, onset = (faults or {}).get(name, (1.0, 0.0, 0))
    return sign * value + bias if k >= onset else value


def commands_late(msgs, steps=5):
    """
    Make each command arrive 1 to ``steps`` steps after its stamp (a closed loop under load).

    The command answering the estimate at t_k is stamped t_k; it arrives after the gyro
    messages of the next few steps (half a millisecond after the last of them).
    """
    out = []
    for kind, ns, arrival, value in msgs:
        if kind == 'u':
            lag = 1 + (ns // 10_000_000) % steps              # steps of 10 ms
            arrival = ns + lag * 10_000_000 + GYRO_LATENCY_NS + 500_000
        out.append((kind, ns, arrival, value))
    return out


def receive_order(msgs):
    """Return the messages in the order they arrive (by arrival time)."""
    return sorted(msgs, key=lambda m: (m[2], m[1]))


def stamp_order(msgs):
    """Return the messages in stamp order: at one stamp the measurements (gyro first), then u."""
    return sorted(msgs, key=lambda m: (m[1], m[0] == 'u', m[0] == 'pitch'))
