# observer_ros.bag.metrics: errors against the truth and residual whiteness.
"""
Metrics of replayed estimates: errors against ``state/true``, residual whiteness.

Shared by ``observer-eval`` and ``observer-tune``; numpy (and scipy.special) only.

"""

import math

import numpy as np

from .replay import innovation_health
from .running_metrics import BLOCK, blocked_state_metrics
from ..core.innovation import ljung_box_acf

__all__ = ['DEFAULT_TOLERANCE', 'STEADY_FRACTION', 'WHITENESS_LAGS', 'truth_at',
           'state_metrics', 'whiteness', 'tolerances', 'score_variant']

DEFAULT_TOLERANCE = 0.02        # fraction of each state's range in the true trajectory
STEADY_FRACTION = 0.2           # the last 20 % of the run is the steady state
WHITENESS_LAGS = 20             # autocorrelation lags 1..k of the residual


def truth_at(truth, stamp_ns, epoch, block=BLOCK):
    """
    Return the true state at the estimates' stamps.

    Exact where a truth stamp matches, linear interpolation inside the epoch's truth
    otherwise, NaN outside. The estimates are taken ``block`` at a time (the temporaries
    are bounded by the block; every value is computed alone, so the result does not
    depend on the block).

    """
    t_ns, values, t_epoch = truth
    out = np.full((stamp_ns.size, values.shape[1]), np.nan)
    prepared = {}
    for lo in range(0, stamp_ns.size, block):
        eb = epoch[lo:lo + block]
        for e in np.unique(eb):
            if e not in prepared:
                tsel = np.flatnonzero(t_epoch == e)
                order = np.argsort(t_ns[tsel], kind='stable')
                tn = t_ns[tsel][order]
                prepared[e] = (tn, values[tsel][order],
                               (tn - tn[0]).astype(np.float64) * 1e-9) if tsel.size else None
            if prepared[e] is not None:
                sel = lo + np.flatnonzero(eb == e)
                _truth_rows(out, sel, stamp_ns[sel], *prepared[e])
    return out


def _truth_rows(out, sel, ns, tn, tv, x):
    pos = np.clip(np.searchsorted(tn, ns), 0, tn.size - 1)
    exact = tn[pos] == ns
    out[sel[exact]] = tv[pos[exact]]
    rest = ~exact & (ns >= tn[0]) & (ns <= tn[-1])
    if rest.any():
        q = (ns[rest] - tn[0]).astype(np.float64) * 1e-9
        for i in range(tv.shape[1]):
            out[sel[rest], i] = np.interp(q, x, tv[:, i])


def state_metrics(t, error, epoch, tolerance, steady_fraction=STEADY_FRACTION):
    """
    Per-state error metrics.

    Parameters
    ----------
    t : (N,) float
        Times (s) of the samples, increasing within each epoch.
    error : (N, n) float
        x_hat - x_true; rows with NaN are not matched and are left out.
    epoch : (N,) int
        Clock-jump epochs: settling is measured from each epoch's first sample.
    tolerance : (n,) float
        Settling band per state.
    steady_fraction : float
        The steady state is the last fraction of each epoch (by time).

    Returns
    -------
    metrics : list of dict
        One per state: samples, rmse, max_abs_error, settling_time, ss_std, ss_mean.
        Computed block by block (``running_metrics``): memory bounded by the block.

    """
    return blocked_state_metrics(t, error, epoch, tolerance, steady_fraction)


def whiteness(r, lags=WHITENESS_LAGS):
    """
    Whiteness of a residual sequence.

    Parameters
    ----------
    r : (N,) float
        Residuals in order (non-finite entries are dropped).
    lags : int
        Largest lag k (reduced to N // 4 for short sequences).

    Returns
    -------
    stats : dict
        ``samples``, ``residual_rms``, ``lags``, ``acf`` (lags 1..k, normalised, mean
        removed), ``ljung_box_q`` = N (N + 2) sum rho_k^2 / (N - k), ``ljung_box_p`` (chi^2
        with k degrees of freedom: small means not white), ``acf_outside`` (fraction of
        lags with |rho_k| > 1.96 / sqrt(N); about 0.05 for white noise).

    """
    r = np.asarray(r, dtype=float)
    r = r[np.isfinite(r)]
    N = r.size
    out = {'samples': int(N), 'residual_rms': float(np.sqrt(np.mean(r * r))) if N else math.nan,
           'lags': 0, 'acf': [], 'ljung_box_q': math.nan, 'ljung_box_p': math.nan,
           'acf_outside': math.nan}
    q, p, acf = ljung_box_acf(r, lags)          # the node's whiteness test (core.innovation)
    if not acf.size:
        return out
    out.update(lags=int(acf.size), acf=acf.tolist(), ljung_box_q=q, ljung_box_p=p,
               acf_outside=float(np.mean(np.abs(acf) > 1.96 / math.sqrt(N))))
    return out


def tolerances(truth_values, names, fraction, absolute):
    """Return the settling band per state: ``absolute``, or ``fraction`` of its true range."""
    tol = {}
    for i, name in enumerate(names):
        if absolute is not None:
            tol[name] = float(absolute)
            continue
        col = truth_values[:, i] if truth_values is not None else np.zeros(0)
        col = col[np.isfinite(col)]
        span = float(np.ptp(col)) if col.size else 0.0
        if span <= 0.0:
            span = float(np.max(np.abs(col))) if col.size else 0.0
        if span <= 0.0:
            span = 1.0
        tol[name] = fraction * span
    return tol


def score_variant(result, vr):
    """Fill a VariantResult's metrics (states against the truth, outputs' whiteness)."""
    rep = vr.replay
    plant = result.vehicle.plant
    if result.truth is not None and len(rep):
        x_true = truth_at(result.truth, rep.stamp_ns, rep.epoch)
        vr.error = rep.x_hat - x_true
        tol = np.array([result.tolerance[s] for s in plant.state_names])
        metrics = state_metrics(rep.t, vr.error, rep.epoch, tol)
        vr.states = dict(zip(plant.state_names, metrics))
        ok = np.all(np.isfinite(vr.error), axis=1)
        norm2 = np.sum(vr.error[ok] ** 2, axis=1)
        vr.summary['matched'] = int(ok.sum())
        vr.summary['error_rms'] = float(np.sqrt(np.mean(norm2))) if ok.any() else math.nan
        settles = [m['settling_time'] for m in metrics]
        vr.summary['settling_time'] = float(max(settles)) if settles else math.nan
    for j, name in enumerate(plant.output_names):
        vr.outputs[name] = whiteness(rep.residual[:, j]) if len(rep) else whiteness([])
    vr.sensors = innovation_health(rep)
