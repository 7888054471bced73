# test_bag_eval.py: bag reading, replay and observer-eval on bags written with rosbags.
"""
Bag tools: decode, replay, metrics, errors and the observer-eval command.

The bags are written in tmp_path with rosbags' own Writer (mcap and sqlite3) from
closed-loop runs simulated here with numpy (test/bag_synth.py: the lockstep nodes'
sequence, exact ZOH plant, u from the estimate of the vehicle's own estimator), so
``state/estimate`` in each bag is the live estimate.

"""

import copy
import json
from pathlib import Path
import pickle
import shutil
import subprocess
import sys

from bag_synth import (at_rest, bag_file, blank, CONFIG, FLOAT64, IMU, JOINT_STATE, simulate,
                       STORE, write_bag)
import numpy as np
from numpy.testing import assert_allclose, assert_array_equal
from observer_ros.bag.errors import BagToolError
from observer_ros.bag.reader import bag_info, decode_messages, read_recording
from observer_ros.core.errors import ObserverError
from observer_ros.evaluation.evaluate import main
from observer_ros.evaluation.evaluator import (evaluate_bag, evaluate_job, parse_tolerance,
                                               parse_variant, whiteness, write_results)
from observer_ros.evaluation.report import format_table
from observer_ros.replay.replay import affine_scan, epochs_of, live_replay, replay
from observer_ros.sensors import extract_measurement
from observer_ros.timeutil import stamp_to_sec
from observer_ros.vehicle import load_vehicle
import pytest

FAST = ['observer.poles:=[-3.0,-3.05,-3.1]']
SLOW = ['observer.poles:=[-0.3,-0.31,-0.32]']


def _vehicle(name, overrides=None):
    return load_vehicle(CONFIG / f'{name}.yaml', overrides=overrides)


class _Lazy(dict):
    """A dict that computes an entry on first use (a failure stays with its tests)."""

    def __init__(self, make):
        super().__init__()
        self._make = make

    def __missing__(self, key):
        value = self._make(key)
        self[key] = value
        return value


_RUNS = {
    'sub': ('submarine', None, {'noise': False}),
    'sub_noisy': ('submarine', None, {'noise': True, 'seed': 3}),
    'cart': ('cart_pendulum', ['simulator.initial_state:=[0.05, 0.0, 0.0, 0.0]'],
             {'noise': False}),
    'cart_noisy': ('cart_pendulum', ['simulator.initial_state:=[0.05, 0.0, 0.0, 0.0]'],
                   {'noise': True, 'seed': 1}),
    'sub_reduced': ('submarine_reduced', None, {'noise': True}),
    # two sensors, one a std_msgs/Float64 without a header (the node stamps it on receipt)
    'sub_two': ('submarine', ['model.outputs:=[theta, q]', 'model.C:=[1.0,0.0,0.0, 0.0,0.0,1.0]',
                              'model.D:=[0.0, 0.0]', 'sensors.names:=[gyro, pitch]',
                              'sensors.pitch.topic:=attitude/pitch',
                              'sensors.pitch.type:=std_msgs/msg/Float64',
                              'sensors.pitch.fields:=[data]', 'sensors.pitch.outputs:=[theta]',
                              'sensors.pitch.noise_std:=[0.001]',
                              'sensors.pitch.rate_divider:=2'], {'noise': True}),
    'cart_reduced': ('cart_pendulum_reduced', None, {'steps': 400, 'noise': True}),
}


@pytest.fixture(scope='module')
def runs():
    """Return the simulated (vehicle, run) pairs, computed on first use."""
    def make(key):
        name, overrides, kwargs = _RUNS[key]
        vehicle = _vehicle(name, overrides)
        return vehicle, simulate(vehicle, **kwargs)
    return _Lazy(make)


@pytest.fixture(scope='module')
def bags(runs, tmp_path_factory):
    """Bags of the runs: key or key_mcap (mcap), key_db3 (sqlite3); submarines in /sub1."""
    root = tmp_path_factory.mktemp('bags')

    def make(name):
        key, _, storage = name.rpartition('_')
        if storage not in ('mcap', 'db3'):
            return out[name + '_mcap']
        ns = '/sub1' if key.startswith('sub') else ''
        return write_bag(root / f'{key}_{storage}', runs[key][1]['messages'], namespace=ns,
                         storage='sqlite3' if storage == 'db3' else 'mcap')
    out = _Lazy(make)
    return out


# ------------------------------------------------------------------------------ decoding

@pytest.mark.parametrize('storage', ['mcap', 'db3'])
@pytest.mark.parametrize('key', ['sub_noisy', 'cart_noisy', 'sub_two', 'sub_reduced'])
def test_bag_decoded_measurements_equal_written(runs, bags, key, storage):
    vehicle, run = runs[key]
    rec = read_recording(bags[f'{key}_{storage}'], vehicle)
    assert rec.namespace == ('/sub1' if key.startswith('sub') else '')
    for sensor in vehicle.sensors:
        stream = rec.sensors[sensor.name]
        written = run['y'][sensor.name]
        assert stream.valid.all()
        assert_array_equal(stream.stamp_ns, [ns for ns, _ in written])
        assert_array_equal(stream.values, np.array([y for _, y in written]))
        assert_array_equal(stream.t, [stamp_to_sec_ns(ns) for ns, _ in written])
        assert stream.bulk == len(stream)            # all decoded from the CDR bytes
    assert_array_equal(rec.truth.values, np.array([x for _, x in run['x_true']]))
    assert_array_equal(rec.estimate.values, np.array([x for _, x in run['x_hat']]))
    assert rec.command is not None and rec.command.valid.all()


def stamp_to_sec_ns(ns):
    """stamp_to_sec of a stamp of ns nanoseconds."""
    class _S:
        sec, nanosec = divmod(int(ns), 1_000_000_000)
    return stamp_to_sec(_S)


def _random_imu(rng, k):
    msg = blank(IMU, int(rng.integers(1, 2**62)) // 4, 'f' * int(rng.integers(0, 24)))
    a = rng.standard_normal(10)
    msg.orientation.x, msg.orientation.w = a[0], a[1]
    msg.angular_velocity.x, msg.angular_velocity.y, msg.angular_velocity.z = a[2:5]
    msg.linear_acceleration.x, msg.linear_acceleration.y = a[5:7]
    msg.linear_acceleration.z = a[7] if k % 7 else np.nan
    msg.angular_velocity_covariance = rng.standard_normal(9)
    return msg


def test_bag_bulk_imu_decode_matches_rosbags_deserialize():
    rng = np.random.default_rng(0)
    msgs = [_random_imu(rng, k) for k in range(200)]
    raws = [bytes(STORE.serialize_cdr(m, IMU)) for m in msgs]
    # big-endian CDR is legal too: the bulk decoder leaves it to the fallback
    raws[5] = bytes(STORE.serialize_cdr(msgs[5], IMU, little_endian=False))
    fields = ('angular_velocity.x', 'angular_velocity.y', 'angular_velocity.z',
              'linear_acceleration.x', 'linear_acceleration.y', 'linear_acceleration.z')
    sensor = _vehicle('pitch_imu').sensors[0]
    sensor = type(sensor)(**{**sensor.__dict__, 'fields': fields,
                             'outputs': tuple(f'y{i}' for i in range(6)),
                             'noise_std': np.ones(6)})

    def fallback(raw):
        msg = STORE.deserialize_cdr(raw, IMU)
        return (msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec,
                extract_measurement(msg, sensor))
    dec = decode_messages(raws, IMU, fields, fallback=fallback)
    assert dec.bulk == len(raws) - 1
    for i, raw in enumerate(raws):
        msg = STORE.deserialize_cdr(raw, IMU)
        assert dec.stamp_ns[i] == msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
        expect = [msg.angular_velocity.x, msg.angular_velocity.y, msg.angular_velocity.z,
                  msg.linear_acceleration.x, msg.linear_acceleration.y,
                  msg.linear_acceleration.z]
        if i % 7 == 0:       # a NaN: invalid, as extract_measurement refuses it
            assert not dec.valid[i]
            with pytest.raises(ObserverError, match='not finite'):
                extract_measurement(msg, sensor)
        else:
            assert dec.valid[i]
            assert_array_equal(dec.values[i], expect)
            assert_array_equal(dec.values[i], extract_measurement(msg, sensor))


def test_bag_bulk_joint_state_decode_matches_rosbags_deserialize():
    rng = np.random.default_rng(1)
    raws, msgs = [], []
    for k in range(400):
        names = list(rng.choice(['cart', 'pole', 'x', 'wheel_long'],
                                size=int(rng.integers(0, 4)), replace=False))
        msg = blank(JOINT_STATE, 10**9 + k, 'b' * int(rng.integers(0, 3)))
        msg.name = names
        msg.position = rng.standard_normal(len(names) if k % 5 else max(0, len(names) - 1))
        msg.velocity = rng.standard_normal(len(names)) if k % 2 else np.zeros(0)
        msgs.append(msg)
        raws.append(bytes(STORE.serialize_cdr(msg, JOINT_STATE)))
    for fields, mode in ((('position.cart', 'velocity.x'), 'sensor'),
                         (('position.cart', 'position.x'), 'vector')):
        dec = decode_messages(raws, JOINT_STATE, fields, mode=mode, max_layouts=10**6)
        assert dec.bulk == len(raws)
        for i, msg in enumerate(msgs):
            idx = {n: j for j, n in enumerate(msg.name)}
            expect = []
            for f in fields:
                array, _, joint = f.partition('.')
                values = getattr(msg, array)
                expect.append(values[idx[joint]] if joint in idx and idx[joint] < len(values)
                              else np.nan)
            expect = np.array(expect)
            if mode == 'vector' and len(msg.position) != len(msg.name):
                expect[:] = np.nan
            assert dec.valid[i] == bool(np.isfinite(expect).all())
            if dec.valid[i]:
                assert_array_equal(dec.values[i], expect)
            assert dec.stamp_ns[i] == 10**9 + i


def test_bag_float64_sensor_uses_receive_time(runs, bags):
    vehicle, run = runs['sub_two']
    rec = read_recording(bags['sub_two'], vehicle)
    pitch = rec.sensors['pitch']
    assert pitch.msgtype == FLOAT64 and not pitch.has_header
    assert_array_equal(pitch.stamp_ns, pitch.log_ns)


# ------------------------------------------------------------------------------ replay

@pytest.mark.parametrize('storage', ['mcap', 'db3'])
@pytest.mark.parametrize('key', ['sub', 'sub_noisy', 'cart', 'cart_noisy', 'sub_two',
                                 'sub_reduced', 'cart_reduced'])
def test_bag_replay_of_design_reproduces_live_estimate(runs, bags, key, storage):
    vehicle, _ = runs[key]
    rec = read_recording(bags[f'{key}_{storage}'], vehicle)
    live = live_replay(rec, vehicle)
    exact = replay(rec, vehicle, exact=True)
    # call by call: bit for bit what the node computed
    assert_array_equal(exact.stamp_ns, live.stamp_ns)
    assert_array_equal(exact.x_hat, live.x_hat)
    assert exact.counts['clock_jumps'] == 0 and exact.counts['out_of_order'] == 0
    # bulk replay: the same to round-off
    bulk = replay(rec, vehicle)
    if len(vehicle.sensors) == 1:
        assert bulk.bulk_steps > 0.9 * len(bulk), bulk.warnings
    scale = np.max(np.abs(live.x_hat), axis=0) + 1.0
    assert_allclose(bulk.x_hat / scale, live.x_hat / scale, rtol=0, atol=1e-10)
    assert_allclose(bulk.residual, exact.residual, rtol=0, atol=1e-9)
    assert_array_equal(bulk.seq, exact.seq)


@pytest.mark.parametrize('overrides', [['observer.type:=open_loop'], FAST,
                                       ['observer.type:=kalman',
                                        'observer.Qd:=[0.0,0.0,0.0,0.0,0.0,0.0,0.0,0.0,1.0e-6]',
                                        'observer.Rd:=[1.0e-6]']])
def test_bag_bulk_replay_equals_exact_replay(runs, bags, overrides):
    vehicle, _ = runs['sub_noisy']
    variant = load_vehicle(CONFIG / 'submarine.yaml', overrides=overrides)
    rec = read_recording(bags['sub_noisy'], vehicle)
    exact = replay(rec, variant, exact=True)
    bulk = replay(rec, variant)
    assert_allclose(bulk.x_hat, exact.x_hat, rtol=1e-9, atol=1e-12)
    # the Kalman filter too: its covariance recursion, then its steady-state gains
    assert bulk.bulk_steps >= len(bulk) - 1 and not bulk.warnings


def test_bag_commands_off_the_estimate_stamps_are_replayed_call_by_call(runs, tmp_path):
    """Commands stamped between measurements propagate inside a step: no bulk there."""
    vehicle, run = runs['cart_noisy']
    messages = []
    for topic, msgtype, ns, msg in run['messages']:
        if topic == 'control/u' and 3 * 10**9 < ns < 4 * 10**9:
            msg = copy.deepcopy(msg)
            msg.header.stamp = blank(JOINT_STATE, ns + 4_000_000).header.stamp
        messages.append((topic, msgtype, ns, msg))
    bag = write_bag(tmp_path / 'shifted', messages)
    rec = read_recording(bag, vehicle)
    exact = replay(rec, vehicle, exact=True)
    bulk = replay(rec, vehicle)
    assert 0 < bulk.bulk_steps < len(bulk)
    assert_allclose(bulk.x_hat, exact.x_hat, rtol=1e-9, atol=1e-10)


def _swap_commands(messages, every=7):
    """
    Reorder as the recorder receives in lockstep: u[k] after y[k+1], at every k % every == 3.

    The command and the next step's messages come from different processes; the
    command is moved after the next sensor message and received with it.

    """
    msgs = list(messages)
    out, held = [], None
    step = -1
    for item in msgs:
        topic, msgtype, ns, msg = item
        if topic == '/clock':
            step += 1
        if topic == 'control/u' and step % every == 3:
            held = item
            continue
        out.append(item)
        if held is not None and topic not in ('/clock', 'state/true'):
            out.append((held[0], held[1], ns, held[3]))     # received with y[k+1]
            held = None
    return out


def test_bag_lockstep_replay_takes_the_nodes_order_not_the_receive_order(runs, tmp_path):
    """The live run: y[k], x_hat[k], u[k], y[k+1]; the bag may hold y[k+1] before u[k]."""
    vehicle, run = runs['sub_noisy']
    swapped = _swap_commands(run['messages'])
    bag = write_bag(tmp_path / 'swapped', swapped)
    rec = read_recording(bag, vehicle)
    live = live_replay(rec, vehicle)
    u, y = rec.command, rec.sensors['gyro']
    late = u.seq[:-1] > y.seq[1:len(u)]                    # u[k] received after y[k+1]
    assert late.sum() == len(range(3, len(u) - 1, 7))
    exact = replay(rec, vehicle, exact=True)
    assert_array_equal(exact.x_hat, live.x_hat)
    bulk = replay(rec, vehicle)
    assert not bulk.warnings and bulk.bulk_steps >= len(bulk) - 1
    assert_allclose(bulk.x_hat, live.x_hat, rtol=0, atol=1e-14)
    # a free-running node takes messages as received: u[k] after y[k+1] is a late command,
    # applied from its stamp, and the row of y[k+1] is revised (it differed by more than
    # 1e-6 before the replay revised rows after late commands): the stamp order's rows,
    # which the lock-step node computed live
    free = load_vehicle(CONFIG / 'submarine.yaml', overrides=['simulator.mode:=realtime'])
    as_received = replay(rec, free, exact=True)
    assert_allclose(as_received.x_hat, live.x_hat, rtol=0, atol=1e-12)
    assert_allclose(replay(rec, free).x_hat, as_received.x_hat, rtol=0, atol=1e-14)


def test_bag_bulk_self_check_catches_a_discrepancy_anywhere(runs, tmp_path, monkeypatch):
    """A wrong input or a wrong step anywhere in a stretch: replayed call by call."""
    import observer_ros.replay.bulk_replay as bulk_module
    vehicle, run = runs['sub_noisy']
    rec = read_recording(write_bag(tmp_path / 'swapped', _swap_commands(run['messages'])),
                         vehicle)
    live = live_replay(rec, vehicle)

    def bag_order_inputs(run, cmd, u0, a, b):
        """Return the input of the last command before each measurement in bag order (wrong)."""
        kind, seq, idx = run['kind'], run['seq'], run['idx']
        pos = np.flatnonzero(kind < 0)
        order = np.argsort(seq[pos], kind='stable')
        c_seq, c_idx = seq[pos][order], idx[pos][order]
        mseq = seq[run['mev']]                   # seq of each measurement
        U = np.empty((b - a, u0.size))
        U[:] = u0
        last = np.searchsorted(c_seq, mseq[a + 1:b + 1]) - 1
        ok = last >= 0
        ok[ok] = c_seq[last[ok]] > mseq[a]
        U[ok] = cmd.values[c_idx[last[ok]]]
        return U
    monkeypatch.setattr(bulk_module, '_held_inputs', bag_order_inputs)
    rep = replay(rec, vehicle)
    assert rep.bulk_steps == 0 and 'bulk replay disabled' in rep.warnings[0]
    assert_array_equal(rep.x_hat, live.x_hat)
    monkeypatch.undo()
    scan = bulk_module.affine_scan
    for where in (0.3, 0.77, 0.999):
        def bad_scan(F, W, x0, steps=None, chunk=1 << 16, where=where):
            X = scan(F, W, x0, steps, chunk)
            X[int(where * len(X)), 1] += 1e-8 * np.max(np.abs(X))      # one step
            return X
        monkeypatch.setattr(bulk_module, 'affine_scan', bad_scan)
        rep = replay(rec, vehicle)
        assert rep.bulk_steps == 0 and 'bulk replay disabled' in rep.warnings[0], where
        assert_array_equal(rep.x_hat, live.x_hat)


def test_bag_clock_jump_back_resets_like_the_node(runs, tmp_path):
    """A looping bag: stamps jump back (receive times go on); the estimator restarts."""
    vehicle, run = runs['sub']
    msgs = run['messages']
    span = msgs[-1][2] - msgs[0][2] + 50_000_000
    log = [ns for _, _, ns, _ in msgs] + [ns + span for _, _, ns, _ in msgs]
    bag = write_bag(tmp_path / 'loop', msgs + msgs, namespace='/sub1', log_ns=log)
    rec = read_recording(bag, vehicle)
    for exact in (True, False):
        # the node's rule: the first two messages of the second loop are far back
        # (skipped), the third in a row is the clock jump
        rep = replay(rec, vehicle, exact=exact)
        assert rep.counts['clock_jumps'] == 1 and rep.counts['far_back_stamps'] == 2
        half = int(np.argmax(rep.epoch))
        assert len(rep) == 2 * half - 2
        assert_array_equal(rep.epoch[:half], 0)
        assert_array_equal(rep.epoch[half:], 1)
        assert_array_equal(rep.stamp_ns[half:], rep.stamp_ns[2:half])
        # a jump at the first message back: the second loop replays the first
        rep = replay(rec, vehicle, exact=exact, clock_jump_agreement=1)
        assert rep.counts['clock_jumps'] == 1
        half = len(rep) // 2
        assert_array_equal(rep.epoch[:half], 0)
        assert_array_equal(rep.epoch[half:], 1)
        assert_allclose(rep.x_hat[half:], rep.x_hat[:half], rtol=0, atol=1e-12)
    result = evaluate_bag(bag, vehicle, clock_jump_agreement=1)
    design = result.variants['design']
    assert design.summary['matched'] == len(design.replay)
    assert result.variants['live'].replay.counts['clock_jumps'] == 1
    single = evaluate_bag(_bag(run, tmp_path / 'once'), vehicle).variants['design']
    for state in vehicle.plant.state_names:
        assert design.states[state]['rmse'] == pytest.approx(single.states[state]['rmse'])
        assert design.states[state]['settling_time'] == pytest.approx(
            single.states[state]['settling_time'])


def _bag(run, path, **kwargs):
    kwargs.setdefault('namespace', '/sub1')
    return write_bag(path, run['messages'], **kwargs)


def test_bag_affine_scan_equals_the_recursion():
    rng = np.random.default_rng(2)
    F = rng.standard_normal((3, 4, 4)) * 0.4
    steps = rng.integers(0, 3, size=5000)
    W = rng.standard_normal((5000, 4))
    x = rng.standard_normal(4)
    X = affine_scan(F, W, x, steps, chunk=777)
    ref = np.empty_like(W)
    for k in range(W.shape[0]):
        x = F[steps[k]] @ x + W[k]
        ref[k] = x
    assert_allclose(X, ref, rtol=1e-10, atol=1e-12)


def test_bag_epochs_of_stamps():
    s = np.array([1, 2, 3, 1, 2, 3, 3, 2, 1], dtype=np.int64) * 10**9
    assert_array_equal(epochs_of(s, 0.5), [0, 0, 0, 1, 1, 1, 1, 2, 3])
    assert_array_equal(epochs_of(s, 2.5), 0)
    assert_array_equal(epochs_of(s[:3], 0.5), [0, 0, 0])


# ------------------------------------------------------------------------------ metrics

def test_bag_metrics_design_beats_open_loop_on_the_unstable_cart(runs, bags):
    vehicle, _ = runs['cart']
    result = evaluate_bag(bags['cart'], vehicle,
                          {'openloop': ['observer.type:=open_loop']})
    design, openloop = result.variants['design'], result.variants['openloop']
    assert design.summary['error_rms'] < 0.1 * openloop.summary['error_rms']
    for state in vehicle.plant.state_names:
        assert design.states[state]['rmse'] < openloop.states[state]['rmse']
    # noise-free: the design converges to round-off, the open loop diverges
    assert design.states['theta']['ss_std'] < 1e-9
    assert openloop.summary['settling_time'] == np.inf
    # printed 'never' (not the bag's length, nor inf) where the error never settles
    settle = [line.split()[5] for line in format_table(result).splitlines()
              if line.startswith('openloop ') and line.split()[1] in vehicle.plant.state_names]
    settle = settle[:vehicle.plant.n]               # the states' table comes first
    assert 'never' in settle, settle
    assert all(s == 'never' or np.isfinite(float(s)) for s in settle), settle
    # the live estimate is the design's
    for state in vehicle.plant.state_names:
        assert result.variants['live'].states[state]['rmse'] == pytest.approx(
            design.states[state]['rmse'], rel=1e-9)


def test_bag_evaluate_job_is_one_variant_of_evaluate_bag_as_plain_data(runs, bags):
    vehicle, _ = runs['sub_noisy']
    path = CONFIG / 'submarine.yaml'
    full = evaluate_bag(bags['sub_noisy'], path, {'fast': FAST})
    for name, overrides in (('design', ()), ('fast', FAST), ('live', ())):
        job = evaluate_job(bags['sub_noisy'], str(path), name, overrides)
        job = pickle.loads(pickle.dumps(job))        # crosses processes as it is
        vr = full.variants[name]
        assert job.variant == name and job.estimates == len(vr.replay)
        assert job.ground_truth
        for state in vehicle.plant.state_names:
            assert job.states[state]['rmse'] == vr.states[state]['rmse']
        assert job.outputs['q']['ljung_box_q'] == vr.outputs['q']['ljung_box_q']
        json.dumps(job.to_dict())
    with pytest.raises(BagToolError, match='takes no overrides'):
        evaluate_job(bags['sub_noisy'], str(path), 'design', FAST)


def test_bag_metrics_faster_poles_let_more_noise_through(runs, bags):
    vehicle, _ = runs['sub_noisy']
    result = evaluate_bag(bags['sub_noisy'], vehicle, {'fast': FAST})
    design, fast = result.variants['design'], result.variants['fast']
    for state in vehicle.plant.state_names:
        assert fast.states[state]['ss_std'] > 2.0 * design.states[state]['ss_std'], state


def test_bag_metrics_slow_poles_settle_later(runs, bags):
    vehicle, _ = runs['sub']
    result = evaluate_bag(bags['sub'], vehicle, {'slow': SLOW, 'fast': FAST})
    settle = {name: v.summary['settling_time'] for name, v in result.variants.items()}
    assert settle['fast'] < settle['design'] < settle['slow']
    assert np.isfinite(settle['design'])
    # tolerance: 2 % of the true range by default; absolute or a percentage when asked
    theta = np.array([x for _, x in runs['sub'][1]['x_true']])[:, 0]
    assert result.tolerance['theta'] == pytest.approx(0.02 * np.ptp(theta))
    wide = evaluate_bag(bags['sub'], vehicle, tolerance='10%')
    assert wide.tolerance['theta'] == pytest.approx(0.1 * np.ptp(theta))
    assert wide.variants['design'].summary['settling_time'] < settle['design']
    assert evaluate_bag(bags['sub'], vehicle, tolerance=0.5).tolerance['w'] == 0.5


def test_bag_residual_whiteness():
    rng = np.random.default_rng(0)
    white = whiteness(rng.standard_normal(5000))
    assert white['ljung_box_p'] > 0.01 and white['acf_outside'] <= 0.2
    walk = whiteness(np.cumsum(rng.standard_normal(5000)))
    assert walk['ljung_box_p'] < 1e-6 and walk['acf_outside'] == 1.0
    assert whiteness([])['samples'] == 0


def test_bag_eval_without_ground_truth_scores_residuals(runs, tmp_path):
    vehicle, run = runs['sub_noisy']
    bag = _bag(run, tmp_path / 'notruth', skip=('state/true',))
    result = evaluate_bag(bag, vehicle, {'fast': FAST})
    assert result.truth is None
    for v in result.variants.values():
        assert not v.states
        q = v.outputs['q']
        assert q['samples'] == len(v.replay) and q['residual_rms'] > 0
        assert 0.0 <= q['ljung_box_p'] <= 1.0
    files = write_results(result, tmp_path / 'out')
    assert {f.name for f in files} >= {'results.csv', 'results.json', 'states.png',
                                       'residuals.png', 'results_bag'}


# ------------------------------------------------------------------------------ errors

def _error(path, vehicle, match, **kwargs):
    with pytest.raises(BagToolError, match=match):
        evaluate_bag(path, vehicle, **kwargs)


def _cli_error(argv, capsys, match):
    assert main([str(a) for a in argv]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith('error: '), err
    assert match in err[0], err[0]


def test_bag_errors_missing_path_and_not_a_bag(runs, tmp_path, capsys):
    vehicle, _ = runs['sub']
    _error(tmp_path / 'nope', vehicle, 'no such file or directory')
    (tmp_path / 'notes.txt').write_text('hello')
    _error(tmp_path / 'notes.txt', vehicle, 'not a bag')
    (tmp_path / 'empty_dir').mkdir()
    _error(tmp_path / 'empty_dir', vehicle, 'not a bag: the directory has no metadata.yaml')
    (tmp_path / 'junk.mcap').write_bytes(b'\x00' * 100)
    _error(tmp_path / 'junk.mcap', vehicle, 'junk.mcap: cannot read the bag')
    _cli_error([tmp_path / 'nope', '--vehicle', CONFIG / 'submarine.yaml', '--out',
                tmp_path / 'o'], capsys, 'no such file or directory')


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_bag_errors_empty_bag(runs, tmp_path, storage, capsys):
    vehicle, _ = runs['sub']
    bag = write_bag(tmp_path / 'empty', [], storage=storage)
    _error(bag, vehicle, 'the bag is empty')
    from rosbags.rosbag2 import StoragePlugin, Writer
    only_conn = tmp_path / 'conn_only'
    plugin = StoragePlugin.MCAP if storage == 'mcap' else StoragePlugin.SQLITE3
    with Writer(only_conn, version=9, storage_plugin=plugin) as w:
        w.add_connection('/sub1/imu/data', IMU, typestore=STORE)
    _error(only_conn, vehicle, 'the bag is empty')
    _cli_error([bag, '--vehicle', CONFIG / 'submarine.yaml', '--out', tmp_path / 'o'],
               capsys, 'the bag is empty')


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_bag_errors_truncated_file(runs, tmp_path, storage, capsys):
    vehicle, run = runs['sub']
    bag = _bag(run, tmp_path / 'cut', storage=storage)
    f = bag_file(bag)
    data = f.read_bytes()
    f.write_bytes(data[:len(data) // 2])
    _error(bag, vehicle, f'{f.name}: cannot read the bag')
    _cli_error([bag, '--vehicle', CONFIG / 'submarine.yaml', '--out', tmp_path / 'o'],
               capsys, 'cannot read the bag')
    assert not (tmp_path / 'o').exists()


def test_bag_missing_metadata_reads_the_storage_file(runs, bags, tmp_path):
    vehicle, _ = runs['sub']
    bag = at_rest(shutil.copytree(bags['sub'], tmp_path / 'nometa'))
    (bag / 'metadata.yaml').unlink()
    rec = read_recording(bag, vehicle)
    assert any('metadata.yaml is missing (a recording that was not closed? '
               f'`observer-bag-recover {bag}` completes it); reading' in w
               for w in rec.warnings)
    assert len(rec.sensors['gyro']) == 601
    # a bare storage file is a bag too
    assert bag_info(bag_file(bag)).message_count == bag_info(bags['sub']).message_count
    (bag / 'copy.mcap').write_bytes(bag_file(bags['sub_noisy']).read_bytes())
    _error(bag, vehicle, 'metadata.yaml is missing and the directory holds 2 storage files')


def test_bag_errors_missing_topic(runs, tmp_path, capsys):
    vehicle, run = runs['sub']
    bag = _bag(run, tmp_path / 'nogyro', skip=('imu/data',))
    _error(bag, vehicle, r"bag has no messages on /sub1/imu/data \(sensor 'gyro' of vehicle "
                         r'submarine\); topics in the bag: /clock')
    _error(bag, vehicle, r'no messages on /other/imu/data', namespace='/other')
    _cli_error([bag, '--vehicle', CONFIG / 'submarine.yaml', '--out', tmp_path / 'o'],
               capsys, "no messages on /sub1/imu/data (sensor 'gyro'")


def test_bag_errors_wrong_topic_type(runs, tmp_path, capsys):
    vehicle, run = runs['sub']

    def as_joint_state(msg):
        js = blank(JOINT_STATE)
        js.header = msg.header
        return js
    bag = _bag(run, tmp_path / 'retyped', retype={'imu/data': (JOINT_STATE, as_joint_state)})
    _error(bag, vehicle, 'topic /sub1/imu/data is sensor_msgs/msg/JointState in the bag; '
                         "sensor 'gyro' of vehicle submarine expects sensor_msgs/msg/Imu")
    _cli_error([bag, '--vehicle', CONFIG / 'submarine.yaml', '--out', tmp_path / 'o'],
               capsys, 'expects sensor_msgs/msg/Imu')


def test_bag_errors_vehicle_outputs_not_in_the_bag(runs, tmp_path, capsys):
    """The cart's encoder joint is 'cart'; a bag whose JointState names another joint."""
    vehicle, run = runs['cart']

    def rename(msg):
        msg = copy.deepcopy(msg)        # the run's messages are shared by the module's bags
        msg.name = ['rail']
        return msg
    bag = write_bag(tmp_path / 'renamed', run['messages'],
                    retype={'joint_states': (JOINT_STATE, rename)})
    _error(bag, vehicle, r"none of the 1001 messages on /joint_states gives the outputs \['x'\] "
                         r"of sensor 'encoder'.*joint 'cart' is not in JointState.name \['rail'\]")
    # a vehicle whose sensors are not in the bag at all
    _error(bag, runs['sub'][0], 'no messages on /imu/data')
    _cli_error([bag, '--vehicle', CONFIG / 'cart_pendulum.yaml', '--out', tmp_path / 'o'],
               capsys, "joint 'cart' is not in JointState.name")


def test_bag_errors_definition_from_another_release(runs, tmp_path):
    """A bag whose Imu definition differs from Jazzy's (another ROS release or a fork)."""
    vehicle, _ = runs['sub']
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import get_types_from_msg, get_typestore, Stores
    jazzy = get_typestore(Stores.ROS2_JAZZY)
    store = get_typestore(Stores.EMPTY)
    store.register({k: v for k, v in jazzy.fielddefs.items() if k != IMU})
    store.register(get_types_from_msg(
        'std_msgs/Header header\nfloat64 extra\n'
        'geometry_msgs/Quaternion orientation\nfloat64[9] orientation_covariance\n'
        'geometry_msgs/Vector3 angular_velocity\nfloat64[9] angular_velocity_covariance\n'
        'geometry_msgs/Vector3 linear_acceleration\n'
        'float64[9] linear_acceleration_covariance\n', IMU))
    # consistent definition and hash, but not Jazzy's: our check names it
    bag = tmp_path / 'other'
    with Writer(bag, version=9) as w:
        conn = w.add_connection('/sub1/imu/data', IMU, typestore=store)
        w.write(conn, 10**9, b'\x00\x01\x00\x00' + bytes(400))
    _error(bag, vehicle, r"/sub1/imu/data \(sensor 'gyro'\): the bag's sensor_msgs/msg/Imu "
                         r"has type hash RIHS01_.*; ROS 2 Jazzy's is RIHS01_7d9a00ff")
    # a definition that does not match its own hash: rosbags refuses it, we name the file
    msgdef, _ = store.generate_msgdef(IMU, ros_version=2)
    bad = tmp_path / 'bad'
    with Writer(bad, version=9) as w:
        conn = w.add_connection('/sub1/imu/data', IMU, msgdef=msgdef,
                                rihs01='RIHS01_' + '0' * 64)
        w.write(conn, 10**9, b'\x00\x01\x00\x00' + bytes(400))
    _error(bad, vehicle, r'bad.db3: cannot read the bag: .*hash mismatch')


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
@pytest.mark.parametrize('version', [8, 9])
def test_bag_written_by_rosbags_any_version_in_a_namespace(runs, tmp_path, storage, version):
    """Read rosbags' own Writer's bag, metadata version 8 (Iron) or 9 (Jazzy), in /sub1."""
    vehicle, run = runs['sub_noisy']
    bag = write_bag(tmp_path / f'v{version}', run['messages'], namespace='/sub1',
                    storage=storage, version=version)
    import yaml
    meta = yaml.safe_load((bag / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    assert meta['version'] == version
    assert meta['storage_identifier'] == storage
    rec = read_recording(bag, vehicle)                      # namespace not given
    assert rec.namespace == '/sub1' and rec.topics.sensors['gyro'] == '/sub1/imu/data'
    # no warning but the note that rosbags' Writer leaves the bag without checksums
    assert [w for w in rec.warnings if 'checksum' not in w and 'CRC' not in w] == []
    assert len(rec.warnings) == 1
    live = live_replay(rec, vehicle)
    assert len(live) == len(run['x_hat'])
    assert_array_equal(replay(rec, vehicle, exact=True).x_hat, live.x_hat)
    assert_allclose(replay(rec, vehicle).x_hat, live.x_hat, rtol=0, atol=1e-14)
    info = bag_info(bag)
    assert info.message_count == len(run['messages'])


def test_bag_namespace_detection(runs, tmp_path):
    vehicle, run = runs['sub']
    both = tmp_path / 'two'
    msgs = run['messages']
    ns2 = [(t if t.startswith('/') else f'/sub2/{t}', mt, ns, m) for t, mt, ns, m in msgs]
    write_bag(both, [(t if t.startswith('/') else f'/sub1/{t}', mt, ns, m)
                     for t, mt, ns, m in msgs] + ns2)
    _error(both, vehicle, r"under several namespaces \('/sub1', '/sub2'\); choose one with "
                          r'--namespace')
    rec = read_recording(both, vehicle, namespace='sub2')
    assert rec.namespace == '/sub2' and rec.topics.sensors['gyro'] == '/sub2/imu/data'
    root = _bag(run, tmp_path / 'root', namespace='')
    assert read_recording(root, vehicle).namespace == ''


# ------------------------------------------------------------------------------ command line

def test_bag_parse_variant_and_tolerance():
    assert parse_variant('slow:observer.poles:=[-0.1,-0.11,-0.12]') == (
        'slow', ['observer.poles:=[-0.1,-0.11,-0.12]'])
    assert parse_variant('k:observer.type:=kalman,observer.Qd:=[1.0, 0.0],observer.Rd:=[2.0]')[
        1] == ['observer.type:=kalman', 'observer.Qd:=[1.0, 0.0]', 'observer.Rd:=[2.0]']
    for bad, match in (('observer.poles:=[1.0]', 'expected NAME'),
                       ('a.b:observer.type:=full', 'must be a letter'),
                       ('design:observer.type:=open_loop', 'reserved'),
                       ('x:observer.type', 'expected KEY:=VALUE'),
                       ('x', 'expected NAME:KEY:=VALUE')):
        with pytest.raises(BagToolError, match=match):
            parse_variant(bad)
    assert parse_tolerance('5%') == (0.05, None)
    assert parse_tolerance('0.01') == (None, 0.01)
    with pytest.raises(BagToolError):
        parse_tolerance('-1')


def test_bag_observer_eval_command(runs, bags, tmp_path, capsys):
    out = tmp_path / 'eval'
    argv = [str(bags['sub_noisy']), '--vehicle', str(CONFIG / 'submarine.yaml'),
            '--out', str(out), '--variant', 'slow:' + SLOW[0],
            '--variant', 'openloop:observer.type:=open_loop']
    assert main(argv) == 0
    stdout = capsys.readouterr().out
    assert 'variant' in stdout and 'openloop' in stdout and 'settle[s]' in stdout
    for name in ('results.csv', 'results.json', 'results.txt', 'states.png',
                 'error_norm.png', 'residuals.png', 'results_bag/metadata.yaml'):
        assert (out / name).exists(), name
    data = json.loads((out / 'results.json').read_text())
    assert list(data['variants']) == ['design', 'slow', 'openloop', 'live']
    assert data['namespace'] == '/sub1' and data['ground_truth']
    assert data['variants']['slow']['overrides'] == SLOW
    csv = (out / 'results.csv').read_text().splitlines()
    assert csv[0].startswith('variant,observer,kind,name,samples,rmse')
    assert len(csv) == 1 + 4 * (3 + 1)
    from rosbags.highlevel import AnyReader
    from observer_ros.bag.reader import jazzy_typestore
    with AnyReader([out / 'results_bag'], default_typestore=jazzy_typestore()) as reader:
        topics = {c.topic: c.msgcount for c in reader.connections}
        conn = [c for c in reader.connections if c.topic == '/eval/design/state/estimate']
        first = next(reader.messages(connections=conn))
        msg = reader.deserialize(first[2], first[0].msgtype)
    assert topics['/eval/state/true'] == 601 and topics['/eval/design/state/estimate'] == 601
    assert '/eval/live/state/estimate' in topics and '/eval/slow/state/error' in topics
    assert list(msg.name) == ['theta', 'w', 'q']
    # the output folder is never overwritten without --force
    _cli_error(argv, capsys, f'{out} exists; refusing to overwrite it')
    assert main(argv + ['--force', '--no-plots', '--no-bag']) == 0
    assert not (out / 'states.png').exists()
    capsys.readouterr()
    other = tmp_path / 'precious'
    other.mkdir()
    (other / 'thesis.tex').write_text('keep me')
    argv[argv.index(str(out))] = str(other)
    _cli_error(argv + ['--force'], capsys, 'not an observer-eval output folder')
    assert (other / 'thesis.tex').exists()


def test_bag_observer_eval_output_goes_next_to_the_bag(runs, tmp_path, monkeypatch, capsys):
    """Without --out: <bag>_eval beside the bag directory, whatever the current directory."""
    vehicle, run = runs['sub']
    bag = _bag(run, tmp_path / 'runs' / 'dive1')
    elsewhere = tmp_path / 'elsewhere'
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    argv = [str(bag), '--vehicle', str(CONFIG / 'submarine.yaml'), '--no-plots', '--no-bag']
    assert main(argv) == 0
    out = tmp_path / 'runs' / 'dive1_eval'
    assert (out / 'results.json').exists()
    assert f'written to {out}/' in capsys.readouterr().out
    assert not any(elsewhere.iterdir())
    _cli_error(argv, capsys, f'{out} exists; refusing to overwrite it')
    assert main(argv + ['--force']) == 0
    # a relative bag path, and the bag's storage file: the same folder
    monkeypatch.chdir(tmp_path / 'runs')
    assert main(['dive1/', *argv[1:], '--force']) == 0
    assert main([str(bag_file(bag)), *argv[1:], '--force']) == 0
    assert sorted(p.name for p in (tmp_path / 'runs').iterdir()) == ['dive1', 'dive1_eval']
    # a bare storage file (no metadata.yaml): <stem>_eval beside it
    bare = tmp_path / 'loose' / 'dive2.mcap'
    bare.parent.mkdir()
    bare.write_bytes(bag_file(bag).read_bytes())
    assert main([str(bare), *argv[1:]]) == 0
    assert (tmp_path / 'loose' / 'dive2_eval' / 'results.json').exists()
    capsys.readouterr()


@pytest.mark.ros
def test_bag_observer_eval_console_script(bags, tmp_path):
    exe = Path(sys.executable).parent / 'observer-eval'
    if not exe.exists():
        pytest.skip('console script not installed')
    done = subprocess.run([str(exe), str(bags['cart']), '--vehicle',
                           str(CONFIG / 'cart_pendulum.yaml'), '--out', str(tmp_path / 'o'),
                           '--no-plots'], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert 'design' in done.stdout
    bad = subprocess.run([str(exe), str(bags['cart']), '--vehicle',
                          str(CONFIG / 'submarine.yaml'), '--out', str(tmp_path / 'p')],
                         capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2
    assert bad.stderr.startswith('error: ') and 'Traceback' not in bad.stderr
    helptext = subprocess.run([str(exe), '--help'], capture_output=True, text=True).stdout
    assert 'NAME:KEY:=VALUE' in helptext and '--tolerance' in helptext
    assert '<bag>_eval next to the bag directory' in helptext


@pytest.mark.ros
def test_bag_tools_do_not_import_rclpy():
    code = ('import sys; import observer_ros.evaluation.evaluate, observer_ros.bag.reader; '
            'sys.exit(1 if "rclpy" in sys.modules else 0)')
    assert subprocess.run([sys.executable, '-c', code]).returncode == 0
