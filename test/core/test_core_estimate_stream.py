# test_core_estimate_stream: which estimates the compensator follows.
"""Tests of observer_ros.core.estimate_stream (in the cart loop: test_core_loop_supervisor)."""

import numpy as np
from observer_ros.core.estimate_stream import CONSISTENCY_TOL, EstimateStream, within
from observer_ros.core.loop_status import ERROR, WARN


def stream():
    counts, logs = {}, []

    def count(key):
        counts[key] = counts.get(key, 0) + 1
    return EstimateStream(count, lambda level, text: logs.append((level, text))), counts, logs


def test_estimates_ignored_are_said_once_and_reported():
    s, counts, logs = stream()
    for _ in range(3):
        assert s.ignore('state/estimate: another writer') is None
    assert counts == {'other_stream_estimates': 3}
    assert logs == [(ERROR, 'state/estimate: another writer, and the others like it')]
    assert s.report() == 3 and s.report() == 0


def test_a_standby_that_disagrees_is_said_once_until_it_agrees_again():
    s, counts, logs = stream()
    for _ in range(2):
        s.standby_disagrees()
    assert not s.standby_agrees and counts == {'standby_disagreements': 2}
    assert len(logs) == 1 and logs[0][0] == WARN, logs
    assert logs[0][1].startswith(f'standby observer: more than {CONSISTENCY_TOL:g}')
    s.standby_agrees = True             # the supervisor, on an estimate that agrees
    s.standby_disagrees()
    assert len(logs) == 2


def test_within_scales_each_state():
    scale = np.array([1.0, 10.0])
    assert within([0.1, 1.0], np.zeros(2), scale, 0.1)
    assert not within([0.1, 1.01], np.zeros(2), scale, 0.1)


def test_an_estimate_belongs_by_the_standby_or_else_by_the_model():
    scale = np.ones(2)
    near, far = np.zeros(2), np.full(2, 1.0)
    x = [0.05, 0.0]

    def never():
        raise AssertionError('the prediction is not needed when the standby agrees')
    s, counts, _ = stream()
    assert s.belongs(x, near, never, scale) and s.standby_agrees
    # the standby far, the model's prediction near: followed, the disagreement counted
    assert s.belongs(x, far, lambda: near, scale)
    assert not s.standby_agrees and counts == {'standby_disagreements': 1}
    # both far: another stream's; no prediction: the standby decides, or nobody does
    assert not s.belongs(x, far, lambda: far, scale)
    assert not s.belongs(x, far, lambda: None, scale)
    assert s.belongs(x, None, lambda: None, scale)
    assert not s.belongs(x, None, lambda: far, scale)
