# observer_ros.core.verify: the one stability rule, and the check every design passes.
"""
Verification of designs: stability verdicts and achieved-versus-requested poles.

**The stability rule** (stated here once; every verdict of the package uses it).
An eigenvalue ``lambda`` of a matrix M is computed with a first-order rounding error of
at most ``b = EIG_BOUND_FACTOR N eps ||M_b|| kappa(lambda)`` (M_b is M balanced, kappa the
eigenvalue's condition number ``1 / |y^H x|`` from its unit left and right
eigenvectors, capped at ``1 / sqrt(eps)``, the size a defective eigenvalue of a 2x2
Jordan block reaches). It is

- *stable* when ``Re lambda < -b`` (discrete: ``|lambda| < 1 - b``): it is stable
  whatever the rounding,
- *unstable* when ``Re lambda > b`` (``|lambda| > 1 + b``),
- *marginally stable* otherwise: rounding cannot tell.

The bound depends on each eigenvalue's own conditioning and on the matrix it comes from,
not on a fixed fraction of ``||A||``: the mode -5e-4 of ``diag(-1e6, -5e-4)`` is stable
(b = 4e-9), an integrator computed as +-1e-17 is marginal.

**Refused versus warned.** A gain that is used (designed or given, controller or
observer) is *refused* when an achieved closed-loop pole (of ``A - B K``, ``A - L C`` or
the reduced-order observer's ``F``) is not stable by this rule, or when a placed pole is
further from the pole asked for than the placement's own conditioning explains
(:func:`placement_bound`). Everything else that is doubtful (a placement that is accurate
to its bound but far from the poles asked for, a slow observer, noise gain) is a
*warning* in the design report.

"""

from dataclasses import dataclass
from typing import Optional

import numpy as np
import scipy.linalg

from .errors import DesignVerificationError

__all__ = ['EIG_BOUND_FACTOR', 'match_eigenvalues', 'PLACEMENT_BOUND_FACTOR', 'eigenvalue_bounds',
           'stability_status', 'unstable_eigenvalues', 'describe_status', 'PlacementCheck',
           'placement_bound', 'verify_placement', 'verify_stable']

_EPS = np.finfo(float).eps

#: Constant of the first-order eigenvalue rounding bound (LAPACK's error bounds of
#: ``xGEEVX`` are ``eps ||M|| / rcond``; the factor 10 N covers the reduction's growth).
EIG_BOUND_FACTOR = 10.0

#: Constant of :func:`placement_bound`. A backward-stable placement would need a factor
#: of order 1; python-control's ``place`` (scipy's Kautsky-Nichols ``place_poles``) with
#: two or three inputs is measured up to 1.2e5 above that on random stable systems with
#: n = 2..12 (120 systems, errors 1e-10..5e-7), one input up to 0.08: 1e7 leaves a
#: factor 80 above the worst measured, and still refuses the failures (error O(1)).
PLACEMENT_BOUND_FACTOR = 1e7

_KAPPA_CAP = 1.0 / np.sqrt(_EPS)


def _kappas(vl, vr):
    dots = np.abs(np.sum(vl.conj() * vr, axis=0))
    with np.errstate(divide='ignore'):
        return np.where(dots > 0, 1.0 / np.maximum(dots, 1e-300), np.inf)


def eigenvalue_bounds(M, norm=None, cap=True):
    """
    Eigenvalues of M and their first-order rounding bounds (the stability rule's ``b``).

    Parameters
    ----------
    M : (N, N) array_like
        Square matrix.
    norm : float, optional
        Norm of the matrix M was taken from, when larger than ``||M_b||`` (for the
        eigenvalues of a block of a transformed plant, the plant's ``||A||``).
    cap : bool
        Cap the condition numbers at ``1 / sqrt(eps)``.

    Returns
    -------
    lam : (N,) ndarray of complex
        ``eig(M)``.
    bound : (N,) ndarray
        ``EIG_BOUND_FACTOR N eps max(||M_b||_2, norm) kappa_i``.

    """
    M = np.atleast_2d(np.asarray(M, dtype=float))
    N = M.shape[0] if M.size else 0
    if N == 0:
        return np.zeros(0, complex), np.zeros(0)
    Mb, _ = scipy.linalg.matrix_balance(M)
    lam, vl, vr = scipy.linalg.eig(Mb, left=True, right=True)
    kappa = _kappas(vl, vr)
    if cap:
        kappa = np.minimum(kappa, _KAPPA_CAP)
    scale = max(float(np.linalg.norm(Mb, 2)), float(norm or 0.0), _EPS)
    return lam, EIG_BOUND_FACTOR * N * _EPS * scale * kappa


def stability_status(lam, bound, discrete=False):
    """
    Classify one eigenvalue by the stability rule of this module.

    Parameters
    ----------
    lam : complex
        Eigenvalue.
    bound : float
        Its rounding bound (:func:`eigenvalue_bounds`).
    discrete : bool
        z-plane instead of s-plane.

    Returns
    -------
    str
        ``'stable'``, ``'unstable'`` or ``'marginally stable'``.

    """
    lam = complex(lam)
    x = abs(lam) - 1.0 if discrete else lam.real
    if x < -bound:
        return 'stable'
    return 'unstable' if x > bound else 'marginally stable'


def unstable_eigenvalues(M, discrete=False, norm=None, with_bounds=False):
    """
    Return the eigenvalues of M that are not stable by the stability rule.

    Parameters
    ----------
    M : (N, N) array_like
        Square matrix.
    discrete : bool
        z-plane instead of s-plane.
    norm : float, optional
        See :func:`eigenvalue_bounds`.
    with_bounds : bool
        Also return each eigenvalue's rounding bound.

    Returns
    -------
    list of (complex, str) or (complex, str, float)
        Each eigenvalue that is not stable and its status (and bound), largest real
        part (or modulus) first.

    """
    lam, bound = eigenvalue_bounds(M, norm)
    bad = [(complex(x), stability_status(x, b, discrete), float(b))
           for x, b in zip(lam, bound)]
    bad = sorted([t for t in bad if t[1] != 'stable'],
                 key=lambda t: -(abs(t[0]) if discrete else t[0].real))
    return bad if with_bounds else [t[:2] for t in bad]


def describe_status(lam, status, bound, discrete=False):
    """
    Say in words why an eigenvalue is not stable by the rule: unstable, on the axis, or unknown.

    Parameters
    ----------
    lam : complex
        The eigenvalue.
    status : str
        Its :func:`stability_status`.
    bound : float
        Its rounding bound.
    discrete : bool
        z-plane instead of s-plane.

    Returns
    -------
    str
        ``'unstable'``; ``'marginally stable'`` for an eigenvalue on the imaginary axis
        (unit circle) to within a millionth of its size; otherwise (a pole that looks
        stable, within its own rounding bound of the axis) ``'not verifiably stable:
        rounding of this matrix moves it by up to B'``.

    """
    lam = complex(lam)
    if status != 'marginally stable':
        return status
    x = abs(lam) - 1.0 if discrete else lam.real
    if abs(x) <= 1e-6 * max(1.0, abs(lam)) or x > 0:
        return status
    return f'not verifiably stable: rounding of this matrix moves it by up to {bound:.2g}'


@dataclass(frozen=True)
class PlacementCheck:
    """
    Achieved versus requested poles of one designed gain.

    ``requested`` and ``achieved`` are matched element by element (optimal assignment);
    ``error`` is ``|achieved - requested|`` and ``bound`` what the conditioning of the
    placement allows (:func:`placement_bound`). ``relative_error`` is the largest
    ``error / max(1, |requested|)``; ``worst`` the index with the largest
    ``error / bound``.

    """

    field: str
    requested: np.ndarray
    achieved: np.ndarray
    error: np.ndarray
    bound: np.ndarray
    worst: Optional[int]

    @property
    def relative_error(self):
        """Largest ``|achieved - requested| / max(1, |requested|)``."""
        if not self.error.size:
            return 0.0
        return float(np.max(self.error / np.maximum(1.0, np.abs(self.requested))))

    @property
    def max_error(self):
        """Largest ``|achieved - requested|``."""
        return float(np.max(self.error)) if self.error.size else 0.0

    @property
    def within_bound(self):
        """Return True when every placed pole is within its bound."""
        return bool(np.all(self.error <= self.bound))

    def to_json(self):
        """Return a JSON-serialisable summary."""
        w = self.worst
        pair = (lambda z: [float(np.real(z)), float(np.imag(z))])
        return {'field': self.field,
                'max_error': self.max_error,
                'relative_error': self.relative_error,
                'bound_at_worst': None if w is None else float(self.bound[w]),
                'worst_requested': None if w is None else pair(self.requested[w]),
                'worst_achieved': None if w is None else pair(self.achieved[w]),
                'within_bound': self.within_bound}


def placement_bound(M, perturbation):
    """
    How far each eigenvalue of a placed closed loop may sit from its requested pole.

    A pole-placement algorithm that is backward stable returns a gain K that places the
    poles exactly for a plant perturbed by ``Delta`` with ``||Delta|| <= c n eps
    (||A|| + ||B|| ||K||)`` (the ``perturbation`` given here; for A - L C: ``||A|| +
    ||L|| ||C||``). By the Bauer-Fike theorem every eigenvalue of ``M = A - B K`` is then
    within ``cond(V) ||Delta||`` of a requested pole, V being M's eigenvector matrix
    (unit columns). The robust algorithms (Kautsky-Nichols-Van Dooren, scipy's
    ``place_poles``, python-control's ``place``) compute K from the eigenvectors they
    choose, so their error scales with cond(V) itself, not with the smaller
    per-eigenvalue condition numbers (measured: up to 3e5 times those for two and
    three inputs, within this bound). A placement further off than the bound was not
    solved to the accuracy the problem allows (the algorithm failed, as for 20 states
    and one input), whatever the size of the error; one within it is as accurate as
    double precision permits.

    Parameters
    ----------
    M : (n, n) array_like
        Achieved closed-loop matrix.
    perturbation : float
        ``||A|| + ||B|| ||K||`` (2-norms).

    Returns
    -------
    lam : (n,) ndarray of complex
        ``eig(M)``.
    bound : (n,) ndarray
        ``PLACEMENT_BOUND_FACTOR n eps perturbation cond(V)``, the same for every pole
        (infinite for a defective M: its eigenvalues may move freely). It includes the
        eigenvalues' own rounding error, ``eps ||M|| kappa_i`` with ``kappa_i <=
        cond(V)`` and ``||M|| <= perturbation``.

    """
    M = np.atleast_2d(np.asarray(M, dtype=float))
    n = M.shape[0] if M.size else 0
    if n == 0:
        return np.zeros(0, complex), np.zeros(0)
    lam, V = scipy.linalg.eig(M)
    V = V / np.maximum(np.linalg.norm(V, axis=0), 1e-300)
    with np.errstate(invalid='ignore', over='ignore', divide='ignore'):
        cond = float(np.linalg.cond(V))
        bound = PLACEMENT_BOUND_FACTOR * n * _EPS * float(perturbation) * cond
    if not np.isfinite(bound):
        bound = np.inf
    return lam, np.full(n, bound)


def match_eigenvalues(got, want):
    """
    Return the order of ``got`` that pairs it with ``want`` (``got[order]`` ~ ``want``).

    The assignment of least total relative distance, ``|got - want| / max(1, |want|)``
    (scipy's ``linear_sum_assignment``).
    """
    cost = np.abs(got[:, None] - want[None, :]) / np.maximum(1.0, np.abs(want))[None, :]
    from scipy.optimize import linear_sum_assignment    # scipy.optimize: when first used
    rows, cols = linear_sum_assignment(cost)
    order = np.empty(want.size, dtype=int)
    order[cols] = rows
    return order


def _advice(field):
    if field.startswith('controller'):
        return ('spread the poles apart, ask for fewer clustered poles, or use an LQR '
                'design (controller.lqr_Q and controller.lqr_R)')
    return ('spread the poles apart, ask for fewer clustered poles, or use a Kalman '
            'observer (observer.type: kalman)')


def _fmt(z):
    z = complex(z)
    if abs(z.imag) <= 1e-12 * max(1.0, abs(z)):
        return f'{z.real:.6g}'
    return f'{z.real:.6g}{z.imag:+.6g}j'


def verify_placement(M, requested, field, perturbation, discrete=False):
    """
    Check the poles a designed gain achieves against the poles asked for; refuse a bad one.

    Parameters
    ----------
    M : (n, n) array_like
        The closed-loop matrix built from the gain produced (``A - B K``, ``A - L C``
        or the reduced observer's F).
    requested : (n,) array_like of complex
        The poles asked for, plus any kept uncontrollable (unobservable) eigenvalues.
    field : str
        Vehicle-file field named by the error (``controller.poles``, ``observer.poles``).
    perturbation : float
        ``||A|| + ||B|| ||K||`` (see :func:`placement_bound`).
    discrete : bool
        z-plane instead of s-plane.

    Returns
    -------
    PlacementCheck

    Raises
    ------
    DesignVerificationError
        An achieved pole is not stable (stability rule of this module), or a pole is
        further from the requested one than :func:`placement_bound` allows. The one-line
        message names the field, the worst requested and achieved pole and what to do.

    """
    want = np.asarray(requested, dtype=complex).reshape(-1)
    lam, bound = placement_bound(M, perturbation)
    if want.size != lam.size:
        raise DesignVerificationError(
            f'{field}: {want.size} poles requested for a {lam.size}-state closed loop')
    if not want.size:
        return PlacementCheck(field, want, lam, np.zeros(0), np.zeros(0), None)
    order = match_eigenvalues(lam, want)
    got = lam[order]
    bound = bound[order]
    err = np.abs(got - want)
    with np.errstate(divide='ignore', invalid='ignore'):
        ratio = np.where(err > 0, err / np.maximum(bound, 1e-300), 0.0)
    check = PlacementCheck(field, want, got, err, bound, int(np.argmax(ratio)))
    bad = unstable_eigenvalues(M, discrete, with_bounds=True)
    if bad:
        lam_bad, status, b = bad[0]
        i = int(np.argmin(np.abs(got - lam_bad)))
        raise DesignVerificationError(
            f'{field}: the designed gain does not place pole {_fmt(want[i])}: it lands at '
            f'{_fmt(lam_bad)} ({describe_status(lam_bad, status, b, discrete)}; largest '
            f'placement error {check.max_error:.2g}); '
            f'the placement is too ill-conditioned to trust: {_advice(field)}')
    if not check.within_bound:
        i = check.worst
        raise DesignVerificationError(
            f'{field}: the designed gain places pole {_fmt(want[i])} at {_fmt(got[i])}, '
            f'off by {err[i]:.2g} where the conditioning of the problem allows '
            f'{bound[i]:.2g}: the placement failed; {_advice(field)}')
    return check


def verify_stable(M, field, what, discrete=False, norm=None):
    """
    Refuse a gain whose closed-loop matrix has an eigenvalue that is not stable.

    Parameters
    ----------
    M : (N, N) array_like
        Closed-loop matrix of the gain in use.
    field : str
        Vehicle-file field named by the error (``controller.K``, ``observer.gain``, ...).
    what : str
        The matrix in words, e.g. ``eig(A - B K)``.
    discrete : bool
        z-plane instead of s-plane.
    norm : float, optional
        See :func:`eigenvalue_bounds`.

    Raises
    ------
    DesignVerificationError
        Naming the field and the least stable eigenvalue.

    """
    bad = unstable_eigenvalues(M, discrete, norm, with_bounds=True)
    if bad:
        lam, status, b = bad[0]
        raise DesignVerificationError(
            f'{field} does not stabilize the loop: {what} has the eigenvalue {_fmt(lam)} '
            f'({describe_status(lam, status, b, discrete)})')
