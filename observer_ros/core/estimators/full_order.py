# observer_ros.core.estimators.full_order: the full-order Luenberger observer.
"""
Full-order Luenberger observer in current (filter) form, exact at any sample times.

With a gain instead of poles: the held (continuous) or predictor (discrete) form.

"""

import numpy as np
import scipy.linalg

from . import placement
from .current_form import CurrentForm
from .steps import CACHE_SIZE, DT_DIGITS, GAIN_DIGITS
from ..errors import DimensionError, ObserverError
from ..model import as_matrix, as_poles

__all__ = ['FullOrderEstimator']


class FullOrderEstimator(CurrentForm):
    """
    Full-order Luenberger observer, exact at any (irregular) sample times.

    With poles, the observer runs in current (filter) form so that x_hat at t
    uses y(t)::

        x-  = Ad(dt) x+ + Bd(dt) u                    (propagate, ZOH on u)
        x+  = x- + M (y - D u - C x-)                 (correct)

    The error of two successive corrections h seconds apart obeys
    ``e+ <- (I - M C) Ad(h) e+``, and ``eig((I - M C) Ad) = eig(Ad - M (C Ad))``,
    so M is designed on the pair (Ad(h), C Ad(h)) with the z-plane poles
    ``exp(s h)`` (continuous plant, s the given poles) or ``z^k`` (discrete
    plant, k samples). For a continuous plant h is the step rounded to
    ``gain_digits`` significant digits (Ad of the step itself propagates), so
    with a step that is not a 3-digit number the poles of the error map are
    within about ``|A| |h - dt|`` of ``exp(s h)`` (:meth:`error_matrix` gives the
    map actually applied). With the true plant and no noise the error goes to
    zero to round-off at any sampling, with no step-dependent bias.

    Partial rows: a gain is designed for each set of rows. If (Ad, C[rows] Ad)
    is not observable only its observable part is placed (with the fastest of
    the given poles that fit, see ``_pick_poles``) and the unobservable modes
    are left as they are, even when unstable: the other rows, when they arrive,
    correct them. Messages with the same time stamp are fused (one correction
    with all their rows). Rows that always come at different times still
    converge in the cases tested, but not at the designed rate: on the cart
    with theta and x alternating at 200 Hz the error decays at about -6.2/s
    instead of -10/s (the product of the two maps has other eigenvalues).

    With a gain L given instead of poles:

    * continuous plant: L is the continuous-time gain of
      ``x_hat' = A x_hat + B u + L (y - C x_hat - D u)``, sampled exactly with
      ``ybar = y - D u`` (D u taken with the input held when y arrived) and u held
      constant over each step (ZOH on both): one matrix exponential of
      ``[[A - L C, B, L], [0, 0, 0], [0, 0, 0]] dt``. With D = 0 this is the
      ``[[A - L C, B - L D, L], ...]`` form with y held; holding ybar instead of y
      keeps a later change of u from looking like a change of the measured
      states. x_hat(t) is the prediction before y(t) (ybar(t) is held from t on;
      each output keeps its last value, outputs never received do not enter). This is exact for the
      continuous observer fed by sample-and-hold signals, not for the sampled
      plant: the held y lags the true one, so in a noise-free run the error
      tends to a bias proportional to dt and to dy/dt. Measured on the
      submarine (test_core_estimators.py): the bias is first order in dt (about
      10 times smaller at 100 Hz than at 10 Hz) and vanishes only as the plant
      comes to rest.
    * discrete plant: L is the predictor gain of
      ``x_{k+1} = A x_k + B u_k + L (y_k - C x_k - D u_k)``; the error obeys
      ``e_{k+1} = (A - L C) e_k``. Seed 001 writes the same observer as
      ``z_{k+1} = (A + L C) z_k - L y_k + B u_k``, with the opposite sign of L.
      A measurement enters the next sample step only.

    Parameters
    ----------
    plant : Plant
        The model.
    poles : array_like of complex, optional
        Desired observer poles: n, or the observable rank of (A, C[measured]) for
        a detectable plant; s-plane for a continuous plant, z-plane for a
        discrete one.
    gain : (n, p) array_like, optional
        L given directly (columns for all plant outputs); exactly one of poles
        and gain.
    method : {'auto', 'place', 'acker'}
        Pole-placement method (design.observer_gain).
    x0, t0, measured_rows, dt_digits, cache_size, gain_digits
        See :class:`Estimator`.

    """

    kind = 'full'
    _STATE = CurrentForm._STATE + ('_held', '_held_rows')

    def __init__(self, plant, poles=None, gain=None, method='auto', x0=None, t0=None,
                 measured_rows=None, dt_digits=DT_DIGITS, cache_size=CACHE_SIZE,
                 gain_digits=GAIN_DIGITS):
        super().__init__(plant, x0, t0, measured_rows, dt_digits, cache_size, gain_digits)
        self._method = placement.design_choice(poles, gain, method, 'full-order observer')
        n, p = plant.n, plant.p
        C_m = plant.C[list(self._measured)]
        rank = placement.unobservable_check(plant.A, C_m, plant.is_discrete,
                                            'full-order observer')
        if poles is not None:
            self._mode = 'poles'
            self._poles = as_poles(poles, 'poles', discrete=plant.is_discrete)
            if self._poles.size not in (n, rank):
                expected = f'{n}' if rank == n else f'{n} (or {rank}, the observable rank)'
                raise DimensionError(f'poles has {self._poles.size} poles; expected {expected}')
            self._L = None
        else:
            self._L = as_matrix(gain, 'gain', rows=n, cols=p)
            self._poles = None
            self._mode = 'predictor' if plant.is_discrete else 'held'
        self._held = np.zeros(p)
        self._held_rows = ()
        # given a gain, the measured outputs are held between samples: rewound, not shifted
        self._superposable = self._mode == 'poles'
        self.reset(t0=self._t0)

    @property
    def poles(self):
        """Desired poles as a copy; None when a gain was given."""
        return None if self._poles is None else self._poles.copy()

    @property
    def gain(self):
        """Copy of the gain L given to the constructor; None when poles were given."""
        return None if self._L is None else self._L.copy()

    def _reset_state(self):
        super()._reset_state()
        self._held_rows = ()

    def _gain(self, key, info):
        if key is None:
            return None
        if self._mode != 'poles':
            raise ObserverError('correction_gain and error_matrix apply to a full-order '
                                'observer given poles')
        return self._gain_value(key, info.rows, lambda step: self._verified_design(
            step, info.rows, lambda s, field: placement.place(
                s.Ad, info.C @ s.Ad, self._zpoles(s), self._method, field)))

    def _propagate(self, step):
        mode = self._mode
        if mode == 'poles' or not self._held_rows:
            self._propagate_model(step)
        elif mode == 'held':
            key = ('held', self._held_rows)
            ent = step.extra.get(key)
            if ent is None:
                ent = self._held_matrices(step.h, self._held_rows)
                step.extra[key] = ent
            Phi, Gu, Gy, idx = ent
            x = Phi @ self._x + Gu @ self._u + Gy @ self._held[idx]
            self._x = x
        else:
            self._predictor_step(step)

    def _held_matrices(self, h, rows):
        plant = self._plant
        n, m = plant.n, plant.m
        idx = np.array(rows, dtype=np.intp)
        L = self._L[:, idx]
        k = idx.size
        aug = np.zeros((n + m + k, n + m + k))
        aug[:n, :n] = plant.A - L @ plant.C[idx]
        aug[:n, n:n + m] = plant.B
        aug[:n, n + m:] = L
        E = scipy.linalg.expm(aug * h)
        return E[:n, :n].copy(), E[:n, n:n + m].copy(), E[:n, n + m:].copy(), idx

    def _predictor_step(self, step):
        plant = self._plant
        idx = np.array(self._held_rows, dtype=np.intp)
        L = self._L[:, idx]
        x = plant.A @ self._x + plant.B @ self._u + L @ (self._held[idx] - plant.C[idx] @ self._x)
        if step.k > 1:
            rest = self._cache.get(step.k - 1)
            x = rest.Ad @ x + rest.Bd @ self._u
        self._x = x
        self._held_rows = ()

    def _correct(self, y, info):
        if self._mode == 'poles':
            super()._correct(y, info)
            return
        ybar = y - info.D @ self._u
        self._residual = ybar - info.C @ self._x
        # held (continuous): ybar held from t on; predictor (discrete): ybar used by the
        # next sample step. Holding ybar = y - D u rather than y means a later change of
        # u does not look like a change of the measured states.
        self._held[info.idx] = ybar
        self._held_rows = tuple(sorted(set(self._held_rows) | set(info.rows)))
        self._t_anchor = self._t
