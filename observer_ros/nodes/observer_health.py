# observer_ros.nodes.observer_health: the observer's overload, divergence and gap checks.
"""
What the observer node checks about itself, as a mixin of ObserverNode.

Overload (core.health.LoadMeter: busy fraction, messages missed by their stamps, read by
core.stamp_gaps), a diverging estimate (core.health.Envelope: reported, never OK), and a
measurement after a gap so long that predicting across it would amplify the error (the
estimate restarts at the measurement). The node calls these from its measurement path and
its diagnostics.

"""

from diagnostic_msgs.msg import DiagnosticStatus

from .common import MESSAGE_CLASSES
from ..core.health import (Envelope, ENVELOPE_FACTOR, LoadMeter, max_prediction_gap,
                           state_scale)
from ..core.stamp_gaps import MissedStamps

__all__ = ['DIVERGENCE_HOLD', 'ObserverHealth']

# wall s: a divergence stays reported (ERROR) this long after the last implausible estimate
DIVERGENCE_HOLD = 2.0


class ObserverHealth:
    """The observer's self-checks; needs the ObserverNode attributes it names."""

    def _init_health(self):
        self._load = LoadMeter()            # overload: busy fraction, missed stamps
        self._diverging = None              # the last divergence report, and its wall time
        self._diverged_at = None

    def _build_health(self, vehicle):
        """Set the vehicle's bounds: sensor periods, envelope, longest prediction."""
        # each sensor's period (s): a longer gap between its stamps is missed messages
        self._periods = {s.name: s.rate_divider / vehicle.simulator.rate_hz
                         for s in vehicle.sensors}
        # the gaps between a stamped sensor's stamps say which messages were missed (a
        # message without a stamp, timed when received, says nothing); a gap within 1.5
        # periods, with nothing owed, is not looked at
        self._stamp_gaps = {s.name: MissedStamps(self._periods[s.name])
                            for s in vehicle.sensors
                            if hasattr(MESSAGE_CLASSES[s.msg_type], 'header')}
        self._gap_missed = {s.name: 1.5 * self._periods[s.name] for s in vehicle.sensors}
        self._envelope = Envelope(vehicle.plant.state_names, state_scale(vehicle), 'x_hat')
        self._max_gap = max_prediction_gap(vehicle.plant.A, vehicle.sample_time,
                                           vehicle.plant.is_discrete)

    def _count_missed(self, sensor, t, newest):
        """
        Count in the load meter the messages the sensor's stamps say were missed.

        ``t`` is the measurement's stamp, ``newest`` the sensor's newest stamp before it.
        A gap is counted only when the next message does not make up for it (a late
        message is followed by an early one; a lost one is not): core.stamp_gaps.
        """
        gaps = self._stamp_gaps.get(sensor.name)
        if gaps is None:
            return
        gap = t - newest
        if gaps.owed or not 0.0 < gap <= self._gap_missed[sensor.name]:
            self._load.missed(gaps.gap(gap))

    def _on_divergence(self, t, problem):
        """
        Report an estimate beyond the plausible envelope: ERROR on /diagnostics at once.

        The estimate goes on (a plant that really went far must still be tracked); the
        compensator, with its own envelope, sends the safe command.
        """
        if self._diverging is None:
            self.get_logger().error(f'diverging: {problem}')
        self._diverging, self._diverged_at = problem, self.wall_now()
        self.count('divergence_reports')
        self._on_diagnostics()

    def _long_gap(self, sensor, t):
        """
        Start over: predicting across this gap would amplify the error.

        The caller restarts the estimator at the measurement
        (:func:`~observer_ros.core.estimators.admission.restart_at`).
        """
        gap = t - self.history.t
        self.get_logger().warning(
            f'{sensor.topic}: {gap:.2f} s since the estimate, longer than the '
            f'{self._max_gap:.2f} s over which the unstable model grows the error '
            f'{ENVELOPE_FACTOR:g} x; estimator restarted at the measurement',
            throttle_duration_sec=1.0)
        self.count('estimator_resets')     # long_gap_resets: the admission's
        self._health.restart()              # a new initial transient
        self._envelope.reset()

    def _health_status(self, now, level, message, values):
        """Return the diagnostics level and message with overload and divergence in them."""
        load = self._load
        load.idle(now)
        if load.rate is not None:
            values.update(answered_per_s=f'{load.rate:.1f}', busy=f'{load.busy:.2f}',
                          missed_per_s=f'{load.missed_rate:.1f}')
        if load.overloaded:
            level = DiagnosticStatus.ERROR
            message = (f'overloaded: answering {load.rate:.1f} measurements/s, '
                       f'{load.missed_rate:.1f}/s missed, busy {100 * load.busy:.0f} %')
        if self._diverged_at is not None and now - self._diverged_at < DIVERGENCE_HOLD:
            level, message = DiagnosticStatus.ERROR, f'diverging: {self._diverging}'
        elif self._diverged_at is not None:
            self._diverging = self._diverged_at = None
        return level, message
