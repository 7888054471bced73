# observer_ros.bag.bag_file: open a ROS 2 bag (mcap or sqlite3) and read its messages.
"""
Open a ROS 2 bag, mcap or sqlite3, and read its raw messages.

A bag is a directory with ``metadata.yaml`` (as written by ``ros2 bag record`` or by
rosbags' Writer) or a single ``.mcap`` / ``.db3`` file. It is read with rosbags'
``AnyReader`` and the ROS 2 Jazzy typestore for bags without type definitions
(STYLE.md §3, §10); an indexed mcap file chunk by chunk (:mod:`.mcap_fast`). Every
problem is a :class:`BagToolError` naming the file.

"""

from dataclasses import dataclass, field
import functools
from pathlib import Path
from typing import Dict, List, Optional, Tuple

from rosbags.highlevel import AnyReader
from rosbags.typesys import get_typestore, Stores

from .bag_checks import (check_metadata_file, check_regular, LOCK_NAME, metadata_disagreement,
                         metadata_storage_disagreement, recording_holder, still_growing)
from .cdr_decode import PAD
from .errors import BagToolError
from .integrity import checksum_note, chunk_crcs
from .mcap_fast import fast_chunks, fast_messages

__all__ = ['jazzy_typestore', 'BagInfo', 'BagReader', 'bag_info']

_STORAGE_SUFFIXES = {'.mcap': 'mcap', '.db3': 'sqlite3'}


@functools.lru_cache(maxsize=1)
def jazzy_typestore():
    """Return the (cached) ROS 2 Jazzy typestore of rosbags."""
    return get_typestore(Stores.ROS2_JAZZY)


@dataclass
class BagInfo:
    """What a bag holds: its file, storage, topics and time span."""

    path: Path                          # as given
    storage_path: Path                  # what was opened (the directory or one file)
    storage: str                        # 'mcap' or 'sqlite3'
    topics: Dict[str, Tuple[str, int]]  # topic -> (message type, message count)
    message_count: int
    start_ns: int
    end_ns: int
    ros_distro: Optional[str] = None
    warnings: List[str] = field(default_factory=list)
    chunk_crcs: Optional[List[int]] = None  # MCAP: each chunk's CRC32 (0: none)

    def describe_topics(self, limit=12):
        """Return the bag's topics as one line: ``/a (Imu, 10 msgs), ...``."""
        items = [f'{name} ({msgtype.rsplit("/", 1)[-1]}, {count} msgs)'
                 for name, (msgtype, count) in sorted(self.topics.items())]
        if not items:
            return 'none'
        more = len(items) - limit
        return ', '.join(items[:limit]) + (f', ... ({more} more)' if more > 0 else '')


def _reason(path, err):
    """Turn a rosbags exception into a short explanation with a hint."""
    text = ' '.join(str(a) for a in getattr(err, 'args', ()) if a) or type(err).__name__
    low = text.lower()
    if 'end magic' in low or 'unexpected end' in low or 'could not read' in low \
            and 'bytes' in low:
        bag = Path(path).parent if Path(path).suffix in _STORAGE_SUFFIXES else Path(path)
        hint = ('the file ends early: a recording that was not closed (killed, or the disk '
                f'filled), or a truncated copy; `observer-bag-recover {bag}` completes it up '
                'to its last complete chunk')
    elif 'file magic' in low:
        hint = 'not an MCAP file'
    elif 'malformed' in low or 'not a database' in low:
        hint = 'the sqlite3 database is truncated or corrupted'
    elif 'checksum mismatch' in low:
        hint = ('the data changed on disk after it was written: its CRC32 does not match; '
                'do not trust this bag')
    elif 'hash mismatch' in low:
        hint = ("the bag's message definitions do not match their hashes (another ROS "
                'release or a modified message?)')
    else:
        hint = 'truncated or corrupted?'
    return f'{path}: cannot read the bag: {text} ({hint})'


def _storage_file(path):
    """Return the one storage file of a bag directory (for messages), else the path."""
    path = Path(path)
    if path.is_dir():
        files = sorted(x for x in path.iterdir() if x.suffix in _STORAGE_SUFFIXES)
        if len(files) == 1:
            return files[0]
    return path


class BagReader:
    """
    An open bag: rosbags' AnyReader plus a :class:`BagInfo`, with clear errors.

    Use as a context manager::

        with BagReader('bags/run1') as bag:
            print(bag.info.describe_topics())
            for conn, log_ns, raw in bag.messages(['/imu/gyro']):
                ...

    Parameters
    ----------
    path : str or Path
        A bag directory, or one ``.mcap`` or ``.db3`` file. A directory without its
        ``metadata.yaml`` is read through its single storage file (with a warning).

    Raises
    ------
    BagToolError
        The path is missing, is not a ROS 2 bag, or cannot be read (truncated,
        corrupted); the message names the file.

    """

    def __init__(self, path):
        self.path = Path(path)
        self.reader = None
        self.info = None
        self.warnings = []

    def __enter__(self):
        """Open the bag."""
        return self.load()

    def __exit__(self, *exc):
        """Close the bag."""
        self.close()

    def _storage_path(self):
        p = self.path
        if not p.exists():
            raise BagToolError(f'{p}: no such file or directory')
        folder = p if p.is_dir() else p.parent
        holder = recording_holder(folder)
        if holder:
            raise BagToolError(f'{folder} is being recorded ({holder} holds '
                               f'{folder / LOCK_NAME}); read it once the recorder has closed '
                               'it (Ctrl-C or SIGTERM closes the bag)')
        if p.is_dir():
            files = sorted(x for x in p.iterdir() if x.suffix in _STORAGE_SUFFIXES)
            for file in files:
                check_regular(file)
            if (p / 'metadata.yaml').exists() or (p / 'metadata.yaml').is_symlink():
                check_metadata_file(p / 'metadata.yaml')
                lies = metadata_storage_disagreement(p / 'metadata.yaml', files[0]) \
                    if len(files) == 1 else []
                if not lies:
                    return p
                # the storage file is the truth: read it, not what metadata.yaml names
                self.warnings.append(
                    f'{p / "metadata.yaml"} disagrees with {files[0].name}: '
                    f'{"; ".join(lies)}; the bag is read from {files[0].name}, its storage '
                    f'(`observer-bag-recover {p}` rewrites metadata.yaml from it)')
                return files[0]
            if not files:
                raise BagToolError(
                    f'{p}: not a bag: the directory has no metadata.yaml and no .mcap or '
                    '.db3 file')
            if len(files) > 1:
                raise BagToolError(
                    f'{p}: metadata.yaml is missing and the directory holds '
                    f'{len(files)} storage files ({", ".join(f.name for f in files)}); '
                    f'restore it with `ros2 bag reindex {p}` or pass one file')
            growing = still_growing(files[0])
            if growing:
                raise BagToolError(f'{p} is still being written by another program: '
                                   f'{growing}; read it once its recorder has closed it')
            self.warnings.append(
                f'{p}: metadata.yaml is missing (a recording that was not closed? '
                f'`observer-bag-recover {p}` completes it); reading {files[0].name} directly')
            return files[0]
        if p.suffix == '.bag':
            raise BagToolError(
                f'{p}: a ROS 1 bag; observer_ros reads ROS 2 bags (mcap or sqlite3); '
                'convert it with `rosbags-convert`')
        if p.suffix not in _STORAGE_SUFFIXES:
            raise BagToolError(
                f'{p}: not a bag: expected a bag directory, a .mcap or a .db3 file')
        check_regular(p)
        return p

    def load(self):
        """Open the bag and fill :attr:`info`; return self."""
        storage_path = self._storage_path()
        try:
            reader = AnyReader([storage_path], default_typestore=jazzy_typestore())
            reader.open()
        except BagToolError:
            raise
        except Exception as err:   # noqa: BLE001 - rosbags raises many types
            raise BagToolError(_reason(_storage_file(storage_path), err)) from None
        lies = metadata_disagreement(reader.readers[0].storage) if storage_path.is_dir() \
            else []
        if lies:
            # the storage file is the truth: metadata.yaml only summarises it
            file = _storage_file(storage_path)
            more = f'; and {len(lies) - 4} more' if len(lies) > 4 else ''
            self.warnings.append(
                f'{storage_path / "metadata.yaml"} disagrees with {file.name}: '
                f'{"; ".join(lies[:4])}{more}; the bag is read from {file.name}, its storage '
                f'(`observer-bag-recover {storage_path}` rewrites metadata.yaml from it)')
            try:
                reader.close()
            except Exception:   # noqa: BLE001 - reopened from the file below
                pass
            storage_path = file
            try:
                reader = AnyReader([storage_path], default_typestore=jazzy_typestore())
                reader.open()
            except Exception as err:   # noqa: BLE001 - rosbags raises many types
                raise BagToolError(_reason(storage_path, err)) from None
        self.reader = reader
        try:
            self.info = self._make_info(storage_path)
        except Exception as err:   # noqa: BLE001
            self.close()
            raise BagToolError(_reason(_storage_file(storage_path), err)) from None
        return self

    def _make_info(self, storage_path):
        reader = self.reader
        if not reader.is2:
            raise BagToolError(f'{self.path}: a ROS 1 bag; observer_ros reads ROS 2 bags')
        topics = {}
        for conn in reader.connections:
            msgtype, count = topics.get(conn.topic, (conn.msgtype, 0))
            topics[conn.topic] = (msgtype, count + int(conn.msgcount or 0))
        sub = reader.readers[0]
        inner = getattr(sub, 'storage', None)
        inner = (getattr(inner, 'storages', None) or [inner])[0]
        storage = 'mcap' if 'mcap' in type(inner).__name__.lower() else 'sqlite3'
        count = int(reader.message_count)
        crcs = chunk_crcs(inner) if storage == 'mcap' and getattr(inner, 'bio', None) \
            else None
        note = checksum_note(_storage_file(storage_path), storage, crcs)
        return BagInfo(path=self.path, storage_path=storage_path, storage=storage,
                       topics=topics, message_count=count,
                       start_ns=int(reader.start_time) if count else 0,
                       end_ns=int(reader.end_time) if count else 0,
                       ros_distro=getattr(sub, 'ros_distro', None),
                       warnings=list(self.warnings) + ([note] if note else []),
                       chunk_crcs=crcs)

    def close(self):
        """Close the bag (idempotent)."""
        if self.reader is not None:
            reader, self.reader = self.reader, None
            try:
                reader.close()
            except Exception:   # noqa: BLE001 - closing a broken bag
                pass

    def connections(self, topics=None):
        """Return the connections of the given topics (all when None)."""
        conns = self.reader.connections
        if topics is None:
            return list(conns)
        wanted = set(topics)
        return [c for c in conns if c.topic in wanted]

    def messages(self, topics=None, start=None):
        """
        Yield ``(connection, log_ns, raw)`` in bag order; read errors become BagToolError.

        Parameters
        ----------
        topics : iterable of str, optional
            Only these topics (all when None).
        start : int, optional
            Only messages received at or after this time (ns).

        """
        conns = self.connections(topics)
        if topics is not None and not conns:
            return
        readers = self.reader.readers
        # one rosbag2 recording: read it directly (AnyReader merges several bags)
        source = readers[0] if len(readers) == 1 else self.reader

        def read():
            # an indexed mcap file: read chunk by chunk, same stream (benchmarks P3)
            fast = fast_messages(source, conns, start) if len(readers) == 1 else None
            if fast is None:
                fast = source.messages(connections=conns, start=start)
            yield from fast
        yield from self._guarded(read())

    def message_chunks(self, topics=None):
        """
        Return the messages of :meth:`messages` chunk by chunk as arrays, or None.

        For one indexed MCAP file (see :func:`~observer_ros.bag.mcap_fast.fast_chunks`);
        None when the bag must be read message by message.

        """
        conns = self.connections(topics)
        readers = self.reader.readers
        if len(readers) != 1 or (topics is not None and not conns):
            return None
        try:
            chunks = fast_chunks(readers[0], conns, pad=PAD)
        except Exception:   # noqa: BLE001 - any doubt: the message-by-message path
            return None
        return None if chunks is None else self._guarded(chunks)

    def _guarded(self, items):
        """Yield ``items``; an error reading them becomes BagToolError naming the file."""
        try:
            yield from items
        except BagToolError:
            raise
        except Exception as err:   # noqa: BLE001 - rosbags raises many types
            raise BagToolError(_reason(_storage_file(self.info.storage_path), err)) from None

    def deserialize(self, raw, msgtype):
        """Deserialize one message with the bag's typestore."""
        return self.reader.deserialize(raw, msgtype)

    def check_definition(self, msgtype):
        """
        Return why the bag's definition of msgtype differs from ROS 2 Jazzy's, or ''.

        Compares the recorded type hash (RIHS01, when the bag has one) and the field
        definitions, nested types included.

        """
        store = jazzy_typestore()
        if msgtype not in store.fielddefs:
            return ''
        for conn in self.reader.connections:
            if conn.msgtype == msgtype and conn.digest and \
                    conn.digest != store.hash_rihs01(msgtype):
                return (f"the bag's {msgtype} has type hash {conn.digest[:22]}...; "
                        f"ROS 2 Jazzy's is {store.hash_rihs01(msgtype)[:22]}...")
        bag_store = self.reader.typestore
        todo, seen = [msgtype], set()
        while todo:
            name = todo.pop()
            if name in seen:
                continue
            seen.add(name)
            mine, theirs = bag_store.fielddefs.get(name), store.fielddefs.get(name)
            if mine is None or theirs is None:
                continue
            if mine != theirs:
                return f"the bag's definition of {name} differs from ROS 2 Jazzy's"
            todo.extend(_nested_types(mine))
        return ''


def _nested_types(desc):
    if isinstance(desc, str):
        if '/msg/' in desc:
            yield desc
    elif isinstance(desc, (tuple, list)):
        for item in desc:
            yield from _nested_types(item)


def bag_info(path):
    """
    Return the :class:`BagInfo` of a bag (topics, counts, time span).

    Parameters
    ----------
    path : str or Path
        The bag: its folder or a storage file, as :class:`BagReader` takes it.

    Returns
    -------
    info : BagInfo

    Raises
    ------
    BagToolError
        As :class:`BagReader`.

    """
    with BagReader(path) as bag:
        return bag.info
