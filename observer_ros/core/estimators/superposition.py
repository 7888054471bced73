# observer_ros.core.estimators.superposition: a late input change added to saved states.
"""
The states after a late command, from those saved before it came: by superposition.

A command stamped before messages already applied changes the input held from its stamp
on. Every estimator with a correction gain that does not depend on the input (the
observers given poles, the Kalman filter: its covariance and gain do not depend on u, the
model alone) is linear in its estimate, the input and the measurements, so the states
after the command are those saved before it came plus the response to the input change
``du = u_new - u_old`` alone: propagated from the command's stamp with zero estimate and
measurements, through the same steps and the same gains. That is a few products of small
matrices per message, instead of the message's correction made again (the history's
rewind), and the result is the same to round-off (not to the last bit: the propagation
over a step split at the command's stamp is ``Ad(b) Ad(a)`` instead of ``Ad(a + b)``).

The closed loop sends such a command every step: the command answering the estimate at
t_k is stamped t_k and arrives after the measurements of the next few steps
(benchmarks/README.md).

An estimator kind that can be shifted sets ``_superposable``, gives
``_shift_correction`` and names in ``_MOVED`` the parts of its state besides x and
u that the input moves (a later command's state keeps them from the measurement before
it). The others (the observers given a gain, which hold the measured outputs between
samples) are rewound as before.

"""

import numpy as np

__all__ = ['shifted_states']


def shifted_states(est, t, u_new, du, later):
    """
    Return the states after a command stamped t, from those saved without it.

    Parameters
    ----------
    est : Estimator
        An estimator with ``_superposable`` set.
    t : float
        The command's stamp; every entry of ``later`` is stamped after it.
    u_new : ndarray
        The command's input (checked).
    du : ndarray
        ``u_new`` minus the input held at t before the command came.
    later : list of (float, tuple or None, tuple)
        The messages after the command, in the order applied: stamp, output rows (None
        for a command) and the state saved after the message (:meth:`Estimator.save_state`).

    Returns
    -------
    shifted : list of (tuple, ndarray or None, ndarray or None, ndarray or None)
        Per message: its state with the command, and for a measurement the estimate at
        its stamp, the residual and S (None but for a Kalman filter) with it.

    """
    slots = est._slots
    ix, iu = slots['_x'], slots['_u']
    moving = [i for i, _ in est._moved]
    cache = est._cache
    shift = est._shift_correction
    rows_info = est._rows_info
    infos = {}
    dyb_zero = est._D_zero
    dx = None                       # zero until the first step after the command
    active = True                   # the input change holds until a later command
    t_prev, dt_prev, step = t, None, None
    carry = [None, None, None]      # what a fused correction at one stamp shares
    moved = ()                      # the last measurement's shifted parts besides x and u
    out = []
    for t_e, rows, state in later:
        if t_e > t_prev:
            dt = t_e - t_prev
            if dt != dt_prev:
                step, dt_prev = cache.step(dt), dt
            if dx is None:
                dx = step.Bd @ du
            else:
                dx = step.Ad @ dx + step.Bd @ du if active else step.Ad @ dx
            t_prev = t_e
        elif dx is None:            # not after the command's stamp: cannot happen (sorted)
            dx = np.zeros(est._plant.n)
        new = list(state)
        if rows is None:                            # a later command: its own input
            active = False
            new[ix] = state[ix] + dx
            for i, value in moved:                  # a command keeps the residual...
                new[i] = value
            out.append((tuple(new), None, None, None))
            continue
        info = infos.get(rows)
        if info is None:
            info = infos[rows] = rows_info(rows, 'rows')
        dyb = None if dyb_zero or not active else -(info.D @ du)
        dx, x, residual, S = shift(state, new, dx, dyb, info, t_e, carry)
        moved = [(i, new[i]) for i in moving]
        if active:
            new[iu] = u_new
        out.append((tuple(new), x, residual, S))
    return out
