# observer_ros.core.innovation: are a sensor's residuals consistent with the model?
"""
Innovation health per sensor: normalised innovation squared and whiteness, windowed.

Each residual ``r = y - C x_prior - D u`` of a sensor is whitened by its covariance S,
``e = L^-1 r`` with ``S = L L^T``: for a Kalman filter ``S = C P C^T + R`` (the
predicted covariance of the residual); for the other observers the sensor's noise alone,
``S = diag(noise_std^2)``, which leaves out the estimation error and so under-states the
residual. Over the last ``window`` residuals of the sensor:

- the NIS ``|e|^2`` has mean p (the sensor's number of outputs) when the model holds;
  the window's mean is compared with the chi-square bounds of ``window * p`` degrees of
  freedom: above the upper one the residuals are too large (a bias, a wrong sign or
  frame, noise_std too small), below the lower one too small (noise_std too large,
  reported but not a warning);
- each component of e is tested for whiteness by the one test of
  :mod:`observer_ros.core.whiteness` (the cumulative periodogram of the window): a Kalman
  filter's innovations are white when its model is right; a coloured residual means a
  model error, a wrong latency or a frame mismatch.

A window of a Kalman filter is *inconsistent* when its NIS mean is above the upper bound
or a component is not white; the two tests share the level ``alpha`` so that a window of
a consistent filter (Gaussian residuals, right S) is flagged with probability exactly
alpha: the NIS at ``a = 1 - sqrt(1 - alpha)`` (upper tail), the components' whiteness at
``a`` together (each at ``1 - (1 - a)^(1/p)``; the periodogram's shape is independent of
the NIS of Gaussian residuals). For the other observers (S without the estimation error)
a window is inconsistent when its NIS mean is above :data:`OTHER_MARGIN` times the upper
bound, a residual several times the sensor's noise. The node reports its last window on
/diagnostics. A whole run (:func:`sequence_health`, ``observer-eval``) is judged in
consecutive windows by :func:`observer_ros.core.whiteness.run_rule`: inconsistent when
more windows are flagged than a consistent filter's would be but with probability
:data:`~observer_ros.core.whiteness.RUN_LEVEL`, or when one window is far outside (a short
fault); the exact false-alarm probability of that verdict is reported with it.

The initial transient is not judged (:func:`transient_time`): while the estimate of an
observer other than Kalman converges, the estimation error dominates its residuals (the
submarine's 30 deg initial error gives a gyro NIS of 52 in its first window, against about
1 once converged), and S leaves that error out. Its residuals are judged from one settling
time of the observer's slowest pole after the estimator starts (or restarts). A Kalman
filter's S = C P C^T + R carries the estimation error through P: judged from the start.

"""

from dataclasses import dataclass
import math

import numpy as np
import scipy.linalg
from scipy.special import chdtrc, chdtri
from scipy.stats import kstwo

from .health import settling_time
from .whiteness import (component_level, critical_distance, periodogram_statistic,
                        RUN_LEVEL, run_rule, run_verdict)

__all__ = ['InnovationMonitor', 'SensorHealth', 'whiten', 'ljung_box', 'ljung_box_acf',
           'ljung_box_of_products',
           'nis_bounds', 'sequence_health', 'sequence_health_blocks', 'transient_time',
           'WINDOW', 'LAGS', 'ALPHA', 'OTHER_MARGIN']

#: Residuals per sensor in a window.
WINDOW = 50

#: Largest lag of :func:`ljung_box` (a descriptive figure; the verdicts use
#: :mod:`observer_ros.core.whiteness`).
LAGS = 5

#: Level of a window's verdict: a window of a consistent Kalman filter is flagged with
#: this probability (the NIS and the whiteness tests together).
ALPHA = 1e-3

#: Observers other than Kalman whiten by the sensor noise only: their NIS is flagged only
#: above this many times the chi-square bound.
OTHER_MARGIN = 10.0


def transient_time(poles, dt, discrete=False, kalman=False):
    """
    Return the seconds after an estimator starts during which its residuals are not judged.

    Parameters
    ----------
    poles : array_like of complex
        The observer's poles (its error dynamics): s-plane, or z-plane if ``discrete``.
    dt : float
        The sample time, s (for discrete poles).
    discrete : bool
        Whether the poles are discrete.
    kalman : bool
        A Kalman filter (its S carries the estimation error): 0.

    Returns
    -------
    seconds : float
        The settling time of the slowest pole (:func:`observer_ros.core.health.settling_time`,
        its decay to 2 %); ``inf`` when a pole does not decay (never judged: the estimate
        never converges, so its residuals say nothing about the sensor).

    """
    return 0.0 if kalman else float(settling_time(poles, dt, discrete))


def whiten(residual, S):
    """
    Return ``e = L^-1 r`` with ``S = L L^T`` (Cholesky): unit covariance if r's is S.

    Parameters
    ----------
    residual : (p,) array_like
        Residual of one message.
    S : (p, p) array_like
        Its covariance, positive definite.

    Returns
    -------
    e : (p,) ndarray
        ``|e|^2`` is the NIS ``r^T S^-1 r``.

    """
    r = np.asarray(residual, dtype=float).reshape(-1)
    L = scipy.linalg.cholesky(np.atleast_2d(np.asarray(S, dtype=float)), lower=True)
    return scipy.linalg.solve_triangular(L, r, lower=True)


def nis_bounds(samples, dim, alpha=ALPHA):
    """
    Return the two-sided bounds of a window mean of NIS for a consistent sensor.

    Parameters
    ----------
    samples : int
        Residuals in the window.
    dim : int
        Outputs per residual (p).
    alpha : float
        Level: a consistent sensor's mean falls outside with probability alpha.

    Returns
    -------
    low, high : float
        ``chi2(samples * dim)`` quantiles ``alpha / 2`` and ``1 - alpha / 2``, divided by
        samples.

    """
    k = samples * dim
    return float(chdtri(k, 1.0 - alpha / 2.0)) / samples, float(chdtri(k, alpha / 2.0)) / samples


def ljung_box(x, lags=LAGS):
    """
    Ljung-Box statistic of a sequence (mean removed) and its p-value.

    The sequence x and the largest lag (at most N // 4) are those of
    :func:`ljung_box_acf`.

    Returns
    -------
    q : float
        ``N (N + 2) sum_{j<=k} rho_j^2 / (N - j)``; NaN when it is undefined.
    p : float
        Chi-square survival of q with k degrees of freedom (small: not white).

    """
    q, p, _ = ljung_box_acf(x, lags)
    return q, p


def ljung_box_acf(x, lags=LAGS):
    """
    Return :func:`ljung_box`'s q and p and the autocorrelations they come from.

    Parameters
    ----------
    x : (N,) array_like
        The sequence.
    lags : int
        Largest lag k (at most N // 4).

    Returns
    -------
    q, p : float
        The statistic and its chi-square p-value, as :func:`ljung_box` (NaN when
        undefined: fewer than 4 samples, a constant).
    acf : (k,) ndarray
        ``rho_j``, j = 1..k, mean removed, normalised by lag 0; empty when undefined.

    """
    x = np.asarray(x, dtype=float)
    N = x.size
    k = min(int(lags), N // 4)
    d = x - x.mean() if N else x
    denom = float(d @ d)
    if k < 1 or not denom > 0.0 or not math.isfinite(denom):
        return math.nan, math.nan, np.zeros(0)
    return ljung_box_of_products([float(d[:-j] @ d[j:]) for j in range(1, k + 1)], denom, N)


def ljung_box_of_products(lagged, denom, N):
    """
    Return :func:`ljung_box_acf`'s q, p and acf from the sums of products it divides.

    Parameters
    ----------
    lagged : (k,) array_like
        ``sum_t d_t d_{t+j}``, j = 1..k, of the sequence d with its mean removed (summed
        however the caller can, e.g. a block at a time).
    denom : float
        ``sum_t d_t^2``.
    N : int
        The length of the sequence.

    """
    k = len(lagged)
    if k < 1 or not denom > 0.0 or not math.isfinite(denom):
        return math.nan, math.nan, np.zeros(0)
    rho = np.asarray(lagged, dtype=float) / denom
    q = float(N * (N + 2) * np.sum(rho ** 2 / (N - np.arange(1, k + 1))))
    return q, float(chdtrc(k, q)), rho


@dataclass
class SensorHealth:
    """The health of one sensor's residuals over its last window."""

    name: str
    samples: int                 # residuals so far
    nis_mean: float              # window mean of the NIS (NaN until the window is full)
    nis_low: float
    nis_high: float
    whiteness_p: float           # smallest whiteness p over the components
    consistent: bool             # False: a WARN naming the sensor
    problem: str = ''            # what is wrong, naming the sensor
    transient: int = 0           # residuals of the initial transient, not judged
    converging: bool = False     # still in the initial transient (none judged yet)

    def as_dict(self):
        """Return the figures as a plain dict."""
        return dict(vars(self))


def _test_level(alpha):
    """Return the level of each of the window's two tests (NIS, whiteness): alpha together."""
    return -math.expm1(0.5 * math.log1p(-float(alpha)))


def _nis_limit(window, p, alpha, kalman):
    """Return the window mean NIS above which a window is flagged at level alpha."""
    high = float(chdtri(window * p, _test_level(alpha))) / window
    return high if kalman else OTHER_MARGIN * high


def _white_limit(points, p, alpha):
    """Return the periodogram distance above which a component flags its window."""
    if not points:
        return math.inf
    return critical_distance(points, component_level(_test_level(alpha), p))


def _window_figures(E):
    """Return the NIS sum and the largest periodogram distance of windows (W, N, p)."""
    nis = np.sum(E * E, axis=(1, 2))
    D, points = periodogram_statistic(np.moveaxis(E, 2, 1).reshape(-1, E.shape[1]))
    D = D.reshape(E.shape[0], E.shape[2])
    worst = np.max(np.nan_to_num(D, nan=-1.0), axis=1)
    worst[worst < 0.0] = np.nan
    return nis, worst, points


def _problem(name, window, nis_mean, limit, worst, points):
    if not nis_mean <= limit:
        return (f'{name}: residuals too large for the model (mean NIS {nis_mean:.3g} over '
                f'the last {window}, at most {limit:.3g} expected): a bias, a wrong sign or '
                'frame, or noise_std too small')
    p = float(kstwo.sf(worst, points)) if points and math.isfinite(worst) else math.nan
    return (f'{name}: residuals not white (cumulative periodogram p {p:.2g} over the last '
            f'{window}): a model error, a latency or a frame mismatch')


def _judge(name, E, kalman, alpha, samples):
    """Health of the whitened residuals E (window x p)."""
    W, p = E.shape
    a = _test_level(alpha)
    low, high = nis_bounds(W, p, 2.0 * a)
    nis, worst, points = _window_figures(E[None])
    nis_mean = float(nis[0]) / W
    worst = float(worst[0])
    white_p = float(kstwo.sf(worst, points)) if points and math.isfinite(worst) \
        else math.nan
    limit = _nis_limit(W, p, alpha, kalman)
    bad = not nis_mean <= limit or (kalman and worst > _white_limit(points, p, alpha))
    problem = _problem(name, W, nis_mean, limit, worst, points) if bad else ''
    return SensorHealth(name, samples, nis_mean, low, high, white_p, not problem, problem)


class InnovationMonitor:
    """
    Windowed NIS and whiteness of each sensor's residuals (see the module's text).

    Parameters
    ----------
    sensors : sequence of (str, array_like)
        Each sensor's name and noise_std (one per output; S of the observers other
        than Kalman, and R's part when no S is given).
    kalman : bool
        The residuals come with S = C P C^T + R (a Kalman filter): both tests apply.
    window, lags, alpha
        See :data:`WINDOW`, :data:`ALPHA`; ``lags`` is not used (the whiteness test
        takes the window's whole periodogram).
    transient : float
        Seconds after the first residual (or :meth:`restart`) whose residuals are not
        judged (:func:`transient_time`); they need the time ``t`` given to :meth:`add`.

    """

    def __init__(self, sensors, kalman, window=WINDOW, lags=LAGS, alpha=ALPHA,
                 transient=0.0):
        if int(window) < 8:
            raise ValueError(f'window must be at least 8; got {window!r}')
        if not float(transient) >= 0.0:
            raise ValueError(f'transient must be >= 0 s; got {transient!r}')
        self._window = int(window)
        self._alpha = float(alpha)
        self._kalman = bool(kalman)
        self._transient = float(transient)
        self._std = {}
        self._inv_std = {}              # None where a noise_std is 0 (cannot whiten)
        self._size = {}                 # outputs per sensor (an int: read per message)
        # per sensor, the last ``window`` residuals as (values, factor): plain floats and
        # what whitens them (1 / noise_std, or 1 / sqrt(S) of one output, or 1.0 when
        # already whitened), multiplied when the window is judged (:meth:`health`, at the
        # node's diagnostics rate) rather than per message
        self._ring = {}
        self._count = {}
        self._skipped = {}              # residuals of the transient, per sensor
        for name, std in sensors:
            std = np.asarray(std, dtype=float).reshape(-1)
            self._std[name] = std
            self._size[name] = std.size
            self._inv_std[name] = 1.0 / std if np.all(std > 0.0) else None
            self._ring[name] = [None] * self._window
        self.restart()

    def restart(self):
        """Forget the residuals: the estimator restarted (a new initial transient)."""
        self._judge_from = None if self._transient > 0.0 else -math.inf
        for name, ring in self._ring.items():
            ring[:] = [None] * self._window
            self._count[name] = 0
            self._skipped[name] = 0

    @property
    def window(self):
        """Return the number of residuals per window."""
        return self._window

    def add(self, name, residual, S=None, t=None):
        """
        Add one residual of a sensor.

        Parameters
        ----------
        name : str
            The sensor.
        residual : (p,) array_like
            Its residual.
        S : (p, p) array_like, optional
            Its covariance (Kalman); default ``diag(noise_std^2)``. A residual that
            cannot be whitened (a zero noise_std, a non-finite value) is not counted.
        t : float, optional
            Its stamp, s: residuals in the first ``transient`` seconds are not judged
            (without t every residual is).

        """
        if t is not None:
            judge_from = self._judge_from
            if judge_from is None:
                judge_from = self._judge_from = t + self._transient
            if t < judge_from:
                self._skipped[name] += 1
                return
        try:
            values = residual.tolist() if type(residual) is np.ndarray and residual.ndim == 1 \
                else np.asarray(residual, dtype=float).reshape(-1).tolist()
            if S is None:
                factor = self._inv_std[name]
                if factor is None:
                    return
            elif len(values) == 1 and len(S) == 1:      # one output: no Cholesky
                s = float(S[0][0])
                if not s > 0.0:
                    return
                factor = 1.0 / math.sqrt(s)
            else:
                values, factor = whiten(values, S).tolist(), 1.0
        except (ValueError, TypeError, np.linalg.LinAlgError):
            return
        # plain floats: cheaper than numpy on a few elements (per message)
        if len(values) != self._size[name] or not all(map(math.isfinite, values)):
            return
        k = self._count[name]
        self._ring[name][k % self._window] = (values, factor)
        self._count[name] = k + 1

    def health(self, name):
        """
        Return the :class:`SensorHealth` of a sensor's last window.

        Parameters
        ----------
        name : str
            The sensor.

        Returns
        -------
        health : SensorHealth
            Consistent (with NaN figures) until the window is full.

        """
        count = self._count[name]
        skipped = self._skipped[name]
        if count < self._window:
            p = self._std[name].size
            low, high = nis_bounds(self._window, p, 2.0 * _test_level(self._alpha))
            return SensorHealth(name, count, math.nan, low, high, math.nan, True,
                                transient=skipped, converging=self.converging)
        k = count % self._window
        ring = self._ring[name]
        E = np.array([np.multiply(values, factor)                   # oldest first
                      for values, factor in ring[k:] + ring[:k]])
        h = _judge(name, E, self._kalman, self._alpha, count)
        h.transient = skipped
        return h

    @property
    def converging(self):
        """Tell whether the residuals are still those of the initial transient."""
        return self._judge_from is None or (
            self._judge_from > -math.inf and not any(self._count.values()))

    @property
    def transient(self):
        """Seconds of the initial transient that are not judged."""
        return self._transient

    def report(self):
        """Return the health of every sensor (list of :class:`SensorHealth`)."""
        return [self.health(name) for name in self._std]


def sequence_health(name, E, kalman, window=WINDOW, lags=LAGS, alpha=ALPHA, since=None,
                    transient=0.0, level=RUN_LEVEL):
    """
    Health of a sensor over a whole run: its windows judged as the node judges them.

    Parameters
    ----------
    name : str
        The sensor.
    E : (N, p) array_like
        Its whitened residuals in order (rows with a non-finite value are left out).
    kalman : bool
        See :class:`InnovationMonitor`.
    window, lags, alpha
        See :class:`InnovationMonitor` (``lags`` is not used).
    since : (N,) array_like, optional
        Seconds from the estimator's (re)start to each residual: those before
        ``transient`` (:func:`transient_time`) are not judged, as the node does not.
    transient : float
        See ``since``.
    level : float
        The largest false-alarm probability of the run's verdict
        (:func:`observer_ros.core.whiteness.run_rule`).

    Returns
    -------
    figures : dict
        ``samples`` (judged), ``transient`` (residuals of the initial transient, not
        judged), ``nis_mean`` (judged residuals), ``nis_low`` and ``nis_high`` (bounds
        of a window mean), ``windows`` (consecutive, non-overlapping),
        ``windows_inconsistent`` (flagged at ``alpha``), ``windows_allowed`` (the most
        a consistent run may have), ``windows_extreme`` (flagged at the rule's far
        smaller level), ``false_alarm`` (the exact probability that a consistent run is
        called inconsistent), ``whiteness_p`` (smallest over the windows),
        ``consistent`` (the run's verdict) and ``problem`` (the first flagged window's,
        when the run is inconsistent).

    """
    return sequence_health_blocks(name, [(E, since)], kalman, window, lags, alpha, transient,
                                  level=level)


def sequence_health_blocks(name, blocks, kalman, window=WINDOW, lags=LAGS, alpha=ALPHA,
                           transient=0.0, rows=None, level=RUN_LEVEL, nis=None):
    """
    Return :func:`sequence_health`'s figures of a run given a block of residuals at a time.

    The figures are those of :func:`sequence_health` over the blocks' rows in order,
    exactly: the windows run across the blocks, and the NIS mean is taken over every
    judged row at once. Each window keeps two numbers (its NIS and its largest
    periodogram distance) until the run is judged.

    Parameters
    ----------
    name, kalman, window, lags, alpha, transient, level
        See :func:`sequence_health`.
    blocks : iterable of (E, since)
        The run's whitened residuals ``(n, p)`` and their seconds since the estimator's
        (re)start ``(n,)`` (or None), a block at a time; the first block gives p.
    rows : int, optional
        At least the number of rows of all the blocks: the judged rows' NIS is kept in
        one array this long (8 bytes a row) instead of a list joined at the end.
    nis : column, optional
        Where the judged rows' NIS go instead, an object with ``append(values)`` and
        ``mean()`` (numpy's mean of them): e.g. a column in a temporary file, so that a
        long run's are not held in memory.

    Returns
    -------
    figures : dict
        As :func:`sequence_health`.

    """
    skipped = 0
    p = None
    sink = nis
    nis = np.empty(rows) if rows is not None and sink is None else []
    N = 0
    rest = None                 # judged rows not yet in a full window
    sums, worst = [], []        # per window: NIS sum, largest periodogram distance
    points = 0
    for E, since in blocks:
        E = np.asarray(E, dtype=float)
        if since is not None and transient > 0.0 and E.size:
            keep = ~(np.asarray(since, dtype=float) < transient)
            skipped += int(np.count_nonzero(~keep))
            E = E[keep]
        E = E[np.all(np.isfinite(E), axis=1)] if E.size else \
            E.reshape(0, max(E.shape[-1:] or [1]))
        if p is None:
            p = E.shape[1] if E.ndim == 2 else 1
        if not E.shape[0]:
            continue
        if sink is not None:
            sink.append(np.sum(E * E, axis=1))
        elif rows is not None:
            nis[N:N + E.shape[0]] = np.sum(E * E, axis=1)
        else:
            nis.append(np.sum(E * E, axis=1))
        N += E.shape[0]
        if rest is not None and rest.shape[0]:
            E = np.concatenate([rest, E])
        full = E.shape[0] // window
        if full:
            s, w, points = _window_figures(E[:full * window].reshape(full, window, -1))
            sums.append(s)
            worst.append(w)
        rest = E[full * window:].copy()
    if sink is not None:
        nis = sink
    else:
        nis = nis[:N] if rows is not None else (np.concatenate(nis) if nis else np.zeros(0))
    p = 1 if p is None else p
    a = _test_level(alpha)
    low, high = nis_bounds(window, p, 2.0 * a)
    sums = np.concatenate(sums) if sums else np.zeros(0)
    worst = np.concatenate(worst) if worst else np.zeros(0)
    rule = run_rule(sums.size, alpha, level)

    def bad(at):
        out = ~(sums / window <= _nis_limit(window, p, at, kalman))
        if kalman:
            out |= np.nan_to_num(worst, nan=0.0) > _white_limit(points, p, at)
        return out
    flagged = bad(alpha)
    verdict = run_verdict(rule, np.count_nonzero(flagged),
                          np.count_nonzero(bad(rule['alpha_extreme'])))
    problem = ''
    if verdict['white'] is False:
        k = int(np.argmax(flagged))
        problem = _problem(name, window, sums[k] / window, _nis_limit(window, p, alpha, kalman),
                           worst[k], points)
    top = np.nanmax(worst) if np.isfinite(worst).any() else math.nan
    return {'samples': int(N), 'transient': skipped,
            'nis_mean': float(np.mean(nis)) if N else math.nan,
            'nis_low': low, 'nis_high': high, 'windows': int(sums.size),
            'windows_inconsistent': verdict['flagged'],
            'windows_allowed': verdict['allowed'], 'windows_extreme': verdict['extreme'],
            'false_alarm': verdict['level'],
            'whiteness_p': float(kstwo.sf(top, points)) if points and math.isfinite(top)
            else math.nan,
            'consistent': verdict['white'] is not False, 'problem': problem}
