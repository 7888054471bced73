# observer_ros.core.whiteness: is a residual sequence white? One calibrated test.
"""
Whiteness of residuals: the one test of the node, ``observer-eval`` and ``observer-tune``.

**The window test** (Bartlett's cumulative periodogram test; G. E. P. Box, G. M. Jenkins,
*Time Series Analysis*, the cumulative periodogram check). The periodogram of a window of
N residuals, ``I_j = |sum_t x_t exp(-2 pi i j t / N)|^2`` at the Fourier frequencies
``j = 1 .. m``, ``m = (N - 1) // 2`` (the window's mean does not enter), is for Gaussian
white residuals a set of m independent, identically exponential ordinates. So the
normalised cumulative sums ``U_j = (I_1 + .. + I_j) / (I_1 + .. + I_m)``, ``j < m``, are
distributed *exactly* as the order statistics of m - 1 uniform variables, whatever N and
the residuals' variance. The statistic is their Kolmogorov-Smirnov distance D from the
uniform distribution and its p-value the exact one of ``scipy.stats.kstwo`` with m - 1
points. A white window is flagged (p < alpha) with probability exactly alpha; a coloured
one (a spectrum that is not flat: a model error, a latency, a wrong noise covariance)
more often.

**The run verdict.** A run judged in W windows (``observer-eval``, ``observer-tune``) is
*not white* when more than c windows are flagged, or when one window is flagged at a much
smaller level (a short fault): :func:`run_rule`. Its false-alarm probability on white
residuals is computed exactly (the count is discrete: at most :data:`RUN_LEVEL`) and
reported beside the verdict.

``benchmarks/whiteness_calibration.py`` measures both rates on white residuals.

No ROS here: numpy and scipy only.

"""

import functools
import math

import numpy as np
from scipy.stats import binom, kstwo

__all__ = ['MIN_WINDOW', 'RUN_LEVEL', 'periodogram_statistic', 'critical_distance',
           'window_p', 'flagged', 'component_level', 'run_rule', 'run_verdict',
           'WindowWhiteness']

#: Shortest window the test judges (three periodogram ordinates).
MIN_WINDOW = 8

#: Largest false-alarm probability of a run's verdict on white residuals.
RUN_LEVEL = 0.01


def periodogram_statistic(x):
    """
    Return the cumulative periodogram's distance D from the uniform and its points.

    Parameters
    ----------
    x : (N,) or (W, N) array_like
        One window, or W windows of N residuals (rows).

    Returns
    -------
    D : float or (W,) ndarray
        Kolmogorov-Smirnov distance of ``U_1 .. U_(m-1)`` from the uniform; NaN for a
        window whose periodogram is zero (a constant) or not finite.
    points : int
        m - 1, the number of points D is taken over (0 when N < :data:`MIN_WINDOW`).

    """
    x = np.asarray(x, dtype=float)
    one = x.ndim == 1
    X = x.reshape(1, -1) if one else x
    N = X.shape[1]
    m = (N - 1) // 2
    n = m - 1
    if N < MIN_WINDOW:
        D = np.full(X.shape[0], np.nan)
        return (float(D[0]) if one else D), 0
    F = np.fft.rfft(X, axis=1)[:, 1:m + 1]
    ordinates = F.real ** 2 + F.imag ** 2
    total = np.cumsum(ordinates, axis=1)
    with np.errstate(invalid='ignore', divide='ignore'):
        U = total[:, :-1] / total[:, -1:]
    i = np.arange(1, n + 1)
    D = np.maximum(np.max(i / n - U, axis=1), np.max(U - (i - 1) / n, axis=1))
    D[~(total[:, -1] > 0.0) | ~np.isfinite(total[:, -1])] = np.nan
    return (float(D[0]) if one else D), n


@functools.lru_cache(maxsize=256)
def critical_distance(points, alpha):
    """Return the D above which a window of ``points`` points is flagged at level alpha."""
    return float(kstwo.isf(float(alpha), int(points)))


def window_p(x):
    """
    Return the p-value of the window test (NaN when undefined).

    Parameters
    ----------
    x : (N,) array_like
        The window's residuals (N >= :data:`MIN_WINDOW`).

    """
    D, n = periodogram_statistic(x)
    if not n or not math.isfinite(D):
        return math.nan
    return float(kstwo.sf(D, n))


def flagged(D, points, alpha):
    """Return whether each distance D (of windows of ``points`` points) is flagged."""
    D = np.asarray(D, dtype=float)
    if not points:
        return np.zeros(D.shape, dtype=bool)
    return np.nan_to_num(D, nan=0.0) > critical_distance(points, alpha)


def component_level(alpha, components):
    """
    Return the level of each of ``components`` independent tests making one of level alpha.

    ``1 - (1 - alpha)^(1 / components)`` (Sidak): a window is flagged when any of its
    components is, with probability exactly alpha when they are independent (the
    whitened components of a consistent Kalman filter's residual are).

    """
    return -math.expm1(math.log1p(-float(alpha)) / max(int(components), 1))


def run_rule(windows, alpha, level=RUN_LEVEL):
    """
    Return the rule judging a run of windows, each flagged with probability alpha if white.

    The run is *not white* when more than c windows are flagged at alpha, or when one
    window is flagged at the much smaller ``alpha_extreme`` (a short fault). c is the
    smallest count with ``P(Binom(W, alpha) > c) <= level / 2``, ``alpha_extreme =
    min(alpha, 1 - (1 - level / 2)^(1 / W))``. Windows of a white run are independent and
    each is either not flagged (probability 1 - alpha), flagged but not extreme
    (alpha - alpha_extreme) or extreme (alpha_extreme), so the false-alarm probability of
    the rule is exactly ``1 - (1 - alpha_extreme)^W P(Binom(W, a) <= c)``, ``a = (alpha -
    alpha_extreme) / (1 - alpha_extreme)``: at most ``level``.

    Returns
    -------
    rule : dict
        ``windows``, ``alpha``, ``allowed`` (c), ``alpha_extreme`` and ``level`` (the
        exact false-alarm probability).

    """
    W, alpha = int(windows), float(alpha)
    if W <= 0:
        return {'windows': 0, 'alpha': alpha, 'allowed': 0, 'alpha_extreme': alpha,
                'level': 0.0}
    half = 0.5 * float(level)
    c = int(binom.isf(half, W, alpha))
    while c > 0 and binom.sf(c - 1, W, alpha) <= half:
        c -= 1
    while binom.sf(c, W, alpha) > half:
        c += 1
    extreme = min(alpha, -math.expm1(math.log1p(-half) / W))
    a = (alpha - extreme) / (1.0 - extreme)
    exact = -math.expm1(W * math.log1p(-extreme)) if c >= W else \
        1.0 - math.exp(W * math.log1p(-extreme)) * float(binom.cdf(c, W, a))
    return {'windows': W, 'alpha': alpha, 'allowed': c, 'alpha_extreme': extreme,
            'level': float(exact)}


def run_verdict(rule, flagged_windows, extreme_windows):
    """Return :func:`run_rule`'s figures with ``flagged``, ``extreme`` and ``white``."""
    out = dict(rule)
    out.update(flagged=int(flagged_windows), extreme=int(extreme_windows),
               white=None if not rule['windows'] else
               bool(flagged_windows <= rule['allowed'] and not extreme_windows))
    return out


class WindowWhiteness:
    """
    The window test over runs given a block of rows at a time, each column on its own.

    Consecutive, non-overlapping windows of ``window`` finite values of each column
    (NaN rows of a column, a measurement missing there, are left out of it); the
    windows are taken across the blocks. Each window's distance D is kept (8 bytes a
    window); :meth:`verdicts` judges each column by :func:`run_rule`.

    Parameters
    ----------
    columns : int
        Columns (outputs).
    window : int
        Values per window (at least :data:`MIN_WINDOW`).
    alpha : float
        Each window's level.

    """

    def __init__(self, columns, window, alpha):
        if int(window) < MIN_WINDOW:
            raise ValueError(f'window must be at least {MIN_WINDOW}; got {window!r}')
        self.window, self.alpha = int(window), float(alpha)
        self.points = periodogram_statistic(np.zeros(self.window))[1]
        self._rest = [np.zeros(0) for _ in range(int(columns))]
        self._D = [[] for _ in range(int(columns))]

    def add(self, block):
        """Add the next rows ``(n, columns)`` of the run."""
        block = np.asarray(block, dtype=float).reshape(-1, len(self._rest))
        for j in range(block.shape[1]):
            col = block[:, j]
            col = np.concatenate([self._rest[j], col[np.isfinite(col)]])
            full = col.size // self.window
            if full:
                D, _ = periodogram_statistic(col[:full * self.window].reshape(
                    full, self.window))
                self._D[j].append(D)
            self._rest[j] = col[full * self.window:].copy()

    def verdicts(self, level=RUN_LEVEL):
        """
        Return each column's :func:`run_verdict`, with ``min_p`` (its smallest window p).

        Also ``window`` (values per window).

        """
        out = []
        for parts in self._D:
            D = np.concatenate(parts) if parts else np.zeros(0)
            rule = run_rule(D.size, self.alpha, level)
            v = run_verdict(rule, np.count_nonzero(flagged(D, self.points, self.alpha)),
                            np.count_nonzero(flagged(D, self.points,
                                                     rule['alpha_extreme'])))
            worst = np.nanmax(D) if np.isfinite(D).any() else math.nan
            v['min_p'] = float(kstwo.sf(worst, self.points)) if math.isfinite(worst) \
                else math.nan
            v['window'] = self.window
            out.append(v)
        return out
