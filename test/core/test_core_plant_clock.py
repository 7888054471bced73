# test_core_plant_clock: the plant's time from the wall clock, when measurements queue up.
"""Tests of observer_ros.core.plant_clock."""

import random

from observer_ros.core import plant_clock
from observer_ros.core.plant_clock import PlantClock
import pytest


def test_measurements_taken_as_they_come_give_their_stamps():
    clock = PlantClock(rate=1.0)
    assert clock.at(5.0) is None and clock.behind(1.0, 5.0) == 0.0
    for k in range(50):
        clock.seen(1.0 + 0.01 * k, 100.0 + 0.01 * k + 0.001 * (k % 3))    # 0-2 ms late
    assert clock.at(100.49) == pytest.approx(1.49)
    assert clock.behind(1.49, 100.49) == pytest.approx(0.0)


def test_a_stall_is_the_time_the_queued_measurements_waited():
    clock = PlantClock(rate=1.0)
    for k in range(20):
        clock.seen(1.0 + 0.01 * k, 100.0 + 0.01 * k)
    # 80 ms without running, then the queue taken at once: the plant is at 1.27
    for k in range(20, 28):
        clock.seen(1.0 + 0.01 * k, 100.27)
        assert clock.behind(1.0 + 0.01 * k, 100.27) == pytest.approx(0.27 - 0.01 * k)
    assert clock.at(100.3) == pytest.approx(1.30)


def test_the_rate_scales_wall_time_to_plant_time():
    clock = PlantClock(rate=4.0)
    for k in range(10):
        clock.seen(1.0 + 0.01 * k, 100.0 + 0.0025 * k)
    assert clock.at(100.1) == pytest.approx(1.4)      # 0.1 s of wall is 0.4 s of plant


def test_an_offset_is_forgotten_after_the_window():
    """A plant that fell behind the wall clock (a paused simulator) is believed again."""
    clock = PlantClock(rate=1.0, window=0.5)
    clock.seen(1.0, 100.0)
    for k in range(1, 22):                   # the plant paused 0.3 s, then stepped on
        clock.seen(1.0 + 0.01 * k, 100.3 + 0.01 * k)
        late = 0.3 if 100.3 + 0.01 * k <= 100.5 + 1e-9 else 0.0   # the window: 0.5 s
        assert clock.behind(1.0 + 0.01 * k, 100.3 + 0.01 * k) == pytest.approx(late), k
    clock.reset()
    assert clock.at(100.6) is None


def _plant(clock, rate, until, spread=0.0, t=1.0, now=100.0, late=0.001, seed=0):
    """
    Feed ``clock`` a plant stepping 0.01 s at ``rate`` of the wall clock until wall ``until``.

    Each step comes ``spread`` of its mean wall time early or late at random (a timer on a
    busy host), each measurement taken ``late`` s after its step. Returns (t, now) of the
    last measurement, and the wall time of the step after it.
    """
    rng = random.Random(seed)
    while True:
        clock.seen(t, now + late)
        step = now + 0.01 / rate * (1.0 + spread * rng.uniform(-1.0, 1.0))
        if step >= until:
            return t, now + late, step
        t, now = t + 0.01, step


def test_a_plant_slower_than_the_wall_clock_is_measured():
    """A simulator skipping ticks: its rate measured, its measurements on time again."""
    clock = PlantClock(rate=1.0, window=0.5)
    t, now, step = _plant(clock, 0.4, 102.0)
    assert clock.rate == pytest.approx(0.4)
    assert clock.behind(t, now) == pytest.approx(0.0, abs=1e-9)
    # the next step's measurement taken 80 ms late (this process did not run): the plant
    # went on at its rate meanwhile
    clock.seen(t + 0.01, step + 0.08)
    assert clock.behind(t + 0.01, step + 0.08) == pytest.approx(0.4 * 0.079)
    clock.reset()
    assert clock.rate == 1.0 and clock.at(now) is None


@pytest.mark.parametrize('seed', range(5))
def test_a_plant_stepping_irregularly_is_taken_for_no_more_than_a_few_steps_ahead(seed):
    """Steps 10 to 48 ms of wall time apart: a few steps ahead, not the window's 0.3 s."""
    clock = PlantClock(rate=1.0, window=0.5)
    t, now, _ = _plant(clock, 0.4, 103.0, spread=0.9, seed=seed)
    assert 0.35 < clock.rate < 0.6, clock.rate
    assert clock.behind(t, now) < 0.08, clock.behind(t, now)


def test_the_rate_is_at_most_the_nominal_rate_and_at_least_a_hundredth_of_it():
    clock = PlantClock(rate=1.0)
    t, now, _ = _plant(clock, 2.0, 102.0)
    assert clock.rate == 1.0
    assert clock.behind(t, now) == pytest.approx(0.0, abs=1e-9)
    for k in range(200):            # the plant stands: its stamp repeats
        clock.seen(t, now + 0.01 * k)
    assert clock.rate == pytest.approx(0.01)
    assert clock.behind(t, now + 2.0) < 0.01


def test_one_window_of_measurements_all_taken_late_does_not_slow_the_rate():
    clock = PlantClock(rate=1.0, window=0.5)
    t, _, step = _plant(clock, 1.0, 101.0)
    t, _, step = _plant(clock, 1.0, 101.6, t=t + 0.01, now=step, late=0.1)
    assert clock.rate == pytest.approx(1.0)
    t, now, _ = _plant(clock, 1.0, 102.6, t=t + 0.01, now=step)
    assert clock.rate == pytest.approx(1.0)
    assert clock.behind(t, now) == pytest.approx(0.0, abs=1e-9)


def test_the_longest_wait_of_a_measurement_is_kept_two_seconds():
    clock = PlantClock(rate=1.0)
    assert clock.waited(100.0) == 0.0 and clock.extra_steps(100.0, 0.01) == 0
    t, _, step = _plant(clock, 1.0, 101.0, late=0.0)
    assert clock.waited(step) == pytest.approx(0.0, abs=1e-9)
    # the next measurement taken 40 ms late: the plant is 40 ms past it
    clock.seen(t + 0.01, step + 0.04)
    assert clock.waited(step + 0.04) == pytest.approx(0.04)
    assert clock.extra_steps(step + 0.04, 0.01) == 4
    t, _, last = _plant(clock, 1.0, step + 1.9, t=t + 0.02, now=step + 0.01, late=0.0)
    assert clock.waited(last) == pytest.approx(0.04)
    assert clock.waited(step + 2.05) == pytest.approx(0.0, abs=1e-9)    # 2 s later
    # a wait longer than LEAD_MOST adds LEAD_MOST to the lead
    clock.seen(t + 0.01, last + 0.3)
    assert clock.extra_steps(last + 0.3, 0.01) == round(plant_clock.LEAD_MOST / 0.01)
    clock.reset()
    assert clock.waited(step) == 0.0


@pytest.mark.parametrize('rate, window', [(0.0, 0.5), (1.0, 0.0), (-1.0, 1.0)])
def test_a_bad_rate_or_window_is_refused_by_name(rate, window):
    with pytest.raises(ValueError, match='rate|window'):
        PlantClock(rate, window)
