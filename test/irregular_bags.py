# test/irregular_bags.py: closed-loop bags with lost messages and jittered stamps.
"""
An independent writer of recordings, for the tuning tests: numpy, scipy and rosbags only.

Nothing of observer_ros is used here (not its model sampling, estimators, designs,
message filling or bag writing), so the tuner is checked against data it did not make.

A continuous plant ``x' = A x + B u + Gw w`` (w white, intensity Qc) is sampled at stamps
``t_k = t0 + k h + j_k`` with ``j_k`` uniform in ``+-jitter h`` (so the steps between
samples run from ``(1 - 2 jitter) h`` to ``(1 + 2 jitter) h``), exactly: each step's
transition, input matrix and process noise come from one matrix exponential of its own
length (Van Loan). Each sensor's message of a sample is lost with probability
``dropout``, independently. A controller closes the loop: its own steady-state Kalman
filter (scipy's discrete Riccati solution at the nominal step) runs at the stamps with
the messages that arrived, and ``u = -K x_hat`` with an LQR gain K (scipy's continuous
Riccati solution); the command is stamped at the sample and published every sample. The
bag holds the sensors' messages, ``control/u`` and ``state/true`` (at every sample), each
serialised with rosbags' Jazzy typestore and written with rosbags' Writer (mcap).

"""

from dataclasses import dataclass
from pathlib import Path
from typing import List

import numpy as np
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import get_typestore, Stores
import scipy.linalg

STORE = get_typestore(Stores.ROS2_JAZZY)
IMU = 'sensor_msgs/msg/Imu'
JOINT_STATE = 'sensor_msgs/msg/JointState'


@dataclass
class Sensor:
    """One sensor: its topic and message, the plant outputs it measures, its noise."""

    topic: str
    msgtype: str              # IMU (angular_velocity.<axis>) or JOINT_STATE (position)
    rows: List[int]           # rows of C
    std: List[float]
    field: str = ''           # IMU axis ('y') or JointState joint name


@dataclass
class System:
    """A continuous plant with its noise and its sensors."""

    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    Gw: np.ndarray
    Qc: np.ndarray            # intensity of w
    sensors: List[Sensor]
    h: float                  # nominal sample step
    state_names: List[str]
    input_names: List[str]


def submarine(Qc, states=(0, 1)):
    """Return the submarine pitch plant with noise on ``states`` and a rate gyro."""
    A = np.array([[0.0, 0.0, 1.0], [0.0135, -0.322, -0.7102], [-0.036, 0.126, -0.7395]])
    B = np.array([[0.0], [0.0322], [-0.0857]])
    C = np.array([[0.0, 0.0, 1.0]])
    Gw = np.eye(3)[:, list(states)]
    return System(A, B, C, Gw, np.diag(Qc), [Sensor('imu/data', IMU, [0], [0.001], 'y')],
                  0.05, ['theta', 'w', 'q'], ['delta'])


def spring_chain(Qc):
    """Return two masses on springs and dampers (x1, v1, x2, v2), force on the second."""
    k1, k2, c1, c2, m1, m2 = 4.0, 2.0, 0.3, 0.2, 1.0, 0.5
    A = np.array([[0.0, 1.0, 0.0, 0.0],
                  [-(k1 + k2) / m1, -(c1 + c2) / m1, k2 / m1, c2 / m1],
                  [0.0, 0.0, 0.0, 1.0],
                  [k2 / m2, c2 / m2, -k2 / m2, -c2 / m2]])
    B = np.array([[0.0], [0.0], [0.0], [1.0 / m2]])
    C = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]])
    Gw = np.eye(4)[:, [1, 3]]
    sensors = [Sensor('mass1/joint_states', JOINT_STATE, [0], [0.002], 'm1'),
               Sensor('mass2/joint_states', JOINT_STATE, [1], [0.003], 'm2')]
    return System(A, B, C, Gw, np.diag(Qc), sensors, 0.02, ['x1', 'v1', 'x2', 'v2'],
                  ['force'])


def _steps(A, B, S, tau):
    """
    Return the exact (Ad, Bd, Qd) of steps of lengths tau, from A's eigenvectors.

    With ``A = V diag(lam) V^-1``: ``Ad = V diag(e^(lam t)) V^-1``, ``Bd = V diag((e^(lam
    t) - 1) / lam) V^-1 B`` and ``Qd = V [S'_ij (e^((lam_i + conj lam_j) t) - 1) / (lam_i
    + conj lam_j)] V^H``, ``S' = V^-1 S V^-H`` (the plants here have distinct eigenvalues,
    none zero).

    """
    lam, V = np.linalg.eig(A)
    Vi = np.linalg.inv(V)
    tau = np.asarray(tau, dtype=float)[:, None]
    e = np.exp(lam[None] * tau)                                        # (K, n)
    Ad = np.einsum('ij,kj,jl->kil', V, e, Vi).real
    Bd = np.einsum('ij,kj,jl->kil', V, (e - 1.0) / lam[None], Vi @ B).real
    Sp = Vi @ S @ Vi.conj().T
    mu = lam[:, None] + lam.conj()[None, :]
    W = (np.exp(mu[None] * tau[:, :, None]) - 1.0) / mu[None] * Sp[None]
    Qd = np.einsum('ij,kjl,ml->kim', V, W, V.conj()).real
    return Ad, Bd, 0.5 * (Qd + np.swapaxes(Qd, 1, 2))


def _one_step(A, B, S, tau):
    """Return the exact (Ad, Bd, Qd) of one step by matrix exponentials (a check)."""
    n, m = B.shape
    aug = np.zeros((n + m, n + m))
    aug[:n, :n], aug[:n, n:] = A, B
    E = scipy.linalg.expm(aug * tau)
    V = np.zeros((2 * n, 2 * n))
    V[:n, :n], V[:n, n:], V[n:, n:] = -A, S, A.T
    F = scipy.linalg.expm(V * tau)
    Qd = F[n:, n:].T @ F[:n, n:]
    return E[:n, :n], E[:n, n:], 0.5 * (Qd + Qd.T)


def simulate(system, steps, seed, dropout=0.05, jitter=0.2, t0=1.0, x0=None):
    """
    Return the samples of a closed-loop run (see the module).

    Returns
    -------
    run : dict
        ``t`` (stamps, s), ``x`` (true states), ``y`` (measurements, NaN where the
        message was lost), ``u`` (commands). The plant starts at ``x0`` (default zero),
        the controller's filter at zero.

    """
    s = system
    n, m = s.B.shape
    p = s.C.shape[0]
    R = np.diag([sd ** 2 for sensor in s.sensors for sd in sensor.std])
    rows = [r for sensor in s.sensors for r in sensor.rows]
    Cs = s.C[rows]
    S = s.Gw @ s.Qc @ s.Gw.T
    rng = np.random.default_rng(seed)
    t = t0 + s.h * np.arange(steps) + rng.uniform(-jitter, jitter, steps) * s.h
    # the controller: an LQR gain and a steady Kalman filter at the nominal step
    P = scipy.linalg.solve_continuous_are(s.A, s.B, np.eye(n), np.eye(m))
    K = s.B.T @ P
    Ad0, _, Qd0 = _one_step(s.A, s.B, S, s.h)
    Ads, Bds, Qds = _steps(s.A, s.B, S, np.diff(t))
    check = _one_step(s.A, s.B, S, float(t[1] - t[0]))
    assert all(np.allclose(a[0], b, rtol=1e-9, atol=1e-14) for a, b in zip(
        (Ads, Bds, Qds), check)), 'the eigenvector sampling disagrees with expm'
    lw, Vw = np.linalg.eigh(Qds)
    Ws = (Vw * np.sqrt(np.maximum(lw, 0.0))[:, None, :]) @ rng.standard_normal((steps - 1, n, 1))
    Pf = scipy.linalg.solve_discrete_are(Ad0.T, Cs.T, Qd0 + 1e-12 * np.eye(n), R)
    Kf = Pf @ Cs.T @ np.linalg.inv(Cs @ Pf @ Cs.T + R)
    x = np.zeros(n) if x0 is None else np.array(x0, dtype=float)
    xh = np.zeros(n)
    X, Y, U = np.empty((steps, n)), np.full((steps, p), np.nan), np.empty((steps, m))
    lost = rng.random((steps, len(s.sensors))) < dropout
    for k in range(steps):
        y = Cs @ x + np.sqrt(np.diag(R)) * rng.standard_normal(p)
        got = np.zeros(p, dtype=bool)
        for i, sensor in enumerate(s.sensors):
            if not lost[k, i]:
                got[[rows.index(r) for r in sensor.rows]] = True
        Y[k, got] = y[got]
        if got.any():
            Kg = Kf[:, got]
            xh = xh + Kg @ (y[got] - Cs[got] @ xh)
        u = -K @ xh
        X[k], U[k] = x, u
        if k + 1 < steps:
            x = Ads[k] @ x + Bds[k] @ u + Ws[k, :, 0]
            xh = Ads[k] @ xh + Bds[k] @ u
    return {'t': t, 'x': X, 'y': Y, 'u': U}


def _time(sec):
    ns = int(round(sec * 1e9))
    return STORE.types['builtin_interfaces/msg/Time'](sec=ns // 10**9, nanosec=ns % 10**9)


def _header(sec, frame=''):
    return STORE.types['std_msgs/msg/Header'](stamp=_time(sec), frame_id=frame)


def _joint_state(sec, names, values):
    return STORE.types[JOINT_STATE](header=_header(sec), name=list(names),
                                    position=np.asarray(values, dtype=np.float64),
                                    velocity=np.zeros(0), effort=np.zeros(0))


def _imu(sec, axis, value, frame):
    T = STORE.types
    v = {'x': 0.0, 'y': 0.0, 'z': 0.0}
    v[axis] = float(value)
    return T[IMU](header=_header(sec, frame),
                  orientation=T['geometry_msgs/msg/Quaternion'](x=0.0, y=0.0, z=0.0, w=1.0),
                  orientation_covariance=np.zeros(9),
                  angular_velocity=T['geometry_msgs/msg/Vector3'](**v),
                  angular_velocity_covariance=np.zeros(9),
                  linear_acceleration=T['geometry_msgs/msg/Vector3'](x=0.0, y=0.0, z=0.0),
                  linear_acceleration_covariance=np.zeros(9))


def write(path, system, run, frame='base_link_frd', latency=1e-3):
    """Write a run as a bag (receive time = stamp + latency); return its path."""
    s = system
    path = Path(path)
    rows = [r for sensor in s.sensors for r in sensor.rows]
    conns = {}
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        def put(topic, msgtype, sec, msg):
            if topic not in conns:
                conns[topic] = writer.add_connection(f'/{topic}', msgtype, typestore=STORE)
            writer.write(conns[topic], int(round((sec + latency) * 1e9)),
                         STORE.serialize_cdr(msg, msgtype))
        for k, sec in enumerate(run['t']):
            put('state/true', JOINT_STATE, sec, _joint_state(sec, s.state_names, run['x'][k]))
            for sensor in s.sensors:
                cols = [rows.index(r) for r in sensor.rows]
                y = run['y'][k, cols]
                if np.isnan(y).any():
                    continue
                if sensor.msgtype == IMU:
                    put(sensor.topic, IMU, sec, _imu(sec, sensor.field, y[0], frame))
                else:
                    put(sensor.topic, JOINT_STATE, sec, _joint_state(sec, [sensor.field], y))
            put('control/u', JOINT_STATE, sec, _joint_state(sec, s.input_names, run['u'][k]))
    return path


def _floats(values):
    return '[' + ', '.join(repr(float(x)) for x in np.ravel(values)) + ']'


def three_mass_chain(Qc):
    """
    Return three masses in a row on springs and dampers, force on the third (x1..v3).

    Noise on the three velocities; positions of the first and third masses measured, on
    two topics. Unlike :func:`spring_chain`: six states, three
    process noises from two outputs, the sensor far from the force.

    """
    k, c, m = [3.0, 2.0, 1.5], [0.2, 0.15, 0.1], [1.0, 0.7, 0.5]
    A = np.zeros((6, 6))
    for i in range(3):
        A[2 * i, 2 * i + 1] = 1.0
    K = np.array([[k[0] + k[1], -k[1], 0.0], [-k[1], k[1] + k[2], -k[2]], [0.0, -k[2], k[2]]])
    D = np.array([[c[0] + c[1], -c[1], 0.0], [-c[1], c[1] + c[2], -c[2]], [0.0, -c[2], c[2]]])
    for i in range(3):
        A[2 * i + 1, 0::2] = -K[i] / m[i]
        A[2 * i + 1, 1::2] = -D[i] / m[i]
    B = np.zeros((6, 1))
    B[5, 0] = 1.0 / m[2]
    C = np.zeros((2, 6))
    C[0, 0] = C[1, 4] = 1.0
    sensors = [Sensor('cart1/joint_states', JOINT_STATE, [0], [0.002], 'c1'),
               Sensor('cart3/joint_states', JOINT_STATE, [1], [0.004], 'c3')]
    return System(A, B, C, np.eye(6)[:, [1, 3, 5]], np.diag(Qc), sensors, 0.02,
                  ['x1', 'v1', 'x2', 'v2', 'x3', 'v3'], ['force'])


def mass_spring(Qc):
    """Return a mass on a spring (x, v) with one position sensor, noise on both states."""
    A = np.array([[0.0, 1.0], [-4.0, -0.4]])
    sensors = [Sensor('mass/joint_states', JOINT_STATE, [0], [0.001], 'm')]
    return System(A, np.array([[0.0], [1.0]]), np.array([[1.0, 0.0]]), np.eye(2),
                  np.diag(Qc), sensors, 0.01, ['x', 'v'], ['force'])


def vehicle_file(sysm, name, path, observer_poles=None):
    """Write a vehicle file of a System (full observer by poles, default -1..-4)."""
    n = sysm.A.shape[0]
    poles = np.linspace(-1.0, -4.0, n) if observer_poles is None else observer_poles
    outputs = [sysm.state_names[int(np.argmax(row))] for row in sysm.C]
    lines = ['/**:', '  ros__parameters:', '    vehicle:', f'      name: {name}',
             '    model:', '      time_domain: continuous',
             f'      states: [{", ".join(sysm.state_names)}]',
             f'      inputs: [{", ".join(sysm.input_names)}]',
             f'      outputs: [{", ".join(outputs)}]',
             f'      A: {_floats(sysm.A)}', f'      B: {_floats(sysm.B)}',
             f'      C: {_floats(sysm.C)}', '    sensors:',
             f'      names: [{", ".join(s.field for s in sysm.sensors)}]']
    for s in sysm.sensors:
        lines += [f'      {s.field}:', f'        topic: {s.topic}',
                  f'        type: {s.msgtype}', f'        fields: [position.{s.field}]',
                  f'        outputs: [{", ".join(outputs[r] for r in s.rows)}]',
                  f'        noise_std: {_floats(s.std)}']
    lines += ['    observer:', '      type: full',
              f'      poles: {_floats(poles)}',
              '    controller:',
              f'      poles: {_floats(-1.0 - 0.1 * np.arange(n))}', '    simulator:',
              f'      rate_hz: {1.0 / sysm.h}', '      duration: 10.0',
              f'      initial_state: {_floats(np.zeros(n))}']
    path = Path(path)
    path.write_text('\n'.join(lines) + '\n')
    return path


def chain_vehicle(path):
    """Write the spring chain's vehicle file (full observer by poles); return its path."""
    s = spring_chain(np.zeros(2))

    def floats(a):
        return '[' + ', '.join(repr(float(v)) for v in np.ravel(a)) + ']'
    text = f"""/**:
  ros__parameters:
    vehicle:
      name: spring_chain
      description: two masses on springs and dampers, force on the second
    model:
      time_domain: continuous
      states: [x1, v1, x2, v2]
      inputs: [force]
      outputs: [x1, x2]
      A: {floats(s.A)}
      B: {floats(s.B)}
      C: {floats(s.C)}
    sensors:
      names: [mass1, mass2]
      mass1:
        topic: mass1/joint_states
        type: sensor_msgs/msg/JointState
        fields: [position.m1]
        outputs: [x1]
        noise_std: [0.002]
      mass2:
        topic: mass2/joint_states
        type: sensor_msgs/msg/JointState
        fields: [position.m2]
        outputs: [x2]
        noise_std: [0.003]
    observer:
      type: full
      poles: [-3.0, -3.1, -3.2, -3.3]
    controller:
      poles: [-1.0, -1.1, -1.2, -1.3]
    simulator:
      rate_hz: 50.0
      duration: 10.0
      initial_state: [0.0, 0.0, 0.0, 0.0]
"""
    path = Path(path)
    path.write_text(text)
    return path
