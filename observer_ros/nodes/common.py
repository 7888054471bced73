# observer_ros.nodes.common: what the nodes share (parameters, QoS, messages).
"""Shared pieces of the observer_ros nodes: vehicle parameters, QoS, conversions."""

import array
import sys
import time

from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
import numpy as np
from rcl_interfaces.msg import SetParametersResult
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import (DurabilityPolicy, HistoryPolicy, qos_profile_sensor_data, QoSProfile,
                       ReliabilityPolicy)
from sensor_msgs.msg import Imu, JointState
from std_msgs.msg import Float64

from .callback_watch import CallbackWatch
from .command_line import params_files
from .parameters import declare_parameters, GatedParameterService, set_undeclared
from .topic_watch import level_rank, TopicWatch
from ..core.errors import ObserverError
from ..core.estimators.admission import check_stamp
from ..sensors import max_components, too_many_components, vector_from_joint_state
from ..timeutil import sec_to_stamp_parts, stamp_to_sec
from ..vehicle import vehicle_from_parameters

__all__ = ['VEHICLE_SECTIONS', 'SAFE_COMMAND_FRAME', 'SENSOR_QOS', 'SENSOR_SUB_QOS',
           'STATE_QOS', 'STATE_PUB_QOS', 'LATCHED_QOS', 'MESSAGE_CLASSES', 'TOPICS',
           'VehicleNode', 'about', 'joint_state', 'checked_stamp', 'vector_from_joint_state',
           'stamp_to_sec', 'to_stamp', 'max_components', 'too_many_components']

# The parameter namespaces that belong to the vehicle file; anything else is a node's own.
VEHICLE_SECTIONS = ('vehicle', 'model', 'sensors', 'observer', 'controller', 'simulator')

# Measurements: the sensor-data profile (best effort, keep last 5), as real sensor drivers use.
SENSOR_QOS = qos_profile_sensor_data
# What the observer reads sensors with: the same best-effort profile, with a deeper queue so
# that a burst or a moment of CPU starvation does not overwrite samples before we take them.
SENSOR_SUB_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT,
                            history=HistoryPolicy.KEEP_LAST,
                            durability=DurabilityPolicy.VOLATILE)
# Estimates, commands, true state: reliable, volatile, keep last 10 (talker_qos.py /
# STYLE.md §11), as robot_localization publishes its odometry: a subscriber that comes late
# (`ros2 topic echo`) gets the next message, never an old one kept for it.
STATE_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                       history=HistoryPolicy.KEEP_LAST, durability=DurabilityPolicy.VOLATILE)
# What their publishers offer: the same. A reliable writer keeps its last 10 samples for a
# reader that has not acknowledged them: a recorder whose whole process stalls longer than
# 10 steps of a loop faster than real time would lose the steps between (its 1000-deep
# reader queue does not help: the samples never reach it). A lock-step simulator started
# with wait_for_recorder (observer-run, the launch file) steps at most RECORDER_WINDOW (5)
# steps past the recorder's recorder/progress, so a recorded lock-step run loses none; a
# realtime loop does not wait for the recorder.
STATE_PUB_QOS = STATE_QOS
# The reference x_d: latched, so a late subscriber gets it.
LATCHED_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         history=HistoryPolicy.KEEP_LAST,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)

# The sensor message types a vehicle file may name.
MESSAGE_CLASSES = {
    'sensor_msgs/msg/Imu': Imu,
    'sensor_msgs/msg/JointState': JointState,
    'std_msgs/msg/Float64': Float64,
}

# Relative topic names: they follow the node's namespace (-r __ns:=/sub1).
TOPICS = {
    'true_state': 'state/true',
    'estimate': 'state/estimate',
    'residual': 'observer/residual',
    'covariance': 'state/covariance',
    'command': 'control/u',
    'command_array': 'control/u_array',
    'reference': 'control/reference',
    'run_complete': 'simulator/run_complete',
}


def to_stamp(t):
    """Return a builtin_interfaces/Time for t seconds."""
    sec, nanosec = sec_to_stamp_parts(t)
    return Time(sec=sec, nanosec=nanosec)


#: header.frame_id of the compensator's safe command for a stale estimate (no estimate
#: behind it): a lock-step simulator does not take it for the answer while the observer
#: is alive. A safe command that answers a refused estimate or command is not marked.
SAFE_COMMAND_FRAME = 'safe_command'


def joint_state(names, values, t, frame_id='', stamp=None):
    """
    Build a JointState whose ``name`` are the vector's component names.

    ``stamp`` (a builtin_interfaces/Time), when given, is used as it is instead of ``t``:
    an answer to a message carries that message's stamp exactly (float seconds keep only
    about 0.2 us of a wall-clock stamp, and ExactTime synchronisers match to the ns).

    """
    msg = JointState()
    msg.header.stamp = to_stamp(t) if stamp is None else stamp
    msg.header.frame_id = frame_id
    msg.name = list(names)
    # an array('d') is taken as it is; a list is checked element by element (on the hot
    # path of every node: 4 us instead of 11 per message here)
    msg.position = array.array('d', values.tolist() if isinstance(values, np.ndarray)
                               else values)
    return msg


def checked_stamp(stamp, topic):
    """
    Return the seconds of a message's ``header.stamp``; refuse a malformed one.

    The admission's rule (:func:`observer_ros.core.estimators.admission.check_stamp`): a
    stamp is refused (ObserverError naming the topic) when ``nanosec`` is not below
    10^9, ``sec`` is negative, or it lies in the first second of its clock (``sec`` 0:
    an unset header, 0 s + 1 ns included; the simulator starts at 1 s). Called first by
    the callbacks, before a stamp reaches the estimator's time logic.

    """
    return check_stamp(stamp.sec, stamp.nanosec, topic)


def about(topic, err):
    """
    Return an error's text about a topic, said once: ``control/u: missing component(s) ...``.

    The message checks (:func:`vector_from_joint_state`, :func:`checked_stamp`) already
    name the topic; other errors get it in front (before, ``control/u: control/u: ...``).
    """
    text = str(err)
    return text if text.startswith(f'{topic}:') else f'{topic}: {text}'


class VehicleNode(Node):
    """
    A node whose parameters are a vehicle file (plus a few of its own).

    Parameters come from ``--params-file config/<vehicle>.yaml`` (and ``-p`` overrides);
    they are declared from the overrides and read through the same loader as the offline
    tools. A file that cannot be used stops the node before it creates any topic.

    """

    def __init__(self, node_name, own_parameters=(), load=True):
        # load: False for a managed node, which reads its vehicle when it is configured
        try:
            # the parameter services are ours: set requests admitted by a work budget
            super().__init__(node_name, automatically_declare_parameters_from_overrides=False,
                             start_parameter_services=False)
        except ValueError as err:   # rclpy refuses some parameter values before we see them
            raise ObserverError(
                f'parameters: {err} (an empty list [] has no type in ROS 2: remove the key '
                'or give it values; double arrays need floats, 1.0 not 1)') from None
        # each with a ParameterDescriptor: description, read_only, range (nodes/parameters.py)
        declare_parameters(self, own_parameters)
        if not any(name.split('.', 1)[0] in VEHICLE_SECTIONS for name in self._parameters):
            given = params_files(sys.argv)
            if given:
                raise ObserverError(
                    f'no vehicle parameters in {", ".join(given)}: a vehicle file has the '
                    f'sections {", ".join(VEHICLE_SECTIONS)} under "/**: ros__parameters:" '
                    f"(or under this node's name, {self.get_name()}); see "
                    'config/submarine.yaml')
            raise ObserverError('no vehicle parameters: start the node with --ros-args '
                                '--params-file config/<vehicle>.yaml (see --help)')
        self.vehicle = self.load_vehicle() if load else None
        self.add_on_set_parameters_callback(self._check_vehicle_change)
        self._parameter_service = GatedParameterService(self)
        # set to an exit status by a node whose work is done (the simulator at the end of
        # its run): run_nodes stops spinning and the process exits with it
        self.exit_code = None
        self._counters = {}
        self._diag_pub = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
        # Watchdogs and diagnostics run on the steady clock: with use_sim_time the ROS clock
        # stands still whenever the simulation waits, and a dead time source must still be
        # noticed.
        self.steady_clock = Clock(clock_type=ClockType.STEADY_TIME)
        # publishers this node cannot hear (QoS, type); its executor's lag, floods, and
        # /diagnostics kept on time from a thread of its own (nodes/callback_watch.py)
        self.topic_watch = TopicWatch(self)
        self.callback_watch = CallbackWatch(self, self._publish_late, self._diagnostics_period)

    def watched_subscription(self, msg_class, topic, callback, qos, shed=True, raw=False,
                             matched=None):
        """
        Create a subscription whose unheard publishers and floods are reported.

        Its publishers of another type or of an incompatible QoS are named on /diagnostics
        (:class:`~observer_ros.nodes.topic_watch.TopicWatch`); with ``shed`` its messages
        are dropped while a flood keeps the callbacks behind
        (:class:`~observer_ros.nodes.callback_watch.CallbackWatch`). ``matched``, if given,
        is called with each change of its matched publishers (rmw_matched_status_t).
        """
        entry = None
        if shed:
            entry, callback = self.callback_watch.guard(topic, callback, raw)
        events = self.topic_watch.event_callbacks(topic)
        events.matched = matched
        sub = self.create_subscription(msg_class, topic, callback, qos, raw=raw,
                                       event_callbacks=events)
        if entry is not None:
            entry.subscription = sub
        self.topic_watch.add(sub, msg_class, qos)
        return sub

    def _diagnostics_period(self):
        param = self._parameters.get('diagnostics_period')
        return None if param is None else param.value

    def destroy_node(self):
        """Stop the callback watch's thread, then destroy the node."""
        self.callback_watch.stop()
        return super().destroy_node()

    def wall_timer(self, period, callback):
        """Create a timer on the steady (wall) clock."""
        return self.create_timer(period, callback, clock=self.steady_clock)

    @staticmethod
    def wall_now():
        """Return steady-clock seconds (for ages and timeouts; cheap on the hot path)."""
        return time.monotonic()

    def set_parameters_atomically(self, parameter_list):
        """
        Set parameters as rclpy does; declare first a writable vehicle key not yet declared.

        ``ros2 param set /observer observer.rate_hz 50.0`` on a node whose file has no
        ``observer.rate_hz`` declares it (checked as any change); an unknown or read-only
        name is refused with a reason naming it (nodes/parameters.py, ``set_undeclared``).
        """
        fresh = [p for p in parameter_list if not self.has_parameter(p.name)]
        if fresh:
            result = set_undeclared(self, fresh)
            names = {p.name for p in fresh}
            parameter_list = [p for p in parameter_list if p.name not in names]
            if not result.successful or not parameter_list:
                return result
        return super().set_parameters_atomically(parameter_list)

    def vehicle_parameters(self):
        """Return the vehicle-file parameters of this node as a flat dict."""
        flat = {}
        for name, param in self._parameters.items():
            if name.split('.', 1)[0] in VEHICLE_SECTIONS:
                flat[name] = param.value
        return flat

    def load_vehicle(self, overrides=None):
        """Load the vehicle from this node's parameters; log and raise on errors."""
        flat = self.vehicle_parameters()
        if overrides:
            flat.update(overrides)
        vehicle = vehicle_from_parameters(flat, source=f'node {self.get_fully_qualified_name()}')
        for text in vehicle.warnings:
            self.get_logger().warning(text)
        return vehicle

    def _check_vehicle_change(self, params):
        """Refuse a run-time change that makes the vehicle invalid, as a whole, with why."""
        changed = {p.name: p.value for p in params
                   if p.name.split('.', 1)[0] in VEHICLE_SECTIONS}
        if not changed or self.vehicle is None:     # unconfigured: checked at configure
            return SetParametersResult(successful=True)
        flat = self.vehicle_parameters()
        flat.update(changed)
        try:
            vehicle_from_parameters(flat, source=f'node {self.get_fully_qualified_name()}')
        except (ObserverError, ValueError) as err:
            self.count('parameter_changes_refused')
            return SetParametersResult(successful=False, reason=str(err))
        return SetParametersResult(successful=True)

    def duplicate_publishers(self, topics):
        """
        Return ``"topic (N publishers)"`` for each topic with more than one publisher.

        One node publishes the estimate and one the command of a vehicle: a second one
        (two observers started with one name, a stray node) sends conflicting data.

        """
        found = []
        for topic in topics:
            n = self.count_publishers(topic)
            if n > 1:
                found.append(f'{self.resolve_topic_name(topic)} ({n} publishers)')
        return found

    def param(self, name):
        """Return the value of one of the node's own parameters."""
        return self.get_parameter(name).value

    def count(self, key, n=1):
        """Increment a diagnostics counter."""
        self._counters[key] = self._counters.get(key, 0) + n

    def publish_diagnostics(self, level, message, values=None, extra=()):
        """
        Publish this node's DiagnosticStatus on /diagnostics (and ``extra`` ones after it).

        ``extra``: ``(name suffix, level, message, values)`` of statuses named
        ``<node>/<suffix>`` in the same array (the observer's per-sensor innovation health).
        """
        items = dict(self._counters)
        items.update(values or {})
        # what keeps messages from this node: unheard publishers, a flood (worst first)
        watch = self.topic_watch.problems()
        flood = self.callback_watch.status()
        if flood is not None:
            watch = [flood] + watch
        items.update(self.topic_watch.counters())
        items.update(self.callback_watch.values())
        for i, (_, text) in enumerate(watch, 1):
            items[f'problem {i}'] = text
        if watch and level_rank(watch[0][0]) >= level_rank(level):
            more = f' (and {len(watch) - 1} more)' if len(watch) > 1 else ''
            ok = level_rank(level) == level_rank(DiagnosticStatus.OK)
            level, message = watch[0][0], watch[0][1] + more + ('' if ok else f'; {message}')
        self._publish_status(level, message, items, extra)
        now = time.monotonic()
        self.callback_watch.status_at = self.callback_watch.reported_at = now

    def _publish_late(self, level, message, values):
        """Publish the callback watch's report for this node, its own being overdue (a thread)."""
        items = dict(self._counters)
        items.update(values)
        self._publish_status(level, message, items)

    def _publish_status(self, level, message, items, extra=()):
        status = DiagnosticStatus()
        status.level = level
        status.name = f'{self.get_fully_qualified_name()}'
        status.message = message
        status.hardware_id = self.vehicle.name
        status.values = [KeyValue(key=str(k), value=str(v)) for k, v in sorted(items.items())]
        array = DiagnosticArray()
        array.header.stamp = self.get_clock().now().to_msg()
        array.status = [status]
        for suffix, level, text, more in extra:
            part = DiagnosticStatus(level=level, name=f'{status.name}/{suffix}', message=text,
                                    hardware_id=status.hardware_id)
            part.values = [KeyValue(key=str(k), value=str(v)) for k, v in sorted(more.items())]
            array.status.append(part)
        self._diag_pub.publish(array)
