# Closed-loop runs over DDS: four processes, recorded to a bag, checked from the bag.
"""The plant simulator, observer, compensator and recorder in closed loop."""

import concurrent.futures
import os
import signal

import numpy as np
from observer_ros.bag.vectors import read_vector_topic
from observer_ros.core.estimators import make_estimator
from observer_ros.core.vehicle_design import design_vehicle
from observer_ros.nodes.recorder import recorded_topics
from observer_ros.timeutil import stamp_to_sec
from observer_ros.tools.run_closed_loop import run_closed_loop, run_started
from observer_ros.vehicle import load_vehicle
import pytest
from ros_helpers import CONFIG, domain_env, made_once, Probe, processes
from rosbags.highlevel import AnyReader
from rosbags.typesys import get_typestore, Stores
from sensor_msgs.msg import JointState

pytestmark = pytest.mark.ros      # processes or DDS participants

NOISE_OFF = 'simulator.noise:=false'


def _run(tmp_path, vehicle, *params, name='bag', namespace=None, storage='mcap',
         container=False):
    with domain_env():
        return run_closed_loop(CONFIG / vehicle, tmp_path / name, storage=storage,
                               namespace=namespace, overrides=params, quiet=True,
                               container=container)


def _vectors(bag, topic, names):
    t, x = read_vector_topic(bag, topic, names)
    assert len(t), f'no messages on {topic}'
    return t, x


def _unique(t, x):
    """One sample per stamp (an unanswered estimate may be re-sent under load)."""
    stamps, first = np.unique(t, return_index=True)
    return stamps, x[first]


def _at_common_stamps(ta, xa, tb, xb):
    common, ia, ib = np.intersect1d(ta, tb, return_indices=True)
    return common, xa[ia], xb[ib]


@pytest.fixture(scope='module')
def submarine_bag(tmp_path_factory):
    """Record a noise-free submarine run, 20 s simulated (400 lock-step exchanges), once."""
    def record(folder):
        _run(folder, 'submarine.yaml', NOISE_OFF, 'simulator.duration:=20.0')
    return made_once(tmp_path_factory, 'closed_loop_submarine', record) / 'bag'


def _noisy_run(tmp_path_factory, storage):
    """Record the 5-s submarine run with measurement noise on, once per run of the suite."""
    def record(folder):
        _run(folder, 'submarine.yaml', 'simulator.duration:=5.0', storage=storage)
    return made_once(tmp_path_factory, f'closed_loop_noisy_{storage}', record) / 'bag'


@pytest.fixture(scope='module')
def noisy_bag(tmp_path_factory):
    """Return the 5-s noisy submarine run (three processes, mcap): what layouts equal."""
    return _noisy_run(tmp_path_factory, 'mcap')


@pytest.fixture(scope='module')
def noisy_sqlite3_bag(tmp_path_factory):
    """Return the same run again, recorded to sqlite3."""
    return _noisy_run(tmp_path_factory, 'sqlite3')


def test_estimate_converges_at_the_designed_rate(submarine_bag):
    vehicle = load_vehicle(CONFIG / 'submarine.yaml')
    names = vehicle.plant.state_names
    t_true, x_true = _vectors(submarine_bag, '/state/true', names)
    t_est, x_est = _vectors(submarine_bag, '/state/estimate', names)
    t, x, xh = _at_common_stamps(t_true, x_true, t_est, x_est)
    assert len(t) >= 400
    err = np.linalg.norm(x - xh, axis=1)
    # theta(0) = 30 deg, theta_hat(0) = 0: the error starts at 0.52 rad ...
    assert err[0] == pytest.approx(np.deg2rad(30.0), rel=1e-9)
    # ... and each observer mode decays at its designed rate. The poles -0.6, -0.61, -0.62
    # are so close that the norm of the error is dominated by t^2 exp(-0.6 t) for a long
    # time, so the rates are measured on the modes: the projection of the error on the left
    # eigenvector w of the sampled error matrix F = (I - M C) Ad (eig F = exp(p dt)) obeys
    # w e[k+1] = exp(p dt) w e[k].
    F = make_estimator(vehicle.plant, vehicle.observer).error_matrix(vehicle.sample_time)
    z, W = np.linalg.eig(F.T)
    e = (x - xh)[2:]
    for zi, w in zip(z, W.T):
        rate = np.log(zi.real) / vehicle.sample_time
        proj = np.abs(e @ w)
        window = (t[2:] - t[0] > 1.0) & (t[2:] - t[0] < 15.0)
        slope = np.polyfit(t[2:][window], np.log(proj[window]), 1)[0]
        assert slope == pytest.approx(rate, rel=0.05)
        assert rate == pytest.approx(min(vehicle.observer.poles.real, key=lambda p:
                                         abs(p - rate)), rel=1e-9)
    # noise free and exactly sampled: the recorded error follows e[k+1] = F e[k] to
    # round-off at every step (so it goes to zero, with no step-dependent bias)
    np.testing.assert_allclose(e[1:], e[:-1] @ F.T, rtol=0, atol=1e-12 * err[0])
    assert err[-1] < 1e-3 * err[0]


def test_command_is_minus_k_times_the_estimate_at_matching_stamps(submarine_bag):
    vehicle = load_vehicle(CONFIG / 'submarine.yaml')
    K = np.asarray(design_vehicle(vehicle).K).reshape(1, 3)
    t_est, x_est = _vectors(submarine_bag, '/state/estimate', vehicle.plant.state_names)
    t_u, u = _vectors(submarine_bag, '/control/u', vehicle.plant.input_names)
    t, xh, uu = _at_common_stamps(t_est, x_est, t_u, u)
    assert len(t) >= 400
    np.testing.assert_allclose(uu[:, 0], -(xh @ K.T)[:, 0], rtol=1e-12, atol=1e-15)


def test_bag_has_every_topic_and_reads_back(submarine_bag):
    vehicle = load_vehicle(CONFIG / 'submarine.yaml')
    expected = {('/' + name.lstrip('/')) for name, _, _ in recorded_topics(vehicle)}
    store = get_typestore(Stores.ROS2_JAZZY)
    with AnyReader([submarine_bag], default_typestore=store) as reader:
        counts = {c.topic: c.msgcount for c in reader.connections}
        assert expected <= set(counts), f'missing {expected - set(counts)}'
        for topic in expected:
            assert counts[topic] > 0, f'{topic} is empty'
        # every message deserialises
        n = sum(1 for c, _, raw in reader.messages() if reader.deserialize(raw, c.msgtype))
        assert n == sum(counts.values())
    assert (submarine_bag / 'metadata.yaml').exists()
    assert list(submarine_bag.glob('*.mcap'))


def test_lockstep_run_is_reproducible_bit_for_bit(noisy_bag, noisy_sqlite3_bag):
    """Two runs with measurement noise on give identical trajectories (either storage)."""
    vehicle = load_vehicle(CONFIG / 'submarine.yaml')
    names = vehicle.plant.state_names
    runs = [noisy_bag, noisy_sqlite3_bag]
    (t1, x1), (t2, x2) = [_unique(*_vectors(b, '/state/true', names)) for b in runs]
    (e1, xh1), (e2, xh2) = [_unique(*_vectors(b, '/state/estimate', names)) for b in runs]
    assert np.array_equal(t1, t2) and np.array_equal(x1, x2)
    assert np.array_equal(e1, e2) and np.array_equal(xh1, xh2)


def _child_node(name, missing_ok=False):
    """Return the pid of this process's child running the package's node ``name``."""
    for pid, ppid, argv in processes():
        if ppid == os.getpid() and 'observer_ros.nodes.entry' in argv and name in argv:
            return pid
    if missing_ok:
        return None
    raise AssertionError(f'no {name} process')


def _log_says(path, text):
    return path.exists() and text in path.read_text(errors='replace')


def _held_run(tmp_path, name):
    """
    Run the 20-s noise-free submarine, holding the observer once estimates reach t = 2 s.

    The lock-step run takes about 2 s of wall time, and the probe's discovery of the
    observer can take longer (it missed a whole run in 3 of 6 tries on an idle host): the
    simulator is held (SIGSTOP) from its start until the probe has found the observer's
    publisher, before its first step, which the hold cannot change. Returns the bag, or
    None when the run ended before the probe saw t = 2 s all the same.
    """
    logs = tmp_path / f'{name}_logs'
    probe = Probe('held_probe')
    newest = [0.0]
    probe.node.create_subscription(
        JointState, '/state/estimate',
        lambda m: newest.__setitem__(0, stamp_to_sec(m.header.stamp)), 10)
    held = []
    try:
        with concurrent.futures.ThreadPoolExecutor(1) as pool:
            run = pool.submit(_run, tmp_path, 'submarine.yaml', NOISE_OFF,
                              'simulator.duration:=20.0', name=name)
            try:
                simulator = [None]

                def simulator_started():
                    simulator[0] = _child_node('plant_simulator', missing_ok=True)
                    return simulator[0] is not None or run.done()

                probe.spin_until(simulator_started, what='the simulator started')
                if simulator[0] is not None:
                    os.kill(simulator[0], signal.SIGSTOP)
                    try:
                        if not run_started(logs / 'plant_simulator.log'):
                            probe.spin_until(
                                lambda: probe.node.count_publishers('/state/estimate') >= 1,
                                what="the observer's estimates found by the probe")
                    finally:
                        os.kill(simulator[0], signal.SIGCONT)
                probe.spin_until(lambda: newest[0] >= 2.0 or run.done(),
                                 what='estimates at t >= 2 s')
                if run.done():
                    run.result()
                    return None
                held = [_child_node('compensator'), _child_node('observer_node')]
                for pid in held:
                    os.kill(pid, signal.SIGSTOP)
                os.kill(held[0], signal.SIGCONT)    # the observer alone stays held
                probe.spin_until(lambda: _log_says(logs / 'compensator.log', 'estimate stale')
                                 and _log_says(logs / 'plant_simulator.log',
                                               'no command for step'),
                                 what='the compensator stale and the simulator waiting')
            finally:
                for pid in held:
                    os.kill(pid, signal.SIGCONT)
            bag = run.result()
    finally:
        probe.close()
    assert _log_says(logs / 'compensator.log', 'estimates back from the same observer')
    return bag


def test_an_observer_held_off_the_cpu_leaves_the_lockstep_run_unchanged(
        tmp_path, submarine_bag):
    """
    The observer stopped (SIGSTOP) mid-run until the simulator reports no command.

    Longer than ``controller.stale_timeout``: the compensator goes stale and, while the
    observer's publisher is matched, sends no safe command (the simulator waits). When the
    same observer's estimates come back, the compensator follows them at once, and the
    observer takes the command it waited for before the next measurement: the run is the
    run without the hold. A run that ends before the probe sees it is run again (at most
    three runs).
    """
    names = load_vehicle(CONFIG / 'submarine.yaml').plant.state_names
    for attempt in range(3):
        bag = _held_run(tmp_path, f'held{attempt}')
        if bag is not None:
            break
    assert bag is not None, 'three runs ended before the probe saw t = 2 s'
    for topic in ('/state/true', '/state/estimate'):
        (t1, x1), (t2, x2) = [_unique(*_vectors(b, topic, names)) for b in (submarine_bag, bag)]
        assert np.array_equal(t1, t2), topic
        assert np.array_equal(x1, x2), (topic, int(np.sum(np.any(x1 != x2, axis=1))))


def test_container_and_either_executor_give_the_same_run_bit_for_bit(
        tmp_path, monkeypatch, noisy_bag):
    """
    The same lock-step run from every layout and executor.

    Observer and compensator in one process (``container``), or each node spun by rclpy's
    SingleThreadedExecutor instead of the EventsExecutor, against three processes with the
    EventsExecutor (``noisy_bag``).

    """
    vehicle = load_vehicle(CONFIG / 'submarine.yaml')
    names = vehicle.plant.state_names
    runs = [noisy_bag,
            _run(tmp_path, 'submarine.yaml', 'simulator.duration:=5.0', name='container',
                 container=True)]
    monkeypatch.setenv('OBSERVER_ROS_EXECUTOR', 'single_threaded')
    runs.append(_run(tmp_path, 'submarine.yaml', 'simulator.duration:=5.0', name='single'))
    true = [_unique(*_vectors(b, '/state/true', names)) for b in runs]
    est = [_unique(*_vectors(b, '/state/estimate', names)) for b in runs]
    assert len(true[0][0]) == 101          # 5 s of 0.05 s steps, and the initial state
    for (t, x), (e, xh) in zip(true[1:], est[1:]):
        assert np.array_equal(t, true[0][0]) and np.array_equal(x, true[0][1])
        assert np.array_equal(e, est[0][0]) and np.array_equal(xh, est[0][1])
    log = (runs[1].parent / 'container_logs' / 'container.log').read_text()
    assert 'observer' in log and 'error: ' not in log


def test_reduced_order_observer_reproduces_the_measured_state(tmp_path):
    vehicle = load_vehicle(CONFIG / 'cart_pendulum_reduced.yaml')
    names = vehicle.plant.state_names
    bag = _run(tmp_path, 'cart_pendulum_reduced.yaml', NOISE_OFF, 'simulator.duration:=3.0')
    t_true, x_true = _vectors(bag, '/state/true', names)
    t_est, x_est = _vectors(bag, '/state/estimate', names)
    t, x, xh = _at_common_stamps(t_true, x_true, t_est, x_est)
    assert len(t) >= 300
    i = names.index('x')
    # the cart displacement is measured: the estimate is the measurement, exactly
    np.testing.assert_allclose(xh[:, i], x[:, i], rtol=0, atol=1e-12)
    # the others converge (poles -20, -20 +- 20i: e^-20 per second)
    err = np.abs(x - xh).max(axis=1)
    assert err[-1] < 1e-6


def test_sqlite3_storage(noisy_sqlite3_bag):
    bag = noisy_sqlite3_bag
    assert list(bag.glob('*.db3')) and not list(bag.glob('*.mcap'))
    vehicle = load_vehicle(CONFIG / 'submarine.yaml')
    t, _ = _unique(*_vectors(bag, '/state/estimate', vehicle.plant.state_names))
    assert len(t) == 101


def test_two_namespaced_vehicles_do_not_interfere(tmp_path):
    """Two submarines side by side, in /sub1 and /sub2, with different initial states."""
    vehicle = load_vehicle(CONFIG / 'submarine.yaml')
    names = vehicle.plant.state_names
    initial = {'sub1': [0.5, 0.0, 0.0], 'sub2': [-0.2, 0.1, 0.0]}
    with concurrent.futures.ThreadPoolExecutor(2) as pool:
        futures = {ns: pool.submit(
            _run, tmp_path, 'submarine.yaml', NOISE_OFF, 'simulator.duration:=5.0',
            f'simulator.initial_state:={x0}', name=ns, namespace=f'/{ns}')
            for ns, x0 in initial.items()}
        bags = {ns: f.result() for ns, f in futures.items()}
    for ns, bag in bags.items():
        other = 'sub2' if ns == 'sub1' else 'sub1'
        t, x = _vectors(bag, f'/{ns}/state/true', names)
        np.testing.assert_allclose(x[0], initial[ns])
        assert len(t) == 101                    # one true state per step, none doubled
        te, xe = _vectors(bag, f'/{ns}/state/estimate', names)
        # one estimate per step; under load an unanswered estimate is re-sent (same stamp,
        # same values), so count the stamps
        stamps, first = np.unique(te, return_index=True)
        assert len(stamps) == 101
        for k, stamp in enumerate(te):
            np.testing.assert_array_equal(xe[k], xe[first[np.searchsorted(stamps, stamp)]])
        store = get_typestore(Stores.ROS2_JAZZY)
        with AnyReader([bag], default_typestore=store) as reader:
            assert not [c.topic for c in reader.connections if other in c.topic]


def test_discrete_vehicle_closes_the_loop_with_the_sampled_design(tmp_path):
    """
    config/submarine_discrete.yaml (seed 001: x[k+1] = A x[k] + B u[k]) through the nodes.

    Its A, B are the submarine's ZOH model at T = 0.05 s and its observer poles exp(s T), so
    the observer's error matrix equals the one the continuous vehicle's estimator uses at T;
    the recorded error follows it at every step.
    """
    cont = load_vehicle(CONFIG / 'submarine.yaml')
    disc = load_vehicle(CONFIG / 'submarine_discrete.yaml')
    F = make_estimator(disc.plant, disc.observer).error_matrix(disc.plant.dt)
    F_cont = make_estimator(cont.plant, cont.observer).error_matrix(disc.plant.dt)
    np.testing.assert_allclose(F, F_cont, rtol=0, atol=1e-12)
    names = disc.plant.state_names
    bag = _run(tmp_path, 'submarine_discrete.yaml', NOISE_OFF, 'simulator.duration:=10.0')
    t, x = _unique(*_vectors(bag, '/state/true', names))
    te, xh = _unique(*_vectors(bag, '/state/estimate', names))
    assert np.array_equal(t, te) and len(t) == 201
    e = (x - xh)[2:]
    np.testing.assert_allclose(e[1:], e[:-1] @ F.T, rtol=0, atol=1e-12)
    assert np.linalg.norm(e[-1]) < 0.1 * np.linalg.norm(e[0])
