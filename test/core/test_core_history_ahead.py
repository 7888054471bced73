# test_core_history_ahead: commands stamped ahead of the estimate, held pending.
"""Tests of the history's pending commands: the cart's delay compensation stamps them ahead."""

from history_cases import feed, GYRO, KINDS, make, messages, PITCH, stamp_order
import numpy as np
from numpy.testing import assert_allclose, assert_array_equal
from observer_ros.core.errors import DimensionError
from observer_ros.core.estimators import History
import pytest

DT = 0.01
AHEAD = 3           # controller.delay_compensation: commands stamped 3 steps ahead


def cart_like(duration=2.0, late_pitch=0.0):
    """
    Messages whose commands are stamped AHEAD steps after the measurement they answer.

    Each command arrives 2 ms after the gyro of its step (which arrives 1 ms after its
    stamp); the pitch arrives ``late_pitch`` s after its stamp (0: just after the gyro).
    Returns (messages, arrival order).
    """
    msgs = []
    for t, arrival, kind, value, rows in messages(duration):
        if kind == 'u':
            t = 1.0 + (round((t - 1.0) / DT) + AHEAD) * DT     # a measurement's stamp
        elif rows != GYRO:
            arrival = t + (late_pitch or 0.0011)
        msgs.append((t, arrival, kind, value, rows))
    return msgs, sorted(msgs, key=lambda m: m[1])


def estimates_in_stamp_order(kind, msgs):
    """Return the estimator fed in stamp order, and its estimate after each measurement."""
    est = make(kind)
    after = {}
    for t, _, what, value, rows in stamp_order(msgs):
        if what == 'y':
            after[(t, rows)] = est.correct(t, value, rows)
        else:
            est.set_input(t, value)
    return est, after


@pytest.mark.parametrize('kind', KINDS)
def test_commands_stamped_ahead_make_no_measurement_late(kind):
    msgs, arrival = cart_like()
    reference, after = estimates_in_stamp_order(kind, msgs)
    history = History(make(kind), length=0.25)
    late = 0
    for t, _, what, value, rows in arrival:
        if what == 'y':
            late += history.t is not None and t < history.t
            history.correct(t, value, rows)
            assert_allclose(history.x_at_stamp, after[(t, rows)], rtol=0.0, atol=1e-9)
            assert history.t == t           # a command ahead does not move the estimate
        else:
            assert history.set_input(t, value) is False
    assert late == 0 and history.rewinds == 0 and history.reapplied == 0
    # the commands at and after the last measurement's stamp are held; a prediction
    # uses them
    assert history.pending == AHEAD + 1
    assert_allclose(history.predict(reference.t), reference.x_hat, rtol=0.0, atol=1e-9)
    assert history.pending == AHEAD + 1


@pytest.mark.parametrize('kind', KINDS)
def test_a_late_sensor_with_commands_ahead_gives_the_stamp_order_estimate(kind):
    msgs, arrival = cart_like(late_pitch=0.04)
    reference, after = estimates_in_stamp_order(kind, msgs)
    history = History(make(kind), length=0.1)
    for t, _, what, value, rows in arrival:
        if what == 'y':
            history.correct(t, value, rows)
            if rows != GYRO:    # when a pitch comes, everything stamped before it has come
                assert_allclose(history.x_at_stamp, after[(t, rows)], rtol=0.0, atol=1e-9)
        else:
            history.set_input(t, value)
    assert history.rewinds == sum(1 for m in msgs if m[2] == 'y' and m[4] != GYRO)
    assert_allclose(history.predict(reference.t), reference.x_hat, rtol=0.0, atol=1e-9)


def test_stamp_order_and_commands_ahead_give_the_same_bits():
    # the pending commands are applied by the same calls as the stamp order makes
    msgs, arrival = cart_like(duration=1.0)
    last_y = max(m[0] for m in msgs if m[2] == 'y')
    history = History(make('kalman'))
    feed(history, arrival)
    est = make('kalman')
    feed(est, [m for m in stamp_order(msgs) if m[0] <= last_y])
    assert history.t == est.t == last_y
    assert_array_equal(history.x_hat, est.x_hat)
    assert_array_equal(history.estimator.P, est.P)


def test_a_bad_measurement_after_pending_commands_changes_nothing():
    history = History(make('full'))
    history.correct(1.0, [0.0], GYRO)
    history.set_input(1.02, [0.5])
    x, held = history.x_hat, history.estimator.u
    with pytest.raises(DimensionError):
        history.correct(1.03, [np.nan], GYRO)
    assert history.pending == 1 and history.t == 1.0
    assert_array_equal(history.x_hat, x)
    assert_array_equal(history.estimator.u, held)
    with pytest.raises(DimensionError):
        history.set_input(1.04, [np.inf])         # refused when it comes, not held
    assert history.pending == 1
    history.correct(1.03, [0.01], GYRO)
    assert history.pending == 0 and history.t == 1.03
    assert_array_equal(history.estimator.u, [0.5])


def test_pending_commands_at_one_stamp_keep_their_arrival_order_and_a_reset_drops_them():
    history = History(make('full'))
    history.correct(1.0, [0.0], GYRO)
    for u in ([0.1], [0.2], [0.3]):
        history.set_input(1.02, u)
    history.set_input(1.01, [0.4])
    history.correct(1.015, [0.0], GYRO)          # after 1.01: [0.4] held
    assert_array_equal(history.estimator.u, [0.4])
    assert history.pending == 3
    history.correct(1.02, [0.0], GYRO)           # at 1.02: measured before the three
    assert_array_equal(history.estimator.u, [0.4])
    assert history.pending == 3 and history.rewinds == 0
    history.set_input(1.02, [0.6])               # after the three
    history.correct(1.02, [0.0], PITCH)          # before them: in order too
    assert history.rewinds == 0
    history.correct(1.03, [0.0], GYRO)
    assert_array_equal(history.estimator.u, [0.6])
    assert history.pending == 0
    history.set_input(1.05, [0.9])
    history.reset()
    assert history.pending == 0 and len(history) == 0
