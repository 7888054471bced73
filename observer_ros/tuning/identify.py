# observer_ros.tuning.identify: noise covariances of a vehicle from bags (ALS).
"""
Identify a vehicle's process and measurement noise covariances from bags.

The bags' outputs and commands at their steps (:mod:`observer_ros.tuning.sampled`), the
innovations of a stable reference predictor (the vehicle's own observer), the transient
dropped, and autocovariance least squares (:mod:`observer_ros.core.als`), pooled over the
bags. Data with every output at every sample and equal steps take the time-invariant
model; outputs missing at some samples or jittered stamps take the filter run at the
actual stamps and the time-varying model (:mod:`observer_ros.core.als_ltv`).

Each later pass (:data:`PASSES` in all by default) repeats it with the Kalman predictor
of the previous pass's covariances as the reference (Rajamani & Rawlings 2009 recommend
a reference close to the optimal filter), each variance at least its standard error
(:func:`filter_Q`), started from the reference's prediction at the end of the transient
corrected by the initial state that best explains its first innovations
(:func:`~observer_ros.core.als_ltv.fit_initial_state`: the Kalman filter's slowest mode
may take longer than the bag to forget the reference's error). The lags are chosen from
the plant for each pass unless given.

Every identified entry has a standard error; an entry the data do not determine (its +-2
sigma reaching zero) is named with the remedies. A measurement noise that comes out
non-positive or not told from zero, or a fit far off (chi2/dof above :data:`POOR_FIT`),
is diagnosed: the other noise structures are fitted to the same autocovariances and the
likely cause named; the identification is refused when another structure does far
better. The whiteness of the innovations before (reference) and after (Kalman filter of
the identified covariances) is judged by the test of the node and ``observer-eval``
(:mod:`observer_ros.core.whiteness`).

"""

from dataclasses import dataclass, field
from functools import cached_property
import math
from typing import Dict, List

import numpy as np

from .sampled import (noise_input, present_patterns, reference_gain, sampled_data,
                      sampled_model, unit_kalman_gain, unstable_pattern)
from .undetermined import minimax_Q
from ..bag.errors import BagToolError
from ..bag.reader import read_recording
from ..core.als import (ALSError, choose_lags, DEFAULT_LAGS, identify_noise,
                        kalman_predictor_gain, predictor_blocks, predictor_innovations,
                        process_noise_map)
from ..core.als_ltv import event_predictor, fit_initial_state, LTVModel, StepModel
from ..core.als_stats import DECAYS
from ..core.autocovariance import LaggedSums
from ..core.innovation import ALPHA, WINDOW
from ..core.whiteness import WindowWhiteness
from ..evaluation.cli import resolve_vehicle
from ..evaluation.results import jsonable

__all__ = ['BLOCK', 'TRANSIENT_DECAY', 'RATE_TOLERANCE', 'POOR_FIT', 'Identification',
           'identify', 'filter_Q', 'FILE_FLOOR', 'PASSES', 'tuned_Q',
           'uncertain_entries']

#: Samples dropped at the start of each bag: until the reference predictor's slowest mode
#: has decayed to this fraction.
TRANSIENT_DECAY = 1e-6
#: Innovations are computed and summed this many samples at a time.
BLOCK = 1 << 16
#: Bags identified together: their median steps within this fraction of the first's.
RATE_TOLERANCE = 0.05
#: A fit whose chi2 per degree of freedom is above this is poor: a warning.
POOR_FIT = 2.0
#: Most innovations a later pass fits its start's transient to.
FIT_START_MAX = 50_000
#: The tuned vehicle file's Kalman filter has no variance below this many standard errors.
FILE_FLOOR = 0.5
#: ALS passes by default: the reference, then twice the Kalman filter of the estimate.
PASSES = 3


@dataclass
class Identification:
    """What :func:`identify` found (see the module)."""

    vehicle: object
    bags: List[str]
    dt: float
    G: np.ndarray
    noise_names: List[str]
    reference: str
    passes: list                  # ALSResult per pass; the last is the answer
    samples: Dict[str, int]
    burn: int
    whiteness_before: Dict[str, dict]
    whiteness_after: Dict[str, dict]
    warnings: List[str] = field(default_factory=list)
    irregular: Dict[str, dict] = field(default_factory=dict)   # bag -> missing, steps
    lags_given: bool = False
    tuned_Q: np.ndarray = None      # the Q the tuned file's filter is given (:func:`tuned_Q`)
    choice: object = None           # undetermined.Choice of the entries chosen, or None

    @property
    def file_Q(self):
        """Return the Q of the tuned file's Kalman filter."""
        return self.tuned_Q if self.tuned_Q is not None else filter_Q(self.result, FILE_FLOOR)

    @property
    def result(self):
        """Return the last pass's ALSResult."""
        return self.passes[-1]

    def to_dict(self):
        """Return JSON-ready data."""
        r = self.result
        return jsonable({
            'bags': self.bags, 'vehicle': self.vehicle.name, 'dt': self.dt,
            'noise_input': self.G.tolist(), 'noise_names': self.noise_names,
            'reference': self.reference, 'samples': self.samples, 'burn': self.burn,
            'Qd': r.Q.tolist(), 'Rd': r.R.tolist(), 'Qd_std': r.Q_std.tolist(),
            'Rd_std': r.R_std.tolist(), 'condition': r.condition,
            'Qd_tuned': np.asarray(self.file_Q).tolist(),
            'undetermined_choice': None if self.choice is None else self.choice.to_dict(),
            'entries': [{'kind': k, 'name': n, 'value': v, 'std': s}
                        for k, n, v, s in r.entries()],
            'passes': [p.to_dict() for p in self.passes], 'irregular': self.irregular,
            'whiteness_reference': self.whiteness_before,
            'whiteness_tuned_kalman': self.whiteness_after, 'warnings': self.warnings})


class _RMS:
    """Running mean square of each column over its finite values."""

    def __init__(self, p):
        self.sq = np.zeros(p)
        self.n = np.zeros(p)

    def add(self, block):
        finite = np.isfinite(block)
        self.sq += np.sum(np.where(finite, block, 0.0) ** 2, axis=0)
        self.n += np.count_nonzero(finite, axis=0)


def _whiteness(white, rms, names):
    """Return the verdict of each output (the test of the node and observer-eval)."""
    out = {}
    for j, (name, v) in enumerate(zip(names, white.verdicts())):
        v['samples'] = int(rms.n[j])
        v['residual_rms'] = math.sqrt(rms.sq[j] / rms.n[j]) if rms.n[j] else math.nan
        out[name] = v
    return out


class _Bag:
    """
    One bag's data as the passes use them.

    The stamps in seconds, ``y - D u`` and the measured steps are made on first use
    (only data with gaps or jitter need them: regular data run on ``y`` itself).

    """

    def __init__(self, name, s, D, drop):
        self.name = name
        self.s = s
        self._D = D
        self.count = int(s.measured)            # steps with a measurement
        self.drop = int(min(drop, self.count))
        # the step (incl. command-only steps) where the summed innovations start
        if s.regular:
            self.first = self.drop
        else:
            self.first = int(self.measured[self.drop]) if self.drop < self.count \
                else s.y.shape[0]

    @cached_property
    def t(self):
        """Return the steps' stamps in seconds from the first."""
        return self.s.t

    @cached_property
    def z(self):
        """Return the outputs less the inputs' direct feedthrough, ``y - D u_meas``."""
        D = self._D
        return self.s.y - self.s.u_meas @ D.T if D.size else self.s.y.copy()

    @cached_property
    def measured(self):
        """Return the steps with a measurement."""
        return np.flatnonzero(np.isfinite(self.s.y).any(axis=1))

    def sequence(self):
        """Return (t, present, start) of its measured steps for the time-varying model."""
        m = self.measured
        return self.t[m], np.isfinite(self.s.y[m]), self.drop


def _structures(vehicle, G, input_noise, states):
    """Return the other noise structures to try: (what, option, G, names)."""
    plant = vehicle.plant
    out = []
    candidates = [('every state', f'--states {",".join(plant.state_names)}',
                   *noise_input(vehicle, list(plant.state_names)))]
    if plant.m:
        candidates.append(('the inputs (a force or torque disturbance)', '--input-noise',
                           *noise_input(vehicle, inputs=True)))
    if vehicle.observer.Bd is not None:
        candidates.append(("observer.Bd's columns", 'neither --input-noise nor --states',
                           *noise_input(vehicle)))
    for what, option, Galt, names in candidates:
        if Galt.shape == G.shape and np.allclose(Galt, G):
            continue
        out.append((what, option, Galt, names))
    return out


def _describe(G, vehicle, input_noise, states):
    if input_noise:
        return 'the inputs (--input-noise)'
    if states:
        return f'the states {", ".join(states)} (--states)'
    if vehicle.observer.Bd is not None:
        return "observer.Bd's columns"
    return 'every state'


def _fmt(x):
    return f'{x:.3g}'


def _determined(res):
    """Tell whether every measurement noise variance is positive beyond two standard errors."""
    rd, rs = np.diag(res.R), np.diag(res.R_std)
    return bool(np.all(rd > 2.0 * np.where(np.isfinite(rs), rs, np.inf)))


def _diagnose(res, fits, current, outputs):
    """
    Return the refusal of an R that is not positive (or not told from zero), or None.

    The other noise structures are fitted to the same autocovariances; one whose R is
    positive beyond two standard errors and whose fit is not worse names the likely
    cause. None: R is positive but undetermined and no other structure does better (the
    identification goes on, with its warnings).

    """
    rd, rs = np.diag(res.R), np.diag(res.R_std)
    positive = bool(np.all(rd > 0.0)) and np.min(np.linalg.eigvalsh(res.R)) > 0.0
    ratio = res.residual / max(res.dof, 1)
    bad = [f'{outputs[i]} {_fmt(rd[i])} +- {_fmt(rs[i])}' for i in range(rd.size)
           if not rd[i] > 2.0 * rs[i]]
    lines = [f'the identified measurement noise covariance R is '
             f'{"not told from zero" if positive else "not positive definite"} '
             f'({"; ".join(bad)}): with process noise on {current}, the autocovariances '
             'leave no room for measurement noise'
             + ('' if positive else ', and a Kalman filter cannot be designed') + '.',
             f'fit with process noise on {current}: chi2/dof {_fmt(ratio)}']
    good = []
    for what, option, alt in fits:
        if isinstance(alt, str):
            lines.append(f'with process noise on {what}: {alt}')
            continue
        r, sd = np.diag(alt.R), np.diag(alt.R_std)
        fit = alt.residual / max(alt.dof, 1)
        lines.append(f'with process noise on {what}: R diag '
                     f'{", ".join(f"{_fmt(x)} +- {_fmt(y)}" for x, y in zip(r, sd))}, '
                     f'chi2/dof {_fmt(fit)}')
        if _determined(alt) and fit <= 1.1 * ratio:
            good.append((fit, what, option))
    if good:
        fit, what, option = min(good)
        lines.append(f'likely cause: the noise structure. The process noise is not only on '
                     f'{current}; with noise on {what} R is positive and the fit is '
                     f'{"better" if fit < ratio else "as good"}: identify with {option}')
    elif positive:
        return None
    else:
        lines.append('likely cause: no noise structure tried gives a positive R: the outputs '
                     'show no measurement noise beyond what the process noise explains (a '
                     "filtered or quantised sensor), or the model (A, C, the sensors' "
                     'outputs) differs from the plant')
    return '\n'.join(lines)


def _missing_text(runs):
    """Return how much of each output is missing, for a refusal ('' when nothing is)."""
    gone = {}
    for r in runs:
        for name, frac in r.s.missing.items():
            gone.setdefault(name, []).append(frac)
    parts = [f'{name} {max(v):.1%}' for name, v in gone.items() if max(v) > 0.0]
    return f' (measurements missing at some samples: {", ".join(parts)})' if parts else ''


def filter_Q(res, floor=1.0):
    """
    Return the Q a Kalman filter is designed with: no variance below ``floor`` sigma.

    A variance the data do not tell from zero (its estimate below ``floor`` times its
    standard error) is raised to that: a filter given zero stops following that noise for
    good (its slowest mode then forgets an error only at the plant's own rate). The later
    passes' references take each variance at least at its standard error (``floor`` 1: a
    reference that follows any noise the data cannot rule out keeps the next pass's
    standard errors honest); the tuned vehicle file at least at half of it
    (:data:`FILE_FLOOR`: an estimate at zero raised no further than it need be, since a
    filter that overrates a noise's intensity loses more than one that underrates it by as
    much: over seeds 1-10 of ``benchmarks/tune_bars.py``'s submarine, theta's noise raised
    to one standard error instead, one run's RMSE was above 1.05 times the true-covariance
    filter's on 4 seeds against 3, median 1.017 against 1.0005). The identified values and
    their standard errors are reported as they are.

    """
    Q = np.array(res.Q, dtype=float)
    sd = np.diag(res.Q_std) if res.Q_std is not None else np.zeros(Q.shape[0])
    low = float(floor) * sd
    raise_ = np.where(np.isfinite(low) & (low > np.diag(Q)), low - np.diag(Q), 0.0)
    return Q + np.diag(raise_)


def tuned_Q(res, Ad, C, F):
    """
    Return ``(Q, choice)``: the Q the tuned file's Kalman filter is given.

    A diagonal Q with entries the data do not determine (+-2 sigma reaching zero): each
    such entry at the value in its +-2 sigma whose filter's excess mean square error over
    the filter that knew the true value is least at worst
    (:func:`~observer_ros.tuning.undetermined.minimax_Q`, on the sampled model ``Ad``,
    ``C`` and the noise map ``F``), ``choice`` saying which and why. Otherwise (or a full
    Q) :func:`filter_Q` at :data:`FILE_FLOOR` and None.

    """
    if not res.full and res.Q_std is not None:
        basis = [F(np.diag(e)) for e in np.eye(res.Q.shape[0])]
        choice = minimax_Q(Ad, C, basis, res.Q, res.Q_std, res.R)
        if choice.entries:
            return choice.Q, choice
    return filter_Q(res, FILE_FLOOR), None


def _poor_fit(res, fits, current):
    """
    Return the text of a poor fit, and whether another noise structure fits far better.

    Far better: its chi2/dof under half this one's and its R positive beyond two
    standard errors (then the identification is refused: its numbers would mislead).

    """
    ratio = res.residual / res.dof
    text = (f'the identified model fits the autocovariances poorly (chi2/dof {_fmt(ratio)} '
            f'over {res.dof}, about 1 when it fits)')
    better = sorted((alt.residual / max(alt.dof, 1), what, option) for what, option, alt in fits
                    if not isinstance(alt, str) and _determined(alt) and
                    alt.residual / max(alt.dof, 1) < 0.5 * ratio)
    if better:
        fit, what, option = better[0]
        return (text + f' with process noise on {current}; with process noise on {what} it '
                f'is {_fmt(fit)}: likely cause: the noise structure (the process noise is not '
                f'only on {current}): identify with {option}'), True
    return (text + ': no other noise structure fits better; the model (A, C, the sensors) '
            'may differ from the plant'), False


def uncertain_entries(res, lags_given, samples, choice=None):
    """
    Return a warning for each entry whose +-2 sigma reaches zero, with the remedies.

    ``choice`` (:func:`tuned_Q`'s) says what the tuned filter is given for such an entry.

    """
    out = []
    entries = res.entries()
    corr = res.correlation() if res.cov is not None and np.all(np.isfinite(res.cov)) \
        else None
    for u, (kind, name, value, std) in enumerate(entries):
        if not (2.0 * std >= abs(value) or not value > 0.0):
            continue
        what = 'Qd' if kind == 'Q' else 'Rd'
        remedies = []
        want = DECAYS * res.decay
        if want > res.lags:
            if lags_given and res.auto_lags > res.lags:
                remedies.append(f'more lags (--lags {res.auto_lags}: the slowest mode the '
                                f'noise excites takes {res.decay} lags to decay; {res.lags} '
                                'used)')
            else:
                remedies.append(f'more lags ({want}: {DECAYS} times the {res.decay} the '
                                f'slowest mode takes to decay; {res.lags} is the most '
                                f'{samples} samples allow: a longer bag)')
        if value > 0.0 and math.isfinite(std):
            factor = (4.0 * std / value) ** 2
            remedies.append(f'a longer bag (sigma falls as 1/sqrt(samples): about '
                            f'{_fmt(factor)}x the {samples} samples for +-2 sigma within half '
                            'the value)')
        else:
            remedies.append('a longer bag (sigma falls as 1/sqrt(samples)), or this noise '
                            'may be absent')
        if corr is not None:
            row = np.abs(np.nan_to_num(corr[u]))
            row[u] = 0.0
            k = int(np.argmax(row))
            if row[k] > 0.8:
                remedies.append(f'fewer unknowns (it trades off with {entries[k][1]}: '
                                f'correlation {_fmt(corr[u, k])}; estimate fewer noise '
                                'entries, e.g. --states or --input-noise)')
        chosen = [j for j, i in enumerate(choice.entries) if res.labels[u] == ('Q', i, i)] \
            if choice is not None else []
        raised = kind == 'Q' and FILE_FLOOR * std > value and \
            res.labels[u][1] == res.labels[u][2]
        if chosen:
            j = chosen[0]
            i = choice.entries[j]
            written = (f'; the tuned Kalman filter is given {_fmt(choice.Q[i, i])}, the value '
                       f'in its +-2 sigma ({_fmt(choice.low[j])} .. {_fmt(choice.high[j])}) '
                       'whose excess error over the filter that knew the true value is least '
                       'at worst (its predicted RMS error at most '
                       f"{choice.worst:.3f} times that filter's there)")
        elif raised:
            written = (f'; the tuned Kalman filter is given half its standard error, '
                       f'{_fmt(FILE_FLOOR * std)}, not zero')
        else:
            written = ''
        out.append(f'{what} {name} = {_fmt(value)} +- {_fmt(std)} (1 sigma): +-2 sigma '
                   f'reaches zero, so these data do not determine it{written}; remedies: '
                   + '; '.join(remedies))
    return out


def _masked_reference(vehicle, Ad, C, dt, G, Lp, reference, data, warn):
    """
    Return the reference for bags with outputs missing at some samples, and what it is.

    The reference runs at the bag's samples with the outputs present there. A gain
    whose columns offset one another (observer poles placed close together: three
    masses in a row with two position sensors and poles at -3..-3.5 amplify the error by
    1.39 at each sample with the first sensor lost) is unstable with an output missing;
    the innovations then do not follow the fitted model (chi2/dof 2.7e4, R refused). Such
    a reference is replaced by the Kalman predictor of unit noise when that is stable at
    every pattern of outputs present (or less unstable), and a warning says so.

    """
    patterns = present_patterns(data)
    bad = unstable_pattern(Ad, C, Lp, patterns)
    if bad is None:
        return Lp, reference
    names = list(vehicle.plant.output_names)
    only = ', '.join(n for n, keep in zip(names, bad[1]) if keep)
    Lk = unit_kalman_gain(vehicle, Ad, dt, G)
    other = unstable_pattern(Ad, C, Lk, patterns)
    text = (f'the reference ({reference}) is unstable at samples with only {only} present '
            f"(|z| {bad[0]:.3g} there: its gain's columns offset one another, e.g. observer "
            'poles placed close together)')
    if other is not None and other[0] >= bad[0]:
        warn.append(text + '; its innovations may not fit the model: give the vehicle '
                    'observer poles further apart, or a kalman observer')
        return Lp, reference
    warn.append(text + '; the first pass takes a Kalman predictor of unit noise instead')
    return Lk, f'a Kalman predictor of unit noise ({reference} is unstable with {only} alone)'


def identify(bags, vehicle, namespace=None, lags=DEFAULT_LAGS, full=False, states=None,
             burn=None, passes=PASSES, input_noise=False, block=BLOCK, recordings=None):
    """
    Identify the process and measurement noise covariances from bags (ALS).

    Parameters
    ----------
    bags : sequence of str or Path
        Bags of the same vehicle at about the same sample rate.
    vehicle : str or Path or Vehicle
        The vehicle (its model, sensors and observer, the reference).
    namespace : str, optional
        The vehicle's namespace in the bags (detected when None).
    lags : int, optional
        Autocovariance lags (default: chosen from the plant for each pass).
    full : bool
        Full symmetric covariances (default diagonal).
    states : sequence of str, optional
        Process noise on these states (default ``observer.Bd``, else every state).
    burn : int, optional
        Samples dropped at the start of each bag (default: the reference's transient).
    passes : int
        ALS passes; each after the first uses the previous pass's Kalman predictor.
    input_noise : bool
        Process noise on the inputs (G = B) instead.
    block : int
        Innovations computed this many at a time (never held whole).
    recordings : dict, optional
        Filled with each bag's recording as read (``{str(bag): Recording}``, in memory),
        for a gain search that follows to replay without reading the bags again;
        by default only the sampled arrays are kept.

    Returns
    -------
    result : Identification

    Raises
    ------
    BagToolError
        A bag cannot be used (see :func:`~observer_ros.tuning.sampled.sampled_data`).
    ALSError
        The noise is not identifiable with this model and these data, or the measurement
        noise comes out non-positive (the message names the likely cause).

    """
    vehicle = resolve_vehicle(vehicle)
    plant = vehicle.plant
    data, warn = [], []
    for bag in bags:
        rec = read_recording(bag, vehicle, namespace)
        s = sampled_data(rec, vehicle)
        warn += [f'{bag}: {w}' for w in rec.warnings + s.warnings]
        data.append(s)
        if recordings is not None:
            recordings[str(bag)] = rec
    del rec                 # only the sampled arrays are kept (and ``recordings``)
    dt = data[0].dt
    for bag, s in zip(bags, data):
        if abs(s.dt / dt - 1.0) > RATE_TOLERANCE:
            raise BagToolError(f'{bag}: median step {s.dt:.6g} s differs from {dt:.6g} s of '
                               f'{bags[0]}: identify bags of one rate together')
    regular = all(s.regular and s.dt == dt for s in data)
    Ad, Bd = sampled_model(vehicle, dt)
    C, D = np.asarray(plant.C, float), np.asarray(plant.D, float)
    A, B = np.asarray(plant.A, float), np.asarray(plant.B, float)
    G, noise_names = noise_input(vehicle, states, input_noise)
    F = process_noise_map(plant.A, G, dt, plant.is_discrete)
    Lp, reference = reference_gain(vehicle, Ad, dt, G)
    if not regular:
        Lp, reference = _masked_reference(vehicle, Ad, C, dt, G, Lp, reference, data, warn)
    rho = float(np.max(np.abs(np.linalg.eigvals(Ad - Lp @ C))))
    drop = max(10, int(math.ceil(math.log(TRANSIENT_DECAY) / math.log(rho)))) \
        if 0.0 < rho < 1.0 else 10
    if burn is not None:
        drop = int(burn)
    need = 10 * (lags if lags is not None else 10)
    short = [str(b) for b, s in zip(bags, data) if s.measured - drop < need]
    if short:
        raise BagToolError(f'{short[0]}: fewer than {need} samples after dropping the '
                           f'first {drop} (the transient); record longer or lower --burn')
    names = (noise_names, list(plant.output_names))
    outputs = list(plant.output_names)
    p = len(outputs)
    runs = [_Bag(str(b), s, D, drop) for b, s in zip(bags, data)]
    irregular = {r.name: {'missing': r.s.missing, 'step_range': list(r.s.steps),
                          'measured_steps': r.s.measured, 'steps': int(r.s.y.shape[0])}
                 for r in runs}
    samples = sum(r.count - r.drop for r in runs)

    def model(gain):
        return StepModel(A, B, C, gain, dt, plant.is_discrete)

    # the reference's prediction at the end of the transient starts every later pass
    if regular:
        starts = [predictor_blocks(Ad, Bd, C, D, Lp, r.s.y[:r.first], r.s.u[:r.first],
                                   r.s.u_meas[:r.first], block=block) for r in runs]
    else:
        ref = model(Lp)
        starts = [event_predictor(ref, r.t[:r.first], r.z[:r.first], r.s.u[:r.first])
                  for r in runs]

    def fitted_starts(gain):
        """Return each bag's start for ``gain``: the reference's, its transient fitted."""
        if gain is Lp:
            return starts
        Phi = Ad - gain @ C
        rho_k = float(np.max(np.abs(np.linalg.eigvals(Phi))))
        steps = FIT_START_MAX if not 0.0 < rho_k < 1.0 else \
            int(min(FIT_START_MAX, math.ceil(math.log(1e-3) / math.log(rho_k))))
        out = []
        for r, x0 in zip(runs, starts):
            a = r.first
            if regular:
                T = min(steps, r.s.y.shape[0] - a)
                e = predictor_innovations(Ad, Bd, C, D, gain, r.s.y[a:a + T], r.s.u[a:a + T],
                                          r.s.u_meas[a:a + T], x0=x0)
                psi = np.empty((T, p, Ad.shape[0]))
                left = C.copy()
                for k in range(T):
                    psi[k] = left
                    left = left @ Phi
            else:
                end = int(r.measured[min(r.measured.size - 1, r.drop + steps)]) + 1
                _, psi, e = event_predictor(model(gain), r.t[a:end], r.z[a:end],
                                            r.s.u[a:end], x0=x0, free=steps)
            out.append(np.asarray(x0, float) + fit_initial_state(psi, e))
        return out

    def run(gain, nlags, white=False):
        """Run the predictor of ``gain`` after the transient; return its sums."""
        sums = LaggedSums(p, nlags)
        extra = [WindowWhiteness(p, WINDOW, ALPHA), _RMS(p)] if white else []
        if not regular:
            sm = model(gain)
        for r, x0 in zip(runs, fitted_starts(gain)):
            sums.new_sequence()
            a = r.first
            if regular:
                predictor_blocks(Ad, Bd, C, D, gain, r.s.y[a:], r.s.u[a:], r.s.u_meas[a:],
                                 x0=x0, sinks=[sums] + extra, block=block)
            else:
                event_predictor(sm, r.t[a:], r.z[a:], r.s.u[a:], x0=x0,
                                sinks=[sums] + extra, block=min(block, 1 << 14))
        return sums, extra

    results = []
    gain = Lp
    before = None
    current = _describe(G, vehicle, input_noise, states)
    for i in range(max(1, int(passes))):
        auto, decay = choose_lags(Ad, C, gain, F, G.shape[1], samples, full)
        nlags = int(lags) if lags is not None else auto
        sums, extra = run(gain, nlags, white=i == 0)
        if i == 0:
            before = _whiteness(*extra, outputs)
        ltv = None if regular else LTVModel(model(gain), G, [r.sequence() for r in runs])
        try:
            res = identify_noise(sums, Ad, C, gain, F, G.shape[1], nlags, full, names, ltv)
        except ALSError as err:
            raise ALSError(f'{err}{_missing_text(runs)}') from None
        res.decay, res.auto_lags = decay, auto
        results.append(res)

        def alternatives():
            """Fit the other noise structures to these autocovariances."""
            fits = []
            for what, option, Galt, alt_names in _structures(vehicle, G, input_noise, states):
                Falt = process_noise_map(plant.A, Galt, dt, plant.is_discrete)
                alt_ltv = None if regular else LTVModel(model(gain), Galt,
                                                        [r.sequence() for r in runs])
                try:
                    alt = identify_noise(sums, Ad, C, gain, Falt, Galt.shape[1], nlags, full,
                                         (alt_names, outputs), alt_ltv)
                except ALSError as err:
                    alt = f'not identifiable ({err})'
                fits.append((what, option, alt))
            return fits
        if not _determined(res) or np.min(np.linalg.eigvalsh(res.R)) <= 0.0:
            refusal = _diagnose(res, alternatives(), current, outputs)
            if refusal is not None:
                raise ALSError(refusal)
        # a poor fit is judged on the last pass: an earlier pass's reference may be far
        # from the optimal filter (three masses in a row, observer poles -1..-4: chi2/dof
        # 9.8 with the right structure on the first pass, a good fit on the last)
        if i == max(1, int(passes)) - 1 and res.dof > 0 and res.residual / res.dof > POOR_FIT:
            text, better = _poor_fit(res, alternatives(), current)
            if better:
                raise ALSError(text)
            warn.append(text)
        gain = kalman_predictor_gain(Ad, C, F(filter_Q(res)), res.R)
    _, extra = run(gain, 1, white=True)
    after = _whiteness(*extra, outputs)
    final = results[-1]
    Qf, choice = tuned_Q(final, Ad, C, F)
    warn += uncertain_entries(final, lags is not None, samples, choice)
    return Identification(vehicle, [str(b) for b in bags], dt, G, noise_names, reference,
                          results, {r.name: r.count for r in runs},
                          drop, before, after, warn, irregular, lags is not None, Qf, choice)
