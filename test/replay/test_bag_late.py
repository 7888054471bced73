# test_bag_late: bags whose sensors have different latencies, replayed in receive order.
"""A bag in receive order gives the estimates of the same bag in stamp order."""

import json

from bag_cases import late_bag
import control
import late_sensors
import numpy as np
from numpy.testing import assert_allclose, assert_array_equal
from observer_ros.bag.reader import read_recording
from observer_ros.evaluation.evaluate import main as eval_main
from observer_ros.replay.replay import replay
from observer_ros.vehicle import load_vehicle
import pytest


@pytest.fixture(scope='module', params=['full', 'kalman'])
def bags(request, tmp_path_factory):
    tmp = tmp_path_factory.mktemp(f'late_{request.param}')
    veh = late_sensors.vehicle(tmp, request.param)
    msgs, truth = late_sensors.messages(veh)
    received = late_bag(tmp / 'received', veh, late_sensors.stamp_order(msgs), truth)
    stamped = late_bag(tmp / 'stamped', veh, late_sensors.stamp_order(msgs), truth, latency=False)
    return veh, received, stamped, tmp


def test_receive_order_bag_gives_the_stamp_order_estimates(bags):
    veh, received, stamped, _ = bags
    late = replay(read_recording(received, veh), veh, exact=True)
    ref = replay(read_recording(stamped, veh), veh)
    assert late.counts['out_of_order'] == 0
    assert late.counts['late_measurements'] == 60           # every pitch message
    assert late.counts['measurements'] == ref.counts['measurements'] == 360
    assert_array_equal(late.stamp_ns, ref.stamp_ns)
    assert_allclose(late.x_hat, ref.x_hat, rtol=0.0, atol=1e-9)
    # without a history (length 0) all 60 pitch messages are dropped as out of order
    path = late_sensors.write_vehicle(received.parent, veh.observer.kind)
    none = load_vehicle(path, overrides=['observer.history_length:=0.0'])
    dropped = replay(read_recording(received, none), none)
    assert dropped.counts['out_of_order'] == 60
    assert dropped.counts['late_measurements'] == 0


def test_bulk_replay_is_off_for_a_bag_with_late_messages(bags):
    veh, received, _, _ = bags
    rec = read_recording(received, veh)
    assert_array_equal(replay(rec, veh).x_hat, replay(rec, veh, exact=True).x_hat)
    assert replay(rec, veh).bulk_steps == 0


def _evaluated(tmp, vehicle_file, received, stamped):
    """Run observer-eval on both bags; return their results.json (received, stamped)."""
    results = []
    for name, bag in (('received', received), ('stamped', stamped)):
        out = tmp / f'eval_{name}'
        assert eval_main([str(bag), '--vehicle', str(vehicle_file), '--out', str(out),
                          '--no-plots', '--no-bag', '--force']) == 0
        results.append(json.loads((out / 'results.json').read_text()))
    return results


def test_observer_eval_on_receive_order_reports_the_stamp_order_error(bags):
    veh, received, stamped, tmp = bags
    vehicle_file = late_sensors.write_vehicle(tmp, veh.observer.kind)
    got, want = _evaluated(tmp, vehicle_file, received, stamped)
    a = got['variants']['design']['states']
    b = want['variants']['design']['states']
    assert list(a) == ['theta', 'w', 'q']
    for state in a:
        assert a[state]['rmse'] == pytest.approx(b[state]['rmse'], rel=1e-9, abs=1e-15)
    assert got['variants']['design']['counts']['out_of_order'] == 0
    assert np.isfinite([a[state]['rmse'] for state in a]).all()


def _gain_design(veh):
    """Return an ``observer.gain`` line: L placing the continuous poles of FULL_POLES."""
    poles = [float(p) for p in late_sensors.FULL_POLES.strip('[]').split(',')]
    L = control.place(veh.plant.A.T, veh.plant.C.T, poles).T
    return 'gain: [' + ', '.join(f'{v:.17g}' for v in L.reshape(-1)) + ']'


@pytest.mark.parametrize('kind', ['full', 'kalman', 'full_gain'])
def test_late_commands_revise_every_row_to_the_stamp_order(kind, tmp_path):
    # the command answering the estimate at t_k is stamped t_k and arrives after the
    # measurements of the next 1-5 steps: every row between its stamp and its arrival
    # must become the stamp order's (superposition for poles and Kalman, a rewind for a
    # gain), not keep the estimate made before the command came
    base = late_sensors.vehicle(tmp_path, 'kalman' if kind == 'kalman' else 'full')
    design = _gain_design(base) if kind == 'full_gain' else None
    path = late_sensors.write_vehicle(tmp_path, 'kalman' if kind == 'kalman' else 'full',
                                      design=design)
    veh = load_vehicle(path)
    msgs, truth = late_sensors.messages(veh)
    msgs = late_sensors.stamp_order(late_sensors.commands_late(msgs))
    received = late_bag(tmp_path / 'received', veh, msgs, truth)
    stamped = late_bag(tmp_path / 'stamped', veh, msgs, truth, latency=False)
    late = replay(read_recording(received, veh), veh, exact=True)
    ref = replay(read_recording(stamped, veh), veh, exact=True)
    assert late.counts['commands'] == ref.counts['commands'] == 300
    assert late.counts['out_of_order'] == 0
    assert_array_equal(late.stamp_ns, ref.stamp_ns)
    assert_allclose(late.x_hat, ref.x_hat, rtol=0.0, atol=1e-9)
    assert_allclose(late.residual, ref.residual, rtol=0.0, atol=1e-9)
    if kind == 'kalman':
        assert_allclose(late.whitened, ref.whitened, rtol=0.0, atol=1e-6)
    # and observer-eval reports the stamp order's error
    got, want = _evaluated(tmp_path, path, received, stamped)
    a = got['variants']['design']['states']
    b = want['variants']['design']['states']
    for state in a:
        assert a[state]['rmse'] == pytest.approx(b[state]['rmse'], rel=1e-9, abs=1e-15)
