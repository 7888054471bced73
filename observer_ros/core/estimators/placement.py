# observer_ros.core.estimators.placement: the correction gain of one sampled step.
"""
Pole placement for the gain of a step: a quick direct formula, else the full design.

Also the detectability check the observers run on (A, C) when they are built.

"""

import warnings

import numpy as np

from ..analysis import is_stable_eigenvalue, observable_decomposition, stability_margin
from ..design import observer_gain, pole_placement_error
from ..errors import DesignError, NotDetectableError
from ..verify import verify_placement

#: A gain from the quick placement (:func:`_quick_gain`) is kept only if its poles
#: are within this relative error (``design.pole_placement_error``) of those asked
#: for; otherwise the full design (place and acker compared) runs.
QUICK_PLACE_TOL = 1e-10


def design_choice(poles, gain, method, what):
    """Check a constructor's (poles or gain, method) choice; return the method."""
    if (poles is None) == (gain is None):
        raise DesignError(f'give exactly one of poles and gain for a {what}')
    if method not in ('auto', 'place', 'acker'):
        raise DesignError(f"method must be 'auto', 'place' or 'acker'; got {method!r}")
    return method


def _pick_poles(z, count):
    """
    Choose ``count`` of the desired z-plane poles ``z`` (conjugate pairs kept).

    The fastest poles (smallest ``|z|``) are taken first. When only one place is
    left for a complex pair, the real pole ``|z|`` (same decay) is used.

    """
    z = np.asarray(z, dtype=complex)
    if z.size == count:
        return z
    if z.size < count:
        raise DesignError(f'{count} poles are needed but only {z.size} were given')
    tol = 1e-9 * max(1.0, float(np.max(np.abs(z))))
    order = sorted(range(z.size), key=lambda i: (abs(z[i]), -z[i].imag, z[i].real))
    used = set()
    chosen = []
    for i in order:
        if len(chosen) == count:
            break
        if i in used:
            continue
        used.add(i)
        if abs(z[i].imag) <= tol:
            chosen.append(complex(z[i].real))
            continue
        partner = [j for j in order if j not in used and abs(z[j] - np.conj(z[i])) <= tol]
        if partner:
            used.add(partner[0])
        if len(chosen) + 2 <= count:
            chosen.extend([z[i], np.conj(z[i])])
        else:
            chosen.append(complex(abs(z[i])))
    return np.array(chosen, dtype=complex)


def _quick_gain(A, C, z, method):
    """
    M with eig(A - M C) = z by one direct formula, or None when it is not accurate.

    One output (``auto`` or ``acker``): Ackermann's formula for the observer,
    ``M = phi(A) O^-1 e_n`` with ``O = [C; C A; ...; C A^(n-1)]`` and phi the
    polynomial with roots z (tens of microseconds). Then, for ``auto`` when
    Ackermann lost digits, for several outputs, or for ``place``: scipy's
    ``place_poles`` on the dual (what python-control's place calls; about a
    millisecond for a few states, seconds for 20). A result is kept only if its
    placed poles are within :data:`QUICK_PLACE_TOL` of z, where neither method can
    lose to the other by much, so it stands for the comparison
    ``design.observer_gain`` makes (several milliseconds: decompositions, both
    methods, four pole errors). Every failure (singular O, repeated poles, loss of
    digits) gives None.

    Returns
    -------
    M : (n, p) ndarray or None
        The accurate gain.
    placed : (n, p) ndarray or None
        ``place_poles``' gain whether accurate or not (None if not computed or it
        failed): with several outputs it is python-control's ``place``, the only
        candidate ``observer_gain`` has, so :func:`place` does not compute it twice.

    """
    p = C.shape[0]
    if p == 1 and method in ('auto', 'acker'):
        M = _checked(A, C, z, _ackermann)
        if M is not None or method == 'acker':
            return M, None
    if method in ('auto', 'place'):
        placed = _attempt(_place_poles, A, C, z)
        if placed is not None and pole_placement_error(A - placed @ C, z) <= QUICK_PLACE_TOL:
            return placed, placed
        return None, placed
    return None, None


def _ackermann(A, C, z):
    n = A.shape[0]
    obsv = np.empty((n, n))
    row = C[0]
    for i in range(n):
        obsv[i] = row
        row = row @ A
    coeffs = np.poly(z).real
    P = np.eye(n)
    for c in coeffs[1:]:
        P = P @ A
        P.flat[::n + 1] += c
    e = np.zeros(n)
    e[-1] = 1.0
    return (P @ np.linalg.solve(obsv, e)).reshape(n, 1)


def _place_poles(A, C, z):
    """
    Return scipy's Tits-Yang gain; its 'Convergence was not reached' is not passed on.

    The caller measures the gain's placement error and, when it is not accurate, runs the
    full design (which says a placement that did not converge in its own words); the
    warning, printed in a node's log at a step, said nothing that check does not.

    """
    import scipy.signal
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter('always')
        gain = scipy.signal.place_poles(A.T, C.T, z, method='YT').gain_matrix.T
    for w in caught:
        if not str(w.message).startswith('Convergence was not reached'):
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    return gain


def _attempt(formula, A, C, z):
    try:
        M = formula(A, C, z)
    except (ValueError, np.linalg.LinAlgError):
        return None
    return np.ascontiguousarray(M, dtype=float) if np.all(np.isfinite(M)) else None


def _checked(A, C, z, formula):
    M = _attempt(formula, A, C, z)
    if M is None or pole_placement_error(A - M @ C, z) > QUICK_PLACE_TOL:
        return None
    return M


def place(A, C, zpoles, method, field='observer.poles'):
    """
    Gain M with the observable part of eig(A - M C) at (some of) ``zpoles``, verified.

    The quick formula of :func:`_quick_gain` is tried first (all n poles, checked).
    Otherwise, when (A, C) is observable all n poles are placed
    (design.observer_gain). Otherwise the pair is split by the orthogonal
    observable decomposition ``T^T A T = [[Ao, 0], [A21, Au]]``, ``C T = [Co, 0]``;
    r = rank poles are chosen by :func:`_pick_poles` and placed for (Ao, Co), and
    the unobservable eigenvalues eig(Au) are kept: ``M = T[:, :r] Mo``.

    With several outputs the quick path's ``place_poles`` gain is the full design's
    too (python-control's place is that call), so it is not computed twice.
    Whichever path made it, the gain then passes the check every design passes
    (``verify.verify_placement``, z-plane): the achieved eigenvalues of ``A - M C``
    (of its observable block ``Ao - Mo Co`` when partial) must be stable and within
    the placement's conditioning bound of the poles asked for.

    Raises
    ------
    DesignVerificationError
        The gain fails that check; the message starts with ``field``.

    """
    n = A.shape[0]
    placed = None
    if len(zpoles) == n:
        z = np.asarray(zpoles, dtype=complex)
        M, placed = _quick_gain(A, C, z, method)
        if M is not None:
            return _verified(A, C, M, z, field)
    _, _, _, T, r = observable_decomposition(A, None, C)
    if r == n:
        z = _pick_poles(zpoles, n)
        if placed is not None and C.shape[0] > 1:
            # observer_gain would call the same place_poles again (its only candidate
            # with several outputs): seconds for 20 states
            return _verified(A, C, placed, z, field)
        return _verified(A, C, observer_gain(A, C, z, method), z, field)
    if r == 0:
        return np.zeros((n, C.shape[0]))
    To = T[:, :r]
    z = _pick_poles(zpoles, r)
    Ao, Co = To.T @ A @ To, C @ To
    Mo = _verified(Ao, Co, observer_gain(Ao, Co, z, method), z, field)
    return To @ Mo


def _verified(A, C, M, z, field):
    """Return M after ``verify_placement`` of ``A - M C`` against the z-plane poles z."""
    norm = np.linalg.norm(A, 2) + np.linalg.norm(M, 2) * np.linalg.norm(C, 2)
    verify_placement(A - M @ C, z, field, norm, discrete=True)
    return M


def unobservable_check(A, C, discrete, what):
    """Rank of (A, C); raise NotDetectableError if an unobservable mode is not stable."""
    Abar, _, _, _, r = observable_decomposition(A, None, C)
    n = A.shape[0]
    if r < n:
        margin = stability_margin(A)
        for lam in np.linalg.eigvals(Abar[r:, r:]):
            if not is_stable_eigenvalue(lam, discrete, margin):
                raise NotDetectableError(
                    f'{what}: (A, C) is not detectable: the unobservable eigenvalue '
                    f'{complex(lam):.6g} is not stable')
    return r
