# test_core_innovation_transient: the initial transient is not a sensor fault.
"""
The submarine's own design on its own data is consistent; a bias or a flipped axis is not.

The closed loop of ``make demo`` (config/submarine.yaml: gyro only, full-order observer,
theta(0) = 30 deg, theta_hat(0) = 0), simulated exactly (ZOH) with the gyro's noise. The
estimate's convergence makes the first window's NIS about 50 times the noise's: judged
from one settling time of the observer's slowest pole on, the design is consistent, in
the node's monitor and in the evaluation's figures alike; a fault after that is named.
"""

from bag_cases import GYRO_NOISE, innovation_run
from bag_synth import write_bag
import numpy as np
from observer_ros.bag.reader import read_recording
from observer_ros.core.health import settling_time
from observer_ros.core.innovation import sequence_health, transient_time
from observer_ros.replay.replay import innovation_health, replay
import pytest


def test_the_transient_is_one_settling_time_of_the_slowest_pole(submarine_design):
    veh, design = submarine_design
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
def test_the_own_design_on_its_own_data_is_consistent(submarine_design, seed):
    monitor, E, since, transient = innovation_run(submarine_design, seed=seed)
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


def test_the_monitor_says_it_is_converging_before_judging(submarine_design):
    monitor, _, _, transient = innovation_run(submarine_design, steps=100)        # 5 s < 6.7 s
    h = monitor.health('gyro')
    assert h.consistent and h.converging and h.samples == 0 and h.transient == 100
    monitor.restart()                                            # an estimator reset
    assert monitor.health('gyro').transient == 0
    monitor.add('gyro', [0.0], None, 50.0)
    monitor.add('gyro', [0.0], None, 50.0 + transient)           # judged again from here
    h = monitor.health('gyro')
    assert h.transient == 1 and h.samples == 1 and not h.converging


@pytest.mark.parametrize('fault', [{'bias': 10 * GYRO_NOISE}, {'sign': -1.0}],
                         ids=['bias', 'flip'])
def test_a_fault_after_the_transient_is_named(submarine_design, fault):
    # from 15 s on (converged); the data stop when the window holds 50 faulty residuals
    monitor, E, since, transient = innovation_run(submarine_design, steps=350, onset=300, **fault)
    h = monitor.health('gyro')
    assert not h.consistent
    assert h.problem.startswith('gyro: residuals too large'), h.problem
    figures = sequence_health('gyro', E, False, since=since, transient=transient)
    assert not figures['consistent'] and figures['windows_inconsistent'] >= 1
    assert figures['problem'].startswith('gyro: ')


@pytest.mark.parametrize('fault', [{}, {'bias': 10 * GYRO_NOISE}], ids=['correct', 'bias'])
def test_observer_eval_judges_as_the_node(submarine_design, fault, tmp_path):
    # the same data recorded and replayed: the evaluation's per-variant figures are the
    # node's (the same core function decides what is transient)
    veh, _ = submarine_design
    monitor, E, since, transient = innovation_run(submarine_design, steps=350, onset=300, **fault)
    bag = write_bag(tmp_path / 'run', innovation_run.messages)
    rep = replay(read_recording(bag, veh), veh, exact=True)
    figures = innovation_health(rep)['gyro']
    h = monitor.health('gyro')
    assert figures['transient'] == h.transient > 100
    assert figures['samples'] == h.samples
    assert figures['consistent'] == h.consistent == (not fault)
    if fault:
        assert figures['problem'].startswith('gyro: residuals too large')
