# observer_ros.evaluation.metrics: errors against the truth and residual whiteness.
"""
Metrics of replayed estimates: errors against ``state/true``, residual whiteness.

Shared by ``observer-eval`` and ``observer-tune``; numpy (and scipy.special) only.

"""

import math

import numpy as np

from .running_metrics import BLOCK, blocked_state_metrics
from ..bag.spill import blocks, count_true, is_spilled, pairwise_sum, Sink, SortedColumn
from ..core.innovation import ljung_box_acf, ljung_box_of_products
from ..replay.replay import innovation_health
from ..timeutil import ns_to_secs

__all__ = ['DEFAULT_TOLERANCE', 'STEADY_FRACTION', 'WHITENESS_LAGS', 'truth_at',
           'TruthAt', 'StateError',
           'state_metrics', 'whiteness', 'tolerances', 'score_variant']

DEFAULT_TOLERANCE = 0.02        # fraction of each state's range in the true trajectory
STEADY_FRACTION = 0.2           # the last 20 % of the run is the steady state
WHITENESS_LAGS = 20             # autocorrelation lags 1..k of the residual
WHITENESS_BLOCK = 1 << 20       # values: the whiteness takes this many at a time


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
    """
    :func:`truth_at` for one truth, each epoch's truth sorted once for all calls.

    A truth in temporary files (:class:`~observer_ros.bag.spill.SpilledColumn`) is not
    copied: an epoch already in stamp order (a recording's truth) is searched where it
    is (:class:`~observer_ros.bag.spill.SortedColumn`), reading the rows each block of
    estimates needs; only an epoch out of stamp order is sorted in memory.

    """

    def __init__(self, truth):
        self.truth = truth
        self.prepared = {}
        self.ranges = _epoch_ranges(truth[2]) if is_spilled(truth[0]) else None

    def _epoch(self, e):
        if e not in self.prepared:
            t_ns, values, t_epoch = self.truth
            if self.ranges is not None:
                self.prepared[e] = self._spilled_epoch(e)
                return self.prepared[e]
            tsel = np.flatnonzero(t_epoch == e)
            order = np.argsort(t_ns[tsel], kind='stable')
            tn = t_ns[tsel][order]
            self.prepared[e] = (tn, values[tsel][order],
                                (tn - tn[0]).astype(np.float64) * 1e-9) if tsel.size else None
        return self.prepared[e]

    def _spilled_epoch(self, e):
        if e not in self.ranges:
            return None
        t_ns, values, _ = self.truth
        lo, hi = self.ranges[e]
        if _sorted(t_ns, lo, hi):
            return (SortedColumn(t_ns, lo, hi),)
        order = np.argsort(t_ns[lo:hi], kind='stable')      # out of order: in memory
        tn = t_ns[lo:hi][order]
        return tn, values[lo:hi][order], (tn - tn[0]).astype(np.float64) * 1e-9

    def __call__(self, stamp_ns, epoch, block=BLOCK):
        """Return the true state at these stamps (of these epochs), NaN where none."""
        out = np.full((stamp_ns.size, self.truth[1].shape[1]), np.nan)
        for lo in range(0, stamp_ns.size, block):
            eb = epoch[lo:lo + block]
            for e in np.unique(eb):
                prepared = self._epoch(e)
                if prepared is not None:
                    sel = lo + np.flatnonzero(eb == e)
                    if len(prepared) == 1:
                        _spilled_truth_rows(out, sel, stamp_ns[sel], prepared[0],
                                            self.truth[1])
                    else:
                        _truth_rows(out, sel, stamp_ns[sel], *prepared)
        return out


def _epoch_ranges(epoch):
    """Return ``{epoch: (first row, end)}`` of a column of contiguous epochs."""
    ranges = {}
    for lo, part in blocks(epoch):
        cuts = np.flatnonzero(np.diff(part)) + 1
        for start, end in zip([0, *cuts.tolist()], [*cuts.tolist(), part.size]):
            e = int(part[start])
            first = ranges.get(e, (lo + start,))[0]
            ranges[e] = (first, lo + end)
    return ranges


def _sorted(column, lo, hi):
    """Tell whether rows lo..hi-1 of a column are non-decreasing, a block at a time."""
    for start in range(lo, hi, BLOCK):
        part = column[start:min(hi, start + BLOCK + 1)]
        if np.any(part[1:] < part[:-1]):
            return False
    return True


def _spilled_truth_rows(out, sel, ns, found, values):
    """
    :func:`_truth_rows` on an epoch in stamp order where it is (``found`` searches it).

    The same numbers: the same position of each stamp, the exact matches' values, and
    ``np.interp`` over the two rows around each other stamp (those it interpolates
    between in the whole epoch), with the same seconds since the epoch's first stamp.

    """
    t_ns = found.column
    lo, hi = found.lo, found.hi
    first, last = int(t_ns[lo]), int(t_ns[hi - 1])
    pos = np.clip(found.searchsorted(ns), lo, hi - 1)
    exact = t_ns[pos] == ns
    out[sel[exact]] = values[pos[exact]]
    rest = ~exact & (ns >= first) & (ns <= last)
    if rest.any():
        at = np.unique(np.concatenate([pos[rest] - 1, pos[rest]]))
        x = (t_ns[at] - first).astype(np.float64) * 1e-9
        tv = values[at]
        q = (ns[rest] - first).astype(np.float64) * 1e-9
        for i in range(tv.shape[1]):
            out[sel[rest], i] = np.interp(q, x, tv[:, i])


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
        return ns_to_secs(self.stamp_ns[rows])


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
    # figures (Ljung-Box); the verdicts are core.whiteness's
    return _with_ljung_box(out, *ljung_box_acf(r, lags))


def _with_ljung_box(out, q, p, acf):
    """Add the Ljung-Box figures (:func:`whiteness`'s) to ``out``; return it."""
    if acf.size:
        out.update(lags=int(acf.size), acf=acf.tolist(), ljung_box_q=q, ljung_box_p=p,
                   acf_outside=float(np.mean(np.abs(acf) > 1.96 / math.sqrt(out['samples']))))
    return out


def tolerances(truth_values, names, fraction, absolute):
    """Return the settling band per state: ``absolute``, or ``fraction`` of its true range."""
    tol = {}
    spilled = truth_values is not None and is_spilled(truth_values)
    for i, name in enumerate(names):
        if absolute is not None:
            tol[name] = float(absolute)
            continue
        if spilled:
            span = _span(truth_values, i)
        else:
            col = truth_values[:, i] if truth_values is not None else np.zeros(0)
            col = col[np.isfinite(col)]
            span = float(np.ptp(col)) if col.size else 0.0
            if span <= 0.0:
                span = float(np.max(np.abs(col))) if col.size else 0.0
        if span <= 0.0:
            span = 1.0
        tol[name] = fraction * span
    return tol


def _span(values, i):
    """Return the range of column i's finite values (their largest magnitude if 0), by blocks."""
    low = high = None
    for _, part in blocks(values):
        col = part[:, i][np.isfinite(part[:, i])]
        if col.size:
            low = col.min() if low is None else min(low, col.min())
            high = col.max() if high is None else max(high, col.max())
    if low is None:
        return 0.0
    span = float(high - low)
    return span if span > 0.0 else float(max(abs(low), abs(high)))


def _matched_norm2(error, block=BLOCK, spill=None):
    """
    Return the rows of ``error`` with every state finite, and their squared norms.

    A block of rows at a time (each norm is summed over its own row, so the values do
    not depend on the block): no whole copies of the errors, the matched ones and
    their squares. With ``spill`` both columns are in temporary files.

    """
    ok = Sink(bool, (), len(error), spill)
    norm2 = Sink(np.float64, (), len(error), spill)     # the matched rows' only
    for lo in range(0, len(error), block):
        e = error[lo:lo + block]
        fine = np.all(np.isfinite(e), axis=1)
        ok.append(fine)
        norm2.append(np.sum(e[fine] ** 2, axis=1))
    return ok.result(), norm2.result()


def _finite_column(values, j, block=BLOCK, spill=None):
    """Return the finite values of column j in order, read a block of rows at a time."""
    count = sum(int(np.count_nonzero(np.isfinite(part[:, j])))
                for _, part in blocks(values, block))
    out = Sink(np.float64, (), count, spill)
    for _, part in blocks(values, block):
        col = part[:, j]
        out.append(col[np.isfinite(col)])
    return out.result()


def column_whiteness(values, j, lags=WHITENESS_LAGS, spill=None, block=WHITENESS_BLOCK):
    """
    :func:`whiteness` of the finite values of column j, in bounded memory.

    Up to ``block`` values (2^20 by default, 16 MiB) the values are taken whole:
    :func:`whiteness` itself. Beyond, they go to a temporary file with ``spill`` and are
    read back a block at a time: the mean and the RMS are numpy's sums of the whole
    sequence bit for bit (:func:`~observer_ros.bag.spill.pairwise_sum`), and the lagged
    products are summed block by block, in memory or spilled alike (so the figures are
    the same either way, and may differ from one product over the whole sequence in
    the last digits).

    """
    r = _finite_column(values, j, spill=spill)
    N = len(r)
    if N <= block:
        return whiteness(np.asarray(r), lags)
    mean = pairwise_sum(r) / N                  # x.mean()
    out = {'samples': int(N), 'residual_rms': float(np.sqrt(pairwise_sum(r, square=True) / N)),
           'lags': 0, 'acf': [], 'ljung_box_q': math.nan, 'ljung_box_p': math.nan,
           'acf_outside': math.nan}
    k = min(int(lags), N // 4)
    denom, lagged = 0.0, np.zeros(k)
    tail = np.zeros(0)                          # the last k values of d so far
    for _, part in blocks(r, block):
        d = part - mean
        denom += float(d @ d)
        T = tail.size
        for i in range(1, k + 1):
            if i < d.size:                      # both values of a pair in this block
                lagged[i - 1] += float(d[:-i] @ d[i:])
            c0, c1 = max(0, i - T), min(i, d.size)  # the earlier value before it
            if c1 > c0:
                lagged[i - 1] += float(tail[T + c0 - i:T + c1 - i] @ d[c0:c1])
        tail = (d[-k:] if d.size >= k else np.concatenate([tail, d])[-k:]).copy()
    return _with_ljung_box(out, *ljung_box_of_products(lagged, denom, N))


def score_variant(result, vr, health=True, states=True):
    """
    Fill a VariantResult's metrics (states against the truth, outputs' whiteness).

    ``health``: also each sensor's innovation health (``vr.sensors``; a gain search,
    which does not score it, leaves it out). ``states``: also each state's metrics
    (``vr.states``) and the settling time; without them the summary has the error
    norm's RMS and the matched count only.

    """
    rep = vr.replay
    plant = result.vehicle.plant
    # a replay whose rows are in temporary files: the per-row figures go there too
    spill = (rep.x_hat.directory or True) if is_spilled(rep.x_hat) else None
    if result.truth is not None and len(rep):
        if getattr(result, 'truth_at', None) is None:  # one sorted truth for every variant
            result.truth_at = TruthAt(result.truth)
        vr.error = StateError(rep, result.truth_at)    # computed block by block
        if states:
            tol = np.array([result.tolerance[s] for s in plant.state_names])
            metrics = state_metrics(_Seconds(rep.stamp_ns), vr.error, rep.epoch, tol)
            vr.states = dict(zip(plant.state_names, metrics))
        ok, norm2 = _matched_norm2(vr.error, spill=spill)
        vr.matched = ok
        vr.summary['matched'] = count_true(ok)
        vr.summary['error_rms'] = float(np.sqrt(np.mean(norm2))) if len(norm2) else math.nan
        if states:
            settles = [m['settling_time'] for m in metrics]
            vr.summary['settling_time'] = float(max(settles)) if settles else math.nan
    for j, name in enumerate(plant.output_names):
        vr.outputs[name] = column_whiteness(rep.residual, j, spill=spill) if len(rep) else \
            whiteness([])
    vr.sensors = innovation_health(rep, spill) if health else {}
