# observer_ros.core.model: the plant model and argument checking shared by the core.
"""Plant model (A, B, C, D), argument checking and exact discretisation."""

from dataclasses import dataclass, field
import math
from typing import Optional, Sequence, Tuple

import numpy as np
import scipy.linalg

from .errors import DimensionError, ObserverError

__all__ = ['as_matrix', 'as_vector', 'as_poles', 'Plant', 'zoh_matrices',
           'map_poles_to_discrete']


def as_matrix(X, name, rows=None, cols=None, square=False):
    """
    Convert X to a 2-D float array and check its shape.

    Parameters
    ----------
    X : array_like
        A scalar, a 1-D sequence (taken as one row) or a 2-D array.
    name : str
        The name used in error messages ("C has 3 columns; expected 2").
    rows, cols : int, optional
        Expected number of rows and columns.
    square : bool
        Require a square matrix.

    Returns
    -------
    M : ndarray
        2-D float array, finite, of the expected shape.

    """
    try:
        M = np.array(X, dtype=float)
    except (TypeError, ValueError):
        raise DimensionError(f'{name} is not a numeric matrix: {X!r}') from None
    if M.ndim == 0:
        M = M.reshape(1, 1)
    elif M.ndim == 1:
        M = M.reshape(1, -1)
    elif M.ndim != 2:
        raise DimensionError(f'{name} has {M.ndim} dimensions; expected 2')
    if square and M.shape[0] != M.shape[1]:
        raise DimensionError(
            f'{name} is {M.shape[0]}x{M.shape[1]}; expected a square matrix')
    if rows is not None and M.shape[0] != rows:
        raise DimensionError(f'{name} has {M.shape[0]} rows; expected {rows}')
    if cols is not None and M.shape[1] != cols:
        raise DimensionError(f'{name} has {M.shape[1]} columns; expected {cols}')
    if not np.all(np.isfinite(M)):
        raise DimensionError(f'{name} has non-finite entries')
    return M


def as_vector(x, name, size=None):
    """
    Convert x to a 1-D float array of the expected size.

    Parameters
    ----------
    x : array_like
        Scalar or sequence.
    name : str
        Name used in error messages.
    size : int, optional
        Expected length.

    Returns
    -------
    v : ndarray
        1-D float array, finite.

    """
    try:
        v = np.array(x, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        raise DimensionError(f'{name} is not a numeric vector: {x!r}') from None
    if size is not None and v.size != size:
        raise DimensionError(f'{name} has {v.size} elements; expected {size}')
    if not np.all(np.isfinite(v)):
        raise DimensionError(f'{name} has non-finite entries')
    return v


def as_poles(poles, name, count=None, discrete=False, require_stable=True):
    """
    Check a set of desired poles.

    Parameters
    ----------
    poles : array_like of complex
        Desired eigenvalues.
    name : str
        Name used in error messages (for example ``observer.poles``).
    count : int, optional
        Required number of poles.
    discrete : bool
        Poles are z-plane poles (stable inside the unit circle).
    require_stable : bool
        Refuse poles in the closed right half plane (or on/outside the unit circle).

    Returns
    -------
    p : ndarray of complex
        The poles; complex ones come in conjugate pairs.

    """
    try:
        p = np.array(poles, dtype=complex).reshape(-1)
    except (TypeError, ValueError):
        raise DimensionError(f'{name} is not a list of numbers: {poles!r}') from None
    if count is not None and p.size != count:
        raise DimensionError(f'{name} has {p.size} poles; expected {count}')
    if not np.all(np.isfinite(p)):
        raise DimensionError(f'{name} has non-finite poles')
    scale = max(1.0, float(np.max(np.abs(p)))) if p.size else 1.0
    tol = 1e-9 * scale
    remaining = list(p[np.abs(p.imag) > tol])
    while remaining:
        q = remaining.pop()
        partner = [i for i, r in enumerate(remaining) if abs(r - np.conj(q)) <= tol]
        if not partner:
            raise ObserverError(
                f'{name}: pole {_fmt(q)} has no complex-conjugate partner '
                f'{_fmt(np.conj(q))}')
        remaining.pop(partner[0])
    if require_stable:
        bad = p[np.abs(p) >= 1.0] if discrete else p[p.real >= 0.0]
        if bad.size:
            where = 'on or outside the unit circle' if discrete else \
                'in the closed right half plane'
            raise ObserverError(
                f'{name}: pole {_fmt(bad[0])} is {where}; it would not be stable')
    return p


def _fmt(z):
    z = complex(z)
    if z.imag == 0:
        return f'{z.real:g}'
    return f'{z.real:g}{z.imag:+g}j'


def zoh_matrices(A, B, dt):
    """
    Exact zero-order-hold discretisation of x' = A x + B u.

    Parameters
    ----------
    A : (n, n) array_like
        State matrix.
    B : (n, m) array_like
        Input matrix.
    dt : float
        Sample time, > 0.

    Returns
    -------
    Ad, Bd : ndarray
        ``Ad = expm(A dt)`` and ``Bd = int_0^dt expm(A s) ds B``, from one
        matrix exponential of the augmented matrix (Van Loan).

    """
    A = as_matrix(A, 'A', square=True)
    n = A.shape[0]
    B = as_matrix(B, 'B', rows=n)
    m = B.shape[1]
    if not (dt > 0.0 and math.isfinite(dt)):
        raise ObserverError(f'sample time must be positive and finite; got {dt!r}')
    M = np.zeros((n + m, n + m))
    M[:n, :n] = A * dt
    M[:n, n:] = B * dt
    E = scipy.linalg.expm(M)
    return E[:n, :n], E[:n, n:]


def map_poles_to_discrete(poles, dt):
    """
    Map continuous-time poles s to z = exp(s dt).

    Parameters
    ----------
    poles : array_like of complex
        Continuous-time poles s.
    dt : float
        Sample time.

    Returns
    -------
    z : ndarray of complex

    """
    return np.exp(np.asarray(poles, dtype=complex) * dt)


@dataclass(frozen=True)
class Plant:
    """
    A linear time-invariant plant x' = A x + B u, y = C x + D u.

    Continuous time when ``dt`` is None, otherwise x[k+1] = A x[k] + B u[k]
    with sample time ``dt``. Names default to x1.., u1.., y1...

    """

    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    D: np.ndarray
    dt: Optional[float] = None
    state_names: Tuple[str, ...] = field(default=())
    input_names: Tuple[str, ...] = field(default=())
    output_names: Tuple[str, ...] = field(default=())

    def __post_init__(self):
        A = as_matrix(self.A, 'A', square=True)
        n = A.shape[0]
        B = as_matrix(self.B, 'B', rows=n)
        C = as_matrix(self.C, 'C', cols=n)
        m, p = B.shape[1], C.shape[0]
        D = np.zeros((p, m)) if self.D is None else as_matrix(self.D, 'D', rows=p, cols=m)
        if self.dt is not None and not (self.dt > 0.0 and math.isfinite(self.dt)):
            raise ObserverError(f'sample time must be positive; got {self.dt!r}')
        object.__setattr__(self, 'A', A)
        object.__setattr__(self, 'B', B)
        object.__setattr__(self, 'C', C)
        object.__setattr__(self, 'D', D)
        for attr, size, prefix in (('state_names', n, 'x'), ('input_names', m, 'u'),
                                   ('output_names', p, 'y')):
            names = tuple(getattr(self, attr)) or tuple(
                f'{prefix}{i + 1}' for i in range(size))
            if len(names) != size:
                raise DimensionError(f'{attr} has {len(names)} names; expected {size}')
            if len(set(names)) != len(names):
                raise DimensionError(f'{attr} has duplicate names: {list(names)}')
            object.__setattr__(self, attr, names)

    @property
    def n(self):
        """Return the number of states."""
        return self.A.shape[0]

    @property
    def m(self):
        """Return the number of inputs."""
        return self.B.shape[1]

    @property
    def p(self):
        """Return the number of outputs."""
        return self.C.shape[0]

    @property
    def is_discrete(self):
        """Return True for a discrete-time plant."""
        return self.dt is not None

    def output_rows(self, names: Sequence[str]):
        """Return the row indices of C for the named outputs."""
        index = {name: i for i, name in enumerate(self.output_names)}
        missing = [name for name in names if name not in index]
        if missing:
            raise DimensionError(
                f'unknown output name(s) {missing}; outputs are {list(self.output_names)}')
        return [index[name] for name in names]

    def select_outputs(self, names: Sequence[str]):
        """Return the plant with only the named outputs (rows of C and D)."""
        rows = self.output_rows(names)
        return Plant(self.A, self.B, self.C[rows], self.D[rows], self.dt,
                     self.state_names, self.input_names, tuple(names))

    def discretize(self, dt):
        """
        Return the exact zero-order-hold discretisation at sample time dt.

        A discrete plant is returned unchanged when dt equals its own sample time.

        """
        if self.is_discrete:
            if abs(dt - self.dt) > 1e-12 * self.dt:
                raise ObserverError(
                    f'plant is discrete with sample time {self.dt}; cannot resample to {dt}')
            return self
        Ad, Bd = zoh_matrices(self.A, self.B, dt)
        return Plant(Ad, Bd, self.C, self.D, dt, self.state_names,
                     self.input_names, self.output_names)
