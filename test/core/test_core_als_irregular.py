# test/test_core_als_irregular.py: ALS on irregular arrays, its statistics and lags.
"""
The pieces of ALS on irregular data, each against a reference.

The steps' exact
discretisation against scipy's expm and Van Loan, the lagged sums with missing values
against the sum over pairs, the time-varying model against the time-invariant one on
regular data and against the data on irregular data, Bartlett's covariance against a
Monte Carlo, and the identification of known noise with its standard errors.

"""

import irregular_bags
import numpy as np
from numpy.testing import assert_allclose
from observer_ros.core.als import (als_matrix, ALSError, choose_lags, identify_noise,
                                   process_noise_map)
from observer_ros.core.als_ltv import (event_predictor, ltv_autocovariance_sums, LTVModel,
                                       steady_covariances, StepModel)
from observer_ros.core.als_stats import als_rows, autocovariance_covariance, plant_lags
from observer_ros.core.autocovariance import LaggedSums
from observer_ros.core.design import observer_gain
from observer_ros.core.estimators import process_noise_covariance
from observer_ros.core.model import map_poles_to_discrete, zoh_matrices
from observer_ros.core.step_matrices import noise_steps, zoh_steps
import pytest
import scipy.linalg


SUB = irregular_bags.submarine([1e-4, 4e-4])
H = SUB.h


def test_each_step_is_sampled_exactly():
    rng = np.random.default_rng(0)
    tau = np.concatenate([H * rng.uniform(0.6, 1.4, 50), [1e-4, 2 * H, 3 * H + 0.01, 7.3]])
    Ad, Bd = zoh_steps(SUB.A, SUB.B, tau, H)
    S = SUB.Gw @ SUB.Qc @ SUB.Gw.T
    Qd = noise_steps(SUB.A, S, tau, H)
    for k, t in enumerate(tau):
        aug = np.zeros((4, 4))
        aug[:3, :3], aug[:3, 3:] = SUB.A, SUB.B
        E = scipy.linalg.expm(aug * t)
        assert_allclose(Ad[k], E[:3, :3], rtol=1e-12, atol=1e-15)
        assert_allclose(Bd[k], E[:3, 3:], rtol=1e-11, atol=1e-16)
        want = process_noise_covariance(SUB.A, SUB.Qc, t, SUB.Gw)
        assert_allclose(Qd[k], want, rtol=1e-10, atol=1e-14 * np.abs(want).max())


def test_lagged_sums_average_the_pairs_that_exist():
    rng = np.random.default_rng(1)
    e = rng.standard_normal((700, 2))
    e[rng.random((700, 2)) < 0.2] = np.nan
    sums = LaggedSums(2, 6)
    for a in range(0, 700, 97):                       # blocks: the same sums
        sums.add(e[a:a + 97])
    got = sums.autocovariances(6)
    for j in range(6):
        for i in range(2):
            for l_ in range(2):
                x, y = e[j:, i], e[:700 - j, l_]
                ok = np.isfinite(x) & np.isfinite(y)
                assert sums.counts[j, i, l_] == ok.sum()
                assert got[j, i, l_] == pytest.approx(np.mean(x[ok] * y[ok]), rel=1e-12)
    assert_allclose(sums.missing, np.isnan(e).sum(axis=0))


def _two_output_model():
    C = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    Ad, Bd = zoh_matrices(SUB.A, SUB.B, H)
    Lp = observer_gain(Ad, C, map_poles_to_discrete([-0.6, -0.61, -0.62], H), discrete=True)
    return C, Ad, Lp, StepModel(SUB.A, SUB.B, C, Lp, H)


def test_time_varying_model_on_regular_steps_is_the_time_invariant_one():
    C, Ad, Lp, model = _two_output_model()
    G = np.eye(3)
    M, _, _ = als_matrix(Ad, C, Lp, process_noise_map(SUB.A, G, H), 3, 12)
    K = 1500
    tau, present = np.full(K, H), np.ones((K, 2), dtype=bool)
    Phi, L = model.step_gains(tau, present)
    basis = [np.diag(e) for e in np.eye(3)]
    noise = np.stack([model.step_noise(tau, S) for S in basis], axis=1)
    Rb = np.array([np.diag(e) for e in np.eye(2)])
    P0 = steady_covariances(Phi[0], L[0], noise[0], Rb)
    sums, counts = ltv_autocovariance_sums(Phi, L, noise, Rb, present, C, 12, 300, P0)
    assert_allclose((sums / counts[..., None]).reshape(-1, 5), M, rtol=1e-9,
                    atol=1e-12 * np.abs(M).max())
    assert counts[3, 0, 1] == K - 300


def _irregular_arrays(N, seed, dropout=0.05, jitter=0.2):
    """Two outputs of the submarine, noise on every state; samples lost, stamps jittered."""
    C, Ad, Lp, model = _two_output_model()
    system = irregular_bags.System(SUB.A, SUB.B, C, np.eye(3), np.diag([1e-4, 4e-4, 1e-3]),
                                   [irregular_bags.Sensor('a', '', [0], [0.01]),
                                    irregular_bags.Sensor('b', '', [1], [0.02])],
                                   H, ['theta', 'w', 'q'], ['delta'])
    run = irregular_bags.simulate(system, N, seed, dropout=dropout, jitter=jitter)
    keep = np.isfinite(run['y']).any(axis=1)
    return C, Ad, Lp, model, run['t'][keep] - run['t'][0], run['y'][keep], run['u'][keep]


def test_irregular_data_identified_within_the_standard_errors():
    # 5 % of each output lost, stamps +-20 %: the filter at the stamps and the
    # time-varying model give the truth within 4 standard errors, and within 3 but for
    # at most one of the 15 entries; the standard errors are those of the spread over
    # seeds (Bartlett through the weighted least squares)
    truth = np.array([1e-4, 4e-4, 1e-3, 1e-4, 4e-4])
    G = np.eye(3)
    est, std = [], []
    for seed in range(3):
        C, Ad, Lp, model, t, y, u = _irregular_arrays(6000, seed)
        F = process_noise_map(SUB.A, G, H)
        lags = choose_lags(Ad, C, Lp, F, 3, t.size)[0]
        sums = LaggedSums(2, lags)
        x0 = event_predictor(model, t[:300], y[:300], u[:300])
        event_predictor(model, t[300:], y[300:], u[300:], x0=x0, sinks=[sums])
        assert 0.03 < sums.missing[0] / sums.samples < 0.07
        ltv = LTVModel(model, G, [(t, np.isfinite(y), 300)], steps=6000)
        res = identify_noise(sums, Ad, C, Lp, F, 3, lags, ltv=ltv)
        values = np.array([e[2] for e in res.entries()])
        sd = np.array([e[3] for e in res.entries()])
        assert np.all(np.abs(values - truth) < 4 * sd), (values, sd)
        # w's noise reaches the outputs only through q's weak coupling (0.126 w)
        assert np.all(np.delete(sd < 0.5 * truth, 1))
        est.append(values)
        std.append(sd)
    z = (np.array(est) - truth) / np.array(std)
    assert np.count_nonzero(np.abs(z) > 3) <= 1, z
    spread = np.std(est, axis=0, ddof=1)
    ratio = spread / np.mean(std, axis=0)
    assert np.all((ratio > 0.1) & (ratio < 3.0)), ratio      # 3 seeds: a rough check


def test_bartlett_covariance_against_a_monte_carlo():
    # y1 = x + v1, y2 = x / 2 + v2, x an AR(1): the spread of the sample
    # autocovariances over 400 runs against the formula
    rng = np.random.default_rng(4)
    phi, N, runs = 0.7, 1500, 400
    gamma = np.zeros((60, 2, 2))
    for d in range(60):
        gamma[d] = phi ** d / (1 - phi ** 2) * np.array([[1, 0.5], [0.5, 0.25]])
    gamma[0] += np.diag([0.5, 0.3])
    rows = als_rows(3, 2)
    Sigma = autocovariance_covariance(gamma, rows, [N - j for j in rows[0]])
    est = np.empty((runs, rows[0].size))
    for r in range(runs):
        w = rng.standard_normal(N + 100)
        x = np.zeros(N + 100)
        for t in range(1, N + 100):
            x[t] = phi * x[t - 1] + w[t]
        x = x[100:]
        y = np.column_stack([x + np.sqrt(0.5) * rng.standard_normal(N),
                             0.5 * x + np.sqrt(0.3) * rng.standard_normal(N)])
        est[r] = [y[j:, i] @ y[:N - j, l_] / (N - j) for j, i, l_ in zip(*rows)]
    ratio = np.std(est, axis=0, ddof=1) / np.sqrt(np.diag(Sigma))
    assert np.all((ratio > 0.85) & (ratio < 1.15)), ratio


def test_lags_cover_the_decay_of_the_slowest_mode():
    C, Ad, Lp, _ = _two_output_model()
    F = process_noise_map(SUB.A, np.eye(3), H)
    lags, decay = choose_lags(Ad, C, Lp, F, 3, 10_000)
    # the reference's poles at -0.6: a factor 1e-3 of energy is left after about
    # ln(1e3) / (2 * 0.6 * 0.05) = 115 steps, or more (each column has a transient first)
    assert 100 <= decay <= 300 and lags == min(4 * decay, 375)      # 375: 1500 rows / 2^2
    # a slower reference needs more; few samples cap the lags
    slow = observer_gain(Ad, C, map_poles_to_discrete([-0.2, -0.21, -0.22], H),
                         discrete=True)
    assert choose_lags(Ad, C, slow, F, 3, 10_000)[1] > 2 * decay
    assert choose_lags(Ad, C, Lp, F, 3, 1000)[0] == 125
    X = np.zeros((50, 1, 1, 1))
    X[:5] = 1.0
    assert plant_lags(X, 40) == (20, 5)


def test_a_column_that_does_not_reach_the_outputs_is_refused():
    C, Ad, Lp, model = _two_output_model()
    e = np.random.default_rng(0).standard_normal((3000, 2))
    G = np.zeros((3, 1))
    with pytest.raises(ALSError, match='does not reach the measured outputs'):
        identify_noise(e, Ad, C, Lp, process_noise_map(SUB.A, G, H), 1, 20)
