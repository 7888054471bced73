# observer_ros.core.vehicle_design: the observer and controller a vehicle file asks for.
"""
Vehicle design: gains from a vehicle file, verified, with rule-of-thumb warnings.

:func:`design_vehicle` designs the observer and the controller a vehicle describes,
checks every gain (``core/verify.py``) and the closed loop (``core/closed_loop.py``), and
collects the warnings of :func:`design_warnings`.

"""

from dataclasses import dataclass, field
import math
from typing import Optional, Tuple
import warnings

import numpy as np
import scipy.linalg

from ._lazy import control
from .analysis import (controllability_report, ControllabilityReport, format_complex,
                       observability_report, ObservabilityReport, stability_margin,
                       unobservable_eigenvalues)
from .closed_loop import (compensator_poles, compensator_ss, plant_matrices,
                          separation_details, tracking_ok, tracking_residual)
from .design import (controller_gain, kalman_gain, lqr_gain, observer_gain,
                     reduced_order_observer, ReducedOrderDesign)
from .errors import (DesignError, DimensionError, NotDetectableError, ObserverDesignWarning,
                     ObserverError)
from .estimators.sampled import check_sampled_observer, SampledCheck
from .health import divergence_envelopes
from .model import as_matrix, as_poles, as_vector
from .verify import (PlacementCheck, stability_status, unstable_eigenvalues, verify_placement,
                     verify_stable)

__all__ = ['observer_noise_gain', 'design_warnings', 'VehicleDesign', 'design_vehicle',
           'measurement_intensity',
           'SPEED_RATIO', 'NOISE_GAIN_LIMIT']

#: Seed 000's rule of thumb: observer poles "twice as negative" as the controller's.
SPEED_RATIO = 2.0

#: An observer whose estimate of a measured output is noisier than the sensor
#: itself (ratio > 1) amplifies measurement noise.
NOISE_GAIN_LIMIT = 1.0

# ---------------------------------------------------------------- warnings


def _decay_rate(lam, discrete):
    lam = complex(lam)
    if discrete:
        return math.inf if abs(lam) == 0.0 else -math.log(abs(lam))
    return -lam.real


def observer_noise_gain(A, C, L, noise_std, sample_time=None, discrete=False):
    """
    Noise gain of a full-order observer: std of its estimate of each output / sensor std.

    Parameters
    ----------
    A, C : array_like
        Plant: state and output matrices.
    L : (n, p) array_like
        Observer gain.
    noise_std : (p,) array_like
        Measurement noise standard deviation per output.
    sample_time : float or (p,) array_like, optional
        Sample time of each sensor; required in continuous time, where sampled
        noise of variance sigma^2 every dt is white noise of intensity
        ``sigma^2 dt``.
    discrete : bool
        Discrete plant: the noise enters every step with variance sigma^2.

    Returns
    -------
    ratio : (p,) ndarray
        ``sqrt(diag(C P C^T)) / sigma`` where P is the steady-state covariance of
        the estimation error driven by the measurement noise alone:
        ``(A - L C) P + P (A - L C)^T + L R L^T = 0`` (continuous,
        scipy ``solve_continuous_lyapunov``) or ``P = Phi P Phi^T + L R L^T``
        (discrete). A ratio above 1 means the observer's estimate of a
        measured quantity is noisier than the measurement: the gain is too large
        (poles too fast) for the sensor. NaN for outputs with sigma = 0, inf if
        the observer is unstable.
    P : (n, n) ndarray
        The covariance (per-state noise std is ``sqrt(diag(P))``).

    """
    A = as_matrix(A, 'A', square=True)
    n = A.shape[0]
    C = as_matrix(C, 'C', cols=n)
    p = C.shape[0]
    L = as_matrix(L, 'L', rows=n, cols=p)
    sigma = as_vector(noise_std, 'noise_std', p)
    if discrete:
        R = np.diag(sigma ** 2)
    else:
        if sample_time is None:
            raise ObserverError('sample_time is needed for the noise gain of a continuous '
                                'observer')
        dt = np.broadcast_to(np.asarray(sample_time, dtype=float), (p,))
        R = np.diag(sigma ** 2 * dt)
    Phi = A - L @ C
    if unstable_eigenvalues(Phi, discrete):
        return np.full(p, np.inf), np.full((n, n), np.inf)
    Q = L @ R @ L.T
    if discrete:
        P = _discrete_lyapunov(Phi, Q)
    else:
        P = scipy.linalg.solve_continuous_lyapunov(Phi, -Q)
    P = (P + P.T) / 2.0
    out_std = np.sqrt(np.maximum(np.diag(C @ P @ C.T), 0.0))
    with np.errstate(divide='ignore', invalid='ignore'):
        ratio = np.where(sigma > 0, out_std / np.where(sigma > 0, sigma, 1.0), np.nan)
    return ratio, P


def _discrete_lyapunov(Phi, Q):
    """
    Return P = sum_k Phi^k Q Phi^kT for a stable Phi.

    scipy's direct solver, or, when it warns of an ill-conditioned system (a deadbeat
    Phi: nilpotent and far from normal), Smith's doubling ``P <- P + Phi_j P Phi_j^T``,
    ``Phi_j <- Phi_j^2``, which sums the same series.

    """
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter('always')
        P = scipy.linalg.solve_discrete_lyapunov(Phi, Q)
    if not caught and np.all(np.isfinite(P)):
        return P
    P, Pk = Q.copy(), Phi.copy()
    for _ in range(64):
        P = P + Pk @ P @ Pk.T
        Pk = Pk @ Pk
        if not np.any(Pk) or np.linalg.norm(Pk, 1) < 1e-17:
            break
    return P


def design_warnings(A, B, C, K, L, D=None, discrete=False, noise_std=None,
                    sample_time=None, output_names=None, speed_ratio=SPEED_RATIO,
                    noise_gain_limit=NOISE_GAIN_LIMIT):
    """
    Rule-of-thumb checks of a compensator design; a list of human-readable warnings.

    Parameters
    ----------
    A, B, C : array_like
        Plant: state, input and output matrices.
    K : (m, n) array_like or None
        Controller gain (None: observer only, rules 1 and 2 are skipped).
    L : (n, p) array_like or ReducedOrderDesign
        Observer gain L or reduced design.
    D : (p, m) array_like, optional
        Feedthrough matrix; default zeros.
    discrete : bool
        Discrete time: z-plane instead of s-plane.
    noise_std : (p,) array_like, optional
        Sensor noise std per output, for rule 4.
    sample_time : float or (p,) array_like, optional
        Sensor sample times (continuous plant), for rule 4.
    output_names : sequence of str, optional
        Output names for messages.
    speed_ratio : float
        Rule 1 factor (2: seed 000's "twice as negative").
    noise_gain_limit : float
        Rule 4 threshold.

    Returns
    -------
    list of str
        The rules:

        1. Observer too slow (seed 000, seed 004): the slowest observer pole must
           decay at least ``speed_ratio`` times as fast as the slowest controller
           pole, decay rate ``-Re(s)`` (or ``-ln|z|`` per step).
        2. Unstable compensator (seed 000): an eigenvalue of the compensator's state
           matrix in the closed right half plane (on/outside the unit circle):
           the loop is only conditionally stable and not robust.
        3. Unstable observer: the estimation error does not decay (an open-loop
           observer of an unstable plant drifts, seed 004).
        4. Noise amplification (seed 000, seed 004; full-order observers): the
           :func:`observer_noise_gain` of an output exceeds ``noise_gain_limit``.

    """
    A, B, C, D = plant_matrices(A, B, C, D)
    n, m, p = A.shape[0], B.shape[1], C.shape[0]
    out_names = list(output_names) if output_names else [f'y{i + 1}' for i in range(p)]
    observer = L
    reduced = isinstance(observer, ReducedOrderDesign)
    if reduced:
        obs_poles = observer.poles
        L = None
    else:
        L = as_matrix(observer, 'L', rows=n, cols=p)
        obs_poles = np.linalg.eigvals(A - L @ C)
    out = []
    unstable_obs = [lam for lam, _ in unstable_eigenvalues(
        observer.F if reduced else A - L @ C, discrete)]
    if unstable_obs:
        what = 'the open-loop observer drifts (L = 0 and A is not stable)' \
            if L is not None and not np.any(L) else 'the estimation error does not decay'
        out.append(f'observer is not stable: poles '
                   f'{", ".join(format_complex(x, 4) for x in unstable_obs)}; {what}')
    if K is not None:
        K = as_matrix(K, 'K', rows=m, cols=n)
        ctrl_poles = np.linalg.eigvals(A - B @ K)
        ctrl_rate = min(_decay_rate(x, discrete) for x in ctrl_poles) if n else math.inf
        obs_rate = min(_decay_rate(x, discrete) for x in obs_poles) if len(obs_poles) else \
            math.inf
        if 0.0 < ctrl_rate < math.inf and obs_rate < speed_ratio * ctrl_rate * (1 - 1e-6):
            slow_o = min(obs_poles, key=lambda x: _decay_rate(x, discrete))
            slow_c = min(ctrl_poles, key=lambda x: _decay_rate(x, discrete))
            out.append(
                f'observer is slow: its slowest pole {format_complex(slow_o, 4)} is not '
                f'{speed_ratio:g}x as fast as the slowest controller pole '
                f'{format_complex(slow_c, 4)}; the estimate lags and the loop responds '
                'like the observer (seed 000: make observer poles twice as negative)')
        comp = compensator_poles(A, B, C, K, observer, D)
        cm = stability_margin(A - B @ K)
        bad = [lam for lam in comp if stability_status(lam, cm, discrete) == 'unstable']
        if bad:
            out.append(
                f'unstable compensator: D(s) has the pole(s) '
                f'{", ".join(format_complex(x, 4) for x in bad)}; the closed loop is only '
                'conditionally stable and may not be robust to model errors (seed 000)')
    if noise_std is not None and not reduced and not unstable_obs:
        sigma = as_vector(noise_std, 'noise_std', p)
        if discrete or sample_time is not None:
            ratio, _ = observer_noise_gain(A, C, L, sigma, sample_time, discrete)
            for i in range(p):
                if np.isfinite(ratio[i]) and ratio[i] > noise_gain_limit:
                    out.append(
                        f'observer amplifies the noise of {out_names[i]}: its estimate of '
                        f'{out_names[i]} has {ratio[i]:.3g}x the sensor noise std; the '
                        'observer poles are too fast (gains too large) for this sensor')
    return out


# ---------------------------------------------------------------- vehicle design


@dataclass(frozen=True)
class VehicleDesign:
    """
    Everything designed for a vehicle: reports, gains, poles, compensator, warnings.

    ``L`` is the gain in use: (n, p) for 'full', 'kalman' and 'open_loop' (zeros),
    (n - p, p) for 'reduced' (whose full design is ``reduced``). ``K`` is None
    when the vehicle has no controller. Poles are s-plane for a continuous plant
    and z-plane for a discrete one.

    """

    kind: str
    discrete: bool
    sample_time: Optional[float]
    state_names: Tuple[str, ...]
    input_names: Tuple[str, ...]
    output_names: Tuple[str, ...]
    observability: ObservabilityReport
    controllability: ControllabilityReport
    L: np.ndarray
    K: Optional[np.ndarray]
    observer_poles: np.ndarray
    controller_poles: np.ndarray
    closed_loop_poles: np.ndarray
    expected_poles: np.ndarray
    separation_ok: Optional[bool]
    compensator: Optional['control.StateSpace']
    compensator_poles: np.ndarray
    reduced: Optional[ReducedOrderDesign] = None
    P: Optional[np.ndarray] = None
    Kd: Optional[np.ndarray] = None
    reference: Optional[np.ndarray] = None
    tracking_residual: Optional[np.ndarray] = None
    noise_gain: Optional[np.ndarray] = None
    warnings: Tuple[str, ...] = field(default=())
    observer_placement: Optional[PlacementCheck] = None
    controller_placement: Optional[PlacementCheck] = None
    separation_error: Optional[float] = None
    separation_allowed: Optional[float] = None
    sampled: Optional[SampledCheck] = None

    @property
    def observer(self):
        """Return what the closed-loop helpers take: L (full order) or the ReducedOrderDesign."""
        return self.reduced if self.reduced is not None else self.L


def _poles_from_spec(poles, name, discrete):
    if poles is None:
        return None
    try:
        return as_poles(poles, name, None, discrete=discrete, require_stable=True)
    except DimensionError:
        raise
    except ObserverError as err:
        raise DesignError(str(err)) from None


def _prefixed(name, fn, *args, **kwargs):
    """Call fn; prefix the vehicle-file field name to a DimensionError about poles."""
    try:
        return fn(*args, **kwargs)
    except DimensionError as err:
        if str(err).startswith('poles'):
            raise DimensionError(f'{name}: {err}') from None
        raise


def _noise_per_output(vehicle):
    plant = vehicle.plant
    p = plant.p
    sigma = np.full(p, np.nan)
    dt = np.full(p, np.nan)
    base = vehicle.sample_time
    for s in vehicle.sensors:
        stds = np.asarray(s.noise_std, dtype=float).reshape(-1)
        for j, out in enumerate(s.outputs):
            if out in plant.output_names and j < stds.size:
                i = plant.output_names.index(out)
                sigma[i] = stds[j]
                dt[i] = base * max(1, int(s.rate_divider))
    return sigma, dt


def measurement_intensity(vehicle):
    """
    Return the measurement noise of a Kalman observer as its continuous design sees it.

    ``observer.Rd`` is the covariance of each sample, as the observer node's sampled filter
    uses it. For a continuous plant that filter tends, as the samples come faster, to the
    Kalman-Bucy filter whose measurement noise has the intensity ``Rd`` scaled by the
    sample periods (``h_i h_j Rd_ij / sqrt(h_i h_j)``, h_i the period of output i's
    sensor): that is the design reported. A discrete plant's Rd is used as it is.

    Parameters
    ----------
    vehicle : observer_ros.core.spec.Vehicle
        A vehicle with a kalman observer.

    Returns
    -------
    (p, p) ndarray

    """
    Rd = np.asarray(vehicle.observer.Rd, dtype=float)
    if vehicle.plant.is_discrete:
        return Rd
    _, dt = _noise_per_output(vehicle)
    h = np.sqrt(np.where(np.isfinite(dt), dt, vehicle.sample_time))
    return Rd * h[:, None] * h[None, :]


def design_vehicle(vehicle):
    """
    Design the observer and controller a vehicle file asks for, and check them.

    Parameters
    ----------
    vehicle : observer_ros.core.spec.Vehicle
        The vehicle.

    Returns
    -------
    VehicleDesign

    Raises
    ------
    NotDetectableError
        The observer ('full', 'reduced', 'kalman') cannot converge: an
        unobservable mode is not stable (seed 002 Example 5.15).
    NotControllableError
        Controller poles asked of a plant that is not stabilizable (or n poles
        of an uncontrollable one).
    DesignError
        Unusable specs: unstable or unpaired poles, a given K or L that does not
        stabilize, a failed LQR/Kalman design, ...
    DimensionError
        Wrong number of poles or wrong gain shapes (named by their field).

    """
    plant = vehicle.plant
    A, B, C, D = plant.A, plant.B, plant.C, plant.D
    n, m, p = plant.n, plant.m, plant.p
    discrete = plant.is_discrete
    names = plant.state_names
    obs_spec = vehicle.observer
    ctrl_spec = vehicle.controller
    kind = obs_spec.kind
    messages = []
    obs_check = None

    obs_report = observability_report(A, C, names, discrete)
    ctrb_report = controllability_report(A, B, names, discrete)

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter('always', ObserverDesignWarning)
        reduced = None
        P = None
        if kind in ('full', 'reduced', 'kalman') and not obs_report.detectable:
            bad = '; '.join(md.describe() for md in obs_report.modes if not md.stable)
            raise NotDetectableError(
                f'the plant is not detectable with outputs {list(plant.output_names)}: '
                f'the unobservable {bad} cannot be estimated and does not decay; no '
                f'{kind!r} observer converges (add a sensor on those states)')
        if kind == 'full':
            if (obs_spec.poles is None) == (obs_spec.gain is None):
                raise DesignError('observer: give exactly one of observer.poles and '
                                  'observer.gain')
            if obs_spec.gain is not None:
                L = as_matrix(obs_spec.gain, 'observer.gain', rows=n, cols=p)
            else:
                poles = _poles_from_spec(obs_spec.poles, 'observer.poles', discrete)
                L = _prefixed('observer.poles', observer_gain, A, C, poles, obs_spec.method,
                              discrete, names)
                obs_check = verify_placement(
                    A - L @ C, np.concatenate([poles, obs_report.unobservable_eigenvalues]),
                    'observer.poles', _norm(A) + _norm(L) * _norm(C), discrete)
            observer_poles = np.linalg.eigvals(A - L @ C)
        elif kind == 'reduced':
            if (obs_spec.poles is None) == (obs_spec.gain is None):
                raise DesignError('observer: give exactly one of observer.poles and '
                                  'observer.gain')
            poles = _poles_from_spec(obs_spec.poles, 'observer.poles', discrete)
            gain = None if obs_spec.gain is None else \
                as_matrix(obs_spec.gain, 'observer.gain', rows=n - p, cols=p)
            reduced = _prefixed('observer.poles', reduced_order_observer, A, B, C, D,
                                poles=poles, gain=gain, method=obs_spec.method,
                                discrete=discrete, state_names=names)
            L = reduced.L
            observer_poles = reduced.poles
            if poles is not None:
                obs_check = verify_placement(
                    reduced.F, np.concatenate([poles, unobservable_eigenvalues(reduced.A22,
                                                                               reduced.A12)]),
                    'observer.poles', _norm(reduced.A22) + _norm(L) * _norm(reduced.A12),
                    discrete)
        elif kind == 'open_loop':
            L = np.zeros((n, p))
            observer_poles = np.linalg.eigvals(A)
        elif kind == 'kalman':
            if obs_spec.Qd is None or obs_spec.Rd is None:
                raise DesignError('observer: a kalman observer needs observer.Qd and '
                                  'observer.Rd')
            L, P, observer_poles = kalman_gain(A, C, obs_spec.Qd,
                                               measurement_intensity(vehicle), obs_spec.Bd,
                                               discrete, names)
            verify_stable(A - L @ C, 'the Kalman gain of observer.Qd and observer.Rd',
                          'eig(A - L C)', discrete)
        else:
            raise DesignError(f'observer.type is {kind!r}; expected full, reduced, '
                              'open_loop or kalman')
        if kind in ('full', 'reduced') and obs_spec.gain is not None:
            verify_stable(A - L @ C if reduced is None else reduced.F, 'observer.gain',
                          'eig(A - L C)' if reduced is None else 'eig(F)', discrete)

        # the gains the loop runs: per sampled step and set of outputs, at the sensors' rates
        sampled, sampled_messages = check_sampled_observer(vehicle)
        messages.extend(sampled_messages)
        K, ctrl_check = _controller(ctrl_spec, A, B, n, m, discrete, names,
                                    ctrb_report.uncontrollable_eigenvalues)
    messages.extend(str(w.message) for w in caught
                    if issubclass(w.category, ObserverDesignWarning))
    for w in caught:   # re-emit anything that is not ours
        if not issubclass(w.category, ObserverDesignWarning):
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)

    observer = reduced if reduced is not None else L
    full_L = None if reduced is not None else L
    sigma, dt = _noise_per_output(vehicle)
    noise_gain = None
    if full_L is not None and np.any(np.isfinite(sigma)):
        try:
            noise_gain, _ = observer_noise_gain(A, C, full_L, np.nan_to_num(sigma),
                                                np.nan_to_num(dt, nan=vehicle.sample_time),
                                                discrete)
            noise_gain = np.where(np.isfinite(sigma), noise_gain, np.nan)
        except (ObserverError, np.linalg.LinAlgError, ValueError):
            noise_gain = None
    warn_sigma = np.where(np.isfinite(sigma), sigma, 0.0) if np.any(np.isfinite(sigma)) \
        else None
    messages.extend(design_warnings(A, B, C, K, observer, D, discrete, warn_sigma,
                                    None if discrete else np.nan_to_num(
                                        dt, nan=vehicle.sample_time),
                                    plant.output_names))
    if kind == 'kalman' and obs_spec.poles is not None:
        messages.append('observer.poles is ignored by a kalman observer')

    controller_poles = np.linalg.eigvals(A - B @ K) if K is not None else np.zeros(0, complex)
    Kd = reference = residual = None
    if K is not None:
        # the closed-loop poles are the union of the verified blocks (exact in error
        # coordinates, where the matrix is block triangular); the full 2n matrix's
        # eigenvalues are only compared with them
        ok, _, expected, sep_err, sep_allowed = separation_details(A, B, C, K, observer, D=D)
        cl = expected
        comp = compensator_ss(A, B, C, K, observer, D, plant.dt)
        comp_poles = compensator_poles(A, B, C, K, observer, D)
        Kd = np.zeros((m, n)) if ctrl_spec.Kd is None else \
            as_matrix(ctrl_spec.Kd, 'controller.Kd', rows=m, cols=n)
        reference = np.zeros(n) if ctrl_spec.reference is None else \
            as_vector(ctrl_spec.reference, 'controller.reference', n)
        residual = tracking_residual(A, B, reference, Kd, discrete=discrete)
        if np.any(reference) and not tracking_ok(A, B, reference, Kd, discrete=discrete):
            messages.append(
                'the reference is not tracked without steady-state error: '
                f'(A_d - A + B Kd) x_d = {np.array2string(residual, precision=4)} is not '
                'zero (seed 002 Eq. 5.117); choose Kd or a reachable x_d')
        if ctrl_spec.u_min is None and ctrl_spec.u_max is None and \
                unstable_eigenvalues(A, discrete):
            # the compensator's command bound without limits (core/health.py)
            bound = divergence_envelopes(vehicle, K, reference, Kd)[1].bound
            messages.append(
                'the plant is unstable and controller.u_min/u_max are not given: the '
                "compensator bounds its commands by 100 x |K| applied to the file's state "
                f'scale (+-{np.array2string(bound, precision=3)}), not by the actuator; '
                "give the actuator's limits")
        if not ok:
            messages.append(f'separation check failed: the eigenvalues of the closed-loop '
                            f'matrix differ from eig(A - BK) and the observer poles by '
                            f'{sep_err:.2g}, more than rounding explains ({sep_allowed:.2g})')
    else:
        ok = None
        sep_err = sep_allowed = None
        cl = expected = comp_poles = np.zeros(0, complex)
        comp = None
    return VehicleDesign(
        kind=kind, discrete=discrete, sample_time=plant.dt, state_names=names,
        input_names=plant.input_names, output_names=plant.output_names,
        observability=obs_report, controllability=ctrb_report, L=L, K=K,
        observer_poles=observer_poles, controller_poles=controller_poles,
        closed_loop_poles=cl, expected_poles=expected, separation_ok=ok, compensator=comp,
        compensator_poles=comp_poles, reduced=reduced, P=P, Kd=Kd, reference=reference,
        tracking_residual=residual, noise_gain=noise_gain, warnings=tuple(messages),
        observer_placement=obs_check, controller_placement=ctrl_check,
        separation_error=sep_err, separation_allowed=sep_allowed, sampled=sampled)


def _norm(M):
    return float(np.linalg.norm(M, 2)) if np.size(M) else 0.0


def _controller(spec, A, B, n, m, discrete, names, kept):
    """Return (K or None, PlacementCheck or None); every K returned is verified stable."""
    given = [k for k, v in (('controller.poles', spec.poles), ('controller.K', spec.K),
                            ('controller.lqr_Q', spec.lqr_Q)) if v is not None]
    if len(given) > 1:
        raise DesignError(f'controller: give only one of {", ".join(given)}')
    if spec.poles is not None:
        poles = _poles_from_spec(spec.poles, 'controller.poles', discrete)
        K = _prefixed('controller.poles', controller_gain, A, B, poles, 'auto', discrete,
                      names)
        return K, verify_placement(A - B @ K, np.concatenate([poles, kept]),
                                   'controller.poles', _norm(A) + _norm(B) * _norm(K),
                                   discrete)
    if spec.K is not None:
        K = as_matrix(spec.K, 'controller.K', rows=m, cols=n)
        verify_stable(A - B @ K, 'controller.K', 'eig(A - B K)', discrete)
        return K, None
    if spec.lqr_Q is not None or spec.lqr_R is not None:
        if spec.lqr_Q is None or spec.lqr_R is None:
            raise DesignError('controller: an LQR design needs both controller.lqr_Q and '
                              'controller.lqr_R')
        Q = as_matrix(spec.lqr_Q, 'controller.lqr_Q', rows=n, cols=n)
        R = as_matrix(spec.lqr_R, 'controller.lqr_R', rows=m, cols=m)
        K = lqr_gain(A, B, Q, R, discrete)[0]
        verify_stable(A - B @ K, 'the LQR gain of controller.lqr_Q and controller.lqr_R',
                      'eig(A - B K)', discrete)
        return K, None
    return None, None
