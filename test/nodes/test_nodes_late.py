# test_nodes_late: the observer node with sensors of different latencies, over DDS.
"""Late messages published out of order reach the stamp-order estimate; fixed-rate output."""

import late_sensors
import numpy as np
from numpy.testing import assert_allclose
from observer_ros.core.estimators import make_estimator
from observer_ros.nodes.common import joint_state, SENSOR_QOS, STATE_QOS
from observer_ros.nodes.observer_node import covariance_names
from observer_ros.timeutil import ns_to_sec, stamp_to_sec
import pytest
from ros_helpers import (COMMANDS, GYRO, gyro_msg, innovation_status, level_of,
                         observer_under_test, stamped, WAIT)
from sensor_msgs.msg import JointState

pytestmark = pytest.mark.ros      # processes or DDS participants


def _pitch(ns, theta):
    msg = stamped(JointState(), ns)
    msg.name, msg.position = ['theta'], [float(theta)]
    return msg


@pytest.fixture
def late_observer(tmp_path, request):
    kind, params = request.param
    path = late_sensors.write_vehicle(tmp_path, kind)
    pitch = ('pitch', JointState, SENSOR_QOS)
    with observer_under_test(tmp_path, publish=[GYRO, pitch, COMMANDS], vehicle=path,
                             params=['diagnostics_period:=0.2', *params]) as run:
        pubs = {'gyro': run.pubs['imu/data'], 'pitch': run.pubs['pitch'],
                'u': run.pubs['control/u']}
        yield run.proc, run.probe, run.listener, pubs, late_sensors.vehicle(tmp_path, kind)


@pytest.mark.parametrize('late_observer,commands_late', [
    (('full', ()), False),
    (('full', ()), True),           # the closed loop's commands, 1-5 steps late
    (('kalman', ()), True),
], indirect=['late_observer'])
def test_messages_out_of_order_over_dds_give_the_stamp_order_estimate(late_observer,
                                                                      commands_late):
    proc, probe, listener, pubs, veh = late_observer
    msgs, _ = late_sensors.messages(veh, steps=150)
    if commands_late:               # inserted by superposition, not re-applied
        msgs = late_sensors.commands_late(msgs)
    # one more gyro message after all the others: its answer holds every message before
    last_ns = msgs[-1][1] + 10_000_000
    msgs.append(('gyro', last_ns, max(m[2] for m in msgs) + 1_000_000, 0.001))
    answered = 0
    for kind, ns, _, value in late_sensors.receive_order(msgs):
        if kind == 'u':
            pubs['u'].publish(joint_state(['delta'], [value], ns_to_sec(ns)))
            continue
        pubs[kind].publish(gyro_msg(ns, value) if kind == 'gyro' else _pitch(ns, value))
        answered += 1
        # each measurement is answered by one estimate (the newest, revised if it was late)
        probe.spin_until(lambda: len(listener.estimates) >= answered, WAIT,
                         f'the answer to {kind} stamped {ns}')
    # the reference: the core estimator given the same messages in stamp order
    est = make_estimator(veh.plant, veh.observer)
    for kind, ns, _, value in late_sensors.stamp_order(msgs):
        if kind == 'u':
            est.set_input(ns_to_sec(ns), [value])
        else:
            est.correct(ns_to_sec(ns), [value], (0,) if kind == 'gyro' else (1,))
    final = listener.estimates[-1]
    assert stamp_to_sec(final.header.stamp) == ns_to_sec(last_ns)
    assert_allclose(final.position, est.x_hat, rtol=0.0, atol=1e-9)
    listener.wait_counter('observer', 'late_measurements', 30)
    listener.wait_counter('observer', 'measurements', answered)
    assert listener.counter('observer', 'out_of_order') == 0
    assert listener.counter('observer', 'measurements') == answered
    assert proc.alive(), proc.output()


@pytest.mark.parametrize('late_observer', [('full', ('observer.publish_rate_hz:=50.0',))],
                         indirect=True)
def test_publish_rate_gives_the_prediction_to_now(late_observer):
    proc, probe, listener, pubs, veh = late_observer
    # a measurement stamped now (the node's clock is the system clock): then predictions
    now_ns = probe.node.get_clock().now().nanoseconds
    pubs['gyro'].publish(gyro_msg(now_ns, 0.02))
    t0 = ns_to_sec(now_ns)
    probe.spin_until(lambda: sum(stamp_to_sec(m.header.stamp) > t0
                                 for m in listener.estimates) >= 10, WAIT, '10 predictions')
    est = make_estimator(veh.plant, veh.observer)
    est.correct(t0, [0.02], (0,))
    predictions = [m for m in listener.estimates if stamp_to_sec(m.header.stamp) > t0]
    stamps = [stamp_to_sec(m.header.stamp) for m in predictions]
    assert all(b > a for a, b in zip(stamps, stamps[1:]))
    for msg, t in zip(predictions, stamps):
        probe_est = make_estimator(veh.plant, veh.observer)
        probe_est.restore_state(est.save_state())
        assert_allclose(msg.position, probe_est.predict(t), rtol=1e-9, atol=1e-12)
    listener.wait_counter('observer', 'rate_publications', 1)


@pytest.mark.parametrize('late_observer', [('kalman', ())], indirect=True)
@pytest.mark.parametrize('fault', [(1.0, 0.1, 500), (-1.0, 0.0, 500)], ids=['bias', 'flip'])
def test_a_faulty_sensor_is_named_on_diagnostics(late_observer, fault):
    proc, probe, listener, pubs, veh = late_observer
    # the pitch sensor gets a 0.1 rad bias (10 sigma), or its axis flipped, from step 500;
    # the data stop when the monitor's window (50 pitch readings) holds only faulty ones
    msgs, _ = late_sensors.messages(veh, steps=750, process_noise=True, seed=3,
                                    commands=False, faults={'pitch': fault})
    covariances = []
    sub = probe.node.create_subscription(JointState, 'state/covariance', covariances.append,
                                         STATE_QOS)
    probe.wait_matched(sub, 'state/covariance')
    answered = 0
    for kind, ns, _, value in late_sensors.receive_order(msgs):
        pubs[kind].publish(gyro_msg(ns, value) if kind == 'gyro' else _pitch(ns, value))
        answered += 1
        probe.spin_until(lambda: len(listener.estimates) >= answered, WAIT,
                         f'the answer to {kind} stamped {ns}')
    WARN = 1
    probe.spin_until(lambda: (s := innovation_status(listener, 'pitch')) is not None and
                     level_of(s) == WARN, WAIT, 'an innovation WARN naming pitch')
    status = innovation_status(listener, 'pitch')
    assert status.message.startswith('pitch: residuals'), status.message
    gyro = innovation_status(listener, 'gyro')
    assert level_of(gyro) == 0, gyro.message
    # the node's main status is not changed by it
    assert listener.latest_status('observer').name.endswith('observer')
    # the Kalman covariance of the last estimate, with its stamp: that of the core filter
    # given the messages in stamp order
    est = make_estimator(veh.plant, veh.observer)
    for kind, ns, _, value in late_sensors.stamp_order(msgs):
        est.correct(ns_to_sec(ns), [value], (0,) if kind == 'gyro' else (1,))
    probe.spin_until(lambda: covariances and covariances[-1].header.stamp ==
                     listener.estimates[-1].header.stamp, WAIT, 'the last covariance')
    last = covariances[-1]
    assert last.name == covariance_names(['theta', 'w', 'q'])
    assert last.name[:3] == ['theta,theta', 'theta,w', 'theta,q']
    upper = np.triu_indices(3)
    assert_allclose(last.position, est.P[upper], rtol=1e-9, atol=1e-15)
    assert_allclose(listener.estimates[-1].position, est.x_hat, rtol=0.0, atol=1e-9)
    assert proc.alive(), proc.output()
