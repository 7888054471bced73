# observer_ros.bag.bag_checks: a bag folder checked before anything reads or repairs it.
"""
A bag folder checked before it is opened: regular files, no writer, truthful metadata.

- **Regular files**: ``metadata.yaml`` and the storage file are opened only when they are
  regular files (a FIFO named ``x.mcap`` would block the reader forever); ``metadata.yaml``
  is at most :data:`MAX_METADATA_BYTES` and has no YAML anchor or alias (rosbags' parser
  expands aliases: a "billion laughs" file would take every byte of memory).
- **A bag being recorded**: the recorder (:mod:`observer_ros.nodes.recorder`) holds an
  exclusive ``flock`` on ``BAG/.recording.lock`` (holding its process id) from the moment
  the bag exists until it is closed; a killed recorder's lock goes with its process.
  :func:`recording_holder` says who holds it; recovery and evaluation refuse such a bag.
  A bag another program records (``ros2 bag record``) has no such lock:
  :func:`still_growing` watches its storage file for a moment when it changed in the last
  :data:`RECENT` s.
- **Metadata that lies**: ``metadata.yaml`` is a summary of the storage file. When it
  disagrees (message counts, topics, types, time span), :func:`metadata_disagreement`
  names the differences; when it names another storage (``storage_identifier``) or other
  files (``relative_file_paths``) than the folder's one storage file,
  :func:`metadata_storage_disagreement` does. The storage file is the truth, and the bag
  is read from it.

"""

import fcntl
import json
import os
from pathlib import Path
import stat
import time

import yaml

from .errors import BagToolError
from .mcap_records import MAGIC as MCAP_MAGIC

__all__ = ['LOCK_NAME', 'MAX_METADATA_BYTES', 'RECENT', 'check_regular', 'check_metadata_file',
           'hold_recording_lock', 'recording_holder', 'still_growing',
           'metadata_disagreement', 'metadata_storage_disagreement', 'storage_kind']

LOCK_NAME = '.recording.lock'
# a rosbag2 metadata.yaml is a few kB per hundred topics
MAX_METADATA_BYTES = 16 << 20
# s: a storage file changed this recently, in a bag without the recorder's lock, is watched
RECENT = 5.0
# s: how long it is watched for growth (more than the recorder's flush period, 1 s)
WATCH = 2.0
# the first bytes of each storage rosbag2 writes
_MAGIC = {MCAP_MAGIC: 'mcap', b'SQLite format 3\x00': 'sqlite3'}


def _kind(mode):
    for test, name in ((stat.S_ISFIFO, 'a FIFO (named pipe)'), (stat.S_ISDIR, 'a folder'),
                       (stat.S_ISCHR, 'a character device'), (stat.S_ISBLK, 'a block device'),
                       (stat.S_ISSOCK, 'a socket')):
        if test(mode):
            return name
    return 'not a regular file'


def check_regular(path, error=BagToolError):
    """Refuse, without opening it, a path that exists and is not a regular file."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        return
    except OSError as err:
        raise error(f'{path}: cannot read: {err.strerror or err}') from None
    if not stat.S_ISREG(st.st_mode):
        raise error(f'{path} is {_kind(st.st_mode)}, not a bag file; not opened')


def check_metadata_file(path, error=BagToolError):
    """Refuse a metadata.yaml that is not a regular file, too big, or has anchors/aliases."""
    check_regular(path, error)
    size = os.stat(path).st_size
    if size > MAX_METADATA_BYTES:
        raise error(f'{path}: {size} bytes; a metadata.yaml of more than '
                    f'{MAX_METADATA_BYTES} bytes is not read (MAX_METADATA_BYTES)')
    data = Path(path).read_bytes()
    if b'&' not in data:        # no anchor, hence no alias
        return
    try:
        loader = getattr(yaml, 'CSafeLoader', yaml.SafeLoader)
        for event in yaml.parse(data, Loader=loader):
            if isinstance(event, yaml.AliasEvent) or getattr(event, 'anchor', None):
                mark = event.start_mark
                raise error(f'{path}: a YAML anchor or alias (line {mark.line + 1}); '
                            'rosbag2 never writes one, and its expansion is not read')
    except yaml.YAMLError as err:
        raise error(f'{path}: not valid YAML: {" ".join(str(err).split())}') from None


def hold_recording_lock(bag):
    """
    Take the recorder's lock on a bag it has just made; return the open file (keep it).

    The lock is released when the file is closed, or when the process dies.
    """
    path = Path(bag) / LOCK_NAME
    fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o644)
    stream = os.fdopen(fd, 'r+')
    try:
        fcntl.flock(stream.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        stream.write(json.dumps({'pid': os.getpid(), 'program': 'observer_ros recorder'})
                     + '\n')
        stream.flush()
    except OSError:
        stream.close()
        path.unlink(missing_ok=True)
        raise
    return stream


def recording_holder(bag):
    """
    Return who records the bag (``the recorder, process 1234``), or None.

    None when there is no lock file, or when nobody holds it (a recorder that was killed:
    the lock file stays, the lock does not).
    """
    path = Path(bag) / LOCK_NAME
    try:
        if not stat.S_ISREG(os.lstat(path).st_mode):
            return None
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_NOFOLLOW)
    except OSError:
        return None
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            try:
                pid = json.loads(os.read(fd, 4096).decode()).get('pid')
            except (ValueError, AttributeError, OSError):
                pid = None
            return f'the recorder (process {pid})' if pid else 'a recorder'
        return None
    finally:
        os.close(fd)


def still_growing(path, recent=RECENT, watch=WATCH):
    """
    Return how a storage file changed while watched, or None when it is at rest.

    A file not modified in the last ``recent`` s is at rest at once; otherwise its size and
    modification time are watched for ``watch`` s.
    """
    try:
        st = os.stat(path)
    except OSError:
        return None
    if time.time() - st.st_mtime > recent:
        return None
    end = time.monotonic() + watch
    while time.monotonic() < end:
        time.sleep(0.2)
        now = os.stat(path)
        if (now.st_size, now.st_mtime_ns) != (st.st_size, st.st_mtime_ns):
            return (f'{path} changed while watched ({st.st_size} -> {now.st_size} bytes in '
                    f'under {watch:g} s)')
    return None


def metadata_disagreement(directory_reader):
    """
    Return what a bag's metadata.yaml says that its storage file does not ([] if nothing).

    Parameters
    ----------
    directory_reader : rosbags.rosbag2.reader.DirectoryReader
        The open reader of a bag folder (its metadata, and its one storage, each with its
        own connections and counts).

    """
    storages = getattr(directory_reader, 'storages', None) or []
    if len(storages) != 1:
        return []
    storage = storages[0]
    said = {(c.topic, c.msgtype): int(c.msgcount or 0) for c in directory_reader.connections}
    held = {}
    for c in storage.connections:
        held[(c.topic, c.msgtype)] = held.get((c.topic, c.msgtype), 0) + int(c.msgcount or 0)
    out = []
    total_said = int(directory_reader.metadata.message_count or 0)
    total_held = int(storage.metadata.message_count or 0)
    if total_said != total_held:
        out.append(f'message_count {total_said}, the storage holds {total_held}')
    for key in sorted(set(said) | set(held)):
        topic, msgtype = key
        if key not in held:
            if said[key]:
                out.append(f'{topic} ({msgtype}): {said[key]} messages, not in the storage')
        elif key not in said:
            if held[key]:
                out.append(f'{topic} ({msgtype}): not listed, the storage holds {held[key]}')
        elif said[key] != held[key]:
            out.append(f'{topic}: {said[key]} messages, the storage holds {held[key]}')
    if total_said and total_held and (
            directory_reader.metadata.start_time != storage.metadata.start_time or
            directory_reader.metadata.end_time != storage.metadata.end_time):
        out.append("its time span differs from the storage's")
    return out


def storage_kind(path):
    """Return what a storage file's first bytes say it is: ``mcap``, ``sqlite3`` or None."""
    try:
        with open(path, 'rb') as f:
            head = f.read(16)
    except OSError:
        return None
    return next((kind for magic, kind in _MAGIC.items() if head.startswith(magic)), None)


def metadata_storage_disagreement(metadata_path, file):
    """
    Return how a metadata.yaml misnames a bag folder's one storage file ([] if it does not).

    What rosbags opens is what ``metadata.yaml`` says: another ``storage_identifier`` than
    the file's own first bytes, or ``relative_file_paths`` that are not the file, and the
    bag does not open (``file is not a database``, ``Some database files are missing``)
    though its storage is whole.

    Parameters
    ----------
    metadata_path : Path
        The folder's ``metadata.yaml``, checked by :func:`check_metadata_file`.
    file : Path
        The folder's one storage file (``.mcap`` or ``.db3``).

    """
    try:
        loader = getattr(yaml, 'CSafeLoader', yaml.SafeLoader)
        info = yaml.load(Path(metadata_path).read_bytes(), Loader=loader)
        info = info['rosbag2_bagfile_information']
        said_kind = info.get('storage_identifier')
        said_files = [str(p) for p in info.get('relative_file_paths') or []]
    except Exception:   # noqa: BLE001 - unreadable: the reader says why
        return []
    out = []
    kind = storage_kind(file)
    if kind and said_kind != kind:
        out.append(f'storage_identifier {said_kind}, {file.name} is an {kind} file')
    if said_files != [file.name]:
        out.append(f'relative_file_paths {said_files}, the folder holds {file.name}')
    return out
