"""
Every worked example of the seed documents, to the digits they print.

Seeds: 000 (submarine pitch, observer design notes), 001 (Luenberger's sign
convention), 002 (Examples 5.15-5.21: unobservable plant, inverted pendulum on a
cart), 003 (observable decomposition), 004 (separation principle, Kalman-Bucy).
"""

import itertools

import control
import numpy as np
from numpy.testing import assert_allclose
from observer_ros.core.analysis import (numerical_rank, observability_report,
                                        observable_decomposition, obsv)
from observer_ros.core.closed_loop import (closed_loop_matrix, compensator_matrices,
                                           error_dynamics_matrix, reduced_closed_loop_matrix,
                                           separation_check, tracking_residual)
from observer_ros.core.design import (controller_gain, kalman_gain, observer_gain,
                                      reduced_order_observer)
from observer_ros.core.errors import NotDetectableError
from observer_ros.core.vehicle_design import design_warnings
import pytest
import scipy.linalg


def half_unit(printed):
    """Half a unit of the last digit of a number printed as the string ``printed``."""
    decimals = len(printed.split('.')[1]) if '.' in printed else 0
    return 0.5 * 10.0 ** -decimals


# ======================================================================== seed 000
# Submarine pitch, states [theta, w, q] (seed 000 prints A and B in its observer
# equations with 3-4 decimals), input delta, a rate gyro measures q.

SUB_A_TEXT = [['0', '0', '1'],
              ['0.0135', '-0.322', '-0.7102'],
              ['-0.036', '0.126', '-0.7395']]
SUB_B_TEXT = [['0'], ['0.0322'], ['-0.0857']]
SUB_A = np.array([[float(x) for x in row] for row in SUB_A_TEXT])
SUB_B = np.array([[float(x) for x in row] for row in SUB_B_TEXT])
SUB_C = np.array([[0.0, 0.0, 1.0]])
# theta' = q is exact (structural 0 and 1); every other printed entry is rounded.
SUB_PERTURBED = [('A', 1, 0), ('A', 1, 1), ('A', 1, 2), ('A', 2, 0), ('A', 2, 1),
                 ('A', 2, 2), ('B', 1, 0), ('B', 2, 0)]


def _perturb(signs):
    A, B = SUB_A.copy(), SUB_B.copy()
    for (which, i, j), s in zip(SUB_PERTURBED, signs):
        text = (SUB_A_TEXT if which == 'A' else SUB_B_TEXT)[i][j]
        (A if which == 'A' else B)[i, j] += s * half_unit(text)
    return A, B


def attainable_range(f):
    """
    Range of f(A, B) over A, B within half a unit of the last printed digit.

    Linearised bound (central differences, one entry at a time: f0 +- sum |df|)
    widened by 10 %, after checking that every vertex of the box (2^8 designs)
    lies inside it, i.e. that the linearisation is good enough.
    """
    f0 = np.asarray(f(SUB_A, SUB_B), dtype=float).ravel()
    radius = np.zeros_like(f0)
    for k in range(len(SUB_PERTURBED)):
        plus = [0.0] * len(SUB_PERTURBED)
        minus = [0.0] * len(SUB_PERTURBED)
        plus[k], minus[k] = 1.0, -1.0
        radius += np.abs(np.asarray(f(*_perturb(plus))).ravel()
                         - np.asarray(f(*_perturb(minus))).ravel()) / 2.0
    lo, hi = f0 - 1.1 * radius, f0 + 1.1 * radius
    for signs in itertools.product((-1.0, 1.0), repeat=len(SUB_PERTURBED)):
        v = np.asarray(f(*_perturb(signs))).ravel()
        assert np.all(v >= lo) and np.all(v <= hi), 'linearised bound too small'
    return lo, hi


def assert_printed_attainable(printed_text, f):
    printed = np.array([float(x) for x in printed_text])
    lo, hi = attainable_range(f)
    assert np.all(printed >= lo) and np.all(printed <= hi), (printed, lo, hi)
    return lo, hi


# The seed's A and B are printed rounded (4 decimals, some with 3-4 significant
# digits), so a design from the rounded matrices does not hit the printed
# digits exactly (it gives L = [-21.942, -2.2601, 0.7685] and
# K = [-0.8443, -1.4722, 0.9813]). These tests prove that the printed values are
# what this rounding allows: each printed entry of A and B is moved within half
# a unit of its last printed digit, and every printed component must lie in the
# attainable range. Entries that do not depend on the rounding beyond the trace
# (L3 = trace(A) - sum(poles), because C picks q) must match to all 4 printed
# decimals.


def test_submarine_observability_matrix():
    O_printed = [['0', '0', '1.0000'],
                 ['-0.0360', '0.1260', '-0.7395'],
                 ['0.0283', '-0.1338', '0.4214']]
    Ob = obsv(SUB_A, SUB_C)
    assert numerical_rank(Ob) == 3 and observability_report(SUB_A, SUB_C).observable
    # rows C and C A are exact copies of printed entries: 4 decimals
    assert_allclose(Ob[:2], [[float(x) for x in r] for r in O_printed[:2]], atol=5e-5)
    # row C A^2 carries the rounding of A (-0.13375 from the rounded A is printed
    # -0.1338): the printed row must be attainable
    assert_printed_attainable(O_printed[2], lambda A, B: obsv(A, SUB_C)[2])


def test_submarine_fast_observer_poles():
    poles = [-0.6, -0.61, -0.62]
    printed = ['-21.9614', '-2.2636', '0.7685']
    L = observer_gain(SUB_A, SUB_C, poles)
    assert np.abs(L[2, 0] - 0.7685) <= half_unit('0.7685')
    assert_printed_attainable(printed, lambda A, B: observer_gain(A, SUB_C, poles))
    assert_allclose(np.sort(np.linalg.eigvals(SUB_A - L @ SUB_C).real), sorted(poles))


def test_submarine_slow_observer_poles():
    poles = [-0.1, -0.11, -0.12]
    L = observer_gain(SUB_A, SUB_C, poles)
    assert np.abs(L[2, 0] - (-0.7315)) <= half_unit('-0.7315')
    assert_printed_attainable(['0.8664', '-0.4817', '-0.7315'],
                              lambda A, B: observer_gain(A, SUB_C, poles))


def test_submarine_controller():
    # "With poles at -0.3": the printed u = 0.8451 theta + 1.4733 w - 0.9807 q,
    # i.e. u = -K x with K = [-0.8451, -1.4733, 0.9807], comes from the poles
    # -0.3, -0.31, -0.32 (a triple pole at -0.3 gives a very different K).
    poles = [-0.3, -0.31, -0.32]
    lo, hi = assert_printed_attainable(
        ['-0.8451', '-1.4733', '0.9807'], lambda A, B: controller_gain(A, B, poles))
    K_triple = controller_gain(SUB_A, SUB_B, [-0.3, -0.3, -0.3])
    assert not np.all((K_triple.ravel() >= lo) & (K_triple.ravel() <= hi))


def test_submarine_fast_observer_meets_the_rule_of_thumb_and_slow_one_does_not():
    # seed 000: -0.6.. are "twice as negative" as the controller's -0.3..; -0.1.. are slower
    K = controller_gain(SUB_A, SUB_B, [-0.3, -0.31, -0.32])
    fast = observer_gain(SUB_A, SUB_C, [-0.6, -0.61, -0.62])
    slow = observer_gain(SUB_A, SUB_C, [-0.1, -0.11, -0.12])
    assert not [w for w in design_warnings(SUB_A, SUB_B, SUB_C, K, fast) if 'slow' in w]
    assert [w for w in design_warnings(SUB_A, SUB_B, SUB_C, K, slow) if 'slow' in w]


def test_submarine_heave_reduced_order_observer():
    # Seed 000 section 3.5: theta and q measured, w estimated, observer pole p = -0.6.
    # Our state order is [theta, w, q]; the seed reorders to [theta, q, w], which is
    # exactly x_bar = T x of reduced_coordinates (x_bar = [C x; w]).
    p = -0.6
    C = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    d = reduced_order_observer(SUB_A, SUB_B, C, poles=[p])
    assert d.rest == (1,)
    a11U, a12U, a13zGB = SUB_A[1, 1], SUB_A[1, 2], SUB_A[1, 0]     # w row
    a21U, a22U, a23zGB = SUB_A[2, 1], SUB_A[2, 2], SUB_A[2, 0]     # q row
    b1U2, b2U2 = SUB_B[1, 0], SUB_B[2, 0]
    assert (a11U, a21U) == (-0.322, 0.126)
    l2 = (a11U - p) / a21U
    # The seed chooses l1 = 0 "for simplicity" (l1 plays no role in F);
    # python-control's place (scipy's YT method) returns that minimum-norm gain too.
    assert_allclose(d.L, [[0.0, l2]], atol=1e-12)
    assert_allclose(d.F, [[p]], atol=1e-12)
    assert_allclose(d.H, [[b1U2 - l2 * b2U2]], atol=1e-12)
    assert_allclose(d.G, [[a13zGB - l2 * a23zGB, a12U - l2 * a22U + p * l2]], atol=1e-12)
    # w_hat = l2 q + z (seed): state_estimate puts it back in [theta, w, q] order
    x = np.array([0.1, 0.5, -0.2])
    z = x[1] - l2 * x[2]
    assert_allclose(d.state_estimate(C @ x, [z]), x)


# ======================================================================== seed 001


def test_luenberger_sign_convention():
    # seed 001 writes z' = (A + L C) z - L y + B u: its L is minus ours
    L = observer_gain(SUB_A, SUB_C, [-0.6, -0.61, -0.62])
    assert_allclose(np.sort(np.linalg.eigvals(SUB_A + (-L) @ SUB_C).real),
                    [-0.62, -0.61, -0.6])


# ======================================================================== seed 002

CART_A = np.array([[0, 0, 1, 0], [0, 0, 0, 1], [10.78, 0, 0, 0], [-0.98, 0, 0, 0]], float)
CART_B = np.array([[0.0], [0.0], [-1.0], [1.0]])
CART_C = np.array([[0.0, 1.0, 0.0, 0.0]])          # y = x (cart displacement)
CART_OBS_POLES = [-10 - 10j, -10 + 10j, -20 - 20j, -20 + 20j]
CART_L_PRINTED = np.array([[-25149.79591836735], [60.0], [-183183.8861224490], [1810.780]])
CART_K_POLES = [-7.853 + 3.2528j, -7.853 - 3.2528j, -7.853 + 7.853j, -7.853 - 7.853j]
CART_K_PRINTED = np.array([[-1362.364050360232, -909.3160795202226, -344.8741667548096,
                            -313.4621667548089]])
CART_K2_POLES = [-0.7853 + 3.25328j, -0.7853 - 3.25328j, -0.7853 + 0.7853j,
                 -0.7853 - 0.7853j]


def test_example_515_516_unobservable_and_undetectable():
    # Example 5.15: x1' = 2 x1 + 3 u, x2' = -x2, x3' = 5 x3 - u,
    # y1 = x1, y2 = 2 x2 + x1 + u, hence C = [[1, 0, 0], [1, 2, 0]] and D = [0; 1].
    A = np.diag([2.0, -1.0, 5.0])
    C = np.array([[1.0, 0.0, 0.0], [1.0, 2.0, 0.0]])
    rep = observability_report(A, C)
    assert (rep.rank, rep.observable, rep.detectable) == (2, False, False)
    assert rep.unobservable_modes == ('eigenvalue 5 (unstable): x3',)
    with pytest.raises(NotDetectableError, match=r'eigenvalue 5 \(unstable\): x3'):
        observer_gain(A, C, [-1.0, -2.0])
    # Example 5.16 prints A with 1 in place of 2 and C = [[1, 0, 0], [2, 1, 0]]
    # (row 2 transposed); both are garblings of Example 5.15 (seed README). The
    # verdict is the same, and its printed test matrix N = ctrb(A', C') (Eq. 5.94)
    # is exactly what the garbled matrices give.
    A16 = np.diag([1.0, -1.0, 5.0])
    C16 = np.array([[1.0, 0.0, 0.0], [2.0, 1.0, 0.0]])
    N_printed = np.array([[1, 2, 1, 2, 1, 2], [0, 1, 0, -1, 0, 1], [0, 0, 0, 0, 0, 0]], float)
    assert_allclose(control.ctrb(A16.T, C16.T), N_printed)
    for Ax, Cx in ((A16, C16), (A16, C), (A, C16)):
        rep16 = observability_report(Ax, Cx)
        assert (rep16.rank, rep16.detectable) == (2, False)
        assert rep16.unobservable_modes == ('eigenvalue 5 (unstable): x3',)


def test_example_517_observability_and_observer_gain():
    assert numerical_rank(obsv(CART_A, [[1.0, 0, 0, 0]])) == 2     # y = theta
    assert numerical_rank(obsv(CART_A, CART_C)) == 4               # y = x
    assert_allclose(np.poly(CART_OBS_POLES)[1:].real, [60, 1800, 24000, 160000])
    for method in ('auto', 'acker', 'place'):
        L = observer_gain(CART_A, CART_C, CART_OBS_POLES, method=method)
        assert_allclose(L, CART_L_PRINTED, rtol=1e-12)
    # Eq. 5.106 by hand, as the seed types it: a = poly(A)(2:5),
    # Pdash = [1 -a(1:3); 0 1 -a(1:2); 0 0 1 -a(1); 0 0 0 1] (Eq. 5.51, printed with
    # 10.78 above the diagonal; its last printed row is garbled),
    # N = ctrb(A', C') and L = ((beta - a) Pdash N^-1)'
    a = np.poly(CART_A)[1:]
    beta = np.poly(CART_OBS_POLES)[1:].real
    Pdash = np.array([[1, -a[0], -a[1], -a[2]], [0, 1, -a[0], -a[1]], [0, 0, 1, -a[0]],
                      [0, 0, 0, 1]])
    assert_allclose(Pdash, [[1, 0, 10.78, 0], [0, 1, 0, 10.78], [0, 0, 1, 0], [0, 0, 0, 1]],
                    atol=1e-12)
    N = control.ctrb(CART_A.T, CART_C.T)
    L_formula = ((beta - a) @ Pdash @ np.linalg.inv(N)).reshape(-1, 1)
    assert_allclose(L_formula, CART_L_PRINTED, rtol=1e-12)


def test_example_518_regulator_and_closed_loop():
    K = controller_gain(CART_A, CART_B, CART_K_POLES)
    assert_allclose(K, CART_K_PRINTED, rtol=1e-12)
    Acl = closed_loop_matrix(CART_A, CART_B, CART_C, CART_K_PRINTED, CART_L_PRINTED)
    printed = [-20 + 20j, -20 - 20j, -10 + 10j, -10 - 10j, -7.8530 + 7.8530j,
               -7.8530 - 7.8530j, -7.8530 + 3.2528j, -7.8530 - 3.2528j]
    eig = np.linalg.eigvals(Acl)
    for z in printed:
        assert np.min(np.abs(eig - z)) < 5e-5 * max(1.0, abs(z))
    ok, _, _ = separation_check(CART_A, CART_B, CART_C, CART_K_PRINTED, CART_L_PRINTED)
    assert ok
    # Kd = 0 tracks x_d = [0, 1, 0, 0] (Eq. 5.121: the residual is
    # [0, 0, -Kd2, Kd2] with our B = [0, 0, -1, 1]; the seed prints [0, 0, Kd2, Kd2])
    x_d = np.array([0.0, 1.0, 0.0, 0.0])
    assert_allclose(tracking_residual(CART_A, CART_B, x_d), 0.0)
    Kd = np.array([[0.0, 0.3, 0.0, 0.0]])
    assert_allclose(tracking_residual(CART_A, CART_B, x_d, Kd), [0, 0, -0.3, 0.3])
    Kd_other = np.array([[1.0, 0.0, 2.0, 3.0]])        # other entries are free
    assert_allclose(tracking_residual(CART_A, CART_B, x_d, Kd_other), 0.0)


def test_example_518_second_regulator():
    K = controller_gain(CART_A, CART_B, CART_K2_POLES)
    assert_allclose(K, [[-27.0904, -1.4097, -5.1339, -1.9927]], atol=5e-5)


def test_example_519_reduced_order_observer():
    d = reduced_order_observer(CART_A, CART_B, CART_C, poles=[-20, -20 + 20j, -20 - 20j])
    assert d.rest == (0, 2, 3)                  # x2 = [theta, thetadot, xdot]
    assert_allclose(d.A22, [[0, 1, 0], [10.78, 0, 0], [-0.98, 0, 0]])
    assert_allclose(d.A12, [[0, 0, 1]])
    assert_allclose(d.A11, [[0.0]])
    assert_allclose(d.A21, [[0], [0], [0]])
    assert_allclose(d.B2, [[0], [-1], [1]])
    assert_allclose(d.B1, [[0.0]])
    # printed L = -1.6437e+003 -1.6987e+004 6.0000e+001
    for got, text in zip(d.L.ravel(), ['-1.6437e3', '-1.6987e4', '6.0000e1']):
        mant, exp = text.split('e')
        assert abs(got - float(text)) <= half_unit(mant) * 10.0 ** int(exp)
    # the seed's own command: L = (place(A22', A12'*C', v))' with C = 1
    L_seed = control.place(d.A22.T, d.A12.T * 1.0, [-20, -20 + 20j, -20 - 20j]).T
    assert_allclose(d.L, L_seed, rtol=1e-12)
    eig = np.linalg.eigvals(d.F)
    for z in (-20 + 20j, -20 - 20j, -20):
        assert np.min(np.abs(eig - z)) < 5e-4


def test_example_520_reduced_order_compensator():
    d = reduced_order_observer(CART_A, CART_B, CART_C, poles=[-20, -20 + 20j, -20 - 20j])
    # The seed re-orders the states to [x, theta, thetadot, xdot] (Eq. 5.133)
    perm = [1, 0, 2, 3]
    A_s = CART_A[np.ix_(perm, perm)]
    B_s = CART_B[perm]
    assert_allclose(A_s, [[0, 0, 0, 1], [0, 0, 1, 0], [0, 10.78, 0, 0], [0, -0.98, 0, 0]])
    K_s = controller_gain(A_s, B_s, CART_K2_POLES)
    # printed K = -1.4097e+000 -2.7090e+001 -5.1339e+000 -1.9927e+000
    assert_allclose(K_s, [[-1.4097, -27.090, -5.1339, -1.9927]], atol=5e-4)
    K2 = K_s[:, 1:]
    ACL_seed = np.block([[A_s - B_s @ K_s, -B_s @ K2], [np.zeros((3, 4)), d.F]])
    printed = [-0.78530 + 3.2533j, -0.78530 - 3.2533j, -0.78530 + 0.78530j,
               -0.78530 - 0.78530j, -20 + 20j, -20 - 20j, -20]
    tol = [5e-5, 5e-5, 5e-5, 5e-5, 5e-4, 5e-4, 5e-4]
    K = controller_gain(CART_A, CART_B, CART_K2_POLES)
    ours = reduced_closed_loop_matrix(CART_A, CART_B, K, d, coordinates='error')
    for M in (ACL_seed, ours):
        eig = np.linalg.eigvals(M)
        for z, t in zip(printed, tol):
            assert np.min(np.abs(eig.real - z.real) + np.abs(eig.imag - z.imag)) <= 2 * t
    # our error-form K2 is K on the estimated states [theta, thetadot, xdot]
    assert_allclose(ours[:4, 4:], -CART_B @ K[:, [0, 2, 3]])
    assert separation_check(CART_A, CART_B, CART_C, K, d)[0]


# ======================================================================== seed 003


def test_observable_decomposition_has_the_seed_003_form():
    A = np.diag([2.0, -1.0, 5.0])
    B = np.array([[3.0], [0.0], [-1.0]])
    C = np.array([[1.0, 0.0, 0.0], [1.0, 2.0, 0.0]])
    Abar, Bbar, Cbar, T, m = observable_decomposition(A, B, C)
    assert m == 2
    assert_allclose(np.linalg.solve(T, A @ T), Abar, atol=1e-14)   # Abar = T^-1 A T
    assert_allclose(np.linalg.solve(T, B), Bbar, atol=1e-14)
    assert_allclose(C @ T, Cbar, atol=1e-14)
    assert_allclose(Abar[:m, m:], 0.0)                              # [[Ao, 0], [A21, Aob]]
    assert_allclose(Cbar[:, m:], 0.0)                               # [Co, 0]
    assert_allclose(obsv(A, C) @ T[:, m:], 0.0, atol=1e-14)         # null space of O


# ======================================================================== seed 004


def test_separation_principle_seed_004():
    K = controller_gain(SUB_A, SUB_B, [-0.3, -0.31, -0.32])
    L = observer_gain(SUB_A, SUB_C, [-0.6, -0.61, -0.62])
    ok, cl, expected = separation_check(SUB_A, SUB_B, SUB_C, K, L)
    assert ok
    assert_allclose(np.sort(expected.real), [-0.62, -0.61, -0.6, -0.32, -0.31, -0.3])
    assert_allclose(np.sort(cl.real), np.sort(expected.real), atol=1e-8)
    # seed 004's proof, state [x; e] with e = x - x_hat: [[A - BK, BK], [0, A - LC]]
    E = error_dynamics_matrix(SUB_A, SUB_B, SUB_C, K, L)
    M = np.block([[E[:3, :3], -E[:3, 3:]], [E[3:, :3], E[3:, 3:]]])
    assert_allclose(np.sort(np.linalg.eigvals(M).real), np.sort(expected.real), atol=1e-8)


def test_kalman_bucy_seed_004():
    # L = P C^T Rd^-1 with A P + P A^T + Qd - P C^T Rd^-1 C P = 0 (Bd = I). The
    # slide prints "L = A P_d C^T R_d^-1", a garbling: the continuous Kalman-Bucy
    # gain has no A (lqe, and MATLAB's kalman, give P C^T Rd^-1).
    Qd = np.diag([1e-3, 1e-2, 1e-2])
    Rd = np.array([[1e-4]])
    L, P, E = kalman_gain(SUB_A, SUB_C, Qd, Rd)
    assert_allclose(L, P @ SUB_C.T @ np.linalg.inv(Rd), rtol=1e-10)
    res = SUB_A @ P + P @ SUB_A.T + Qd - P @ SUB_C.T @ np.linalg.solve(Rd, SUB_C) @ P
    assert np.abs(res).max() < 1e-10 * np.abs(P).max()
    assert_allclose(P, scipy.linalg.solve_continuous_are(SUB_A.T, SUB_C.T, Qd, Rd),
                    rtol=1e-8)
    assert np.all(np.linalg.eigvals(SUB_A - L @ SUB_C).real < 0)


def test_overall_controller_seed_004():
    # Ak = A - B K - L C, Bk = [B L], Ck = -K, Dk = [1 0]: the y -> u part is ours
    # with u = -D(s) y
    K = controller_gain(SUB_A, SUB_B, [-0.3, -0.31, -0.32])
    L = observer_gain(SUB_A, SUB_C, [-0.6, -0.61, -0.62])
    Ac, Bc, Cc, Dc = compensator_matrices(SUB_A, SUB_B, SUB_C, K, L)
    assert_allclose(Ac, SUB_A - SUB_B @ K - L @ SUB_C)
    assert_allclose(Bc, L)
    assert_allclose(-Cc, -K)
    assert_allclose(Dc, 0.0)
