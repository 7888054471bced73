# observer_ros.nodes.compensator: u = K (x_d - x_hat) - Kd x_d from the estimate.
"""
Compensator node: ``state/estimate`` in, the command ``control/u`` out.

The control law is the seeds' tracking form u = K (x_d - x_hat) - Kd x_d (seed 002,
Eq. 5.109; with x_d = 0 it is u = -K x_hat), clipped to the file's input limits. The
command carries the stamp of the estimate it answers. A stale or non-finite estimate, or
a malformed stamp, gives the file's safe command (zero or hold) and an error on
/diagnostics. Every command passes one gate before it is sent: finite and inside
``controller.u_min``/``u_max``, or it is not sent (the safe command instead, an ERROR on
/diagnostics). A second publisher of ``control/u`` or ``state/estimate`` is reported as
an ERROR naming the topic.

"""

from diagnostic_msgs.msg import DiagnosticStatus
import numpy as np
from rcl_interfaces.msg import SetParametersResult
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

from .common import (checked_stamp, joint_state, LATCHED_QOS, run_node, SAFE_COMMAND_FRAME,
                     STATE_PUB_QOS, STATE_QOS, TOPICS, vector_from_joint_state, VehicleNode)
from ..core.compensator import design_vehicle
from ..core.errors import ObserverError

__all__ = ['CompensatorNode', 'command_problem', 'control_law', 'main']


def control_law(K, x_hat, x_d, Kd, u_min=None, u_max=None):
    """
    Return u = K (x_d - x_hat) - Kd x_d, clipped to [u_min, u_max].

    Parameters
    ----------
    K, Kd : (m, n) ndarray
        Feedback gain and desired-state gain.
    x_hat, x_d : (n,) ndarray
        State estimate and desired state.
    u_min, u_max : (m,) ndarray, optional
        Input limits (None: no limit on that side).

    Returns
    -------
    u : (m,) ndarray

    """
    u = K @ (x_d - x_hat) - Kd @ x_d
    if u_min is not None or u_max is not None:
        u = np.clip(u, u_min, u_max)
    return u


def command_problem(u, m, u_min=None, u_max=None):
    """
    Return why a command must not be sent, or None when it may.

    A command is sent only when it has ``m`` values, all finite and inside
    ``[u_min, u_max]`` (None: no limit on that side).

    Returns
    -------
    str or None

    """
    u = np.asarray(u, dtype=float)
    if u.shape != (m,):
        return f'{u.size} values for {m} inputs'
    if not np.isfinite(u).all():
        return f'not finite: {u.tolist()}'
    low = -np.inf if u_min is None else np.asarray(u_min, dtype=float)
    high = np.inf if u_max is None else np.asarray(u_max, dtype=float)
    if np.any(u < low) or np.any(u > high):
        return f'{u.tolist()} outside the limits [{u_min}, {u_max}]'
    return None


class CompensatorNode(VehicleNode):
    """Close the loop on the estimate."""

    def __init__(self):
        super().__init__('compensator', own_parameters=(
            ('publish_array', False, 'also publish control/u_array, a Float64MultiArray '
             '(ros2_control)'),
            ('diagnostics_period', 1.0, 's (wall) between /diagnostics reports'),
        ))
        self._apply(self.vehicle, design_vehicle(self.vehicle))
        self._last_u = np.zeros(self.vehicle.plant.m)
        self._last_estimate_time = None      # node clock when the last good x_hat came
        self._stale = False
        self._refused = None                 # why the last command was not sent
        self._duplicates = []                # other publishers of our topics
        self._cmd_pub = self.create_publisher(JointState, TOPICS['command'], STATE_PUB_QOS)
        self._array_pub = None
        if self.param('publish_array'):
            self._array_pub = self.create_publisher(
                Float64MultiArray, TOPICS['command_array'], STATE_QOS)
        self._ref_pub = self.create_publisher(JointState, TOPICS['reference'], LATCHED_QOS)
        self._publish_reference()
        self._sub = self.create_subscription(
            JointState, TOPICS['estimate'], self._on_estimate, STATE_QOS)
        self.add_on_set_parameters_callback(self._on_set_parameters)
        period = min(self.vehicle.controller.stale_timeout / 2.0, 0.1)
        self._watchdog = self.wall_timer(period, self._on_watchdog)
        self._diag_timer = self.wall_timer(self.param('diagnostics_period'),
                                           self._on_diagnostics)

    def _apply(self, vehicle, design):
        n, m = vehicle.plant.n, vehicle.plant.m
        c = vehicle.controller
        self.vehicle = vehicle
        self.K = np.asarray(design.K, dtype=float).reshape(m, n)
        self.x_d = np.zeros(n) if c.reference is None else np.asarray(c.reference, float)
        self.Kd = np.zeros((m, n)) if c.Kd is None else np.asarray(c.Kd, float).reshape(m, n)
        self.u_min, self.u_max = c.u_min, c.u_max
        self.design = design

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
            self._publish_safe(self._now())     # the stamp is not usable: the node's time
            return
        try:
            x_hat = vector_from_joint_state(msg, self.vehicle.plant.state_names, topic)
        except (ObserverError, ValueError) as err:
            self.count('bad_estimates')
            self.get_logger().error(f'{err}; safe command', throttle_duration_sec=1.0)
            self._publish_safe(t, msg.header.stamp)
            return
        with np.errstate(all='ignore'):     # an overflow gives inf/NaN: refused below
            u = control_law(self.K, x_hat, self.x_d, self.Kd, self.u_min, self.u_max)
        self._last_estimate_time = self.wall_now()
        self._stale = False
        if self._publish(u, t, msg.header.stamp):   # the estimate's stamp, to the ns
            self.count('commands')

    def _now(self):
        return self.get_clock().now().nanoseconds * 1e-9

    def _publish(self, u, t, stamp=None):
        """Send a command that passes the gate; else the safe command. Return True if sent."""
        problem = command_problem(u, self.vehicle.plant.m, self.u_min, self.u_max)
        if problem is not None:
            self.count('refused_commands')
            self._refused = f'command {problem}: safe command sent instead'
            self.get_logger().error(self._refused, throttle_duration_sec=1.0)
            self._publish_safe(t, stamp)
            return False
        self._send(u, t, stamp)
        return True

    def _send(self, u, t, stamp=None, frame_id=''):
        self._last_u = u
        self._cmd_pub.publish(joint_state(self.vehicle.plant.input_names, u, t,
                                          frame_id=frame_id, stamp=stamp))
        if self._array_pub is not None:
            self._array_pub.publish(Float64MultiArray(data=[float(v) for v in u]))

    def _publish_safe(self, t, stamp=None, frame_id=''):
        """
        Send the safe command: the one entry point of every fallback.

        ``hold`` repeats the last command sent (it passed the gate), ``zero`` sends zero,
        clipped into the limits (a vehicle whose limits exclude zero). ``frame_id``
        SAFE_COMMAND_FRAME marks one that answers no estimate (a stale one).
        """
        c = self.vehicle.controller
        u = self._last_u if c.safe_command == 'hold' else np.zeros(self.vehicle.plant.m)
        if self.u_min is not None or self.u_max is not None:
            u = np.clip(u, self.u_min, self.u_max)
        self._send(u, t, stamp, frame_id)
        self.count('safe_commands')

    def _on_watchdog(self):
        if self._last_estimate_time is None:
            return
        age = self.wall_now() - self._last_estimate_time
        if age > self.vehicle.controller.stale_timeout:
            if not self._stale:
                self.get_logger().error(f'estimate stale ({age:.2f} s); safe command '
                                        f'({self.vehicle.controller.safe_command})')
            self._stale = True
            # no estimate behind it: marked, so that lock-step does not take it for one
            self._publish_safe(self._now(), frame_id=SAFE_COMMAND_FRAME)

    def _on_set_parameters(self, params):
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
        except (ObserverError, ValueError) as err:
            self.count('parameter_changes_refused')
            return SetParametersResult(successful=False, reason=str(err))
        self._apply(vehicle, design)
        self._publish_reference()
        self.get_logger().info(f'controller redesigned: K = {self.K.tolist()}')
        self.count('parameter_changes_applied')
        return SetParametersResult(successful=True)

    def _on_diagnostics(self):
        self._duplicates = self.duplicate_publishers((TOPICS['command'], TOPICS['estimate']))
        refused, self._refused = self._refused, None
        if self._duplicates:
            level = DiagnosticStatus.ERROR
            message = f'more than one publisher: {", ".join(self._duplicates)}'
        elif refused:
            level, message = DiagnosticStatus.ERROR, refused
        elif self._stale:
            level, message = DiagnosticStatus.ERROR, \
                f'estimate stale: safe command ({self.resolve_topic_name(TOPICS["estimate"])})'
        elif self._last_estimate_time is None:
            level, message = DiagnosticStatus.WARN, \
                f'waiting for {self.resolve_topic_name(TOPICS["estimate"])}'
        else:
            level, message = DiagnosticStatus.OK, 'closing the loop'
        self.publish_diagnostics(level, message, {'u': np.array2string(self._last_u)})


def main(args=None):
    """Run the compensator node."""
    return run_node(CompensatorNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
