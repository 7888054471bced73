# observer_ros.core.estimators: the estimator step shared by the observer node and bag replay.
"""
State estimators stepped at the times the measurements arrive.

The same calls in the same order give bit-identical estimates: the step has no
randomness, no wall clock and no dependence on what is already cached (every
matrix is a function of the quantised step only, see :class:`StepCache`). The
ROS observer node and the offline bag replay both drive these classes.

Two keys per step: the state is propagated with the exact sampled model of the
step rounded to ``dt_digits`` (12) significant digits, while correction gains
(pole placement, reduced-order Lr, Kalman process noise) are designed for the
step rounded to ``gain_digits`` (3). Real time stamps jitter, so nearly every
step is new to twelve digits; it then costs a matrix exponential, not a pole
placement (see :data:`GAIN_DIGITS`).

Time is a float in seconds. Keep it small: pass times relative to the start of
a run (a float holding Unix time has a resolution of about 0.2 microseconds,
which would make every step different).

Estimators
----------
:class:`FullOrderEstimator`
    Luenberger observer in current (filter) form, exact at any sample times.
:class:`ReducedOrderEstimator`
    Reduced-order observer (seeds 000 section 3.5 and 002 section 5.4.2) that
    reproduces the measured combinations C x_hat = y - D u exactly.
:class:`OpenLoopEstimator`
    The model alone; measurements only give a residual.
:class:`KalmanEstimator`
    Time-varying discrete Kalman filter on the exactly sampled model.

Modules
-------
``steps``
    The exactly sampled step (Ad, Bd) and its caches, the grid of gain steps.
``placement``
    The correction gain of a step (pole placement) and the detectability check.
``base``
    :class:`Estimator` (time keeping, held input, the public calls) and
    :class:`OpenLoopEstimator`.
``current_form``
    The correction shared by the full- and reduced-order observers.
``full_order``, ``reduced_order``, ``kalman``
    One observer each.
``history``
    :class:`History`: late and out-of-order messages, by rewinding.
``rewind``, ``superposition``
    How the history inserts a late message: a rewind from a checkpoint; a late command's
    input change added to the states kept after it.
``factory``
    :func:`make_estimator` from an ObserverSpec.

"""

from .._lazy import exports

# the submodule that defines each exported name, imported when one of its names is first
# asked for: the admission and the history are used without the observers' designs
_EXPORTS = {
    'steps': ('DT_DIGITS', 'GAIN_DIGITS', 'CACHE_SIZE', 'GAIN_CACHE_SIZE', 'StepCache',
              'process_noise_covariance'),
    'base': ('TimeOrderError', 'Estimator', 'OpenLoopEstimator'),
    'full_order': ('FullOrderEstimator',),
    'reduced_order': ('ReducedOrderEstimator',),
    'kalman': ('KalmanEstimator',),
    'factory': ('make_estimator',),
    'history': ('History', 'HISTORY_LENGTH', 'HISTORY_MAX_MESSAGES', 'CHECKPOINT_EVERY',
                'DENSE_DEPTH', 'DENSE_FOR'),
}

__all__, __getattr__, __dir__ = exports(globals(), _EXPORTS)
