# test/test_core_whiteness.py: the one whiteness test, calibrated.
"""
The whiteness test of the node, observer-eval and observer-tune, calibrated.

Its false-alarm rates on white residuals against the levels it states (fewer seeds than
the benchmark, with binomial bounds), its run rule against a simulation of it, and its
power.

``benchmarks/whiteness_calibration.py`` measures the same rates over thousands of runs.

"""

import math

import numpy as np
from observer_ros.core.innovation import (ALPHA, InnovationMonitor, sequence_health,
                                          sequence_health_blocks)
from observer_ros.core.whiteness import (flagged, periodogram_statistic, run_rule,
                                         run_verdict, window_p, WindowWhiteness)
import pytest
from scipy.stats import binom, kstwo


def _bounds(trials, rate):
    """Return the counts outside which a rate is refuted (two-sided, 1e-4 each side)."""
    return binom.ppf(1e-4, trials, rate), binom.isf(1e-4, trials, rate)


def test_window_test_flags_white_windows_at_its_level_for_any_length():
    # 200 seeds x 100 windows per length: the exact level, not an approximation's
    rng = np.random.default_rng(0)
    for N, alpha in ((8, 0.1), (50, 0.05), (50, 0.01), (201, 0.02)):
        X = rng.standard_normal((200 * 100, N)) * rng.uniform(0.1, 10.0)
        D, points = periodogram_statistic(X)
        count = int(np.count_nonzero(flagged(D, points, alpha)))
        low, high = _bounds(X.shape[0], alpha)
        assert low <= count <= high, (N, alpha, count, X.shape[0] * alpha)
    # the p-value is the exact Kolmogorov-Smirnov one of the window's points
    x = rng.standard_normal(50)
    D, points = periodogram_statistic(x)
    assert points == 23 and window_p(x) == pytest.approx(kstwo.sf(D, 23), rel=1e-12)
    # the mean does not enter; a constant is undefined
    assert window_p(x + 100.0) == pytest.approx(window_p(x), rel=1e-9)
    assert math.isnan(window_p(np.ones(50)))


def test_window_test_finds_colour():
    rng = np.random.default_rng(1)
    e = rng.standard_normal((2000, 250))
    x = np.zeros_like(e)
    for t in range(1, 250):
        x[:, t] = 0.6 * x[:, t - 1] + e[:, t]
    D, points = periodogram_statistic(x[:, 200:])
    assert np.mean(flagged(D, points, 1e-3)) > 0.7


def test_run_rule_level_is_its_exact_false_alarm_probability():
    # simulate the rule itself: each window flagged with probability alpha, extreme with
    # alpha_extreme (a subset), independently
    rng = np.random.default_rng(2)
    for W, alpha in ((1, 1e-3), (40, 0.01), (200, 0.02)):
        rule = run_rule(W, alpha, level=0.05)
        assert rule['level'] <= 0.05
        runs = 50_000
        u = rng.random((runs, W))
        flags = np.count_nonzero(u < alpha, axis=1)
        extreme = np.count_nonzero(u < rule['alpha_extreme'], axis=1)
        alarms = np.count_nonzero((flags > rule['allowed']) | (extreme > 0))
        low, high = _bounds(runs, rule['level'])
        assert low <= alarms <= high, (W, alpha, alarms / runs, rule)
    v = run_verdict(run_rule(200, 1e-3), 2, 0)
    assert v['white'] and v['allowed'] == 2
    assert not run_verdict(run_rule(200, 1e-3), 3, 0)['white']
    assert not run_verdict(run_rule(200, 1e-3), 1, 1)['white']
    assert run_verdict(run_rule(0, 1e-3), 0, 0)['white'] is None


@pytest.mark.parametrize('p', [1, 2])
def test_node_window_verdict_rate_on_white_residuals(p):
    # at a level 50 times the node's, to count enough alarms in 100 seeds x 10 windows
    alpha = 50 * ALPHA
    alarms = trials = 0
    for seed in range(100):
        rng = np.random.default_rng(100 + seed)
        mon = InnovationMonitor([('s', [1.0] * p)], kalman=True, alpha=alpha)
        S = np.diag(rng.uniform(0.5, 2.0, p))
        for _ in range(10):
            mon.restart()
            for row in rng.standard_normal((50, p)) @ np.sqrt(S):
                mon.add('s', row, S)
            alarms += not mon.health('s').consistent
            trials += 1
    low, high = _bounds(trials, alpha)
    assert low <= alarms <= high, (alarms, trials * alpha)


def test_run_verdicts_rate_on_white_residuals():
    # observer-eval (NIS and whiteness) and observer-tune (whiteness): 400 runs each at
    # a level 5 times RUN_LEVEL: the alarms within the binomial bounds of the level stated
    level = 0.05
    alarms = {'eval': 0, 'tune': 0}
    stated = {'eval': [], 'tune': []}
    for seed in range(400):
        E = np.random.default_rng(1000 + seed).standard_normal((3000, 1))
        h = sequence_health('s', E, True, level=level)
        alarms['eval'] += not h['consistent']
        stated['eval'].append(h['false_alarm'])
        white = WindowWhiteness(1, 50, ALPHA)
        white.add(E[:1234])
        white.add(E[1234:])
        v = white.verdicts(level)[0]
        alarms['tune'] += not v['white']
        stated['tune'].append(v['level'])
    for key in alarms:
        low, high = _bounds(400, float(np.mean(stated[key])))
        assert low <= alarms[key] <= high, (key, alarms[key], np.mean(stated[key]))
        assert np.mean(stated[key]) <= level


def test_blocks_windows_and_the_monitor_agree():
    # the run's windows across blocks are those of the whole array; each window's flag
    # is the node monitor's verdict on it
    rng = np.random.default_rng(5)
    E = rng.standard_normal((1000, 2))
    E[500:550] *= 3.0                                   # one window far outside
    whole = sequence_health('s', E, True)
    parts = sequence_health_blocks('s', [(E[:333], None), (E[333:], None)], True)
    assert whole == parts
    assert not whole['consistent'] and whole['windows_extreme'] == 1
    assert whole['problem'].startswith('s: residuals too large')
    mon = InnovationMonitor([('s', [1.0, 1.0])], kalman=True)
    flags = 0
    for w in range(20):
        mon.restart()
        for row in E[50 * w:50 * (w + 1)]:
            mon.add('s', row, np.eye(2))
        flags += not mon.health('s').consistent
    assert flags == whole['windows_inconsistent']
    # missing values (NaN) are left out of a column's windows
    white = WindowWhiteness(2, 50, ALPHA)
    F = E.copy()
    F[::7, 1] = np.nan
    white.add(F)
    v = white.verdicts()
    assert v[0]['windows'] == 20 and v[1]['windows'] == (1000 - 143) // 50
