# test_core_estimate_stream: which writer's estimates the compensator follows.
"""Tests of observer_ros.core.estimate_stream, alone and in the simulated cart loop."""

import numpy as np
from observer_ros.core.estimate_stream import CONSISTENCY_TOL, EstimateStream, within
from observer_ros.core.loop_status import ERROR, WARN
import pytest
from test_core_loop_supervisor import CartLoop


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


def _corrupted_standby(u):
    """Run the cart loop with one command the plant never got, known to the standby alone."""
    loop = CartLoop(jitter=0.002)
    loop.observer()
    loop.run(8.0)
    # between two sample times: no command the compensator sends replaces it
    loop.sup.standby.command(8.0555, [u])
    loop.run(12.0)
    return loop


@pytest.mark.parametrize('u', [5.0, 50.0])
def test_a_standby_that_disagrees_with_the_stream_followed_does_not_take_the_loop(u):
    """
    The standby wrong, the observer right: the loop stays closed on the observer.

    With the standby as the only reference, the observer's estimates were taken for
    another stream's and ignored, the standby closed the loop, and the cart left x_d by
    0.46 m (5 N) to 3.6 m (50 N).
    """
    loop = _corrupted_standby(u)
    theta, off = loop.worst(8.0)
    assert off < 0.02 and theta < 0.01, (theta, off)
    assert loop.counts.get('standby_disagreements', 0) >= 10
    assert 'other_stream_estimates' not in loop.counts
    assert 'standby_commands' not in loop.counts
    assert any(level == WARN and text.startswith('standby observer: more than 0.1')
               for level, text in loop.logs), loop.logs


def test_a_second_observer_is_ignored_then_followed_if_the_first_stops():
    loop = CartLoop(jitter=0.002)
    loop.observer(pause=(9.5, 99.0))    # the first falls silent for good at 9.5 s
    loop.observer(start=8.0)            # unconverged: x_hat(0) = 0 with the cart at 1 m
    loop.run(9.5)
    theta, off = loop.worst(8.0)
    assert off < 0.02, off
    # ignored while it converges (those after the first's at a stamp: repeats)
    assert loop.counts['other_stream_estimates'] >= 5
    # silent: the second one's estimates, converged, continue the stream followed (the
    # model's prediction from the last estimate followed) and agree with the standby:
    # followed; none ignored from then on
    loop.run(11.0)
    n = loop.counts['other_stream_estimates']
    loop.run(13.0)
    theta, off = loop.worst(8.0)
    assert off < 0.05 and theta < 0.05, (theta, off)
    assert loop.sup.mode == 'closed'
    assert loop.counts['other_stream_estimates'] == n
