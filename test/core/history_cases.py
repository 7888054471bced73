# Messages of the two-sensor submarine and estimators fed with them, for the history's tests.
"""The two-sensor submarine's estimators and messages: (stamp, arrival, kind, value, rows)."""

import numpy as np
from observer_ros.core.estimators import (FullOrderEstimator, KalmanEstimator,
                                          OpenLoopEstimator, ReducedOrderEstimator)
from observer_ros.core.model import zoh_matrices
from plants import GYRO, PITCH, two_sensor_submarine as plant

DT = 0.01


def make(kind):
    """Return an estimator of the two-sensor submarine."""
    p = plant()
    x0 = [0.1, 0.0, 0.0]
    if kind == 'full':
        return FullOrderEstimator(p, poles=[-0.6, -0.61, -0.62], x0=x0)
    if kind == 'full_gain':
        return FullOrderEstimator(p, gain=[[-1.0, 0.5], [0.2, 0.1], [2.0, 0.3]], x0=x0)
    if kind == 'reduced':
        return ReducedOrderEstimator(p, poles=[-0.9], x0=x0)
    if kind == 'open_loop':
        return OpenLoopEstimator(p, x0=x0)
    return KalmanEstimator(p, Qd=np.diag([1e-6, 1e-4, 1e-4]), Rd=np.diag([1e-6, 1e-4]), x0=x0)


def messages(duration=3.0, seed=0):
    """
    Messages of the two-sensor submarine: (stamp, arrival, kind, value, rows).

    Gyro q at 100 Hz arriving 1 ms late, pitch theta at 20 Hz arriving 40 ms late, the
    command at 100 Hz (stamped like the gyro, arriving 2 ms late); noisy measurements
    of the exactly sampled plant.
    """
    rng = np.random.default_rng(seed)
    p = plant()
    x = np.array([0.5, 0.1, 0.0])
    out = []
    dt = 0.01
    Ad, Bd = zoh_matrices(p.A, p.B, dt)
    for k in range(int(round(duration / dt))):
        t = 1.0 + k * dt
        u = np.array([0.05 * np.sin(0.7 * t)])
        y = p.C @ x + rng.normal(0.0, [1e-3, 1e-2])
        out.append((t, t + 0.001, 'y', y[[0]], GYRO))
        if k % 5 == 0:
            out.append((t, t + 0.040, 'y', y[[1]], PITCH))
        out.append((t, t + 0.002, 'u', u, ()))
        x = Ad @ x + Bd @ u
    return out


def stamp_order(msgs):
    """Sort messages by stamp; at one stamp the measurements (gyro, then pitch), then u."""
    return sorted(msgs, key=lambda m: (m[0], m[2] == 'u', m[4]))


def feed(target, msgs):
    """Give the messages to an estimator or a History, in the order of the list."""
    for t, _, kind, value, rows in msgs:
        if kind == 'y':
            target.correct(t, value, rows)
        else:
            target.set_input(t, value)
    return target.x_hat


KINDS = ['full', 'full_gain', 'reduced', 'open_loop', 'kalman']


def closed_loop(steps, seed=0, lag=1):
    """
    Gyro at 100 Hz and the command answering each estimate, as the closed loop sends them.

    The command stamped t_k (computed from the estimate at t_k) arrives after the gyro
    measurement stamped t_{k+lag}. Returns (stamp order, arrival order) of
    ``(stamp, arrival, kind, value, rows)``.
    """
    rng = np.random.default_rng(seed)
    msgs = []
    for k in range(steps):
        t = 1.0 + k * DT
        msgs.append((t, t, 'y', rng.normal(0.0, 1e-2, 1), GYRO))
        msgs.append((t, t + (lag + 0.5) * DT, 'u', rng.normal(0.0, 0.1, 1), ()))
    return stamp_order(msgs), sorted(msgs, key=lambda m: m[1])
