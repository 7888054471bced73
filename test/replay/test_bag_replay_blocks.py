# test/replay/test_bag_replay_blocks.py: the bulk stretches found a block at a time.
"""
The replay finds its bulk stretches a block of steps at a time (``bulk_runs._Runs``).

Any block size gives the same pieces and bit-identical estimates, residuals and
counts as one block over the whole bag, on bags with several sensors, commands, truth,
lockstep reordering, clock jumps and late messages. That the transient memory of finding
them does not grow with the bag is measured by benchmarks/m1_memory.py.

"""

import copy
import tracemalloc

from bag_cases import CASES
from bag_synth import CONFIG, simulate, write_bag
import numpy as np
from numpy.testing import assert_array_equal
from observer_ros.bag.reader import read_recording
from observer_ros.core.estimators import make_estimator
from observer_ros.core.innovation import sequence_health, transient_time
from observer_ros.core.vehicle_design import design_vehicle
from observer_ros.replay import bulk_runs, events as replay_events, health as replay_health
from observer_ros.replay.bulk_runs import find_runs, has_late
from observer_ros.replay.events import epoch_cuts, Events
from observer_ros.replay.replay import epochs_of, innovation_health, replay
from observer_ros.vehicle import load_vehicle
import pytest

WHOLE = 1 << 40                 # one block over the whole bag


BULK = ('sub', 'lockstep_swapped', 'reduced', 'discrete', 'sample_submarine',
        'sample_cart_pendulum', 'sample_submarine_reduced')     # mostly in bulk


def _replayed(rec, veh, monkeypatch, block, max_run):
    monkeypatch.setattr(bulk_runs, 'RUN_BLOCK', block)
    monkeypatch.setattr(bulk_runs, 'MAX_RUN', max_run)
    return replay(rec, veh)


@pytest.mark.parametrize('name', CASES)
def test_bag_replay_in_blocks_equals_one_block(cases, name, monkeypatch):
    veh, bag = cases(name)
    rec = read_recording(bag, veh)
    for max_run in (bulk_runs.MAX_RUN, 100):
        ref = _replayed(rec, veh, monkeypatch, WHOLE, max_run)
        if name == 'late':
            assert ref.counts['late_measurements'] > 0 and ref.bulk_steps == 0
        elif name == 'cart_shifted':
            assert 0 < ref.bulk_steps < len(ref)
        elif name in BULK:
            assert ref.bulk_steps > len(ref) // 2, name
        if name == 'loop':
            assert ref.counts['clock_jumps'] == 1
        for block in (7, 113):
            got = _replayed(rec, veh, monkeypatch, block, max_run)
            for field in ('stamp_ns', 'x_hat', 'residual', 'epoch', 'seq', 'sensor'):
                assert_array_equal(getattr(got, field), getattr(ref, field), err_msg=field)
            assert_array_equal(got.whitened_rows(), ref.whitened_rows())
            assert got.counts == ref.counts
            assert got.bulk_steps == ref.bulk_steps
            assert got.warnings == ref.warnings


def _runs(rec, veh, block):
    sensors = list(veh.sensors)
    counts = dict.fromkeys(('bad_stamps', 'bad_messages', 'bad_commands'), 0)
    events = Events(rec, sensors, veh.plant, counts,
                    lockstep=veh.simulator.mode == 'lockstep')
    est = make_estimator(veh.plant, veh.observer)
    return events, find_runs(events, events.streams, events.command, est, 0.5, 10.0,
                             block=block)


@pytest.mark.parametrize('name', ['sub', 'cart_shifted', 'lockstep_swapped', 'discrete'])
def test_bag_runs_pieces_and_their_arrays_do_not_depend_on_the_block(cases, name,
                                                                     monkeypatch):
    veh, bag = cases(name)
    rec = read_recording(bag, veh)
    monkeypatch.setattr(bulk_runs, 'MAX_RUN', 80)
    _, ref = _runs(rec, veh, WHOLE)
    assert ref.pieces
    if name == 'cart_shifted':
        assert len(ref.pieces) > 2          # several stretches, not only MAX_RUN's cuts
    for block in (1, 7, 113):
        events, got = _runs(rec, veh, block)
        assert got.pieces == ref.pieces
        for i in ref.pieces:
            a, b = ref.get(i), got.get(i)
            assert set(a) == set(b)
            for key in a:
                assert_array_equal(a[key], b[key], err_msg=key)
            assert (a['step_class'] >= 0).all() and a['b'] == a['tm'].size - 1


@pytest.mark.parametrize('name', ['sub', 'late', 'realtime_swapped'])
def test_bag_has_late_in_blocks_equals_the_whole_scan(cases, name):
    veh, bag = cases(name)
    rec = read_recording(bag, veh)
    events, _ = _runs(rec, veh, WHOLE)
    whole = has_late(events, events.streams, events.command, 0.5, block=WHOLE)
    assert whole == (name != 'sub')      # a late message, a late command
    for block in (1, 7, 113):
        assert has_late(events, events.streams, events.command, 0.5, block=block) == whole


def test_bag_runs_of_no_events_are_none():
    """No measurement, no stretch: an empty recording's events find no runs."""
    veh = load_vehicle(CONFIG / 'submarine.yaml')
    est = make_estimator(veh.plant, veh.observer)

    class _NoEvents:
        kind = idx = seq = np.zeros(0, dtype=np.int64)

        def __len__(self):
            return 0
    runs = find_runs(_NoEvents(), [], None, est, 0.5, 10.0, block=7)
    assert not runs and runs.get(0) is None


def _whole_health(rep):
    """Return the innovation health from whole-replay arrays (the code before the blocks)."""
    veh = rep.vehicle
    plant = veh.plant
    transient = transient_time(design_vehicle(veh).observer_poles, veh.sample_time,
                               plant.is_discrete, rep.kalman)
    t = rep.t
    starts, first = np.unique(rep.epoch, return_index=True)
    since = t - t[first][np.searchsorted(starts, rep.epoch)] if len(rep) else t
    out = {}
    for k, s in enumerate(veh.sensors):
        cols = list(plant.output_rows(s.outputs))
        mine = rep.sensor == k
        out[s.name] = sequence_health(s.name, rep.whitened_rows()[mine][:, cols], rep.kalman,
                                      since=since[mine], transient=transient)
    return out


@pytest.mark.parametrize('name', ['sub', 'two_sensors', 'loop', 'late', 'discrete',
                                  'sample_submarine', 'sample_cart_pendulum'])
def test_bag_innovation_health_in_blocks_equals_the_whole_arrays(cases, name, monkeypatch):
    veh, bag = cases(name)
    rep = replay(read_recording(bag, veh), veh)
    ref = _whole_health(rep)
    assert sum(f['windows'] for f in ref.values()) > 0 or name == 'late'
    if name in ('sub', 'loop'):
        assert ref['gyro']['transient'] > 0            # the initial transient is left out
    for block in (1, 7, 113, WHOLE):
        monkeypatch.setattr(replay_health, 'HEALTH_BLOCK', block)
        assert innovation_health(rep) == ref, block


def test_bag_innovation_health_of_a_kalman_filter_and_of_no_rows(tmp_path, monkeypatch):
    veh = load_vehicle(CONFIG / 'aircraft_lateral.yaml')
    rep = replay(read_recording(write_bag(tmp_path / 'air', simulate(veh, noise=True)[
        'messages']), veh), veh)
    assert rep.kalman and len(rep)
    monkeypatch.setattr(replay_health, 'HEALTH_BLOCK', 5)
    assert innovation_health(rep) == _whole_health(rep)
    empty = copy.copy(rep)
    for field in ('stamp_ns', 'x_hat', 'residual', 'whitened', 'epoch', 'seq', 'sensor'):
        setattr(empty, field, getattr(rep, field)[:0])       # a Kalman filter's whitened
    got = innovation_health(empty)
    assert got.keys() == _whole_health(empty).keys()
    for name, figures in got.items():
        ref = _whole_health(empty)[name]
        assert figures['samples'] == 0 and figures['nis_high'] == ref['nis_high']


def _tiled(rep, size):
    """Return the replay repeated (stamps shifted on) to at least ``size`` estimates."""
    reps = -(-size // len(rep))
    big = copy.copy(rep)
    span = int(rep.stamp_ns[-1] - rep.stamp_ns[0]) + 10**7
    big.stamp_ns = np.concatenate([rep.stamp_ns + i * span for i in range(reps)])
    for field in ('residual', 'epoch', 'sensor'):
        setattr(big, field, np.concatenate([getattr(rep, field)] * reps))
    return big


def _health_peak(rep):
    tracemalloc.start()
    innovation_health(rep)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return peak


def test_bag_innovation_health_memory_per_estimate(cases):
    # the whole-replay code held about 60-85 bytes per estimate (stamps, times since the
    # epoch's start, the sensor's rows copied twice); now the judged rows' NIS (8 bytes)
    veh, bag = cases('sample_submarine')
    rep = replay(read_recording(bag, veh), veh)
    small, large = _tiled(rep, 200_000), _tiled(rep, 600_000)
    _health_peak(small)                     # the first call's one-off allocations
    grow = (_health_peak(large) - _health_peak(small)) / (len(large) - len(small))
    assert grow < 12.0, grow


def test_bag_replay_outputs_are_held_once_in_narrow_types(cases):
    # an observer other than Kalman: the whitened residuals are residual / noise_std,
    # computed for the rows asked for, not held next to the residuals
    veh, bag = cases('two_sensors')
    rep = replay(read_recording(bag, veh), veh)
    assert not rep.kalman and rep.whitened is None
    std = np.full(veh.plant.p, np.nan)
    for s in veh.sensors:
        std[list(veh.plant.output_rows(s.outputs))] = s.noise_std
    assert_array_equal(rep.whitened_rows(), rep.residual / std)
    assert_array_equal(rep.whitened_rows(5, 40), rep.whitened_rows()[5:40])
    assert np.isfinite(rep.whitened_rows()).any()
    assert set(np.unique(rep.sensor).tolist()) == {0, 1}
    assert (rep.sensor.dtype, rep.seq.dtype, rep.epoch.dtype) == (np.int8, np.int32, np.int32)


def _reference_events(rec, veh):
    """Return (seq, kind, idx) in the node's order, from the definitions, whole-bag."""
    parts = []
    for k, s in enumerate(veh.sensors):
        st = rec.sensors[s.name]
        ok = st.valid & ((st.stamp_ns != 0) if st.has_header else True)
        sel = np.flatnonzero(ok)
        parts.append((st.seq[sel], np.full(sel.size, k), sel, st.stamp_ns[sel]))
    cmd = rec.command
    if cmd is not None and veh.plant.m:
        sel = np.flatnonzero(cmd.valid)
        parts.append((cmd.seq[sel], np.full(sel.size, -1), sel, cmd.stamp_ns[sel]))
    seq, kind, idx, stamp = (np.concatenate(c) for c in zip(*parts))
    order = np.argsort(seq)
    if veh.simulator.mode == 'lockstep':
        stamp = stamp[order]
        order = order[np.lexsort((seq[order], kind[order] < 0, stamp, epochs_of(stamp)))]
    return seq[order], kind[order], idx[order]


@pytest.mark.parametrize('name', CASES)
def test_bag_events_merged_in_blocks_are_in_the_nodes_order(cases, name, monkeypatch):
    veh, bag = cases(name)
    rec = read_recording(bag, veh)
    want = _reference_events(rec, veh)
    for block in (1, 7, 113, replay_events.EVENT_BLOCK):
        monkeypatch.setattr(replay_events, 'EVENT_BLOCK', block)
        counts = dict.fromkeys(('bad_stamps', 'bad_messages', 'bad_commands'), 0)
        events = Events(rec, list(veh.sensors), veh.plant, counts,
                        lockstep=veh.simulator.mode == 'lockstep')
        for got, ref, field in zip((events.seq, events.kind, events.idx), want,
                                   ('seq', 'kind', 'idx')):
            assert_array_equal(got, ref, err_msg=f'{field}, block {block}')


def test_bag_epoch_cuts_in_blocks_equal_epochs_of():
    rng = np.random.default_rng(4)
    for trial in range(20):
        stamp = np.cumsum(rng.integers(-3, 10, size=200)) * 100_000_000
        jumps = rng.integers(0, 200, size=trial % 5)
        for j in jumps:
            stamp[j:] -= int(rng.integers(0, 3)) * 10**9      # back by 0, 1 or 2 s
        want = (np.flatnonzero(np.diff(epochs_of(stamp, 0.5))) + 1).tolist()
        for block in (1, 2, 7, 64, 1000):
            assert epoch_cuts(stamp, 0.5, block) == want, (trial, block)
    assert epoch_cuts(np.zeros(0, dtype=np.int64), 0.5) == []
