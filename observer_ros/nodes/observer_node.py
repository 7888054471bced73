# observer_ros.nodes.observer_node: the state estimator as a ROS 2 node.
"""
Observer node: sensor topics and the command u in, the state estimate x_hat out.

Subscribes to every sensor of the vehicle file (sensor-data QoS) and to ``control/u``;
publishes ``state/estimate`` (JointState named by the states) and ``observer/residual``
(named by the outputs); a Kalman observer also ``state/covariance``, the covariance P of
each estimate that answers a measurement (:func:`covariance_names`). Each measurement
corrects with its own rows of C at its own stamp; a message stamped before the estimate
but inside ``observer.history_length`` is used at its stamp (the core's
:class:`~observer_ros.core.estimators.History` rewinds), so sensors with different
latencies all count. Per sensor, /diagnostics carries the innovation health
(``<node>/innovation/<sensor>``, :mod:`observer_ros.core.innovation`). With
``observer.publish_rate_hz`` (free running) the estimate predicted to now is also
published at that rate.

What each stamp means is :class:`~observer_ros.core.estimators.admission.Admission`'s
decision, the same the bag replay asks for: a malformed stamp is refused
(``bad_stamps``); a duplicate, a stamp older than the history or far in the future of the
clock is skipped and counted; a measurement stamped more than ``clock_jump_tolerance``
before the newest is skipped (``far_back_stamps``) unless ``clock_jump_agreement`` of them
come in a row, a clock jump (``clock_jumps``): the estimator restarts. A command never
resets the estimator. A reset is always logged and counted (``estimator_resets``). A
second publisher of ``state/estimate`` or ``control/u`` is reported as an ERROR naming the
topic.

"""

import math
import time

from diagnostic_msgs.msg import DiagnosticStatus
import numpy as np
from rcl_interfaces.msg import SetParametersResult
from rclpy.event_handler import PublisherEventCallbacks, UnsupportedEventTypeError
from sensor_msgs.msg import JointState

from .checks import changed_pole_problem, own_parameter_problem
from .common import about, MESSAGE_CLASSES, SENSOR_SUB_QOS, STATE_PUB_QOS, STATE_QOS, TOPICS
from .managed import ManagedVehicleNode
from .observer_health import ObserverHealth
from .observer_reset import ObserverReset
from .runner import run_node
from .wire import JointStateWriter, SensorReader, stamp_bytes, VectorReader, WireError
from ..core.clock_jump import far_back_text
from ..core.errors import ObserverError
from ..core.estimators import History, make_estimator
from ..core.estimators.admission import (Admission, AHEAD_COMMAND, BAD_STAMP, check_stamp,
                                         CLOCK_JUMP, DUPLICATE, FAR_BACK, LATE, OUT_OF_ORDER,
                                         restart_at, STALE_COMMAND)
from ..core.innovation import InnovationMonitor, transient_time
from ..core.lockstep_wait import CommandWait, GAVE_UP, RESEND, WATCH_PERIOD
from ..core.vehicle_design import design_vehicle

__all__ = ['ObserverNode', 'covariance_names', 'main', 'silence_watch_period']

# the node's parameters the admission reads (and takes again when they change)
ADMISSION_PARAMETERS = ('clock_jump_tolerance', 'future_tolerance', 'clock_jump_agreement')


class ObserverNode(ObserverHealth, ObserverReset, ManagedVehicleNode):
    """Estimate the state from the vehicle's sensors and commands (a managed node)."""

    def __init__(self):
        super().__init__('observer', own_parameters=(
            'clock_jump_tolerance', 'clock_jump_agreement', 'future_tolerance',
            'diagnostics_period'))
        self._init_reset()

    def configure_vehicle(self):
        """Design, build the estimator, create the publishers (nodes/managed.py)."""
        self._design_and_build(self.vehicle)
        v = self.vehicle
        if v.observer.history_length > self.param('clock_jump_tolerance'):
            self.get_logger().warning(
                f'observer.history_length ({v.observer.history_length:g} s) is longer than '
                f'clock_jump_tolerance ({self.param("clock_jump_tolerance"):g} s): a message '
                'that late resets the estimator as a clock jump instead')
        self._lockstep = v.simulator.mode == 'lockstep'
        self._est_pub = self.create_publisher(JointState, TOPICS['estimate'], STATE_PUB_QOS)
        # Kalman: P of each estimate answering a measurement (covariance_names)
        self._cov_pub = _CountedPublisher(self, TOPICS['covariance']) \
            if v.observer.kind == 'kalman' else None
        self._res_pub = _CountedPublisher(self, TOPICS['residual'])
        self.add_on_set_parameters_callback(self._on_set_parameters)

    def activate_vehicle(self):
        """Subscribe to the sensors and the command, start the timers (a fresh start)."""
        v = self.vehicle
        if self.history.t is not None:      # activated again: the estimate starts over
            self._design_and_build(v)
        self._wait = CommandWait()          # lockstep: estimates whose command is not back
        self._queue = []                    # lockstep: measurements waiting for that command
        self._last_estimate = None
        self._last_seen = {}                # sensor name -> wall time of last message
        self._init_health()
        self._subs = []
        # diagnostics name the topics as remapped and namespaced (/sub1/imu/data)
        self._resolved = {s.name: self.resolve_topic_name(s.topic) for s in v.sensors}
        # taken as bytes: read at fixed offsets (nodes/wire.py), no message objects
        for sensor in v.sensors:
            cls = MESSAGE_CLASSES[sensor.msg_type]
            self._subs.append(self.watched_subscription(
                cls, sensor.topic, lambda msg, s=sensor: self._on_measurement(s, msg),
                SENSOR_SUB_QOS, raw=True))
        self._cmd_sub = self.watched_subscription(
            JointState, TOPICS['command'], self._on_command, STATE_QOS, raw=True)
        self._subscribe_set_state()
        self._diag_timer = self.wall_timer(self.param('diagnostics_period'),
                                           self._on_diagnostics)
        if self._lockstep:
            self._lockstep_timer = self.wall_timer(WATCH_PERIOD,
                                                   self._on_lockstep_watchdog)
        else:
            # free running: when every sensor is silent past its timeout, publish the
            # prediction at observer.rate_hz (default: the simulator's rate); while they
            # speak the silence is watched at a slower period (_on_predict switches)
            rate = v.observer.rate_hz or v.simulator.rate_hz
            self._predict_ns = round(1e9 / rate)
            self._watch_ns = round(1e9 * silence_watch_period(
                rate, [s.timeout for s in v.sensors]))
            self._predicting = False
            self._look_ns = self._watch_ns
            self._predict_timer = self.wall_timer(self._watch_ns * 1e-9, self._on_predict)
            if v.observer.publish_rate_hz:
                self._publish_timer = self.wall_timer(1.0 / v.observer.publish_rate_hz,
                                                      self._on_publish_rate)

    # -- design -------------------------------------------------------------------------
    def _design_and_build(self, vehicle):
        """Design (refusing an unusable file) and build the estimator."""
        design = design_vehicle(vehicle)
        log = self.get_logger()
        rep = design.observability
        log.info(f'{vehicle.name}: observer {vehicle.observer.kind}; '
                 f'observable={rep.observable} (rank {rep.rank}/{rep.n}), '
                 f'detectable={rep.detectable}; '
                 f'observer poles {_poles(design.observer_poles)}; '
                 f'separation {"ok" if design.separation_ok else "FAILED"}')
        for text in design.warnings:
            log.warning(text)
        self.design = design
        self.estimator = make_estimator(vehicle.plant, vehicle.observer)
        # every message goes through the history (late ones at their stamps); the
        # estimator is read (x_hat, t) but only the history changes it
        self.history = History(self.estimator, vehicle.observer.history_length)
        self._health = _innovation_monitor(vehicle, design)
        self.vehicle = vehicle
        # each sensor's rows of C, looked up once rather than per message
        self._rows = {s.name: tuple(vehicle.plant.output_rows(s.outputs))
                      for s in vehicle.sensors}
        # the messages in and out as bytes (nodes/wire.py)
        self._readers = {s.name: SensorReader(s, MESSAGE_CLASSES[s.msg_type])
                         for s in vehicle.sensors}
        self._cmd_reader = VectorReader(vehicle.plant.input_names, TOPICS['command'])
        self._est_writer = JointStateWriter(vehicle.plant.state_names)
        self._res_writers = {s.name: JointStateWriter(s.outputs) for s in vehicle.sensors}
        self._cov_writer = JointStateWriter(covariance_names(vehicle.plant.state_names))
        self._build_health(vehicle)
        # what each stamp means (core: the bag replay asks the same); the ROS clock is
        # read once a second, or when a stamp passes the last reading, not per message
        try:
            self._admission = Admission(
                self.history, *(self.param(name) for name in ADMISSION_PARAMETERS),
                max_gap=self._max_gap, clock=self._clock_seconds, counts=self._counters)
        except ValueError as err:       # a tolerance out of its range: refused at start
            raise ObserverError(f'parameters: {err}') from None

    def _clock_seconds(self):
        return self.get_clock().now().nanoseconds * 1e-9

    def _on_set_parameters(self, params):
        problem = own_parameter_problem(params)
        if problem is not None:
            self.count('parameter_changes_refused')
            return SetParametersResult(successful=False, reason=problem)
        for p in params:                    # checked above
            if p.name in ADMISSION_PARAMETERS:
                setattr(self._admission, p.name, p.value)
        observer_params = [p for p in params if p.name.startswith('observer.')]
        if not observer_params:
            return SetParametersResult(successful=True)
        overrides = {p.name: p.value for p in params}
        try:
            # the loader refuses unstable or unpaired poles, the design an unusable gain,
            # the margin check poles stable in name only
            vehicle = self.load_vehicle(overrides)
            design = design_vehicle(vehicle)
            problem = changed_pole_problem(vehicle, 'observer', set(overrides))
            estimator = make_estimator(vehicle.plant, vehicle.observer)
        except (ObserverError, ValueError) as err:
            problem = str(err)
        if problem is not None:
            self.count('parameter_changes_refused')
            return SetParametersResult(successful=False, reason=problem)
        # Keep the estimate: only the gain changes (the history starts again).
        if self.estimator.t is not None:
            estimator.reset(self.estimator.x_hat, self.estimator.t)
        self.vehicle, self.design, self.estimator = vehicle, design, estimator
        self.history = History(estimator, vehicle.observer.history_length)
        self._admission.history = self.history
        self._health = _innovation_monitor(vehicle, design)
        self.get_logger().info(f'observer redesigned: poles {_poles(design.observer_poles)}')
        self.count('parameter_changes_applied')
        return SetParametersResult(successful=True)

    # -- callbacks ----------------------------------------------------------------------
    def _on_measurement(self, sensor, msg):
        start = self._last_seen[sensor.name] = self.wall_now()
        if self._lockstep and self._wait.pending:
            self._queue.append((sensor, msg))
        else:
            self._process_measurement(sensor, msg)
        if self._load.took(start, self.wall_now()) and self._load.overloaded:
            # said at once: a saturated executor may run the diagnostics timer late
            self._on_diagnostics()

    def _process_measurement(self, sensor, msg):
        try:
            header, y, problem = self._readers[sensor.name].read(msg)
        except WireError as err:            # bytes that are no such message: no time
            self._reject('bad_messages', str(err))
            return
        if header is not None:
            # every answer to this message carries its own stamp (its 8 bytes), to the
            # nanosecond (float seconds keep only ~0.2 us of a wall-clock stamp)
            stamp = header[2]
            try:
                t = check_stamp(header[0], header[1], sensor.topic)
            except ObserverError as err:    # no usable time: not even a prediction
                self._reject(BAD_STAMP.counter, str(err))
                return
        else:   # std_msgs/Float64 carries no stamp: the time it was received
            stamp = None
            t = self.get_clock().now().nanoseconds * 1e-9
        if problem is not None:
            self._reject('bad_messages', problem)
            self._answer_without_correction(sensor, t, stamp)
            return
        history = self.history
        head = history.t
        verdict = self._admission.measurement(sensor.name, t, self._last_seen[sensor.name])
        if not verdict.use:
            self._refused(sensor, verdict, t, head, stamp)
            return
        rows = self._rows[sensor.name]
        if verdict.restart:
            if verdict is CLOCK_JUMP:
                self._clock_jump(sensor, t)
            else:
                self._long_gap(sensor, t)
            # start over at the measurement: the initial estimate made to agree with it
            restart_at(history, self.estimator, rows, y)
        estimator = self.estimator
        skipped = estimator.unverified_corrections
        try:
            x_hat = history.correct(t, y, rows, tag=stamp)
        except (ObserverError, ValueError) as err:
            self._reject('rejected_updates', about(sensor.topic, err))
            self._answer_without_correction(sensor, t, stamp)
            return
        if skipped != estimator.unverified_corrections:
            # the gain of this step failed its verification: prediction only (core)
            reason = next(reversed(self.estimator.gain_failures.values()))
            self._reject('unverified_gain_corrections',
                         f'{sensor.topic}: correction skipped (prediction only): {reason}')
        # plain floats from here on: numpy's reductions cost more on a few elements
        x_hat = x_hat.tolist()
        if not all(map(math.isfinite, x_hat)):
            # Never publish a NaN: restart from the initial estimate.
            self._reset_estimator('numerical_resets', f'{sensor.topic}: estimate not finite',
                                  t)
            self._answer_without_correction(sensor, t, stamp)
            return
        problem = self._envelope.check(t, x_hat)
        if problem is not None:
            self._on_divergence(t, problem)
        newest = self._admission.previous
        if newest is not None:
            self._count_missed(sensor, t, newest)       # the load meter's
        self.count('measurements')
        # the estimate first: it is what the compensator waits for (benchmarks P1). A late
        # measurement is answered with the estimate at the newest stamp, now revised.
        if verdict is LATE:
            self._publish_estimate(history.t, history.head_tag, x_hat)
        else:
            self._publish_estimate(t, stamp, x_hat)
        if self._cov_pub is not None:
            self._publish_covariance()
        residual = history.residual
        if residual is not None:
            self._health.add(sensor.name, residual, history.innovation_covariance, t)
        if residual is not None and self._res_pub.subscribed():
            self._res_pub.publisher.publish(self._res_writers[sensor.name].write(
                stamp_bytes(t) if stamp is None else stamp, sensor.frame_id,
                residual.tolist()))

    def _publish_estimate(self, t, stamp=None, x_hat=None):
        """Publish x_hat (default: the estimator's) stamped ``stamp`` (8 bytes), else t."""
        x_hat = self.estimator.x_hat if x_hat is None else x_hat
        if stamp is None:
            stamp = stamp_bytes(t)
        # one frame for every estimate, whichever sensor it answers: the vehicle's body
        frame_id = self.vehicle.base_frame
        msg = self._est_writer.write(
            stamp, frame_id, x_hat.tolist() if isinstance(x_hat, np.ndarray) else x_hat)
        self._est_pub.publish(msg)
        self._last_estimate = msg
        self._last_header = (stamp, frame_id)
        if self._lockstep:
            self._wait.published(t, time.monotonic())

    def _publish_covariance(self):
        """Kalman: publish P of the estimate just published, with its stamp."""
        pub = self._cov_pub
        if not pub.subscribed():
            return
        P = getattr(self.estimator, 'P', None)
        if P is None or self._last_estimate is None:
            return
        upper = np.triu_indices(len(self.vehicle.plant.state_names))
        pub.publisher.publish(self._cov_writer.write(*self._last_header, P[upper].tolist()))

    def _answer_without_correction(self, sensor, t, stamp=None):
        """
        Lockstep: a measurement that was refused still gets an answer (the prediction).

        The simulator waits for a command per measurement; predicting to the message's
        stamp (when it is a usable time) keeps the loop going without the bad data.
        """
        if not self._lockstep or t is None or t <= 0.0:
            return
        last = self.history.t
        x_hat, at = self.estimator.x_hat, last
        if last is None or t >= last:
            try:
                x_hat, at = self.history.predict(t), t
            except (ObserverError, ValueError):
                return
        if np.isfinite(x_hat).all():
            at = t if at is None else at
            self._publish_estimate(at, stamp if at == t else None, x_hat)

    def _refused(self, sensor, verdict, t, head, stamp):
        """Log a measurement the admission refused (it counted it); answer a repeat."""
        topic = sensor.topic
        if verdict is DUPLICATE:
            # a repeat (a simulator re-sending a message whose answer was lost): answer it
            # again with the current estimate, without correcting twice
            text = f'{topic}: duplicate stamp {t:.6f}; estimate re-published'
            if head == t:
                self._publish_estimate(t, stamp)
        elif verdict is FAR_BACK:
            adm = self._admission
            newest = adm.newest if adm.newest is not None else head
            text = far_back_text(topic, t, newest, adm.clock_jump_agreement)
            if self._lockstep:      # the simulator waits for an answer at this stamp
                self._publish_estimate(t, stamp, self.estimator.x_hat)
        elif verdict is OUT_OF_ORDER:
            text = (f'{topic}: stamp {t:.6f} older than the history '
                    f'({self.history.length:g} s before the estimate, {head:.6f}); skipped')
        else:   # FUTURE
            now = self.get_clock().now().nanoseconds * 1e-9
            text = f'{topic}: stamp {t:.3f} is {t - now:.1f} s ahead of the clock; skipped'
        self.get_logger().warning(text, throttle_duration_sec=1.0)

    def _clock_jump(self, sensor, t):
        """Messages in a row agree that the clock jumped back: start again at them."""
        jump = self._admission.clock_jump_agreement
        self._reset_estimator(None, f'{sensor.topic}: clock jumped back to {t:.3f} s '
                              f'({jump} message{"s" if jump > 1 else ""} in a row)',
                              how='restarted at the measurement')
        self._envelope.reset()

    def _reset_estimator(self, counter, reason, t=None, how='reset to its initial estimate'):
        """Reset the estimator to its initial estimate: always logged and counted."""
        self.history.reset(None, t)         # the estimator, and its history forgotten
        self._health.restart()              # a new initial transient
        if counter is not None:
            self.count(counter)
        self.count('estimator_resets')
        self.get_logger().warning(f'{reason}; estimator {how}', throttle_duration_sec=1.0)

    def _on_command(self, msg):
        topic = TOPICS['command']
        try:
            header, u, problem = self._cmd_reader.read(msg)
        except WireError as err:            # bytes that are no JointState
            self._reject('bad_commands', str(err))
            return
        try:
            t = check_stamp(header[0], header[1], topic)
        except ObserverError as err:
            self._reject(BAD_STAMP.counter, str(err))
            return
        try:
            if problem is not None:
                raise ObserverError(problem)
            # a command is not a time source: it never moves the estimator's time (one
            # stamped ahead is held until the estimate reaches it) nor resets it
            head = self.history.t
            verdict = self._admission.command(t, self.wall_now())
            if verdict.use:
                # ahead: pending; inside the history: from its stamp on; older: held from
                # the estimate's time
                self.history.set_input(t, u, tag=header[2])
                self.count('commands')
                if verdict is STALE_COMMAND:
                    self.get_logger().warning(
                        f'{topic}: stamp {t:.6f} is {head - t:.3f} s older than the '
                        'estimate; held from now on', throttle_duration_sec=1.0)
            elif verdict is AHEAD_COMMAND:
                self.get_logger().warning(
                    f'{topic}: stamp {t:.6f} is {t - head:.3f} s ahead of the estimate; '
                    'skipped', throttle_duration_sec=1.0)
            else:
                now = self.get_clock().now().nanoseconds * 1e-9
                self.get_logger().warning(
                    f'{topic}: stamp {t:.3f} is {t - now:.1f} s ahead of the clock; '
                    'skipped', throttle_duration_sec=1.0)
        except (ObserverError, ValueError) as err:
            self._reject('bad_commands', about(topic, err))
        if self._lockstep and self._wait.answered(t):
            self._drain_queue()

    def _drain_queue(self):
        while self._queue and not self._wait.pending:
            sensor, msg = self._queue.pop(0)
            self._process_measurement(sensor, msg)

    def _on_lockstep_watchdog(self):
        """Re-send an unanswered estimate, give up late, or wait on (core.lockstep_wait)."""
        verdict = self._wait.check(time.monotonic(), self.vehicle.simulator.command_timeout)
        if verdict is None or (verdict is RESEND and self._last_estimate is None):
            return
        self.count(verdict)
        if verdict is GAVE_UP:
            self._drain_queue()
        elif verdict is RESEND:
            self._est_pub.publish(self._last_estimate)

    def _reject(self, counter, text):
        self.count(counter)
        self.get_logger().warning(text, throttle_duration_sec=1.0)

    def _on_predict(self):
        """
        Predict only while all sensors are silent; the estimate keeps coming.

        While a sensor speaks, the next look is a watch period past the moment the last
        one would fall silent (its newest message plus its timeout), not every watch
        period: the first prediction still comes at most a watch period after the
        timeout, and a gyro at 250 Hz costs two wake-ups a second instead of twenty.
        """
        now_wall = self.wall_now()
        if self.history.t is None:
            # no estimate yet (before the first measurement, after a reset): nothing to
            # predict; looked at every watch period
            speaking, quiet_at = True, now_wall
        else:
            quiet_at = max(self._last_seen.get(s.name, -np.inf) + s.timeout
                           for s in self.vehicle.sensors)
            speaking = now_wall <= quiet_at
        if speaking:
            # back to watching, or watching on: the next look from now
            self._predicting = False
            self._look_in(round((quiet_at - now_wall) * 1e9) + self._watch_ns)
            return
        if not self._predicting:                # the sensors fell silent: at the rate
            self._predicting = True
            self._look_in(self._predict_ns)
        self._publish_prediction('predictions')

    def _look_in(self, period_ns):
        """Call _on_predict next after period_ns from now, and every period_ns after."""
        if period_ns != self._look_ns:      # unchanged: the timer goes on as it is
            self._look_ns = period_ns
            self._predict_timer.timer_period_ns = period_ns
            self._predict_timer.reset()

    def _on_publish_rate(self):
        """Publish the estimate predicted to now (``observer.publish_rate_hz``)."""
        self._publish_prediction('rate_publications')

    def _publish_prediction(self, counter):
        """Publish the estimate predicted to the clock's time (the history unchanged)."""
        last = self.history.t
        now = self.get_clock().now().nanoseconds * 1e-9
        # only when the stamps are on this node's clock (not a replayed bag's old time)
        if last is None or not 0.0 < now - last < 100.0 * max(
                s.timeout for s in self.vehicle.sensors):
            return
        try:
            x_hat = self.history.predict(now)
        except (ObserverError, ValueError):
            return
        self.count(counter)
        self._publish_estimate(now, None, x_hat)

    def _on_diagnostics(self):
        now = self.wall_now()
        level, message = DiagnosticStatus.OK, 'estimating'
        silent = []
        for sensor in self.vehicle.sensors:
            seen = self._last_seen.get(sensor.name)
            if seen is None or now - seen > sensor.timeout:
                silent.append(self._resolved[sensor.name])
        if silent:
            level = DiagnosticStatus.WARN
            message = f'predicting only: no data on {", ".join(silent)}'
        values = {'observer_type': self.vehicle.observer.kind,
                  'x_hat': np.array2string(self.estimator.x_hat, precision=6)}
        level, message = self._health_status(now, level, message, values)
        if self._counters.get('unverified_gain_corrections') and level == DiagnosticStatus.OK:
            level = DiagnosticStatus.WARN
            message = 'some corrections skipped: their step gain failed verification'
        duplicates = self.duplicate_publishers((TOPICS['estimate'], TOPICS['command']))
        if duplicates:
            level = DiagnosticStatus.ERROR
            message = f'more than one publisher: {", ".join(duplicates)}'
        self.publish_diagnostics(level, message, values, extra=self._health_statuses())

    def _health_statuses(self):
        """Return one status per sensor: its residuals' consistency with the model."""
        out = []
        for h in self._health.report():
            level = DiagnosticStatus.OK if h.consistent else DiagnosticStatus.WARN
            text = h.problem or (f'{h.name}: consistent' if h.samples >= self._health.window
                                 else f'{h.name}: estimate converging (residuals judged '
                                 f'from {self._health.transient:.3g} s on)' if h.converging
                                 else f'{h.name}: {h.samples} residuals, window not full')
            out.append((f'innovation/{h.name}', level, text, {
                'samples': h.samples, 'transient_samples': h.transient,
                'nis_mean': f'{h.nis_mean:.4g}',
                'nis_bounds': f'{h.nis_low:.4g}..{h.nis_high:.4g}',
                'whiteness_p': f'{h.whiteness_p:.3g}'}))
        return out


def silence_watch_period(rate_hz, timeouts):
    """
    Return the period (s) at which a free-running observer watches its sensors' silence.

    A tenth of the shortest sensor timeout, never faster than the prediction rate: the
    first prediction comes at most that much after the timeout. (Watched at the
    prediction rate, 1 kHz in P2, the timer's calls alone were 15 % of the observer's CPU
    while every measurement was answered; benchmarks/README.md.)

    Parameters
    ----------
    rate_hz : float
        ``observer.rate_hz`` (or the simulator's rate): predictions per second once silent.
    timeouts : sequence of float
        Each sensor's ``timeout`` (s).

    """
    return max(1.0 / rate_hz, min(timeouts) / 10.0)


class _CountedPublisher:
    """
    A JointState publisher that knows whether anyone subscribes, without an rcl call.

    The subscribers are counted from the middleware's matched events: asking for them per
    message (get_subscription_count, 2-4 us) was the measurement callback's largest part.
    A middleware without matched events: asked per message.
    """

    def __init__(self, node, topic):
        self.subscribers = 0
        try:
            self.publisher = node.create_publisher(
                JointState, topic, STATE_PUB_QOS,
                event_callbacks=PublisherEventCallbacks(matched=self._on_matched))
        except UnsupportedEventTypeError:
            self.publisher = node.create_publisher(JointState, topic, STATE_PUB_QOS)
            self.subscribers = None

    def _on_matched(self, info):
        self.subscribers = info.current_count

    def subscribed(self):
        """Return the number of subscribers (0: no message need be built)."""
        count = self.subscribers
        return self.publisher.get_subscription_count() if count is None else count


def _innovation_monitor(vehicle, design):
    """Return the innovation monitor of a design: its initial transient not judged."""
    return InnovationMonitor(
        [(s.name, s.noise_std) for s in vehicle.sensors],
        kalman=vehicle.observer.kind == 'kalman',
        transient=transient_time(design.observer_poles, vehicle.sample_time,
                                 vehicle.plant.is_discrete, vehicle.observer.kind == 'kalman'))


def covariance_names(state_names):
    """
    Return the names of the entries of ``state/covariance``: the upper triangle of P.

    ``'theta,w'`` is ``P[theta, w]``, row by row (``theta,theta``, ``theta,w``, ...,
    ``w,w``, ...); n (n + 1) / 2 of them.
    """
    n = len(state_names)
    return [f'{state_names[i]},{state_names[j]}' for i in range(n) for j in range(i, n)]


def _poles(poles):
    return '[' + ', '.join(f'{complex(p).real:.4g}{complex(p).imag:+.4g}j'
                           if abs(complex(p).imag) > 0 else f'{complex(p).real:.4g}'
                           for p in poles) + ']'


def main(args=None):
    """Run the observer node."""
    return run_node(ObserverNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
