# test_core_superposition: late commands added to the history's states by superposition.
"""
Tests of observer_ros.core.estimators.superposition through the History.

A late command is inserted without re-applying the messages after it: the states,
estimates, residuals and S after it must be those the rewind (``superpose = False``,
every message applied again) and the stamp order give, to round-off.
"""

from history_cases import closed_loop, feed, KINDS, make, stamp_order
import numpy as np
from numpy.testing import assert_allclose, assert_array_equal
from observer_ros.core.errors import DimensionError
from observer_ros.core.estimators import (FullOrderEstimator, History, KalmanEstimator,
                                          OpenLoopEstimator, ReducedOrderEstimator)
from observer_ros.core.model import Plant
import pytest

SHIFTED = ['full', 'reduced', 'open_loop', 'kalman']     # 'full_gain' holds y: rewound


def both(estimators):
    """Return two Histories of the same estimator: superposition on, and off."""
    on, off = History(estimators(), length=0.25), History(estimators(), length=0.25)
    off.superpose = False
    return on, off


def close(a, b, what):
    """Assert two arrays (or None) equal to round-off."""
    if a is None or b is None:
        assert a is None and b is None, what
        return
    assert_allclose(a, b, rtol=1e-10, atol=1e-13, err_msg=what)


def same_entries(on, off):
    """Assert the two histories hold the same messages with the same states to round-off."""
    a, b = on._entries, off._entries
    common = min(len(a), len(b))           # the oldest go a checkpoint's worth at a time
    a, b = a[len(a) - common:], b[len(b) - common:]
    assert common > 20 and [(e[0], e[1]) for e in a] == [(e[0], e[1]) for e in b]
    slots = on.estimator._slots
    for ea, eb in zip(a, b):
        if ea[5] is None or eb[5] is None:
            continue
        for name in ('_x', '_u', '_residual', '_x_prior', '_acc', '_P', '_S'):
            if name in slots:
                close(ea[5][slots[name]], eb[5][slots[name]], f'{name} at {ea[0]}')


def run(history, arrival):
    """Feed the messages one by one; return the revised lists of the calls."""
    revised = []
    for m in arrival:
        feed(history, [m])
        revised.append(history.revised)
    return revised


@pytest.mark.parametrize('kind', KINDS)
@pytest.mark.parametrize('lag', [1, 2, 5])
def test_closed_loop_commands_are_superposed_and_match_the_rewind(kind, lag):
    in_stamp_order, arrival = closed_loop(200, seed=lag, lag=lag)
    on, off = both(lambda: make(kind))
    revised_on, revised_off = run(on, arrival), run(off, arrival)
    if kind in SHIFTED:
        # a step late, every command shifts the estimator itself (_superpose_head: no
        # state saved); deeper, every one after the first (a rewind, which turns the
        # dense states on) shifts the states kept after it: nothing is applied again
        rewound = 0 if lag == 1 else 1
        assert on.superposed == on.rewinds - rewound and on.superposed > 150
        assert on.reapplied <= (0 if lag == 1 else lag + 1) and off.reapplied > 150 * lag
        assert (on._dense == 0) == (lag == 1)   # a step late needs no states kept densely
    else:
        assert on.superposed == 0 and on.reapplied == off.reapplied
    close(on.x_hat, off.x_hat, 'x_hat')
    close(on.x_hat, feed(make(kind), in_stamp_order), 'x_hat against the stamp order')
    close(on.estimator.residual, off.estimator.residual, 'residual')
    same_entries(on, off)
    for got, want in zip(revised_on, revised_off):
        assert [r[0] for r in got] == [r[0] for r in want]
        for (_, x1, r1, S1), (_, x2, r2, S2) in zip(got, want):
            close(x1, x2, 'revised x')
            close(r1, r2, 'revised residual')
            close(S1, S2, 'revised S')


def feedthrough_plant():
    """Return a plant with D != 0 and two outputs: u moves y directly (the residual's D u)."""
    A = [[0.0, 1.0], [-2.0, -0.3]]
    B = [[0.0], [1.0]]
    C = [[1.0, 0.0], [0.0, 1.0]]
    D = [[0.0], [0.5]]
    return Plant(A, B, C, D)


def feedthrough(kind):
    """Return an estimator of the plant with D."""
    p = feedthrough_plant()
    if kind == 'full':
        return FullOrderEstimator(p, poles=[-3.0, -3.1], x0=[0.2, 0.0])
    if kind == 'reduced':
        return ReducedOrderEstimator(p, poles=[-4.0], measured_rows=[0], x0=[0.2, 0.0])
    if kind == 'open_loop':
        return OpenLoopEstimator(p, x0=[0.2, 0.0])
    return KalmanEstimator(p, Qd=np.diag([1e-4, 1e-3]), Rd=np.diag([1e-4, 1e-3]),
                           x0=[0.2, 0.0])


def jittered_messages(kind, seed, steps=150):
    """Both sensors (one at each stamp, fused), commands late by 0-6 steps, jittered stamps."""
    rng = np.random.default_rng(seed)
    rows = [(0,)] if kind == 'reduced' else [(0,), (1,)]
    msgs, t = [], 1.0
    for k in range(steps):
        t += 0.01 * (1.0 + 0.2 * rng.uniform(-1.0, 1.0))
        for r in rows:
            if k % 3 or r == (0,):                         # the second sensor at 2/3 of them
                msgs.append((t, t + 1e-4 * r[0], 'y', rng.normal(0.0, 0.05, 1), r))
        late = 0.01 * rng.integers(0, 7) + 2e-4
        msgs.append((t, t + late, 'u', rng.normal(0.0, 0.5, 1), ()))
    return msgs


@pytest.mark.parametrize('kind', SHIFTED)
@pytest.mark.parametrize('seed', [0, 1])
def test_feedthrough_fused_sensors_and_commands_overtaking_each_other(kind, seed):
    msgs = jittered_messages(kind, seed)
    arrival = sorted(msgs, key=lambda m: m[1])
    on, off = both(lambda: feedthrough(kind))
    run(on, arrival)
    run(off, arrival)
    # commands overtake each other (a later one already applied), sensors fuse at a stamp
    assert on.superposed > 50
    close(on.x_hat, off.x_hat, 'x_hat')
    close(on.x_hat, feed(feedthrough(kind), stamp_order(msgs)), 'x_hat, stamp order')
    same_entries(on, off)


def test_the_discrete_plant_is_superposed_too():
    p = Plant([[1.0, 0.01], [-0.02, 0.997]], [[0.0], [0.01]], [[1.0, 0.0]], None, dt=0.01)
    in_stamp_order, arrival = closed_loop(120, lag=3)
    arrival = [(t, a, k, v, (0,) if k == 'y' else r) for t, a, k, v, r in arrival]
    in_stamp_order = [(t, a, k, v, (0,) if k == 'y' else r) for t, a, k, v, r in in_stamp_order]
    on, off = both(lambda: FullOrderEstimator(p, poles=[0.5, 0.6]))
    run(on, arrival)
    run(off, arrival)
    assert on.superposed > 100
    close(on.x_hat, off.x_hat, 'x_hat')
    close(on.x_hat, feed(FullOrderEstimator(p, poles=[0.5, 0.6]), in_stamp_order), 'stamp order')


@pytest.mark.parametrize('bad', [[1.0, 2.0], [float('nan')]])
def test_a_bad_late_command_changes_nothing(bad):
    _, arrival = closed_loop(60, lag=3)
    history = History(make('kalman'), length=0.25)
    feed(history, arrival[:-6])
    assert history.superposed > 0
    head_t = history.t
    before = [(e[0], e[5]) for e in history._entries]
    x, P = history.x_hat, history.estimator.P
    with pytest.raises(DimensionError):
        history.set_input(head_t - 0.02, bad)
    assert [(e[0], e[5]) for e in history._entries] == before
    assert_array_equal(history.x_hat, x)
    assert_array_equal(history.estimator.P, P)
    superposed = history.superposed
    history.set_input(head_t - 0.02, [0.3])
    assert history.superposed == superposed + 1
