# observer_ros.core.als: noise covariances from innovations (autocovariance least squares).
"""
Autocovariance least squares (ALS): process and measurement noise covariances from data.

Written from Odelson, Rajamani & Rawlings, "A new autocovariance least-squares method for
estimating noise covariances", Automatica 42(2), 2006, and Rajamani & Rawlings,
"Estimation of the disturbance structure from data using semidefinite programming and
optimal weighting", Automatica 45(1), 2009.

Model (discrete time, the sample period of the data; a continuous plant is sampled with a
zero-order hold, as the estimators do)::

    x[k+1] = Ad x[k] + Bd u[k] + w[k],    cov w = Qk = F(Q)   (n x n)
    y[k]   = C x[k] + D u[k] + v[k],      cov v = R           (p x p)

``F`` maps the identified parameter Q (k x k, on the columns of a noise input matrix G) to
the covariance added per step, linearly: ``G Q G^T`` for a discrete plant (Q per sample),
``int_0^dt expm(A s) G Q G^T expm(A^T s) ds`` for a continuous plant (Q an intensity,
:func:`~observer_ros.core.estimators.process_noise_covariance`), so the result is what the
vehicle file's ``observer.Qd`` means.

A stable predictor ``xh[k+1] = Ad xh[k] + Bd u[k] + Lp (y[k] - C xh[k] - D u[k])`` (any
gain with eig(Ad - Lp C) inside the unit circle) has innovations ``Y[k] = y[k] - C xh[k] -
D u[k]`` with ``e[k+1] = Abar e[k] + w[k] - Lp v[k]``, ``Abar = Ad - Lp C``, ``Y[k] = C
e[k] + v[k]``. In steady state ``P = Abar P Abar^T + Qk + Lp R Lp^T`` and the
autocovariances are::

    C0 = E[Y[k] Y[k]^T]   = C P C^T + R
    Cj = E[Y[k+j] Y[k]^T] = C Abar^j P C^T - C Abar^(j-1) Lp R,    j >= 1

linear in (Q, R). Stacking ``C0 .. C(N-1)`` for each basis element of the unknowns (one
discrete Lyapunov solution each) gives the ALS matrix; the sample autocovariances of the
measured innovations (after the transient) are the right-hand side. When outputs are
missing at some samples or the stamps jitter, the innovations are those of the filter run
at the actual stamps and the ALS matrix that of the time-varying model along the data's
own sequence (:mod:`observer_ros.core.als_ltv`); each sample autocovariance is then the
average over the pairs that exist.

The least squares are weighted by the inverse covariance of the sample autocovariances
(Bartlett's formula under the fitted model: :mod:`observer_ros.core.als_stats`), which
also gives the covariance of the estimate, hence a standard error for every identified
entry. Diagonal Q and R are solved non-negative (``scipy.optimize.lsq_linear``); full
symmetric ones by least squares and projected onto the positive semidefinite cone. The
unknowns are identifiable when the (weighted, column-scaled) ALS matrix has full column
rank; otherwise :class:`ALSError`. The number of lags is chosen from the plant when not
given (:func:`choose_lags`): enough for the slowest mode of the reference filter that the
noise excites and the outputs see.

No ROS here: numpy and scipy only.

"""

from dataclasses import dataclass
import math

import numpy as np
import scipy.linalg
import scipy.signal

from .als_stats import (als_rows, autocovariance_covariance, lag_cap, plant_lags,
                        weighted_als)
from .errors import ObserverError
from .model import as_matrix

__all__ = ['ALSError', 'ALSResult', 'DEFAULT_LAGS', 'RANK_TOL', 'predictor_innovations',
           'predictor_blocks', 'sample_autocovariances', 'model_autocovariances',
           'autocovariance_sigma', 'choose_lags',
           'process_noise_map', 'als_matrix', 'identify_noise', 'kalman_predictor_gain']

#: Lags when none are given: None, chosen from the plant (:func:`choose_lags`).
DEFAULT_LAGS = None
#: The ALS matrix (columns scaled to unit norm) is rank deficient when its smallest
#: singular value is below this fraction of the largest.
RANK_TOL = 1e-9
#: Eigenvector condition up to which a predictor runs mode by mode (see :func:`_modes`).
MODAL_CONDITION = 1e6


class ALSError(ObserverError, ValueError):
    """The noise covariances cannot be identified from these data with this model."""


@dataclass
class ALSResult:
    """
    What :func:`identify_noise` found.

    ``Q`` (k x k) and ``R`` (p x p) are the identified covariances (``Q`` in the units of
    the map ``F``: an intensity for a continuous plant); ``Qk`` = F(Q) per step;
    ``Q_std`` and ``R_std`` the standard error of each entry (the covariance of the
    weighted least squares, ``cov`` over the unknowns ``labels``: ``('Q', i, j)`` or
    ``('R', i, j)``). ``empirical`` and ``fitted`` are the autocovariances (lags, p, p)
    of the data and of the identified model for the reference gain; ``sigma`` (lags, p)
    the standard deviation of the empirical diagonal ones (Bartlett). ``condition`` is
    the condition number of the weighted, column-scaled ALS matrix, ``rank`` its rank of
    ``unknowns``; ``residual`` the weighted residual (chi-square with ``dof`` degrees of
    freedom when the model fits); ``decay`` the lags the slowest column needs.

    """

    Q: np.ndarray
    R: np.ndarray
    Qk: np.ndarray
    lags: int
    samples: int
    empirical: np.ndarray
    fitted: np.ndarray
    sigma: np.ndarray
    condition: float
    rank: int
    unknowns: int
    residual: float
    full: bool
    raw: np.ndarray        # the unconstrained / unprojected solution, stacked
    Q_std: np.ndarray = None
    R_std: np.ndarray = None
    cov: np.ndarray = None
    labels: list = None
    names: tuple = None
    dof: int = 0
    decay: int = 0
    counts: np.ndarray = None
    auto_lags: int = 0

    def entries(self):
        """Return ``(kind, name, value, std)`` of every identified entry (Q's first)."""
        qn, rn = self.names if self.names is not None else \
            ([f'Q[{i}]' for i in range(self.Q.shape[0])],
             [f'R[{i}]' for i in range(self.R.shape[0])])
        out = []
        for kind, i, j in self.labels or []:
            names, M, S = (qn, self.Q, self.Q_std) if kind == 'Q' else (rn, self.R, self.R_std)
            name = names[i] if i == j else f'{names[i]},{names[j]}'
            out.append((kind, name, float(M[i, j]),
                        float(S[i, j]) if S is not None else math.nan))
        return out

    def correlation(self):
        """Return the correlation matrix of the unknowns' estimates."""
        d = np.sqrt(np.abs(np.diag(self.cov)))
        with np.errstate(invalid='ignore', divide='ignore'):
            return self.cov / np.outer(d, d)

    def to_dict(self):
        """Return the result as JSON-ready data."""
        return {'Q': self.Q.tolist(), 'R': self.R.tolist(), 'Qk': self.Qk.tolist(),
                'Q_std': None if self.Q_std is None else self.Q_std.tolist(),
                'R_std': None if self.R_std is None else self.R_std.tolist(),
                'lags': self.lags, 'decay_lags': self.decay, 'samples': self.samples,
                'condition': self.condition, 'rank': self.rank, 'unknowns': self.unknowns,
                'residual': self.residual, 'dof': self.dof,
                'form': 'full' if self.full else 'diagonal'}


def predictor_innovations(Ad, Bd, C, D, Lp, y, u, u_meas=None, x0=None, states=False,
                          final=False):
    """
    Innovations of a fixed-gain predictor run over sampled data.

    Parameters
    ----------
    Ad, Bd, C, D : array_like
        Sampled model (n x n, n x m, p x n, p x m).
    Lp : (n, p) array_like
        Predictor gain; eig(Ad - Lp C) should be inside the unit circle.
    y : (N, p) array_like
        Measurements at the samples.
    u : (N, m) array_like
        Input held from sample k to k + 1.
    u_meas : (N, m) array_like, optional
        Input in effect when y[k] was measured (for D u); default ``u``.
    x0 : (n,) array_like, optional
        Initial prediction; zeros by default.
    states : bool
        Also return the predictions.
    final : bool
        Also return the prediction after the last sample (``xh[N]``, to go on from).

    Returns
    -------
    innovations : (N, p) ndarray
        ``y[k] - C xh[k] - D u_meas[k]``.
    xh : (N, n) ndarray
        The predictions ``xh[k]`` (only with ``states``).
    x_next : (n,) ndarray
        ``xh[N]`` (only with ``final``).

    """
    Ad = as_matrix(Ad, 'Ad', square=True)
    n = Ad.shape[0]
    C = as_matrix(C, 'C', cols=n)
    p = C.shape[0]
    Lp = as_matrix(Lp, 'Lp', rows=n, cols=p)
    y = np.asarray(y, dtype=float).reshape(-1, p)
    N = y.shape[0]
    u = np.asarray(u, dtype=float).reshape(N, -1)
    m = u.shape[1]
    Bd = np.zeros((n, 0)) if m == 0 else as_matrix(Bd, 'Bd', rows=n, cols=m)
    D = np.zeros((p, m)) if D is None or m == 0 else as_matrix(D, 'D', rows=p, cols=m)
    um = u if u_meas is None else np.asarray(u_meas, dtype=float).reshape(N, m)
    # y - D u is known in advance; the recursion needs only one matrix-vector product.
    z = y - um @ D.T
    drive = u @ Bd.T
    Abar = Ad - Lp @ C
    x = np.zeros(n) if x0 is None else np.asarray(x0, dtype=float).reshape(n)
    modes = _modes(Abar)
    if modes is not None and N:
        xs, x = _modal_states(modes, x, drive + z @ Lp.T)
        out = z - xs @ C.T
    else:
        out = np.empty((N, p))
        xs = np.empty((N, n)) if states else None
        for k in range(N):
            if states:
                xs[k] = x
            out[k] = z[k] - C @ x
            x = Abar @ x + drive[k] + Lp @ z[k]
    got = (out,) + ((xs,) if states else ()) + ((x,) if final else ())
    return got if len(got) > 1 else out


def _modes(Abar):
    """
    Return ``(eigenvalues, V, V^-1)`` of ``Abar``, or None when not safely diagonal.

    The recursion ``x[k+1] = Abar x[k] + w[k]`` then runs as one first-order filter per
    mode (scipy.signal.lfilter, in C) instead of a Python step per sample; a matrix
    whose eigenvectors are nearly dependent (condition above :data:`MODAL_CONDITION`)
    keeps the step-by-step recursion.

    """
    try:
        lam, V = np.linalg.eig(Abar)
        if not np.all(np.isfinite(lam)) or np.linalg.cond(V) > MODAL_CONDITION:
            return None
        return lam, V, np.linalg.inv(V)
    except np.linalg.LinAlgError:
        return None


def _modal_states(modes, x0, w):
    """Return the states ``x[0..N-1]`` and ``x[N]`` of ``x[k+1] = Abar x[k] + w[k]``."""
    lam, V, Vi = modes
    xs = np.zeros(w.shape)
    last = np.zeros(w.shape[1])
    for i, li in enumerate(lam):
        # the mode's input, real and imaginary parts by real products (BLAS)
        Wi = (w @ Vi[i].real) + 1j * (w @ Vi[i].imag) if np.iscomplexobj(Vi) else w @ Vi[i]
        start = Vi[i] @ x0
        # y[k] = li y[k-1] + Wi[k], y[-1] = start: y[k] is the mode at step k + 1
        nxt = scipy.signal.lfilter([1.0], [1.0, -li], Wi, zi=[li * start])[0]
        xi = np.empty_like(nxt)
        xi[0] = start
        xi[1:] = nxt[:-1]
        # the mode's share of the states (conjugate pairs' imaginary parts cancel)
        xs += np.multiply.outer(xi.real, V[:, i].real)
        last += (V[:, i] * nxt[-1]).real
        if np.iscomplexobj(xi):
            xs -= np.multiply.outer(xi.imag, V[:, i].imag)
    return xs, last


def predictor_blocks(Ad, Bd, C, D, Lp, y, u, u_meas=None, x0=None, sinks=(),
                     block=1 << 16):
    """
    Run :func:`predictor_innovations` a block of rows at a time; return ``xh[N]``.

    Each block of innovations goes to ``sink.add(block)`` of every sink (e.g. a
    :class:`~observer_ros.core.autocovariance.LaggedSums`), so they are never held whole;
    the predictions are those of one call over every row (up to rounding).

    """
    N = np.asarray(y).shape[0]
    x = x0
    for a in range(0, N, int(block)):
        b = min(N, a + int(block))
        e, x = predictor_innovations(Ad, Bd, C, D, Lp, y[a:b], u[a:b],
                                     None if u_meas is None else u_meas[a:b], x0=x,
                                     final=True)
        for sink in sinks:
            sink.add(e)
    if x is None:
        x = np.zeros(np.asarray(Ad).shape[0])
    return np.asarray(x, dtype=float)


def sample_autocovariances(e, lags):
    """
    Sample autocovariances ``Cj = 1/(N-j) sum_k e[k+j] e[k]^T``, j = 0 .. lags-1.

    Parameters
    ----------
    e : (N, p) array_like, or a list of them
        Innovations (zero mean in theory; the mean is not removed). Several sequences
        (bags) are pooled: the sums over all of them divided by the number of products.
    lags : int
        Number of lags N (>= 1).

    Returns
    -------
    C : (lags, p, p) ndarray

    """
    seqs = e if isinstance(e, (list, tuple)) else [e]
    seqs = [np.asarray(s, dtype=float) for s in seqs]
    seqs = [s.reshape(s.shape[0], -1) for s in seqs]
    total = sum(s.shape[0] for s in seqs)
    if lags < 1 or any(s.shape[0] <= lags for s in seqs):
        raise ALSError(f'{min(s.shape[0] for s in seqs)} innovations are too few for '
                       f'{lags} lags')
    p = seqs[0].shape[1]
    out = np.zeros((lags, p, p))
    for j in range(lags):
        for s in seqs:
            out[j] += s[j:].T @ s[:s.shape[0] - j]
        out[j] /= total - j * len(seqs)
    return out


def model_autocovariances(Ad, C, Lp, Qk, R, lags):
    """
    Autocovariances of the innovations of the predictor with gain Lp (see the module).

    Parameters
    ----------
    Ad : (n, n) array_like
        Sampled state matrix.
    C : (p, n) array_like
        Output matrix.
    Lp : (n, p) array_like
        Predictor gain (stable).
    Qk : (n, n) array_like
        Process noise covariance per step.
    R : (p, p) array_like
        Measurement noise covariance.
    lags : int
        Number of lags.

    Returns
    -------
    C : (lags, p, p) ndarray
        ``C[j] = E[Y[k+j] Y[k]^T]``.

    """
    Ad, C, Lp = np.asarray(Ad, float), np.asarray(C, float), np.asarray(Lp, float)
    Qk, R = np.asarray(Qk, float), np.asarray(R, float)
    Abar = Ad - Lp @ C
    P = scipy.linalg.solve_discrete_lyapunov(Abar, Qk + Lp @ R @ Lp.T)
    out = np.empty((lags, C.shape[0], C.shape[0]))
    out[0] = C @ P @ C.T + R
    left = C.copy()                 # C Abar^(j-1)
    LR = Lp @ R
    PC = P @ C.T
    for j in range(1, lags):
        out[j] = left @ Abar @ PC - left @ LR
        left = left @ Abar
    return out


def autocovariance_sigma(model, samples):
    """
    Return the standard deviation of the diagonal sample autocovariances (Bartlett).

    ``var(c_j) ~ 1/N sum_m (c_m^2 + c_(m+j) c_(m-j))`` over |m| < lags, with the model's
    autocovariances ``c`` of each output (``c_(-m) = c_m``).

    Parameters
    ----------
    model : (L, p, p) array_like
        Model autocovariances (at least twice as many lags as wanted, to sum over).
    samples : int
        Number of innovations the sample autocovariances are computed from.

    Returns
    -------
    sigma : (L // 2, p) ndarray

    """
    model = np.asarray(model, dtype=float)
    L, p = model.shape[0], model.shape[1]
    half = L // 2
    out = np.empty((half, p))
    for i in range(p):
        c = model[:, i, i]
        full = np.concatenate([c[:0:-1], c])          # lags -(L-1) .. L-1
        mid = L - 1

        def at(m):
            return full[mid + m] if abs(m) < L else 0.0
        for j in range(half):
            s = sum(at(m) ** 2 + at(m + j) * at(m - j) for m in range(-half, half + 1))
            out[j, i] = math.sqrt(max(s, 0.0) / max(samples - j, 1))
    return out


def process_noise_map(A, G, dt=None, discrete=False):
    """
    Return F: Q (k x k) -> the process noise covariance per step (n x n), linear in Q.

    Parameters
    ----------
    A : (n, n) array_like
        The plant's state matrix (continuous or discrete).
    G : (n, k) array_like
        Noise input matrix (``observer.Bd``, or the identity for noise on every state).
    dt : float, optional
        Sample period (continuous plant).
    discrete : bool
        Discrete plant: ``F(Q) = G Q G^T`` (Q per sample); otherwise Q is an intensity
        and ``F(Q)`` its exact integral over dt (Van Loan).

    Returns
    -------
    F : callable

    """
    A = as_matrix(A, 'A', square=True)
    G = as_matrix(G, 'G', rows=A.shape[0])
    if discrete:
        return lambda Q: G @ Q @ G.T
    from .estimators import process_noise_covariance
    return lambda Q: process_noise_covariance(A, Q, dt, G)


def symmetric_basis(k, full):
    """Symmetric basis matrices of k x k: diagonal ones, then (i < j) pairs if full."""
    out, labels = [], []
    for i in range(k):
        E = np.zeros((k, k))
        E[i, i] = 1.0
        out.append(E)
        labels.append((i, i))
    if full:
        for i in range(k):
            for j in range(i + 1, k):
                E = np.zeros((k, k))
                E[i, j] = E[j, i] = 1.0
                out.append(E)
                labels.append((i, j))
    return out, labels


def als_matrix(Ad, C, Lp, noise_map, k, lags, full=False):
    """
    Return the ALS matrix: the stacked model autocovariances of each unknown.

    Parameters
    ----------
    Ad, C, Lp : array_like
        Sampled model and the reference predictor gain.
    noise_map : callable
        F of :func:`process_noise_map`.
    k : int
        Size of Q.
    lags : int
        Number of lags.
    full : bool
        Full symmetric Q and R (else diagonal).

    Returns
    -------
    M : (lags p p, unknowns) ndarray
        Column per unknown: ``vec`` of ``C0 .. C(lags-1)``.
    q_labels, r_labels : list of (int, int)
        The entries of Q and of R the columns stand for (Q's first).

    """
    p = np.asarray(C).shape[0]
    n = np.asarray(Ad).shape[0]
    qb, q_labels = symmetric_basis(k, full)
    rb, r_labels = symmetric_basis(p, full)
    cols = [model_autocovariances(Ad, C, Lp, noise_map(E), np.zeros((p, p)), lags).ravel()
            for E in qb]
    cols += [model_autocovariances(Ad, C, Lp, np.zeros((n, n)), E, lags).ravel()
             for E in rb]
    return np.column_stack(cols), q_labels, r_labels


def _assemble(values, labels, k):
    M = np.zeros((k, k))
    for v, (i, j) in zip(values, labels):
        M[i, j] = M[j, i] = v
    return M


def _psd(M):
    w, V = np.linalg.eigh(0.5 * (M + M.T))
    return (V * np.maximum(w, 0.0)) @ V.T


def choose_lags(Ad, C, Lp, noise_map, k, samples, full=False):
    """
    Return the lags to use, from the plant (see the module), and the lags the noise needs.

    Each unknown's column of the ALS matrix (its noise's autocovariances through the
    reference predictor ``Lp``) is computed over a long horizon and covered until
    :data:`~observer_ros.core.als_stats.TAIL_ENERGY` of its energy is left
    (:func:`~observer_ros.core.als_stats.plant_lags`), within the cap of ``samples``
    innovations (:func:`~observer_ros.core.als_stats.lag_cap`).

    Returns
    -------
    lags : int
    decay : int
        The lags the slowest column needs (more than ``lags`` when capped).

    """
    p = np.asarray(C).shape[0]
    cap = lag_cap(int(samples), p)
    horizon = int(min(max(cap, 200), 4000))
    M, _, _ = als_matrix(Ad, C, Lp, noise_map, k, horizon, full)
    return plant_lags(M.reshape(horizon, p, p, -1), cap)


def _row_index(rows, p):
    j, i, l_ = rows
    return (j * p + i) * p + l_


def _gamma(Ad, C, Lp, noise_map, Q, R, horizon, fitted=None):
    """Return the innovations' autocovariances of the fitted model over ``horizon`` lags."""
    gamma = model_autocovariances(Ad, C, Lp, noise_map(Q), R, horizon)
    if fitted is not None:
        gamma[:fitted.shape[0]] = fitted
    return gamma


def _check_rank(fit, unknowns):
    """Refuse a fit whose ALS matrix has a rank below the number of unknowns."""
    if fit['rank'] < unknowns:
        raise ALSError(f'not identifiable: the ALS matrix has rank {fit["rank"]} for '
                       f'{unknowns} unknowns (condition number {fit["condition"]:.3g}); '
                       'estimate fewer noise entries (noise on fewer states or observer.Bd '
                       'columns, diagonal instead of full) or use more lags')


def identify_noise(innovations, Ad, C, Lp, noise_map, k, lags=DEFAULT_LAGS, full=False,
                   names=None, ltv=None):
    """
    Identify Q and R from a stable predictor's innovations (autocovariance least squares).

    Parameters
    ----------
    innovations : (N, p) array_like, or a list of them, or LaggedSums
        The predictor's innovations, the transient already dropped (several
        sequences, e.g. one per bag, are pooled), or their running lagged sums
        (:class:`~observer_ros.core.autocovariance.LaggedSums`, at least ``lags`` lags;
        NaN values, missing outputs, enter no sum).
    Ad, C : array_like
        Sampled model (at the nominal step).
    Lp : (n, p) array_like
        The predictor's gain (must be stable: eig(Ad - Lp C) inside the unit circle).
    noise_map : callable
        F of :func:`process_noise_map`.
    k : int
        Size of Q.
    lags : int, optional
        Number of autocovariance lags (default: :func:`choose_lags`).
    full : bool
        Full symmetric Q and R, projected onto the PSD cone; default diagonal and
        non-negative.
    names : tuple of (list, list), optional
        Names of Q's and R's diagonal entries, for the messages.
    ltv : object, optional
        The time-varying model of irregular data
        (:class:`~observer_ros.core.als_ltv.LTVModel`): its ``als_matrix(k, full, lags)``
        replaces the time-invariant one.

    Returns
    -------
    result : ALSResult

    Raises
    ------
    ALSError
        The predictor is unstable, too few data, or the unknowns are not identifiable
        (the ALS matrix is rank deficient).

    """
    Ad = as_matrix(Ad, 'Ad', square=True)
    C = as_matrix(C, 'C', cols=Ad.shape[0])
    p = C.shape[0]
    Lp = as_matrix(Lp, 'Lp', rows=Ad.shape[0], cols=p)
    rho = float(np.max(np.abs(np.linalg.eigvals(Ad - Lp @ C))))
    if not rho < 1.0:
        raise ALSError(f'the reference predictor is not stable (spectral radius {rho:.4g})')
    sums = innovations if hasattr(innovations, 'autocovariances') else None
    if sums is None:
        seqs = innovations if isinstance(innovations, (list, tuple)) else [innovations]
        seqs = [np.asarray(x, dtype=float).reshape(np.shape(x)[0], -1) for x in seqs]
        samples = sum(x.shape[0] for x in seqs)
    else:
        samples = sums.samples
    auto = lags is None
    chosen, decay = choose_lags(Ad, C, Lp, noise_map, k, samples, full)
    lags = chosen if auto else int(lags)
    if sums is None:
        from .autocovariance import LaggedSums
        if lags < 1 or any(x.shape[0] <= lags for x in seqs):
            raise ALSError(f'{min(x.shape[0] for x in seqs)} innovations are too few for '
                           f'{lags} lags')
        sums = LaggedSums(p, lags)
        for x in seqs:
            sums.new_sequence()
            sums.add(x)
    emp = sums.autocovariances(lags)
    counts = sums.counts[:lags]
    if ltv is not None:
        M, q_labels, r_labels = ltv.als_matrix(k, lags, full)
    else:
        M, q_labels, r_labels = als_matrix(Ad, C, Lp, noise_map, k, lags, full)
    nq = len(q_labels)
    labels = [('Q', i, j) for i, j in q_labels] + [('R', i, j) for i, j in r_labels]
    unknowns = M.shape[1]
    qn, rn = names if names is not None else \
        ([f'Q[{i}]' for i in range(k)], [f'R[{i}]' for i in range(p)])
    rows = als_rows(lags, p)
    n_row = counts[rows]
    keep = n_row > 0
    rows = tuple(r[keep] for r in rows)
    n_row = n_row[keep]
    idx = _row_index(rows, p)
    Mr, b = M[idx], emp.ravel()[idx]
    zero = [qn[i] if c < nq else rn[r_labels[c - nq][0]]
            for c, (i, _) in enumerate(q_labels + r_labels)
            if not np.any(Mr[:, c] != 0.0)]
    if zero:
        raise ALSError(f'not identifiable: {", ".join(zero)} does not reach the '
                       'measured outputs')
    nonneg = not full           # diagonal: non-negative; full: projected afterwards
    # a first fit weighted by each row's variance for white innovations, then the
    # weights of the fitted model (Bartlett), twice
    c0 = np.diag(emp[0])
    j_, i_, l_ = rows
    white = (c0[i_] * c0[l_] + np.where(j_ == 0, emp[0][i_, l_] ** 2, 0.0)) / n_row
    white = np.where(white > 0, white, np.max(white[white > 0], initial=1.0))
    theta, cov, fit = weighted_als(Mr, b, white, nonneg)
    _check_rank(fit, unknowns)
    # the innovations' autocovariances to where they have decayed, for Bartlett's sums
    horizon = int(min(max(2 * lags, lags + 2 * decay), 4000))
    Sigma = None
    for _ in range(2):
        Q = _assemble(theta[:nq], q_labels, k)
        R = _assemble(theta[nq:], r_labels, p)
        fitted = (M @ theta).reshape(lags, p, p) if ltv is not None else None
        gamma = _gamma(Ad, C, Lp, noise_map, Q, R, horizon, fitted)
        if not np.all(np.diag(gamma[0]) > 0.0):
            gamma = np.where(np.isfinite(emp), emp, 0.0)
        Sigma = autocovariance_covariance(gamma, rows, n_row)
        theta, cov, fit = weighted_als(Mr, b, Sigma, nonneg)
    _check_rank(fit, unknowns)
    x = theta
    Q = _assemble(x[:nq], q_labels, k)
    R = _assemble(x[nq:], r_labels, p)
    std = np.sqrt(np.abs(np.diag(cov)))
    Q_std = _assemble(std[:nq], q_labels, k)
    R_std = _assemble(std[nq:], r_labels, p)
    if full:
        Q, R = _psd(Q), _psd(R)
    Qk = noise_map(Q)
    fitted = (M @ x).reshape(lags, p, p) if ltv is not None else \
        model_autocovariances(Ad, C, Lp, Qk, R, lags)
    sigma = np.full((lags, p), np.nan)
    diag = np.sqrt(np.abs(np.diag(Sigma)))
    on = i_ == l_
    sigma[j_[on], i_[on]] = diag[on]
    return ALSResult(Q=Q, R=R, Qk=Qk, lags=lags, samples=int(samples), empirical=emp,
                     auto_lags=int(chosen),
                     fitted=fitted, sigma=sigma, condition=fit['condition'],
                     rank=fit['rank'], unknowns=unknowns, residual=fit['chi2'],
                     full=bool(full), raw=x, Q_std=Q_std, R_std=R_std, cov=cov,
                     labels=labels, names=(list(qn), list(rn)), dof=fit['dof'],
                     decay=int(decay), counts=counts)


def kalman_predictor_gain(Ad, C, Qk, R):
    """
    Steady-state Kalman predictor gain of the sampled model (process noise Qk per step).

    Returns
    -------
    Lp : (n, p) ndarray
        ``Ad P C^T (C P C^T + R)^-1``, P the a-priori covariance (python-control's dlqe).

    """
    from .design import kalman_gain
    Ad = np.asarray(Ad, dtype=float)
    L, _, _ = kalman_gain(Ad, C, Qk, R, discrete=True)
    return L
