# test/bag/test_bag_play.py: observer-play publishes a bag's messages with the recorded timing.
"""
observer-play, run as a subprocess, received by a subscriber node in this process.

Discovery is waited for by counts (the player's ``--wait-subscribers`` waits until our
subscriptions are matched; we wait for the player's publishers), never by fixed sleeps.
The test and the player use their own ROS domain and namespace so that other tests
running at the same time do not interfere.

"""

import os
from pathlib import Path
import signal
import subprocess
import sys
import time

from bag_synth import CONFIG, simulate, write_bag
import numpy as np
from observer_ros.bag.errors import BagToolError
from observer_ros.bag.play import message_class, parse_remap
from observer_ros.vehicle import load_vehicle
import pytest
from ros_helpers import DOMAIN_ID

pytestmark = pytest.mark.filterwarnings('ignore::DeprecationWarning')

rclpy = pytest.importorskip('rclpy')
EXE = Path(sys.executable).parent / 'observer-play'
# this test process's own domain (ros_helpers): /clock is not namespaced, so two players
# in one domain would mix
DOMAIN = DOMAIN_ID
NS = f'/play{os.getpid()}'
DT = 0.05          # the submarine's step (20 Hz)


@pytest.fixture(scope='module')
def bag(tmp_path_factory):
    """Record a 5 s submarine run in namespace NS (mcap)."""
    vehicle = load_vehicle(CONFIG / 'submarine.yaml')
    run = simulate(vehicle, steps=100, noise=True)
    return write_bag(tmp_path_factory.mktemp('play') / 'sub', run['messages'], namespace=NS)


def _env():
    env = dict(os.environ, ROS_DOMAIN_ID=str(DOMAIN), PYTHONWARNINGS='ignore')
    return env


class Listener:
    """A node that records (wall time, stamp ns) of what arrives on some topics."""

    def __init__(self, topics):
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        self.context = Context()
        rclpy.init(context=self.context, domain_id=DOMAIN)
        self.node = rclpy.create_node('play_listener', context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.received = {topic: [] for topic in topics}
        self.subs = []
        for topic, (cls, qos, stamp) in topics.items():
            self.subs.append(self.node.create_subscription(
                cls, topic, lambda msg, t=topic, f=stamp: self._on(t, f, msg), qos))

    def _on(self, topic, stamp, msg):
        s = stamp(msg)
        self.received[topic].append((time.monotonic(), s.sec * 1_000_000_000 + s.nanosec))

    def spin_until(self, done, timeout):
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if done():
                return True
            self.executor.spin_once(timeout_sec=0.05)
        return done()

    def close(self):
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)


def _topics():
    from rclpy.qos import QoSProfile, qos_profile_sensor_data
    from rosgraph_msgs.msg import Clock
    from sensor_msgs.msg import Imu, JointState
    return {
        f'{NS}/imu/data': (Imu, qos_profile_sensor_data, lambda m: m.header.stamp),
        f'{NS}/state/true': (JointState, QoSProfile(depth=100), lambda m: m.header.stamp),
        '/clock': (Clock, QoSProfile(depth=100), lambda m: m.clock),
    }


def _player(bag, *args):
    if not EXE.exists():
        pytest.skip('observer-play console script not installed')
    return subprocess.Popen([str(EXE), str(bag), *args], env=_env(), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def _stop(proc, sig=signal.SIGINT, wait=0.0):
    """Let the player end by itself within ``wait`` s, else send it sig; return (code, err)."""
    try:
        proc.wait(timeout=wait)
    except subprocess.TimeoutExpired:
        proc.send_signal(sig)
    try:
        out, err = proc.communicate(timeout=20)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate()
    return proc.returncode, err


@pytest.mark.ros
def test_bag_play_messages_and_clock_in_order_with_scaled_timing(bag):
    rate = 2.0
    listener = Listener(_topics())
    proc = _player(bag, '--rate', str(rate), '--clock', '50', '--wait-subscribers', '3')
    try:
        truth = listener.received[f'{NS}/state/true']
        # discovery: the player's publishers are seen before anything is expected
        assert listener.spin_until(
            lambda: listener.node.count_publishers(f'{NS}/state/true') >= 1, 30.0)
        assert listener.spin_until(lambda: len(truth) >= 101 or proc.poll() is not None,
                                   60.0)
        listener.spin_until(lambda: proc.poll() is not None, 30.0)
        listener.spin_until(lambda: len(truth) >= 101, 5.0)
    finally:
        code, err = _stop(proc, wait=30.0)
        listener.close()
    assert code == 0, err
    assert 'Traceback' not in err
    # every step's true state, in order (reliable)
    stamps = [s for _, s in truth]
    assert len(stamps) == 101
    assert stamps == sorted(stamps)
    assert stamps[0] == 1_000_000_000 and stamps[-1] == 1_000_000_000 + 100 * 50_000_000
    # recorded spacing (5 s) scaled by the rate, loosely
    wall = np.array([w for w, _ in truth])
    span = wall[-1] - wall[0]
    assert 0.6 * 5.0 / rate < span < 1.6 * 5.0 / rate, span
    assert np.median(np.diff(wall)) == pytest.approx(DT / rate, rel=0.5)
    # the sensor (best effort): in order, nearly all of it
    imu = [s for _, s in listener.received[f'{NS}/imu/data']]
    assert len(imu) >= 90 and imu == sorted(imu)
    # /clock: bag time, in order, about 50 Hz of wall time
    clock = [s for _, s in listener.received['/clock']]
    assert clock == sorted(clock)
    assert 1_000_000_000 <= clock[0] <= 1_100_000_000
    assert clock[-1] <= stamps[-1] + 100_000_000
    assert 0.5 * 50 * span < len(clock) < 2.0 * 50 * span + 10


@pytest.mark.ros
def test_bag_play_loop_jumps_the_clock_back_and_stops_on_sigint(bag):
    listener = Listener(_topics())
    proc = _player(bag, '--rate', '10', '--loop', '--clock', '--wait-subscribers', '3')
    try:
        truth = listener.received[f'{NS}/state/true']

        def looped():
            s = [x for _, x in truth]
            return any(b < a for a, b in zip(s, s[1:])) and len(s) > 110
        assert listener.spin_until(lambda: looped() or proc.poll() is not None, 60.0)
        assert proc.poll() is None, proc.communicate()[1]
    finally:
        code, err = _stop(proc, signal.SIGINT)
        listener.close()
    assert code == 0, err
    assert 'Traceback' not in err and 'published' in err
    s = [x for _, x in truth]
    back = [i for i in range(1, len(s)) if s[i] < s[i - 1]]
    assert s[back[0]] == 1_000_000_000                     # the loop starts again
    clock = [x for _, x in listener.received['/clock']]
    assert any(b < a for a, b in zip(clock, clock[1:]))    # the clock jumped back


@pytest.mark.ros
def test_bag_play_topics_and_remap(bag):
    from rclpy.qos import QoSProfile
    from sensor_msgs.msg import JointState
    stamp = lambda m: m.header.stamp   # noqa: E731
    listener = Listener({'/replay/truth': (JointState, QoSProfile(depth=1000), stamp)})
    proc = _player(bag, '--rate', '20', '--topics', f'{NS}/state/true',
                   '--remap', f'{NS}/state/true:=/replay/truth', '--wait-subscribers', '1')
    try:
        got = listener.received['/replay/truth']
        assert listener.spin_until(lambda: len(got) >= 101 or proc.poll() is not None, 60.0)
        listener.spin_until(lambda: len(got) >= 101, 5.0)
        assert listener.node.count_publishers(f'{NS}/imu/data') == 0
    finally:
        code, err = _stop(proc, wait=30.0)
        listener.close()
    assert code == 0, err
    assert len(got) == 101 and 'published 101 messages' in err


@pytest.mark.ros
def test_bag_play_errors(bag, tmp_path):
    for args, text in (([tmp_path / 'missing'], 'no such file or directory'),
                       ([bag, '--rate', '0'], '--rate must be positive'),
                       ([bag, '--remap', 'a'], 'expected OLD:=NEW'),
                       ([bag, '--topics', '/nope'], 'topics not in the bag')):
        proc = _player(*args)
        _, err = proc.communicate(timeout=60)
        code = proc.returncode
        assert code == 2, err
        assert err.strip().splitlines()[-1].startswith('error: ') and text in err, err


def test_bag_play_helpers():
    from sensor_msgs.msg import Imu
    assert message_class('sensor_msgs/msg/Imu') is Imu
    with pytest.raises(BagToolError, match='no Python message class'):
        message_class('nope_msgs/msg/Nothing')
    assert parse_remap('a/b:=/c') == ('/a/b', '/c')
    with pytest.raises(BagToolError):
        parse_remap('a')


def test_bag_play_uses_the_recorded_qos(tmp_path):
    """Use the QoS from the bag's metadata when recorded (as the recorder node writes it)."""
    from rclpy.qos import DurabilityPolicy, ReliabilityPolicy
    from rosbags.interfaces import (Qos, QosDurability, QosHistory, QosLiveliness,
                                    QosReliability, QosTime)
    from rosbags.rosbag2 import Writer
    from observer_ros.bag.play import _qos
    from observer_ros.bag.reader import BagReader, jazzy_typestore
    zero = QosTime(sec=0, nsec=0)

    def qos(reliability, durability):
        return Qos(history=QosHistory.KEEP_LAST, depth=5, reliability=reliability,
                   durability=durability, deadline=zero, lifespan=zero,
                   liveliness=QosLiveliness.AUTOMATIC, liveliness_lease_duration=zero,
                   avoid_ros_namespace_conventions=False)
    path = tmp_path / 'qos'
    with Writer(path, version=9) as w:
        for topic, q in (('/a/imu', qos(QosReliability.BEST_EFFORT, QosDurability.VOLATILE)),
                         ('/a/ref', qos(QosReliability.RELIABLE,
                                        QosDurability.TRANSIENT_LOCAL))):
            conn = w.add_connection(topic, 'sensor_msgs/msg/JointState',
                                    typestore=jazzy_typestore(), offered_qos_profiles=[q])
            w.write(conn, 1, b'\x00\x01\x00\x00' + bytes(28))
        conn = w.add_connection('/a/state/true', 'sensor_msgs/msg/JointState',
                                typestore=jazzy_typestore())
        w.write(conn, 2, b'\x00\x01\x00\x00' + bytes(28))
        conn = w.add_connection('/a/imu_raw', 'sensor_msgs/msg/Imu',
                                typestore=jazzy_typestore())
        w.write(conn, 3, b'\x00\x01\x00\x00' + bytes(28))
    with BagReader(path) as reader:
        got = {c.topic: _qos(c, c.topic) for c in reader.connections()}
    assert got['/a/imu'].reliability == ReliabilityPolicy.BEST_EFFORT
    assert got['/a/ref'].durability == DurabilityPolicy.TRANSIENT_LOCAL
    assert got['/a/ref'].reliability == ReliabilityPolicy.RELIABLE
    # without recorded QoS: sensor messages best effort, the vehicle's vectors reliable
    assert got['/a/state/true'].reliability == ReliabilityPolicy.RELIABLE
    assert got['/a/imu_raw'].reliability == ReliabilityPolicy.BEST_EFFORT


@pytest.mark.ros
def test_bag_play_publishes_raw_bytes_rclpy_accepts(bag):
    """publisher.publish(bytes) sends serialized data as is (what the player relies on)."""
    from rclpy.context import Context
    from rclpy.serialization import deserialize_message, serialize_message
    from std_msgs.msg import Float64
    ctx = Context()
    rclpy.init(context=ctx, domain_id=DOMAIN)
    try:
        node = rclpy.create_node('raw_check', context=ctx)
        got = []
        node.create_subscription(Float64, f'{NS}/raw', got.append, 10)
        pub = node.create_publisher(Float64, f'{NS}/raw', 10)
        from rclpy.executors import SingleThreadedExecutor
        ex = SingleThreadedExecutor(context=ctx)
        ex.add_node(node)
        deadline = time.monotonic() + 20
        while pub.get_subscription_count() < 1 and time.monotonic() < deadline:
            ex.spin_once(timeout_sec=0.05)
        raw = serialize_message(Float64(data=2.5))
        assert isinstance(raw, bytes)
        pub.publish(raw)
        while not got and time.monotonic() < deadline:
            ex.spin_once(timeout_sec=0.05)
        assert got and got[0].data == 2.5
        assert deserialize_message(raw, Float64).data == 2.5
        ex.shutdown()
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=ctx)
