# observer_ros.core.autocovariance: sample autocovariances from running lagged sums.
"""
Sample autocovariances of sequences given a block at a time (bounded memory).

:class:`LaggedSums` keeps, for lags ``j = 0 .. lags-1``, the sums of the lagged products
``sum_k e[k+j] e[k]^T`` within each sequence, carrying the last ``lags - 1`` rows of a
block into the next, so a sequence of any length is never held whole. Its
:meth:`~LaggedSums.autocovariances` are :func:`observer_ros.core.als.sample_autocovariances`
of the whole sequences (pooled the same way) up to the order of the float summation;
:meth:`~LaggedSums.whiteness` is the Ljung-Box test of
:func:`observer_ros.core.innovation.ljung_box_acf` (mean removed) of one output, from the
same sums, the first and last ``lags`` rows and the sum of the rows.

No ROS here: numpy and scipy only.

"""

import math

import numpy as np
from scipy.special import chdtrc

from .errors import ObserverError

__all__ = ['LaggedSums']


class LaggedSums:
    """
    Running lagged sums of one or more sequences of p-vectors.

    Parameters
    ----------
    p : int
        Size of each row.
    lags : int
        Number of lags kept (0 .. lags-1), at least 1.

    """

    def __init__(self, p, lags):
        if int(lags) < 1:
            raise ObserverError(f'lags must be at least 1, not {lags}')
        self.p, self.lags = int(p), int(lags)
        self.sums = np.zeros((self.lags, self.p, self.p))
        self.total = np.zeros(self.p)       # sum of every row (for the mean)
        self.samples = 0                    # rows of every sequence
        self.lengths = []                   # rows of each sequence
        self._tail = np.zeros((0, self.p))  # the current sequence's last lags-1 rows
        self._head = np.zeros((0, self.p))  # its first lags rows
        self._open = False

    def new_sequence(self):
        """Start a new sequence: no products across its start."""
        self._open = False

    def add(self, block):
        """Add the next rows ``(N, p)`` of the current sequence (a new one if none)."""
        block = np.asarray(block, dtype=float).reshape(-1, self.p)
        if not self._open:
            self.lengths.append(0)
            self._tail = np.zeros((0, self.p))
            self._head = np.zeros((0, self.p))
            self._open = True
        n = block.shape[0]
        if not n:
            return
        # rows of the previous blocks that pair with this block's first rows
        joined = np.concatenate([self._tail, block]) if self._tail.shape[0] else block
        t = self._tail.shape[0]
        for j in range(self.lags):
            if t + n - j <= 0:
                break
            # products e[k+j] e[k]^T whose later row k+j is in this block
            lo = max(t, j)
            self.sums[j] += joined[lo:].T @ joined[lo - j:t + n - j]
        self.total += block.sum(axis=0)
        self.samples += n
        self.lengths[-1] += n
        if self._head.shape[0] < self.lags:
            self._head = np.concatenate([self._head, block[:self.lags - self._head.shape[0]]])
        keep = self.lags - 1
        self._tail = joined[max(0, joined.shape[0] - keep):].copy() if keep else \
            np.zeros((0, self.p))
        self._last = joined[max(0, joined.shape[0] - self.lags):].copy()

    def autocovariances(self, lags=None):
        """
        Return ``C[j] = sum of e[k+j] e[k]^T / (samples - j * sequences)``, j < lags.

        Raises
        ------
        ObserverError
            A sequence has no more rows than lags (as the whole-array function).

        """
        lags = self.lags if lags is None else int(lags)
        if lags > self.lags or lags < 1 or not self.lengths or min(self.lengths) <= lags:
            raise _too_few(min(self.lengths, default=0), lags)
        out = self.sums[:lags].copy()
        for j in range(lags):
            out[j] /= self.samples - j * len(self.lengths)
        return out

    def whiteness(self, column, lags):
        """
        Ljung-Box whiteness of one column of a single sequence, mean removed.

        Returns the dict of :func:`observer_ros.bag.metrics.whiteness` (``samples``,
        ``residual_rms``, ``lags``, ``acf``, ``ljung_box_q``, ``ljung_box_p``,
        ``acf_outside``) for finite rows; the lag is reduced to ``samples // 4``.

        """
        if len(self.lengths) > 1:
            raise ObserverError('whiteness of pooled sequences: use one sequence')
        N = self.samples
        i = int(column)
        out = {'samples': int(N), 'lags': 0, 'acf': [], 'ljung_box_q': math.nan,
               'ljung_box_p': math.nan, 'acf_outside': math.nan,
               'residual_rms': math.sqrt(self.sums[0, i, i] / N) if N else math.nan}
        k = min(int(lags), N // 4, self.lags - 1)
        if k < 1:
            return out
        m = self.total[i] / N
        head = np.concatenate([[0.0], np.cumsum(self._head[:, i])])
        last = self._last[:, i]
        tail = np.concatenate([[0.0], np.cumsum(last[::-1])])
        # sum_{k < N-j} (x[k] - m)(x[k+j] - m) = S_j - m (A_j + B_j) + (N - j) m^2, with
        # A_j the sum without the last j rows and B_j without the first j
        denom = self.sums[0, i, i] - N * m * m
        if not denom > 0.0 or not math.isfinite(denom):
            return out
        j = np.arange(1, k + 1)
        lagged = self.sums[1:k + 1, i, i] - m * ((self.total[i] - tail[j]) +
                                                 (self.total[i] - head[j])) + (N - j) * m * m
        rho = lagged / denom
        q = float(N * (N + 2) * np.sum(rho ** 2 / (N - j)))
        out.update(lags=int(k), acf=rho.tolist(), ljung_box_q=q,
                   ljung_box_p=float(chdtrc(k, q)),
                   acf_outside=float(np.mean(np.abs(rho) > 1.96 / math.sqrt(N))))
        return out


def _too_few(rows, lags):
    from .als import ALSError
    return ALSError(f'{rows} innovations are too few for {lags} lags')
