# test_core_history: late and out-of-order messages through the estimators' history.
"""Tests of observer_ros.core.estimators.history: any arrival order gives the stamp order."""

from pathlib import Path

from history_cases import feed, GYRO, KINDS, make, messages, PITCH, stamp_order
import numpy as np
from numpy.testing import assert_allclose, assert_array_equal
from observer_ros.core.errors import DimensionError, VehicleFileError
from observer_ros.core.estimators import CHECKPOINT_EVERY, History, TimeOrderError
from observer_ros.vehicle import load_vehicle
import pytest


@pytest.mark.parametrize('kind', KINDS)
def test_arrival_order_gives_the_stamp_order_estimate(kind):
    msgs = messages()
    reference = feed(make(kind), stamp_order(msgs))
    arrival = sorted(msgs, key=lambda m: m[1])
    assert arrival != stamp_order(msgs)
    history = History(make(kind), length=0.1)
    got = feed(history, arrival)
    assert_allclose(got, reference, rtol=0.0, atol=1e-9)
    assert history.t == max(m[0] for m in msgs)
    assert history.rewinds > 0


@pytest.mark.parametrize('kind', KINDS)
@pytest.mark.parametrize('seed', [1, 2, 3])
def test_any_order_within_the_history_gives_the_same_estimate(kind, seed):
    # Random delays up to 0.2 s: every message is inside a 0.25 s history when it arrives.
    msgs = messages(duration=2.0)
    rng = np.random.default_rng(seed)
    shuffled = sorted(msgs, key=lambda m: m[0] + rng.uniform(0.0, 0.2))
    reference = feed(make(kind), stamp_order(msgs))
    history = History(make(kind), length=0.25)
    assert_allclose(feed(history, shuffled), reference, rtol=0.0, atol=1e-9)


def test_stamp_order_through_the_history_is_bit_for_bit_the_estimator():
    msgs = stamp_order(messages())
    history = History(make('kalman'))
    assert_array_equal(feed(history, msgs), feed(make('kalman'), msgs))
    assert history.rewinds == 0


def test_a_late_command_applies_from_its_stamp():
    msgs = messages(duration=1.0)
    # every command arrives 30 ms late (after the next measurements)
    late = sorted(msgs, key=lambda m: m[0] + (0.03 if m[2] == 'u' else 0.0))
    reference = feed(make('full'), stamp_order(msgs))
    assert_allclose(feed(History(make('full'), length=0.1), late), reference, atol=1e-12)
    # without a history the same commands are held from the estimate's time: different
    est = make('full')
    for t, _, kind, value, rows in late:
        if kind == 'y':
            est.correct(t, value, rows)
        else:
            est.set_input(max(t, est.t if est.t is not None else t), value)
    assert np.max(np.abs(est.x_hat - reference)) > 1e-6


def test_older_than_the_history_is_refused_and_a_late_command_held_from_now():
    history = History(make('full'), length=0.1)
    history.correct(1.0, [0.0], GYRO)
    history.correct(1.2, [0.0], GYRO)
    assert not history.accepts(1.09)
    assert history.accepts(1.1) and history.accepts(1.15)
    x = history.x_hat
    with pytest.raises(TimeOrderError, match='older than the history'):
        history.correct(1.05, [1.0], PITCH)
    assert_array_equal(history.x_hat, x)
    assert history.set_input(0.5, [1.0]) is True            # held from 1.2 on
    assert_array_equal(history.estimator.u, [1.0])
    assert history.t == 1.2


def test_several_sensors_at_one_stamp_are_all_used_in_either_order():
    results = []
    for order in ((GYRO, PITCH), (PITCH, GYRO)):
        history = History(make('full'))
        history.correct(1.0, [0.0], GYRO)
        history.correct(1.0, [0.0], PITCH)
        values = {GYRO: [0.01], PITCH: [0.3]}
        for rows in order:
            history.correct(1.05, values[rows], rows)
        results.append(history.x_hat)
    fused = make('full')
    fused.correct(1.0, [0.0, 0.0], (0, 1))
    fused.correct(1.05, [0.01, 0.3], (0, 1))
    assert_allclose(results[0], fused.x_hat, atol=1e-12)
    assert_allclose(results[1], fused.x_hat, atol=1e-12)


def test_a_message_never_costs_more_than_one_rewind():
    msgs = messages(duration=2.0)
    history = History(make('kalman'), length=0.25)
    rng = np.random.default_rng(4)
    for m in sorted(msgs, key=lambda m: m[0] + rng.uniform(0.0, 0.2)):
        before_rewinds, before_reapplied, kept = history.rewinds, history.reapplied, len(history)
        feed(history, [m])
        assert history.rewinds - before_rewinds <= 1
        assert history.reapplied - before_reapplied <= kept
    # bounded: the last 0.25 s (220 messages a second), and at most CHECKPOINT_EVERY
    # before them (the base of a rewind is a checkpoint)
    assert len(history) <= 0.25 * 220 + CHECKPOINT_EVERY + 1


def test_history_is_bounded_by_the_number_of_messages():
    history = History(make('full'), length=10.0, max_messages=50)
    for k in range(200):
        history.correct(1.0 + 0.001 * k, [0.0], GYRO)
    assert 50 - CHECKPOINT_EVERY <= len(history) <= 50
    assert not history.accepts(1.0 + 0.001 * 149)      # dropped, though within 10 s
    oldest = 200 - len(history)
    assert history.accepts(1.0 + 0.001 * oldest)
    assert not history.accepts(1.0 + 0.001 * (oldest - 1))


@pytest.mark.parametrize('kind', KINDS)
def test_a_stream_arriving_twice_drops_its_old_entries_without_comparing_arrays(kind):
    """
    Every message twice, equal stamps and values (two publishers answering one stream).

    The entries of one stamp are then equal up to their saved states (arrays): the old
    entries are dropped by finding a checkpoint by identity, never by equality, which
    raised "The truth value of an array with more than one element is ambiguous".
    """
    history = History(make(kind), length=0.05)
    msgs = stamp_order(messages(duration=1.0))
    stamps = sorted({m[0] for m in msgs})
    for t in stamps:        # each stamp's measurements and command, then the same again
        group = [m for m in msgs if m[0] == t]
        feed(history, group + group)
    assert history.t == msgs[-1][0]
    assert len(history) <= 2 * 3 * (0.05 / 0.01 + 1 + CHECKPOINT_EVERY)   # bounded
    assert np.all(np.isfinite(history.x_hat))


def test_a_bad_late_message_leaves_the_history_as_it_was():
    history = History(make('kalman'), length=0.5)
    msgs = stamp_order(messages(duration=0.3))
    feed(history, msgs)
    x, P = history.x_hat, history.estimator.P
    with pytest.raises(DimensionError):
        history.correct(1.1, [np.nan], GYRO)
    assert_array_equal(history.x_hat, x)
    assert_array_equal(history.estimator.P, P)
    assert history.rewinds == 0


def test_predict_leaves_the_history_unchanged():
    msgs = stamp_order(messages(duration=0.5))
    history = History(make('kalman'))
    feed(history, msgs)
    x, t = history.x_hat, history.t
    pred = history.predict(t + 0.5)
    assert np.max(np.abs(pred - x)) > 0.0
    assert history.t == t
    assert_array_equal(history.x_hat, x)


def test_revised_estimates_are_reported_with_their_tags():
    history = History(make('full'), length=0.1)
    history.correct(1.00, [0.0], GYRO, tag='a')
    history.correct(1.01, [0.001], GYRO, tag='b')
    history.correct(1.02, [0.002], GYRO, tag='c')
    assert history.revised == []
    history.correct(1.005, [0.2], PITCH, tag='late')
    assert [tag for tag, _, _, _ in history.revised] == ['b', 'c']
    assert_array_equal(history.revised[-1][1], history.x_hat)
    assert history.head_tag == 'c'


def test_history_length_is_checked():
    with pytest.raises(ValueError, match='history length'):
        History(make('full'), length=-1.0)


def test_vehicle_keys_of_the_history_and_the_publish_rate():
    config = Path(__file__).resolve().parents[2] / 'config'
    v = load_vehicle(config / 'submarine.yaml')
    assert v.observer.history_length == 0.25 and v.observer.publish_rate_hz is None
    v = load_vehicle(config / 'submarine.yaml', overrides=[
        'observer.history_length:=0.5', 'observer.publish_rate_hz:=10.0'])
    assert v.observer.history_length == 0.5 and v.observer.publish_rate_hz == 10.0
    with pytest.raises(VehicleFileError, match='observer.history_length'):
        load_vehicle(config / 'submarine.yaml', overrides=['observer.history_length:=-0.1'])
    with pytest.raises(VehicleFileError, match='observer.publish_rate_hz'):
        load_vehicle(config / 'submarine.yaml', overrides=['observer.publish_rate_hz:=0.0'])


def test_two_alike_commands_held_at_one_stamp_do_not_stop_the_history():
    """Two untagged commands of one value at one stamp, both with a saved state, dropped."""
    h = History(make('full'), 0.23)
    for k in range(10):
        h.correct(10.0 + 0.05 * k, [0.01], GYRO)
    h.correct(h.t - 0.02, [0.1], PITCH)         # late: the states kept densely from here
    head = h.t
    h.set_input(head, [0.1])
    h.set_input(head, [0.1])
    for k in range(1, 20):
        h.correct(head + 0.05 * k, [0.01], GYRO)
    assert h.t == head + 0.05 * 19 and len(h) < 10
