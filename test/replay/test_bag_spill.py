# test/replay/test_bag_spill.py: the replay's rows spilled to temporary files, a block at a time.
"""
A replay whose rows are spilled (``replay(..., spill=...)``, observer-eval's default).

The spilled rows equal the in-memory ones bit for bit on the replay-blocks cases
(several sensors, commands, truth, lockstep and realtime, a looping bag, late
measurements, Kalman), with blocks of 7 rows and bulk pieces of 100 steps; observer-eval
writes byte-identical files either way; a spilled column indexes like an array. What
an evaluation keeps and peaks at per estimate, spilled and in memory, is measured by
benchmarks/m1_memory.py.

"""

import json
import tempfile

from bag_cases import CASES, SAMPLES, spy_on_spill
from bag_synth import CONFIG, simulate, write_bag
import numpy as np
from numpy.testing import assert_array_equal
from observer_ros.bag import spill as spill_mod
from observer_ros.bag.reader import read_recording
from observer_ros.evaluation import evaluate as evaluate_cli, evaluator as evaluate
from observer_ros.evaluation.report import write_results
from observer_ros.replay import bulk_runs, rows as replay_outputs
from observer_ros.replay.replay import replay
from observer_ros.replay.rows import SpilledColumn
from observer_ros.vehicle import load_vehicle
import pytest

FIELDS = ('stamp_ns', 'x_hat', 'residual', 'epoch', 'seq', 'sensor')
KALMAN = ['observer.type:=kalman',
          'observer.Qd:=[0.0,0.0,0.0,0.0,0.0,0.0,0.0,0.0,1.0e-6]', 'observer.Rd:=[1.0e-6]']


def _same(got, ref):
    for name in FIELDS:
        want = getattr(ref, name)
        have = np.asarray(getattr(got, name))
        assert have.dtype == want.dtype, name
        assert_array_equal(have, want, err_msg=name)
    assert_array_equal(np.asarray(got.whitened_rows()), ref.whitened_rows())
    assert got.counts == ref.counts and got.bulk_steps == ref.bulk_steps
    assert got.warnings == ref.warnings


@pytest.mark.parametrize('name', CASES + ['kalman'])
def test_spilled_replay_equals_the_in_memory_one(cases, name, monkeypatch, tmp_path):  # noqa: F811
    veh, bag = cases('sub' if name == 'kalman' else name)
    if name == 'kalman':
        veh = load_vehicle(CONFIG / 'submarine.yaml', overrides=KALMAN)
    rec = read_recording(bag, veh)
    monkeypatch.setattr(bulk_runs, 'MAX_RUN', 100)
    ref = replay(rec, veh)
    assert len(ref) > 3 * 7
    for block in (7, 64, replay_outputs.SPILL_BLOCK):
        monkeypatch.setattr(replay_outputs, 'SPILL_BLOCK', block)
        got = replay(rec, veh, spill=tmp_path)
        _same(got, ref)
        late = ref.counts['late_measurements'] > 0
        assert isinstance(got.x_hat, SpilledColumn) != late      # late: read back, sorted
        if name == 'late':
            assert late
    assert list(tmp_path.iterdir()) == []          # the files have no name on disk


def test_spilled_column_indexes_like_an_array(tmp_path, monkeypatch):
    monkeypatch.setattr(spill_mod, 'READ_BLOCK', 5)
    monkeypatch.setattr(spill_mod, 'CACHE_ROWS', 3)
    rng = np.random.default_rng(1)
    whole = rng.normal(size=(23, 3))
    col = SpilledColumn(np.float64, (3,), tmp_path)
    col.append(whole[:10])
    col.append(whole[10:])
    assert col.shape == whole.shape and len(col) == 23 and col.size == whole.size
    mask = rng.random(23) > 0.5
    keys = [slice(None), slice(3, 17), slice(None, None, 4), slice(-5, None), slice(5, 2),
            7, -1, mask, np.array([22, 0, 5, 5, 13]), np.array([], dtype=int),
            (slice(None), 1), (mask, 2), (np.array([4, 1]), slice(0, 2)), (slice(2, 19, 3), 0)]
    for key in keys:
        assert_array_equal(col[key], whole[key], err_msg=repr(key))
    assert col.min() == whole.min() and col.max() == whole.max()
    assert_array_equal(np.asarray(col), whole)
    col.write_row(4, np.arange(3.0))
    whole[4] = np.arange(3.0)
    assert_array_equal(col[2:8], whole[2:8])
    with pytest.raises(IndexError):
        col[23]
    with pytest.raises(IndexError):
        col[np.array([3, 30])]
    empty = SpilledColumn(np.float64, (3,), tmp_path)
    empty.append(whole[:0])                     # a replay that accepted no measurement
    for key in (slice(None), (slice(None), 1), slice(None, None, 3), np.zeros(0, bool)):
        assert_array_equal(empty[key], whole[:0][key], err_msg=repr(key))
    assert np.asarray(empty).shape == (0, 3)


def _written(result, out, plots=True):
    """Return the files written for an evaluation (the marker's mtimes and run time out)."""
    write_results(result, out, plots=plots)
    files = {}
    for path in sorted(out.rglob('*')):
        if path.is_file() and path.name != '.observer_ros_output.json':   # mtimes
            data = path.read_bytes()
            if path.name == 'results.json':
                doc = json.loads(data)
                doc.pop('seconds', None)
                data = json.dumps(doc, sort_keys=True)
            files[str(path.relative_to(out))] = data
    return files


def _assert_same_files(spilled, memory, plots=True):
    assert 'results_bag/results_bag.mcap' in spilled and ('states.png' in spilled) == plots
    assert spilled.keys() == memory.keys()
    for key in spilled:
        assert spilled[key] == memory[key], key


@pytest.mark.parametrize('name', ['two_sensors', 'late', 'loop', 'lockstep_swapped',
                                  'sample_cart_pendulum'])
def test_eval_writes_the_same_files_spilled_or_in_memory(name, tmp_path, monkeypatch,
                                                         cases):  # noqa: F811
    veh, bag = cases(name)
    monkeypatch.setattr(replay_outputs, 'SPILL_BLOCK', 50)
    variants = {'k': KALMAN} if name == 'loop' else None
    results = [evaluate.evaluate_bag(bag, veh, variants, spill=spill) for spill in (True, None)]
    late = results[1].variants['design'].replay.counts['late_measurements'] > 0
    assert late == (name == 'late')
    assert isinstance(results[0].variants['design'].replay.x_hat, SpilledColumn) != late
    # the plots (0.6 s a folder) drawn from spilled columns in one case; the rows they
    # draw are equal in every case (test_spilled_replay_equals_the_in_memory_one)
    plots = name == 'two_sensors'
    _assert_same_files(_written(results[0], tmp_path / 'spilled', plots),
                       _written(results[1], tmp_path / 'memory', plots), plots)


def test_observer_eval_spills_by_default_with_the_same_files(tmp_path, monkeypatch):
    monkeypatch.setattr(replay_outputs, 'SPILL_BLOCK', 50)
    spills = spy_on_spill(monkeypatch)
    files = []
    for extra in ([], ['--in-memory']):
        out = tmp_path / f'out{len(files)}'
        argv = [str(SAMPLES / 'submarine'), '--vehicle', str(CONFIG / 'submarine.yaml'),
                '--out', str(out), '--variant', 'k:' + ','.join(KALMAN), *extra]
        assert evaluate_cli.main(argv) == 0
        files.append({str(p.relative_to(out)): p.read_bytes() for p in sorted(out.rglob('*'))
                      if p.is_file() and p.suffix in ('.txt', '.csv', '.png', '.mcap')})
    assert spills == [True, None]
    _assert_same_files(*files)


def test_eval_spills_to_a_folder_and_leaves_no_file(tmp_path):
    veh = load_vehicle(CONFIG / 'submarine.yaml')
    bag = write_bag(tmp_path / 'bag', simulate(veh, steps=300, noise=True)['messages'])
    spill = tmp_path / 'spill'
    spill.mkdir()
    result = evaluate.evaluate_bag(bag, veh, spill=spill)
    assert isinstance(result.variants['design'].replay.x_hat, SpilledColumn)
    assert list(spill.iterdir()) == []


def test_observer_eval_says_when_it_cannot_write_its_temporary_files(
        tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(tempfile, 'tempdir', str(tmp_path / 'missing'))
    argv = [str(SAMPLES / 'submarine'), '--vehicle', str(CONFIG / 'submarine.yaml'),
            '--out', str(tmp_path / 'out'), '--no-plots']
    assert evaluate_cli.main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith('error: ') and 'temporary files' in err[-1], err
    assert str(tmp_path / 'missing') in err[-1] and 'TMPDIR' in err[-1]
    assert not (tmp_path / 'out').exists()
    assert evaluate_cli.main([*argv, '--in-memory']) == 0


def test_observer_eval_says_when_its_disk_fills(tmp_path, monkeypatch, capsys):
    # every temporary file is /dev/full: the first block written fails with ENOSPC
    monkeypatch.setattr(replay_outputs, 'SPILL_BLOCK', 50)
    monkeypatch.setattr(spill_mod.tempfile, 'TemporaryFile',
                        lambda **kwargs: open('/dev/full', 'w+b', buffering=0))
    argv = [str(SAMPLES / 'submarine'), '--vehicle', str(CONFIG / 'submarine.yaml'),
            '--out', str(tmp_path / 'out'), '--no-plots']
    assert evaluate_cli.main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith('error: ') and 'temporary files' in err[-1], err
    assert 'No space left' in err[-1] and '--in-memory' in err[-1], err[-1]
    assert not (tmp_path / 'out').exists()
