# test_clock_follower: where a follower simulator's steps fall on /clock (no ROS).
"""Tests of observer_ros.nodes.clock_follower.ClockFollower."""

from observer_ros.nodes.clock_follower import CLOCK_CATCH_UP, ClockFollower
from pytest import approx


def test_waits_for_the_first_clock_then_runs_on_its_own_time():
    f = ClockFollower(0.01, first_wait=20.0)
    assert f.start(0, waited=5.0) is False
    assert f.steps_due(1.0, 0) == (1, None)         # not placed: its own pace
    assert f.start(0, waited=21.0) is None and f.synced
    assert f.steps_due(1.0, 0) == (1, None)         # no /clock: its own pace


def test_starts_at_clock_and_steps_only_as_far_as_it():
    f = ClockFollower(0.01, first_wait=20.0)
    f.heard(12, 500_000_000)
    assert f.start(0, waited=0.1) == approx(12.5, abs=1e-12)
    assert f.steps_due(12.5, 0) == (0, None)        # /clock still at step 0: wait
    f.heard(12, 550_000_000)                        # the owner's 20 Hz step
    assert f.steps_due(12.5, 0) == (5, None)
    assert f.steps_due(12.54, 4) == (1, None)
    assert f.steps_due(12.55, 5) == (0, None)
    assert f.t0_at(5) == approx(12.5, abs=1e-12)


def test_a_clock_gone_back_or_far_ahead_restarts_the_time_base_there():
    f = ClockFollower(0.05, first_wait=20.0)
    f.heard(30, 0)
    assert f.start(100, waited=0.0) == approx(25.0, abs=1e-12)
    f.heard(29, 600_000_000)                        # 0.4 s back: jitter of its owner
    assert f.steps_due(30.0, 100) == (0, None)
    for _ in range(3):                              # the owner restarted at 1 s: its
        f.heard(1, 0)                               # step 0 again, three in a row agree
    due, t0 = f.steps_due(30.0, 100)
    assert due == 1 and t0 + 101 * 0.05 == approx(1.0, abs=1e-12)   # the next at /clock
    f.heard(1 + int(CLOCK_CATCH_UP) + 5, 0)          # far ahead of the step at 1 s
    due, t0 = f.steps_due(1.0, 101)
    assert due == 1 and t0 + 102 * 0.05 == approx(6.0 + CLOCK_CATCH_UP, abs=1e-9)


def test_a_single_clock_far_back_is_skipped_the_agreed_one_restarts():
    counts = {}
    f = ClockFollower(0.05, first_wait=20.0,
                      count=lambda key: counts.__setitem__(key, counts.get(key, 0) + 1))
    f.heard(30, 0)
    f.start(100, waited=0.0)
    assert f.heard(2, 0) is False                   # one wild /clock: the time base stays
    assert f.clock == approx(30.0) and f.steps_due(30.0, 100) == (0, None)
    f.heard(30, 50_000_000)                         # the owner goes on: the streak is broken
    assert f.heard(1, 0) is False and f.heard(1, 50_000_000) is False
    assert f.heard(1, 100_000_000) is True          # the third in a row: the owner restarted
    due, t0 = f.steps_due(30.05, 101)
    assert due == 1 and t0 + 102 * 0.05 == approx(1.1, abs=1e-12)
    assert counts == {'far_back_stamps': 3, 'clock_jumps': 1}
