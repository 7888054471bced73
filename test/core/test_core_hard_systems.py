"""
Hard systems: one observability decision, scaled to the plant, for report, PBH, count, advisor.

A stiff plant (eigenvalues -1e-3 ... -1e5) whose modes -1e4 and -1e-3 the sensor does not
see, built by a similarity transformation (so the modes are unseen to within the rounding
of the data), in ten variants; the same plant in other state and output units; and random
plants with unobservable modes, each checked for agreement between the summary, the PBH
lines, the pole count the design accepts and the sensor advisor.
"""

import warnings

import numpy as np
from numpy.testing import assert_allclose
from observer_ros.core.analysis import (observability_report, observable_decomposition,
                                        pbh_test, unobservable_eigenvalues)
from observer_ros.core.design import observer_gain
from observer_ros.core.errors import DimensionError, ObserverDesignWarning
from observer_ros.core.model import Plant
from observer_ros.core.sensor_subsets import sensor_subsets
from observer_ros.core.spec import (ControllerSpec, ObserverSpec, SensorSpec, SimulatorSpec,
                                    Vehicle)
from observer_ros.core.verify import verify_placement
import pytest

STIFF = np.array([-1e-3, -1e-2, -1.0, -1e2, -1e4, -1e5])
UNSEEN = (0, 4)             # -1e-3 and -1e4


def stiff_plant(seed, orthogonal):
    """Return (A, C): the stiff plant in random coordinates, the modes UNSEEN not in C."""
    rng = np.random.default_rng(seed)
    c = rng.normal(size=(1, 6))
    c[0, list(UNSEEN)] = 0.0
    T = np.linalg.qr(rng.normal(size=(6, 6)))[0] if orthogonal else rng.normal(size=(6, 6))
    Tinv = np.linalg.inv(T)
    return T @ np.diag(STIFF) @ Tinv, c @ Tinv


def assert_one_decision(rep, unseen, rtol=1e-3):
    """Summary, rank, PBH lines and modes say the same (eigenvalues to the data's rounding)."""
    failing = sorted(r.eigenvalue.real for r in rep.pbh if not r.passed)
    assert_allclose(failing, sorted(unseen), rtol=rtol)
    assert rep.rank == rep.n - sum(r.unobserved for r in rep.pbh)
    assert not rep.observable
    assert f'unobservable (rank {rep.rank} of {rep.n})' in rep.summary()
    assert_allclose(sorted(m.eigenvalue.real for m in rep.modes), sorted(unseen), rtol=rtol)
    assert_allclose(np.sort(rep.unobservable_eigenvalues.real), np.sort(unseen), rtol=rtol)
    for r in rep.pbh:
        assert r.passed == (r.rank == r.n) == (r.unobserved == 0)
    assert rep.detectable == all(m.stable for m in rep.modes) == \
        all(r.stable for r in rep.pbh if not r.passed)


@pytest.mark.parametrize('orthogonal', [True, False])
@pytest.mark.parametrize('seed', range(10))
def test_stiff_detectable_plant_one_verdict(seed, orthogonal):
    A, C = stiff_plant(seed, orthogonal)
    rep = observability_report(A, C)
    assert_one_decision(rep, STIFF[list(UNSEEN)])
    assert rep.rank == 4 and rep.detectable
    assert 'detectable' in rep.summary() and 'NOT' not in rep.summary()
    # the pole count the design asks for is the rank, and says why (cond(T) reaches 1e13 in
    # the non-orthogonal variants: -1e-3 is then known to 2e-4 only)
    with pytest.raises(DimensionError, match='poles has 6 poles; expected 4: .*unobservable '
                                             'with rank 4 of 6'):
        observer_gain(A, C, -np.arange(1.0, 7.0))


@pytest.mark.parametrize('seed', range(10))
def test_stiff_plant_four_poles_placed_and_verified(seed):
    A, C = stiff_plant(seed, True)
    rep = observability_report(A, C)
    poles = np.array([-200.0, -300.0, -4000.0, -2e5])
    with warnings.catch_warnings():
        warnings.simplefilter('ignore', ObserverDesignWarning)
        L = observer_gain(A, C, poles)
    norm = np.linalg.norm(A, 2) + np.linalg.norm(L, 2) * np.linalg.norm(C, 2)
    check = verify_placement(A - L @ C, np.concatenate([poles, rep.unobservable_eigenvalues]),
                             'observer.poles', norm)
    assert check.within_bound and check.relative_error < 1e-4


def test_stiff_plant_in_other_units_same_verdict():
    A, C = stiff_plant(3, True)
    base = observability_report(A, C)
    for k in (-6, 6):
        S = np.diag(10.0 ** (k * np.linspace(-1, 1, 6)))       # states in other units
        As, Cs = np.linalg.solve(S, A @ S), C @ S
        for scale in (1e-8, 1.0, 1e8):                          # the sensor in other units
            rep = observability_report(As, Cs * scale)
            assert (rep.rank, rep.detectable) == (base.rank, base.detectable)
            assert_one_decision(rep, STIFF[list(UNSEEN)])


def test_the_advisor_agrees_with_the_report():
    A, c = stiff_plant(5, True)
    rng = np.random.default_rng(1)
    C = np.vstack([c, rng.normal(size=(1, 6))])               # a second sensor sees all
    plant = Plant(A, rng.normal(size=(6, 1)), C, np.zeros((2, 1)),
                  output_names=('partial', 'full'))
    sensors = tuple(SensorSpec(nm, f'{nm}_topic', 'std_msgs/msg/Float64', ('data',), (nm,),
                               np.array([0.01])) for nm in ('partial', 'full'))
    vehicle = Vehicle('stiff', plant, sensors, ObserverSpec('kalman', Qd=np.eye(6),
                                                            Rd=np.eye(2) * 1e-4),
                      ControllerSpec(), SimulatorSpec(1e5, np.zeros(6)))
    got = {s.outputs: s for s in sensor_subsets(vehicle)}
    for rows, outputs in (([0], ('partial',)), ([1], ('full',)), ([0, 1], ('partial', 'full'))):
        rep = observability_report(A, C[rows])
        s = got[outputs]
        assert (s.rank, s.observable, s.detectable) == (rep.rank, rep.observable,
                                                        rep.detectable)
    assert got[('partial',)].rank == 4 and got[('full',)].observable


def random_hidden(rng, n, p, unseen):
    """Return a random plant whose eigenvalues `unseen` C does not see (a similarity)."""
    k = len(unseen)
    r = n - k
    Abar = np.zeros((n, n))
    Abar[:r, :r] = rng.normal(size=(r, r)) * 10.0 ** rng.uniform(-2, 2)
    Abar[r:, :r] = rng.normal(size=(k, r))
    Abar[r:, r:] = np.diag(unseen)
    Cbar = np.zeros((p, n))
    Cbar[:, :r] = rng.normal(size=(p, r))
    T = rng.normal(size=(n, n)) * 10.0 ** rng.uniform(-1, 1, size=n)[None, :]
    Tinv = np.linalg.inv(T)
    return T @ Abar @ Tinv, Cbar @ Tinv


@pytest.mark.parametrize('seed', range(30))
def test_random_hidden_modes_one_decision(seed):
    rng = np.random.default_rng(700 + seed)
    n = int(rng.integers(3, 9))
    k = int(rng.integers(1, n - 1))
    unseen = -10.0 ** rng.uniform(-3, 3, size=k) * rng.choice([-1, 1], size=k, p=[0.2, 0.8])
    A, C = random_hidden(rng, n, int(rng.integers(1, 3)), unseen)
    rep = observability_report(A, C)
    assert_one_decision(rep, unseen)
    assert rep.detectable == bool(np.all(unseen < 0))
    assert observable_decomposition(A, None, C)[4] == n - k
    assert_allclose(np.sort(unobservable_eigenvalues(A, C).real), np.sort(unseen), rtol=1e-6)
    assert sum(not r.passed for r in pbh_test(A, C)) == k
