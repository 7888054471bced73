# observer_ros.nodes.compensator: u = K (x_d - x_hat) - Kd x_d from the estimate.
"""
Compensator node: ``state/estimate`` in, the command ``control/u`` out.

The control law is the seeds' tracking form u = K (x_d - x_hat) - Kd x_d (seed 002,
Eq. 5.109; with x_d = 0 it is u = -K x_hat), clipped to the file's input limits. The
command carries the stamp of the estimate it answers. What to send, and when the safe
command or the standby observer takes over, is decided by the ROS-free
core/loop_supervisor.py (its docstring lists the modes and the gates: an implausible
estimate is refused the first time, one estimate stream is followed, a command leaves
only finite and inside the limits, or without limits inside 100 x K applied to the file's
state scale). This node reads the messages, calls it, and publishes what it returns; a
second publisher of ``control/u`` or ``state/estimate`` is reported as an ERROR naming
the topic.

With ``controller.delay_compensation`` in realtime (``simulator.mode: realtime``), an estimate
that comes after the plant has moved on (a newer stamp on one of the vehicle's sensor
topics) is predicted with the model over the steps it missed, and its command stamped with
the time it takes effect (core/delay_compensation.py): the cart's loop tolerates less than
a millisecond of unmodelled delay. One later than ``observer.history_length`` gets the
safe command (``too_late_estimates``, ERROR on /diagnostics). In realtime, a plant that
cannot be held open loop (the cart) has a standby observer in this node
(core/standby.py): the vehicle's observer run on the sensor topics, which closes the loop
while ``state/estimate`` is silent.

The supervisor's log lines are written once the command they came with is published: the
first log line of a process costs tens of milliseconds on a loaded host (measured 44 ms at
a 1-minute load of 13), which before the command would make it late at the plant. A first
line is written at activation for the same reason.

Once the simulator says its run is over (``simulator/run_complete``, latched), a silent
estimate is the end of the run, not a fault: no safe command, OK on /diagnostics.

A node that follows /clock (``use_sim_time``) stamps its safe commands on /clock's time,
never past it: while /clock stands still (its owner stopped), no safe command is sent
(``safe_commands_held``), and after :data:`CLOCK_STILL` s /diagnostics says so
(``/clock stopped at T s N s ago: no safe command until it moves``).

"""

import time

from diagnostic_msgs.msg import DiagnosticStatus
from rcl_interfaces.msg import SetParametersResult
from rclpy.duration import Duration
from sensor_msgs.msg import JointState
from std_msgs.msg import Bool, Float64MultiArray

from .checks import changed_pole_problem, own_parameter_problem
from .common import (joint_state, LATCHED_QOS, MESSAGE_CLASSES, SAFE_COMMAND_FRAME,
                     SENSOR_SUB_QOS, STATE_PUB_QOS, STATE_QOS, TOPICS)
from .managed import ManagedVehicleNode
from .runner import run_node
from .wire import JointStateWriter, SensorReader, stamp_bytes, VectorReader, WireError
from ..core.control_law import command_problem, control_law
from ..core.errors import ObserverError
from ..core.estimators.admission import check_stamp
from ..core.loop_supervisor import ERROR, LoopSupervisor, OK
from ..core.vehicle_design import design_vehicle

__all__ = ['CompensatorNode', 'command_problem', 'control_law', 'main']

# Seconds between two log lines of one kind (the supervisor's reports can come per message).
LOG_PERIOD = 1.0
# s (wall): /clock standing still this long while stale is said on /diagnostics
CLOCK_STILL = 1.0
# The supervisor's levels (OK, WARN, ERROR: 0, 1, 2) as DiagnosticStatus has them.
LEVELS = (DiagnosticStatus.OK, DiagnosticStatus.WARN, DiagnosticStatus.ERROR)
# s: how long the safe command sent on deactivation may take to be acknowledged
SAFE_COMMAND_ACK_WAIT = 0.5


class CompensatorNode(ManagedVehicleNode):
    """Close the loop on the estimate (a managed node)."""

    def __init__(self):
        self.loop = None
        self.design = None
        self._logged = {}
        self._log_lines = []        # (level, text) to write once the command is out
        self._safe_timer = None
        self._run_complete = False
        super().__init__('compensator', own_parameters=(
            'publish_array', 'diagnostics_period', 'clock_jump_tolerance',
            'clock_jump_agreement', 'command_lead_steps'))

    def configure_vehicle(self):
        """Design, create the publishers (nodes/managed.py)."""
        self.design = design_vehicle(self.vehicle)
        self._cmd_pub = self.create_publisher(JointState, TOPICS['command'], STATE_PUB_QOS)
        self._array_pub = None
        if self.param('publish_array'):
            self._array_pub = self.create_publisher(
                Float64MultiArray, TOPICS['command_array'], STATE_QOS)
        self._ref_pub = self.create_publisher(JointState, TOPICS['reference'], LATCHED_QOS)
        # the messages in and out as bytes, read and written at fixed offsets (nodes/wire.py)
        plant = self.vehicle.plant
        self._est_reader = VectorReader(plant.state_names, TOPICS['estimate'])
        self._cmd_writer = JointStateWriter(plant.input_names)
        self._sensor_readers = {s.name: SensorReader(s, MESSAGE_CLASSES[s.msg_type])
                                for s in self.vehicle.sensors}
        self.add_on_set_parameters_callback(self._on_set_parameters)

    def activate_vehicle(self):
        """Start the loop afresh: publish the reference, subscribe, start the watchdog."""
        self.loop = LoopSupervisor(
            self.vehicle, self.design, self.param('command_lead_steps'),
            self.param('clock_jump_tolerance'), count=self.count, log=self._log,
            clock=self._ros_now, clock_bound=self._followed_clock,
            jump_agreement=self.param('clock_jump_agreement'))
        self._safe_timer = None
        self._safe_clock = self._clock_still_since = None
        self._publish_reference()
        standby = self.loop.standby is not None
        self.get_logger().info(
            f'closing the loop on {self.resolve_topic_name(TOPICS["estimate"])}'
            + (' (standby observer on the sensor topics)' if standby else ''))
        # realtime: the newest sensor stamp is the plant's time (how late an estimate is),
        # and the standby observer's input; subscribed first, so that an executor takes a
        # waiting sensor message first
        self._sensor_subs = []
        if self.loop.wants_sensors:
            for s in self.vehicle.sensors:
                stamped = hasattr(MESSAGE_CLASSES[s.msg_type], 'header')
                if not stamped and not self.loop.wants_values:
                    continue
                self._sensor_subs.append(self.watched_subscription(
                    MESSAGE_CLASSES[s.msg_type], s.topic,
                    lambda msg, sensor=s, stamped=stamped: self._on_sensor(sensor, msg,
                                                                           stamped),
                    SENSOR_SUB_QOS, raw=True))
        # a second publisher of the estimate is known from the match, before its data
        self._sub = self.watched_subscription(
            JointState, TOPICS['estimate'], self._on_estimate, STATE_QOS,
            matched=self._on_matched, raw=True)
        # the simulator's run is over: no safe commands to a plant that no longer runs
        self._run_complete = False
        self._complete_sub = self.watched_subscription(
            Bool, TOPICS['run_complete'], self._on_run_complete, LATCHED_QOS, shed=False)
        period = min(self.vehicle.controller.stale_timeout / 2.0, 0.1)
        self._watchdog = self.wall_timer(period, self._on_watchdog)
        self._diag_timer = self.wall_timer(self.param('diagnostics_period'),
                                           self._on_diagnostics)

    def deactivate_vehicle(self):
        """Send the safe command, as the controller stops (deactivate, shutdown, Ctrl-C)."""
        self._stop_safe_timer()
        fallback = self.vehicle.controller.safe_command     # zero, or hold the last one
        self._send(self.loop.stop_command(self.wall_now()))
        # delivered before the publisher goes (a process that ends destroys it next)
        self._cmd_pub.wait_for_all_acked(Duration(seconds=SAFE_COMMAND_ACK_WAIT))
        self.get_logger().info(f'inactive: safe command sent ({fallback}); no commands '
                               'until activated again')

    # the law's figures, as the active loop has them (tests and tools read them here)
    K = property(lambda self: self.loop.K)
    x_d = property(lambda self: self.loop.x_d)
    Kd = property(lambda self: self.loop.Kd)
    u_min = property(lambda self: self.loop.u_min)
    u_max = property(lambda self: self.loop.u_max)
    safe = property(lambda self: self.loop.safe)
    delay = property(lambda self: self.loop.delay)

    def _ros_now(self):
        return self.get_clock().now().nanoseconds * 1e-9

    def _followed_clock(self):
        """Return /clock's time (s) when this node follows /clock (use_sim_time), else None."""
        clock = self.get_clock()
        return clock.now().nanoseconds * 1e-9 if clock.ros_time_is_active else None

    def _log(self, level, text):
        """Log a report of the loop: each kind at most once per LOG_PERIOD."""
        key = (level, text.split(':', 1)[0])
        now = time.monotonic()
        if now - self._logged.get(key, -LOG_PERIOD) < LOG_PERIOD:
            return
        self._logged[key] = now
        self._log_lines.append((level, text))

    def _write_log(self):
        """Write the log lines kept back while a command was on its way."""
        lines, self._log_lines = self._log_lines, []
        for level, text in lines:
            # one call site per severity: rclpy refuses a severity that changes between calls
            if level >= ERROR:
                self.get_logger().error(text)
            else:
                self.get_logger().warning(text)

    def _publish_reference(self):
        c = self.vehicle.controller
        x_d = [0.0] * self.vehicle.plant.n if c.reference is None else c.reference
        self._ref_pub.publish(joint_state(self.vehicle.plant.state_names, x_d,
                                          self._ros_now()))

    def _on_matched(self, info):
        self.loop.publishers = max(1, int(info.current_count))
        self.loop.resync.matched(info.current_count, info.total_count)
        if self.loop.stale and self.loop.resync.lockstep and not info.current_count:
            self.get_logger().error('no estimate publisher left: safe commands (the lock-step '
                                    'simulator applies them)')

    def _on_estimate(self, msg):
        topic = TOPICS['estimate']
        try:
            header, x_hat, problem = self._est_reader.read(msg)
        except WireError as err:            # bytes that are no JointState: no stamp
            self.count('bad_estimates')
            self.get_logger().error(f'{err}; safe command', throttle_duration_sec=1.0)
            self._send(self.loop.bad_estimate(self.wall_now()))
            return
        try:
            t = check_stamp(header[0], header[1], topic)
        except ObserverError as err:
            self.count('bad_stamps')
            self.get_logger().error(f'{err}; safe command', throttle_duration_sec=1.0)
            self._send(self.loop.bad_estimate(self.wall_now()))   # the stamp is not usable
            return
        stamp = header[2]       # the command carries the estimate's stamp (its 8 bytes)
        if problem is not None:
            self.count('bad_estimates')
            self.get_logger().error(f'{problem}; safe command', throttle_duration_sec=1.0)
            self._send(self.loop.bad_estimate(self.wall_now(), t), stamp)
            return
        self._send(self.loop.estimate(t, x_hat, self.wall_now()), stamp)

    def _on_sensor(self, sensor, msg, stamped):
        """Take a sensor message: the plant's time (its stamp), the standby's measurement."""
        stamp = None
        try:
            header, y, problem = self._sensor_readers[sensor.name].read(msg)
        except WireError:
            return                  # bytes that are no such message: the observer's to report
        if stamped:
            stamp = header[2]
            try:
                t = check_stamp(header[0], header[1], sensor.topic)
            except ObserverError:
                return              # the observer counts and reports it
        else:       # std_msgs/Float64: the time it was received, as the observer takes it
            t = self._ros_now()
        if not self.loop.wants_values:
            y = None
        elif problem is not None:
            self.count('standby_refused_measurements')
        self._send(self.loop.measurement(sensor.name, t, y, self.wall_now()), stamp)

    def _send(self, command, stamp=None):
        """
        Publish a command of the loop (with the answered message's stamp if it answers).

        Then write the log lines the supervisor gave meanwhile (None: no command).
        """
        if command is None:
            self._write_log()
            return
        u = command.u
        if u.__class__ is not list:
            u = [float(v) for v in u]
        # bytes (nodes/wire.py); a command that answers carries its message's stamp
        self._cmd_pub.publish(self._cmd_writer.write(
            stamp if command.answers and stamp is not None else stamp_bytes(command.t),
            SAFE_COMMAND_FRAME if command.marked else '', u))
        if self._array_pub is not None:
            self._array_pub.publish(Float64MultiArray(data=[float(v) for v in u]))
        self._write_log()

    def _stop_safe_timer(self):
        if self._safe_timer is not None:
            self._safe_timer.cancel()
            self.destroy_timer(self._safe_timer)
            self._safe_timer = None

    def _on_run_complete(self, msg):
        complete = bool(msg.data)
        if complete and not self._run_complete:
            self.get_logger().info('the simulator completed its run: no commands while no '
                                   'estimate comes')
            self._stop_safe_timer()
        self._run_complete = complete

    def _on_watchdog(self):
        if self._run_complete:      # a silent estimate is the end of the run, not a fault
            return
        if self.loop.watchdog(self.wall_now()):
            # a safe command every sample time while stale (the prediction's step)
            self._stop_safe_timer()
            self._safe_clock = self._clock_still_since = None
            self._safe_timer = self.wall_timer(self.loop.dt / self.loop.time_rate,
                                               self._on_safe_tick)
            self._on_safe_tick()

    def _on_safe_tick(self):
        if not self.loop.stale or self._run_complete:
            self._stop_safe_timer()
            return
        if self.loop.resync.plant_waits():
            return      # lock-step with an observer matched: the plant waits for its estimates
        now = self.wall_now()
        clock = self._followed_clock()
        if clock is not None and clock == self._safe_clock:
            # /clock stands still (its owner stopped): the plant does not step either, and
            # a command stamped on by the wall clock would be ahead of it when it moves
            self.count('safe_commands_held')
            if self._clock_still_since is None:
                self._clock_still_since = now
            return
        self._safe_clock, self._clock_still_since = clock, None
        # no estimate behind it: marked, so that lock-step does not take it for one
        self._send(self.loop.safe_tick(now))

    def _on_set_parameters(self, params):
        problem = own_parameter_problem(params)
        if problem is not None:
            self.count('parameter_changes_refused')
            return SetParametersResult(successful=False, reason=problem)
        for p in params:
            if self.loop is not None and p.name == 'command_lead_steps':
                self.loop.set_lead_steps(int(p.value))
            if self.loop is not None and p.name in ('clock_jump_tolerance',
                                                    'clock_jump_agreement'):
                # checked above: a finite tolerance > 0, an agreement >= 1
                for jumps in (self.loop.sensor_jumps, self.loop.estimate_jumps):
                    setattr(jumps, p.name[len('clock_jump_'):], p.value)
        changed = [p for p in params if p.name.startswith('controller.')]
        if not changed:
            return SetParametersResult(successful=True)
        overrides = {p.name: p.value for p in params}
        # Poles and K are alternatives: setting one clears the other for this check.
        names = {p.name for p in params}
        if names & {'controller.poles', 'controller.poles_imag'} and 'controller.K' not in names:
            overrides.setdefault('controller.K', [])
        try:
            # the loader refuses unstable or unpaired poles, the design a K that does not
            # stabilise
            vehicle = self.load_vehicle(overrides)
            design = design_vehicle(vehicle)
            problem = changed_pole_problem(vehicle, 'controller', names)
        except (ObserverError, ValueError) as err:
            problem = str(err)
        if problem is not None:
            self.count('parameter_changes_refused')
            return SetParametersResult(successful=False, reason=problem)
        self.vehicle, self.design = vehicle, design
        if self.loop is not None:
            self.loop.apply(vehicle, design)
        self._publish_reference()
        self.get_logger().info(f'controller redesigned: K = {design.K.tolist()}')
        self.count('parameter_changes_applied')
        return SetParametersResult(successful=True)

    def _on_diagnostics(self):
        self._write_log()
        duplicates = self.duplicate_publishers((TOPICS['command'], TOPICS['estimate']))
        self.loop.publishers = max(1, self.count_publishers(TOPICS['estimate']))
        level, message, values = self.loop.status(duplicates)
        if self._run_complete and not duplicates:
            level, message = OK, \
                "run complete (the simulator's): no commands until estimates come again"
        elif self.loop.mode == 'waiting' and not duplicates:
            message = f'waiting for {self.resolve_topic_name(TOPICS["estimate"])}'
        elif message.startswith('estimate stale'):
            message += f' ({self.resolve_topic_name(TOPICS["estimate"])})'
            still = self._clock_still_since
            if still is not None and self.wall_now() - still >= CLOCK_STILL:
                message += (f'; /clock stopped at {self._safe_clock:.3f} s '
                            f'{self.wall_now() - still:.1f} s ago: no safe command until '
                            'it moves')
        self.publish_diagnostics(LEVELS[level], message, values)


def main(args=None):
    """Run the compensator node."""
    return run_node(CompensatorNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
