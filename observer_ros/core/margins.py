# observer_ros.core.margins: how far the loop is from instability, broken at u or at y.
"""
Stability margins of a compensator loop, broken at the plant input or output.

With ``u = -D(s) y`` the loop transfer broken at the plant input is ``L_i = D P`` (m x m),
at the plant output ``L_o = P D`` (p x p). For each loop channel (one for a single input
or output; with several, each channel broken with the others closed: loop-at-a-time) the
figures are:

- **gain margin**: the loop stays stable for loop gains in ``[gain_low, gain_high]``
  (an open-loop unstable plant needs a minimum gain, so ``gain_low`` is usually above 0);
- **phase margin**: the least phase change, lead or lag, at a gain crossover
  (``|L| = 1``) that puts the loop on -1;
- **delay margin**: the least delay that does so, ``(angle(L) + 180 deg) / w`` at each
  crossover, the smallest over the crossovers (a conditionally stable loop has several);
- **peak sensitivity** ``Ms = max_w |1 / (1 + L)|`` (``max_w sigma_max((I + L)^-1)``
  for the whole loop): 1/Ms is the distance of the Nyquist plot from -1;
- **disk margin** ``alpha = 1 / max_w |S - 1/2|`` (balanced, skew 0): simultaneous gain
  and phase variations within the disk leave the loop stable; its gain interval
  ``[(1 - alpha/2) / (1 + alpha/2), (1 + alpha/2) / (1 - alpha/2)]`` and phase
  ``+-2 atan(alpha / 2)``.

A single-channel loop uses python-control's ``stability_margins`` (all crossovers) and
``disk_margins``; several channels use the same formulas on the frequency response
(python-control's multivariable disk margin needs slycot, absent here: the whole loop's
disk margin is then the unstructured bound ``1 / max_w sigma_max(S - I/2)``, which
understates it). Warnings of the library are caught and said in words in ``notes``.

"""

from dataclasses import dataclass, field
import math
from typing import Optional, Tuple
import warnings

import numpy as np

from ._lazy import control

__all__ = ['LoopMargins', 'loop_margins', 'frequency_grid', 'GAIN_MARGIN_WARN',
           'PHASE_MARGIN_WARN', 'DELAY_MARGIN_WARN_SAMPLES', 'PEAK_SENSITIVITY_WARN',
           'margin_warnings']

#: Warned when the loop gain cannot grow (or shrink) by this factor (6 dB) either way.
GAIN_MARGIN_WARN = 2.0

#: Warned below this phase margin, degrees.
PHASE_MARGIN_WARN = 30.0

#: Warned when the delay margin is below this many sample periods of the vehicle.
DELAY_MARGIN_WARN_SAMPLES = 2.0

#: Warned above this peak sensitivity (6 dB).
PEAK_SENSITIVITY_WARN = 2.0


@dataclass(frozen=True)
class LoopMargins:
    """The margins of one loop channel (see the module docstring); inf when none applies."""

    side: str                       # 'input' or 'output'
    channel: Optional[str]          # the input or output broken; None: the only one
    gain_low: float
    gain_high: float
    phase: float                    # degrees
    phase_frequency: float
    delay: float                    # s
    delay_frequency: float
    peak_sensitivity: float
    peak_frequency: float
    disk: float
    notes: Tuple[str, ...] = field(default=())

    @property
    def disk_gain(self):
        """Gain interval of the disk margin."""
        a = self.disk / 2.0
        if a >= 1.0:
            return 0.0, math.inf
        return (1.0 - a) / (1.0 + a), (1.0 + a) / (1.0 - a)

    @property
    def disk_phase(self):
        """Phase of the disk margin, degrees."""
        return math.degrees(2.0 * math.atan(self.disk / 2.0))

    @property
    def where(self):
        """``'plant input'`` or ``'plant output'``, with the channel when there are several."""
        text = f'plant {self.side}'
        return text if self.channel is None else f'{text} {self.channel}'

    @property
    def siso(self):
        """Return True for the only channel of its side."""
        return self.channel is None

    def to_json(self):
        """Return a JSON-serialisable dict (inf as None)."""
        def num(x):
            return None if not np.isfinite(x) else float(x)
        lo, hi = self.disk_gain
        return {'side': self.side, 'channel': self.channel, 'gain_low': num(self.gain_low),
                'gain_high': num(self.gain_high), 'phase_deg': num(self.phase),
                'phase_frequency': num(self.phase_frequency), 'delay_s': num(self.delay),
                'delay_frequency': num(self.delay_frequency),
                'peak_sensitivity': num(self.peak_sensitivity),
                'peak_frequency': num(self.peak_frequency), 'disk': num(self.disk),
                'disk_gain': [num(lo), num(hi)], 'disk_phase_deg': num(self.disk_phase),
                'notes': list(self.notes)}


def frequency_grid(systems, dt=None, points=2000):
    """
    Log-spaced frequencies covering the poles and zeros of the systems (rad/s).

    Parameters
    ----------
    systems : sequence of control.StateSpace
        The loop's parts.
    dt : float, optional
        Sample time of a discrete loop: the grid ends at the Nyquist frequency.
    points : int
        Number of frequencies.

    Returns
    -------
    ndarray

    """
    mags = []
    for sys_ in systems:
        lam = np.linalg.eigvals(np.asarray(sys_.A)) if np.size(sys_.A) else np.zeros(0)
        if dt:
            with np.errstate(divide='ignore'):
                lam = np.log(lam.astype(complex)) / dt
        mags.extend(abs(x) for x in lam if np.isfinite(x) and abs(x) > 1e-9)
    lo = 1e-2 * min(mags) if mags else 1e-3
    hi = 1e2 * max(mags) if mags else 1e3
    if dt:
        hi = math.pi / dt * (1.0 - 1e-9)
        lo = min(lo, hi * 1e-6)
    return np.logspace(math.log10(lo), math.log10(hi), points)


def _response(sys_, w, dt):
    """Frequency response of a state-space system, (outputs, inputs, len(w))."""
    A, B, C, D = (np.asarray(M, dtype=float) for M in (sys_.A, sys_.B, sys_.C, sys_.D))
    s = np.exp(1j * w * dt) if dt else 1j * w
    n = A.shape[0]
    if n == 0:
        return np.repeat(D[:, :, None], w.size, axis=2).astype(complex)
    M = s[:, None, None] * np.eye(n)[None] - A[None]
    X = np.linalg.solve(M, np.broadcast_to(B, (w.size,) + B.shape))
    G = C[None] @ X + D[None]
    return np.moveaxis(G, 0, 2)


def _crossings(x):
    """Return the indices i where x changes sign between i and i + 1."""
    return np.nonzero(np.sign(x[:-1]) * np.sign(x[1:]) < 0)[0]


def _siso_numeric(resp, w):
    """Gain interval, phase and delay margins of a scalar loop response."""
    lows, highs = [0.0], [math.inf]
    for i in _crossings(resp.imag):
        f = resp.imag[i] / (resp.imag[i] - resp.imag[i + 1])
        re = resp.real[i] + f * (resp.real[i + 1] - resp.real[i])
        if re < 0.0:
            k = -1.0 / re
            (lows if k < 1.0 else highs).append(k)
    phase, wp, delay, wd = math.inf, math.nan, math.inf, math.nan
    mag = np.abs(resp) - 1.0
    for i in _crossings(mag):
        f = mag[i] / (mag[i] - mag[i + 1])
        wc = w[i] * (w[i + 1] / w[i]) ** f
        z = resp[i] + f * (resp[i + 1] - resp[i])
        lag = (np.angle(z) + math.pi) % (2 * math.pi)
        pm = math.degrees(min(lag, 2 * math.pi - lag))
        if pm < phase:
            phase, wp = pm, wc
        if lag / wc < delay:
            delay, wd = lag / wc, wc
    return max(lows), min(highs), phase, wp, delay, wd


def _siso_control(L, w, dt, notes):
    """Return the same from python-control's stability_margins (all crossovers), or None."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter('always')
        try:
            gm, pm, _, _, wgc, _ = control.stability_margins(L, returnall=True)
        except (ValueError, np.linalg.LinAlgError, TypeError) as err:
            notes.append(f"python-control's stability_margins failed ({err}); the margins "
                         'come from the frequency response')
            return None
    for wmsg in caught:
        if not issubclass(wmsg.category, DeprecationWarning):
            notes.append(f"python-control's stability_margins warned ({wmsg.message}); "
                         'its figures were checked against the frequency response')
    gm = np.atleast_1d(np.asarray(gm, dtype=float))
    gm = gm[np.isfinite(gm) & (gm < 1e12)]
    low = max([0.0] + [g for g in gm if g < 1.0])
    high = min([math.inf] + [g for g in gm if g > 1.0])
    phase, wp, delay, wd = math.inf, math.nan, math.inf, math.nan
    for wc in np.atleast_1d(np.asarray(wgc, dtype=float)):
        if not (np.isfinite(wc) and wc > 0.0):
            continue
        z = complex(np.asarray(L(np.exp(1j * wc * dt) if dt else 1j * wc)).reshape(-1)[0])
        lag = (np.angle(z) + math.pi) % (2 * math.pi)
        pm_c = math.degrees(min(lag, 2 * math.pi - lag))
        if pm_c < phase:
            phase, wp = pm_c, float(wc)
        if lag / wc < delay:
            delay, wd = lag / wc, float(wc)
    del pm
    return low, high, phase, wp, delay, wd


def _peak(S, w):
    """Return the largest sigma_max(S(jw)) over the frequencies, and where."""
    if S.shape[0] == 1:
        mags = np.abs(S[0, 0])
    else:
        mags = np.linalg.svd(np.moveaxis(S, 2, 0), compute_uv=False)[:, 0]
    i = int(np.argmax(mags))
    return float(mags[i]), float(w[i])


def _sensitivity(Lr):
    k = Lr.shape[0]
    return np.moveaxis(np.linalg.inv(np.eye(k)[None] + np.moveaxis(Lr, 2, 0)), 0, 2)


def loop_margins(plant, compensator, side='input', names=None, dt=None, w=None):
    """
    Margins of the loop ``u = -D y`` around the plant, broken at its input or output.

    Parameters
    ----------
    plant, compensator : control.StateSpace
        P (y from u) and D (u = -D y); continuous, or discrete with sample time dt.
    side : {'input', 'output'}
        Where the loop is broken.
    names : sequence of str, optional
        Names of the inputs (outputs) for the channels.
    dt : float, optional
        Sample time of a discrete loop.
    w : ndarray, optional
        Frequencies, rad/s (default :func:`frequency_grid`).

    Returns
    -------
    list of LoopMargins
        One per channel; with several channels, each broken with the others closed
        (loop-at-a-time), and the peak sensitivity and disk margin of the whole loop in
        every entry (the disk margin then the unstructured bound); NaN on the wider side
        of a non-square plant (more outputs than inputs: the output side), where the
        loop's rank is below its size and its singular values depend on the units.

    """
    L = compensator * plant if side == 'input' else plant * compensator
    w = frequency_grid([plant, compensator], dt) if w is None else np.asarray(w, float)
    resp = _response(L, w, dt)
    k = resp.shape[0]
    S = _sensitivity(resp)
    if k > min(plant.ninputs, plant.noutputs):
        # the wider side of a non-square plant: L has rank min(m, p) < k, and the whole
        # loop's sigma_max depends on the units of the channels; loop-at-a-time only
        ms = wms = disk = math.nan
    else:
        ms, wms = _peak(S, w)
        half = S - 0.5 * np.eye(k)[:, :, None]
        disk = 1.0 / max(_peak(half, w)[0], 1e-300)
    out = []
    for i in range(k):
        notes = []
        if k == 1:
            figures = _siso_control(L, w, dt, notes)
            numeric = _siso_numeric(resp[0, 0], w)
            if figures is None:
                figures = numeric
            if not notes:
                with warnings.catch_warnings(record=True) as caught:
                    warnings.simplefilter('always')
                    try:
                        disk = float(control.disk_margins(L, w)[0])
                    except (ValueError, np.linalg.LinAlgError, TypeError) as err:
                        notes.append(f"python-control's disk_margins failed ({err}); the disk "
                                     'margin comes from the frequency response')
                for wmsg in caught:
                    if not issubclass(wmsg.category, DeprecationWarning):
                        notes.append(f"python-control's disk_margins warned ({wmsg.message})")
        else:
            rest = [j for j in range(k) if j != i]
            Li = resp[i, i] - np.einsum(
                'aw,abw,bw->w', resp[i, rest], _sensitivity(resp[np.ix_(rest, rest)]),
                resp[rest, i])
            figures = _siso_numeric(Li, w)
        low, high, phase, wp, delay, wd = figures
        channel = None if k == 1 else (names[i] if names else f'{side} {i + 1}')
        out.append(LoopMargins(side, channel, low, high, phase, wp, delay, wd, ms, wms,
                               disk, tuple(notes)))
    return out


def margin_warnings(margins, sample_time):
    """
    Return the warnings of a list of :class:`LoopMargins` against the module's thresholds.

    Parameters
    ----------
    margins : sequence of LoopMargins
        From :func:`loop_margins`.
    sample_time : float
        The vehicle's sample time (for the delay margin threshold).

    Returns
    -------
    list of str

    """
    out = []
    for m in margins:
        where = f'at the {m.where}'
        if m.gain_high < GAIN_MARGIN_WARN or m.gain_low > 1.0 / GAIN_MARGIN_WARN:
            out.append(f'gain margin {where}: the loop is stable only for loop gains '
                       f'{m.gain_low:.4g} to {m.gain_high:.4g}, less than '
                       f'{GAIN_MARGIN_WARN:g}x (6 dB) either way')
        if m.phase < PHASE_MARGIN_WARN:
            out.append(f'phase margin {where}: {m.phase:.3g} deg (at {m.phase_frequency:.3g} '
                       f'rad/s), below {PHASE_MARGIN_WARN:g} deg')
        if m.delay < DELAY_MARGIN_WARN_SAMPLES * sample_time:
            out.append(f'delay margin {where}: {m.delay * 1e3:.3g} ms (at '
                       f'{m.delay_frequency:.3g} rad/s), below {DELAY_MARGIN_WARN_SAMPLES:g} '
                       f'sample periods ({DELAY_MARGIN_WARN_SAMPLES * sample_time * 1e3:g} ms)')
        out.extend(f'{where}: {note}' for note in m.notes)
    seen = set()
    for m in margins:
        if m.side in seen:
            continue
        seen.add(m.side)
        if np.isfinite(m.peak_sensitivity) and m.peak_sensitivity > PEAK_SENSITIVITY_WARN:
            out.append(f'peak sensitivity at the plant {m.side}: Ms = '
                       f'{m.peak_sensitivity:.3g} (at {m.peak_frequency:.3g} rad/s), above '
                       f'{PEAK_SENSITIVITY_WARN:g} (6 dB); disk margin {m.disk:.3g}')
    return out
