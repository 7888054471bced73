# Files: every tool deletes or rewrites only what it wrote, and refuses up front.
"""Each row of "never destroy what it does not own", asserted on the file system afterwards."""

import os
from pathlib import Path
import subprocess
import sys

from bag_synth import bag_file, simulate, write_bag
from observer_ros.bag.recover import BagRecoveryError, recover_bag
from observer_ros.core.errors import ObserverError
from observer_ros.evaluation.evaluate import main as eval_main
from observer_ros.outputs.folders import MARKER
from observer_ros.tools import run_closed_loop
from observer_ros.tools.run_closed_loop import check_outputs, main as run_main, run_limit
from observer_ros.vehicle import load_vehicle
import pytest
from ros_helpers import Proc

CONFIG = Path(__file__).resolve().parents[2] / 'config'


def _tree(root):
    """Return {relative path: bytes or '->target'} of everything under root."""
    out = {}
    for p in sorted(Path(root).rglob('*')):
        rel = p.relative_to(root).as_posix()
        if p.is_symlink():
            out[rel] = '->' + os.readlink(p)
        elif p.is_file():
            out[rel] = p.read_bytes()
        else:
            out[rel] = 'dir'
    return out


@pytest.fixture(scope='module')
def sub_bag(tmp_path_factory):
    vehicle = load_vehicle(CONFIG / 'submarine.yaml')
    run = simulate(vehicle, steps=60)
    return write_bag(tmp_path_factory.mktemp('bags') / 'dive', run['messages'],
                     namespace='/sub1')


def _eval(bag, out, *extra):
    return eval_main([str(bag), '--vehicle', str(CONFIG / 'submarine.yaml'),
                      '--namespace', '/sub1', '--out', str(out), '--no-plots', *extra])


def test_eval_force_never_deletes_a_folder_it_did_not_write(sub_bag, tmp_path, capsys):
    """Row 1: a folder with a results.json (not written by observer-eval) is left whole."""
    thesis = tmp_path / 'thesis'
    (thesis / 'src').mkdir(parents=True)
    (thesis / 'thesis.tex').write_text('\\chapter{Observers}')
    (thesis / 'src' / 'main.py').write_text('print(1)')
    (thesis / 'results.json').write_text('{}')
    before = _tree(thesis)
    assert _eval(sub_bag, thesis, '--force') == 2
    err = capsys.readouterr().err
    assert err.startswith('error: ') and 'not an observer-eval output folder' in err
    assert err.count('\n') == 1
    assert _tree(thesis) == before


def test_eval_force_keeps_the_users_files_and_replaces_its_own(sub_bag, tmp_path, capsys):
    """Row 1: on a real report folder --force replaces its files only."""
    out = tmp_path / 'report'
    assert _eval(sub_bag, out) == 0
    assert (out / MARKER).is_file() and (out / 'results_bag').is_dir()
    (out / 'notes.md').write_text('my notes')
    (out / 'results_bag' / 'README').write_text('mine too')
    old_json = (out / 'results.json').read_bytes()
    assert _eval(sub_bag, out, '--force', '--no-bag') == 0
    assert (out / 'notes.md').read_text() == 'my notes'
    assert (out / 'results_bag' / 'README').read_text() == 'mine too'
    # its own earlier files are gone (no bag this time), the new ones there
    assert sorted(p.name for p in (out / 'results_bag').iterdir()) == ['README']
    assert (out / 'results.json').read_bytes() == old_json
    capsys.readouterr()
    # a user's file, or a link, under a name observer-eval writes (it did not write it this
    # time: --no-bag): refused, nothing touched, the link's target unchanged
    outside = tmp_path / 'outside'
    outside.write_text('precious')
    for name, make in (('results_bag', lambda p: p.mkdir()),
                       ('states.png', lambda p: p.symlink_to(outside))):
        (out / 'results_bag' / 'README').unlink(missing_ok=True)
        for leftover in ('results_bag', 'states.png'):
            path = out / leftover
            if path.is_symlink() or path.is_file():
                path.unlink()
            elif path.is_dir():
                path.rmdir()
        assert _eval(sub_bag, out, '--force', '--no-bag') == 0
        make(out / name)
        before = _tree(out)
        assert _eval(sub_bag, out, '--force') == 2
        err = capsys.readouterr().err
        assert 'is a link' in err or 'was not written by observer-eval' in err, err
        assert _tree(out) == before and outside.read_text() == 'precious'


def test_eval_force_refuses_a_changed_or_linked_file_and_touches_nothing(
        sub_bag, tmp_path, capsys):
    out = tmp_path / 'report'
    assert _eval(sub_bag, out) == 0
    (out / 'results.txt').write_text('edited by hand for the thesis')
    before = _tree(out)
    assert _eval(sub_bag, out, '--force') == 2
    assert 'was changed after observer-eval wrote it' in capsys.readouterr().err
    assert _tree(out) == before
    # a link in place of one of its files: never followed, never deleted
    outside = tmp_path / 'outside.csv'
    outside.write_text('precious')
    (out / 'results.txt').unlink()
    (out / 'results.csv').unlink()
    (out / 'results.csv').symlink_to(outside)
    before = _tree(out)
    assert _eval(sub_bag, out, '--force') == 2
    assert 'is now a link' in capsys.readouterr().err
    assert _tree(out) == before and outside.read_text() == 'precious'
    # the output folder itself a link: refused, the target untouched
    target = tmp_path / 'target'
    target.mkdir()
    (target / 'x').write_text('x')
    link = tmp_path / 'link'
    link.symlink_to(target)
    assert _eval(sub_bag, link, '--force') == 2
    assert 'is a link' in capsys.readouterr().err
    assert _tree(target) == {'x': b'x'}


def test_eval_refusal_is_before_the_evaluation(sub_bag, tmp_path, capsys):
    """An unusable --out is refused before the bag is read: no folder, no trace."""
    assert _eval(tmp_path / 'missing_bag', tmp_path / 'o') == 2
    assert not (tmp_path / 'o').exists()
    capsys.readouterr()
    assert bag_file(sub_bag).exists()


def _recover_cli(*bags):
    return subprocess.run([sys.executable, '-m', 'observer_ros.bag.recover',
                           *map(str, bags)], capture_output=True, text=True, timeout=120)


@pytest.mark.ros
def test_recover_never_writes_through_a_linked_mcap(sub_bag, tmp_path):
    """Row 2: a .mcap that is a link to a file outside the bag: refused, the file unchanged."""
    outside = tmp_path / 'elsewhere' / 'big.mcap'
    outside.parent.mkdir()
    data = bag_file(sub_bag).read_bytes()
    outside.write_bytes(data[:len(data) // 2] + os.urandom(400_000))   # an unclosed look
    before = outside.read_bytes()
    bag = tmp_path / 'bag'
    bag.mkdir()
    (bag / 'bag_0.mcap').symlink_to(outside)
    (bag / '.disk_reserve').write_bytes(b'\0' * 16)
    done = _recover_cli(bag)
    assert done.returncode == 2
    assert done.stderr.startswith('error: ') and 'is a link' in done.stderr
    assert 'Traceback' not in done.stderr
    assert outside.read_bytes() == before
    # nothing in the bag touched either (the refusal comes before the first write)
    assert sorted(p.name for p in bag.iterdir()) == ['.disk_reserve', 'bag_0.mcap']
    with pytest.raises(BagRecoveryError, match='is a link'):
        recover_bag(bag)


@pytest.mark.ros
@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_recover_leaves_an_intact_bag_alone(tmp_path, storage):
    """Row 2: an intact bag: neither its storage nor its metadata.yaml is rewritten."""
    vehicle = load_vehicle(CONFIG / 'submarine.yaml')
    bag = write_bag(tmp_path / 'bag', simulate(vehicle, steps=20)['messages'],
                    namespace='/sub1', storage=storage)
    stats = {p.name: (p.stat().st_mtime_ns, p.read_bytes()) for p in bag.iterdir()}
    done = _recover_cli(bag)
    assert done.returncode == 0, done.stderr
    assert 'nothing changed' in done.stdout
    assert {p.name: (p.stat().st_mtime_ns, p.read_bytes()) for p in bag.iterdir()} == stats
    report = recover_bag(bag)
    assert report['untouched'] and not report['repaired']
    assert report['total'] == sum(report['messages'].values()) > 0


@pytest.mark.ros
@pytest.mark.parametrize('params, message', [
    (['disk_reserve:=1000000000000000'], 'is not less than the free space'),
    (['flush_period:=0.0'], 'flush_period must be > 0 s'),
    (['flush_period:=-1.0'], 'flush_period must be > 0 s'),
    (["extra_topics:=['/foo:nope_msgs/msg/Nope']"], 'unknown message type nope_msgs/msg/Nope'),
    (["extra_topics:=['no_type_here']"], 'is not "name:pkg/msg/Type"'),
    (["extra_topics:=['/bad topic:std_msgs/msg/Bool']"],
     "topic '/bad topic': topic name must not contain characters other than"),
    (['queue_depth:=0'], 'queue_depth must be >= 1'),
])
def test_recorder_refusals_leave_no_bag_folder(tmp_path, params, message):
    """Row 3: the recorder refuses up front: status 2, one error line, no folder made."""
    bag = tmp_path / 'runs' / 'bag'
    proc = Proc('recorder', CONFIG / 'submarine.yaml', f'output:={bag}', 'use_sim_time:=false',
                *params, log_dir=tmp_path)
    try:
        proc.popen.wait(timeout=120)
    finally:
        code = proc.stop()
    out = proc.output()
    assert code == 2, out
    assert message in out and 'Traceback' not in out, out
    errors = [line for line in out.splitlines() if line.startswith('error:')]
    assert len(errors) == 1 and errors[0].startswith('error: recorder:'), out
    assert not bag.exists() and not bag.parent.exists()


@pytest.mark.ros
def test_observer_run_never_overwrites_logs_and_checks_every_output_first(tmp_path, capsys):
    """Row 4: existing logs, <bag>_slow_poles.yaml, <bag>_eval: refused before any process."""
    bag = tmp_path / 'runs' / 'dive'
    logs = tmp_path / 'runs' / 'dive_logs'
    logs.mkdir(parents=True)
    (logs / 'observer_node.log').write_text('the log of an earlier run')
    vehicle = str(CONFIG / 'submarine.yaml')
    assert run_main([vehicle, '--out', str(bag)]) == 2
    assert f'{logs / "observer_node.log"} exists' in capsys.readouterr().err
    assert _tree(tmp_path / 'runs') == {'dive_logs': 'dir',
                                        'dive_logs/observer_node.log':
                                        b'the log of an earlier run'}
    for name in ('dive_eval', 'dive_slow_poles.yaml'):
        other = tmp_path / name / 'runs'
        other.mkdir(parents=True)
        (other / name).write_text('mine')
        assert run_main([vehicle, '--out', str(other / 'dive'), '--evaluate']) == 2
        err = capsys.readouterr().err
        assert err.startswith('error: ') and f'{other / name} exists' in err
        assert _tree(other) == {name: b'mine'}      # no bag, no logs: nothing started
    # without --evaluate, an existing <bag>_eval does not matter to the check
    check_outputs(run_closed_loop._planned_outputs(tmp_path / 'dive_eval' / 'runs' / 'dive',
                                                   False))


def test_observer_run_limit_and_check_include_the_overrides(tmp_path, capsys):
    """Row 4: -p simulator.duration:=5000.0 gets the limit of a 5000 s run; bad -p up front."""
    vehicle = load_vehicle(CONFIG / 'submarine.yaml')
    steps = round(5000.0 / vehicle.sample_time)
    assert run_limit(CONFIG / 'submarine.yaml', ['simulator.duration:=5000.0']) == \
        pytest.approx(60.0 + 0.02 * steps)
    own = 60.0 + 0.02 * round(vehicle.simulator.duration / vehicle.sample_time)
    assert run_limit(CONFIG / 'submarine.yaml') == pytest.approx(own)
    assert run_limit(CONFIG / 'submarine.yaml', ['simulator.duration:=1.0']) == \
        pytest.approx(own)      # never shorter than the file's own limit
    bag = tmp_path / 'runs' / 'dive'
    assert run_main([str(CONFIG / 'submarine.yaml'), '--out', str(bag),
                     '-p', 'simulator.duration:=-5.0']) == 2
    err = capsys.readouterr().err
    assert err.startswith('error: ') and 'simulator.duration' in err
    assert not (tmp_path / 'runs').exists()


@pytest.mark.parametrize('namespace, words', [
    ('/véhicule_1', ["'/véhicule_1'", "(character 3, 'é')"]),
    ('/1st', ['must not have a token that starts with a number']),
    ('/a//b', ["repeated '/'"]),
])
def test_observer_run_refuses_a_namespace_ros_refuses_before_anything_starts(
        tmp_path, capsys, namespace, words):
    bag = tmp_path / 'runs' / 'dive'
    assert run_main([str(CONFIG / 'submarine.yaml'), '--out', str(bag),
                     '--namespace', namespace]) == 2
    err = capsys.readouterr().err
    assert err.startswith('error: --namespace ') and err.count('\n') == 1, err
    assert all(w in err for w in words), err
    assert not (tmp_path / 'runs').exists()        # no bag, no logs: nothing started


@pytest.mark.ros
def test_observer_run_replaces_its_own_logs_of_a_run_that_left_no_bag(tmp_path):
    """A run whose recorder refused to start leaves logs; the rerun is not blocked by them."""
    from ros_helpers import domain_env
    bag = tmp_path / 'runs' / 'dive'
    logs = tmp_path / 'runs' / 'dive_logs'
    vehicle = CONFIG / 'submarine.yaml'
    with domain_env(), pytest.raises(ObserverError, match='recorder exited with code 2'):
        run_closed_loop.run_closed_loop(vehicle, bag, overrides=['queue_depth:=0'],
                                        timeout=120.0, quiet=True)
    assert not bag.exists() and (logs / 'recorder.log').exists() and (logs / MARKER).exists()
    assert 'queue_depth must be >= 1' in (logs / 'recorder.log').read_text()
    # a user's file next to them is kept; the rerun's check passes
    (logs / 'notes.txt').write_text('mine')
    run_closed_loop.check_logs(logs, bag)
    with domain_env():
        run_closed_loop.run_closed_loop(vehicle, bag, timeout=300.0, quiet=True,
                                        overrides=['simulator.duration:=1.0'])
    assert bag.exists() and (logs / 'notes.txt').read_text() == 'mine'
    assert 'queue_depth' not in (logs / 'recorder.log').read_text()
    # now the logs belong to a run with a bag: refused
    with pytest.raises(ObserverError, match='_logs/plant_simulator.log exists'):
        run_closed_loop.check_logs(logs, bag)
    # a log changed by hand is not replaced either (the bag gone)
    import shutil
    shutil.rmtree(bag)
    with open(logs / 'observer_node.log', 'a') as f:
        f.write('my note\n')
    with pytest.raises(ObserverError, match='observer_node.log was changed after observer-run'):
        run_closed_loop.check_logs(logs, bag)
