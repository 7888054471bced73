# test/core/test_core_control_law.py: the compensator's float law and gate against numpy's.
"""ControlLaw (plain floats) equals control_law (numpy) and command_problem, limits or not."""

import math

import numpy as np
from observer_ros.core.control_law import command_problem, control_law, ControlLaw
import pytest


def _case(rng, n, m):
    K = rng.normal(scale=3.0, size=(m, n))
    Kd = rng.normal(size=(m, n))
    x_d = rng.normal(size=n)
    return K, Kd, x_d


@pytest.mark.parametrize('n, m', [(3, 1), (4, 1), (6, 2), (12, 3)])
def test_float_law_equals_numpy_law_without_and_with_limits(n, m):
    rng = np.random.default_rng(n * 10 + m)
    K, Kd, x_d = _case(rng, n, m)
    u_min, u_max = -np.full(m, 2.0), np.full(m, 1.5)
    u_min[0] = -np.inf                  # an infinite limit is no limit on that side
    free = ControlLaw(K, x_d, Kd)
    bounded = ControlLaw(K, x_d, Kd, u_min, u_max)
    below = ControlLaw(K, x_d, Kd, u_min, None)
    clipped = 0
    for _ in range(300):
        x = rng.normal(scale=2.0, size=n)
        want = control_law(K, x, x_d, Kd)
        scale = 1e-12 * (1.0 + np.abs(K) @ (np.abs(x) + np.abs(x_d)) + np.abs(Kd) @ np.abs(x_d))
        got = free.unclipped(x.tolist())
        assert isinstance(got, list) and len(got) == m
        assert np.all(np.abs(np.array(got) - want) <= scale)
        assert np.all(np.abs(np.array(free(x.tolist())) - want) <= scale)
        want_bounded = control_law(K, x, x_d, Kd, u_min, u_max)
        assert np.all(np.abs(np.array(bounded(x.tolist())) - want_bounded) <= scale)
        assert np.all(np.abs(np.array(bounded.clip(got)) - want_bounded) <= scale)
        want_below = control_law(K, x, x_d, Kd, u_min, None)
        assert np.all(np.abs(np.array(below(x.tolist())) - want_below) <= scale)
        clipped += int(np.any(want_bounded != want))
    assert clipped > 50                 # the limits did bind in many cases


def test_float_law_overflow_gives_inf_or_nan_like_numpy():
    K, Kd, x_d = np.array([[1e300, -1e300]]), np.zeros((1, 2)), np.zeros(2)
    law = ControlLaw(K, x_d, Kd)
    bounded = ControlLaw(K, x_d, Kd, [-1.0], [1.0])
    with np.errstate(all='ignore'):
        # one term overflows: -inf in both, saturated by the limits as np.clip does
        x = [1e10, 0.0]
        want = control_law(K, np.array(x), x_d, Kd)
        assert law.unclipped(x) == want.tolist() == [-math.inf]     # no exception
        assert bounded(x) == control_law(K, np.array(x), x_d, Kd, [-1.0], [1.0]).tolist()
        assert bounded(x) == [-1.0]
        # both overflow, opposite signs: not finite in both (NaN or inf: the summation
        # order decides), so the gate refuses it or the limits saturate it
        x = [1e10, 1e10]
        assert not np.isfinite(control_law(K, np.array(x), x_d, Kd)).any()
    got = law.unclipped(x)
    assert math.isnan(got[0])
    assert math.isnan(bounded(x)[0])                        # NaN stays NaN, as np.clip
    assert math.isnan(np.clip(np.array([np.nan]), -1.0, 1.0)[0])
    assert 'not finite' in bounded.problem(bounded(x))


@pytest.mark.parametrize('u', [[0.2], [1e304], [float('nan')], [float('inf')], [-float('inf')],
                               [0.31], [-0.31], [0.3], [-0.3], [0.0, 0.0]])
@pytest.mark.parametrize('limits', [(None, None), ([-0.3], [0.3]), ([-0.3], None),
                                    (None, [0.3]), ([-np.inf], [np.inf])])
def test_float_gate_equals_command_problem(u, limits):
    u_min, u_max = limits
    law = ControlLaw(np.ones((1, 2)), np.zeros(2), np.zeros((1, 2)), u_min, u_max)
    assert law.problem(u) == command_problem(u, 1, u_min, u_max)
    assert (law.problem(u) is None) == (
        len(u) == 1 and math.isfinite(u[0]) and (u_min is None or u[0] >= u_min[0])
        and (u_max is None or u[0] <= u_max[0]))
