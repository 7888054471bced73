# observer_ros.nodes.plant_simulator: the vehicle's model, integrated exactly, as sensors.
"""
Plant simulator node: the command ``control/u`` in; sensors, ``state/true`` and /clock out.

The model is integrated exactly with a zero-order hold on u (one matrix exponential at
start). Measurement noise comes from ``simulator.seed``. Two modes:

- ``lockstep``: step k publishes its sensor messages one at a time and waits for the
  command that answers each (stamped t_k) before going on; step k+1 starts only when
  step k is answered, so a closed-loop run is reproducible bit for bit, whatever the
  size of the vehicle. A command that does not come within ``simulator.command_timeout``
  (wall time) is reported on /diagnostics and in the log, and the simulator keeps
  waiting (re-sending the measurement with back-off): it never advances without the
  answer, which would make the run depend on the machine's speed (a 20-state observer
  designs its gains for several seconds at its first measurements). With
  ``wait_for_recorder`` it starts once the recorder is ready, holds step 0 until the bag
  has its estimate and command, and steps at most ``RECORDER_WINDOW`` steps past the
  newest true state the recorder wrote (``recorder/progress``; ``recorder_waits`` counts
  the holds), fewer than the publishers keep for a reader: a recorder whose process
  stalls loses nothing. A recorder that is gone (no ``recorder/progress`` publisher) is
  not waited for.
- ``realtime``: a wall-clock timer at ``rate_hz * realtime_factor``. A command's stamp is
  the time it takes effect: one stamped at the current step or before applies from this
  step, one stamped ahead (a compensator that predicted over its latency) waits for its
  step, one older than the command in force is ignored (``out_of_order_commands``). A
  command that arrives after its step is applied from the step it arrives at and counted
  (``commands_applied_late``; /diagnostics gives ``applied_late_ms_max``): there the
  plant held the previous command longer than its stamp says, which the observer cannot
  know. Steps without a fresh command are counted (``late_commands``). The run starts
  when a command answers step 0 (sent again until one does). A plant that can be held
  open loop runs open loop after ``READY_WAIT`` x ``simulator.command_timeout`` without
  one; an unstable one (the cart) waits for it, with a WARN naming the command topic
  every such period (``open_loop_start_refused``): its open loop would fall before a
  late compensator's first command.

Simulated time starts at ``start_time`` (1.0 s: ROS reads a zero stamp as unset). The end
of the run (``simulator.duration``) is published, latched, on ``simulator/run_complete``
(``std_msgs/Bool``: false while the run goes on, true once it is over): the compensator
then stops commanding a plant that no longer runs.

One time base per ROS graph: a simulator with ``simulator.publish_clock: false`` (a second
vehicle, the first one owns /clock) follows /clock once one is published
(:mod:`.clock_follower`). It waits for the first /clock (at most ``READY_WAIT`` x
``simulator.command_timeout``, then runs on its own time), starts its step 0 there, and
takes a step only when /clock has reached it, so its stamps are /clock's time (behind it by
at most the owner's period, a step a tick). Realtime and more than ``CLOCK_RESYNC`` behind,
it integrates the steps in between without sending their measurements
(``catch_up_steps``). When /clock goes back (the owner restarted) or runs more than
``CLOCK_CATCH_UP`` ahead, it starts again from /clock's time: its stamps jump as the
graph's clock did, which its observer and compensator handle as a clock jump
(``clock_resyncs``, logged). While /clock is silent (the owner stopped) it waits, as
simulated time does.

"""

import json
import time

from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticStatus
import numpy as np
from rcl_interfaces.msg import SetParametersResult
from rclpy.duration import Duration
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState
from std_msgs.msg import Bool, String

from .checks import own_parameter_problem
from .clock_follower import CLOCK_RESYNC, ClockFollower
from .common import (joint_state, LATCHED_QOS, MESSAGE_CLASSES, SAFE_COMMAND_FRAME,
                     SENSOR_QOS, stamp_to_sec, STATE_PUB_QOS, STATE_QOS, to_stamp, TOPICS,
                     vector_from_joint_state, VehicleNode)
from .runner import run_node
from ..core.clock_jump import far_back_text
from ..core.model import zoh_matrices
from ..core.simulate import process_noise_factor
from ..core.standby import unstable_plant
from ..sensors import fill_measurement

__all__ = ['PlantSimulatorNode', 'main']

# s: a realtime command stamped further ahead of the simulated time is not for this run
FUTURE_COMMAND = 2.0
# realtime: how many command_timeouts to wait for a matched command publisher at start
# (and a /clock follower for the first /clock)
READY_WAIT = 10.0
# s: how long the end of the run may take to reach its readers before the process exits
RUN_COMPLETE_ACK_WAIT = 1.0
# lockstep with wait_for_recorder: steps at most this far past the newest true state the
# recorder wrote (recorder/progress); below the publishers' history (keep last 10), so a
# recorder that stalls loses no message of the run
RECORDER_WINDOW = 5


class PlantSimulatorNode(VehicleNode):
    """Simulate the vehicle and publish what its sensors would measure."""

    def __init__(self):
        super().__init__('plant_simulator', own_parameters=(
            'start_time', 'wait_for_subscribers', 'wait_for_recorder', 'exit_when_done',
            'diagnostics_period'))
        v = self.vehicle
        plant = v.plant
        self.dt = v.sample_time
        if plant.is_discrete:
            self.Ad, self.Bd = plant.A, plant.B
        else:
            self.Ad, self.Bd = zoh_matrices(plant.A, plant.B, self.dt)
        self.C, self.D = plant.C, plant.D
        # the exact covariance of one step, as core.simulate and the Kalman design read
        # simulator.process_noise_std (an intensity for a continuous model)
        self._w_factor = None if v.simulator.process_noise_std is None else \
            process_noise_factor(plant, v.simulator.process_noise_std, self.dt)
        self.x = np.array(v.simulator.initial_state, dtype=float)
        self.u = np.zeros(plant.m)
        self.k = 0
        self.t0 = float(self.param('start_time'))
        # simulator.duration 0: no end, the run goes on until the node is stopped
        self.steps = int(round(v.simulator.duration / self.dt)) or None
        self.rng = np.random.default_rng(v.simulator.seed)
        self.noise = v.simulator.noise
        self._lockstep = v.simulator.mode == 'lockstep'
        self._sensor_pubs = [
            (s, self.create_publisher(MESSAGE_CLASSES[s.msg_type], s.topic, SENSOR_QOS),
             plant.output_rows(s.outputs)) for s in v.sensors]
        self._state_pub = self.create_publisher(JointState, TOPICS['true_state'], STATE_PUB_QOS)
        # latched: false while the run goes on (a restarted simulator replaces an old true),
        # true once it is complete (the compensator then stands by instead of commanding)
        self._complete_pub = self.create_publisher(Bool, TOPICS['run_complete'], LATCHED_QOS)
        self._complete_pub.publish(Bool(data=False))
        self._clock_pub = None
        if v.simulator.publish_clock:
            self._clock_pub = self.create_publisher(Clock, '/clock', 10)
        # following another vehicle's /clock (one time base per ROS graph)
        self._follower = None
        self._clock_wait = False            # lockstep: the next step waits for /clock
        if not v.simulator.publish_clock:
            self._follower = ClockFollower(self.dt, READY_WAIT * v.simulator.command_timeout,
                                           count=self.count)
            self._clock_sub = self.create_subscription(Clock, '/clock', self._on_clock,
                                                       SENSOR_QOS)
        self._cmd_sub = self.watched_subscription(
            JointState, TOPICS['command'], self._on_command, STATE_QOS)
        self._recorder_ready = False
        self._recorder_heard = None     # (topics recorded, topics in the bag)
        self._held_for_recorder = False     # lockstep: step 0 answered, not yet in the bag
        self._wait_for_recorder = bool(self.param('wait_for_recorder'))     # read-only
        if self._wait_for_recorder:
            self._ready_sub = self.watched_subscription(
                Bool, 'recorder/ready', self._on_recorder_ready, LATCHED_QOS, shed=False)
            self._heard_sub = self.watched_subscription(
                String, 'recorder/heard', self._on_recorder_heard, LATCHED_QOS, shed=False)
            self._progress_sub = self.watched_subscription(
                Time, 'recorder/progress', self._on_recorder_progress, STATE_QOS, shed=False)
        self._recorded = None           # lockstep: the newest true state the recorder wrote
        self._step0_t = None            # lockstep: the time of step 0
        self._held_since = None         # lockstep: wall time it waits for the recorder since
        self._recorder_gone = False     # lockstep: no recorder/progress publisher left
        # lockstep bookkeeping
        self._due = []                  # sensors still to publish at this step
        self._answers = 0               # commands stamped t_k received so far
        self._published = 0             # sensor messages published at this step
        self._waiting_since = None
        self._started = False
        self._done = False
        self._latest_cmd_stamp = None       # stamp of the command in force
        self._ahead = []                    # realtime: (stamp, u) waiting for their step
        self._applied_late = []             # realtime: how late (s) late commands applied
        self._ready_since = None            # realtime: wall time of the first tick
        self._handshake_sent = None         # realtime: when step 0 last went out
        self._step_wall = None              # realtime: wall time the step's gyro went out
        self._unanswered = None             # realtime: (t, wall) of the step before, if late
        self._loop_us = []                  # realtime: measurement -> its command, us
        self._last_sent = None
        self._resends_this_wait = 0
        self._timeout_reported = False
        self._resend_period = 0.2           # s of wall time before a measurement is re-sent
        self.count('command_timeouts', 0)
        self.count('recorder_waits', 0)
        if self._lockstep:
            self._start_timer = self.wall_timer(0.01, self._try_start)
            self._watchdog = self.wall_timer(0.05, self._on_watchdog)
        else:
            period = self.dt / v.simulator.realtime_factor
            self._step_timer = self.wall_timer(period, self._realtime_step)
            self.count('late_commands', 0)
            # said now, before any step: a process's first log line costs tens to hundreds
            # of ms (234 ms at load 27), which at the first step made the timer's next
            # ticks come at once, each a late command (benchmarks P2)
            self.get_logger().info(f'{v.name}: realtime at {1.0 / period:g} Hz; step 0 '
                                   'goes out until a command answers it')
        self._diag_timer = self.wall_timer(self.param('diagnostics_period'),
                                           self._on_diagnostics)
        self.add_on_set_parameters_callback(self._on_set_parameters)

    def _on_set_parameters(self, params):
        problem = own_parameter_problem(params)
        return SetParametersResult(successful=problem is None, reason=problem or '')

    def _on_recorder_ready(self, msg):
        self._recorder_ready = bool(msg.data)

    def _on_recorder_heard(self, msg):
        try:
            said = json.loads(msg.data)
            self._recorder_heard = (set(said['recording']), set(said['heard']))
        except (ValueError, KeyError, TypeError) as err:
            self.get_logger().warning(f'recorder/heard: {err}; not used',
                                      throttle_duration_sec=1.0)
            return
        if self._held_for_recorder and self._step_in_bag():
            self._step_answered()

    def _on_recorder_progress(self, msg):
        t = stamp_to_sec(msg)
        if self._recorded is None or t > self._recorded:
            self._recorded = t
        if self._held_since is not None and not self._recorder_behind():
            self._publish_next()

    def _recorder_behind(self):
        """
        Tell whether the next step would be more than RECORDER_WINDOW past the bag (lockstep).

        The bag's newest true state is what recorder/progress said last (before any, the
        step before step 0). Without wait_for_recorder, or once the recorder is gone, never.
        """
        if not self._lockstep or self._step0_t is None or self._recorder_gone or \
                not self._wait_for_recorder:
            return False
        newest = self._step0_t - self.dt if self._recorded is None else self._recorded
        if self.t + self.dt - newest <= (RECORDER_WINDOW + 0.25) * self.dt:
            self._held_since = None
            return False
        if self._held_since is None:
            self._held_since = time.monotonic()
            self.count('recorder_waits')
        return True

    def _step_in_bag(self):
        """
        Tell whether the recorder has this step's estimate and command (lockstep, step 0).

        Its readers matched the observer's and the compensator's writers, but those writers
        may not have matched its readers yet: the first estimates would go unrecorded. Until
        the bag has a message of each, step 0 is sent again (answered again) and the run
        waits; without wait_for_recorder, or after step 0, nothing is held.
        """
        if self.k != 0 or not self._wait_for_recorder:
            return True
        if self._recorder_heard is None:
            return False
        recording, heard = self._recorder_heard
        loop = {self.resolve_topic_name(TOPICS[key]) for key in ('estimate', 'command')}
        return loop & recording <= heard

    # -- following /clock ---------------------------------------------------------------------
    def _on_clock(self, msg):
        if not self._follower.heard(msg.clock.sec, msg.clock.nanosec):
            follower = self._follower
            self.get_logger().warning(
                far_back_text('/clock', stamp_to_sec(msg.clock),
                              follower.newest, follower.jumps.agreement),
                throttle_duration_sec=1.0)
            return
        if self._clock_wait and self._steps_due() > 0:
            self._clock_wait = False        # lockstep: /clock reached the next step
            self._publish_next()

    def _clock_ready(self, waited):
        """Tell whether step 0 may go out: own time, or on /clock's time once one came."""
        follower = self._follower
        if follower is None or follower.synced:
            return True
        t0 = follower.start(self.k, waited)
        if t0 is False:
            return False
        if t0 is None:
            self.get_logger().warning(f'no /clock after {waited:.1f} s; running on own time '
                                      '(follows /clock once one is published)')
        else:
            self.t0 = t0
            self.get_logger().info(f'following /clock: step {self.k} at t={self.t:.3f} s')
        return True

    def _steps_due(self):
        """Return how many steps /clock has reached since the current one (1 without one)."""
        if self._follower is None:
            return 1
        due, t0 = self._follower.steps_due(self.t, self.k)
        if t0 is not None:
            self.get_logger().warning(
                f'/clock at {self._follower.clock:.3f} s, this vehicle at {self.t:.3f} s: its '
                'time restarts from /clock (a clock jump for its observer and compensator)')
            self.t0 = t0                    # the next step at /clock's time
            self._latest_cmd_stamp = None   # the old run's commands forgotten
            self._ahead = []
            self._step_wall = self._unanswered = None
            self.count('clock_resyncs')
        return due

    # -- time and measurement ---------------------------------------------------------------
    @property
    def t(self):
        """Return the simulated time of the current step."""
        return self.t0 + self.k * self.dt

    def _publish_clock(self):
        if self._clock_pub is not None:
            self._clock_pub.publish(Clock(clock=to_stamp(self.t)))

    def _measure(self, sensor, rows):
        y = self.C[rows] @ self.x + self.D[rows] @ self.u
        if self.noise:
            y = y + self.rng.standard_normal(len(rows)) * sensor.noise_std
        msg = MESSAGE_CLASSES[sensor.msg_type]()
        if hasattr(msg, 'header'):
            msg.header.stamp = to_stamp(self.t)
            msg.header.frame_id = sensor.frame_id
        fill_measurement(msg, sensor, y)
        return msg

    def _sensors_due(self):
        return [(s, pub, rows) for s, pub, rows in self._sensor_pubs
                if self.k % s.rate_divider == 0]

    def _begin_step(self):
        """Publish the clock and the true state of step k; list the sensors due."""
        self._publish_step_state()
        self._due = self._sensors_due()
        self._answers = 0
        self._published = 0

    def _publish_step_state(self):
        """Publish the clock and the true state of step k."""
        self._publish_clock()
        self._state_pub.publish(joint_state(self.vehicle.plant.state_names, self.x, self.t,
                                            self.vehicle.base_frame))

    def _advance(self):
        """Integrate from t_k to t_k+1 holding u."""
        self.x = self.Ad @ self.x + self.Bd @ self.u
        if self._w_factor is not None:
            self.x = self.x + self._w_factor @ self.rng.standard_normal(self.x.size)
        self.k += 1

    # -- lockstep ---------------------------------------------------------------------------
    def _try_start(self):
        need = int(self.param('wait_for_subscribers'))
        # matched readers (not just graph entries): a message sent now reaches them
        if any(pub.get_subscription_count() < need for _, pub, _ in self._sensor_pubs):
            return
        if self._cmd_sub.get_publisher_count() < 1:
            return
        if self._wait_for_recorder and (
                not self._recorder_ready or self._state_pub.get_subscription_count() < 1):
            return
        # the observer and the compensator are up: someone publishes and someone reads the
        # estimate, and someone publishes commands
        if self.count_publishers(TOPICS['command']) < 1 or \
                self.count_publishers(TOPICS['estimate']) < 1 or \
                self.count_subscribers(TOPICS['estimate']) < 1:
            return
        if self._ready_since is None:
            self._ready_since = time.monotonic()
        if not self._clock_ready(time.monotonic() - self._ready_since):
            return
        self._start_timer.cancel()
        self._started = True
        self._step0_t = self.t
        self.get_logger().info(f'{self.vehicle.name}: lockstep run of '
                               f'{self.steps or "unlimited"} steps of {self.dt} s')
        self._begin_step()
        self._publish_next()

    def _publish_next(self):
        """Publish the next due sensor of this step, or advance when all are answered."""
        while True:
            if self._due:
                sensor, pub, rows = self._due.pop(0)
                msg = self._measure(sensor, rows)
                pub.publish(msg)
                self._last_sent = (pub, msg)
                self._resends_this_wait = 0
                self._timeout_reported = False
                self._published += 1
                self._waiting_since = time.monotonic()
                return
            # every sensor of step k answered (or none due): next step
            if self.steps is not None and self.k >= self.steps:
                self._finish()
                return
            if self._recorder_behind():
                return      # _on_recorder_progress (or the watchdog) goes on
            if self._steps_due() == 0:
                self._clock_wait = True     # /clock has not reached it: _on_clock goes on
                return
            self._advance()
            self._begin_step()
            if not self._due:
                self._state_pub.publish(
                    joint_state(self.vehicle.plant.state_names, self.x, self.t,
                                self.vehicle.base_frame))

    def _on_command(self, msg):
        try:
            u = vector_from_joint_state(msg, self.vehicle.plant.input_names, TOPICS['command'])
            stamp = stamp_to_sec(msg.header.stamp)
        except (ValueError, Exception) as err:   # noqa: BLE001 - never crash on a message
            self.count('bad_commands')
            self.get_logger().warning(f'{err}', throttle_duration_sec=1.0)
            return
        if not self._lockstep:
            if stamp > self.t + FUTURE_COMMAND:
                # not an answer to this run (a compensator still on the time of a run
                # before a restart): never applied
                self.count('future_commands')
                return
            self._realtime_command(u, stamp)
            return
        if not self._started or self._done:
            return
        if abs(stamp - self.t) > 0.25 * self.dt:
            self.count('stale_commands')     # an answer to an older step: ignored
            return
        if msg.header.frame_id == SAFE_COMMAND_FRAME and \
                self.count_publishers(TOPICS['estimate']) > 0:
            # the compensator's safe command while the observer is alive (busy, e.g. a
            # 20-state observer designing its gains): not the answer, keep waiting
            self.count('safe_commands_waited_out')
            return
        self.u = u
        self._answers += 1
        if self._answers >= self._published:
            if not self._step_in_bag():
                # the watchdog sends the step again: its estimate and command come again
                self._held_for_recorder = True
                return
            self._step_answered()

    def _step_answered(self):
        """Lockstep: the step is answered (and, at step 0, in the bag): the next one."""
        self._held_for_recorder = False
        self._waiting_since = None
        self._publish_next()

    def _on_watchdog(self):
        if self._held_since is not None and not self._done:
            self._watch_recorder()
        if self._waiting_since is None or self._done:
            return
        waited = time.monotonic() - self._waiting_since
        if waited > self._resend_period * 2 ** self._resends_this_wait and self._last_sent:
            # DDS matching can lag the graph at start-up: send the same message again
            # (same stamp; the observer answers a repeat with its current estimate), with
            # back-off so that a busy observer is not flooded
            pub, msg = self._last_sent
            pub.publish(msg)
            self._resends_this_wait += 1
            self.count('resent_measurements')
        if waited > self.vehicle.simulator.command_timeout and not self._timeout_reported:
            self._timeout_reported = True
            if self._held_for_recorder:
                self.get_logger().warning(
                    f'step 0 answered, but the recorder has not recorded its estimate and '
                    f'command after {waited:.1f} s; sent again until it has')
                return
            self.count('command_timeouts')
            self.get_logger().error(
                f'no command for step {self.k} (t={self.t:.3f}) after {waited:.1f} s; '
                'still waiting (lockstep never advances without the answer)')

    def _watch_recorder(self):
        """Lockstep, held for the recorder: say so once; go on when it is gone."""
        if self.count_publishers('recorder/progress') < 1:
            self._recorder_gone = True
            self._held_since = None
            self.get_logger().warning('recorder/progress has no publisher (the recorder '
                                      'stopped?): stepping on without waiting for it')
            self._publish_next()
            return
        waited = time.monotonic() - self._held_since
        if waited > self.vehicle.simulator.command_timeout and not self._timeout_reported:
            self._timeout_reported = True
            self.get_logger().warning(
                f'step {self.k} (t={self.t:.3f}) answered; waiting {waited:.1f} s for the '
                f'recorder, whose bag ends at t={self._recorded}')

    def _finish(self):
        self._done = True
        self._waiting_since = None
        if not self._lockstep:
            self._step_timer.cancel()
        self.get_logger().info(f'run complete at t={self.t:.3f} s; x = {self.x.tolist()}')
        self.publish_diagnostics(DiagnosticStatus.OK, 'run complete')
        self._complete_pub.publish(Bool(data=True))
        # received before the process ends (exit_when_done): a latched sample goes with it
        self._complete_pub.wait_for_all_acked(Duration(seconds=RUN_COMPLETE_ACK_WAIT))
        if self.param('exit_when_done'):
            self.exit_code = 0      # run_nodes stops spinning: a clean exit, no exception

    # -- realtime ---------------------------------------------------------------------------
    def _realtime_command(self, u, stamp):
        """Apply a command from its stamp: now, at its step ahead, or never (out of order)."""
        tol = 0.25 * self.dt
        if stamp < self._newest_command() - tol:
            # older than a command already received: applying it would undo a newer one
            self.count('out_of_order_commands')
            return
        if self._step_wall is not None and stamp >= self.t - tol:
            # the answer to this step's measurements (at this step, or predicted ahead)
            self._loop_us.append((time.monotonic() - self._step_wall) * 1e6)
            self._step_wall = None
        elif self._unanswered is not None and abs(stamp - self._unanswered[0]) <= tol:
            # the answer to the step before, after the next step went out (a late command):
            # its round trip counts too, or the reported maximum would leave the late out
            self._loop_us.append((time.monotonic() - self._unanswered[1]) * 1e6)
            self._unanswered = None
        if stamp > self.t + tol:
            self._ahead.append((stamp, u))
            return
        if stamp < self.t - tol:
            self.count('commands_applied_late')
            self._applied_late.append(self.t - stamp)
        self.u = u
        self._latest_cmd_stamp = stamp

    def _newest_command(self):
        """Return the newest stamp received: in force or waiting (-inf before any)."""
        if self._ahead:
            return self._ahead[-1][0]
        return -np.inf if self._latest_cmd_stamp is None else self._latest_cmd_stamp

    def _apply_due(self):
        """Put in force the newest command waiting for this step (stamped at it or before)."""
        due = [(s, u) for s, u in self._ahead if s <= self.t + 0.25 * self.dt]
        if due:
            self._latest_cmd_stamp, self.u = due[-1]
            self._ahead = self._ahead[len(due):]

    def _realtime_step(self):
        if self._done:
            return
        if not self._started:
            if not self._realtime_ready():
                return
            self._started = True    # step 0 went out (and was answered): step on
            if self._follower is not None and self._follower.t0_at(self.k) is not None:
                # a follower: the plant waited at step 0 while /clock went on
                self.t0 = self._follower.t0_at(self.k)
            self.get_logger().info(f'{self.vehicle.name}: realtime run of '
                                   f'{self.steps or "unlimited"} '
                                   f'steps of {self.dt} s')
        if self._started:
            due = self._steps_due()
            if due == 0:
                return                      # /clock has not reached the next step
            if self.steps is not None:
                due = min(due, self.steps - self.k)
            # one step a tick; more than CLOCK_RESYNC behind /clock (this simulator is
            # slower than the clock's owner), the steps but one are integrated, not measured
            for _ in range(due - 1 if due * self.dt > CLOCK_RESYNC else 0):
                self._advance()
                self._apply_due()
                self.count('catch_up_steps')
            # the command answering the previous step should be here by now; before the
            # first command the loop is not closed yet (peers starting, DDS matching):
            # those steps are open_loop_steps, not late commands (benchmarks P2)
            if self._latest_cmd_stamp is None:
                self.count('open_loop_steps')
            elif self._newest_command() < self.t - 0.25 * self.dt:
                self.count('late_commands')
                if self._step_wall is not None and time.monotonic() - self._step_wall < \
                        0.75 * self.dt / self.vehicle.simulator.realtime_factor:
                    # this step came less than 3/4 of a period after the last one (the
                    # timer keeps its schedule after a late tick): its command had less time
                    self.count('late_commands_short_step')
            # a step unanswered so far: its answer, when it comes, is timed from its step
            self._unanswered = None if self._step_wall is None else (self.t, self._step_wall)
            self._advance()
            self._apply_due()
        self._started = True
        # the measurements first: they start the loop (the clock and the true state are for
        # the recorder and the evaluation, and would add two publishes to every loop)
        due = self._sensors_due()
        for sensor, pub, rows in due:
            pub.publish(self._measure(sensor, rows))
        self._step_wall = time.monotonic() if due else None
        self._publish_step_state()
        self.count('steps')
        if self.steps is not None and self.k >= self.steps:
            self._finish()

    def _realtime_ready(self):
        """
        Realtime: step on once a command has answered step 0 (commands reach the plant).

        Step 0's measurements go out every resend period once the command publisher and
        ``wait_for_subscribers`` sensor readers are matched, until a command stamped t_0
        comes back (or READY_WAIT x command_timeout passed: then open loop, unless the
        plant is unstable: then a WARN every such period, and it waits). A simulator
        restarted under a running observer and compensator must not step before their
        commands reach it (a matched reader is not enough: the compensator's writer may not
        have matched it yet): the observer would correct with commands the plant never
        gets, and the cart's unstable compensator (D(s) has a pole at +95.75) then
        diverges on its own, x_hat and u x2.6 every 10 ms.
        """
        now = time.monotonic()
        if self._ready_since is None:
            self._ready_since = now
        if not self._clock_ready(now - self._ready_since):
            return False
        # the answer to step 0: stamped at t_0, or ahead of it (a latency predicted over)
        if self._newest_command() >= self.t - 0.25 * self.dt:
            return True
        waited = now - self._ready_since
        wait = READY_WAIT * self.vehicle.simulator.command_timeout
        if waited > wait and not unstable_plant(self.vehicle.plant):
            self.get_logger().warning(f'no command answered step 0 after {waited:.1f} s; '
                                      'running open loop')
            return True
        if waited > wait * (1 + self._counters.get('open_loop_start_refused', 0)):
            self.count('open_loop_start_refused')
            self.get_logger().warning(
                f'no command answered step 0 after {waited:.1f} s: waiting for '
                f'{self.resolve_topic_name(TOPICS["command"])} (an unstable plant does not '
                'run open loop)')
        need = int(self.param('wait_for_subscribers'))
        matched = self._cmd_sub.get_publisher_count() >= 1 and all(
            pub.get_subscription_count() >= need for _, pub, _ in self._sensor_pubs)
        if matched and (self._handshake_sent is None or
                        now - self._handshake_sent >= self._resend_period):
            for sensor, pub, rows in self._sensors_due():
                pub.publish(self._measure(sensor, rows))
            self._publish_step_state()
            self._handshake_sent = self._step_wall = now
            self.count('start_measurements')
        return False

    def _on_diagnostics(self):
        level = DiagnosticStatus.OK
        message = 'running' if self._started or not self._lockstep else 'waiting for peers'
        if self._counters.get('command_timeouts'):
            level, message = DiagnosticStatus.WARN, 'commands came late (waited for)'
        if not self._started and self._counters.get('open_loop_start_refused'):
            level = DiagnosticStatus.WARN
            message = (f'waiting for {self.resolve_topic_name(TOPICS["command"])}: no command '
                       'answered step 0 (an unstable plant does not run open loop)')
        values = {'t': f'{self.t:.6f}', 'step': self.k}
        if self._loop_us:
            # realtime: the loop measurement -> command since the last report (benchmarks P2)
            loop = np.array(self._loop_us)
            self._loop_us = []
            values.update(loop_samples=loop.size,
                          loop_us_p50=f'{np.percentile(loop, 50):.1f}',
                          loop_us_p99=f'{np.percentile(loop, 99):.1f}',
                          loop_us_max=f'{loop.max():.1f}')
        if self._applied_late:
            values['applied_late_ms_max'] = f'{1e3 * max(self._applied_late):.1f}'
            self._applied_late = []
        self.publish_diagnostics(level, message, values)


def main(args=None):
    """Run the plant simulator node."""
    return run_node(PlantSimulatorNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
