# observer_ros.core.autocovariance: sample autocovariances from running lagged sums.
"""
Sample autocovariances of sequences given a block at a time (bounded memory).

:class:`LaggedSums` keeps, for lags ``j = 0 .. lags-1``, the sums of the lagged products
``sum_k e[k+j] e[k]^T`` within each sequence, carrying the last ``lags - 1`` rows of a
block into the next, so a sequence of any length is never held whole. Its
:meth:`~LaggedSums.autocovariances` are :func:`observer_ros.core.als.sample_autocovariances`
of the whole sequences (pooled the same way) up to the order of the float summation.
A missing value (NaN: an output not measured at that step) enters no product: the sums
are over the pairs that exist, and each lag's count of them is kept per pair of columns
(:attr:`~LaggedSums.counts`), so the autocovariances are the averages over those pairs.

No ROS here: numpy only.

"""

import numpy as np

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
        self.samples = 0                    # rows of every sequence
        self.lengths = []                   # rows of each sequence
        self._tail = np.zeros((0, self.p))  # the current sequence's last lags-1 rows
        self._open = False
        self._counts = None                 # per lag and pair; None while nothing is missing

    @property
    def counts(self):
        """Return the number of products in each sum, ``(lags, p, p)``."""
        if self._counts is not None:
            return self._counts.copy()
        j = np.arange(self.lags)
        full = np.sum(np.maximum(np.subtract.outer(self.lengths, j), 0), axis=0) \
            if self.lengths else np.zeros(self.lags)
        return np.broadcast_to(full[:, None, None].astype(float),
                               (self.lags, self.p, self.p)).copy()

    @property
    def missing(self):
        """Return the number of missing values of each column."""
        if self._counts is None:
            return np.zeros(self.p, dtype=np.int64)
        return self.samples - np.rint(np.diagonal(self._counts[0])).astype(np.int64)

    def new_sequence(self):
        """Start a new sequence: no products across its start."""
        self._open = False

    def add(self, block):
        """Add the next rows ``(N, p)`` of the current sequence (a new one if none)."""
        block = np.asarray(block, dtype=float).reshape(-1, self.p)
        finite = np.isfinite(block)
        gaps = not finite.all()
        if gaps and self._counts is None:
            self._counts = self.counts          # every pair so far existed
        if gaps:
            block = np.where(finite, block, 0.0)
        if not self._open:
            self.lengths.append(0)
            self._tail = np.zeros((0, self.p))
            self._mtail = np.zeros((0, self.p))
            self._open = True
        n = block.shape[0]
        if not n:
            return
        # rows of the previous blocks that pair with this block's first rows
        joined = np.concatenate([self._tail, block]) if self._tail.shape[0] else block
        t = self._tail.shape[0]
        mask = None
        if self._counts is not None:
            mask = np.concatenate([self._mtail, finite.astype(float)])
        for j in range(self.lags):
            if t + n - j <= 0:
                break
            # products e[k+j] e[k]^T whose later row k+j is in this block
            lo = max(t, j)
            self.sums[j] += joined[lo:].T @ joined[lo - j:t + n - j]
            if mask is not None:
                self._counts[j] += mask[lo:].T @ mask[lo - j:t + n - j]
        self.samples += n
        self.lengths[-1] += n
        keep = self.lags - 1
        self._tail = joined[max(0, joined.shape[0] - keep):].copy() if keep else \
            np.zeros((0, self.p))
        if mask is not None:
            self._mtail = mask[max(0, mask.shape[0] - keep):].copy() if keep else \
                np.zeros((0, self.p))
        else:
            self._mtail = np.ones(self._tail.shape)

    def autocovariances(self, lags=None):
        """
        Return ``C[j]``: the sum of ``e[k+j] e[k]^T`` over the pairs that exist, averaged.

        With nothing missing, ``sum / (samples - j * sequences)``; otherwise each entry
        is divided by its own count (:attr:`counts`; NaN where there is no pair).

        Raises
        ------
        ObserverError
            A sequence has no more rows than lags (as the whole-array function).

        """
        lags = self.lags if lags is None else int(lags)
        if lags > self.lags or lags < 1 or not self.lengths or min(self.lengths) <= lags:
            raise _too_few(min(self.lengths, default=0), lags)
        out = self.sums[:lags].copy()
        if self._counts is None:
            for j in range(lags):
                out[j] /= self.samples - j * len(self.lengths)
            return out
        with np.errstate(invalid='ignore', divide='ignore'):
            return np.where(self._counts[:lags] > 0, out / self._counts[:lags], np.nan)


def _too_few(rows, lags):
    from .als import ALSError
    return ALSError(f'{rows} innovations are too few for {lags} lags')
