# test_core_history_one_back: a message stamped just before the newest entry (closed loop).
"""
Tests of the history's one-step-late messages: one entry re-applied, the stamp order.

Late commands here go through the rewind (``History.superpose = False``, as for the
observers given a gain); test_core_superposition.py tests the default for the others.
"""

from history_cases import (closed_loop, DT, feed, GYRO, KINDS, make, messages, PITCH,
                           stamp_order)
import numpy as np
from numpy.testing import assert_array_equal
from observer_ros.core.errors import DimensionError
from observer_ros.core.estimators import CHECKPOINT_EVERY, DENSE_DEPTH, DENSE_FOR, History
import pytest


def checkpoints_listed(history):
    """Tell whether the history's deque of checkpoints is its entries with a state."""
    entries = history._entries
    return list(history._checkpoints) == [e for e in entries if e[5] is not None]


def rewinding(estimator):
    """Return a History that re-applies the messages after a late command (no superposition)."""
    history = History(estimator, length=0.25)
    history.superpose = False
    return history


@pytest.mark.parametrize('kind', KINDS)
def test_a_command_one_step_late_reapplies_one_message_and_gives_the_stamp_order(kind):
    in_stamp_order, arrival = closed_loop(300)
    history = rewinding(make(kind))
    reference = make(kind)
    late_commands = 0
    for m in arrival:
        before_rewinds, before_reapplied = history.rewinds, history.reapplied
        feed(history, [m])
        if m[2] == 'u' and history.rewinds > before_rewinds:
            late_commands += 1
            if late_commands > 1:           # the first one turns on the state kept
                assert history.reapplied - before_reapplied == 1
    assert late_commands == 300 - 1          # the last command is in order
    # the same calls on the same states: the stamp order to the last bit
    assert_array_equal(history.x_hat, feed(reference, in_stamp_order))
    assert checkpoints_listed(history)


@pytest.mark.parametrize('kind', KINDS)
def test_a_measurement_one_step_late_reapplies_one_message(kind):
    history = History(make(kind), length=0.25)
    reference = make(kind)
    rng = np.random.default_rng(1)
    msgs = []
    for k in range(100):
        t = 1.0 + k * DT
        msgs.append((t, t, 'y', rng.normal(0.0, 1e-2, 1), GYRO))
        if k % 2:                             # pitch arrives after the next gyro
            msgs.append((t, t + 1.5 * DT, 'y', rng.normal(0.0, 1e-2, 1), PITCH))
    arrival = sorted(msgs, key=lambda m: m[1])
    counts, revised = [], []
    for m in arrival:
        before = history.reapplied
        feed(history, [m])
        counts.append(history.reapplied - before)
        revised.append(len(history.revised))
    late = [(c, r) for m, c, r in zip(arrival, counts, revised) if m[4] == PITCH]
    # one re-applied, the gyro after it (revised); the last pitch arrives in order
    assert late[1:-1] == [(1, 1)] * (len(late) - 2)
    assert late[-1] == (0, 0)
    assert_array_equal(history.x_hat, feed(reference, stamp_order(msgs)))


def test_a_bad_command_one_step_late_leaves_the_history_as_it_was():
    _, arrival = closed_loop(50)
    history = rewinding(make('kalman'))
    feed(history, arrival[:-2])              # ends with a gyro, the command before it due
    head_t = history.t
    x, P = history.x_hat, history.estimator.P
    with pytest.raises(DimensionError):
        history.set_input(head_t - DT, [1.0, 2.0])
    assert_array_equal(history.x_hat, x)
    assert_array_equal(history.estimator.P, P)
    # the state kept survives: the good command after it is still one re-application
    before = history.reapplied
    history.set_input(head_t - DT, [0.3])
    assert history.reapplied - before == 1


@pytest.mark.parametrize('kind', ['full', 'reduced', 'kalman'])
@pytest.mark.parametrize('lag', [2, 5])
def test_commands_a_few_steps_late_reapply_only_the_entries_after_them(kind, lag):
    in_stamp_order, arrival = closed_loop(200, seed=lag, lag=lag)
    history = rewinding(make(kind))
    deltas = []
    for m in arrival:
        before = history.reapplied
        feed(history, [m])
        if m[2] == 'u':
            deltas.append(history.reapplied - before)
    # once the dense checkpoints are on: the lag's measurements (and the commands
    # between them), not those since a regular checkpoint as well
    steady = deltas[CHECKPOINT_EVERY:-lag]
    assert set(steady) == {lag}, steady
    assert_array_equal(history.x_hat, feed(make(kind), in_stamp_order))
    assert checkpoints_listed(history)


def test_dense_checkpoints_only_after_a_shallow_rewind_and_for_a_while():
    history = History(make('full'), length=0.25)
    msgs = stamp_order(messages(duration=1.0))
    feed(history, msgs)
    states = sum(e[5] is not None for e in history._entries)
    assert history._dense == 0 and states <= len(history) // CHECKPOINT_EVERY + 1
    # a deep rewind (more than DENSE_DEPTH entries back) keeps the regular checkpoints
    t = history.t
    history.set_input(t - 0.2, [0.1])                   # about 44 entries back
    assert DENSE_DEPTH < 40
    assert history._dense == 0
    # a shallow one: the next DENSE_FOR measurements are all checkpoints, then no more
    history.set_input(t - 0.5 * DT, [0.2])
    for k in range(DENSE_FOR + CHECKPOINT_EVERY):        # 1 kHz: all inside the window
        history.correct(t + (k + 1) * 0.001, [0.0], GYRO)
    states = [e[5] is not None for e in history._entries[-(DENSE_FOR + CHECKPOINT_EVERY):]]
    assert all(states[:DENSE_FOR]) and not all(states[DENSE_FOR:])
    assert history._dense == 0


@pytest.mark.parametrize('kind', ['full', 'kalman'])
def test_checkpoints_stay_listed_through_rewinds_of_any_depth(kind):
    msgs = messages(duration=2.0)
    rng = np.random.default_rng(7)
    history = History(make(kind), length=0.25)
    for m in sorted(msgs, key=lambda m: m[0] + rng.uniform(0.0, 0.2)):
        feed(history, [m])
        assert checkpoints_listed(history)
