# observer_ros.core.als_stats: the statistics of ALS: weights, standard errors, lags.
"""
How sure an ALS estimate is, and how the least squares are weighted.

**Covariance of the sample autocovariances** (Bartlett's formula for a stationary
Gaussian vector process; Brockwell & Davis, *Time Series: Theory and Methods*, sec.
11.2): with ``G(d) = E[Y_t+d Y_t^T]`` the innovations' autocovariances, the averages
``c_il(j)`` over ``n`` pairs have::

    n Cov(c_il(j), c_ab(h)) -> sum_s [G_ia(s + j - h) G_lb(s) + G_ib(s + j + h) G_la(s)]

(:func:`autocovariance_covariance`); two averages over different numbers of pairs (outputs
missing at some samples) are scaled by ``1 / sqrt(n_r n_r')``, exact for white
innovations and close otherwise. G is the fitted model's, to as many lags as it takes
to decay.

**Weighted least squares** (Rajamani & Rawlings, Automatica 45(1), 2009: the weight
that minimises the estimate's variance is the inverse of that covariance): the rows are
the distinct entries of the autocovariances (lag 0's upper triangle, every entry of the
other lags) that have pairs; ``theta = argmin |W^(1/2) (M theta - c)|^2``, diagonal
unknowns non-negative (``scipy.optimize.lsq_linear``, bvls), and the covariance of the
estimate is ``(M^T W M)^-1`` (:func:`weighted_als`), whose diagonal gives each identified
entry's standard error. The weight needs the model, the model the estimate: a first fit
weighted by each row's white-noise variance, then the weighted one, then once more with
the weight of that estimate.

**Lags from the plant** (:func:`plant_lags`): each unknown's column of the ALS matrix is
the autocovariance its noise gives the reference filter's innovations, decaying with the
slowest mode of the filter that it excites and the outputs see. The decay is the lag
after which :data:`TAIL_ENERGY` of every column's energy is left; the lags are
:data:`DECAYS` times that: the later lags, whose expectation is known to be about zero,
are correlated with the earlier ones and so, weighted, take noise out of them (on the
submarine with noise on theta and w, 10^4 samples: the standard error of theta's noise
fell 5-fold from 1 to 4 decays). The cap (:func:`lag_cap`) keeps the lags below an
eighth of the samples and the rows below :data:`MAX_ROWS`.

No ROS here: numpy and scipy only.

"""

import math

import numpy as np
import scipy.linalg
from scipy.optimize import lsq_linear

__all__ = ['TAIL_ENERGY', 'DECAYS', 'MIN_LAGS', 'MAX_LAGS', 'MAX_ROWS', 'als_rows',
           'autocovariance_covariance', 'weighted_als', 'plant_lags', 'lag_cap']

#: The lags cover each unknown's column of the ALS matrix until this fraction of its
#: energy is left.
TAIL_ENERGY = 1e-3
#: The lags chosen cover this many times the decay.
DECAYS = 4
#: Fewest and most lags chosen from the plant.
MIN_LAGS = 10
MAX_LAGS = 2000
#: Most rows (distinct autocovariance entries) of the weighted least squares.
MAX_ROWS = 1500
#: Rows of the autocovariances' covariance computed at a time.
CHUNK = 128
#: The covariance of the rows is floored at this fraction of its largest eigenvalue.
FLOOR = 1e-9


def als_rows(lags, p):
    """
    Return the rows of the least squares: ``(lag, i, l)`` of each distinct entry.

    Lag 0's upper triangle (it is symmetric), then every entry of the later lags.

    Returns
    -------
    lag, i, l : (rows,) ndarray of int

    """
    iu, lu = np.triu_indices(p)
    ii, ll = np.meshgrid(np.arange(p), np.arange(p), indexing='ij')
    j = np.concatenate([np.zeros(iu.size, dtype=int),
                        np.repeat(np.arange(1, int(lags)), p * p)])
    i = np.concatenate([iu, np.tile(ii.ravel(), int(lags) - 1)])
    l_ = np.concatenate([lu, np.tile(ll.ravel(), int(lags) - 1)])
    return j, i, l_


def autocovariance_covariance(gamma, rows, counts):
    """
    Return the covariance of the sample autocovariances of ``rows`` (Bartlett).

    Parameters
    ----------
    gamma : (T, p, p) array_like
        ``G(d)``, d = 0 .. T-1 (zero beyond): the innovations' autocovariances, to as
        many lags as they take to decay.
    rows : tuple of (rows,) arrays
        ``(lag, i, l)`` of each entry (:func:`als_rows`).
    counts : (rows,) array_like
        The number of pairs each entry averages.

    Returns
    -------
    Sigma : (rows, rows) ndarray

    """
    gamma = np.asarray(gamma, dtype=float)
    T, p, _ = gamma.shape
    j, i, l_ = (np.asarray(r, dtype=int) for r in rows)
    L = int(j.max()) + 1 if j.size else 1
    # G(d) for d = -(T-1) .. T-1, G(-d) = G(d)^T
    full = np.concatenate([np.swapaxes(gamma[:0:-1], 1, 2), gamma])
    size = full.shape[0]
    nfft = 1 << int(math.ceil(math.log2(2 * size + 2 * L)))
    F = np.fft.rfft(full, n=nfft, axis=0)                         # (f, p, p)
    # corr[d, x, y, z, w] = sum_s G_xy(s + d) G_zw(s)
    prod = F[:, :, :, None, None] * np.conj(F[:, None, None, :, :])
    corr = np.fft.irfft(prod, n=nfft, axis=0)

    def at(d, x, y, z, w):
        return corr[np.mod(d, nfft), x, y, z, w]
    H, A, B = j[None, :], i[None, :], l_[None, :]
    n = np.asarray(counts, dtype=float)
    sigma = np.empty((j.size, j.size))
    for a in range(0, j.size, CHUNK):       # a few rows at a time: no (rows, rows) indices
        J, I, Lr = j[a:a + CHUNK, None], i[a:a + CHUNK, None], l_[a:a + CHUNK, None]
        sigma[a:a + CHUNK] = (at(J - H, I, A, Lr, B) + at(J + H, I, B, Lr, A)) / \
            np.sqrt(np.outer(n[a:a + CHUNK], n))
    return sigma


def _whitener(Sigma):
    """
    Return ``W`` with ``W(x) = L^-1 x`` for ``L L^T = Sigma``, Sigma's spectrum floored.

    A model far from the data can make Sigma nearly singular; its eigenvalues are then
    floored at :data:`FLOOR` of the largest, so that no row gets an unbounded weight.

    """
    S = Sigma + Sigma.T                     # one (rows, rows) array, scaled in place
    S *= 0.5
    scale = float(np.max(np.abs(np.diag(S)))) if S.size else 1.0
    if not scale > 0.0 or not math.isfinite(scale):
        return lambda x: x
    S /= scale
    root = math.sqrt(scale)
    try:
        floored = S.copy()
        floored[np.diag_indices_from(floored)] += FLOOR
        # symmetric: its transpose is the same matrix in the order LAPACK factors in place
        L = scipy.linalg.cholesky(floored.T, lower=True, overwrite_a=True)
        del floored
        d = np.diag(L)
        if float(np.min(d)) ** 2 >= FLOOR * float(np.max(d)) ** 2:
            return lambda x: scipy.linalg.solve_triangular(L, x, lower=True) / root
    except (np.linalg.LinAlgError, ValueError):
        pass
    w, V = np.linalg.eigh(S)
    w = np.maximum(w, FLOOR * max(float(w.max()), 1e-300))
    inv = V.T / np.sqrt(w)[:, None] / root
    return lambda x: inv @ x


def weighted_als(M, b, Sigma, nonneg):
    """
    Return the weighted least-squares estimate and its covariance.

    Parameters
    ----------
    M : (rows, U) array_like
        The ALS matrix on the rows.
    b : (rows,) array_like
        The sample autocovariances.
    Sigma : (rows, rows) array_like or (rows,) array_like
        Their covariance (or its diagonal): the weight is its inverse.
    nonneg : sequence of bool, or bool
        Unknowns kept non-negative.

    Returns
    -------
    theta : (U,) ndarray
        The estimate.
    cov : (U, U) ndarray
        ``(M^T Sigma^-1 M)^-1``: the covariance of the unconstrained estimate.
    fit : dict
        ``chi2`` (the weighted residual ``|Sigma^-1/2 (M theta - b)|^2``), ``dof`` (rows -
        unknowns), ``condition`` and ``rank`` of the whitened, column-scaled matrix.

    """
    M = np.asarray(M, dtype=float)
    b = np.asarray(b, dtype=float)
    Sigma = np.asarray(Sigma, dtype=float)
    if Sigma.ndim == 1:
        w = 1.0 / np.sqrt(Sigma)
        Mw, bw = M * w[:, None], b * w
    else:
        white = _whitener(Sigma)
        Mw, bw = white(M), white(b)
    scale = np.linalg.norm(Mw, axis=0)
    scale[scale == 0.0] = 1.0
    Ms = Mw / scale
    sv = np.linalg.svd(Ms, compute_uv=False)
    rank = int(np.sum(sv > 1e-9 * sv[0])) if sv.size and sv[0] > 0 else 0
    cond = float(sv[0] / sv[-1]) if sv.size and sv[-1] > 0 else math.inf
    U = M.shape[1]
    lower = np.where(np.broadcast_to(np.asarray(nonneg, dtype=bool), (U,)), 0.0, -np.inf)
    if np.all(np.isinf(lower)):
        z = np.linalg.lstsq(Ms, bw, rcond=None)[0]
    else:
        z = lsq_linear(Ms, bw, bounds=(lower, np.inf), method='bvls').x
    theta = z / scale
    if rank == U:
        inv = np.linalg.inv(Ms.T @ Ms)
        cov = inv / np.outer(scale, scale)
    else:
        cov = np.full((U, U), np.inf)
    chi2 = float(np.sum((Mw @ theta - bw) ** 2))
    return theta, cov, {'chi2': chi2, 'dof': int(M.shape[0] - U), 'condition': cond,
                        'rank': rank}


def lag_cap(samples, p):
    """Return the most lags for ``samples`` innovations of p outputs."""
    return int(max(2, min(MAX_LAGS, samples // 8, MAX_ROWS // max(p * p, 1))))


def plant_lags(columns, cap):
    """
    Return the lags that cover the decay of every unknown's column (see the module).

    Parameters
    ----------
    columns : (H, p, p, U) array_like
        Each unknown's model autocovariances over a long horizon H (> cap).
    cap : int
        The most lags.

    Returns
    -------
    lags : int
        :data:`DECAYS` times the decay, between :data:`MIN_LAGS` (or cap, if smaller) and
        cap.
    decay : int
        The lags the slowest column takes to decay (the horizon H when it does not
        within it).

    """
    X = np.asarray(columns, dtype=float)
    H = X.shape[0]
    energy = np.sum(X.reshape(H, -1, X.shape[-1]) ** 2, axis=1)      # (H, U)
    tail = np.cumsum(energy[::-1], axis=0)[::-1]                    # energy from lag j on
    total = tail[0]
    need = 0
    for u in range(energy.shape[1]):
        if not total[u] > 0.0:
            continue
        below = np.flatnonzero(tail[:, u] <= TAIL_ENERGY * total[u])
        need = max(need, int(below[0]) if below.size else H)
    lags = int(min(max(DECAYS * need, MIN_LAGS), cap))
    return max(lags, 1), need
