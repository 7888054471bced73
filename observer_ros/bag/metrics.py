# observer_ros.bag.metrics: errors against the truth and residual whiteness.
"""
Metrics of replayed estimates: errors against ``state/true``, residual whiteness.

Shared by ``observer-eval`` and ``observer-tune``; numpy (and scipy.special) only.

"""

import math

import numpy as np

from .running_metrics import BLOCK, blocked_state_metrics
from ..core.innovation import ljung_box_acf
from ..replay.replay import innovation_health

__all__ = ['DEFAULT_TOLERANCE', 'STEADY_FRACTION', 'WHITENESS_LAGS', 'truth_at',
           'TruthAt', 'StateError',
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
    return TruthAt(truth)(stamp_ns, epoch, block)


class TruthAt:
    """:func:`truth_at` for one truth, each epoch's truth sorted once for all calls."""

    def __init__(self, truth):
        self.truth = truth
        self.prepared = {}

    def _epoch(self, e):
        if e not in self.prepared:
            t_ns, values, t_epoch = self.truth
            tsel = np.flatnonzero(t_epoch == e)
            order = np.argsort(t_ns[tsel], kind='stable')
            tn = t_ns[tsel][order]
            self.prepared[e] = (tn, values[tsel][order],
                                (tn - tn[0]).astype(np.float64) * 1e-9) if tsel.size else None
        return self.prepared[e]

    def __call__(self, stamp_ns, epoch, block=BLOCK):
        """Return the true state at these stamps (of these epochs), NaN where none."""
        out = np.full((stamp_ns.size, self.truth[1].shape[1]), np.nan)
        for lo in range(0, stamp_ns.size, block):
            eb = epoch[lo:lo + block]
            for e in np.unique(eb):
                prepared = self._epoch(e)
                if prepared is not None:
                    sel = lo + np.flatnonzero(eb == e)
                    _truth_rows(out, sel, stamp_ns[sel], *prepared)
        return out


class StateError:
    """
    The error ``x_hat - x_true`` of a replay, computed for the rows asked for.

    Never held whole: ``error[rows]`` (a slice, mask or index array) computes those rows
    (each row alone, so any rows give the values of the whole array); ``np.asarray``
    gives the whole array for a caller that wants it. ``truth`` is the truth tuple or a
    :class:`TruthAt` (one shared by the variants of a bag: its sorted copy made once).

    """

    def __init__(self, rep, truth):
        self.x_hat, self.stamp_ns, self.epoch = rep.x_hat, rep.stamp_ns, rep.epoch
        self.truth = truth if isinstance(truth, TruthAt) else TruthAt(truth)
        self.shape = rep.x_hat.shape
        self.ndim = 2

    def __len__(self):
        return self.shape[0]

    def __getitem__(self, rows):
        x_true = self.truth(self.stamp_ns[rows], self.epoch[rows])
        return np.subtract(self.x_hat[rows], x_true, out=x_true)   # in place: no copy

    def __array__(self, dtype=None, copy=None):
        whole = self[:]
        return whole if dtype is None else whole.astype(dtype)


class _Seconds:
    """A replay's stamps in seconds (``ns * 1e-9``), converted for the rows asked for."""

    def __init__(self, stamp_ns):
        self.stamp_ns = stamp_ns
        self.size = stamp_ns.size

    def __getitem__(self, rows):
        return self.stamp_ns[rows].astype(np.float64) * 1e-9


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
    finite = np.isfinite(r)
    if not finite.all():
        r = r[finite]
    del finite
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


def _matched_norm2(error, block=BLOCK):
    """
    Return the rows of ``error`` with every state finite, and their squared norms.

    A block of rows at a time (each norm is summed over its own row, so the values do
    not depend on the block): no whole copies of the errors, the matched ones and
    their squares.

    """
    ok = np.zeros(len(error), dtype=bool)
    norm2 = np.empty(ok.size)                   # the matched rows' first: no parts joined
    done = 0
    for lo in range(0, ok.size, block):
        e = error[lo:lo + block]
        ok[lo:lo + e.shape[0]] = fine = np.all(np.isfinite(e), axis=1)
        part = np.sum(e[fine] ** 2, axis=1)
        norm2[done:done + part.size] = part
        done += part.size
    return ok, norm2[:done]


def _finite_column(values, j, block=BLOCK):
    """Return the finite values of column j in order, read a block of rows at a time."""
    blocks = range(0, len(values), block)
    count = sum(int(np.count_nonzero(np.isfinite(values[lo:lo + block, j]))) for lo in blocks)
    out = np.empty(count)
    done = 0
    for lo in blocks:
        col = values[lo:lo + block, j]
        col = col[np.isfinite(col)]
        out[done:done + col.size] = col
        done += col.size
    return out


def score_variant(result, vr, health=True):
    """
    Fill a VariantResult's metrics (states against the truth, outputs' whiteness).

    ``health``: also each sensor's innovation health (``vr.sensors``; a gain search,
    which does not score it, leaves it out).

    """
    rep = vr.replay
    plant = result.vehicle.plant
    if result.truth is not None and len(rep):
        if getattr(result, 'truth_at', None) is None:  # one sorted truth for every variant
            result.truth_at = TruthAt(result.truth)
        vr.error = StateError(rep, result.truth_at)    # computed block by block
        tol = np.array([result.tolerance[s] for s in plant.state_names])
        metrics = state_metrics(_Seconds(rep.stamp_ns), vr.error, rep.epoch, tol)
        vr.states = dict(zip(plant.state_names, metrics))
        ok, norm2 = _matched_norm2(vr.error)
        vr.matched = ok
        vr.summary['matched'] = int(ok.sum())
        vr.summary['error_rms'] = float(np.sqrt(np.mean(norm2))) if ok.any() else math.nan
        settles = [m['settling_time'] for m in metrics]
        vr.summary['settling_time'] = float(max(settles)) if settles else math.nan
    for j, name in enumerate(plant.output_names):
        vr.outputs[name] = whiteness(_finite_column(rep.residual, j)) if len(rep) else \
            whiteness([])
    vr.sensors = innovation_health(rep) if health else {}
