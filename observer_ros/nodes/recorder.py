# observer_ros.nodes.recorder: record a vehicle's topics to a ROS 2 bag with rosbags.
"""
Recorder node: subscribes raw (no deserialisation) and writes a rosbag2 bag.

Topics: the vehicle's sensors, ``state/true``, ``state/estimate``, ``observer/residual``,
``control/u``, ``control/reference``, ``/clock`` and ``/diagnostics`` (resolved in the
node's namespace), plus ``extra_topics`` ("name:pkg/msg/Type"). The storage is mcap
(Jazzy's default) or sqlite3, metadata version 9, each topic's QoS recorded as offered.
Messages are stamped with the node clock at reception (sim time with use_sim_time; those
received before the first /clock are written at its time). The metadata names the ROS
distribution (``ros_distro: jazzy``, ``$ROS_DISTRO`` when set). The
readers keep up to ``queue_depth`` messages per topic (default 1000, whatever the
publisher's depth), so that a burst loses nothing. The publishers keep only their last 10
estimates, commands and true states (nodes/common.py, STATE_PUB_QOS): a stall of the
recorder's whole process longer than that loses the messages between, unless the run
waits for it. A lock-step simulator started with ``wait_for_recorder`` does: the recorder
publishes on ``recorder/progress`` (builtin_interfaces/Time) the stamp of the newest true
state it wrote, every ``PROGRESS_EVERY`` of them, and the simulator steps at most
``RECORDER_WINDOW`` steps past it (nodes/plant_simulator.py).

SIGINT or SIGTERM closes the bag cleanly: every message received before the signal is
in it. Every ``flush_period`` seconds (wall time) the writer flushes: mcap closes its
pending chunk and flushes the file, sqlite3 commits; then the recorder reports on
/diagnostics (``messages``: the total on disk, ``messages <topic>`` per topic). A SIGKILL
therefore loses at most the messages since the last flush, and ``observer-bag-recover BAG``
(observer_ros.bag.recover) makes such a bag readable again.

A write that fails (disk full, I/O error) stops the recorder with a logged error naming
the bag and exit status 1; the bag is then recovered in place up to its last flush (or,
when even that fails, left for ``observer-bag-recover``). So that recovery finds room on
a full disk, the recorder holds ``disk_reserve`` bytes (default 1 MiB) in a file
``.disk_reserve`` inside the bag, and frees them before recovering (a clean close and
``observer-bag-recover`` delete the file). An existing ``output`` is never
overwritten: the recorder refuses to start (status 2) and names the path. While it writes,
it holds an exclusive lock on ``BAG/.recording.lock`` (its process id inside):
``observer-bag-recover`` and ``observer-eval`` refuse a bag being recorded.

"""

import json
import os
from pathlib import Path
import shutil
import sqlite3
import sys
import time
import warnings

from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticStatus
import rclpy
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rosbags.interfaces import (Qos, QosDurability, QosHistory, QosLiveliness,
                                QosReliability, QosTime)
from rosbags.rosbag2 import StoragePlugin
from rosbags.typesys import get_typestore, Stores
from std_msgs.msg import Bool, String

from . import signals
from .common import LATCHED_QOS, SENSOR_QOS, STATE_PUB_QOS, STATE_QOS, TOPICS, VehicleNode
from .runner import exit_status, init_ros, make_executor, spin_until
from .wire import header_stamp
from ..bag.bag_checks import hold_recording_lock, LOCK_NAME
from ..bag.integrity import CrcWriter
from ..bag.play import message_class
from ..core.errors import error_text, ObserverError
from ..ros_names import check_topic_name

__all__ = ['RecorderNode', 'RecorderWriter', 'RecordingError', 'main', 'recorded_topics']

STORAGES = {'mcap': StoragePlugin.MCAP, 'sqlite3': StoragePlugin.SQLITE3}


def _hold_reserve(bag, size):
    """Write ``size`` bytes to ``bag/.disk_reserve`` (really allocated); return its path."""
    if size <= 0:
        return None
    path = bag / '.disk_reserve'
    try:
        with path.open('xb') as f:
            try:
                os.posix_fallocate(f.fileno(), 0, size)
            except (AttributeError, OSError):
                block = b'\0' * (1 << 20)        # bounded memory, whatever the size
                for start in range(0, size, len(block)):
                    f.write(block[:min(len(block), size - start)])
    except OSError as err:
        path.unlink(missing_ok=True)
        raise ObserverError(f'recorder: cannot reserve {size} bytes in {bag}: '
                            f'{os.strerror(err.errno) if err.errno else err}') from None
    return path


def _check_free_space(path, reserve):
    """Refuse a negative reserve, or one the file system of the bag cannot hold."""
    if reserve < 0:
        raise ObserverError(f'recorder: disk_reserve must be >= 0 bytes; got {reserve}')
    parent = Path(os.path.abspath(path)).parent
    while not parent.exists():
        parent = parent.parent
    free = shutil.disk_usage(parent).free
    if reserve >= free:
        raise ObserverError(f'recorder: disk_reserve ({reserve} bytes) is not less than the '
                            f'free space on {parent} ({free} bytes); nothing written')


# messages received before the first /clock (simulated time 0) kept for it, at most
EARLY_LIMIT = 10000

#: recorder/progress: said every this many true states written (a lock-step simulator
#: with wait_for_recorder steps at most plant_simulator.RECORDER_WINDOW steps past it).
PROGRESS_EVERY = 2
# the ROS distribution named in the bag's metadata (rosbags writes its own name there)
ROS_DISTRO = os.environ.get('ROS_DISTRO') or 'jazzy'


def _name_distro(metadata):
    """Return bag metadata (YAML text) with ``ros_distro`` the ROS distribution's."""
    return metadata.replace('ros_distro: rosbags', f'ros_distro: {ROS_DISTRO}')


class RecorderWriter(CrcWriter):
    """rosbags' Writer with chunk CRCs whose metadata names the ROS distribution."""

    def close(self):
        """Close as rosbags does; ``ros_distro`` in the storage's and the file's metadata."""
        storage = self.storage
        if storage is not None:
            close_storage = storage.close

            def close_named(version, metadata):
                close_storage(version, _name_distro(metadata))
            storage.close = close_named
        super().close()
        tmp = self.metapath.with_suffix('.yaml.tmp')
        tmp.write_text(_name_distro(self.metapath.read_text()), 'utf8')
        tmp.replace(self.metapath)


class RecordingError(ObserverError):
    """Writing the bag failed while recording (disk full, I/O error); the recorder stops."""


def flush_storage(writer):
    """
    Push everything a rosbags Writer holds to the operating system.

    mcap: the pending chunk is closed (written with its message indexes) and the file is
    flushed; sqlite3: the open transaction is committed. After this, a killed process
    leaves every message written so far on disk (``observer-bag-recover`` reads them).
    Uses rosbags 0.11's storage internals; returns False when they are not there.

    """
    storage = writer.storage
    if storage is None:
        return False
    chunk = getattr(storage, 'chunk', None)
    if chunk is not None and hasattr(storage, 'close_chunk') and hasattr(storage, 'bio'):
        if chunk.bio.tell():
            storage.close_chunk()
        storage.bio.flush()
        return True
    conn = getattr(storage, 'conn', None)
    if isinstance(conn, sqlite3.Connection):
        conn.commit()
        return True
    return False


def recorded_topics(vehicle):
    """
    Return the (relative name, type, QoS) of every topic a vehicle's run produces.

    Parameters
    ----------
    vehicle : observer_ros.core.spec.Vehicle
        The vehicle (its sensors give the sensor topics).

    Returns
    -------
    list of tuple

    """
    topics = [(s.topic, s.msg_type, SENSOR_QOS) for s in vehicle.sensors]
    js = 'sensor_msgs/msg/JointState'
    topics += [(TOPICS['true_state'], js, STATE_PUB_QOS),
               (TOPICS['estimate'], js, STATE_PUB_QOS),
               (TOPICS['residual'], js, STATE_PUB_QOS), (TOPICS['command'], js, STATE_PUB_QOS),
               (TOPICS['reference'], js, LATCHED_QOS),
               ('/clock', 'rosgraph_msgs/msg/Clock', STATE_QOS),
               ('/diagnostics', 'diagnostic_msgs/msg/DiagnosticArray', STATE_QOS)]
    return topics


def _bag_qos(qos):
    """Translate an rclpy QoS profile into rosbags' Qos for the metadata."""
    reliable = qos.reliability == ReliabilityPolicy.RELIABLE
    latched = qos.durability == DurabilityPolicy.TRANSIENT_LOCAL
    return Qos(
        history=QosHistory.KEEP_LAST, depth=qos.depth,
        reliability=QosReliability.RELIABLE if reliable else QosReliability.BEST_EFFORT,
        durability=QosDurability.TRANSIENT_LOCAL if latched else QosDurability.VOLATILE,
        deadline=QosTime(sec=0, nsec=0), lifespan=QosTime(sec=0, nsec=0),
        liveliness=QosLiveliness.AUTOMATIC, liveliness_lease_duration=QosTime(sec=0, nsec=0),
        avoid_ros_namespace_conventions=False)


def _deeper(qos, depth):
    """Return the same QoS with a reader queue of at least `depth` (still compatible)."""
    return QoSProfile(history=qos.history, depth=max(qos.depth, depth),
                      reliability=qos.reliability, durability=qos.durability)


class RecorderNode(VehicleNode):
    """Write the vehicle's topics to a bag."""

    def __init__(self):
        super().__init__('recorder', own_parameters=(
            ('output', '', 'bag directory to create (must not exist); required'),
            ('storage', 'mcap', 'mcap or sqlite3'),
            ('extra_topics', [''], 'more topics to record, each "name:pkg/msg/Type"'),
            ('flush_period', 1.0, 's (wall): flush to disk, report counts'),
            ('disk_reserve', 1 << 20, 'bytes kept free for closing/recovering the bag'),
            ('queue_depth', 1000, 'per-topic reader queue (rides out bursts)'),
        ))
        output = self.param('output')
        if not output:
            raise ObserverError('recorder: parameter output (the bag directory) is required')
        storage = self.param('storage')
        if storage not in STORAGES:
            raise ObserverError(f'recorder: storage must be mcap or sqlite3; got {storage!r}')
        path = Path(output)
        if path.exists() or path.is_symlink():
            raise ObserverError(f'recorder: {path} exists; refusing to overwrite a bag')
        self.typestore = get_typestore(Stores.ROS2_JAZZY)
        # every parameter is checked before the bag folder is made: a refusal leaves no trace
        topics = recorded_topics(self.vehicle) + self._extra_topics()
        classes = [message_class(msgtype) for _, msgtype, _ in topics]
        period = self._number('flush_period', float)
        if not period > 0.0 or period == float('inf'):
            raise ObserverError(f'recorder: flush_period must be > 0 s; got {period}')
        depth = self._number('queue_depth', int)
        if depth < 1:
            raise ObserverError(f'recorder: queue_depth must be >= 1; got {depth}')
        reserve = self._number('disk_reserve', int)
        _check_free_space(path, reserve)
        self._early = []        # (connection, data) received before the first /clock
        self.writer = RecorderWriter(path, version=9, storage_plugin=STORAGES[storage])
        try:
            self.writer.open()
        except OSError as err:
            raise ObserverError(f'recorder: cannot create the bag: {error_text(err)}') \
                from None
        self.path = path
        self.failed = None
        self._reserve = None
        self._lock = None
        self.counts = {}
        self.flushes = 0
        self._subs = []
        try:
            # held until the bag is closed: recovery and evaluation refuse a bag being
            # recorded (bag/bag_checks.py); a killed recorder's lock goes with it
            try:
                self._lock = hold_recording_lock(path)
            except OSError as err:      # a file system without locks: record all the same
                self.get_logger().warning(
                    f'cannot lock {path / LOCK_NAME} ({err.strerror or err}): recovery and '
                    'evaluation will not know that the bag is being recorded')
            self._reserve = _hold_reserve(path, reserve)
            for (name, msgtype, qos), cls in zip(topics, classes):
                resolved = self.resolve_topic_name(name)
                conn = self.writer.add_connection(resolved, msgtype,
                                                  typestore=self.typestore,
                                                  offered_qos_profiles=[_bag_qos(qos)])
                self.counts[resolved] = 0
                self._subs.append(self.watched_subscription(
                    cls, name, lambda data, c=conn: self._on_message(c, data),
                    _deeper(qos, depth), shed=False, raw=True))
        except BaseException:
            self._discard_bag()        # made a moment ago by this node: nothing else in it
            raise
        self.get_logger().info(f'recording {len(topics)} topics to {path} ({storage})')
        # the topic definitions go to disk at once: a bag killed before its first periodic
        # flush still recovers (with its topics, no messages)
        if not flush_storage(self.writer):
            self.get_logger().warning('this rosbags version cannot flush while writing: a '
                                      'SIGKILL loses the whole bag')
        self._flush_timer = self.wall_timer(period, self._flush)
        # 'recorder/ready' (latched) once every recorded topic has a matched publisher, so a
        # simulator started with wait_for_recorder loses nothing to DDS matching
        self._ready_pub = self.create_publisher(Bool, 'recorder/ready', LATCHED_QOS)
        self._ready_timer = self.wall_timer(0.05, self._check_ready)
        # 'recorder/heard' (latched): the topics recorded and those a message of which is in
        # the bag. A matched reader is not a matched writer (discovery is not symmetric):
        # a lock-step simulator holds step 0 until the bag has its estimate and command
        self._heard = set()
        self._heard_pub = self.create_publisher(String, 'recorder/heard', LATCHED_QOS)
        self._say_heard()
        # 'recorder/progress': the newest true state's stamp written (the module says why)
        self._true_topic = self.resolve_topic_name(TOPICS['true_state'])
        self._true_written = 0
        self._progress_pub = self.create_publisher(Time, 'recorder/progress', STATE_QOS)

    def _number(self, name, kind):
        """Return a numeric own parameter as ``kind``; refuse another type by name."""
        value = self.param(name)
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ObserverError(f'recorder: {name} must be a number; got {value!r}')
        if kind is int and value != int(value):
            raise ObserverError(f'recorder: {name} must be a whole number; got {value!r}')
        return kind(value)

    def _extra_topics(self):
        """Return the (name, type, QoS) of ``extra_topics``; refuse an entry by its text."""
        topics = []
        for entry in self.param('extra_topics'):
            if not entry:
                continue
            name, _, msgtype = entry.partition(':')
            if not name or not msgtype:
                raise ObserverError(f'recorder: extra_topics entry {entry!r} is not '
                                    '"name:pkg/msg/Type"')
            if msgtype not in self.typestore.types:
                raise ObserverError(f'recorder: extra_topics entry {entry!r}: unknown message '
                                    f'type {msgtype}')
            check_topic_name(name, f'recorder: extra_topics entry {entry!r}: topic')
            topics.append((name, msgtype, STATE_QOS))
        return topics

    def _discard_bag(self):
        """Remove the bag this node has just made (a start-up that failed leaves no trace)."""
        writer, self.writer = self.writer, None
        try:
            writer.abort()
        except Exception:   # noqa: BLE001 - the files go either way
            pass
        self._release_lock()
        for child in self.path.iterdir():
            if child.is_file() and not child.is_symlink():
                child.unlink()
        try:
            self.path.rmdir()
        except OSError:
            pass

    def _check_ready(self):
        waiting = [sub.topic_name for sub in self._subs if sub.get_publisher_count() < 1]
        if waiting:
            self.get_logger().info(f'waiting for publishers of {waiting}',
                                   throttle_duration_sec=2.0)
            return
        self._ready_timer.cancel()
        self._ready_pub.publish(Bool(data=True))
        self.get_logger().info('every topic has a publisher: ready')

    def _flush(self):
        """Push buffered messages to disk, then report the counts (now all on disk)."""
        if self.writer is None:
            return
        try:
            flush_storage(self.writer)
        except (OSError, sqlite3.Error) as err:
            self._fail(err)
        self.flushes += 1
        total = sum(self.counts.values())
        values = {'messages': total, 'flushes': self.flushes}
        values.update({f'messages {topic}': n for topic, n in self.counts.items()})
        self.publish_diagnostics(DiagnosticStatus.OK, f'recording to {self.path}', values)

    def _on_message(self, connection, data):
        if self.writer is None:
            return
        t = self.get_clock().now().nanoseconds
        if not t and len(self._early) < EARLY_LIMIT:
            # simulated time before the first /clock: kept until it comes, then written at
            # its time (a bag that starts at 0 s says nothing of when it was recorded)
            self._early.append((connection, data))
            return
        if self._early:
            self._write_early(t)
        self._write(connection, t, data)

    def _write(self, connection, t, data):
        try:
            self.writer.write(connection, t, data)
        except (OSError, sqlite3.Error) as err:
            self._fail(err)
        self.counts[connection.topic] += 1
        if connection.topic == self._true_topic:
            self._true_written += 1
            if self._true_written % PROGRESS_EVERY == 0 and len(data) >= 12:
                sec, nanosec, _ = header_stamp(data)
                self._progress_pub.publish(Time(sec=sec, nanosec=nanosec))
        if connection.topic not in self._heard:
            self._heard.add(connection.topic)
            self._say_heard()

    def _say_heard(self):
        self._heard_pub.publish(String(data=json.dumps(
            {'recording': sorted(self.counts), 'heard': sorted(self._heard)})))

    def _write_early(self, t):
        """Write what came before the first /clock, in the order it came, at time t."""
        early, self._early = self._early, []
        for connection, data in early:
            self._write(connection, t, data)

    def received(self):
        """Return the messages received so far (on disk, or waiting for the first /clock)."""
        return sum(self.counts.values()) + len(self._early)

    def _release_lock(self, remove=False):
        """Release the recording lock (and remove its file once the bag is closed)."""
        if self._lock is not None:
            lock, self._lock = self._lock, None
            if remove:
                (self.path / LOCK_NAME).unlink(missing_ok=True)
            lock.close()

    def _release_reserve(self):
        if self._reserve is not None:
            self._reserve.unlink(missing_ok=True)
            self._reserve = None

    def _fail(self, err):
        """Abort the bag after a failed write, recover it up to its last flush, raise."""
        writer, self.writer = self.writer, None
        log = self.get_logger()
        self._release_reserve()
        reason = error_text(err) if isinstance(err, OSError) else err
        text = f'cannot write the bag {self.path}: {reason}'
        log.error(f'{text}; recording stopped')
        self.failed = text
        try:
            writer.abort()
        except Exception:   # noqa: BLE001 - the file is closed either way
            pass
        from ..bag.recover import BagRecoveryError, recover_bag
        self._release_lock()        # recovery takes the bag over (and removes the lock file)
        try:
            report = recover_bag(self.path)
            log.error(f'bag {self.path} recovered up to its last flush: '
                      f'{report["total"]} messages readable')
        except (BagRecoveryError, OSError) as rec_err:
            log.error(f'bag {self.path} not recovered now ({error_text(rec_err)}); free '
                      f'some space and run: observer-bag-recover {self.path}')
        try:
            self.publish_diagnostics(DiagnosticStatus.ERROR, text,
                                     {'messages': sum(self.counts.values())})
        except Exception:   # noqa: BLE001 - shutting down anyway
            pass
        raise RecordingError(text)

    def close(self):
        """Close the bag (idempotent)."""
        if self.writer is not None and self._early:     # no /clock ever came
            self._write_early(self.get_clock().now().nanoseconds)
        if self.writer is not None:
            writer, self.writer = self.writer, None
            self._release_reserve()
            try:
                writer.close()
            except (OSError, sqlite3.Error) as err:
                with_abort = f'cannot close the bag {self.path}: {error_text(err)}'
                self.get_logger().error(f'{with_abort}; run observer-bag-recover {self.path}')
                self.failed = with_abort
                try:
                    writer.abort()
                except Exception:   # noqa: BLE001 - the file is closed either way
                    pass
                self._release_lock()
                return
            self._release_lock(remove=True)
            total = sum(self.counts.values())
            self.get_logger().info(f'bag closed: {self.path} ({total} messages)')

    def destroy_node(self):
        """Close the bag, then destroy the node."""
        self.close()
        return super().destroy_node()


def _drain(executor, node, quiet=0.3, limit=10.0):
    """
    Take what DDS already delivered, then stop: the backlog, and stragglers for `quiet` s.

    First every callback that is ready is run, until a few non-blocking spins in a row take
    no message (the recorder has caught up: a lagging recorder writes its whole backlog).
    Then messages are taken for `quiet` s more (a reliable sample still under way). Both
    together never take longer than `limit` s, and a live system, whose messages never
    stop, is not recorded for longer than that: the bag closes within about `quiet` s
    once the backlog is written.

    """
    deadline = time.monotonic() + limit
    idle = 0
    while idle < 3 and time.monotonic() < deadline and not node.failed:
        before = node.received()
        executor.spin_once(timeout_sec=0.0)
        idle = idle + 1 if node.received() == before else 0
    end = min(deadline, time.monotonic() + quiet)
    while time.monotonic() < end and not node.failed:
        executor.spin_once(timeout_sec=max(0.0, end - time.monotonic()))


def main(args=None):
    """
    Run the recorder node; return the exit status.

    SIGINT and SIGTERM stop it cleanly (nodes/signals.py): the messages already delivered
    are drained into the bag, and it is closed; status 0. Status 2:
    it cannot start (bad parameters, the output exists); 1: writing failed.

    """
    warnings.filterwarnings('ignore', category=DeprecationWarning)
    # A stop signal (nodes/signals.py) stops the spinning, then the messages DDS already
    # delivered (a recorder lags a fast lock-step run) are drained into the bag.
    code = init_ros(RecorderNode, args)
    if code is not None:    # --help, an unusable params file, or stopped already
        return code
    node = executor = None
    code = 0
    try:
        node = RecorderNode()
        executor, _ = make_executor()
        executor.add_node(node)
        spin_until(executor, lambda: node.failed)
        _drain(executor, node)
    except RecordingError as err:
        print(f'error: recorder: {err}', file=sys.stderr)
        code = 1
    except Exception as err:   # noqa: BLE001 - reported by exit_status
        code = exit_status(err, 'recorder')
    finally:
        # a later signal only records itself: the bag is closed whatever comes
        if executor is not None:
            executor.shutdown()
        if node is not None:
            node.close()
            if node.failed and code == 0:
                code = 1
            node.destroy_node()
        rclpy.try_shutdown()
        signals.ignore()    # the process only exits now (nodes/runner.py)
    return code


if __name__ == '__main__':
    raise SystemExit(main())
