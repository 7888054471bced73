# test_core_innovation_transient: the initial transient is not a sensor fault.
"""
The submarine's own design on its own data is consistent; a bias or a flipped axis is not.

The closed loop of ``make demo`` (config/submarine.yaml: gyro only, full-order observer,
theta(0) = 30 deg, theta_hat(0) = 0), simulated exactly (ZOH) with the gyro's noise. The
estimate's convergence makes the first window's NIS about 50 times the noise's: judged
from one settling time of the observer's slowest pole on, the design is consistent, in
the node's monitor and in the evaluation's figures alike; a fault after that is named.
"""

from bag_synth import blank, IMU, JOINT_STATE, vector_msg, write_bag
import numpy as np
from observer_ros.bag.reader import read_recording
from observer_ros.core.estimators import make_estimator
from observer_ros.core.health import settling_time
from observer_ros.core.innovation import InnovationMonitor, sequence_health, transient_time
from observer_ros.core.model import zoh_matrices
from observer_ros.core.vehicle_design import design_vehicle
from observer_ros.replay.replay import innovation_health, replay
from observer_ros.sensors import fill_measurement
from observer_ros.vehicle import load_vehicle
import pytest
from ros_helpers import CONFIG

NOISE = 0.001       # rad/s, the file's gyro noise_std


@pytest.fixture(scope='module')
def submarine():
    veh = load_vehicle(CONFIG / 'submarine.yaml')
    return veh, design_vehicle(veh)


def _run(submarine, steps=600, seed=0, sign=1.0, bias=0.0, onset=0, transient=None):
    """
    Close the loop on the estimate; return the monitor and the whitened residuals.

    ``_run.messages`` keeps what a recorder would have: (topic, type, ns, message).
    """
    veh, design = submarine
    plant, dt = veh.plant, veh.sample_time
    if transient is None:
        transient = transient_time(design.observer_poles, dt, plant.is_discrete)
    Ad, Bd = zoh_matrices(plant.A, plant.B, dt)
    rng = np.random.default_rng(seed)
    x = np.array(veh.simulator.initial_state, dtype=float)
    est = make_estimator(plant, veh.observer)
    monitor = InnovationMonitor([('gyro', [NOISE])], kalman=False, transient=transient)
    E, since, msgs = [], [], []
    gyro = veh.sensors[0]
    for k in range(steps):
        ns = 1_000_000_000 + k * int(round(dt * 1e9))
        t = ns * 1e-9
        msgs.append(('state/true', JOINT_STATE, ns, vector_msg(plant.state_names, x, ns)))
        q = (plant.C @ x)[0]
        y = (sign * q + bias if k >= onset else q) + NOISE * rng.normal()
        est.correct(t, [y], (0,))
        monitor.add('gyro', est.residual, None, t)
        E.append(est.residual / NOISE)
        since.append(t - 1.0)
        u = -design.K @ est.x_hat
        est.set_input(t, u)
        x = Ad @ x + Bd @ u
        msg = blank(IMU, ns)
        fill_measurement(msg, gyro, [y])
        msgs.append((gyro.topic, IMU, ns, msg))
        msgs.append(('control/u', JOINT_STATE, ns, vector_msg(plant.input_names, u, ns)))
    _run.messages = msgs
    return monitor, np.array(E), np.array(since), transient


def test_the_transient_is_one_settling_time_of_the_slowest_pole(submarine):
    veh, design = submarine
    t = transient_time(design.observer_poles, veh.sample_time, False)
    assert t == pytest.approx(4.0 / 0.6)                     # poles -0.6, -0.61, -0.62
    assert t == settling_time(design.observer_poles, veh.sample_time)
    # a Kalman filter's S carries the estimation error: judged from the start
    assert transient_time(design.observer_poles, veh.sample_time, kalman=True) == 0.0
    # a pole that does not decay: never judged
    assert transient_time([-1.0, 0.0], 0.05) == np.inf
    # discrete poles: |z| = exp(-0.6 dt)
    z = np.exp(-0.6 * 0.05)
    assert transient_time([z], 0.05, discrete=True) == pytest.approx(4.0 / 0.6)


@pytest.mark.parametrize('seed', range(4))
def test_the_own_design_on_its_own_data_is_consistent(submarine, seed):
    monitor, E, since, transient = _run(submarine, seed=seed)
    h = monitor.health('gyro')
    assert h.consistent, h.problem
    assert h.transient == np.count_nonzero(since < transient) > 100
    assert h.samples == 600 - h.transient
    figures = sequence_health('gyro', E, False, since=since, transient=transient)
    assert figures['consistent'], figures['problem']
    assert figures['windows'] >= 9 and figures['transient'] == h.transient
    # judged from the start, the convergence alone was a WARN (the demo's verdict before)
    everything = sequence_health('gyro', E, False)
    assert not everything['consistent']
    assert everything['problem'].startswith('gyro: residuals too large')


def test_the_monitor_says_it_is_converging_before_judging(submarine):
    monitor, _, _, transient = _run(submarine, steps=100)        # 5 s < 6.7 s
    h = monitor.health('gyro')
    assert h.consistent and h.converging and h.samples == 0 and h.transient == 100
    monitor.restart()                                            # an estimator reset
    assert monitor.health('gyro').transient == 0
    monitor.add('gyro', [0.0], None, 50.0)
    monitor.add('gyro', [0.0], None, 50.0 + transient)           # judged again from here
    h = monitor.health('gyro')
    assert h.transient == 1 and h.samples == 1 and not h.converging


@pytest.mark.parametrize('fault', [{'bias': 10 * NOISE}, {'sign': -1.0}],
                         ids=['bias', 'flip'])
def test_a_fault_after_the_transient_is_named(submarine, fault):
    # from 15 s on (converged); the data stop when the window holds 50 faulty residuals
    monitor, E, since, transient = _run(submarine, steps=350, onset=300, **fault)
    h = monitor.health('gyro')
    assert not h.consistent
    assert h.problem.startswith('gyro: residuals too large'), h.problem
    figures = sequence_health('gyro', E, False, since=since, transient=transient)
    assert not figures['consistent'] and figures['windows_inconsistent'] >= 1
    assert figures['problem'].startswith('gyro: ')


@pytest.mark.parametrize('fault', [{}, {'bias': 10 * NOISE}], ids=['correct', 'bias'])
def test_observer_eval_judges_as_the_node(submarine, fault, tmp_path):
    # the same data recorded and replayed: the evaluation's per-variant figures are the
    # node's (the same core function decides what is transient)
    veh, _ = submarine
    monitor, E, since, transient = _run(submarine, steps=350, onset=300, **fault)
    bag = write_bag(tmp_path / 'run', _run.messages)
    rep = replay(read_recording(bag, veh), veh, exact=True)
    figures = innovation_health(rep)['gyro']
    h = monitor.health('gyro')
    assert figures['transient'] == h.transient > 100
    assert figures['samples'] == h.samples
    assert figures['consistent'] == h.consistent == (not fault)
    if fault:
        assert figures['problem'].startswith('gyro: residuals too large')
