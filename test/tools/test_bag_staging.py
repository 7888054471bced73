# Tools interrupted while writing: the earlier output, or a complete new one; never a mix.
"""observer-tune and observer-eval write aside and put their folder in place whole."""

import errno
import json
import os
from pathlib import Path
import signal
import subprocess
import sys
import time

from observer_ros.bag.errors import BagToolError
from observer_ros.evaluation import report as eval_report
from observer_ros.evaluation.evaluate import main as eval_main
from observer_ros.outputs.folders import MARKER
from observer_ros.outputs.staging import StagedOutput, write_new_file
from observer_ros.tuning import report as tune_report
from observer_ros.tuning.tune import main as tune_main
import pytest
from ros_helpers import tmpfs, WAIT

REPO = Path(__file__).resolve().parents[2]
SAMPLE = REPO / 'bags' / 'samples' / 'submarine'
VEHICLE = REPO / 'config' / 'submarine.yaml'
TUNE = [str(SAMPLE), '--vehicle', str(VEHICLE), '--namespace', '/', '--no-als', '--search',
        'poles', '--grid', '0.5,1', '--no-plots']
EVAL = [str(SAMPLE), '--vehicle', str(VEHICLE), '--namespace', '/', '--no-plots']


def _tree(root):
    """Return {relative path: (inode, bytes)} of every file under root."""
    return {p.relative_to(root).as_posix(): (p.stat().st_ino, p.read_bytes())
            for p in sorted(Path(root).rglob('*')) if p.is_file()}


def _complete(out):
    """Return True when every file the marker lists is there, with its size."""
    files = json.loads((out / MARKER).read_text())['files']
    return all((out / rel).stat().st_size == size for rel, (size, _) in files.items())


def _stages(out):
    return [p for p in out.parent.iterdir() if p.name.startswith(f'.{out.name}.')]


def test_an_interrupted_tune_leaves_its_earlier_output_and_the_rerun_replaces_it(
        tmp_path, monkeypatch, capsys):
    out = tmp_path / 'tune'
    assert tune_main(TUNE + ['--out', str(out)]) == 0
    (out / 'notes.txt').write_text('mine')          # a user's file next to the tool's
    before = _tree(out)
    real = tune_report.write_report

    def interrupted(result, folder, plots):         # Ctrl-C after the first file
        (folder / 'tune.txt').write_text('half')
        raise KeyboardInterrupt
    monkeypatch.setattr('observer_ros.tuning.tune.write_report', interrupted)
    assert tune_main(TUNE + ['--out', str(out), '--force']) == 130
    assert 'error: interrupted' in capsys.readouterr().err
    assert _tree(out) == before and not _stages(out)
    # the rerun recognises every file as its own (the tuned file too) and replaces them
    monkeypatch.setattr('observer_ros.tuning.tune.write_report', real)
    assert tune_main(TUNE + ['--out', str(out), '--force']) == 0
    after = _tree(out)
    assert after['notes.txt'] == before['notes.txt']        # the same file, not a copy
    assert after['tune.json'][0] != before['tune.json'][0] and _complete(out)
    assert not _stages(out)


@pytest.mark.ros
def test_a_tool_terminated_while_writing_leaves_no_mix_and_no_stage(tmp_path):
    out = tmp_path / 'tune'
    assert tune_main(TUNE + ['--out', str(out)]) == 0
    before = _tree(out)
    # SIGTERM (the default action: no clean-up) as soon as its stage exists
    proc = subprocess.Popen([sys.executable, '-W', 'ignore', '-m', 'observer_ros.tuning.tune',
                             *TUNE, '--out', str(out), '--force'],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + WAIT
    while not _stages(out) and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    proc.send_signal(signal.SIGTERM)
    proc.wait(timeout=WAIT)
    if proc.returncode == 0:        # it finished first: a complete new set
        assert _complete(out)
    else:                           # it stopped as Ctrl-C would: its stage removed
        assert proc.returncode == 143 and _tree(out) == before and not _stages(out)
    assert tune_main(TUNE + ['--out', str(out), '--force']) == 0
    assert _complete(out) and not _stages(out)


def test_a_signal_while_the_stage_is_made_leaves_no_stage(tmp_path, monkeypatch):
    """SIGTERM (or Ctrl-C) between the stage's mkdir and its marker: the stage removed."""
    out = tmp_path / 'eval'

    def interrupted(self, users):
        raise KeyboardInterrupt
    monkeypatch.setattr(StagedOutput, '_write_stage_marker', interrupted)
    with pytest.raises(KeyboardInterrupt):
        with StagedOutput(out, False, 'observer-eval'):
            pass
    assert list(tmp_path.iterdir()) == []


def test_an_evaluation_that_cannot_finish_writing_keeps_the_earlier_output(
        tmp_path, monkeypatch, capsys):
    out = tmp_path / 'eval'
    assert eval_main(EVAL + ['--out', str(out)]) == 0
    before = _tree(out)

    def full_disk(*args):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(out / 'results_bag'))
    monkeypatch.setattr(eval_report, 'write_results_bag', full_disk)
    assert eval_main(EVAL + ['--out', str(out), '--force']) == 2
    err = capsys.readouterr().err
    assert err == f'error: {out / "results_bag"}: No space left on device\n'   # not [Errno 28]
    assert _tree(out) == before and not _stages(out)


@pytest.mark.ros
def test_a_stage_left_by_a_killed_run_is_removed_and_an_old_folder_restored(tmp_path):
    out = tmp_path / 'eval'
    code = ('import os, signal, sys\n'
            'from observer_ros.outputs.staging import StagedOutput\n'
            f'stage = StagedOutput({str(out)!r}, False, "observer-eval").__enter__()\n'
            '(stage.path / "results.txt").write_text("half")\n'
            'os.kill(os.getpid(), signal.SIGKILL)\n')
    killed = subprocess.Popen([sys.executable, '-c', code])
    assert killed.wait(timeout=WAIT) == -signal.SIGKILL         # its pid: a dead process
    assert len(_stages(out)) == 1 and not out.exists()
    with StagedOutput(out, False, 'observer-eval') as staged:
        assert [p.name for p in _stages(out)] == [staged.path.name]     # the killed one: gone
        (staged.path / 'results.txt').write_text('the earlier output')
        staged.commit([staged.path / 'results.txt'])
    # killed between the two renames of the fallback (no renameat2): the old output set
    # aside and no folder; the next run puts it back before anything else
    out.rename(tmp_path / f'.eval.observer-eval-{killed.pid}-0.old')
    with StagedOutput(out, True, 'observer-eval') as staged:
        assert (out / 'results.txt').read_text() == 'the earlier output'
    assert not _stages(out) and (out / 'results.txt').exists()


def test_write_new_file_never_replaces_and_leaves_no_partial_file(tmp_path):
    path = write_new_file(tmp_path / 'v.yaml', 'a: 1\n')
    assert path.read_text() == 'a: 1\n'
    with pytest.raises(FileExistsError):
        write_new_file(path, 'b: 2\n')
    assert path.read_text() == 'a: 1\n' and sorted(os.listdir(tmp_path)) == ['v.yaml']


@pytest.fixture
def read_only(tmp_path):
    """Mount a read-only file system (a tmpfs, ro); skip where mounting is not allowed."""
    with tmpfs(tmp_path / 'ro', 'ro,size=1m', 'a read-only tmpfs') as path:
        yield path


@pytest.mark.ros
def test_a_read_only_output_is_one_line_before_the_work(read_only, capsys):
    start = time.monotonic()
    assert eval_main(EVAL + ['--out', str(read_only / 'ev')]) == 2
    err = capsys.readouterr().err
    assert err == f'error: {read_only / "ev"}: cannot write in {read_only}: Read-only file ' \
                  'system\n', err                    # not "[Errno 30] Read-only file system"
    assert tune_main(TUNE + ['--out', str(read_only / 'tune')]) == 2
    assert 'Read-only file system' in capsys.readouterr().err
    assert time.monotonic() - start < WAIT


def test_two_runs_into_one_new_folder_the_second_refused_unless_forced(tmp_path):
    out = tmp_path / 'eval'
    first = StagedOutput(out, False, 'observer-eval')
    second = StagedOutput(out, False, 'observer-eval')
    with first, pytest.raises(BagToolError, match='exists; refusing to overwrite it'):
        (first.path / 'results.txt').write_text('one')
        with second:
            (second.path / 'results.txt').write_text('two')
            first.commit([first.path / 'results.txt'])     # the first one finished first
            second.commit([second.path / 'results.txt'])
    assert (out / 'results.txt').read_text() == 'one' and not _stages(out)


def test_the_current_folder_as_output(tmp_path, monkeypatch):
    out = tmp_path / 'eval'
    for text in ('first', 'here'):          # new, then again from inside it with --force
        with StagedOutput('.' if out.exists() else out, out.exists(), 'observer-eval') as s:
            (s.path / 'results.txt').write_text(text)
            s.commit([s.path / 'results.txt'])
        monkeypatch.chdir(out)
    assert (out / 'results.txt').read_text() == 'here' and not _stages(out)


@pytest.mark.parametrize('odd', ['fifo', 'link', 'big'])
def test_a_marker_that_is_not_a_small_regular_file_is_refused_not_waited_on(tmp_path, capsys,
                                                                            odd):
    out = tmp_path / 'eval'
    out.mkdir()
    marker = out / MARKER
    if odd == 'fifo':       # opening it would wait for a writer forever
        os.mkfifo(marker)
    elif odd == 'link':
        (tmp_path / 'elsewhere.json').write_text('{"tool": "observer-eval", "files": {}}')
        marker.symlink_to(tmp_path / 'elsewhere.json')
    else:
        marker.write_text(' ' * (2 << 20))
    start = time.monotonic()
    assert eval_main(EVAL + ['--out', str(out), '--force']) == 2
    assert time.monotonic() - start < WAIT
    reason = {'fifo': 'not a regular file', 'link': 'is a link', 'big': 'more than'}[odd]
    err = capsys.readouterr().err
    assert err.count('\n') == 1 and f'{out} exists and is not an observer-eval output ' \
        'folder (the marker ' in err and reason in err, err
    assert sorted(p.name for p in out.iterdir()) == [MARKER]
