# test/bag_synth.py: closed-loop runs simulated with numpy and written as real ROS 2 bags.
"""
Synthetic recordings for the bag tool tests.

:func:`simulate` runs a vehicle's closed loop the way the nodes do in lockstep: at each
step the plant simulator publishes /clock and ``state/true``, then each sensor message
in turn; the observer corrects with it (``est.correct(stamp_to_sec(stamp), y, rows)``)
and publishes ``state/estimate`` and ``observer/residual``; the compensator answers with
``control/u`` stamped like the estimate; simulator and observer take that command
(``est.set_input``). The plant is integrated exactly (ZOH). So ``state/estimate`` in the
bag is the live estimate of the vehicle's own design.

:func:`write_bag` serialises the messages with rosbags' typestore (real CDR) and writes
them with rosbags' Writer (mcap or sqlite3), receive time = the sim time at which they
were published, unless told otherwise.

"""

import os
from pathlib import Path
import time

import numpy as np
from observer_ros.bag.bag_checks import RECENT
from observer_ros.core.estimators import make_estimator, process_noise_covariance
from observer_ros.core.model import zoh_matrices
from observer_ros.core.vehicle_design import design_vehicle
from observer_ros.sensors import extract_measurement, fill_measurement
from observer_ros.timeutil import ns_to_sec, sec_to_stamp_parts
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import get_typestore, Stores

STORE = get_typestore(Stores.ROS2_JAZZY)
IMU = 'sensor_msgs/msg/Imu'
JOINT_STATE = 'sensor_msgs/msg/JointState'
FLOAT64 = 'std_msgs/msg/Float64'
CLOCK = 'rosgraph_msgs/msg/Clock'
CONFIG = Path(__file__).resolve().parents[1] / 'config'


def _t(name):
    return STORE.types[name]


def stamp(ns):
    """Return a builtin_interfaces/Time of integer nanoseconds."""
    return _t('builtin_interfaces/msg/Time')(sec=int(ns) // 1_000_000_000,
                                             nanosec=int(ns) % 1_000_000_000)


def header(ns, frame_id=''):
    """Return a std_msgs/Header."""
    return _t('std_msgs/msg/Header')(stamp=stamp(ns), frame_id=frame_id)


def blank(msgtype, ns=0, frame_id=''):
    """Return an all-zero message of one of the types the tests use."""
    if msgtype == IMU:
        q = _t('geometry_msgs/msg/Quaternion')(x=0.0, y=0.0, z=0.0, w=1.0)
        v = _t('geometry_msgs/msg/Vector3')
        return _t(IMU)(header=header(ns, frame_id), orientation=q,
                       orientation_covariance=np.zeros(9),
                       angular_velocity=v(x=0.0, y=0.0, z=0.0),
                       angular_velocity_covariance=np.zeros(9),
                       linear_acceleration=v(x=0.0, y=0.0, z=0.0),
                       linear_acceleration_covariance=np.zeros(9))
    if msgtype == JOINT_STATE:
        return _t(JOINT_STATE)(header=header(ns, frame_id), name=[],
                               position=np.zeros(0), velocity=np.zeros(0),
                               effort=np.zeros(0))
    if msgtype == FLOAT64:
        return _t(FLOAT64)(data=0.0)
    if msgtype == CLOCK:
        return _t(CLOCK)(clock=stamp(ns))
    raise ValueError(msgtype)


def vector_msg(names, values, ns):
    """Return a JointState named vector (state, estimate, command)."""
    msg = blank(JOINT_STATE, ns)
    msg.name = list(names)
    msg.position = np.asarray(values, dtype=np.float64).copy()
    return msg


def control_law(design, vehicle, x_hat):
    """Return u = K (x_d - x_hat) - Kd x_d, as the compensator node."""
    n, m = vehicle.plant.n, vehicle.plant.m
    K = np.asarray(design.K, dtype=float).reshape(m, n)
    c = vehicle.controller
    x_d = np.zeros(n) if c.reference is None else np.asarray(c.reference, float)
    Kd = np.zeros((m, n)) if c.Kd is None else np.asarray(c.Kd, float).reshape(m, n)
    return K @ (x_d - x_hat) - Kd @ x_d


def simulate(vehicle, steps=None, noise=False, seed=0, t0=1.0, closed_loop=True,
             process_noise=None):
    """
    Run the lockstep closed loop; return the published messages in order.

    ``process_noise=(G, Qc)`` adds white process noise ``G w`` of intensity Qc (k x k)
    to a continuous plant (per sample for a discrete one): each step adds noise of the
    exact covariance ``process_noise_covariance(A, Qc, dt, G)`` (``G Qc G^T``).

    Returns
    -------
    run : dict
        ``messages``: list of (relative topic, msgtype, receive ns, message);
        ``x_true``, ``x_hat`` (per step / per estimate), ``t`` (s), ``y`` per sensor.

    """
    plant = vehicle.plant
    dt = vehicle.sample_time
    if plant.is_discrete:
        Ad, Bd = plant.A, plant.B
    else:
        Ad, Bd = zoh_matrices(plant.A, plant.B, dt)
    steps = int(round(vehicle.simulator.duration / dt)) if steps is None else steps
    design = design_vehicle(vehicle)
    est = make_estimator(plant, vehicle.observer)
    rng = np.random.default_rng(seed)
    x = np.array(vehicle.simulator.initial_state, dtype=float)
    u = np.zeros(plant.m)
    S = None
    if process_noise is not None:
        G, Qc = (np.atleast_2d(np.asarray(a, dtype=float)) for a in process_noise)
        Qk = G @ Qc @ G.T if plant.is_discrete else \
            process_noise_covariance(plant.A, Qc, dt, G)
        w, V = np.linalg.eigh(Qk)
        S = V * np.sqrt(np.maximum(w, 0.0))
    messages = []
    xs, estimates, ys = [], [], {s.name: [] for s in vehicle.sensors}
    for k in range(steps + 1):
        ns = int(round((t0 + k * dt) * 1e9))
        sec, nsec = sec_to_stamp_parts(t0 + k * dt)
        ns = sec * 1_000_000_000 + nsec
        messages.append(('/clock', CLOCK, ns, blank(CLOCK, ns)))
        messages.append(('state/true', JOINT_STATE, ns,
                         vector_msg(plant.state_names, x, ns)))
        xs.append((ns, x.copy()))
        for sensor in vehicle.sensors:
            if k % sensor.rate_divider:
                continue
            rows = plant.output_rows(sensor.outputs)
            y = plant.C[rows] @ x + plant.D[rows] @ u
            if noise:
                y = y + rng.standard_normal(len(rows)) * np.asarray(sensor.noise_std)
            msg = blank(sensor.msg_type, ns, sensor.frame_id)
            fill_measurement(msg, sensor, y)
            messages.append((sensor.topic, sensor.msg_type, ns, msg))
            y = extract_measurement(msg, sensor)      # what the observer node reads
            ys[sensor.name].append((ns, np.array(y, dtype=float)))
            # observer node: the stamp (or, for Float64, its clock) in seconds
            x_hat = est.correct(ns_to_sec(ns), y, rows)
            estimates.append((ns, x_hat.copy()))
            messages.append(('state/estimate', JOINT_STATE, ns,
                             vector_msg(plant.state_names, x_hat, ns)))
            messages.append(('observer/residual', JOINT_STATE, ns,
                             vector_msg(sensor.outputs, est.residual, ns)))
            if closed_loop and plant.m:
                u = control_law(design, vehicle, x_hat)
                messages.append(('control/u', JOINT_STATE, ns,
                                 vector_msg(plant.input_names, u, ns)))
                est.set_input(ns_to_sec(ns), u)
        x = Ad @ x + Bd @ u
        if S is not None:
            x = x + S @ rng.standard_normal(plant.n)
    return {'messages': messages, 'x_true': xs, 'x_hat': estimates, 'y': ys,
            'design': design}


def write_bag(path, messages, namespace='', storage='mcap', skip=(), retype=None,
              log_ns=None, version=9, writer_class=Writer):
    """
    Write messages (relative topic, msgtype, receive ns, msg) to a new bag.

    Parameters
    ----------
    path : path-like
        Directory of the new bag.
    messages : iterable of tuple
        (relative topic, msgtype, receive ns, msg), in receive order.
    namespace : str
        Prefix of relative topics ('' or '/sub1').
    storage : {'mcap', 'sqlite3'}
        Storage plugin.
    skip : collection of str
        Topics (relative) left out.
    retype : dict, optional
        Relative topic -> (msgtype, msg factory(msg) -> msg).
    log_ns : sequence of int, optional
        Receive times to use instead of the recorded ones (one per message).
    version : {8, 9}
        The metadata version (8: Humble/Iron, no type hashes; 9: Jazzy).
    writer_class : type
        rosbags' Writer (no chunk CRCs), or observer_ros.bag.integrity.CrcWriter.

    """
    path = Path(path)
    plugin = StoragePlugin.MCAP if storage == 'mcap' else StoragePlugin.SQLITE3
    retype = retype or {}
    conns = {}
    with writer_class(path, version=version, storage_plugin=plugin) as writer:
        for i, (topic, msgtype, ns, msg) in enumerate(messages):
            if topic in skip:
                continue
            if topic in retype:
                msgtype, make = retype[topic]
                msg = make(msg)
            name = topic if topic.startswith('/') else f'{namespace}/{topic}'
            conn = conns.get(name)
            if conn is None:
                conn = writer.add_connection(name, msgtype, typestore=STORE)
                conns[name] = conn
            data = STORE.serialize_cdr(msg, msgtype)
            writer.write(conn, ns if log_ns is None else int(log_ns[i]), data)
    return path


def bag_file(path):
    """Return the storage file of a bag directory."""
    files = [p for p in Path(path).iterdir() if p.suffix in ('.mcap', '.db3')]
    assert len(files) == 1, files
    return files[0]


def at_rest(path):
    """
    Date a bag's files (or one file) back, as a recording closed or killed a minute ago.

    Recovery and the reader watch a storage file changed in the last ``RECENT`` s for a
    writer still at work (bag_checks.still_growing); a test's bag written a moment ago
    would wait out that watch.
    """
    path = Path(path)
    when = time.time() - RECENT - 60.0
    for p in ([path] if path.is_file() else [p for p in path.iterdir() if p.is_file()]):
        os.utime(p, (when, when))
    return path
