# test/test_bag_tune_irregular.py: observer-tune on bags with lost messages and jitter.
"""
observer-tune on bags of an independent writer, with lost messages and jittered stamps.

Closed-loop bags from test/irregular_bags.py (numpy, scipy and rosbags, nothing of
observer_ros), 5 % of each sensor's messages lost
and stamps jittered by +-20 % of the step, known noise: a spring-damper chain with two
position sensors (a system the project's files do not have) and the submarine.

``benchmarks/tune_bars.py`` runs the same over many seeds (the figures of the README).

"""

from pathlib import Path

import irregular_bags as ib
import numpy as np
from observer_ros.core.als import ALSError
from observer_ros.evaluation.evaluator import evaluate_bag
from observer_ros.tuning.identify import identify
from observer_ros.tuning.tune import main
from observer_ros.vehicle import load_vehicle
import pytest

CONFIG = Path(__file__).resolve().parents[2] / 'config'


def _floats(values):
    return '[' + ', '.join(repr(float(x)) for x in np.ravel(values)) + ']'


@pytest.fixture(scope='module')
def chain(tmp_path_factory):
    root = tmp_path_factory.mktemp('chain')
    Qc = [0.0016, 0.0036]
    system = ib.spring_chain(Qc)
    bag = ib.write(root / 'chain', system, ib.simulate(system, 10_000, seed=11))
    return bag, ib.chain_vehicle(root / 'spring_chain.yaml'), system, Qc, [4e-6, 9e-6]


def test_chain_with_lost_messages_and_jitter(chain, tmp_path, capsys):
    bag, vehicle, system, Qc, R = chain
    out = tmp_path / 'tune'
    assert main([str(bag), '--vehicle', str(vehicle), '--states', 'v1,v2', '--search', 'none',
                 '--out', str(out), '--no-plots']) == 0
    text = capsys.readouterr().out
    # how much is missing and how the steps vary, said
    assert 'measurements missing at some samples (x1 ' in text and 'x2 ' in text
    assert 'x the median (the filter and the model at the actual stamps)' in text
    assert 'std_err' in text and 'chosen from the plant' in text
    import json
    ident = json.loads((out / 'tune.json').read_text())['identification']
    missing = ident['irregular'][str(bag)]['missing']
    assert 0.03 < missing['x1'] < 0.07 and 0.03 < missing['x2'] < 0.07
    values = {e['name']: (e['value'], e['std']) for e in ident['entries']}
    for name, true in zip(('x1', 'x2'), R):
        assert abs(values[name][0] / true - 1) < 0.10, (name, values[name], true)
    for name, true in zip(('w_v1', 'w_v2'), Qc):
        value, std = values[name]
        assert abs(value - true) < 3 * std and std < 0.2 * true, (name, value, std, true)
    # the reference's innovations are coloured, the tuned filter's white (the test of the
    # node and observer-eval)
    assert all(not w['white'] for w in ident['whiteness_reference'].values())
    assert all(w['white'] for w in ident['whiteness_tuned_kalman'].values())
    tuned = out / 'spring_chain_tuned.yaml'
    assert '# standard errors (1 sigma): w_v1 ' in tuned.read_text()
    # the tuned filter against the one of the true covariances, replayed at the stamps
    true = ['observer.type:=kalman', f'observer.Qd:={_floats(np.diag(Qc))}',
            f'observer.Rd:={_floats(np.diag(R))}', f'observer.Bd:={_floats(system.Gw)}']
    ev = evaluate_bag(bag, vehicle, {'truekf': true}, compare={'tuned': tuned},
                      include_live=False, include_design=False)
    ratio = ev.variants['tuned'].summary['error_rms'] / ev.variants['truekf'].summary['error_rms']
    assert abs(ratio - 1) < 0.05, ratio
    for name, h in ev.variants['truekf'].sensors.items():
        assert h['consistent'], (name, h)
        assert 0 < h['false_alarm'] <= 0.01


def test_submarine_theta_noise_the_gyro_cannot_determine(tmp_path):
    # noise on theta and w, a rate gyro only: theta's noise intensity is not determined
    # by 10^4 samples; said with the remedies, and the filter is not given zero
    system = ib.submarine([1e-5, 4e-4])
    bag = ib.write(tmp_path / 'sub', system, ib.simulate(system, 10_000, seed=1))
    ident = identify([bag], CONFIG / 'submarine.yaml', states=['theta', 'w'])
    (_, _, theta, theta_sd), (_, _, w, w_sd), (_, _, r, r_sd) = ident.result.entries()
    assert abs(r / 1e-6 - 1) < 0.1 and abs(w - 4e-4) < 3 * w_sd and w_sd < 0.15 * 4e-4
    assert abs(theta - 1e-5) < 2 * theta_sd and 2 * theta_sd > theta
    warning = [w for w in ident.warnings if w.startswith('Qd w_theta = ')]
    assert len(warning) == 1, ident.warnings
    assert '+-2 sigma reaches zero, so these data do not determine it' in warning[0]
    assert 'a longer bag' in warning[0]
    # the tuned filter's value: chosen in the +-2 sigma range (minimax), said
    choice = ident.choice
    assert choice.entries == [0] and 0 < ident.file_Q[0, 0] <= theta + 2 * theta_sd
    assert ident.file_Q[1, 1] == w
    assert f'the tuned Kalman filter is given {ident.file_Q[0, 0]:.3g}, the value in its ' \
        '+-2 sigma' in warning[0]
    assert [p.lags for p in ident.passes] == [p.auto_lags for p in ident.passes]
    assert ident.passes[0].lags > 15 and ident.passes[0].decay * 4 >= ident.passes[0].lags


def test_wrong_noise_structure_is_named(tmp_path):
    # noise on every state of the chain, identified as a force on the second mass alone:
    # the fit is far off, noise on every state fits; refused, the cause and the option
    # named (its numbers would mislead)
    system = ib.spring_chain([0.0, 0.0])
    system.Gw, system.Qc = np.eye(4), np.diag([1e-5, 1e-3, 1e-5, 1e-3])
    bag = ib.write(tmp_path / 'chain', system, ib.simulate(system, 10_000, seed=3))
    vehicle = ib.chain_vehicle(tmp_path / 'spring_chain.yaml')
    with pytest.raises(ALSError) as err:
        identify([bag], vehicle, input_noise=True)
    text = str(err.value)
    assert text.startswith('the identified model fits the autocovariances poorly')
    assert 'with process noise on every state it is' in text
    assert 'likely cause: the noise structure' in text
    assert text.endswith('identify with --states x1,v1,x2,v2')


def _result(R, R_std, chi2, dof=100):
    from observer_ros.core.als import ALSResult
    R, R_std = np.atleast_2d(R), np.atleast_2d(R_std)
    return ALSResult(Q=np.eye(1), R=R, Qk=np.eye(1), lags=10, samples=1000, empirical=None,
                     fitted=None, sigma=None, condition=1.0, rank=2, unknowns=2,
                     residual=chi2 * dof, full=False, raw=None, Q_std=np.eye(1),
                     R_std=R_std, dof=dof, labels=[('Q', 0, 0), ('R', 0, 0)])


def test_measurement_noise_not_positive_is_diagnosed():
    from observer_ros.tuning.identify import _diagnose
    zero = _result(0.0, 1e-7, 1.3)
    fits = [('every state', '--states theta,w,q', _result(1e-6, 1e-8, 1.0)),
            ('the inputs', '--input-noise', 'not identifiable (rank 1 of 2)')]
    text = _diagnose(zero, fits, 'the inputs (--input-noise)', ['q'])
    assert text.startswith('the identified measurement noise covariance R is not positive '
                           'definite (q 0 +- 1e-07)')
    assert 'with process noise on every state: R diag 1e-06 +- 1e-08, chi2/dof 1' in text
    assert 'with process noise on the inputs: not identifiable' in text
    assert text.endswith('fit is better: identify with --states theta,w,q')
    # no structure gives a positive R: said so; an undetermined but positive R without a
    # better structure goes on (None: the warnings name it)
    text = _diagnose(zero, fits[1:], 'every state', ['q'])
    assert 'no noise structure tried gives a positive R' in text
    assert _diagnose(_result(1e-7, 1e-7, 1.0), fits[1:], 'every state', ['q']) is None


def test_an_undetermined_variance_is_given_half_its_standard_error():
    # the tuned file's filter: a variance below half its standard error is raised to it
    # (zero would stop the filter following that noise); one above it is kept
    from observer_ros.core.als import ALSResult
    from observer_ros.tuning.identify import FILE_FLOOR, filter_Q
    res = ALSResult(Q=np.diag([0.0, 4e-6, 3e-5]), R=np.eye(1), Qk=np.eye(3), lags=10,
                    samples=1000, empirical=None, fitted=None, sigma=None, condition=1.0,
                    rank=4, unknowns=4, residual=100.0, full=False, raw=None,
                    Q_std=np.diag([1e-5, 1e-5, 1e-5]), R_std=np.eye(1), dof=100,
                    labels=[('Q', 0, 0), ('Q', 1, 1), ('Q', 2, 2), ('R', 0, 0)])
    assert FILE_FLOOR == 0.5
    written = np.diag(filter_Q(res, FILE_FLOOR))
    assert np.allclose(written, [5e-6, 5e-6, 3e-5], rtol=1e-12, atol=0)
    assert np.array_equal(res.Q, np.diag([0.0, 4e-6, 3e-5]))       # reported as identified


def test_a_sensor_that_never_reports_is_refused(chain, tmp_path):
    bag, vehicle, *_ = chain
    other = load_vehicle(vehicle, overrides=['sensors.mass2.topic:=mass3/joint_states'])
    with pytest.raises(Exception, match="sensor 'mass2'|mass3"):
        identify([bag], other, states=['v1', 'v2'])


def test_reference_unstable_with_an_output_missing_is_replaced(tmp_path):
    # three masses in a row, observer poles at -3..-3.5: the gain's columns offset one
    # another, and a sample with x3 alone amplifies the error by 1.39; with lost messages
    # that reference is replaced by a Kalman predictor of unit noise, with a warning
    from observer_ros.tuning.identify import _masked_reference
    from observer_ros.tuning.sampled import (noise_input, present_patterns, reference_gain,
                                             sampled_model, unstable_pattern)
    system = ib.three_mass_chain([0.001, 0.002, 0.004])
    vehicle = load_vehicle(ib.vehicle_file(system, 'three_mass_chain', tmp_path / 'c3.yaml',
                                           np.linspace(-3.0, -3.5, 6)))
    Ad, _ = sampled_model(vehicle, system.h)
    C = np.asarray(vehicle.plant.C, float)
    G, _ = noise_input(vehicle, ['v1', 'v2', 'v3'])
    Lp, reference = reference_gain(vehicle, Ad, system.h, G)

    class Data:
        y = np.array([[1.0, 1.0], [np.nan, 1.0], [1.0, np.nan], [np.nan, np.nan]])
    patterns = present_patterns([Data])
    assert patterns.tolist() == [[False, True], [True, False], [True, True]]
    rho, only = unstable_pattern(Ad, C, Lp, patterns)
    assert 1.3 < rho < 1.5 and only.tolist() == [False, True]
    warn = []
    gain, what = _masked_reference(vehicle, Ad, C, system.h, G, Lp, reference, [Data], warn)
    assert what.startswith('a Kalman predictor of unit noise') and 'x3 alone' in what
    assert unstable_pattern(Ad, C, gain, patterns) is None
    assert len(warn) == 1 and 'unstable at samples with only x3 present (|z| 1.39' in warn[0]
    # every output at every sample: the vehicle's own observer stays
    regular = type('Regular', (), {'y': np.ones((3, 2))})
    gain, what = _masked_reference(vehicle, Ad, C, system.h, G, Lp, reference, [regular], [])
    assert gain is Lp and what == reference
