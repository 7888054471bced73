"""observer-run's summary: lost or timed-out steps and divergence are failures."""

import importlib.util
from pathlib import Path

from bag_synth import CONFIG, simulate, write_bag
import numpy as np
from observer_ros.core.errors import DesignVerificationError
from observer_ros.evaluation.evaluator import evaluate_bag
from observer_ros.tools.run_closed_loop import (_print_summary, diverging, run_scale,
                                                run_started, summarize_bag)
from observer_ros.vehicle import load_vehicle
import pytest


def _run(tmp_path, drop_every=0, name='bag'):
    vehicle = load_vehicle(str(CONFIG / 'submarine.yaml'), overrides=['simulator.duration:=5.0'])
    run = simulate(vehicle)
    messages = run['messages']
    if drop_every:
        est = [i for i, m in enumerate(messages) if m[0] == 'state/estimate']
        gone = set(est[::drop_every])
        messages = [m for i, m in enumerate(messages) if i not in gone]
    path = tmp_path / name
    write_bag(path, messages)
    return vehicle, summarize_bag(path, vehicle)


def test_complete_run_has_no_problems(tmp_path, capsys):
    vehicle, summary = _run(tmp_path)
    assert summary['lost_steps'] == 0 and summary['expected_steps'] == 101
    assert not summary['diverging']
    assert _print_summary(vehicle, summary) == []
    assert 'FAILED' not in capsys.readouterr().out


def test_lost_estimates_are_reported(tmp_path, capsys):
    vehicle, summary = _run(tmp_path, drop_every=10)
    assert summary['lost_steps'] == 11
    problems = _print_summary(vehicle, summary)
    assert len(problems) == 1 and problems[0].startswith('11 of 101 steps')
    assert 'FAILED: 11 of 101 steps' in capsys.readouterr().out


def test_diverging_trajectory_is_never_settled():
    t = np.arange(300) * 0.05
    grow = np.exp(0.8 * t)[:, None] * np.array([[1.0, -0.5]])
    assert diverging(grow)
    assert diverging(np.array([[1.0], [np.inf]]))
    decay = np.exp(-0.8 * t)[:, None] * np.array([[1.0, -0.5]])
    assert not diverging(decay)
    # 1e57 within the first steps, then "decaying"
    blew = np.concatenate([[[0.45]], [[3e7]], [[1e57]], 1e57 * decay[:, :1]])
    assert diverging(blew)


def test_a_move_from_rest_to_the_reference_converges():
    """The cart from x(0) = 0 to x_d = 1 m: judged by its error from x_d, not by |x(0)|."""
    vehicle = load_vehicle(str(CONFIG / 'cart_pendulum.yaml'))
    scale = run_scale(vehicle)
    assert scale.tolist() == [1.0, 1.0, 1.0, 1.0]      # x_d moves x by 1; the rest take it
    x_d = np.array(vehicle.controller.reference)
    t = np.arange(1001) * 0.01
    move = np.outer(1.0 - np.exp(-t), x_d)
    move[:, 0] = 0.1 * np.exp(-t) * np.sin(3.0 * t)    # the pendulum swings and settles
    assert not diverging(move, x_d, scale)
    # the cart runs away from the reference, 14 m by the end: diverging
    away = np.zeros_like(move)
    away[:, 1] = 1.0 - 1.5 * (1.0 - np.exp(-0.3 * t)) * t
    assert diverging(away, x_d, scale)
    # 100 x the scale anywhere: blown up, even if it comes back
    spike = move.copy()
    spike[10, 0] = 150.0
    assert diverging(spike, x_d, scale)


def test_eval_variant_gains_are_verified_before_replay(tmp_path):
    """observer-eval's variants pass the same design verification."""
    vehicle = load_vehicle(str(CONFIG / 'submarine.yaml'), overrides=['simulator.duration:=1.0'])
    path = tmp_path / 'bag'
    write_bag(path, simulate(vehicle)['messages'])
    bad = ['observer.poles:=null', 'observer.gain:=[0.0, 0.0, -5.0]']
    with pytest.raises(DesignVerificationError, match=r"variant 'bad': observer\.gain does "
                       r'not stabilize the loop: eig\(A - L C\) has the eigenvalue'):
        evaluate_bag(path, vehicle, {'bad': bad})


def test_the_run_limit_counts_from_the_simulators_first_step(tmp_path):
    # observer-run's --timeout counts from the line the simulator logs at its first step
    # (the nodes' start before it, imports and discovery on a loaded host, has its own)
    log = tmp_path / 'plant_simulator.log'
    assert not run_started(log)                                 # not written yet
    log.write_text('[INFO] [1.0] [plant_simulator]: waiting for peers\n')
    assert not run_started(log)
    node = importlib.util.find_spec('observer_ros.nodes.plant_simulator').origin
    source = Path(node).read_text()
    for mode in ('lockstep', 'realtime'):
        assert f"{{self.vehicle.name}}: {mode} run of '" in source
        log.write_text(f'[INFO] [2.0] [plant_simulator]: cart: {mode} run of 1000 steps '
                       'of 0.01 s\n')
        assert run_started(log)
