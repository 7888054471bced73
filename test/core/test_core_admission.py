# test_core_admission: what each message's stamp means, decided once for node and replay.
"""Tests of observer_ros.core.estimators.admission (no ROS)."""

import math

import numpy as np
from numpy.testing import assert_array_equal
from observer_ros.core.errors import ObserverError
from observer_ros.core.estimators import admission as adm
from observer_ros.core.estimators import FullOrderEstimator, History
from observer_ros.core.estimators.admission import Admission
from plants import GYRO, PITCH, two_sensor_submarine
import pytest


def _history(length=0.25):
    plant = two_sensor_submarine()
    return History(FullOrderEstimator(plant, poles=[-0.6, -0.61, -0.62], x0=[0.1, 0, 0]),
                   length)


class _Run:
    """An admission and its history, fed as the node feeds them."""

    def __init__(self, agreement=3, clock=None, **options):
        self.history = _history()
        self.admission = Admission(self.history, clock_jump_agreement=agreement,
                                   clock=clock, **options)
        self.verdicts = []

    def measure(self, key, t, y=0.01, now=100.0, wall=0.0):
        now = None if self.admission._clock is not None else now
        v = self.admission.measurement(key, t, wall=wall, now=now)
        self.verdicts.append(v)
        if v.use:
            if v.restart:
                self.history.reset(None, None)
            self.history.correct(t, [y], GYRO if key == 'gyro' else PITCH)
        return v

    def command(self, t, u=0.1, now=100.0):
        v = self.admission.command(t, now=now)
        if v.use:
            self.history.set_input(t, [u])
        return v

    @property
    def counts(self):
        return self.admission.counts


def test_in_order_late_out_of_order_duplicate_and_future():
    run = _Run()
    assert run.measure('gyro', 10.0) is adm.IN_ORDER
    assert run.measure('gyro', 10.05) is adm.IN_ORDER
    assert run.measure('pitch', 10.0) is adm.LATE              # inside the 0.25 s history
    assert run.measure('pitch', 9.7) is adm.OUT_OF_ORDER       # 0.35 s back: older
    assert run.measure('gyro', 10.05) is adm.DUPLICATE
    assert run.measure('pitch', 10.0) is adm.DUPLICATE         # its own newest, again
    assert run.measure('gyro', 200.0, now=100.0) is adm.FUTURE  # 100 s ahead of now
    assert run.measure('gyro', 109.9, now=100.0) is adm.IN_ORDER
    assert run.counts == {'late_measurements': 1, 'out_of_order': 1, 'duplicates': 2,
                          'future_stamps': 1}
    assert run.history.t == 109.9


def test_a_lone_stamp_an_hour_back_is_skipped_and_leaves_the_estimate_alone():
    plain, glitched = _Run(), _Run()
    for k in range(20):
        t = 100.0 + 0.05 * k
        plain.measure('gyro', t, y=0.01 * k)
        glitched.measure('gyro', t, y=0.01 * k)
        if k == 10:
            x_before = glitched.history.x_hat
            assert glitched.measure('gyro', t - 3600.0, y=5.0) is adm.FAR_BACK
            assert_array_equal(glitched.history.x_hat, x_before)
            assert glitched.history.t == t
    # the estimate goes on as if the outlier never came, to the last bit
    assert_array_equal(glitched.history.x_hat, plain.history.x_hat)
    assert glitched.counts == {'far_back_stamps': 1}


def test_a_clock_jump_needs_agreeing_messages_in_a_row():
    run = _Run(agreement=3)
    for k in range(10):
        run.measure('gyro', 100.0 + 0.05 * k)
    # two far back, then one in the old time base: the streak is broken, no reset
    assert run.measure('gyro', 1.0) is adm.FAR_BACK
    assert run.measure('pitch', 1.0) is adm.FAR_BACK
    assert run.measure('gyro', 100.5) is adm.IN_ORDER
    assert run.measure('gyro', 1.05) is adm.FAR_BACK
    # an outlier further back does not agree with the one before: a new streak
    assert run.measure('gyro', 1.05 - 3600.0) is adm.FAR_BACK
    assert run.admission.jumps.streak == 1
    assert run.measure('gyro', 1.1) is adm.FAR_BACK
    # the third in a row (another sensor, the same new time base): the clock jumped
    assert run.measure('pitch', 1.12) is adm.CLOCK_JUMP
    assert run.history.t == 1.12 and run.admission.newest == 1.12
    assert run.measure('gyro', 1.15) is adm.IN_ORDER
    assert run.counts['clock_jumps'] == 1
    assert run.counts['far_back_stamps'] == 5


def test_a_restarted_simulator_repeating_its_step_0_agrees_with_itself():
    """A realtime simulator sends step 0 again until it is answered: three make the jump."""
    run = _Run(agreement=3)
    for k in range(10):
        run.measure('gyro', 100.0 + 0.05 * k)
    assert run.measure('gyro', 1.0) is adm.FAR_BACK
    assert run.measure('gyro', 1.0) is adm.FAR_BACK
    assert run.measure('gyro', 1.0) is adm.CLOCK_JUMP
    assert run.history.t == 1.0


def test_agreement_one_is_a_jump_at_once_and_bad_values_are_refused():
    run = _Run(agreement=1)
    run.measure('gyro', 100.0)
    assert run.measure('gyro', 50.0) is adm.CLOCK_JUMP
    assert run.history.t == 50.0
    for bad in (0, 2.5, -1, True):
        with pytest.raises(ValueError, match='clock_jump_agreement'):
            run.admission.clock_jump_agreement = bad
    with pytest.raises(ValueError, match='clock_jump_tolerance'):
        run.admission.clock_jump_tolerance = math.nan
    with pytest.raises(ValueError, match='future_tolerance'):
        run.admission.future_tolerance = -1.0


def test_a_command_never_resets_and_never_moves_the_time():
    run = _Run()
    for k in range(10):
        run.measure('gyro', 100.0 + 0.05 * k)
    head = run.history.t
    assert run.command(head) is adm.COMMAND
    assert run.command(head - 0.1) is adm.COMMAND              # inside the history
    assert run.command(head - 0.3) is adm.HELD_COMMAND         # older: held from now
    assert run.command(head - 3600.0) is adm.STALE_COMMAND     # far back: held, counted
    assert run.command(head + 0.6) is adm.AHEAD_COMMAND        # past the jump tolerance
    assert run.command(head + 1e6, now=100.0) is adm.FUTURE_COMMAND
    assert run.command(head + 0.05) is adm.COMMAND             # pending
    assert run.history.t == head and run.counts.get('clock_jumps') is None
    assert run.history.estimator.u.tolist() == [0.1]       # held from the estimate's time
    assert run.counts == {'late_commands_held_from_now': 1, 'late_commands': 1,
                          'future_stamps': 2}


def test_a_long_gap_restarts_in_order_only():
    run = _Run(max_gap=2.0)
    run.measure('gyro', 100.0)
    assert run.measure('gyro', 101.9) is adm.IN_ORDER
    assert run.measure('gyro', 104.0) is adm.LONG_GAP
    assert run.counts == {'long_gap_resets': 1}


def test_the_clock_is_read_once_a_second_while_stamps_stay_below_its_bound():
    reads = []
    now = [100.0]

    def clock():
        reads.append(now[0])
        return now[0]
    run = _Run(clock=clock)
    for k in range(100):        # 100 messages in 0.5 s of wall time: one reading
        assert run.measure('gyro', 99.0 + 0.01 * k, wall=0.005 * k).use
    assert len(reads) == 1
    # a stamp past the bound (reading + future_tolerance) reads the clock again
    assert run.measure('gyro', 111.0, wall=0.6) is adm.FUTURE
    assert len(reads) == 2
    # the clock went back (a restarted clock): the bound lasts a second of wall time
    now[0] = 5.0
    assert run.measure('gyro', 100.0, wall=0.7) is adm.IN_ORDER
    assert len(reads) == 2
    assert run.measure('gyro', 100.01, wall=1.7) is adm.FUTURE
    assert len(reads) == 3
    # no clock yet (simulated time before the first /clock): nothing is ahead
    now[0] = 0.0
    assert run.measure('gyro', 1e6, wall=2.0) is adm.IN_ORDER


@pytest.mark.parametrize('sec,nanosec,ok', [
    (5, 0, True), (1, 0, True), (1_700_000_000, 999_999_999, True),
    (0, 1, False), (0, 999_999_999, False), (-3, 0, False), (-1, 999_999_999, False),
    (5, 1_000_000_000, False), (5, 4_000_000_000, False)])
def test_one_rule_for_a_malformed_stamp_in_parts_and_in_nanoseconds(sec, nanosec, ok):
    """The node checks sec/nanosec; the replay's decoder gives ns: the same verdict."""
    if ok:
        assert adm.check_stamp(sec, nanosec, 'imu/data') == (sec * 10**9 + nanosec) * 1e-9
    else:
        with pytest.raises(ObserverError, match='imu/data'):
            adm.check_stamp(sec, nanosec, 'imu/data')
    assert bool(adm.malformed_ns(adm.stamp_ns(sec, nanosec))) is not ok
    ns = adm.stamp_ns(np.array([sec], dtype=np.int64), np.array([nanosec], dtype=np.int64))
    assert bool(adm.malformed_ns(ns)[0]) is not ok
