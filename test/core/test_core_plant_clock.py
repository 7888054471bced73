# test_core_plant_clock: the plant's time from the wall clock, when measurements queue up.
"""Tests of observer_ros.core.plant_clock."""

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


@pytest.mark.parametrize('rate, window', [(0.0, 0.5), (1.0, 0.0), (-1.0, 1.0)])
def test_a_bad_rate_or_window_is_refused_by_name(rate, window):
    with pytest.raises(ValueError, match='rate|window'):
        PlantClock(rate, window)
