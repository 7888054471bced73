# observer_ros.core.limits: what no controller can do with the chosen sensors.
"""
Fundamental limits of feedback for a plant and a set of outputs.

For the minimal part of ``(A, B, C, D)`` (the decision of ``core/analysis.py``), the
unstable poles p and the non-minimum-phase transmission zeros z (right half plane, or
outside the unit circle) bound every stabilising controller (Skogestad and Postlethwaite,
*Multivariable Feedback Control*, 2nd ed., sections 5.9-5.13 and 6.3-6.6):

- **peak sensitivity.** One input and one output: ``Ms >= prod_p |z + conj(p)| / |z - p|``
  for each zero z (``|1 - conj(p) z| / |z - p|`` in discrete time); several: for each
  pair, ``Ms >= sqrt(sin^2 phi + cos^2 phi |z + conj(p)|^2 / |z - p|^2)``, phi the angle
  between the zero's and the pole's output directions. With ``Ms >= M`` no design reaches
  a disk margin above ``1 / (M - 1/2)`` (``|S - 1/2| >= |S| - 1/2``): that disk margin's
  gain and phase are the best margins any controller could reach.
- **bandwidth and delay.** A real unstable pole p needs a gain crossover above about
  ``2 p`` (rule of thumb), and no linear controller keeps the loop stable with a delay of
  ``2 / p`` or more (for one real unstable pole; more poles allow less). A zero z limits
  the crossover to below about ``z / 2``.

Measuring every state removes every transmission zero (a plant ``(sI - A)^-1 B`` has
none), so a bound that exceeds :data:`~observer_ros.core.margins.PEAK_SENSITIVITY_WARN`
because of a zero is the **sensor set's**: :func:`fundamental_limit` then names the state
whose measurement, added to the outputs, lowers the bound most.

"""

from dataclasses import dataclass, field
import math
from typing import Optional, Tuple

import numpy as np
import scipy.linalg

from .analysis import (controllability_report, controllable_decomposition, format_complex,
                       observability_report, observable_decomposition)
from .margins import PEAK_SENSITIVITY_WARN
from .verify import eigenvalue_bounds, stability_status

__all__ = ['FundamentalLimit', 'fundamental_limit', 'transmission_zeros', 'best_disk_margin']


@dataclass(frozen=True)
class FundamentalLimit:
    """
    The limits of :func:`fundamental_limit` (see the module docstring).

    ``pairs`` lists ``(zero, pole, bound)``; ``ms_bound`` is the largest bound (1 when
    there is no RHP zero); ``crossover_min`` / ``delay_max`` come from the largest
    unstable pole (None without one), ``crossover_max`` from the smallest zero;
    ``sensor_obstacle`` says the bound comes from the outputs (``full_state_bound``, the
    bound with every state measured, is lower), ``better_with`` names the state whose
    measurement lowers it most and ``better_bound`` what it becomes.

    """

    outputs: Tuple[str, ...]
    rhp_poles: np.ndarray
    rhp_zeros: np.ndarray
    pairs: Tuple[Tuple[complex, complex, float], ...]
    ms_bound: float
    crossover_min: Optional[float]
    delay_max: Optional[float]
    crossover_max: Optional[float]
    sensor_obstacle: bool = False
    better_with: Optional[str] = None
    better_bound: Optional[float] = None
    full_state_bound: Optional[float] = None
    notes: Tuple[str, ...] = field(default=())

    @property
    def best_disk(self):
        """Return the largest disk margin any controller could reach, its gain and phase."""
        return best_disk_margin(self.ms_bound)

    def to_json(self):
        """Return a JSON-serialisable dict."""
        def cplx(z):
            return [float(np.real(z)), float(np.imag(z))]

        def num(x):
            return None if x is None or not np.isfinite(x) else float(x)
        alpha, gain, phase = self.best_disk
        return {'outputs': list(self.outputs),
                'rhp_poles': [cplx(p) for p in self.rhp_poles],
                'rhp_zeros': [cplx(z) for z in self.rhp_zeros],
                'pairs': [{'zero': cplx(z), 'pole': cplx(p), 'ms_bound': b}
                          for z, p, b in self.pairs],
                'ms_bound': num(self.ms_bound), 'best_disk_margin': alpha,
                'best_disk_gain': num(gain), 'best_disk_phase_deg': phase,
                'crossover_min': self.crossover_min, 'delay_max': self.delay_max,
                'crossover_max': self.crossover_max, 'sensor_obstacle': self.sensor_obstacle,
                'better_with': self.better_with, 'better_bound': self.better_bound,
                'full_state_bound': self.full_state_bound,
                'notes': list(self.notes)}

    def lines(self):
        """Return the report's lines."""
        out = [f'Fundamental limit (outputs {list(self.outputs)}): unstable poles '
               f'{_list(self.rhp_poles)}; non-minimum-phase zeros {_list(self.rhp_zeros)}']
        if self.pairs:
            z, p, b = max(self.pairs, key=lambda t: t[2])
            alpha, gain, phase = self.best_disk
            how = '|z+p|/|z-p|' if len(self.pairs) == 1 else 'the largest pair'
            out.append(f'  every stabilising controller has Ms >= {self.ms_bound:.3g} ({how}, '
                       f'zero {format_complex(z, 4)}, pole {format_complex(p, 4)}); no design '
                       f'reaches a disk margin above {alpha:.3g} (gain {1 / gain:.4g} to '
                       f'{gain:.4g}, phase +-{phase:.3g} deg)')
        elif not math.isfinite(self.ms_bound):
            out.append('  no controller stabilises the loop with these outputs (an unstable '
                       'mode they do not see, or one the input does not move)')
        else:
            out.append('  no non-minimum-phase zero: no lower bound on Ms from these outputs')
        if self.crossover_min is not None:
            out.append(f'  the unstable pole allows no controller {self.delay_max * 1e3:.4g} ms '
                       f'of loop delay (2/p), and wants a crossover above about '
                       f'{self.crossover_min:.3g} rad/s (2p, rule of thumb for Ms near 2)')
        if self.crossover_max is not None:
            out.append(f'  the zero limits the crossover to below about '
                       f'{self.crossover_max:.3g} rad/s (z/2, rule of thumb)'
                       + (': the two cannot both hold'
                          if self.crossover_min is not None and
                          self.crossover_min > self.crossover_max else ''))
        if self.sensor_obstacle:
            add = f'; measuring {self.better_with} as well brings it to ' \
                  f'{self.better_bound:.3g}' if self.better_with else ''
            out.append(f'  the sensor set is the obstacle: with every state measured the '
                       f'bound is {self.full_state_bound:.3g}{add}')
        out.extend(f'  {note}' for note in self.notes)
        return out


def _list(values):
    vals = [z for z in np.asarray(values).reshape(-1) if np.imag(z) >= 0]
    return ', '.join(format_complex(z, 4) for z in vals) if vals else 'none'


def best_disk_margin(ms_bound):
    """
    Return the largest disk margin alpha with ``Ms >= ms_bound``, its gain and phase (deg).

    Parameters
    ----------
    ms_bound : float
        Lower bound on the peak sensitivity.

    Returns
    -------
    alpha, gain, phase : float
        ``alpha = min(2, 1 / (ms_bound - 1/2))``, the disk's upper gain
        ``(1 + alpha/2) / (1 - alpha/2)`` and phase ``2 atan(alpha/2)``.

    """
    alpha = 2.0 if ms_bound <= 1.0 else min(2.0, 1.0 / (ms_bound - 0.5))
    a = alpha / 2.0
    gain = math.inf if a >= 1.0 else (1.0 + a) / (1.0 - a)
    return alpha, gain, math.degrees(2.0 * math.atan(a))


def _minimal(A, B, C):
    """Return the controllable and observable part of (A, B, C)."""
    Abar, Bbar, Cbar, _, r = controllable_decomposition(A, B, C)
    A, B, C = Abar[:r, :r], Bbar[:r], Cbar[:, :r]
    Abar, Bbar, Cbar, _, m = observable_decomposition(A, B, C)
    return Abar[:m, :m], Bbar[:m], Cbar[:, :m]


def _square_zeros(A, B, C, D):
    n = A.shape[0]
    k = B.shape[1]
    M = np.block([[A, B], [C, D]])
    N = np.zeros_like(M)
    N[:n, :n] = np.eye(n)
    z = scipy.linalg.eigvals(M, N)
    scale = max(1.0, float(np.linalg.norm(M, 2)))
    del k
    return z[np.isfinite(z) & (np.abs(z) < 1e8 * scale)]


def _rosenbrock_gap(A, B, C, D, z):
    n = A.shape[0]
    M = np.block([[A - z * np.eye(n), B], [C, D]])
    s = scipy.linalg.svd(M, compute_uv=False)
    k = min(M.shape)
    return float(s[k - 1]) / max(1.0, float(s[0]))


def transmission_zeros(A, B, C, D=None):
    """
    Return the transmission zeros of (A, B, C, D) (its minimal part).

    Parameters
    ----------
    A, B, C : array_like
        Plant.
    D : array_like, optional
        Feedthrough; default zeros.

    Returns
    -------
    ndarray of complex
        The finite s (z) where the Rosenbrock matrix ``[[A - sI, B], [C, D]]`` of the
        minimal part loses rank; a non-square plant's are those of a random square
        combination of its outputs (inputs) that the full matrix confirms (its smallest
        singular value below 1e-8 of its largest).

    """
    A = np.atleast_2d(np.asarray(A, dtype=float))
    B = np.asarray(B, dtype=float).reshape(A.shape[0], -1)
    C = np.asarray(C, dtype=float).reshape(-1, A.shape[0])
    D = np.zeros((C.shape[0], B.shape[1])) if D is None else \
        np.asarray(D, dtype=float).reshape(C.shape[0], B.shape[1])
    A, B, C = _minimal(A, B, C)
    if A.shape[0] == 0:
        return np.zeros(0, complex)
    p, m = C.shape[0], B.shape[1]
    if p == m:
        return _square_zeros(A, B, C, D)
    rng = np.random.default_rng(12345)
    if p > m:
        W = rng.standard_normal((m, p))
        cand = _square_zeros(A, B, W @ C, W @ D)
    else:
        W = rng.standard_normal((m, p))
        cand = _square_zeros(A, B @ W, C, D @ W)
    return np.array([z for z in cand if _rosenbrock_gap(A, B, C, D, z) < 1e-8],
                    dtype=complex)


def _unstable(values, A, discrete):
    _, bound = eigenvalue_bounds(A)
    b = float(np.max(bound)) if bound.size else 0.0
    return np.array([z for z in values if stability_status(z, b, discrete) == 'unstable'],
                    dtype=complex)


def _output_direction_of_pole(A, C, p):
    lam, V = np.linalg.eig(A)
    i = int(np.argmin(np.abs(lam - p)))
    y = C @ V[:, i]
    return y / max(float(np.linalg.norm(y)), 1e-300)


def _output_direction_of_zero(A, B, C, D, z):
    n = A.shape[0]
    M = np.block([[A - z * np.eye(n), B], [C, D]])
    U, _, _ = scipy.linalg.svd(M)
    y = U[n:, -1]
    return y / max(float(np.linalg.norm(y)), 1e-300)


def _factor(z, p, discrete):
    if discrete:
        return abs(1.0 - np.conj(p) * z) / abs(z - p)
    return abs(z + np.conj(p)) / abs(z - p)


def _bound(A, B, C, D, discrete):
    """(rhp poles, rhp zeros, pairs, ms bound) of the minimal part of (A, B, C, D)."""
    Am, Bm, Cm = _minimal(A, B, C)
    poles = _unstable(np.linalg.eigvals(Am), Am, discrete) if Am.size else np.zeros(0, complex)
    zeros = transmission_zeros(A, B, C, D)
    zeros = _unstable(zeros, Am, discrete) if zeros.size else zeros
    pairs = []
    siso = B.shape[1] == 1 and C.shape[0] == 1
    for z in zeros:
        if siso:
            b = float(np.prod([_factor(z, p, discrete) for p in poles])) if poles.size else 1.0
            if poles.size:
                worst = max(poles, key=lambda q: _factor(z, q, discrete))
                pairs.append((complex(z), complex(worst), b))
            continue
        yz = _output_direction_of_zero(Am, Bm, Cm, D, z)
        for p in poles:
            yp = _output_direction_of_pole(Am, Cm, p)
            c2 = min(1.0, abs(np.vdot(yz, yp)) ** 2)
            f = _factor(z, p, discrete)
            pairs.append((complex(z), complex(p), float(math.sqrt((1 - c2) + c2 * f * f))))
    ms = max([1.0] + [b for _, _, b in pairs])
    if not observability_report(A, C, discrete=discrete).detectable:
        ms = math.inf
    return poles, zeros, tuple(pairs), ms


def _s_plane(z, discrete, dt):
    return np.log(complex(z)) / dt if discrete else complex(z)


def fundamental_limit(A, B, C, D=None, discrete=False, dt=None, output_names=None,
                      state_names=None, explain=True):
    """
    Return the :class:`FundamentalLimit` of a plant with the given outputs.

    Parameters
    ----------
    A, B, C : array_like
        Plant (C: the outputs measured).
    D : array_like, optional
        Feedthrough; default zeros.
    discrete : bool
        z-plane instead of s-plane.
    dt : float, optional
        Sample time of a discrete plant (for the crossover and delay figures).
    output_names, state_names : sequence of str, optional
        Names for the report.
    explain : bool
        Also find whether the sensor set is the obstacle, and which added state
        measurement lowers the bound most (one more bound per state).

    Returns
    -------
    FundamentalLimit

    """
    A = np.atleast_2d(np.asarray(A, dtype=float))
    n = A.shape[0]
    B = np.asarray(B, dtype=float).reshape(n, -1)
    C = np.asarray(C, dtype=float).reshape(-1, n)
    D = np.zeros((C.shape[0], B.shape[1])) if D is None else \
        np.asarray(D, dtype=float).reshape(C.shape[0], B.shape[1])
    names = tuple(output_names) if output_names else \
        tuple(f'y{i + 1}' for i in range(C.shape[0]))
    states = tuple(state_names) if state_names else tuple(f'x{i + 1}' for i in range(n))
    poles, zeros, pairs, ms = _bound(A, B, C, D, discrete)
    if not controllability_report(A, B, discrete=discrete).stabilizable:
        ms = math.inf
    notes = []
    if discrete and not dt:
        notes.append('no sample time: crossover and delay figures left out')
    cross_min = delay_max = cross_max = None
    if poles.size and (not discrete or dt):
        s = [_s_plane(p, discrete, dt) for p in poles]
        p_big = max(abs(x) for x in s)
        cross_min = 2.0 * p_big
        real = [x.real for x in s if abs(x.imag) <= 1e-9 * abs(x)]
        delay_max = 2.0 / max(real) if real else 2.0 / p_big
    if zeros.size and (not discrete or dt):
        cross_max = min(abs(_s_plane(z, discrete, dt)) for z in zeros) / 2.0
    obstacle, better, better_bound, full = False, None, None, None
    if explain and ms > PEAK_SENSITIVITY_WARN and \
            controllability_report(A, B, discrete=discrete).stabilizable:
        full = _bound(A, B, np.eye(n), np.zeros((n, B.shape[1])), discrete)[3]
        if full < ms:
            obstacle = True
            trials = []
            for i in range(n):
                row = np.eye(n)[i:i + 1]
                if np.any(np.all(np.isclose(C, row), axis=1)):
                    continue
                b = _bound(A, B, np.vstack([C, row]),
                           np.vstack([D, np.zeros((1, B.shape[1]))]), discrete)[3]
                trials.append((b, states[i]))
            if trials:
                better_bound, better = min(trials)
    return FundamentalLimit(names, poles, zeros, pairs, float(ms), cross_min, delay_max,
                            cross_max, obstacle, better, better_bound, full, tuple(notes))
