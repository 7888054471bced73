# The recorder against signals, SIGKILL, a full disk and an existing bag (reliability issue).
"""The recorder keeps every message it reported on disk, whatever stops it."""

import os
from pathlib import Path
import signal
import subprocess
import sys
import time

from bag_synth import at_rest
from diagnostic_msgs.msg import DiagnosticArray
from observer_ros.bag.errors import BagToolError
from observer_ros.bag.reader import BagReader
from observer_ros.bag.recover import BagRecoveryError, recover_bag
from observer_ros.nodes.common import STATE_PUB_QOS, STATE_QOS
from observer_ros.timeutil import stamp_to_ns
import pytest
from ros_helpers import CONFIG, Listener, Probe, Proc, processes, ros_env, tmpfs, WAIT
from rosbags.highlevel import AnyReader
from rosbags.typesys import get_typestore, Stores
from sensor_msgs.msg import JointState

VEHICLE = CONFIG / 'submarine.yaml'
TOPIC = '/state/true'
STORE = get_typestore(Stores.ROS2_JAZZY)


class Feeder:
    """A probe that publishes numbered JointState on state/true and reads the recorder."""

    def __init__(self, name='recorder_feeder'):
        self.probe = Probe(name)
        node = self.probe.node
        self.pub = node.create_publisher(JointState, 'state/true', STATE_PUB_QOS)
        self.diagnostics = []
        self.sub = node.create_subscription(DiagnosticArray, '/diagnostics',
                                            self.diagnostics.append, STATE_QOS)
        self.sent = 0

    def wait_recorder(self):
        """Wait until the recorder reads state/true and publishes /diagnostics."""
        self.probe.wait_matched(self.pub, 'the recorder subscribed to state/true')
        self.probe.wait_matched(self.sub, 'the recorder publishing /diagnostics')

    def publish(self, n, width=1, wait=True, batch=8):
        """
        Publish n messages numbered from self.sent (position[0] = the number).

        With ``wait``, after each batch wait until the recorder reports them on disk: the
        recorder's reader keeps the last 10, so fewer than 10 are ever in flight.
        """
        while n > 0:
            for _ in range(min(n, batch)):
                msg = JointState()
                msg.header.stamp.sec = 1 + self.sent
                msg.name = [f'j{i}' for i in range(width)]
                msg.position = [float(self.sent)] * width
                self.pub.publish(msg)
                self.sent += 1
                n -= 1
            if wait:
                self.wait_recorded(self.sent)

    def recorded(self, key=f'messages {TOPIC}'):
        """Return the recorder's latest count of state/true messages on disk (-1: none)."""
        for array in reversed(self.diagnostics):
            for status in array.status:
                if status.name.endswith('/recorder'):
                    for kv in status.values:
                        if kv.key == key:
                            return int(kv.value)
        return -1

    def wait_recorded(self, n, timeout=WAIT):
        """Wait until the recorder reports at least n state/true messages flushed."""
        self.probe.spin_until(lambda: self.recorded() >= n, timeout,
                              f'the recorder reporting {n} messages on {TOPIC}')

    def close(self):
        """Shut the probe down."""
        self.probe.close()


@pytest.fixture
def feeder():
    f = Feeder()
    yield f
    f.close()


def _recorder(bag, storage, *params, log_dir=None):
    return Proc('recorder', VEHICLE, f'output:={bag}', f'storage:={storage}',
                'use_sim_time:=false', *params, log_dir=log_dir)


def _numbers(bag):
    """Return the numbers of the state/true messages in a bag, in bag order."""
    with AnyReader([Path(bag)], default_typestore=STORE) as reader:
        conns = [c for c in reader.connections if c.topic == TOPIC]
        return [int(reader.deserialize(raw, c.msgtype).position[0])
                for c, _, raw in reader.messages(connections=conns)]


def _opens(bag):
    try:
        with AnyReader([Path(bag)], default_typestore=STORE) as reader:
            sum(1 for _ in reader.messages())
        return True
    except Exception:   # noqa: BLE001 - any failure to read counts as not opening
        return False


@pytest.mark.ros
@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
@pytest.mark.parametrize('sig', [signal.SIGTERM, signal.SIGINT], ids=['SIGTERM', 'SIGINT'])
def test_a_signal_closes_the_bag_with_every_message(tmp_path, feeder, storage, sig):
    bag = tmp_path / 'bag'
    rec = _recorder(bag, storage, 'flush_period:=0.1', log_dir=tmp_path)
    try:
        feeder.wait_recorder()
        n = 150
        feeder.publish(n)
        feeder.wait_recorded(n)
        code = rec.stop(sig, timeout=20)
    finally:
        rec.stop(signal.SIGKILL)
    assert code == 0, rec.log_path.read_text()
    assert 'bag closed' in rec.log_path.read_text()
    assert (bag / 'metadata.yaml').exists()
    assert not (bag / '.disk_reserve').exists()
    # closed cleanly: readable as it is, exactly the n messages, in order
    assert _numbers(bag) == list(range(n))
    if storage == 'mcap':     # every chunk carries its CRC32 (bag/integrity.py)
        with BagReader(bag) as opened:
            assert opened.info.chunk_crcs and all(opened.info.chunk_crcs)


@pytest.mark.ros
@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_sigkill_loses_at_most_what_came_after_the_last_flush(tmp_path, feeder, storage):
    bag = tmp_path / 'bag'
    rec = _recorder(bag, storage, 'flush_period:=0.5', log_dir=tmp_path)
    try:
        feeder.wait_recorder()
        flushed = 120
        feeder.publish(flushed)
        feeder.wait_recorded(flushed)        # reported after a flush: on disk
        feeder.publish(8, wait=False)        # maybe received, not yet flushed
        rec.stop(signal.SIGKILL)
    finally:
        rec.stop(signal.SIGKILL)
    assert rec.popen.returncode == -signal.SIGKILL
    assert not (bag / 'metadata.yaml').exists()
    assert not _opens(bag)                   # what a killed writer leaves ...
    assert (bag / '.disk_reserve').exists()
    report = recover_bag(bag)                # ... and what recovery makes of it
    assert not (bag / '.disk_reserve').exists()
    assert report['storage'] == storage
    numbers = _numbers(bag)
    assert flushed <= len(numbers) <= feeder.sent
    assert numbers == list(range(len(numbers)))   # a prefix: nothing lost in between
    assert report['messages'][TOPIC] == len(numbers)
    # recovering again changes nothing
    again = recover_bag(bag)
    assert not again['repaired'] and _numbers(bag) == numbers


@pytest.mark.ros
def test_recover_command_line(tmp_path, feeder):
    bag = tmp_path / 'bag'
    rec = _recorder(bag, 'mcap', 'flush_period:=0.1', log_dir=tmp_path)
    try:
        feeder.wait_recorder()
        feeder.publish(30)
        feeder.wait_recorded(30)
        rec.stop(signal.SIGKILL)
    finally:
        rec.stop(signal.SIGKILL)
    out = subprocess.run([sys.executable, '-m', 'observer_ros.bag.recover', str(bag)],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert f'{TOPIC}: 30' in out.stdout
    assert _numbers(bag) == list(range(30))
    bad = subprocess.run([sys.executable, '-m', 'observer_ros.bag.recover',
                          str(tmp_path / 'nothing')], capture_output=True, text=True,
                         timeout=120)
    assert bad.returncode == 2 and 'not a bag directory' in bad.stderr


@pytest.mark.ros
def test_an_existing_bag_is_never_overwritten(tmp_path):
    bag = tmp_path / 'bag'
    bag.mkdir()
    (bag / 'keep.txt').write_text('precious')
    rec = _recorder(bag, 'mcap', log_dir=tmp_path)
    code = rec.popen.wait(timeout=60)
    rec.stop()
    assert code == 2
    log = rec.log_path.read_text()
    assert str(bag) in log and 'refusing to overwrite' in log
    assert sorted(p.name for p in bag.iterdir()) == ['keep.txt']
    assert (bag / 'keep.txt').read_text() == 'precious'


@pytest.fixture
def small_disk(tmp_path):
    """Mount a 2 MiB tmpfs (root only); unmount it afterwards."""
    with tmpfs(tmp_path / 'disk', 'size=2m', 'a 2 MiB tmpfs') as disk:
        yield disk


@pytest.mark.ros
@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_a_full_disk_stops_the_recorder_with_a_clear_error(tmp_path, feeder, small_disk,
                                                           storage):
    bag = small_disk / 'bag'
    rec = _recorder(bag, storage, 'flush_period:=0.1', 'disk_reserve:=262144',
                    log_dir=tmp_path)
    try:
        feeder.wait_recorder()
        # ~40 KB per message: 2 MiB fill up after about 50
        while rec.alive() and feeder.sent < 500:
            feeder.publish(1, width=2500, wait=False)
            feeder.probe.spin_until(
                lambda: feeder.recorded() >= feeder.sent or not rec.alive(), WAIT,
                'the recorder writing the message or stopping')
        code = rec.popen.wait(timeout=60)
    finally:
        rec.stop(signal.SIGKILL)
    log = rec.log_path.read_text()
    assert code == 1, log
    assert str(bag) in log
    assert ('No space left on device' in log) or ('disk is full' in log), log
    on_disk = max(feeder.recorded(), 0)
    # the recorder recovered the bag itself; recovering again must agree
    assert 'recovered up to its last flush' in log, log
    report = recover_bag(bag)
    numbers = _numbers(bag)
    assert numbers == list(range(len(numbers)))
    # the write that fails may be the index after a chunk already whole on disk: then every
    # message sent is readable (seen: 36 of 36); the messages are never more than were sent
    assert on_disk <= len(numbers) <= feeder.sent
    assert report['total'] >= len(numbers)
    assert os.statvfs(small_disk).f_bavail >= 0


def test_recovery_refuses_what_is_not_a_bag(tmp_path):
    with pytest.raises(BagRecoveryError, match='not a bag directory'):
        recover_bag(tmp_path / 'missing')
    (tmp_path / 'empty').mkdir()
    with pytest.raises(BagRecoveryError, match='expected one .mcap or .db3'):
        recover_bag(tmp_path / 'empty')
    (tmp_path / 'junk').mkdir()
    (tmp_path / 'junk' / 'junk.mcap').write_bytes(b'not an mcap file at all')
    with pytest.raises(BagRecoveryError, match='not an mcap file'):
        recover_bag(at_rest(tmp_path / 'junk'))


@pytest.mark.ros
def test_a_bag_being_recorded_is_refused_by_recovery_and_evaluation(tmp_path, feeder):
    """The recorder's lock: recovery and evaluation refuse it; once killed, recovery works."""
    bag = tmp_path / 'bag'
    rec = _recorder(bag, 'mcap', 'flush_period:=0.1', log_dir=tmp_path)
    try:
        feeder.wait_recorder()
        feeder.publish(20)
        before = {p.name: p.read_bytes() for p in bag.iterdir()}
        pid = rec.popen.pid
        with pytest.raises(BagRecoveryError, match=rf'is being recorded \(the recorder '
                           rf'\(process {pid}\) holds .*\.recording\.lock\); nothing changed'):
            recover_bag(bag)
        # nothing touched: the live recorder's reserve is still there
        assert (bag / '.disk_reserve').exists()
        assert {p.name for p in bag.iterdir()} == set(before)
        with pytest.raises(BagToolError, match='is being recorded'):
            BagReader(bag).load()
        rec.stop(signal.SIGKILL)
    finally:
        rec.stop(signal.SIGKILL)
    # the lock went with the process; its file stays until recovery removes it
    assert (bag / '.recording.lock').exists()
    report = recover_bag(bag)
    assert report['messages'][TOPIC] >= 20 and not (bag / '.recording.lock').exists()


@pytest.mark.ros
def test_the_recorder_says_which_topics_are_in_the_bag(tmp_path, feeder):
    """recorder/heard (latched): the topics recorded, and those with a message in the bag."""
    import json
    from observer_ros.nodes.common import LATCHED_QOS
    from std_msgs.msg import String
    said = []
    feeder.probe.node.create_subscription(String, 'recorder/heard',
                                          lambda m: said.append(json.loads(m.data)),
                                          LATCHED_QOS)
    rec = _recorder(tmp_path / 'bag', 'mcap', log_dir=tmp_path)
    try:
        feeder.wait_recorder()
        feeder.probe.spin_until(lambda: said, WAIT, 'recorder/heard')
        assert {TOPIC, '/state/estimate', '/control/u'} <= set(said[-1]['recording'])
        assert TOPIC not in said[-1]['heard']
        feeder.publish(1)
        feeder.probe.spin_until(lambda: TOPIC in said[-1]['heard'], WAIT,
                                f'{TOPIC} in recorder/heard')
        assert '/state/estimate' not in said[-1]['heard']
    finally:
        assert rec.stop() == 0


def _recorder_of(bag):
    """Return the pid of the recorder writing ``bag`` (its command line has output:=bag)."""
    for pid, _, argv in processes():
        if f'output:={bag}' in argv:
            return pid
    raise AssertionError(f'no recorder writing {bag}')


@pytest.mark.ros
def test_a_stalled_recorder_loses_no_step_of_a_lockstep_run(tmp_path):
    """
    The recorder's whole process stopped 1 s in a recorded lock-step run: every step is in.

    observer-run starts the simulator with wait_for_recorder: it steps at most
    RECORDER_WINDOW steps past the newest true state the recorder wrote, fewer than the
    publishers keep, so nothing is lost while the recorder does not run.
    """
    bag = tmp_path / 'run'
    log = open(tmp_path / 'observer-run.log', 'w')
    run = subprocess.Popen(
        [str(Path(sys.executable).parent / 'observer-run'), str(VEHICLE), '--out', str(bag),
         '-p', 'simulator.duration:=300.0'],
        stdout=log, stderr=subprocess.STDOUT, env=ros_env(), start_new_session=True)
    probe = Probe('stalled_recorder_probe')
    listener = Listener(probe)
    steps = []
    probe.node.create_subscription(JointState, 'state/true', steps.append, STATE_QOS)
    try:
        probe.spin_until(lambda: len(steps) >= 20, WAIT, 'the lock-step run stepping')
        recorder = _recorder_of(bag)
        os.kill(recorder, signal.SIGSTOP)
        time.sleep(1.0)                 # the stall: nothing waits on it
        os.kill(recorder, signal.SIGCONT)
        # the simulator held for it (else the test would not test the window)
        listener.wait_counter('plant_simulator', 'recorder_waits', 1)
        probe.close()
        code = run.wait(timeout=WAIT)
    finally:
        if run.poll() is None:
            os.killpg(run.pid, signal.SIGINT)
            run.wait(timeout=60)
    out = (tmp_path / 'observer-run.log').read_text()
    assert code == 0, out[-3000:]
    stamps = {}
    with AnyReader([bag], default_typestore=STORE) as reader:
        for c, _, raw in reader.messages():
            if c.topic in ('/state/true', '/state/estimate', '/control/u'):
                stamp = reader.deserialize(raw, c.msgtype).header.stamp
                stamps.setdefault(c.topic, []).append(stamp_to_ns(stamp))
    # 300 s at 20 Hz: 6001 steps with step 0, each a true state (one), an estimate and a
    # command (an unanswered estimate may be sent again, with its stamp)
    assert len(stamps['/state/true']) == len(set(stamps['/state/true'])) == 6001
    for topic in ('/state/estimate', '/control/u'):
        assert set(stamps[topic]) == set(stamps['/state/true']), topic


def test_the_lockstep_window_is_below_the_publishers_history():
    # a lock-step simulator never gets further ahead of the bag than the writers keep for
    # it, and the recorder says its progress more often than the window is wide (else the
    # simulator would wait for a report that is not due)
    from observer_ros.nodes.plant_simulator import RECORDER_WINDOW
    from observer_ros.nodes.recorder import PROGRESS_EVERY
    from observer_ros.vehicle.schema import NODE_KEYS
    assert PROGRESS_EVERY < RECORDER_WINDOW < STATE_PUB_QOS.depth
    assert f'at most {RECORDER_WINDOW} steps past' in NODE_KEYS['wait_for_recorder'].description
