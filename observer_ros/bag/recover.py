# observer_ros.bag.recover: make a bag that was not closed (SIGKILL, disk full) readable again.
"""
Recover a rosbag2 bag whose writer died before closing it: ``observer-bag-recover BAG``.

A writer that is killed leaves no ``metadata.yaml``; an mcap file also lacks its summary
and footer, and may end in the middle of a record. The recorder (observer_ros.nodes.
recorder) flushes every ``flush_period`` (mcap: closes the pending chunk; sqlite3:
commits), so everything up to the last flush is complete on disk. Recovery keeps exactly
that:

- **mcap**: the records are scanned from the start; the file is cut after the last
  complete chunk (a chunk cut short, or damaged, and whatever follows it are dropped),
  the message indexes of that chunk are rebuilt, and a summary (schemas, channels, chunk
  indexes, statistics) and the footer are appended. Earlier bytes are not rewritten, so
  recovery needs little free space.
- **sqlite3**: opening the database rolls back the transaction that was open (SQLite's
  journal), leaving what was committed.

The recorder's ``.disk_reserve`` file is deleted first, so that this works on the disk
that filled up. Then ``metadata.yaml`` (rosbag2 version 9) is written from what the
storage holds, and the bag is opened with rosbags' AnyReader to check it. A bag that is
already intact is left as it is. The original mcap, when it is cut, is not kept: copy the
bag first to keep the damaged bytes.

Refused before anything is touched: a bag being recorded (the recorder holds its lock,
``.recording.lock``; or, without one, its storage file still changes: another program
records it), a file of the bag that is a link, a FIFO or a device. A storage file with
other hard links (``cp -al bag backup``) is copied first, inside the bag, and the copy is
repaired: the other names keep every byte, and the report says so. A ``metadata.yaml`` that
disagrees with the storage (message counts 0 on a full mcap) is rewritten from it.

"""

import argparse
import contextlib
import fcntl
import os
from pathlib import Path
import shutil
import sqlite3
import sys

import yaml

from .bag_checks import (check_regular, LOCK_NAME, metadata_disagreement,
                         metadata_storage_disagreement, recording_holder, still_growing)
from .errors import BagRecoveryError
from .mcap_repair import channel_counts, repair_mcap, scan_mcap, time_range
from ..core.errors import error_text, quiet_on_closed_pipe

__all__ = ['BagRecoveryError', 'recover_bag', 'main']

# the files next to a storage file that its writer or SQLite may leave, and recovery touches
_SIDE_FILES = ('-journal', '-wal', '-shm')


# ---------------------------------------------------------------------------- metadata
def _rihs01(msgtype):
    """Return the type hash of msgtype from the Jazzy typestore ('' when unknown)."""
    from rosbags.typesys import get_typestore, Stores
    try:
        return get_typestore(Stores.ROS2_JAZZY).hash_rihs01(msgtype)
    except Exception:   # noqa: BLE001 - a type the store does not know: no hash
        return ''


def _metadata(storage, file_name, topics, t_min, t_max):
    """
    Return the rosbag2 (version 9) metadata dict, as rosbags' Writer.close writes it.

    ``topics`` is a list of (name, type, serialization_format, qos_text, hash, count).
    """
    count = sum(t[5] for t in topics)
    start = t_min if count else 0
    duration = max(0, t_max - t_min) if count else 0
    return {'rosbag2_bagfile_information': {
        'version': 9,
        'storage_identifier': storage,
        'relative_file_paths': [file_name],
        'duration': {'nanoseconds': duration},
        'starting_time': {'nanoseconds_since_epoch': start},
        'message_count': count,
        'topics_with_message_count': [
            {'topic_metadata': {
                'name': name, 'type': msgtype, 'serialization_format': fmt,
                'offered_qos_profiles': yaml.safe_load(qos) if qos else [],
                'type_description_hash': digest or _rihs01(msgtype)},
             'message_count': n}
            for name, msgtype, fmt, qos, digest, n in topics],
        'compression_format': '',
        'compression_mode': '',
        'files': [{'path': file_name, 'starting_time': {'nanoseconds_since_epoch': start},
                   'duration': {'nanoseconds': duration}, 'message_count': count}],
        'custom_data': {'recovered_by': 'observer-bag-recover'},
        'ros_distro': 'rosbags',
    }}


def _write_metadata(bag, metadata):
    """Write metadata.yaml (through a temporary file), unless it already says the same."""
    text = yaml.safe_dump(metadata, default_flow_style=False, sort_keys=False)
    target = bag / 'metadata.yaml'
    try:
        if target.is_file() and target.read_text() == text:
            return
    except (OSError, UnicodeDecodeError):
        pass
    tmp = bag / 'metadata.yaml.tmp'
    try:
        tmp.unlink(missing_ok=True)         # never written through (another link to it)
        with open(tmp, 'x') as f:
            f.write(text)
        tmp.replace(target)
    except OSError as err:
        tmp.unlink(missing_ok=True)
        raise BagRecoveryError(f'{bag}: cannot write metadata.yaml: {err}') from None


def _mcap_topics(scan):
    counts = channel_counts(scan)
    schema_names = {sid: s[1] for sid, s in scan['schemas'].items()}
    return [(ch['topic'], schema_names.get(ch['schema_id'], ''), ch['encoding'],
             ch['metadata'].get('offered_qos_profiles', ''), '', counts.get(cid, 0))
            for cid, ch in sorted(scan['channels'].items())]


def _recover_mcap(bag, file):
    scan = scan_mcap(file)
    t_min, t_max = time_range(scan)
    metadata = _metadata('mcap', file.name, _mcap_topics(scan), t_min, t_max)
    repaired = not scan['intact']
    if repaired:
        inner = yaml.safe_dump(metadata['rosbag2_bagfile_information'],
                               default_flow_style=False, sort_keys=False).strip()
        repair_mcap(file, scan, inner)
    _write_metadata(bag, metadata)
    return {'storage': 'mcap', 'file': str(file), 'repaired': repaired,
            'dropped_bytes': scan['size'] - scan['cut'] if repaired else 0,
            'chunks': len(scan['chunks']),
            'messages': {t[0]: t[5] for t in _mcap_topics(scan)}}


def _recover_sqlite3(bag, file):
    try:
        # a read-write connection: SQLite rolls back the transaction left open (the hot
        # journal) before the first read, leaving what was committed
        con = sqlite3.connect(str(file))
        try:
            topics = con.execute(
                'SELECT topics.id, name, type, serialization_format, offered_qos_profiles, '
                'type_description_hash, count(messages.id) FROM topics LEFT JOIN messages '
                'ON topics.id == messages.topic_id GROUP BY topics.id ORDER BY topics.id'
            ).fetchall()
            t_min, t_max = con.execute(
                'SELECT min(timestamp), max(timestamp) FROM messages').fetchone()
            metadata = _metadata('sqlite3', file.name,
                                 [row[1:] for row in topics], t_min or 0, t_max or 0)
            try:
                if not con.execute('SELECT count(*) FROM metadata').fetchone()[0]:
                    inner = yaml.safe_dump(metadata['rosbag2_bagfile_information'],
                                           default_flow_style=False, sort_keys=False)
                    con.execute('INSERT INTO metadata(metadata_version, metadata) '
                                'VALUES(?, ?)', (9, inner.strip()))
                    con.commit()
            except sqlite3.Error:
                con.rollback()           # optional (ros2 bag reads it); not needed here
        finally:
            con.close()
    except sqlite3.Error as err:
        raise BagRecoveryError(f'{file}: cannot read the database: {err}') from None
    _write_metadata(bag, metadata)
    return {'storage': 'sqlite3', 'file': str(file), 'repaired': False, 'dropped_bytes': 0,
            'messages': {row[1]: row[6] for row in topics}}


def _check_opens(bag):
    """Open the bag with AnyReader and read every message; return the count."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import get_typestore, Stores
    store = get_typestore(Stores.ROS2_JAZZY)
    try:
        with AnyReader([Path(bag)], default_typestore=store) as reader:
            return sum(1 for _ in reader.messages())
    except Exception as err:   # noqa: BLE001 - any reader failure is a failed recovery
        raise BagRecoveryError(f'{bag}: still does not open after recovery: {err}') from None


def _check_inside(bag, paths):
    """Refuse, before touching anything, a file of the bag that is a link or not a file."""
    for path in paths:
        if path.is_symlink():
            raise BagRecoveryError(f'{path} is a link (to {os.readlink(path)}); refusing to '
                                   'write through it: copy the file into the bag first')
        if path.exists() and path.resolve().parent != bag.resolve():
            raise BagRecoveryError(f'{path} lies outside the bag folder; refusing it')
        check_regular(path, BagRecoveryError)


def _is_intact(bag, file):
    """Return True for a bag its writer closed: metadata.yaml there, storage complete."""
    if not (bag / 'metadata.yaml').is_file() or (bag / '.disk_reserve').exists():
        return False
    if file.suffix == '.mcap':
        try:
            if not scan_mcap(file)['intact']:
                return False
        except BagRecoveryError:
            return False
    # sqlite3: a writer that died leaves its journal (or write-ahead log) next to the file
    elif any(file.with_name(file.name + tail).exists() for tail in ('-journal', '-wal')):
        return False
    return not _metadata_lies(bag, file)


def _metadata_lies(bag, file):
    """Return what metadata.yaml says that the storage does not ([] when it agrees)."""
    from rosbags.rosbag2 import Reader
    misnamed = metadata_storage_disagreement(bag / 'metadata.yaml', file)
    if misnamed:
        return misnamed
    try:
        with Reader(bag) as reader:
            return metadata_disagreement(reader.storage)
    except Exception:   # noqa: BLE001 - unreadable metadata: recovery rewrites it
        return ['it cannot be read']


def _own_copies(bag, file):
    """
    Give each file recovery writes in place a name of its own, if it has other hard links.

    The file is copied beside itself and the copy renamed over it: the other names keep
    the original's bytes. Returns the names copied.
    """
    copied = []
    for path in [file] + [file.with_name(file.name + tail) for tail in _SIDE_FILES]:
        try:
            links = os.lstat(path).st_nlink
        except FileNotFoundError:
            continue
        if links < 2:
            continue
        tmp = path.with_name(path.name + '.recover-copy')
        try:
            tmp.unlink(missing_ok=True)
            with open(path, 'rb') as src, open(tmp, 'xb') as dst:
                shutil.copyfileobj(src, dst, 1 << 20)
                dst.flush()
                os.fsync(dst.fileno())
            shutil.copystat(path, tmp)
            tmp.replace(path)
        except OSError as err:
            tmp.unlink(missing_ok=True)
            raise BagRecoveryError(
                f'{path} has {links} hard links (another name shares its bytes, e.g. a '
                f'cp -al backup); copying it first failed ({err.strerror or err}), and '
                'recovering in place would change the other names too: nothing changed') \
                from None
        copied.append((path.name, links))
    return copied


def _read_counts(bag):
    """Return the message count per topic of a readable bag (empty when unreadable)."""
    from rosbags.rosbag2 import Reader
    try:
        with Reader(bag) as reader:
            return {c.topic: c.msgcount for c in reader.connections}
    except Exception:   # noqa: BLE001 - _check_opens reports an unreadable bag
        return {}


def recover_bag(path):
    """
    Make a bag left open by a dead writer readable; return what was found.

    Parameters
    ----------
    path : path-like
        The bag directory (holding one ``.mcap`` or ``.db3`` file).

    Returns
    -------
    dict
        ``storage``, ``file``, ``repaired`` (the mcap file was cut and completed),
        ``dropped_bytes`` (of an incomplete last record), ``messages`` per topic,
        ``total`` (read back through AnyReader) and ``untouched`` (a bag closed cleanly:
        nothing was written).

    Raises
    ------
    BagRecoveryError
        The path is not a bag directory, one of its files is a link (refused before
        anything is touched), or its storage file cannot be made readable.

    """
    bag = Path(path)
    if not bag.is_dir():
        raise BagRecoveryError(f'{bag}: not a bag directory')
    files = sorted(bag.glob('*.mcap')) + sorted(bag.glob('*.db3'))
    if len(files) != 1:
        raise BagRecoveryError(f'{bag}: expected one .mcap or .db3 file; found '
                               f'{[f.name for f in files] or "none"}')
    file = files[0]
    _check_inside(bag, [file, bag / 'metadata.yaml', bag / 'metadata.yaml.tmp',
                        bag / '.disk_reserve', bag / LOCK_NAME] +
                  [file.with_name(file.name + tail) for tail in _SIDE_FILES])
    with _recovery_lock(bag):       # one recovery of a bag at a time
        return _recover(bag, file)


@contextlib.contextmanager
def _recovery_lock(bag):
    """Hold an exclusive lock on the bag folder while it is recovered; refuse a second one."""
    fd = os.open(bag, os.O_RDONLY | os.O_DIRECTORY)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise BagRecoveryError(f'{bag} is being recovered by another process; nothing '
                                   'changed') from None
        except OSError:         # a file system without locks: recover all the same
            pass
        yield
    finally:
        os.close(fd)


def _recover(bag, file):
    """Recover a bag whose files were checked (recover_bag), under the recovery lock."""
    holder = recording_holder(bag)
    if holder:
        raise BagRecoveryError(f'{bag} is being recorded ({holder} holds {bag / LOCK_NAME}); '
                               'nothing changed: stop the recorder (Ctrl-C), it closes the '
                               'bag itself')
    if _is_intact(bag, file):
        # a bag closed cleanly: nothing is rewritten, not even its metadata.yaml
        return {'storage': file.suffix[1:].replace('db3', 'sqlite3'), 'file': str(file),
                'repaired': False, 'dropped_bytes': 0, 'untouched': True, 'copied': [],
                'messages': _read_counts(bag), 'total': _check_opens(bag)}
    growing = still_growing(file)
    if growing:
        raise BagRecoveryError(f'{bag} is still being written ({growing}, and no '
                               'observer_ros recorder holds it: another program records '
                               'it); nothing changed: recover it once its writer stopped')
    lies = _metadata_lies(bag, file) if (bag / 'metadata.yaml').is_file() else []
    copied = _own_copies(bag, file)
    # the space the recorder kept free for this moment (nodes.recorder, disk_reserve)
    (bag / '.disk_reserve').unlink(missing_ok=True)
    if file.suffix == '.mcap':
        report = _recover_mcap(bag, file)
    else:
        report = _recover_sqlite3(bag, file)
    (bag / LOCK_NAME).unlink(missing_ok=True)      # a killed recorder's (held by nobody)
    report.update(untouched=False, copied=copied, metadata_disagreed=lies)
    report['total'] = _check_opens(bag)
    return report


@quiet_on_closed_pipe
def main(argv=None):
    """Entry point of ``observer-bag-recover``."""
    parser = argparse.ArgumentParser(
        prog='observer-bag-recover',
        description='Make a bag whose writer died (SIGKILL, disk full) readable: cut an '
                    'mcap after its last complete chunk and write its summary, then write '
                    'metadata.yaml from the storage.')
    parser.add_argument('bag', nargs='+', help='bag directory')
    args = parser.parse_args(argv)
    code = 0
    for bag in args.bag:
        try:
            rep = recover_bag(bag)
        except (BagRecoveryError, OSError) as err:
            print(f'error: {error_text(err)}', file=sys.stderr)
            code = 2
            continue
        for name, links in rep.get('copied', ()):
            print(f'{bag}: {name} had {links} hard links: copied first, the copy recovered; '
                  'the other names keep the original bytes')
        if rep.get('metadata_disagreed'):
            print(f'{bag}: metadata.yaml disagreed with the storage '
                  f'({"; ".join(rep["metadata_disagreed"][:3])}): rewritten from it')
        what = (f'cut after chunk {rep["chunks"]} ({rep["dropped_bytes"]} bytes dropped) '
                'and completed' if rep['repaired'] else 'storage intact')
        meta = 'nothing changed' if rep['untouched'] else 'metadata.yaml written'
        print(f'{bag}: {rep["storage"]}, {what}; {meta}; '
              f'{rep["total"]} messages read back')
        for topic, n in rep['messages'].items():
            print(f'  {topic}: {n}')
    return code


if __name__ == '__main__':
    raise SystemExit(main())
