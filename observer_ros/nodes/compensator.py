# observer_ros.nodes.compensator: u = K (x_d - x_hat) - Kd x_d from the estimate.
"""
Compensator node: ``state/estimate`` in, the command ``control/u`` out.

The control law is the seeds' tracking form u = K (x_d - x_hat) - Kd x_d (seed 002,
Eq. 5.109; with x_d = 0 it is u = -K x_hat), clipped to the file's input limits. The
command carries the stamp of the estimate it answers. A stale, non-finite or diverging
estimate, or a malformed stamp, gives the safe command (core/safe_command.py:
predict-and-hold for ``controller.predict_timeout``, then ``controller.safe_command``)
and an ERROR on /diagnostics. Every command passes one gate before it is sent: finite and
inside ``controller.u_min``/``u_max``, or it is not sent (the safe command instead, an
ERROR on /diagnostics). A second publisher of ``control/u`` or ``state/estimate`` is
reported as an ERROR naming the topic.

With ``controller.delay_compensation`` in realtime (``simulator.mode: realtime``), an estimate
that comes after the plant has moved on (a newer stamp on one of the vehicle's sensor
topics, which the node reads for their stamps only) is predicted with the model over the
steps it missed, and its command stamped with the time it takes effect
(core/delay_compensation.py): the cart's loop tolerates less than a millisecond of
unmodelled delay. One later than ``observer.history_length`` gets the safe command
(``too_late_estimates``, ERROR on /diagnostics).

"""

import math

from diagnostic_msgs.msg import DiagnosticStatus
import numpy as np
from rcl_interfaces.msg import SetParametersResult
from rclpy.duration import Duration
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

from .checks import changed_pole_problem, divergence_envelopes, own_parameter_problem
from .common import (checked_stamp, joint_state, LATCHED_QOS, MESSAGE_CLASSES,
                     SAFE_COMMAND_FRAME, SENSOR_QOS, stamp_to_sec, STATE_PUB_QOS, STATE_QOS,
                     TOPICS, vector_from_joint_state)
from .managed import ManagedVehicleNode
from .runner import run_node
from ..core.control_law import command_problem, control_law, ControlLaw
from ..core.delay_compensation import DelayCompensation
from ..core.errors import ObserverError
from ..core.health import SettleCheck, settling_time
from ..core.safe_command import SafeCommand
from ..core.vehicle_design import design_vehicle

__all__ = ['CompensatorNode', 'command_problem', 'control_law', 'main']

# After an outage, wait at most this many observer settling times for it to settle again.
RESYNC_SETTLINGS = 10.0
# s: how long the safe command sent on deactivation may take to be acknowledged
SAFE_COMMAND_ACK_WAIT = 0.5


class CompensatorNode(ManagedVehicleNode):
    """Close the loop on the estimate (a managed node)."""

    def __init__(self):
        super().__init__('compensator', own_parameters=(
            'publish_array', 'diagnostics_period', 'clock_jump_tolerance',
            'command_lead_steps'))

    def configure_vehicle(self):
        """Design, create the publishers (nodes/managed.py)."""
        self._apply(self.vehicle, design_vehicle(self.vehicle))
        self._cmd_pub = self.create_publisher(JointState, TOPICS['command'], STATE_PUB_QOS)
        self._array_pub = None
        if self.param('publish_array'):
            self._array_pub = self.create_publisher(
                Float64MultiArray, TOPICS['command_array'], STATE_QOS)
        self._ref_pub = self.create_publisher(JointState, TOPICS['reference'], LATCHED_QOS)
        self.add_on_set_parameters_callback(self._on_set_parameters)

    def activate_vehicle(self):
        """Publish the reference, subscribe to the estimate, start the watchdog."""
        self._last_estimate_time = None      # node clock when the last good x_hat came
        self._last_stamp = None              # its stamp (s): the estimates' time base
        self._stale = False
        self._diverging = None               # what diverges (a report), or None
        self._safe_mode = None               # how the last safe command was decided
        self._resyncing = False              # back from an outage, the observer settling
        self._recovering = False             # closing the loop again after an outage
        self._inside_since = None            # recovering: stamp since inside the envelope
        self._safe_timer = None
        self._refused = None                 # why the last command was not sent
        self._duplicates = []                # other publishers of our topics
        self._max_steps_late = 0             # since the last report (delay compensation)
        self._too_late = 0                   # estimates too late to predict, since then
        self._jump_tolerance = self.param('clock_jump_tolerance')   # read once per change
        self._publish_reference()
        # realtime: the newest sensor stamp is the plant's time (how late an estimate is);
        # subscribed first, so that an executor takes a waiting sensor message first
        self._sensor_time = {}              # each sensor's newest stamp (its clock's jumps)
        self._plant_time = None             # the newest of them
        self._sensor_subs = [self.watched_subscription(
            MESSAGE_CLASSES[s.msg_type], s.topic,
            lambda msg, name=s.name: self._on_sensor(name, msg), SENSOR_QOS)
            for s in self.vehicle.sensors
            if self.delay is not None and hasattr(MESSAGE_CLASSES[s.msg_type], 'header')]
        self._sub = self.watched_subscription(
            JointState, TOPICS['estimate'], self._on_estimate, STATE_QOS)
        period = min(self.vehicle.controller.stale_timeout / 2.0, 0.1)
        self._watchdog = self.wall_timer(period, self._on_watchdog)
        self._diag_timer = self.wall_timer(self.param('diagnostics_period'),
                                           self._on_diagnostics)

    def deactivate_vehicle(self):
        """Send the safe command, as the controller stops (deactivate, shutdown, Ctrl-C)."""
        self._stop_safe_timer()
        fallback = self.vehicle.controller.safe_command     # zero, or hold the last one
        u = self.safe.last_command if fallback == 'hold' else np.zeros(self.vehicle.plant.m)
        if self.u_min is not None or self.u_max is not None:
            u = np.clip(u, self.u_min, self.u_max)
        self._send(u, self._estimate_clock(), frame_id=SAFE_COMMAND_FRAME)
        # delivered before the publisher goes (a process that ends destroys it next)
        self._cmd_pub.wait_for_all_acked(Duration(seconds=SAFE_COMMAND_ACK_WAIT))
        self.get_logger().info(f'inactive: safe command sent ({fallback}); no commands '
                               'until activated again')

    def _apply(self, vehicle, design):
        n, m = vehicle.plant.n, vehicle.plant.m
        c = vehicle.controller
        self.vehicle = vehicle
        self.K = np.asarray(design.K, dtype=float).reshape(m, n)
        self.x_d = np.zeros(n) if c.reference is None else np.asarray(c.reference, float)
        self.Kd = np.zeros((m, n)) if c.Kd is None else np.asarray(c.Kd, float).reshape(m, n)
        self.u_min, self.u_max = c.u_min, c.u_max
        self.law = ControlLaw(self.K, self.x_d, self.Kd, self.u_min, self.u_max)   # floats
        self.design = design
        last = getattr(self, 'safe', None)
        self.safe = SafeCommand(vehicle.plant, self._law, vehicle.sample_time, c.safe_command,
                                c.predict_timeout)
        if last is not None:
            self.safe.sent(last.last_command)
        self.x_envelope, self.u_envelope = divergence_envelopes(vehicle, self.K, self.x_d,
                                                                self.Kd)
        # after an outage the observer needs this long (its slowest pole) to converge
        self.settle = settling_time(design.observer_poles, vehicle.sample_time,
                                    vehicle.plant.is_discrete)
        self.settle_check = SettleCheck(self.safe.Ad, self.safe.Bd, self.safe.dt,
                                        self.x_envelope.file_scale)
        # lock-step has no latency (the simulator waits for each answer): nothing to predict
        compensate = c.delay_compensation and vehicle.simulator.mode == 'realtime'
        self.delay = DelayCompensation(
            self.safe.Ad, self.safe.Bd, self.safe.dt, vehicle.observer.history_length,
            self.param('command_lead_steps')) if compensate else None

    def _law(self, x_hat):
        """Return the law's command for x_hat (an ndarray): the safe command's prediction."""
        return self.law(x_hat.tolist())

    def _publish_reference(self):
        now = self.get_clock().now().nanoseconds * 1e-9
        self._ref_pub.publish(joint_state(self.vehicle.plant.state_names, self.x_d, now))

    def _on_estimate(self, msg):
        topic = TOPICS['estimate']
        try:
            t = checked_stamp(msg.header.stamp, topic)
        except ObserverError as err:
            self.count('bad_stamps')
            self.get_logger().error(f'{err}; safe command', throttle_duration_sec=1.0)
            self._publish_safe(self._estimate_clock())   # the stamp is not usable
            return
        try:
            x_hat = vector_from_joint_state(msg, self.vehicle.plant.state_names, topic)
        except (ObserverError, ValueError) as err:
            self.count('bad_estimates')
            self.get_logger().error(f'{err}; safe command', throttle_duration_sec=1.0)
            self._publish_safe(t, msg.header.stamp)
            return
        restarted = self._last_stamp is not None and \
            self._last_stamp - t > self._jump_tolerance
        if restarted:
            self._clock_restarted(t)
        steps = self._steps_late(t)
        if steps is None:
            # too late to predict from, and no sign of a live estimate: the safe command
            # (the prediction from the last trusted estimate, then the fallback), ERROR
            self.count('too_late_estimates')
            self._too_late += 1
            self._publish_safe(self._estimate_clock())
            return
        if not restarted and self._stale and np.isfinite(self.settle):
            # back after an outage: the observer restarts or catches up; until it has
            # settled (its estimates follow the model again; at most RESYNC_SETTLINGS of
            # its settling times) the prediction keeps closing the loop
            self._resyncing = True
            self.settle_check.start(self._estimate_clock() + RESYNC_SETTLINGS * self.settle)
        self._last_estimate_time = self.wall_now()
        self._last_stamp = t
        self._stale = False
        if self._resyncing:
            self.count('resync_commands')
            self._publish_safe(t, msg.header.stamp)
            if self.settle_check.settled(t, x_hat, self.safe.last_command):
                self._resyncing = False
                self._recovering = True
                self._inside_since = None
            return
        if self._recovering:
            self._recover(t, x_hat, msg.header.stamp, steps)
            return
        t_apply, x_apply, stamp = (t, x_hat, msg.header.stamp) if not steps else \
            self._at_application(t, x_hat, msg.header.stamp, steps)
        u_law, u = self._laws(x_hat, x_apply)
        # an overflowing law is the command gate's (refused, or saturated by the limits)
        problem = None if not all(map(math.isfinite, u_law)) else (
            self.x_envelope.check(t, x_hat) or self.u_envelope.check(t, u_law))
        if problem is not None:
            if self._diverging is None:
                self.get_logger().error(f'diverging: {problem}; safe command')
            self._diverging = problem
            self.count('divergence_safe_commands')
            self._publish_safe(t, msg.header.stamp)
            return
        self._diverging = None
        if self._safe_timer is not None:    # (a call per estimate otherwise)
            self._stop_safe_timer()
        if self._publish(u, t_apply, stamp):    # on time: the estimate's stamp, to the ns
            self.safe.trusted(t_apply, x_apply, u)
            self.count('commands')

    def _laws(self, x_hat, x_apply):
        """
        Return the law's u on x_hat before the limits, and the command for x_apply.

        Floats (core/control_law.py); one evaluation when x_apply is x_hat (on time).
        """
        u_law = self.law.unclipped(x_hat.tolist())
        if x_apply is not x_hat:
            return u_law, self.law(x_apply.tolist())
        return u_law, self.law.clip(u_law)

    def _on_sensor(self, name, msg):
        t = stamp_to_sec(msg.header.stamp)
        if t < self._sensor_time.get(name, t) - self._jump_tolerance:
            self._sensor_time.clear()       # a clock that started over
            self._plant_time = None
        self._sensor_time[name] = t
        if self._plant_time is None or t > self._plant_time:
            self._plant_time = t

    def _steps_late(self, t):
        """Return the steps the estimate stamped t is late (0 without compensation)."""
        if self.delay is None:
            return 0
        return self.delay.steps_late(self._plant_time, t)

    def _at_application(self, t, x_hat, stamp, steps):
        """Return (time, estimate, stamp) at which a command answering x_hat takes effect."""
        if not steps:
            return t, x_hat, stamp
        self.count('delay_compensated_commands')
        self._max_steps_late = max(self._max_steps_late, steps)
        t_apply = t + steps * self.safe.dt
        with np.errstate(all='ignore'):
            return t_apply, self.delay.predict(x_hat, t, steps), None

    def _recover(self, t, x_hat, stamp, steps=0):
        """
        Close the loop on the estimate after an outage, even beyond the envelope.

        The prediction has had its time (predict_timeout, then the observer's settling
        time): the plant may really be far away now (an unstable plant predicted open loop
        for seconds), and only the closed loop brings it back. Beyond the envelope this is
        reported as ERROR (``diverging``); once x_hat and u are strictly inside the
        envelope (:meth:`Envelope.inside`) for an observer settling time, it is armed again.
        """
        t_apply, x_apply, stamp = self._at_application(t, x_hat, stamp, steps)
        u_law, u = self._laws(x_hat, x_apply)
        # back only when strictly inside both bounds for an observer settling time: the
        # envelope's check lets values beyond the bound pass while they do not grow, and
        # a loop reopened by a divergence safe command in mid-recovery diverges for good
        inside = self.x_envelope.inside(x_hat) and self.u_envelope.inside(u_law)
        if not inside:
            self._inside_since = None
        elif self._inside_since is None:
            self._inside_since = t
        if inside and t - self._inside_since >= self.settle:
            self._recovering = False
            self._diverging = None
            self.x_envelope.check(t, x_hat)     # re-armed from here on
            self.u_envelope.check(t, u_law)
        else:
            problem = self.x_envelope.check(t, x_hat) or self.u_envelope.check(t, u_law) \
                or (f'back inside the envelope for less than {self.settle:g} s' if inside
                    else 'beyond the envelope')
            self._diverging = f'{problem} (recovering after an outage: closing the loop)'
            self.count('recovery_commands')
        if self._publish(u, t_apply, stamp):
            self.safe.trusted(t_apply, x_apply, u)
            self.count('commands')

    def _clock_restarted(self, t):
        """Estimates from a clock that started over: forget the old run's commands."""
        self.get_logger().warning(f'state/estimate: clock jumped back {self._last_stamp - t:.3f}'
                                  ' s (a restarted simulator?); safe command and limits reset')
        self.count('clock_jumps')
        self._resyncing = False
        self._recovering = False
        self.safe.reset()
        if self.delay is not None:
            self.delay.reset()
        self.x_envelope.reset()
        self.u_envelope.reset()

    def _estimate_clock(self):
        """
        Return now on the estimates' time base (their last stamp plus the time since).

        With delay compensation: the plant's time (the newest sensor stamp) plus the lead,
        when the command takes effect. A simulator slower than the wall clock (a loaded
        machine) would otherwise get safe commands stamped ahead of it, which it holds
        until their time, and which the observer's estimate would follow ahead of the
        measurements.
        """
        if self.delay is not None and self._plant_time is not None:
            return self._plant_time + self.delay.lead * self.delay.dt
        if self._last_stamp is None:
            return self._now()
        sim = self.vehicle.simulator
        rate = sim.realtime_factor if sim.mode == 'realtime' else 1.0
        return self._last_stamp + (self.wall_now() - self._last_estimate_time) * rate

    def _now(self):
        return self.get_clock().now().nanoseconds * 1e-9

    def _publish(self, u, t, stamp=None):
        """Send a command that passes the gate; else the safe command. Return True if sent."""
        problem = self.law.problem(u)
        if problem is not None:
            self.count('refused_commands')
            self._refused = f'command {problem}: safe command sent instead'
            self.get_logger().error(self._refused, throttle_duration_sec=1.0)
            self._publish_safe(t, stamp)
            return False
        self._send(u, t, stamp)
        return True

    def _send(self, u, t, stamp=None, frame_id=''):
        self.safe.sent(u)
        if self.delay is not None:
            self.delay.sent(t, u)
        self._cmd_pub.publish(joint_state(self.vehicle.plant.input_names, u, t,
                                          frame_id=frame_id, stamp=stamp))
        if self._array_pub is not None:
            self._array_pub.publish(Float64MultiArray(data=[float(v) for v in u]))

    def _publish_safe(self, t, stamp=None, frame_id=''):
        """
        Send the safe command for time t: the one place it is decided (SafeCommand).

        Predict-and-hold within ``controller.predict_timeout`` of the last trusted estimate,
        then ``controller.safe_command`` (zero or hold), clipped into the limits; sent
        without the gate (every fallback comes here: #15's refused commands too). ``frame_id``
        SAFE_COMMAND_FRAME marks one that answers no estimate (a stale one).
        """
        u, self._safe_mode = self.safe.command(t)
        if self.u_min is not None or self.u_max is not None:
            u = np.clip(u, self.u_min, self.u_max)
        self._send(u, t, stamp, frame_id)
        self.count('safe_commands')
        self.count(f'safe_commands_{self._safe_mode}')

    def _stop_safe_timer(self):
        if self._safe_timer is not None:
            self._safe_timer.cancel()
            self.destroy_timer(self._safe_timer)
            self._safe_timer = None

    def _on_watchdog(self):
        if self._last_estimate_time is None:
            return
        age = self.wall_now() - self._last_estimate_time
        if age > self.vehicle.controller.stale_timeout and not self._stale:
            c = self.vehicle.controller
            self.get_logger().error(f'estimate stale ({age:.2f} s); safe command '
                                    f'(predict {c.predict_timeout:g} s, then '
                                    f'{c.safe_command})')
            self._stale = True
            # a safe command every sample time while stale (the prediction's step)
            self._stop_safe_timer()
            self._safe_timer = self.wall_timer(
                self.vehicle.sample_time / self._time_rate(), self._on_safe_tick)
            self._on_safe_tick()

    def _time_rate(self):
        sim = self.vehicle.simulator
        return sim.realtime_factor if sim.mode == 'realtime' else 1.0

    def _on_safe_tick(self):
        if not self._stale:
            self._stop_safe_timer()
            return
        # no estimate behind it: marked, so that lock-step does not take it for one
        self._publish_safe(self._estimate_clock(), frame_id=SAFE_COMMAND_FRAME)

    def _on_set_parameters(self, params):
        problem = own_parameter_problem(params)
        if problem is not None:
            self.count('parameter_changes_refused')
            return SetParametersResult(successful=False, reason=problem)
        for p in params:
            if p.name == 'command_lead_steps' and self.delay is not None:
                self.delay.lead = int(p.value)
            if p.name == 'clock_jump_tolerance':     # checked above: finite and > 0
                self._jump_tolerance = float(p.value)
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
        self._apply(vehicle, design)
        self._publish_reference()
        self.get_logger().info(f'controller redesigned: K = {self.K.tolist()}')
        self.count('parameter_changes_applied')
        return SetParametersResult(successful=True)

    def _on_diagnostics(self):
        values = {'u': np.array2string(self.safe.last_command),
                  'max_steps_predicted': self._max_steps_late}
        if self._plant_time is not None:
            values['plant_time'] = f'{self._plant_time:.6f}'
        self._max_steps_late = 0
        too_late, self._too_late = self._too_late, 0
        self._duplicates = self.duplicate_publishers((TOPICS['command'], TOPICS['estimate']))
        refused, self._refused = self._refused, None
        if self._duplicates:
            level = DiagnosticStatus.ERROR
            message = f'more than one publisher: {", ".join(self._duplicates)}'
        elif refused:
            level, message = DiagnosticStatus.ERROR, refused
        elif too_late:
            level = DiagnosticStatus.ERROR
            message = (f'{too_late} estimates later than observer.history_length '
                       f'({self.vehicle.observer.history_length:g} s): safe command '
                       f'({self._safe_mode})')
        elif self._diverging is not None:
            level, message = DiagnosticStatus.ERROR, f'diverging: {self._diverging}'
        elif self._stale:
            level = DiagnosticStatus.ERROR
            message = (f'estimate stale: safe command ({self._safe_mode}; '
                       f'{self.resolve_topic_name(TOPICS["estimate"])})')
        elif self._last_estimate_time is None:
            level, message = DiagnosticStatus.WARN, \
                f'waiting for {self.resolve_topic_name(TOPICS["estimate"])}'
        else:
            level, message = DiagnosticStatus.OK, 'closing the loop'
        self.publish_diagnostics(level, message, values)


def main(args=None):
    """Run the compensator node."""
    return run_node(CompensatorNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
