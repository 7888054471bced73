"""Tests of core.design_review and observer-design's robustness section."""

from dataclasses import replace
import json
from pathlib import Path
import warnings

import late_sensors
import numpy as np
from observer_ros.core.design_review import review_design
from observer_ros.core.model import Plant
from observer_ros.core.spec import (ControllerSpec, ObserverSpec, SensorSpec, SimulatorSpec,
                                    Vehicle)
from observer_ros.core.vehicle_design import design_vehicle
from observer_ros.core.vehicle_report import format_report
from observer_ros.tools.design_report import main as design_main
from observer_ros.vehicle import load_vehicle
import pytest

CONFIG = Path(__file__).resolve().parents[2] / 'config'


def reviewed(vehicle):
    with warnings.catch_warnings():
        warnings.simplefilter('ignore')
        d = design_vehicle(vehicle)
        return d, review_design(d, vehicle)


def test_seed_cart_review_states_margins_growth_and_the_limit():
    v = load_vehicle(CONFIG / 'cart_pendulum.yaml')
    d, r = reviewed(v)
    text = format_report(d, v, r)
    assert 'Delay margin at the plant input: 0.576 ms (at 19.7 rad/s)' in text
    assert 'less than one sample (10 ms)' in text
    assert 'every stabilising controller has Ms >= 42' in text
    assert 'the sensor set is the obstacle' in text
    w = '\n'.join(r.warnings)
    for needle in ('phase margin at the plant input', 'delay margin at the plant input',
                   'peak sensitivity at the plant input: Ms = 210', 'transient growth',
                   'reaches a peak sensitivity below 42', 'measuring theta as well'):
        assert needle in w, needle
    # one input, one output: the loop is broken once
    assert [m.side for m in r.margins] == ['input']
    assert r.closed_loop_growth[0] > 100 and r.observer_growth[0] > 100


def test_an_unstable_vehicle_without_command_limits_is_warned():
    """observer-design names the command bound the compensator falls back on."""
    needle = 'the plant is unstable and controller.u_min/u_max are not given'
    cart = load_vehicle(CONFIG / 'cart_pendulum.yaml')
    assert any(w.startswith(needle) for w in design_vehicle(cart).warnings)
    limited = replace(cart, controller=replace(cart.controller, u_min=np.array([-20.0]),
                                               u_max=np.array([20.0])))
    assert not any(w.startswith(needle) for w in design_vehicle(limited).warnings)
    submarine = load_vehicle(CONFIG / 'submarine.yaml')
    assert not any(w.startswith(needle) for w in design_vehicle(submarine).warnings)


def test_shipped_robust_cart_meets_its_margins():
    seed = load_vehicle(CONFIG / 'cart_pendulum.yaml')
    v = load_vehicle(CONFIG / 'cart_pendulum_robust.yaml')
    d, r = reviewed(v)
    (m,) = [m for m in r.margins if m.side == 'input']
    assert m.peak_sensitivity <= 2.5 and m.phase >= 25.0 and m.delay >= 0.020
    ds, _ = reviewed(seed)
    settle = 4.0 / min(-d.closed_loop_poles.real)
    assert settle <= 2.0 * 4.0 / min(-ds.closed_loop_poles.real)
    assert not v.controller.delay_compensation
    assert not any(w.startswith(('pole sensitivity', 'transient growth', 'peak sensitivity'))
                   for w in r.warnings), r.warnings
    # the header states what the design reaches, and the limit of its outputs
    head = (CONFIG / 'cart_pendulum_robust.yaml').read_text().split('/**:')[0]
    assert 'observer-design --robust' in head and 'peak sensitivity Ms' in head


def test_multi_rate_decay_and_growth_against_the_design(tmp_path):
    # gyro 100 Hz, pitch 20 Hz, poles -0.6, -0.7, -0.8: the period map decays slower
    v = late_sensors.vehicle(tmp_path, 'full')
    d, r = reviewed(v)
    sc = d.sampled
    rate = -np.log(sc.spectral_radius) / sc.period
    assert rate < 0.8 * 0.6
    text = '\n'.join(r.lines(d, v.sample_time))
    assert f'decays at {rate:.3g}/s against the designed 0.6/s' in text
    assert r.sampled_growth >= 1.0
    assert any(f'error decays at {rate:.3g}/s' in w and 'of the designed 0.6/s' in w
               for w in r.warnings), r.warnings


def test_deadbeat_and_library_warnings_say_nothing_raw(capsys):
    rc = design_main([str(CONFIG / 'submarine_discrete.yaml'), '-p',
                      'observer.poles:=[0.0, 0.0, 0.0]'])
    out, err = capsys.readouterr()
    assert rc == 0, err
    for raw in ('divide by zero', '-inf', 'RuntimeWarning', 'Convergence was not reached',
                'Badly conditioned', "Falling back to 'frd'"):
        assert raw not in out + err, raw
    rc = design_main([str(CONFIG / 'submarine_discrete.yaml'), '--json'])
    out, _ = capsys.readouterr()

    def refuse(token):
        raise AssertionError(f'{token} in JSON')
    data = json.loads(out, parse_constant=refuse)
    assert data['robustness']['margins'][0]['side'] == 'input'
    assert data['robustness']['fundamental_limit']['ms_bound'] == 1.0


def random_vehicle(seed):
    """Return a random plant with random stable poles, some far from the plant's."""
    rng = np.random.default_rng(seed)
    n = int(rng.integers(2, 6))
    A = rng.normal(size=(n, n)) * 10.0 ** rng.uniform(-1, 1)
    B = rng.normal(size=(n, 1))
    C = rng.normal(size=(1, n))
    spread = 10.0 ** rng.uniform(0, 3)
    cp = -rng.uniform(0.5, 1.0, n) * 10.0 ** rng.uniform(-1, 1, n)
    op = -rng.uniform(0.5, 1.0, n) * spread * 10.0 ** rng.uniform(-1, 1, n)
    plant = Plant(A, B, C, np.zeros((1, 1)))
    sensor = SensorSpec('s', 'y', 'std_msgs/msg/Float64', ('data',), ('y1',), np.array([0.01]))
    return Vehicle(f'rand_{seed}', plant, (sensor,), ObserverSpec('full', poles=op),
                   ControllerSpec(poles=cp), SimulatorSpec(1000.0, np.zeros(n)))


# The random vehicles among seeds 0-39 whose designs grow above 1e4 (the other 32 grow
# less, 9.95e3 at most, or are refused by the verification): the claim's cases, each
# checked to still grow that much.
GROWING_SEEDS = (0, 15, 17, 22, 25, 29, 31, 39)


@pytest.mark.parametrize('seed', GROWING_SEEDS)
def test_every_design_growing_above_1e4_is_warned_of_sensitivity_and_growth(seed):
    v = random_vehicle(seed)
    d, r = reviewed(v)
    assert max(r.closed_loop_growth[0], r.observer_growth[0]) > 1e4, v.name
    assert any(w.startswith('pole sensitivity') for w in r.warnings), v.name
    assert any(w.startswith('transient growth') for w in r.warnings), v.name


def test_review_of_an_observer_without_controller():
    v = load_vehicle(CONFIG / 'submarine.yaml')
    v = replace(v, controller=replace(v.controller, poles=None))
    d, r = reviewed(v)
    assert d.K is None and r.margins == () and r.closed_loop_growth is None
    assert r.sensitivity_of == 'observer error' and r.observer_growth[0] >= 1.0


@pytest.mark.parametrize('name', ['submarine.yaml', 'aircraft_lateral.yaml', 'pitch_imu.yaml',
                                  'submarine_reduced.yaml'])
def test_seed_files_review_without_error(name):
    v = load_vehicle(CONFIG / name)
    d, r = reviewed(v)
    assert r.limit is not None and r.sensitivity is not None
    json.dumps(r.to_json())
