# observer_ros.core.estimators.factory: the estimator an ObserverSpec describes.
"""
Build the estimator of a vehicle's ``observer`` section.

The one call the node and the bag replay use to make their estimator.

"""

from .base import OpenLoopEstimator
from .full_order import FullOrderEstimator
from .kalman import KalmanEstimator
from .reduced_order import ReducedOrderEstimator
from ..errors import ObserverError
from ..spec import OBSERVER_TYPES, ObserverSpec

__all__ = ['make_estimator']


def make_estimator(plant, observer_spec, measured_rows=None, **kwargs):
    """
    Build the estimator an ObserverSpec describes.

    Parameters
    ----------
    plant : Plant
        The model.
    observer_spec : ObserverSpec
        ``kind`` one of full, reduced, open_loop, kalman; poles or gain;
        Qd, Rd, Bd for kalman; initial_estimate.
    measured_rows : sequence of int, optional
        The outputs the estimator will be given; default all.
    **kwargs
        Passed on to the estimator (t0, dt_digits, cache_size, gain_digits, P0 for
        kalman).

    Returns
    -------
    Estimator

    """
    spec = observer_spec
    if not isinstance(spec, ObserverSpec):
        raise ObserverError(f'observer_spec must be an ObserverSpec; got {type(spec).__name__}')
    kind = spec.kind
    common = dict(x0=spec.initial_estimate, measured_rows=measured_rows, **kwargs)
    if kind == 'full':
        return FullOrderEstimator(plant, poles=spec.poles, gain=spec.gain,
                                  method=spec.method, **common)
    if kind == 'reduced':
        return ReducedOrderEstimator(plant, poles=spec.poles, gain=spec.gain,
                                     method=spec.method, **common)
    if kind == 'open_loop':
        return OpenLoopEstimator(plant, **common)
    if kind == 'kalman':
        if spec.Qd is None or spec.Rd is None:
            raise ObserverError('observer.Qd and observer.Rd are required for a kalman observer')
        return KalmanEstimator(plant, spec.Qd, spec.Rd, spec.Bd, **common)
    raise ObserverError(f'observer.type is {kind!r}; expected one of {list(OBSERVER_TYPES)}')
