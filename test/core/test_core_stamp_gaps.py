# Messages missed, read from a sensor's stamps: jitter is none, a lost message is one.
"""core.stamp_gaps.MissedStamps: which gaps between stamps are missed messages."""

import random

from observer_ros.core.stamp_gaps import MissedStamps, PAUSE_PERIODS
import pytest


def _missed(stamps, period=0.05):
    """Return the messages missed over ``stamps`` (each newer than the one before)."""
    gaps = MissedStamps(period)
    return sum(gaps.gap(b - a) for a, b in zip(stamps, stamps[1:]))


def test_a_lost_message_is_counted_once_the_next_one_comes():
    gaps = MissedStamps(0.05)
    assert gaps.gap(0.05) == 0
    assert gaps.gap(0.10) == 0          # one message lost: owed, not yet counted
    assert gaps.owed == pytest.approx(1.0)
    assert gaps.gap(0.05) == 1          # the next one on time: it stays lost
    assert gaps.owed == pytest.approx(0.0)
    assert gaps.gap(0.30) == 0 and gaps.gap(0.05) == 5     # five at once


def test_a_late_message_then_an_early_one_is_no_message_missed():
    # a publisher starved of CPU: one message 1.2 periods late, the next at once (it
    # catches up) or on its slot; the old rule (each gap over 1.5 periods) counted one
    assert _missed([0.0, 0.05, 0.16, 0.1601, 0.20, 0.25]) == 0
    assert _missed([0.0, 0.05, 0.13, 0.15, 0.20]) == 0


def test_jitter_of_a_period_either_way_over_a_long_run_is_none_missed():
    rng = random.Random(3)
    # each stamp up to 0.9 period from its slot, in either direction (in order)
    stamps = [k * 0.05 + rng.uniform(0.0, 0.045) for k in range(20000)]
    assert _missed(stamps) == 0


def test_losses_amid_jitter_are_counted():
    rng = random.Random(4)
    stamps = [k * 0.05 + rng.uniform(0.0, 0.02) for k in range(20000)]
    lost = set(rng.sample(range(1, 19999), 300))
    kept = [t for k, t in enumerate(stamps) if k not in lost]
    assert _missed(kept) == pytest.approx(300, abs=30)


def test_a_burst_banks_no_credit_against_a_later_loss():
    gaps = MissedStamps(0.05)
    for _ in range(100):                # a flood: stamps microseconds apart
        assert gaps.gap(1e-5) == 0
    assert gaps.owed == 0.0
    assert gaps.gap(0.10) == 0 and gaps.gap(0.05) == 1


def test_a_reordered_message_makes_up_one_and_a_pause_is_no_loss():
    gaps = MissedStamps(0.05)
    assert gaps.gap(0.10) == 0          # stamps 0, 0.10: 0.05 owed
    assert gaps.gap(-0.05) == 0         # 0.05 came after 0.10: nothing owed
    assert gaps.owed == 0.0 and gaps.gap(0.05) == 0
    assert gaps.gap(PAUSE_PERIODS * 0.05) == 0 and gaps.owed == 0.0
    assert gaps.gap(0.05) == 0


def test_a_period_must_be_positive():
    with pytest.raises(ValueError, match='period must be > 0'):
        MissedStamps(0.0)
