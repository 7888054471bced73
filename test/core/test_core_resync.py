# test_core_resync: after an outage, when the compensator follows the estimates again.
"""Tests of observer_ros.core.resync, through the LoopSupervisor that asks it."""

import numpy as np
from observer_ros.core.loop_supervisor import LoopSupervisor
from observer_ros.core.resync import Resync, RESYNC_AGREE
from observer_ros.core.vehicle_design import design_vehicle
from observer_ros.vehicle import load_vehicle
from ros_helpers import CONFIG

X = np.array([0.1, 0.0, 0.0])


def _stale_lockstep(*overrides, publishers=1):
    """Return a lock-step submarine's supervisor gone stale at t = 0.5 s, and its log."""
    v = load_vehicle(str(CONFIG / 'submarine.yaml'), overrides=list(overrides))
    logs = []
    sup = LoopSupervisor(v, design_vehicle(v), log=lambda level, text: logs.append(text))
    assert sup.resync.lockstep
    sup.resync.matched(publishers, publishers)
    for k in range(10):
        sup.estimate(0.05 * k, X, 0.05 * k)
    assert sup.watchdog(0.45 + 1.0) and sup.stale
    return sup, logs


def test_lockstep_sends_no_safe_command_while_an_observer_is_matched():
    # the simulator would wait it out; the observer would take it for the step's input
    sup, logs = _stale_lockstep()
    assert 'waiting for its estimates (lock-step' in logs[-1]
    assert sup.safe_tick(1.5) is None and sup.safe_tick(2.0) is None
    # the observer's publisher gone: the simulator applies safe commands, so they are sent
    sup.resync.matched(0, 1)
    command = sup.safe_tick(2.1)
    assert command is not None and command.marked and command.source == 'safe'


def test_lockstep_follows_the_same_observer_at_once_when_it_is_back():
    sup, logs = _stale_lockstep()
    command = sup.estimate(0.5, X, 3.0)
    assert sup.mode == 'closed' and command.source == 'observer' and command.answers
    np.testing.assert_allclose(command.u, -(sup.K @ X))
    assert logs[-1].startswith('estimates back from the same observer')


def test_lockstep_resyncs_on_an_observer_matched_meanwhile():
    # a publisher matched since the estimates went stale (a restarted observer): its
    # estimates are not followed before they settle; the prediction answers meanwhile
    sup, logs = _stale_lockstep()
    sup.resync.matched(1, 2)
    command = sup.estimate(0.5, X, 3.0)
    assert sup.mode == 'resync' and command.source == 'safe'


def test_realtime_resyncs_the_same_observer_as_ever():
    sup_args = ('simulator.mode:=realtime',)
    v = load_vehicle(str(CONFIG / 'submarine.yaml'), overrides=list(sup_args))
    sup = LoopSupervisor(v, design_vehicle(v))
    assert not sup.resync.lockstep and not sup.resync.plant_waits()
    for k in range(10):
        sup.estimate(0.05 * k, X, 0.05 * k)
    assert sup.watchdog(1.45) and sup.safe_tick(1.5) is not None
    command = sup.estimate(1.5, X, 1.5)
    assert sup.mode == 'resync' and command.source == 'safe'


def test_agreement_counts_estimates_in_a_row():
    resync = Resync()
    scale = np.ones(3)
    for _ in range(RESYNC_AGREE - 1):
        assert not resync.agrees(X, X, scale)
    assert not resync.agrees(X, X + 1.0, scale)     # one that disagrees starts it over
    assert not resync.agrees(X, None, scale) and resync.agreeing == 0
    for k in range(RESYNC_AGREE):
        assert resync.agrees(X, X, scale) is (k == RESYNC_AGREE - 1)
