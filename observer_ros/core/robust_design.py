# observer_ros.core.robust_design: the observer (and controller) with the most margin.
"""
Robust redesign of a vehicle: minimise the peak sensitivity under a settling-time bound.

:func:`robust_design` searches the vehicle's observer and, when allowed, its controller
for the design whose loop, broken at the plant input, has the smallest peak sensitivity
``Ms`` (the largest disk margin), with every closed-loop pole settling within the bound
the user gives (4 time constants of the slowest pole, the compensator's own settle rule,
``core/health.py``), no pole faster than :data:`FASTEST_FRACTION` of the Nyquist
frequency (the sampled loop then behaves as the continuous design whose margins are
computed), and Ms weighed up by ``1 + log10(c / CONDITION_CAP)`` when the closed loop's
pole condition number c (``core/conditioning.py``) exceeds :data:`CONDITION_CAP`: a
margin bought with poles that a model error moves far is not one. The report warns from
``POLE_CONDITION_WARN`` (1e4) on; the search accepts more before it weighs, since the
least Ms of a plant near its limit needs it (the encoder-only cart: Ms 56 at c = 1e7,
no design below Ms 77 at c <= 1e4 in two minutes of search). The search:

1. controllers: the vehicle's own gain and, when allowed, LQR gains ``Q = rho I``,
   ``R = I`` over a range of rho (an LQR state feedback has Ms <= 1 at the plant input:
   the margins an observer can then recover);
2. observers, for each controller: the vehicle's own observer and Kalman filters with the
   process noise ``Qd = q0 I + q B B^T`` over a range of q (loop transfer recovery:
   as q grows the loop at the plant input tends to the state feedback's, when the plant
   has no non-minimum-phase zero for these outputs), the sensors' noise as ``Rd``;
3. with one input, one output, a full-order observer and the controller searched: the
   closed loop's characteristic polynomial itself. Every strictly proper controller of
   the plant's order is an observer-based one, and its 2n closed-loop poles fix it (the
   Diophantine equation ``a d + b n = phi``), so Nelder-Mead runs from
   :data:`POLYNOMIAL_STARTS` seeded random pole sets in the allowed region over the
   factors of ``phi`` (Ms on the search grid, no gain formed); the best set is split
   into controller and observer poles (the split of least cost);
4. a Nelder-Mead refinement of the best few: the observer poles (a full-order observer),
   or ``log q`` (Kalman), and the controller poles when allowed.

The result is checked by ``design_vehicle`` (every gain verified) and reviewed
(``core/design_review.py``) before and after, the figures a caller writes into the new
vehicle file. A plant whose outputs impose ``Ms >= M`` (``core/limits.py``) is searched
all the same; the result says how close to M it came.

"""

from dataclasses import dataclass, replace
import itertools
import math
from typing import Optional, Tuple
import warnings

import numpy as np
import scipy.linalg
import scipy.optimize
import scipy.signal

from ._lazy import control
from .conditioning import pole_sensitivity
from .design import lqr_gain
from .design_review import review_design
from .errors import ObserverError
from .health import POLE_FASTEST
from .limits import best_disk_margin, fundamental_limit
from .vehicle_design import design_vehicle, measurement_intensity

__all__ = ['RobustResult', 'robust_design', 'settling_of', 'loop_figures', 'ROBUST_TARGET']

#: What a robust design aims at, Ms at the plant input (also the report's warning level).
ROBUST_TARGET = 2.0

#: No searched pole is faster than this fraction of the Nyquist frequency pi / dt: the
#: sampled loop then behaves as the continuous design the margins are computed for.
FASTEST_FRACTION = 0.25

#: Frequencies of the search's Ms (the final figures come from the review's finer grid).
GRID_POINTS = 800

#: Candidates refined by Nelder-Mead, and its evaluations per parameter.
REFINED = 2
EVALUATIONS_PER_PARAMETER = 100

#: Nelder-Mead runs per start (each from where the last stopped).
RESTARTS = 2

#: The pole condition number above which the search weighs Ms up.
CONDITION_CAP = 1e7

#: Seeded random starts of the characteristic-polynomial search, its evaluations per
#: start, and the largest plant order it is used for (Sylvester matrices grow
#: ill-conditioned beyond).
POLYNOMIAL_STARTS = 4
POLYNOMIAL_EVALUATIONS = 2000
POLYNOMIAL_ORDER = 8

_RHOS = np.logspace(-3, 4, 15)
_QS = np.logspace(-4, 10, 15)


@dataclass(frozen=True)
class RobustResult:
    """
    What :func:`robust_design` found.

    ``vehicle`` is the redesigned vehicle (None when nothing better was found);
    ``before`` / ``after`` its figures (:func:`loop_figures`); ``settling_bound`` the
    bound searched under; ``ms_bound`` the fundamental limit of the outputs;
    ``searched`` what was varied; ``message`` one paragraph for the user.

    """

    vehicle: object
    before: dict
    after: Optional[dict]
    settling_bound: float
    ms_bound: float
    searched: Tuple[str, ...]
    message: str


def settling_of(poles, discrete=False, dt=None):
    """4 time constants of the slowest pole (s); inf when one does not decay."""
    poles = np.asarray(poles, dtype=complex).reshape(-1)
    if not poles.size:
        return 0.0
    with np.errstate(divide='ignore'):
        rates = -np.log(np.abs(poles)) / dt if discrete else -poles.real
    slowest = float(np.min(rates))
    return math.inf if slowest <= 0.0 else 4.0 / slowest


class _Loop:
    """Fast evaluation of Ms at the plant input for gains (K, L) of a full-order observer."""

    def __init__(self, plant, w):
        self.A, self.B, self.C, self.D = plant.A, plant.B, plant.C, plant.D
        self.dt = plant.dt
        self.w = w
        s = np.exp(1j * w * plant.dt) if plant.dt else 1j * w
        self.s = s
        n = self.A.shape[0]
        M = s[:, None, None] * np.eye(n)[None] - self.A[None]
        X = np.linalg.solve(M, np.broadcast_to(self.B, (w.size,) + self.B.shape))
        self.P = self.C[None] @ X + self.D[None]              # (w, p, m)

    def peak(self, K, L):
        A, B, C, D = self.A, self.B, self.C, self.D
        n = A.shape[0]
        Ac = A - B @ K - L @ C + L @ D @ K
        M = self.s[:, None, None] * np.eye(n)[None] - Ac[None]
        X = np.linalg.solve(M, np.broadcast_to(L, (self.w.size,) + L.shape))
        Dc = K[None] @ X                                      # (w, m, p)
        Li = Dc @ self.P                                      # (w, m, m)
        m = Li.shape[1]
        S = np.linalg.inv(np.eye(m)[None] + Li)
        if m == 1:
            mags = np.abs(S[:, 0, 0])
        else:
            mags = np.linalg.svd(S, compute_uv=False)[:, 0]
        if not np.all(np.isfinite(mags)):
            return math.inf
        return float(np.max(mags))


def loop_figures(design, review):
    """Return the figures a robust design is judged by, from a design and its review."""
    inputs = [m for m in review.margins if m.side == 'input']
    first = inputs[0] if inputs else None
    cl = design.closed_loop_poles if design.K is not None else design.observer_poles
    return {
        'Ms': None if first is None else first.peak_sensitivity,
        'disk_margin': None if first is None else first.disk,
        'gain_margin': None if first is None else
        (min(m.gain_low for m in inputs), max(m.gain_high for m in inputs)),
        'phase_margin_deg': None if first is None else min(m.phase for m in inputs),
        'delay_margin_s': None if first is None else min(m.delay for m in inputs),
        'settling_s': settling_of(cl, design.discrete, design.sample_time),
        'observer_growth': None if review.observer_growth is None else
        review.observer_growth[0],
        'closed_loop_growth': None if review.closed_loop_growth is None else
        review.closed_loop_growth[0],
    }


def _pattern(poles):
    """Parameters (log decay, log frequency) of each pair and log decay of each real pole."""
    poles = np.asarray(poles, dtype=complex)
    x, kinds = [], []
    for z in sorted(poles, key=lambda z: (z.real, -z.imag)):
        if abs(z.imag) > 1e-9 * max(1.0, abs(z)):
            if z.imag > 0:
                x += [math.log(max(-z.real, 1e-6)), math.log(z.imag)]
                kinds.append('pair')
        else:
            x.append(math.log(max(-z.real, 1e-6)))
            kinds.append('real')
    return np.array(x), tuple(kinds)


def _poles(x, kinds):
    out, i = [], 0
    for k in kinds:
        if k == 'pair':
            s, f = math.exp(x[i]), math.exp(x[i + 1])
            out += [complex(-s, f), complex(-s, -f)]
            i += 2
        else:
            out.append(complex(-math.exp(x[i]), 0.0))
            i += 1
    return np.array(out)


def _noise_covariance(vehicle):
    """Rd per sample: the sensors' noise_std squared (1 where not given)."""
    plant = vehicle.plant
    Rd = np.ones(plant.p)
    for s in vehicle.sensors:
        std = np.asarray(s.noise_std, dtype=float).reshape(-1)
        for j, out in enumerate(s.outputs):
            if out in plant.output_names and j < std.size and std[j] > 0:
                Rd[plant.output_names.index(out)] = std[j] ** 2
    return np.diag(Rd)


class _Search:
    def __init__(self, vehicle, bound):
        self.vehicle = vehicle
        plant = vehicle.plant
        self.plant = plant
        self.bound = bound
        self.dt = vehicle.sample_time
        self.fastest = min(POLE_FASTEST, FASTEST_FRACTION * math.pi) / self.dt
        lam = np.linalg.eigvals(plant.A)
        if plant.is_discrete:
            with np.errstate(divide='ignore'):
                lam = np.log(lam.astype(complex)) / plant.dt
        mags = [abs(z) for z in lam if np.isfinite(z) and abs(z) > 1e-9]
        lo = 0.01 * min(mags + [4.0 / bound])
        hi = math.pi / self.dt
        self.loop = _Loop(plant, np.logspace(math.log10(lo), math.log10(hi), GRID_POINTS))
        self.Rd_sample = _noise_covariance(vehicle)
        self.Rd = measurement_intensity(replace(vehicle, observer=replace(
            vehicle.observer, Rd=self.Rd_sample)))
        self.q0 = 1e-6 * float(np.trace(self.Rd)) / plant.p
        self.evaluations = 0
        self._kalman = {}

    def cost(self, K, L, poles):
        """Ms, or a penalty above any Ms for poles that break the bounds."""
        self.evaluations += 1
        penalty = self.penalty(poles)
        if penalty:
            return penalty
        return self.loop.peak(K, L) * self._conditioning(K, L)

    def penalty(self, poles):
        """0, or a penalty above any Ms for closed-loop poles that break the bounds."""
        poles = np.asarray(poles, dtype=complex)
        if self.plant.is_discrete:
            settle = settling_of(poles, True, self.plant.dt)
            fast = 0.0
        else:
            settle = settling_of(poles)
            fast = float(np.max(np.abs(poles))) if poles.size else 0.0
        if not math.isfinite(settle):
            return 1e12
        penalty = 0.0
        if settle > self.bound:
            penalty += 1e6 * (1.0 + settle / self.bound)
        if fast > self.fastest:
            penalty += 1e6 * (1.0 + fast / self.fastest)
        return penalty

    def _conditioning(self, K, L):
        """1, or more for a closed loop whose poles are too sensitive (log10 above the limit)."""
        A, B, C = self.plant.A, self.plant.B, self.plant.C
        M = np.block([[A, -B @ K], [L @ C, A - L @ C - B @ K]])
        sensitivity = pole_sensitivity(M)       # with cond(V) of M as formed
        c = max(sensitivity.max_condition, sensitivity.eigenvector_condition)
        if not np.isfinite(c):
            return 1e6
        return 1.0 + max(0.0, math.log10(c / CONDITION_CAP))

    def kalman(self, q):
        """
        Return the Kalman gain of ``Qd = q0 I + q B B^T`` (python-control's lqe form).

        Solved once per q: every controller of the search pairs with the same filters.

        """
        q = float(q)
        if q not in self._kalman:
            self._kalman[q] = self._solve_kalman(q)
        return self._kalman[q]

    def _solve_kalman(self, q):
        plant = self.plant
        A, C, R = plant.A, plant.C, self.Rd
        Qd = self.q0 * np.eye(plant.n) + q * plant.B @ plant.B.T
        if plant.is_discrete:
            P = scipy.linalg.solve_discrete_are(A.T, C.T, Qd, R)
            L = A @ P @ C.T @ np.linalg.inv(C @ P @ C.T + R)
        else:
            P = scipy.linalg.solve_continuous_are(A.T, C.T, Qd, R)
            L = P @ C.T @ np.linalg.inv(R)
        return L, np.linalg.eigvals(A - L @ C), Qd


def _place(A, B, poles):
    """Return a gain placing the poles (acker with one input, else Tits-Yang), unverified."""
    if B.shape[1] == 1:
        return np.asarray(control.acker(A, B, poles), dtype=float).reshape(1, -1)
    return np.asarray(scipy.signal.place_poles(A, B, poles).gain_matrix, dtype=float)


def _sylvester(a, b, n):
    """Return (M, base): ``phi[1:] = base + M [d_1..d_n, c_0..c_{n-1}]`` for a d + b c."""
    M = np.zeros((2 * n + 1, 2 * n))
    for k in range(1, n + 1):
        M[k:k + n + 1, k - 1] = a
    for j in range(n):
        M[j + 1:j + n + 2, n + j] = b
    base = np.zeros(2 * n + 1)
    base[:n + 1] = a
    return M[1:], base[1:]


def _factors(x):
    """Return the product of the factors s^2 + 2 zeta w s + w^2, x = (log w, zeta) each."""
    phi = np.array([1.0])
    for logw, zeta in x.reshape(-1, 2):
        w = math.exp(min(logw, 50.0))
        # np.polymul without its poly1d conversions: the same product, at a fraction of the cost
        phi = np.convolve(phi, [1.0, 2.0 * zeta * w, w * w])
    return phi


def _groups(poles):
    """Return the poles as conjugate pairs and real poles (lists of one or two)."""
    left = sorted(np.asarray(poles, dtype=complex), key=lambda z: (z.real, z.imag))
    out = []
    while left:
        z = left.pop(0)
        if abs(z.imag) > 1e-9 * max(1.0, abs(z)):
            j = min(range(len(left)), key=lambda i: abs(left[i] - z.conjugate()))
            left.pop(j)
            out.append([complex(z.real, abs(z.imag)), complex(z.real, -abs(z.imag))])
        else:
            out.append([complex(z.real, 0.0)])
    return out


def _polynomial_search(search):
    """
    Find the 2n closed-loop poles of least Ms (one input, one output), as a candidate.

    The plant ``b / a`` and a controller ``c / d`` (d monic of degree n, c of degree
    n - 1) close to ``phi = a d + b c``: given the poles, one linear solve gives d, and
    ``S = a d / phi``. Returns ``(cost, K, controller poles, ('poles', observer poles))``
    of the split of least cost, or None.

    """
    plant = search.plant
    n = plant.n
    with warnings.catch_warnings():
        warnings.simplefilter('ignore')
        num, den = scipy.signal.ss2tf(plant.A, plant.B, plant.C, plant.D)
    a = np.asarray(den, dtype=float).reshape(-1)
    b = np.asarray(num, dtype=float).reshape(-1)
    b = np.concatenate([np.zeros(n + 1 - b.size), b])[-(n + 1):]
    M, base = _sylvester(a, b, n)
    if np.linalg.cond(M) > 1e12:
        return None
    s = 1j * search.loop.w
    a_s = np.polyval(a, s)

    def ms(x):
        search.evaluations += 1
        phi = _factors(x)
        penalty = search.penalty(np.roots(phi))
        if penalty:
            return penalty
        d = np.concatenate([[1.0], np.linalg.solve(M, phi[1:] - base)[:n]])
        S = a_s * np.polyval(d, s) / np.polyval(phi, s)
        peak = float(np.max(np.abs(S)))
        return peak if math.isfinite(peak) else 1e12

    rng = np.random.default_rng(0)
    lo, hi = math.log(4.0 / search.bound), math.log(search.fastest)
    best = None
    for _ in range(POLYNOMIAL_STARTS):
        x = np.column_stack([rng.uniform(lo, hi, n), rng.uniform(0.05, 1.5, n)]).reshape(-1)
        for _ in range(RESTARTS):
            res = scipy.optimize.minimize(ms, x, method='Nelder-Mead',
                                          options={'maxfev': POLYNOMIAL_EVALUATIONS,
                                                   'adaptive': True})
            x = res.x
        if best is None or res.fun < best[0]:
            best = (res.fun, x)
    if best is None or best[0] >= 1e6:
        return None
    groups = _groups(np.roots(_factors(best[1])))
    out = None
    for r in range(1, len(groups) + 1):
        for chosen in itertools.combinations(range(len(groups)), r):
            pc = [z for i in chosen for z in groups[i]]
            if len(pc) != n:
                continue
            po = [z for i in range(len(groups)) if i not in chosen for z in groups[i]]
            pc, po = np.array(pc), np.array(po)
            K = _quiet(_place, plant.A, plant.B, pc)
            Lt = _quiet(_place, plant.A.T, plant.C.T, po)
            if K is None or Lt is None:
                continue
            c = search.cost(K, Lt.T, np.concatenate([pc, po]))
            if out is None or c < out[0]:
                out = (c, K, pc, ('poles', po))
    return out


def _quiet(fn, *args):
    with warnings.catch_warnings():
        warnings.simplefilter('ignore')
        try:
            return fn(*args)
        except (ObserverError, ValueError, np.linalg.LinAlgError):
            return None


def _controllers(search, design, allow):
    plant = search.plant
    out = [('file', design.K, np.linalg.eigvals(plant.A - plant.B @ design.K))]
    if not allow:
        return out
    for rho in _RHOS:
        res = _quiet(lqr_gain, plant.A, plant.B, rho * np.eye(plant.n), np.eye(plant.m),
                     plant.is_discrete)
        if res is not None:
            out.append((f'lqr {rho:.3g}', res[0], res[2]))
    return out


def robust_design(vehicle, settling_time=None, controller=False, design=None, review=None):
    """
    Search the observer (and the controller) for the smallest Ms at the plant input.

    Parameters
    ----------
    vehicle : observer_ros.core.spec.Vehicle
        A vehicle with a controller and a 'full', 'reduced' or 'kalman' observer.
    settling_time : float, optional
        Bound on the settling time (s, 4 time constants of the slowest closed-loop pole);
        default twice the vehicle's own design's.
    controller : bool
        Search the controller too (LQR, then its poles); otherwise keep its gain.
    design, review : optional
        The vehicle's design and review (computed when not given).

    Returns
    -------
    RobustResult

    """
    plant = vehicle.plant
    if design is None:
        design = design_vehicle(vehicle)
    if review is None:
        review = review_design(design, vehicle)
    if design.K is None:
        raise ObserverError('--robust needs a controller (controller.poles, controller.K or '
                            'controller.lqr_Q/lqr_R): the margins are those of the loop')
    before = loop_figures(design, review)
    bound = float(settling_time) if settling_time else 2.0 * before['settling_s']
    if not (bound > 0.0 and math.isfinite(bound)):
        raise ObserverError(f'settling-time bound {bound!r} s is not a positive finite time')
    limit = fundamental_limit(plant.A, plant.B, plant.C, plant.D, plant.is_discrete,
                              plant.dt, plant.output_names, plant.state_names)
    search = _Search(vehicle, bound)
    candidates = []      # (cost, K, ctrl poles, observer: ('poles', poles) | ('kalman', q))
    file_obs = design.observer_poles if design.reduced is None else None
    for _, K, cpoles in _controllers(search, design, controller):
        if design.reduced is None:
            c = search.cost(K, design.L, np.concatenate([cpoles, file_obs]))
            candidates.append((c, K, cpoles, ('poles', file_obs)))
        for q in _QS * max(1.0, float(np.trace(search.Rd))):
            res = _quiet(search.kalman, q)
            if res is None:
                continue
            L, E, _ = res
            candidates.append((search.cost(K, L, np.concatenate([cpoles, E])), K, cpoles,
                               ('kalman', q)))
    candidates.sort(key=lambda t: t[0])
    best = candidates[0]
    starts = list(candidates[:REFINED])
    if plant.p == 1:
        # one output: the Kalman gain is the placement of its own poles; searching those
        # poles directly has more freedom than the single weight q
        kal = [c for c in candidates if c[3][0] == 'kalman'][:1]
        for c in kal:
            L, E, _ = search.kalman(c[3][1])
            starts.append((c[0], c[1], c[2], ('poles', E)))
    if controller and plant.m == 1 and plant.p == 1 and design.reduced is None and \
            not plant.is_discrete and plant.n <= POLYNOMIAL_ORDER:
        cand = _polynomial_search(search)
        if cand is not None:
            starts.append(cand)
    for cand in starts:
        for _ in range(RESTARTS):
            cand = _refine(search, cand, controller)
        if cand[0] < best[0]:
            best = cand
    searched = ('observer (full-order poles, Kalman weights Qd = q0 I + q B B^T)',) + \
        (('controller (LQR, then its poles)',) if controller else ())
    return _result(vehicle, design, before, best, search, limit, searched, controller)


def _refine(search, cand, controller):
    """Nelder-Mead on the observer (poles or log q) and, if allowed, the controller poles."""
    cost0, K0, cpoles, (kind, obs) = cand
    plant = search.plant
    if plant.is_discrete:
        return cand
    cx, ckinds = _pattern(cpoles)
    ox, okinds = _pattern(obs) if kind == 'poles' else (np.array([math.log(obs)]), None)
    nc = cx.size if controller else 0

    def unpack(x):
        if controller:
            pc = _poles(x[:nc], ckinds)
            K = _quiet(_place, plant.A, plant.B, pc)
        else:
            pc, K = cpoles, K0
        if K is None:
            return None
        if kind == 'poles':
            po = _poles(x[nc:], okinds)
            Lt = _quiet(_place, plant.A.T, plant.C.T, po)
            return None if Lt is None else (K, pc, Lt.T, po, ('poles', po))
        res = _quiet(search.kalman, math.exp(x[nc]))
        return None if res is None else (K, pc, res[0], res[1], ('kalman', math.exp(x[nc])))

    def f(x):
        if kind == 'poles':
            # the poles are known before any gain is placed: those that break the bounds
            # cost their penalty without the placements (most of an evaluation's time)
            pc = _poles(x[:nc], ckinds) if controller else cpoles
            penalty = search.penalty(np.concatenate([pc, _poles(x[nc:], okinds)]))
            if penalty:
                search.evaluations += 1
                return penalty
        got = unpack(x)
        if got is None:
            return 1e12
        K, pc, L, po, _ = got
        return search.cost(K, L, np.concatenate([pc, po]))

    x0 = np.concatenate([cx[:nc], ox])
    res = scipy.optimize.minimize(f, x0, method='Nelder-Mead',
                                  options={'maxfev': EVALUATIONS_PER_PARAMETER * x0.size,
                                           'xatol': 1e-3,
                                           'fatol': 1e-4, 'adaptive': True})
    got = unpack(res.x)
    if got is None or res.fun >= cost0:
        return cand
    K, pc, _, _, obs_new = got
    return res.fun, K, pc, obs_new


def _result(vehicle, design, before, best, search, limit, searched, controller):
    cost, K, cpoles, (kind, obs) = best
    plant = vehicle.plant
    o = vehicle.observer
    if kind == 'kalman':
        Qd = search.q0 * np.eye(plant.n) + obs * plant.B @ plant.B.T
        obs_spec = replace(o, kind='kalman', poles=None, gain=None, Qd=(Qd + Qd.T) / 2.0,
                           Rd=search.Rd_sample, Bd=None)
    else:
        obs_spec = replace(o, kind='full', poles=np.asarray(obs, dtype=complex), gain=None,
                           Qd=None, Rd=None, Bd=None)
    ctrl = vehicle.controller
    if controller:
        if plant.m == 1:
            ctrl = replace(ctrl, poles=np.asarray(cpoles, dtype=complex), K=None,
                           lqr_Q=None, lqr_R=None)
        else:
            ctrl = replace(ctrl, poles=None, K=np.asarray(K, dtype=float), lqr_Q=None,
                           lqr_R=None)
    new = replace(vehicle, observer=obs_spec, controller=ctrl, warnings=())
    with warnings.catch_warnings():
        warnings.simplefilter('ignore')
        d2 = design_vehicle(new)
        r2 = review_design(d2, new)
    after = loop_figures(d2, r2)
    ms_before, ms_after = before['Ms'], after['Ms']
    bound_text = (f'the outputs {list(limit.outputs)} allow no controller below '
                  f'Ms = {limit.ms_bound:.3g}') if limit.ms_bound > 1.0 else \
        f'the outputs {list(limit.outputs)} impose no bound on Ms'
    if ms_after >= ms_before:
        return RobustResult(None, before, after, search.bound, limit.ms_bound, searched,
                            "no design found with a smaller Ms than the file's "
                            f'({ms_before:.3g}) within the settling bound '
                            f'{search.bound:.3g} s; {bound_text}')
    if math.isfinite(limit.ms_bound) and limit.ms_bound > ROBUST_TARGET:
        ratio = ms_after / limit.ms_bound
        verdict = (f'{ratio:.2g}x that bound; no controller with these outputs reaches Ms '
                   f'{ROBUST_TARGET:g} (a disk margin above '
                   f'{best_disk_margin(limit.ms_bound)[0]:.2g} is out of reach)')
        if limit.sensor_obstacle and limit.better_with:
            verdict += (f': the sensor set is the obstacle (measuring {limit.better_with} as '
                        f'well lowers the bound to {limit.better_bound:.3g})')
    else:
        verdict = 'meets the target' if ms_after <= ROBUST_TARGET else \
            f'above the target {ROBUST_TARGET:g}'
    msg = (f'Ms at the plant input {ms_before:.3g} -> {ms_after:.3g} ({bound_text}; '
           f'{verdict}), settling {before["settling_s"]:.3g} -> {after["settling_s"]:.3g} s '
           f'(bound {search.bound:.3g} s), {search.evaluations} designs evaluated')
    return RobustResult(new, before, after, search.bound, limit.ms_bound, searched, msg)
