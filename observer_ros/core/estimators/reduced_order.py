# observer_ros.core.estimators.reduced_order: the reduced-order observer.
"""
Reduced-order observer that reproduces the measured combinations exactly.

Seeds 000 section 3.5 and 002 section 5.4.2.

"""

import numpy as np
import scipy.linalg

from . import placement
from .current_form import CurrentForm
from .steps import CACHE_SIZE, DT_DIGITS, GAIN_DIGITS
from ..design import reduced_coordinates
from ..errors import DimensionError, ObserverError
from ..model import as_matrix, as_poles

__all__ = ['ReducedOrderEstimator']


class ReducedOrderEstimator(CurrentForm):
    """
    Reduced-order observer: measured combinations taken from y, the rest estimated.

    In the coordinates ``x_bar = T x`` of design.reduced_coordinates(C) (C the
    measured rows), ``x_bar[:p] = C x = ybar = y - D u`` and ``x_bar[p:]`` are
    the states ``rest``. On the exactly sampled model ``Phi = T Ad Tinv``,
    ``Gam = T Bd`` (blocks 11, 12, 21, 22 and 1, 2) the current-form observer of
    Franklin and Powell is::

        x2_{k+1} = Phi22 x2_k + Phi21 ybar_k + Gam2 u_k
                   + Lr (ybar_{k+1} - Phi11 ybar_k - Gam1 u_k - Phi12 x2_k)

    with the error ``e2_{k+1} = (Phi22 - Lr Phi12) e2_k``; Lr places the n - p
    poles exp(s h) (continuous) or z^k (discrete) for (Phi22, Phi12). This is the
    full-order current form with ``M = Tinv [I; Lr]``, so predictions between
    measurements are the model's, and ``C x_hat = y - D u`` holds exactly (to
    round-off) after every correction. The first measurement sets ybar and
    keeps x2 from x0 (``M = Tinv [I; 0]``).

    Outputs missing from a message: the correction uses the columns of M of the
    rows received (the missing measured coordinates keep their predicted value).
    Rows with the same time stamp are fused into one full correction, so sensors
    stamped together give the exact reduced-order observer; rows that always come
    at different times give a heuristic that is not guaranteed to converge.

    With a gain Lr given instead of poles:

    * continuous plant: Lr is the continuous gain of seeds 000/002,
      ``x2_hat = Lr ybar + z``, ``z' = F z + G ybar + H u`` with
      ``F = A22 - Lr A12``, ``G = A21 - Lr A11 + F Lr``, ``H = B2 - Lr B1``
      (blocks of ``T A Tinv`` and ``T B``), integrated exactly with u held over
      each step. Between measurements ybar is held (predictions); when a
      measurement arrives, the step since the previous one is redone with ybar
      ramping linearly from the previous measurement to this one (first-order
      hold, one extra matrix ``Gamma1(h)``). A held ybar would leave a bias of
      order ``|F^-1 G| dt dy/dt``, and G is large for a reduced observer: with
      the seed's cart gain at 1 kHz it was 4 rad/s on theta', against 2e-4
      with the ramp (second order: 2e-2 at 100 Hz, test_core_estimators.py).
      A missing output keeps its last value; the first measurement sets ybar
      and keeps x2.
    * discrete plant: Lr is the current-form gain of the equation above (exact
      when measurements come every sample; used as is for longer steps).

    Parameters
    ----------
    plant : Plant
        The model.
    poles : array_like of complex, optional
        n - p desired poles (or the observable rank minus p for a detectable
        plant); s-plane (continuous) or z-plane (discrete).
    gain : (n - p, p) array_like, optional
        Lr given directly; exactly one of poles and gain.
    method : {'auto', 'place', 'acker'}
        Pole-placement method.
    x0, t0, measured_rows, dt_digits, cache_size, gain_digits
        See :class:`Estimator`; p is the number of measured rows, which must be
        independent.

    """

    kind = 'reduced'
    _STATE = CurrentForm._STATE + ('_ybar', '_z')

    def __init__(self, plant, poles=None, gain=None, method='auto', x0=None, t0=None,
                 measured_rows=None, dt_digits=DT_DIGITS, cache_size=CACHE_SIZE,
                 gain_digits=GAIN_DIGITS):
        super().__init__(plant, x0, t0, measured_rows, dt_digits, cache_size, gain_digits)
        self._method = placement.design_choice(poles, gain, method, 'reduced-order observer')
        n = plant.n
        C_m = plant.C[list(self._measured)]
        pm = C_m.shape[0]
        self._T, self._Tinv, self._rest = reduced_coordinates(C_m)
        self._pm = pm
        self._pos = {r: i for i, r in enumerate(self._measured)}
        rank = placement.unobservable_check(plant.A, C_m, plant.is_discrete,
                                            'reduced-order observer')
        self._L = None
        self._poles = None
        if poles is not None:
            self._poles = as_poles(poles, 'poles', discrete=plant.is_discrete)
            if self._poles.size not in (n - pm, rank - pm):
                expected = f'{n - pm}' if rank == n else \
                    f'{n - pm} (or {rank - pm}, the observable rank minus p)'
                raise DimensionError(f'poles has {self._poles.size} poles; expected {expected}')
            self._mode = 'poles'
        else:
            self._L = as_matrix(gain, 'gain', rows=n - pm, cols=pm)
            self._mode = 'discrete_gain' if plant.is_discrete else 'held'
            if self._mode == 'held':
                self._setup_held()
        self._ybar = np.zeros(pm)
        self._z = np.zeros(n - pm)
        # the z-form of a continuous plant's given gain holds ybar: rewound, not shifted
        self._superposable = self._mode != 'held'
        self.reset(t0=self._t0)

    @property
    def coordinates(self):
        """Return copies of T, Tinv and rest as given by design.reduced_coordinates."""
        return self._T.copy(), self._Tinv.copy(), list(self._rest)

    @property
    def poles(self):
        """Desired poles as a copy; None when a gain was given."""
        return None if self._poles is None else self._poles.copy()

    @property
    def gain(self):
        """Copy of the gain Lr given to the constructor; None when poles were given."""
        return None if self._L is None else self._L.copy()

    def _cols(self, info):
        return [self._pos[r] for r in info.rows]

    def _full_gain(self, Lr):
        return self._Tinv @ np.vstack([np.eye(self._pm), Lr])

    def _gain(self, key, info):
        if self._mode == 'held':
            raise ObserverError('correction_gain and error_matrix apply to a reduced-order '
                                'observer given poles (or a discrete plant)')
        if key is None:
            M = self._init_gains.get(info.rows)
            if M is None:
                M = self._Tinv[:, :self._pm][:, self._cols(info)]
                self._init_gains[info.rows] = M
            return M
        step = self._cache.get(key)
        M = step.extra.get(info.rows)
        if M is None:
            Mfull = self._gain_value(key, 'Mfull', self._design_gain)
            M = None if Mfull is None else Mfull[:, self._cols(info)]
            step.extra[info.rows] = M
        return M

    def _design_gain(self, step):
        """Tinv [I; Lr] of a step: Lr places the poles on (Phi22, Phi12) (or is given)."""
        if self._mode == 'poles':
            Lr = self._verified_design(step, self._all.rows, self._place_reduced)
            if Lr is None:
                return None
        else:
            Lr = self._L
        return self._full_gain(Lr)

    def _place_reduced(self, step, field):
        pm = self._pm
        Phi = self._T @ step.Ad @ self._Tinv
        return placement.place(Phi[pm:, pm:], Phi[:pm, pm:], self._zpoles(step),
                               self._method, field)

    # continuous given gain: z-form with ybar held ---------------------------

    def _setup_held(self):
        plant = self._plant
        pm = self._pm
        Ab = self._T @ plant.A @ self._Tinv
        Bb = self._T @ plant.B
        A11, A12, A21, A22 = Ab[:pm, :pm], Ab[:pm, pm:], Ab[pm:, :pm], Ab[pm:, pm:]
        L = self._L
        F = A22 - L @ A12
        self._F = F
        self._G = A21 - L @ A11 + F @ L
        self._H = Bb[pm:] - L @ Bb[:pm]

    def _held_matrices(self, h):
        q, pm, m = self._F.shape[0], self._pm, self._plant.m
        aug = np.zeros((q + pm + m, q + pm + m))
        aug[:q, :q] = self._F
        aug[:q, q:q + pm] = self._G
        aug[:q, q + pm:] = self._H
        E = scipy.linalg.expm(aug * h)
        return E[:q, :q].copy(), E[:q, q:q + pm].copy(), E[:q, q + pm:].copy()

    def _held_x(self):
        x2 = self._L @ self._ybar + self._z
        self._x = self._Tinv @ np.concatenate([self._ybar, x2])

    def _reset_state(self):
        super()._reset_state()
        if self._mode == 'held':
            xb = self._T @ self._x
            self._ybar = xb[:self._pm].copy()
            self._z = xb[self._pm:] - self._L @ self._ybar

    def _propagate(self, step):
        if self._mode != 'held':
            self._propagate_model(step)
            return
        ent = step.extra.get('held')
        if ent is None:
            ent = self._held_matrices(step.h)
            step.extra['held'] = ent
        Phi, Gy, Gu = ent
        self._z = Phi @ self._z + Gy @ self._ybar + Gu @ self._u
        self._held_x()

    def _foh_matrix(self, step):
        """Gamma1(h) = (1/h) int_0^h expm(F (h - s)) G s ds (ybar ramping over the step)."""
        ent = step.extra.get('foh')
        if ent is None:
            q, pm = self._F.shape[0], self._pm
            aug = np.zeros((q + 2 * pm, q + 2 * pm))
            aug[:q, :q] = self._F
            aug[:q, q:q + pm] = self._G
            aug[q:q + pm, q + pm:] = np.eye(pm)
            E = scipy.linalg.expm(aug * step.h)
            ent = E[:q, q + pm:] / step.h
            step.extra['foh'] = ent
        return ent

    def _correct(self, y, info):
        if self._mode != 'held':
            super()._correct(y, info)
            return
        t = self._t
        ybar = y - info.D @ self._u
        self._residual = ybar - info.C @ self._x
        new = self._ybar.copy()
        new[self._cols(info)] = ybar
        if self._t_corr is None or t != self._t_corr:
            self._acc_key = None if self._t_corr is None else self._cache.key(t - self._t_corr)
            self._t_corr = t
        if self._acc_key is None:
            # First measurement: it sets ybar and keeps x2 (z absorbs the jump of Lr ybar).
            self._z += self._L @ (self._ybar - new)
        else:
            # The held ybar is replaced, over the step just ended, by the ramp from the
            # previous measurement to this one (first-order hold): the lag of a held y,
            # amplified by the large G of a reduced observer, is removed.
            self._z += self._foh_matrix(self._cache.get(self._acc_key)) @ (new - self._ybar)
        self._ybar = new
        self._held_x()
        self._t_anchor = t
