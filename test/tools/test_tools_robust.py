"""Tests of ``observer-design --robust``: the search, the file it writes, what it says."""

from pathlib import Path
import warnings

import numpy as np
from observer_ros.core.design_review import review_design
from observer_ros.core.robust_design import loop_figures
from observer_ros.core.vehicle_design import design_vehicle
from observer_ros.params_file import check_parameters_file
from observer_ros.tools.design_report import main as design_main
from observer_ros.vehicle import load_parameters, load_vehicle
import pytest
import yaml

CONFIG = Path(__file__).resolve().parents[2] / 'config'
# README.md's robust design command (its README-commands test leaves it to this file)
README_ROBUST = ('observer-design config/cart_pendulum_two_encoders.yaml --robust --controller '
                 '--settling-time 6 --out cart_pendulum_robust.yaml')


def figures(path):
    v = load_vehicle(path)
    with warnings.catch_warnings():
        warnings.simplefilter('ignore')
        d = design_vehicle(v)
        return v, loop_figures(d, review_design(d, v))


def test_two_encoder_cart_robust_file(tmp_path, capsys):
    readme = (CONFIG.parent / 'README.md').read_text()
    assert README_ROBUST in ' '.join(readme.replace('\\\n', ' ').split())
    out = tmp_path / 'robust.yaml'
    words = README_ROBUST.split()
    assert words[:2] == ['observer-design', 'config/cart_pendulum_two_encoders.yaml']
    rc = design_main([str(CONFIG / 'cart_pendulum_two_encoders.yaml'), *words[2:-1], str(out)])
    text = capsys.readouterr().out
    assert rc == 0 and f'written: {out}' in text
    _, seed = figures(CONFIG / 'cart_pendulum.yaml')
    v, after = figures(out)
    assert after['Ms'] <= 2.5 and after['phase_margin_deg'] >= 25.0
    assert after['delay_margin_s'] >= 0.020
    assert after['settling_s'] <= min(6.0, 2.0 * seed['settling_s'])
    # the ROS params-file rules: /** section, floats in double arrays, no aliases, a bare
    # N (which rcl reads as false) quoted; the header has the figures before and after
    body = out.read_text()
    assert '\n/**:\n' in body and '&id' not in body and '*id' not in body
    check_parameters_file(out)
    events = list(yaml.parse(body))
    assert not any(isinstance(e, yaml.AliasEvent) for e in events)
    flat = load_parameters(out)
    for key in ('model.A', 'controller.poles', 'observer.Qd', 'observer.poles'):
        if key in flat:
            assert all(isinstance(x, float) for x in flat[key]), key
    assert "- 'N'" in body or "['N']" in body
    head = body.split('/**:')[0]
    assert head.startswith('# Written by: observer-design ') and 'before' in head
    assert 'peak sensitivity Ms at the plant input' in head and 'delay margin, ms' in head
    assert flat['vehicle.name'] == 'robust'                 # the file's stem
    assert flat['controller.delay_compensation'] is False
    # never overwritten
    before = out.read_bytes()
    rc = design_main([str(CONFIG / 'cart_pendulum_two_encoders.yaml'), '--robust',
                      '--out', str(out)])
    assert rc == 2 and 'never overwritten' in capsys.readouterr().err
    assert out.read_bytes() == before


def test_encoder_alone_comes_within_1_5x_of_the_bound(tmp_path, capsys):
    out = tmp_path / 'cart_robust.yaml'
    rc = design_main([str(CONFIG / 'cart_pendulum.yaml'), '--robust', '--controller',
                      '--out', str(out)])
    text = capsys.readouterr().out
    assert rc == 0 and 'allow no controller below Ms = 42' in text
    _, seed = figures(CONFIG / 'cart_pendulum.yaml')
    _, after = figures(out)
    # the least Ms any controller reaches is 41.97; the search comes within 1.5x of it,
    # every pole within the default settling bound (twice the seed design's)
    assert 41.9 <= after['Ms'] <= 1.5 * 41.97, text
    assert after['settling_s'] <= 2.0 * seed['settling_s'] + 1e-9
    assert f'{after["Ms"] / 41.97:.2g}x that bound' in text
    assert 'no controller with these outputs reaches Ms 2' in text
    assert 'the sensor set is the obstacle' in text and 'measuring theta' in text


def test_polynomial_search_is_the_loop_it_designs():
    # the characteristic-polynomial stage: its Ms (from a d / phi) is the Ms of the
    # observer-based compensator whose K and L place the same 2n poles
    from observer_ros.core import robust_design as rd
    v = load_vehicle(CONFIG / 'cart_pendulum.yaml')
    search = rd._Search(v, 10.0)
    cand = rd._polynomial_search(search)
    assert cand is not None
    _, K, pc, (kind, po) = cand
    assert kind == 'poles' and len(pc) == len(po) == 4
    P = v.plant
    L = rd._place(P.A.T, P.C.T, po).T
    closed = np.block([[P.A, -P.B @ K], [L @ P.C, P.A - L @ P.C - P.B @ K]])
    assert rd.settling_of(np.linalg.eigvals(closed)) <= 10.0 * (1 + 1e-6)
    assert np.max(np.abs(np.linalg.eigvals(closed))) <= search.fastest * (1 + 1e-6)
    assert 41.97 < search.loop.peak(K, L) <= 1.5 * 41.97


def test_robust_options_go_together(capsys):
    with pytest.raises(SystemExit):
        design_main([str(CONFIG / 'submarine.yaml'), '--settling-time', '3'])
    assert '--robust' in capsys.readouterr().err
    out = design_main([str(CONFIG / 'submarine.yaml'), '--robust', '--settling-time', '-1',
                       '--out', '/nonexistent/never.yaml'])
    assert out == 2 and 'settling-time bound' in capsys.readouterr().err


def test_the_shipped_robust_file_is_what_the_tool_writes():
    # config/cart_pendulum_robust.yaml: the tool's output for the command in its header
    body = (CONFIG / 'cart_pendulum_robust.yaml').read_text()
    assert body.startswith('# Written by: observer-design --robust --controller '
                           '--settling-time 6')
    flat = load_parameters(CONFIG / 'cart_pendulum_robust.yaml')
    source = load_parameters(CONFIG / 'cart_pendulum_two_encoders.yaml')
    for key in ('model.A', 'model.B', 'model.C', 'sensors.encoders.noise_std',
                'controller.reference', 'simulator.rate_hz'):
        assert np.allclose(flat[key], source[key]), key
