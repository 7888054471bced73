# observer_ros.core.pole_placement: a gain that places given poles, the best of several.
"""
Pole placement for a controllable pair (A, B): candidates, the choice, repeated poles.

Every placement returns ``K`` with ``eig(A - B K)`` at the poles asked for; the caller
(``core/design.py``) verifies it like any other gain (``core/verify.py``). The candidates:

- python-control's ``place`` (scipy's ``place_poles``, Tits-Yang, 30 iterations), and,
  with several inputs, the same algorithm run to convergence (``place_poles`` with
  ``maxiter=ROBUST_MAXITER``): with several inputs many gains place the same poles, and
  the robust algorithm picks the one whose eigenvectors are best conditioned (small
  gain, small sensitivity); python-control stops it after 30 iterations;
- Ackermann's formula (python-control ``acker``) with one input, where the gain is unique;
- for a pole repeated more often than there are independent inputs (which ``place_poles``
  refuses), a rank-one gain ``K = g k^T``: Ackermann on the single input ``B g`` for
  the combination ``g`` of the inputs that places the poles best; when no combination
  makes ``(A, B g)`` controllable (an eigenvalue of A of geometric multiplicity above
  one), a cyclic design: a first gain ``K0`` (LQR) makes ``A - B K0`` cyclic, then the
  rank-one gain on it, ``K = K0 + g k^T``.

The choice: the candidate that places the poles most accurately; with several inputs,
among those at least as accurate as python-control's ``place``, the one with the best
conditioned eigenvectors (``cond(V)``, unit columns), when that is at least 10 % better
than place's.

"""

import warnings

import numpy as np

from ._lazy import control
from .analysis import format_complex, is_controllable
from .errors import DesignError, DimensionError, ObserverDesignWarning
from .model import as_matrix
from .verify import match_eigenvalues

__all__ = ['pole_placement_error', 'place_gain', 'eigenvector_condition',
           'PLACEMENT_WARN_TOL', 'ACKER_DIGITS_LOST', 'ROBUST_MAXITER']

#: A design whose placed poles are further than this (relative, see
#: :func:`pole_placement_error`) from the poles asked for emits an
#: :class:`ObserverDesignWarning`.
PLACEMENT_WARN_TOL = 1e-6

#: ``method='acker'`` warns when Ackermann's formula is this many times less
#: accurate than ``place`` (two digits) and its error exceeds 1e-9.
ACKER_DIGITS_LOST = 100.0

#: Iterations of the robust (Tits-Yang) placement run to convergence.
ROBUST_MAXITER = 300

#: A gain other than python-control's place is chosen (several inputs) only when its
#: eigenvector condition number is below this fraction of place's.
CONDITION_GAIN = 0.9

#: Combinations of the inputs tried by the rank-one design, besides each input alone.
RANK_ONE_TRIES = 6


def _pole_clusters(p, rel=1e-9):
    groups = []
    for i, z in enumerate(p):
        for g in groups:
            if abs(z - p[g[0]]) <= rel * max(1.0, abs(p[g[0]])):
                g.append(i)
                break
        else:
            groups.append([i])
    return groups


def pole_placement_error(M, poles):
    """
    Relative distance between eig(M) and the poles asked for.

    Parameters
    ----------
    M : (n, n) array_like
        Closed-loop matrix (``A - L C`` or ``A - B K``).
    poles : array_like of complex, length n
        Desired eigenvalues.

    Returns
    -------
    err : float
        The eigenvalues are matched to the poles (optimal assignment). For a pole
        p of multiplicity k matched by eigenvalues l_i the error is
        ``max(|mean(l_i) - p|, max_i |l_i - p|^k / s^(k-1)) / s`` with
        ``s = max(1, |p|)``: a k-fold eigenvalue moves by delta^(1/k) under a
        perturbation delta, so this is a backward error, and it reduces to
        ``|l - p| / max(1, |p|)`` for a simple pole.

    """
    M = as_matrix(M, 'M', square=True)
    want = np.asarray(poles, dtype=complex).reshape(-1)
    if want.size != M.shape[0]:
        raise DimensionError(f'poles has {want.size} poles; expected {M.shape[0]}')
    if want.size == 0:
        return 0.0
    got = np.linalg.eigvals(M)
    if not np.all(np.isfinite(got)):
        return float('inf')
    matched = got[match_eigenvalues(got, want)]
    err = 0.0
    for g in _pole_clusters(want):
        p0 = want[g[0]]
        s = max(1.0, abs(p0))
        k = len(g)
        mean_err = abs(np.mean(matched[g]) - p0) / s
        spread = float(np.max(np.abs(matched[g] - p0))) / s
        err = max(err, mean_err, spread ** k)
    return float(err)


def eigenvector_condition(M):
    """
    Return ``cond(V)`` of M's eigenvector matrix (unit columns): the Bauer-Fike constant.

    Any perturbation E of M moves every eigenvalue by at most ``cond(V) ||E||``, and
    ``sup_t ||e^{M t}|| <= cond(V)`` for a stable M; inf for a defective M.

    Parameters
    ----------
    M : (n, n) array_like
        Square matrix.

    Returns
    -------
    float

    """
    M = np.atleast_2d(np.asarray(M, dtype=float))
    if not M.size:
        return 1.0
    _, V = np.linalg.eig(M)
    V = V / np.maximum(np.linalg.norm(V, axis=0), 1e-300)
    with np.errstate(all='ignore'):
        c = float(np.linalg.cond(V))
    return c if np.isfinite(c) else float('inf')


def _multiplicities(p):
    return [(p[g[0]], len(g)) for g in _pole_clusters(p, 1e-12)]


def _error(A, B, K, p):
    # eig(M) and eig(M^T) are the same poles, but LAPACK's round-off differs between the
    # two (by 10x on ill-conditioned placements): judge each gain by the larger, so that
    # the choice holds for the observer's A - L C as much as for its dual.
    M = A - B @ K
    return max(pole_placement_error(M, p), pole_placement_error(M.T, p))


def _robust(A, B, p):
    """Tits-Yang run to convergence; (K, converged)."""
    from scipy.signal import place_poles    # scipy.signal: when first used
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter('always')
        res = place_poles(A, B, p, method='YT', maxiter=ROBUST_MAXITER, rtol=1e-6)
    converged = not any('Convergence was not reached' in str(w.message) for w in caught)
    return np.asarray(res.gain_matrix, dtype=float), converged


def _acker(A, b, p):
    return np.asarray(control.acker(A, b, p), dtype=float).reshape(1, A.shape[0])


def _rank_one(A, B, p):
    """Rank-one (or cyclic) gains for poles repeated beyond rank(B): {name: K}."""
    n, m = B.shape
    rng = np.random.default_rng(0)
    U = np.linalg.svd(B, full_matrices=False)[2].T if m else np.zeros((0, 0))
    directions = [np.eye(m)[i] for i in range(m)] + [U[:, 0]] + \
        [rng.standard_normal(m) for _ in range(RANK_ONE_TRIES)]
    out = {}
    for base_name, K0 in (('rank-one', np.zeros((m, n))), ('cyclic', None)):
        if base_name == 'cyclic':
            if out:
                break
            try:    # a first loop with distinct eigenvalues (cyclic), then rank one on it
                K0 = np.asarray(control.lqr(A, B, np.eye(n), np.eye(m))[0], dtype=float)
            except (ValueError, np.linalg.LinAlgError):
                break
        A0 = A - B @ K0
        for i, g in enumerate(directions):
            g = g / max(float(np.linalg.norm(g)), 1e-300)
            b = (B @ g).reshape(n, 1)
            if not is_controllable(A0, b):
                continue
            try:
                k = _acker(A0, b, p)
            except (ValueError, np.linalg.LinAlgError):
                continue
            K = K0 + np.outer(g, k)
            if np.all(np.isfinite(K)):
                out[f'{base_name} {i}'] = K
    return out


def place_gain(A, B, p, method='auto', role='controller'):
    """
    Return K placing ``eig(A - B K)`` at p, for a controllable pair (A, B).

    Parameters
    ----------
    A : (n, n) ndarray
        State matrix (for an observer: A^T).
    B : (n, m) ndarray
        Input matrix (for an observer: C^T).
    p : (n,) ndarray of complex
        The poles, in conjugate pairs.
    method : {'auto', 'place', 'acker'}
        ``place``: python-control's place only; ``acker``: Ackermann only (one input);
        ``auto``: every candidate of the module (see its docstring), the choice its rule.
    role : {'controller', 'observer'}
        Names the side (inputs or outputs) in messages.

    Returns
    -------
    K : (m, n) ndarray

    Raises
    ------
    DesignError
        A method that cannot place these poles (``place`` with a pole repeated more
        often than there are independent inputs, ``acker`` with several), or no
        candidate at all.

    Warns
    -----
    ObserverDesignWarning
        The chosen gain's placement error exceeds ``PLACEMENT_WARN_TOL``; ``acker``
        asked for loses digits against ``place``; the robust placement did not converge.

    """
    n, m = B.shape
    if n == 0:
        return np.zeros((m, 0))
    rank_b = int(np.linalg.matrix_rank(B))
    side = 'outputs' if role == 'observer' else 'inputs'
    worst, mult = max(_multiplicities(p), key=lambda t: t[1])
    place_ok = mult <= rank_b
    if method == 'acker' and m != 1:
        raise DesignError(f"method 'acker' needs a single {side[:-1]}; there are {m} {side}")
    if not place_ok and method == 'place':
        raise DesignError(
            f'{role} pole {format_complex(worst)} is repeated {mult} times; '
            f"method 'place' allows at most {rank_b} (the independent {side}); use method "
            + ("'acker' or 'auto'" if m == 1 else "'auto' (a rank-one or cyclic design)"))
    candidates = {}
    unconverged = False
    if place_ok:
        try:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter('always')
                candidates['place'] = np.asarray(control.place(A, B, p), dtype=float)
            unconverged = any('Convergence was not reached' in str(w.message)
                              for w in caught)
        except (ValueError, np.linalg.LinAlgError) as err:
            if method == 'place':
                raise DesignError(f'{role} pole placement failed: {err}') from None
        if m > 1 and method == 'auto' and unconverged:
            try:
                K, converged = _robust(A, B, p)
                candidates['place (converged)'] = K
                unconverged = not converged
            except (ValueError, np.linalg.LinAlgError):
                pass
    if m == 1 and method in ('auto', 'acker'):
        try:
            candidates['acker'] = _acker(A, B, p)
        except (ValueError, np.linalg.LinAlgError) as err:
            if method == 'acker':
                raise DesignError(f'{role} pole placement by acker failed: {err}') from None
    if not place_ok and m > 1:
        candidates.update(_rank_one(A, B, p))
    if not candidates:
        what = (f'{role} pole {format_complex(worst)} repeated {mult} times: no combination of '
                f'the {side} makes the pair controllable, and no cyclic design was found'
                if not place_ok else f'the {role} poles')
        raise DesignError(f'no placement method could place {what} (method={method!r})')
    errors = {name: _error(A, B, K, p) for name, K in candidates.items()}
    chosen = _choose(method, candidates, errors, lambda K: eigenvector_condition(A - B @ K))
    if method == 'acker' and 'place' in errors and errors['acker'] > 1e-9 and \
            errors['acker'] > ACKER_DIGITS_LOST * max(errors['place'], 1e-300):
        warnings.warn(
            f"method 'acker' places the {role} poles with relative error "
            f"{errors['acker']:.1e}, place with {errors['place']:.1e}: Ackermann's formula "
            "loses digits here; prefer method 'place' or 'auto'",
            ObserverDesignWarning, stacklevel=4)
    if errors[chosen] > PLACEMENT_WARN_TOL:
        how = chosen.split(' ')[0] if not chosen.startswith('place') else chosen
        warnings.warn(
            f'{role} poles placed with relative error {errors[chosen]:.1e} '
            f'(> {PLACEMENT_WARN_TOL:g}) by {how}: the placement is ill-conditioned; '
            'the gain is large or the poles are nearly repeated',
            ObserverDesignWarning, stacklevel=4)
    if chosen.startswith('place') and unconverged:
        warnings.warn(
            f'{role} poles: the robust placement (Tits-Yang, scipy place_poles) did not '
            f'settle on the best-conditioned gain in {ROBUST_MAXITER} iterations; the gain '
            'places the poles (verified) but a better-conditioned one may exist',
            ObserverDesignWarning, stacklevel=4)
    return candidates[chosen]


def _choose(method, candidates, errors, condition):
    """Return the candidate of the module's rule: most accurate, then best conditioned."""
    if method in candidates:
        return method
    best = min(errors, key=errors.get)
    if 'place (converged)' not in errors:
        if best.startswith(('rank-one', 'cyclic')):
            # among the rank-one gains as accurate as the best (to 10x), the smallest
            close = [k for k in errors if errors[k] <= 10.0 * max(errors[best], 1e-15)]
            return min(close, key=lambda k: float(np.linalg.norm(candidates[k])))
        return best
    # several inputs: as accurate as python-control's place and better conditioned by
    # CONDITION_GAIN at least, else place itself
    ok = [k for k in errors if errors[k] <= max(errors['place'], 1e-15)]
    cond = {k: condition(candidates[k]) for k in ok}
    better = min(ok, key=cond.get)
    return better if cond[better] < CONDITION_GAIN * cond['place'] else 'place'
