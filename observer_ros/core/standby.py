# observer_ros.core.standby: the compensator's own observer, kept warm for when x_hat stops.
"""
A standby observer: the vehicle's observer, run by the compensator on the sensor topics.

An unstable plant cannot be held open loop: the cart's pendulum grows e^{3.28 t}, so no
predict-and-hold outlives a silence of a few seconds. The compensator therefore keeps its
own copy of the vehicle's observer (the same file, the same core estimator and history as
the observer node) fed with every measurement and every command it sends. While the
observer node is silent it closes the loop on this estimate; the observer's own, when it
speaks again, is compared with it before it is followed again. The standby also tells
an estimate stream that does not belong to this loop (a second observer with the same
name, unconverged) from the one it follows.

Each measurement is judged by the observer node's own :class:`~.estimators.admission.Admission`
(the same ``max_gap`` from :func:`.health.max_prediction_gap`): a stamp repeated is not
corrected with twice, and after a gap longer than the unstable model can be predicted
over (a plant that waited at its step 0 while /clock went on) the standby restarts at the
measurement, as the observer does, and is not warm until it has run on measurements for
``warm_after`` again. Far-back stamps and clock jumps are the compensator's to judge
(:meth:`reset`); no stamp is refused for being ahead of a clock.

No ROS here: the node reads the sensor messages (``sensors.extract_measurement``) and
passes stamps and values.

"""

from collections import OrderedDict

import numpy as np

from .errors import ObserverError
from .estimators import History, make_estimator
from .estimators.admission import Admission, DUPLICATE, restart_at
from .health import max_prediction_gap
from .verify import unstable_eigenvalues

__all__ = ['StandbyObserver', 'unstable_plant']

# How many of the standby's recent estimates are kept by stamp (to compare the observer's).
RECENT = 64
# s: the standby's admission never finds a stamp far back (a clock jump): the compensator
# judges those (``sensor_jumps``) before a measurement reaches the standby, and resets it
NEVER_FAR_BACK = 1e9


def unstable_plant(plant):
    """
    Tell whether a plant has a mode that is not stable: it cannot be held open loop.

    By the one stability rule (:func:`.verify.unstable_eigenvalues`): an unstable or
    marginal eigenvalue of A (an integrator drifts too).
    """
    return bool(unstable_eigenvalues(plant.A, plant.is_discrete))


class StandbyObserver:
    """
    The vehicle's observer on the sensor topics, for the compensator.

    Parameters
    ----------
    vehicle : Vehicle
        The vehicle file (plant, observer, sensors).
    warm_after : float
        Seconds of measurements (on their stamps) after which it counts as converged
        (:attr:`warm`): one settling time of the observer's slowest pole; inf: never.

    Attributes
    ----------
    warm : bool
        It has run on measurements for ``warm_after`` seconds since its start, reset or
        restart.
    refused : int
        Measurements it could not use (older than its history, not finite, a bad size).
    counts : dict
        The admission's counters (``duplicates``, ``long_gap_resets``, ...).
    restarted : float or None
        The gap (s) the last measurement restarted the standby after, else None.

    """

    def __init__(self, vehicle, warm_after=0.0):
        self._vehicle = vehicle
        self.warm_after = float(warm_after)
        self._rows = {s.name: tuple(vehicle.plant.output_rows(s.outputs))
                      for s in vehicle.sensors}
        plant = vehicle.plant
        self._max_gap = max_prediction_gap(plant.A, vehicle.sample_time, plant.is_discrete)
        self.refused = 0
        self.counts = {}
        self.restarted = None
        self.reset()

    def reset(self):
        """Start again from the file's initial estimate (a clock that started over)."""
        self._estimator = make_estimator(self._vehicle.plant, self._vehicle.observer)
        self.history = History(self._estimator, self._vehicle.observer.history_length)
        self._admission = Admission(self.history, clock_jump_tolerance=NEVER_FAR_BACK,
                                    future_tolerance=None, max_gap=self._max_gap,
                                    counts=self.counts)
        self._recent = OrderedDict()
        self._first = None
        self.warm = False

    @property
    def t(self):
        """Return the time of the standby's estimate (None before its first measurement)."""
        return self.history.t

    def measurement(self, sensor, t, y):
        """
        Correct with one measurement of a sensor; return the estimate at t, or None.

        Parameters
        ----------
        sensor : str
            The sensor's name in the vehicle file.
        t : float
            Its stamp, s.
        y : array_like
            Its values, in the order of the sensor's outputs.

        Returns
        -------
        x_hat : ndarray or None
            The estimate at t (a copy); None when the measurement was refused (counted in
            :attr:`refused`) or is older than the estimate (used at its stamp; the
            estimate at the newest stamp is revised).

        """
        history = self.history
        head = history.t
        verdict = self._admission.measurement(sensor, t)
        self.restarted = None
        if verdict is DUPLICATE:        # answered with the estimate made at that stamp
            x = self._recent.get(t)
            return None if x is None else x.copy()
        if not verdict.use:
            self.refused += 1
            return None
        rows = self._rows[sensor]
        if verdict.restart:             # a long gap: at the measurement, as the observer
            self.restarted = t - head
            restart_at(history, self._estimator, rows, y)
            self._recent.clear()
            self._first, self.warm, head = None, False, None
        try:
            x = history.correct(t, y, rows)
        except (ObserverError, ValueError):
            self.refused += 1
            return None
        if not np.all(np.isfinite(x)):
            self.refused += 1
            self.reset()
            return None
        x = np.array(x, dtype=float)
        if head is not None and t < head:
            self._recent[history.t] = np.array(history.x_hat, dtype=float)
            return None
        self._remember(t, x)
        if not self.warm:
            if self._first is None:
                self._first = t
            self.warm = t - self._first >= self.warm_after
        return x

    def command(self, t, u):
        """Hold the command u sent from its stamp t on (as the observer node does)."""
        try:
            self.history.set_input(t, np.asarray(u, dtype=float))
        except (ObserverError, ValueError):
            self.refused += 1

    def at(self, t):
        """
        Return the standby's estimate at stamp t (a copy), or None if it has none there.

        An estimate it made at that stamp; for a stamp after its newest, its prediction;
        None for an older stamp it has no estimate for.
        """
        x = self._recent.get(t)
        if x is not None:
            return x.copy()
        head = self.history.t
        if head is not None and t >= head:
            return np.array(self.history.predict(t), dtype=float)
        return None

    def _remember(self, t, x):
        recent = self._recent
        recent[t] = x
        recent.move_to_end(t)
        while len(recent) > RECENT:
            recent.popitem(last=False)
