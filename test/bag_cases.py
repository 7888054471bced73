# Bags the replay, evaluation and tuning tests share: how each is made.
"""Recorded runs for the offline tests: cases by name, late and jittered messages, noisy loops."""

import copy
import importlib.util
import json

from bag_synth import (blank, CONFIG, control_law, IMU, JOINT_STATE, simulate, vector_msg,
                       write_bag)
import late_sensors
import numpy as np
from observer_ros.core.estimators import make_estimator, process_noise_covariance
from observer_ros.core.innovation import InnovationMonitor, transient_time
from observer_ros.core.model import zoh_matrices
from observer_ros.evaluation import evaluate as evaluate_cli, evaluator as evaluate
from observer_ros.sensors import fill_measurement
from observer_ros.vehicle import load_vehicle

SAMPLES = CONFIG.parent / 'bags' / 'samples'


TWO = ['model.outputs:=[theta, q]', 'model.C:=[1.0,0.0,0.0, 0.0,0.0,1.0]',
       'model.D:=[0.0, 0.0]', 'sensors.names:=[gyro, pitch]',
       'sensors.pitch.topic:=attitude/pitch', 'sensors.pitch.type:=std_msgs/msg/Float64',
       'sensors.pitch.fields:=[data]', 'sensors.pitch.outputs:=[theta]',
       'sensors.pitch.noise_std:=[0.001]', 'sensors.pitch.rate_divider:=2']


def _shift_commands(messages, lo, hi, by):
    """Stamp the commands received in [lo, hi) ns ``by`` ns later (no bulk there)."""
    out = []
    for topic, msgtype, ns, msg in messages:
        if topic == 'control/u' and lo < ns < hi:
            msg = copy.deepcopy(msg)
            msg.header.stamp = blank(JOINT_STATE, ns + by).header.stamp
        out.append((topic, msgtype, ns, msg))
    return out


def _swap_commands(messages, every=7):
    """Receive u[k] after y[k+1] at every k % every == 3 (a lockstep recording)."""
    out, held, step = [], None, -1
    for item in messages:
        topic, msgtype, ns, msg = item
        step += topic == '/clock'
        if topic == 'control/u' and step % every == 3:
            held = item
            continue
        out.append(item)
        if held is not None and topic not in ('/clock', 'state/true'):
            out.append((held[0], held[1], ns, held[3]))
            held = None
    return out


def make_case(name, tmp):
    if name.startswith('sample_'):           # the sample bags with their vehicles
        bag = name[len('sample_'):]
        return load_vehicle(CONFIG / f'{bag}.yaml'), SAMPLES / bag
    if name in ('late', 'two_stamped'):      # two sensors, received late or at their stamps
        veh = late_sensors.vehicle(tmp, 'full')
        msgs, truth = late_sensors.messages(veh)
        return veh, late_bag(tmp / name, veh, late_sensors.stamp_order(msgs), truth,
                             latency=name == 'late')
    if name == 'loop':                       # the run twice: the stamps jump back
        veh = load_vehicle(CONFIG / 'submarine.yaml')
        msgs = simulate(veh, noise=True, seed=2)['messages']
        span = msgs[-1][2] - msgs[0][2] + 50_000_000
        log = [ns for _, _, ns, _ in msgs] + [ns + span for _, _, ns, _ in msgs]
        return veh, write_bag(tmp / name, msgs + msgs, log_ns=log)
    base, overrides, kwargs, edit = {
        'sub': ('submarine', None, {'noise': True, 'seed': 3}, None),
        'cart_shifted': ('cart_pendulum', ['simulator.initial_state:=[0.05, 0.0, 0.0, 0.0]'],
                         {'noise': True, 'seed': 1},
                         lambda m: _shift_commands(m, 3 * 10**9, 4 * 10**9, 4_000_000)),
        'two_sensors': ('submarine', TWO, {'noise': True}, None),
        'lockstep_swapped': ('submarine', None, {'noise': True, 'seed': 3}, _swap_commands),
        'realtime_swapped': ('submarine', ['simulator.mode:=realtime'],
                             {'noise': True, 'seed': 3}, _swap_commands),
        'reduced': ('submarine_reduced', None, {'noise': True}, None),
        'discrete': ('submarine_discrete', None, {'noise': True}, None),
    }[name]
    veh = load_vehicle(CONFIG / f'{base}.yaml', overrides=overrides)
    messages = simulate(veh, **kwargs)['messages']
    if edit is not None:
        messages = edit(messages)
    return veh, write_bag(tmp / name, messages)


CASES = ['sub', 'cart_shifted', 'two_sensors', 'two_stamped', 'lockstep_swapped',
         'realtime_swapped', 'loop', 'reduced', 'discrete', 'late', 'sample_submarine',
         'sample_cart_pendulum', 'sample_submarine_reduced']


LATE_TOPICS = {'gyro': ('imu/data', IMU), 'pitch': ('pitch', JOINT_STATE)}


def late_bag(path, veh, msgs, truth, latency=True):
    """Write the messages received at their arrival (or, latency=False, stamp) times."""
    sensors = {s.name: s for s in veh.sensors}
    out = [('state/true', JOINT_STATE, ns, vector_msg(veh.plant.state_names, x, ns))
           for ns, x in truth]
    for kind, ns, arrival, value in msgs:
        if kind == 'u':
            out.append(('control/u', JOINT_STATE, arrival if latency else ns,
                        vector_msg(['delta'], [value], ns)))
            continue
        topic, msgtype = LATE_TOPICS[kind]
        msg = blank(msgtype, ns)
        fill_measurement(msg, sensors[kind], [value])
        out.append((topic, msgtype, arrival if latency else ns, msg))
    # receive order; messages received together keep the order of the list (stamp order)
    out.sort(key=lambda m: m[2])
    return write_bag(path, out)


JITTER_NS = 300_000


def jittered(messages, seed=3):
    """Move every step's messages (stamp and receive time) by one jitter of +-0.3 ms."""
    rng = np.random.default_rng(seed)
    shift = {}
    out = []
    for topic, msgtype, ns, msg in messages:
        if ns not in shift:
            shift[ns] = int(rng.integers(-JITTER_NS, JITTER_NS + 1))
        t = ns + shift[ns]
        msg = copy.deepcopy(msg)
        stamp = msg.header.stamp if hasattr(msg, 'header') else msg.clock
        stamp.sec, stamp.nanosec = t // 1_000_000_000, t % 1_000_000_000
        out.append((topic, msgtype, t, msg))
    return out


def p3_benchmark():
    spec = importlib.util.spec_from_file_location(
        'p3_replay', CONFIG.parent / 'benchmarks' / 'p3_replay.py')
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def numbers(rows):
    """Return the rows without their timings, as comparable text (NaN compares equal)."""
    return [json.dumps({k: v for k, v in r.items() if k not in ('seconds', 'cpu_seconds')},
                       sort_keys=True)
            for r in rows]


STEPS = 10_000


# process noise intensity on the input (std per sqrt(s)): large enough to matter
# against each vehicle's measurement noise, small enough to keep the loop near its design
INPUT_NOISE = {'submarine': 0.02, 'cart_pendulum': 0.01}


def true_noise(name):
    v = load_vehicle(CONFIG / f'{name}.yaml')
    q = INPUT_NOISE[name] ** 2
    r = float(v.sensors[0].noise_std[0]) ** 2
    return v, q, r


def simulate_noisy(v, q, seed, steps=STEPS, t0=1.0, x0=None, noise_scale=1.0):
    """
    Return the messages of a closed loop with input noise of intensity q (see above).

    The loop starts at rest (x = 0, where the observers start too) unless ``x0`` is
    given: the vehicle files' initial errors (the submarine's 30 degrees) would make the
    RMSE mostly a measure of one transient, not of the noise. ``noise_scale`` multiplies
    the sensor's noise_std.

    """
    from bag_synth import blank
    from observer_ros.core.vehicle_design import design_vehicle
    from observer_ros.sensors import fill_measurement
    plant, dt = v.plant, v.sample_time
    Ad, Bd = zoh_matrices(plant.A, plant.B, dt)
    w, V = np.linalg.eigh(process_noise_covariance(plant.A, [[q]], dt, plant.B))
    S = V * np.sqrt(np.maximum(w, 0.0))
    design = design_vehicle(v)
    sensor = v.sensors[0]
    rows = plant.output_rows(sensor.outputs)
    std = noise_scale * np.asarray(sensor.noise_std, float)
    rng = np.random.default_rng(seed)
    x = np.zeros(plant.n) if x0 is None else np.asarray(x0, float).copy()
    u = np.zeros(plant.m)
    messages = []
    for k in range(steps + 1):
        ns = int(round(t0 * 1e9)) + k * int(round(dt * 1e9))
        messages.append(('state/true', JOINT_STATE, ns, vector_msg(plant.state_names, x, ns)))
        y = plant.C[rows] @ x + plant.D[rows] @ u + std * rng.standard_normal(len(rows))
        msg = blank(sensor.msg_type, ns, sensor.frame_id)
        fill_measurement(msg, sensor, y)
        messages.append((sensor.topic, sensor.msg_type, ns, msg))
        u = control_law(design, v, x)
        messages.append(('control/u', JOINT_STATE, ns, vector_msg(plant.input_names, u, ns)))
        x = Ad @ x + Bd @ u + S @ rng.standard_normal(plant.n)
    return messages


def spy_on_spill(monkeypatch):
    """Record the ``spill`` argument of every evaluate_bag call; return that list."""
    spills = []
    evaluate_bag = evaluate.evaluate_bag

    def recorded(*args, **kwargs):
        spills.append(kwargs.get('spill'))
        return evaluate_bag(*args, **kwargs)
    # the evaluator's own name (jobs, gain search) and the one observer-eval's main calls
    for module in (evaluate, evaluate_cli):
        monkeypatch.setattr(module, 'evaluate_bag', recorded)
    return spills


GYRO_NOISE = 0.001       # rad/s, the file's gyro noise_std


def innovation_run(submarine, steps=600, seed=0, sign=1.0, bias=0.0, onset=0, transient=None):
    """
    Close the loop on the estimate; return the monitor and the whitened residuals.

    ``innovation_run.messages`` keeps what a recorder would have: (topic, type, ns, message).
    """
    veh, design = submarine
    plant, dt = veh.plant, veh.sample_time
    if transient is None:
        transient = transient_time(design.observer_poles, dt, plant.is_discrete)
    Ad, Bd = zoh_matrices(plant.A, plant.B, dt)
    rng = np.random.default_rng(seed)
    x = np.array(veh.simulator.initial_state, dtype=float)
    est = make_estimator(plant, veh.observer)
    monitor = InnovationMonitor([('gyro', [GYRO_NOISE])], kalman=False, transient=transient)
    E, since, msgs = [], [], []
    gyro = veh.sensors[0]
    for k in range(steps):
        ns = 1_000_000_000 + k * int(round(dt * 1e9))
        t = ns * 1e-9
        msgs.append(('state/true', JOINT_STATE, ns, vector_msg(plant.state_names, x, ns)))
        q = (plant.C @ x)[0]
        y = (sign * q + bias if k >= onset else q) + GYRO_NOISE * rng.normal()
        est.correct(t, [y], (0,))
        monitor.add('gyro', est.residual, None, t)
        E.append(est.residual / GYRO_NOISE)
        since.append(t - 1.0)
        u = -design.K @ est.x_hat
        est.set_input(t, u)
        x = Ad @ x + Bd @ u
        msg = blank(IMU, ns)
        fill_measurement(msg, gyro, [y])
        msgs.append((gyro.topic, IMU, ns, msg))
        msgs.append(('control/u', JOINT_STATE, ns, vector_msg(plant.input_names, u, ns)))
    innovation_run.messages = msgs
    return monitor, np.array(E), np.array(since), transient
