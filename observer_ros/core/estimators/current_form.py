# observer_ros.core.estimators.current_form: the correction shared by full and reduced order.
"""
Current-form correction ``x+ = x- + M (ybar - C x-)`` with same-stamp fusion.

The full-order and reduced-order observers given poles differ only in their gain M.

"""

import numpy as np

from .base import as_rows, Estimator
from ..errors import DesignVerificationError


class CurrentForm(Estimator):
    """
    Estimators whose correction is ``x+ = x- + M(h, rows) (ybar - C x-)``.

    h is the time since the previous correction (or since the initial estimate),
    so predictions in between do not change the error dynamics from one
    correction to the next, ``e+ <- (I - M C) Ad(h) e+``. Several corrections
    at one time are fused: the correction is recomputed from the prior at that
    time with all the rows received at that time (ybar = y - D u of each row as
    received).

    Every gain designed for a step is verified (``placement.place``). A step whose
    gain fails the check is never corrected with it: that correction is skipped
    (prediction only, as if the measurement had not come), counted in
    :attr:`unverified_corrections`, and :attr:`gain_failures` keeps the reason per
    (step, rows). ``correction_gain`` and ``error_matrix`` raise it instead.

    """

    _STATE = Estimator._STATE + ('_x_prior', '_acc', '_acc_rows', '_acc_key', '_t_corr',
                                 '_gain_used')
    _MOVED = ('_residual', '_x_prior', '_acc')

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        p = self._plant.p
        n = self._plant.n
        self._x_prior = np.zeros(n)
        self._acc = np.zeros(p)
        self._acc_rows = set()
        self._acc_key = None
        self._t_corr = None
        self._gain_used = None          # (M, rows) of the last correction (superposition)
        self._init_gains = {}
        self.unverified_corrections = 0
        self.gain_failures = {}

    def _reset_state(self):
        self._acc_rows = set()
        self._acc_key = None
        self._t_corr = None

    def _correct(self, y, info):
        t = self._t
        ybar = y - info.D @ self._u
        if self._t_corr is None or t != self._t_corr:
            h = t - self._t_anchor
            self._acc_key = None if h <= 0.0 else self._cache.key(h)
            np.copyto(self._x_prior, self._x)
            self._acc_rows = set(info.rows)
            self._t_corr = t
            union = info if info.is_sorted else \
                self._rows_info(tuple(sorted(info.rows)), 'rows')
        else:
            self._acc_rows.update(info.rows)
            union = self._rows_info(tuple(sorted(self._acc_rows)), 'rows')
        self._acc[info.idx] = ybar
        self._residual = ybar - info.C @ self._x_prior
        self._t_anchor = t
        M = self._gain(self._acc_key, union)
        self._gain_used = (M, union)
        if M is None:
            if self._acc_key is not None:
                self.unverified_corrections += 1
            np.copyto(self._x, self._x_prior)
            return
        innov = self._acc[union.idx] - union.C @ self._x_prior
        np.dot(M, innov, out=self._buf)
        self._buf += self._x_prior
        self._x, self._buf = self._buf, self._x

    def _shift_correction(self, state, new, dx, dyb, info, t, carry):
        """
        Move a saved state by a late input change (see :mod:`.superposition`).

        The prior moves by dx (at the first correction of a stamp; the later ones at that
        stamp share it, in ``carry``), ybar by dyb (-D du; None when zero or after a later
        command), and the estimate by ``dx_prior + M (dybar - C dx_prior)`` with the M the
        correction used. ``carry`` keeps ybar's change per row as last set, as ``_acc``
        keeps ybar.
        """
        slots = self._slots
        if carry[0] != t:
            carry[0], carry[1] = t, dx
        dx_prior = carry[1]
        dacc = carry[2]                 # ybar's change per row, as last set (any stamp)
        C_dx = info.C @ dx_prior
        if dyb is None:
            dres = -C_dx
            if dacc is not None:
                dacc[info.idx] = 0.0    # after a later command: no change from here
        else:
            if dacc is None:
                carry[2] = dacc = np.zeros(self._plant.p)
            dacc[info.idx] = dyb
            dres = dyb - C_dx
        if dacc is not None:
            i = slots['_acc']
            new[i] = state[i] + dacc
        M, union = state[slots['_gain_used']]
        if union is not info:           # fused with the rows before it at this stamp
            C_dx = union.C @ dx_prior
        if M is None:
            dx = dx_prior
        elif dacc is None:
            dx = dx_prior - M @ C_dx
        else:
            dx = dx_prior + M @ (dacc[union.idx] - C_dx)
        ip = slots['_x_prior']
        new[ip] = state[ip] + dx_prior
        return (dx,) + self._shifted(state, new, dx, dres) + (None,)

    def _gain(self, key, info):
        """Return M (n x len(info.rows)) for the interval key, or None (no correction)."""
        raise NotImplementedError

    def _verified_design(self, step, rows, design):
        """
        Return ``design(step)``, or None when the gain fails its verification.

        The refusal's message names the step and the outputs; it is kept in
        :attr:`gain_failures` under ``(step.key, rows)``.

        """
        names = [self._plant.output_names[i] for i in rows]
        at = f'{step.k} sample(s)' if step.k is not None else f'h = {step.h:.6g} s'
        try:
            return design(step, f'observer.poles at the sampled step {at} with outputs {names}')
        except DesignVerificationError as err:
            self.gain_failures[(step.key, tuple(rows))] = str(err)
            return None

    def _checked_gain(self, key, info):
        M = self._gain(key, info)
        if M is None:
            reason = self.gain_failures.get((key, info.rows)) or next(
                reversed(self.gain_failures.values()), 'no gain for this step')
            raise DesignVerificationError(reason)
        return M

    def _zpoles(self, step):
        if step.k is None:
            return np.exp(self._poles * step.h)
        return self._poles ** step.k

    def correction_gain(self, dt, rows=None):
        """
        Return the gain M of a correction that comes dt seconds after the previous one.

        Parameters
        ----------
        dt : float
            Time since the previous correction, > 0.
        rows : sequence of int, optional
            Output rows of the correction; default all measured rows.

        Returns
        -------
        M : (n, len(rows)) ndarray
            ``x+ = x- + M (y - D u - C[rows] x-)``.

        """
        info = self._all if rows is None else self._rows_info(tuple(sorted(
            as_rows(rows, 'rows', self._plant))), 'rows')
        return self._checked_gain(self._cache.key(self._as_time(dt)), info).copy()

    def error_matrix(self, dt, rows=None):
        """
        Return the error transition from one correction to the next, dt seconds later.

        Parameters
        ----------
        dt : float
            Time between the corrections, > 0.
        rows : sequence of int, optional
            Output rows of the second correction; default all measured rows.

        Returns
        -------
        F : (n, n) ndarray
            ``e+_{k+1} = F e+_k`` with ``F = (I - M C[rows]) Ad(dt)``; its
            eigenvalues are the z-plane observer poles exp(s dt).

        Raises
        ------
        DesignVerificationError
            The gain of this step fails its verification (also ``correction_gain``).

        """
        info = self._all if rows is None else self._rows_info(tuple(sorted(
            as_rows(rows, 'rows', self._plant))), 'rows')
        step = self._cache.step(self._as_time(dt))
        M = self._checked_gain(step.key, info)
        return (np.eye(self._plant.n) - M @ info.C) @ step.Ad
