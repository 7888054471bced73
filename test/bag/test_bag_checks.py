# A bag folder checked before it is read or repaired: links, writers, lies, odd files.
"""Recovery and evaluation against hard links, a writer at work, lying metadata, FIFOs."""

import os
from pathlib import Path
import shutil
import sqlite3
import threading
import time

from bag_synth import at_rest, bag_file, simulate, write_bag
from observer_ros.bag.bag_checks import hold_recording_lock, MAX_METADATA_BYTES
from observer_ros.bag.errors import BagRecoveryError, BagToolError
from observer_ros.bag.reader import BagReader
from observer_ros.bag.recover import main as recover_main, recover_bag
from observer_ros.evaluation.evaluate import main as eval_main
from observer_ros.vehicle import load_vehicle
import pytest
import yaml

REPO = Path(__file__).resolve().parents[2]
CONFIG = REPO / 'config'


@pytest.fixture(scope='module')
def vehicle():
    return load_vehicle(CONFIG / 'submarine.yaml')


def _bag(path, vehicle, storage='mcap', steps=200):
    return at_rest(write_bag(path, simulate(vehicle, steps=steps)['messages'],
                             namespace='/sub1', storage=storage))


def _cut(bag):
    """Make a bag look like a recording killed mid-write: no metadata, the mcap's end cut."""
    (bag / 'metadata.yaml').unlink()
    file = bag_file(bag)
    data = file.read_bytes()
    file.write_bytes(data[:len(data) - 100])   # the footer and part of the summary
    return at_rest(file)


def _tree(root):
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob('*'))
            if p.is_file()}


def test_a_hard_linked_backup_keeps_every_byte(tmp_path, vehicle, capsys):
    bag = _bag(tmp_path / 'bag', vehicle)
    _cut(bag)
    backup = tmp_path / 'bag_backup'         # cp -al bag bag_backup
    backup.mkdir()
    for p in bag.iterdir():
        os.link(p, backup / p.name)
    saved = _tree(backup)
    assert recover_main([str(bag)]) == 0
    out = capsys.readouterr().out
    assert 'had 2 hard links: copied first, the copy recovered; the other names keep the ' \
           'original bytes' in out
    assert _tree(backup) == saved                       # 356,605 -> 337,587 bytes before
    assert bag_file(bag).stat().st_nlink == 1 and (bag / 'metadata.yaml').exists()
    with BagReader(bag) as opened:
        assert opened.info.message_count > 0 and not opened.info.warnings[1:]


def test_a_hard_linked_sqlite3_database_is_copied_before_it_is_written(tmp_path, vehicle):
    bag = _bag(tmp_path / 'bag', vehicle, storage='sqlite3')
    (bag / 'metadata.yaml').unlink()                    # left unclosed: recovery writes
    db = bag_file(bag)
    other = tmp_path / 'other.db3'
    os.link(db, other)
    saved = other.read_bytes()
    report = recover_bag(bag)
    assert report['copied'] == [(db.name, 2)]
    assert other.read_bytes() == saved
    with sqlite3.connect(db) as con:                    # the copy got its metadata row
        assert con.execute('SELECT count(*) FROM metadata').fetchone()[0] == 1


def test_a_bag_another_program_still_writes_is_refused(tmp_path, vehicle):
    bag = _bag(tmp_path / 'bag', vehicle)
    file = _cut(bag)
    stop = threading.Event()

    def writer():           # a recorder without our lock (ros2 bag record) appending
        with open(file, 'ab') as f:
            while not stop.wait(0.05):
                f.write(b'\0' * 64)
                f.flush()
    thread = threading.Thread(target=writer)
    thread.start()
    try:
        time.sleep(0.2)
        with pytest.raises(BagRecoveryError, match='is still being written .* another '
                           'program records it\\); nothing changed'):
            recover_bag(bag)
        with pytest.raises(BagToolError, match='still being written by another program'):
            BagReader(bag).load()
    finally:
        stop.set()
        thread.join()
    assert sorted(p.name for p in bag.iterdir()) == [file.name]


def test_our_own_lock_held_refuses_recovery_and_evaluation(tmp_path, vehicle):
    bag = _bag(tmp_path / 'bag', vehicle)
    _cut(bag)
    (bag / '.disk_reserve').write_bytes(b'\0' * 1024)
    lock = hold_recording_lock(bag)
    try:
        saved = _tree(bag)
        with pytest.raises(BagRecoveryError, match=f'the recorder \\(process {os.getpid()}\\)'):
            recover_bag(bag)
        assert _tree(bag) == saved                      # the reserve too
        with pytest.raises(BagToolError, match='is being recorded'):
            BagReader(bag_file(bag)).load()             # the file alone as well
    finally:
        lock.close()
    recover_bag(bag)
    assert not (bag / '.recording.lock').exists() and not (bag / '.disk_reserve').exists()


def _lie(bag):
    meta = yaml.safe_load((bag / 'metadata.yaml').read_text())
    info = meta['rosbag2_bagfile_information']
    info['message_count'] = 0
    for topic in info['topics_with_message_count']:
        topic['message_count'] = 0
    (bag / 'metadata.yaml').write_text(yaml.safe_dump(meta))


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_metadata_that_lies_is_named_and_the_storage_is_read(tmp_path, vehicle, capsys,
                                                             storage):
    bag = _bag(tmp_path / 'bag', vehicle, storage=storage)
    with BagReader(bag) as opened:
        truth = opened.info.message_count
    _lie(bag)
    with BagReader(bag) as opened:
        assert opened.info.message_count == truth
        note = [w for w in opened.info.warnings if 'disagrees' in w]
        assert note and f'message_count 0, the storage holds {truth}' in note[0]
        assert ': 0 messages, the storage holds 201' in note[0] and 'more; the bag is read ' \
            f'from {bag_file(bag).name}, its storage' in note[0]
    code = eval_main([str(bag), '--vehicle', str(CONFIG / 'submarine.yaml'), '--namespace',
                      '/sub1', '--out', str(tmp_path / 'eval'), '--no-plots'])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    assert 'metadata.yaml disagrees with' in captured.err + captured.out
    # recovery rewrites the metadata from the storage; then nothing disagrees
    report = recover_bag(bag)
    assert report['metadata_disagreed'] and not report['untouched']
    with BagReader(bag) as opened:
        assert not [w for w in opened.info.warnings if 'disagrees' in w]
    assert recover_bag(bag)['untouched']


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
@pytest.mark.parametrize('lie', ['storage_identifier', 'relative_file_paths'])
def test_metadata_naming_another_storage_or_file_is_named_and_the_storage_is_read(
        tmp_path, vehicle, capsys, storage, lie):
    bag = _bag(tmp_path / 'bag', vehicle, storage=storage)
    file = bag_file(bag)
    with BagReader(bag) as opened:
        truth = opened.info.message_count
    meta = yaml.safe_load((bag / 'metadata.yaml').read_text())
    info = meta['rosbag2_bagfile_information']
    other = {'mcap': 'sqlite3', 'sqlite3': 'mcap'}[storage]
    if lie == 'storage_identifier':
        info['storage_identifier'] = other
        said = f'storage_identifier {other}, {file.name} is an {storage} file'
    else:
        info['relative_file_paths'] = ['other' + file.suffix]
        for entry in info.get('files') or []:
            entry['path'] = 'other' + file.suffix
        said = f"relative_file_paths ['other{file.suffix}'], the folder holds {file.name}"
    (bag / 'metadata.yaml').write_text(yaml.safe_dump(meta))
    with BagReader(bag) as opened:
        assert opened.info.message_count == truth
        note = [w for w in opened.info.warnings if 'disagrees' in w]
        assert note and said in note[0] and f'the bag is read from {file.name}' in note[0]
    code = eval_main([str(bag), '--vehicle', str(CONFIG / 'submarine.yaml'), '--namespace',
                      '/sub1', '--out', str(tmp_path / 'eval'), '--no-plots', '--no-bag'])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    assert said in captured.err
    # recovery names it and rewrites metadata.yaml from the storage; then it agrees
    report = recover_bag(bag)
    assert report['metadata_disagreed'] == [said] and not report['untouched']
    with BagReader(bag) as opened:
        assert not [w for w in opened.info.warnings if 'disagrees' in w]
    assert recover_bag(bag)['untouched']


@pytest.mark.parametrize('which', ['metadata.yaml', 'storage'])
def test_a_fifo_in_a_bag_is_refused_not_waited_on(tmp_path, vehicle, which):
    bag = _bag(tmp_path / 'bag', vehicle)
    target = bag / 'metadata.yaml' if which == 'metadata.yaml' else bag_file(bag)
    target.unlink()
    os.mkfifo(target)
    with pytest.raises(BagToolError, match='is a FIFO \\(named pipe\\), not a bag file'):
        BagReader(bag).load()
    with pytest.raises(BagRecoveryError, match='is a FIFO'):
        recover_bag(bag)


def test_metadata_with_an_alias_bomb_or_too_big_is_refused(tmp_path, vehicle):
    bag = _bag(tmp_path / 'bag', vehicle)
    lines = ['a: &a ["lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol"]']
    for i in range(1, 10):
        name, prev = chr(97 + i), chr(96 + i)
        lines.append(f'{name}: &{name} [' + ', '.join([f'*{prev}'] * 9) + ']')
    (bag / 'metadata.yaml').write_text('\n'.join(lines) + '\n')
    with pytest.raises(BagToolError, match='a YAML anchor or alias \\(line 1\\)'):
        BagReader(bag).load()
    with open(bag / 'metadata.yaml', 'w') as f:
        f.truncate(MAX_METADATA_BYTES + 1)
    with pytest.raises(BagToolError, match='MAX_METADATA_BYTES'):
        BagReader(bag).load()


def test_a_half_written_bag_points_to_the_projects_recovery(tmp_path, vehicle, capsys):
    bag = _bag(tmp_path / 'bag', vehicle)
    _cut(bag)
    code = eval_main([str(bag), '--vehicle', str(CONFIG / 'submarine.yaml'), '--namespace',
                      '/sub1', '--out', str(tmp_path / 'eval'), '--no-plots'])
    err = capsys.readouterr().err
    assert code == 2
    assert f'observer-bag-recover {bag}' in err and 'reindex' not in err, err
    assert 'mcap recover' not in err
    shutil.rmtree(tmp_path / 'eval', ignore_errors=True)


def test_recovery_cuts_before_a_chunk_whose_crc_fails(tmp_path):
    """A byte changed in an unclosed bag's 5th chunk: recovery keeps chunks 1-4, and opens."""
    from observer_ros.bag.mcap_repair import scan_mcap
    bag = shutil.copytree(REPO / 'bags' / 'samples' / 'submarine', tmp_path / 'bag')
    file = bag_file(bag)
    chunks = scan_mcap(file)['chunks']
    assert len(chunks) >= 6
    (bag / 'metadata.yaml').unlink()
    data = bytearray(file.read_bytes()[:chunks[-1]['offset']])     # the end not written
    flip = chunks[4]['offset'] + chunks[4]['length'] - 40
    data[flip] ^= 0xFF
    file.write_bytes(bytes(data))
    report = recover_bag(at_rest(bag))
    assert report['chunks'] == 4 and report['repaired']
    with BagReader(bag) as opened:
        kept = opened.info.message_count
    assert 0 < kept == report['total'] < 3637


def test_a_second_recovery_of_the_same_bag_is_refused(tmp_path, vehicle):
    import fcntl
    bag = _bag(tmp_path / 'bag', vehicle)
    _cut(bag)
    saved = _tree(bag)
    fd = os.open(bag, os.O_RDONLY | os.O_DIRECTORY)    # what the first recovery holds
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        with pytest.raises(BagRecoveryError, match='is being recovered by another process'):
            recover_bag(bag)
        assert _tree(bag) == saved
    finally:
        os.close(fd)
    assert recover_bag(bag)['repaired']
