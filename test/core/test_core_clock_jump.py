# test_core_clock_jump: one rule for a clock that jumped back, asked by every component.
"""Tests of observer_ros.core.clock_jump and of the components that ask it."""

import math
import random

import numpy as np
from observer_ros.core.clock_jump import CLOCK_JUMP, ClockJump, FAR_BACK, IN_BASE
from observer_ros.core.estimators import History, make_estimator
from observer_ros.core.estimators.admission import Admission
from observer_ros.core.loop_supervisor import LoopSupervisor
from observer_ros.core.vehicle_design import design_vehicle
from observer_ros.nodes.clock_follower import ClockFollower
from observer_ros.vehicle import load_vehicle
import pytest
from ros_helpers import CONFIG


def _counter():
    counts = {}

    def count(key, n=1):
        counts[key] = counts.get(key, 0) + n
    return counts, count


def test_a_single_wild_stamp_never_jumps():
    counts, count = _counter()
    jumps = ClockJump(0.5, 3, count)
    newest = 100.0
    for wild in (99.4, 50.0, 1.0, -3600.0, 99.0):
        assert jumps.judge(wild, newest) is FAR_BACK
        assert jumps.judge(newest + 0.01, newest) is IN_BASE     # the time base goes on
        newest += 0.01
    assert counts == {'far_back_stamps': 5}
    assert jumps.judge(99.6, 100.0) is IN_BASE                   # within the tolerance


@pytest.mark.parametrize('agreement', [1, 2, 3, 5])
def test_a_restart_is_accepted_at_the_agreed_count(agreement):
    counts, count = _counter()
    jumps = ClockJump(0.5, agreement, count)
    verdicts = [jumps.judge(1.0 + 0.01 * k, 30.0) for k in range(agreement)]
    assert verdicts == [FAR_BACK] * (agreement - 1) + [CLOCK_JUMP]
    assert counts == {'far_back_stamps': agreement - 1, 'clock_jumps': 1} if agreement > 1 \
        else {'clock_jumps': 1}
    assert jumps.streak == 0


def test_stamps_agree_only_without_the_old_base_between_and_close_together():
    jumps = ClockJump(0.5, 3)
    assert jumps.judge(1.0, 30.0) is FAR_BACK
    assert jumps.judge(1.0, 30.0) is FAR_BACK                # a repeat agrees
    assert jumps.judge(30.01, 30.0) is IN_BASE               # the old base: streak broken
    assert jumps.judge(1.0, 30.01) is FAR_BACK
    assert jumps.judge(1.0 - 3600.0, 30.01) is FAR_BACK      # far before the streak: anew
    assert jumps.streak == 1
    assert jumps.judge(1.02, 30.01) is FAR_BACK              # after it: agrees
    assert jumps.judge(1.03, 30.01) is CLOCK_JUMP


def test_bad_settings_are_refused_by_name():
    for bad in (0, -1, 1.5, True):
        with pytest.raises(ValueError, match='clock_jump_agreement'):
            ClockJump(0.5, bad)
    for bad in (0.0, -1.0, math.inf, math.nan):
        with pytest.raises(ValueError, match='clock_jump_tolerance'):
            ClockJump(bad, 3)


def _stamps(seed):
    """Return a run's sensor stamps: wild ones now and then, a restart now and then."""
    rnd = random.Random(seed)
    clock, stamps = 10.0, []
    for _ in range(3000):
        clock = round(clock + 0.01, 9)
        if rnd.random() < 0.004:
            clock = round(rnd.uniform(1.0, 5.0), 2)                # the simulator restarts
        stamps.append(clock)
        if rnd.random() < 0.01:
            stamps.append(round(clock - rnd.uniform(0.6, 3600.0), 6))   # one wild stamp
    return stamps


@pytest.mark.parametrize('seed', [0, 1])
def test_the_observer_the_compensator_and_a_clock_follower_jump_on_the_same_stamps(seed):
    """Each component keeps its own newest; each counts as the others do."""
    v = load_vehicle(str(CONFIG / 'cart_pendulum.yaml'), overrides=['simulator.mode:=realtime'])
    history = History(make_estimator(v.plant, v.observer), v.observer.history_length)
    admission = Admission(history)
    sup_counts, sup_count = _counter()
    sup = LoopSupervisor(v, design_vehicle(v), count=sup_count)
    follower_counts, follower_count = _counter()
    follower = ClockFollower(0.01, first_wait=1.0, count=follower_count)
    jumped = {'observer': [], 'compensator': [], 'follower': []}
    for i, t in enumerate(_stamps(seed)):
        verdict = admission.measurement('encoder', t, now=t)
        if verdict.restart:
            jumped['observer'].append(i)
            history.reset(None, None)
        if verdict.use:
            history.correct(t, [0.0], (0,))
        before = sup.plant_time
        sup.measurement('encoder', t, None, float(i))
        if before is not None and sup.plant_time is not None and sup.plant_time < before:
            jumped['compensator'].append(i)
        newest = follower.newest
        follower.heard(int(t), int(round((t - int(t)) * 1e9)))
        if newest is not None and follower.newest < newest:
            jumped['follower'].append(i)
    assert len(jumped['observer']) >= 5
    assert jumped['compensator'] == jumped['observer'] == jumped['follower']
    keys = ('far_back_stamps', 'clock_jumps')
    observer = {k: admission.counts.get(k, 0) for k in keys}
    assert observer['far_back_stamps'] > 20
    assert {k: sup_counts.get(k, 0) for k in keys} == observer
    assert {k: follower_counts.get(k, 0) for k in keys} == observer
    np.testing.assert_equal(sup.plant_time, admission.newest)
