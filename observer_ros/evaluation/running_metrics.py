# observer_ros.evaluation.running_metrics: per-state error metrics fed block by block.
"""
Per-state error metrics computed from blocks of samples, in memory bounded by the block.

:func:`observer_ros.evaluation.metrics.state_metrics` defines the metrics; this module computes
the same ones without copies of the whole series (rows with a NaN left out, one epoch
selected, the steady state selected), so a long bag can be scored block by block:

- rmse and max |error|: running sums of squares and maxima;
- settling time: per epoch and state, the time (from the epoch's first matched sample)
  of the sample after the last one outside the band, carried across blocks; inf (printed
  ``never``) when that sample falls in the steady state (the last ``steady_fraction`` of
  the epoch: the error leaves the band there, it has not settled) or the epoch's last
  sample is outside;
- steady state: the last ``steady_fraction`` of each epoch by time, known before the
  blocks from each epoch's first and last matched time (:func:`epoch_spans`, one pass
  over the times only); its mean and population std merged block by block (Chan, Golub
  and LeVeque's pairwise update of count, mean and sum of squared deviations).

"""

import math

import numpy as np

__all__ = ['BLOCK', 'epoch_spans', 'StateAccumulator', 'blocked_state_metrics']

BLOCK = 1 << 16                  # rows per block


def _finite_rows(error):
    return np.all(np.isfinite(error), axis=1)


def epoch_spans(t, error, epoch, block=BLOCK):
    """Return ``{epoch: (first, last)}`` times of the rows without NaN, block by block."""
    spans = {}
    for lo in range(0, t.size, block):
        hi = lo + block
        ok = _finite_rows(error[lo:hi])
        tb, eb = t[lo:hi][ok], epoch[lo:hi][ok]
        for e in np.unique(eb):
            te = tb[eb == e]
            spans[int(e)] = (spans.get(int(e), te)[0], te[-1])
    return spans


class StateAccumulator:
    """
    Running per-state error metrics over blocks of (t, error, epoch) rows.

    Parameters
    ----------
    n : int
        Number of states.
    tolerance : (n,) float
        Settling band per state.
    spans : dict
        ``{epoch: (first, last)}`` matched times (:func:`epoch_spans`).
    steady_fraction : float
        The steady state is the last fraction of each epoch (by time).

    """

    def __init__(self, n, tolerance, spans, steady_fraction):
        self.n = n
        self.tolerance = np.asarray(tolerance, dtype=float)
        self.spans = spans
        self.fraction = steady_fraction
        self.count = 0
        self.sumsq = np.zeros(n)
        self.max_abs = np.full(n, -math.inf)
        self.ss_count = 0
        self.ss_mean = np.zeros(n)
        self.ss_m2 = np.zeros(n)
        self.after_bad = {}          # epoch -> (n,) tau after the last outside sample
        self.pending = {}            # epoch -> (n,) bool: the last sample seen is outside

    def update(self, t, error, epoch):
        """Add a block of rows (rows with a NaN are left out, as in ``state_metrics``)."""
        ok = _finite_rows(error)
        if not ok.all():
            t, error, epoch = t[ok], error[ok], epoch[ok]
        if not t.size:
            return
        self.count += t.size
        self.sumsq += np.einsum('ij,ij->j', error, error)
        self.max_abs = np.maximum(self.max_abs, np.max(np.abs(error), axis=0))
        steady = np.zeros(t.size, dtype=bool)
        for e in np.unique(epoch):
            e = int(e)
            sel = np.flatnonzero(epoch == e)
            first, last = self.spans[e]
            tau = t[sel] - first
            steady[sel[tau >= (1.0 - self.fraction) * (last - first)]] = True
            self._settling(e, tau, np.abs(error[sel]) > self.tolerance[None, :])
        if steady.any():
            self._merge_steady(error[steady])

    def _settling(self, e, tau, outside):
        after = self.after_bad.setdefault(e, np.zeros(self.n))
        pending = self.pending.setdefault(e, np.zeros(self.n, dtype=bool))
        for i in range(self.n):
            bad = np.flatnonzero(outside[:, i])
            if bad.size and bad[-1] == tau.size - 1:
                pending[i] = True
            elif bad.size:
                after[i], pending[i] = tau[bad[-1] + 1], False
            elif pending[i]:
                after[i], pending[i] = tau[0], False

    def _merge_steady(self, ss):
        nb = ss.shape[0]
        mean_b = np.mean(ss, axis=0)
        m2_b = np.sum((ss - mean_b) ** 2, axis=0)
        na = self.ss_count
        total = na + nb
        delta = mean_b - self.ss_mean
        self.ss_mean = self.ss_mean + delta * (nb / total)
        self.ss_m2 = self.ss_m2 + m2_b + delta * delta * (na * nb / total)
        self.ss_count = total

    def result(self):
        """Return one dict per state, as ``state_metrics``."""
        if not self.count:
            return [{'samples': 0, 'rmse': math.nan, 'max_abs_error': math.nan,
                     'settling_time': math.nan, 'ss_std': math.nan, 'ss_mean': math.nan}
                    for _ in range(self.n)]
        settle = np.zeros(self.n)
        for e, after in self.after_bad.items():
            # settled: inside the band from then on, through the steady state (the last
            # steady_fraction of the epoch); later than that, or outside at the end, is
            # never (an error that leaves the band in the steady state has not settled)
            first, last = self.spans[e]
            late = after > (1.0 - self.fraction) * (last - first)
            settle = np.maximum(settle, np.where(self.pending[e] | late, math.inf, after))
        out = []
        for i in range(self.n):
            k = self.ss_count
            out.append({
                'samples': int(self.count),
                'rmse': float(math.sqrt(self.sumsq[i] / self.count)),
                'max_abs_error': float(self.max_abs[i]),
                'settling_time': float(settle[i]),
                'ss_std': float(math.sqrt(self.ss_m2[i] / k)) if k > 1 else math.nan,
                'ss_mean': float(self.ss_mean[i]) if k else math.nan,
            })
        return out


def blocked_state_metrics(t, error, epoch, tolerance, steady_fraction, block=BLOCK):
    """Return ``state_metrics`` computed over blocks of ``block`` rows."""
    acc = StateAccumulator(error.shape[1], tolerance, epoch_spans(t, error, epoch, block),
                           steady_fraction)
    for lo in range(0, t.size, block):
        acc.update(t[lo:lo + block], error[lo:lo + block], epoch[lo:lo + block])
    return acc.result()
