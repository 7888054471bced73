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

"""

import argparse
import io
import os
from pathlib import Path
import sqlite3
import struct
import sys

import yaml

from ..core.errors import ObserverError

__all__ = ['BagRecoveryError', 'recover_bag', 'main']

MAGIC = b'\x89MCAP0\r\n'
# mcap opcodes (https://mcap.dev/spec)
OP_HEADER, OP_FOOTER, OP_SCHEMA, OP_CHANNEL, OP_MESSAGE = 0x01, 0x02, 0x03, 0x04, 0x05
OP_CHUNK, OP_MESSAGE_INDEX, OP_CHUNK_INDEX = 0x06, 0x07, 0x08
OP_METADATA, OP_METADATA_INDEX, OP_STATISTICS = 0x0C, 0x0D, 0x0B
OP_SUMMARY_OFFSET, OP_DATA_END = 0x0E, 0x0F
MAX_TIME = 2**63 - 1


class BagRecoveryError(ObserverError):
    """A bag cannot be recovered; the message names the bag and the reason."""


# ------------------------------------------------------------------------------ encoding
def _u16(v):
    return struct.pack('<H', v)


def _u32(v):
    return struct.pack('<I', v)


def _u64(v):
    return struct.pack('<Q', v)


def _string(text):
    data = text.encode() if isinstance(text, str) else bytes(text)
    return _u32(len(data)) + data


def _record(op, body):
    return bytes([op]) + _u64(len(body)) + body


class _Cursor:
    """Read little-endian mcap primitives from a bytes object."""

    def __init__(self, data, pos=0):
        self.data = data
        self.pos = pos

    def take(self, n):
        if self.pos + n > len(self.data):
            raise ValueError('record ends early')
        out = self.data[self.pos:self.pos + n]
        self.pos += n
        return out

    def u16(self):
        return struct.unpack('<H', self.take(2))[0]

    def u32(self):
        return struct.unpack('<I', self.take(4))[0]

    def u64(self):
        return struct.unpack('<Q', self.take(8))[0]

    def string(self):
        return self.take(self.u32()).decode()

    def blob(self):
        return self.take(self.u32())


# -------------------------------------------------------------------------------- mcap
def _decompress(data, compression, size):
    if compression == '':
        out = data
    elif compression == 'zstd':
        if sys.version_info >= (3, 14):
            from compression import zstd
        else:
            from backports import zstd
        out = zstd.decompress(data)
    elif compression == 'lz4':
        import lz4.frame
        out = lz4.frame.decompress(data)
    else:
        raise ValueError(f'unsupported chunk compression {compression!r}')
    if len(out) != size:
        raise ValueError('chunk size does not match its header')
    return out


def _parse_records(records, schemas, channels):
    """
    Parse a run of mcap records (a chunk's content); collect schemas and channels.

    Returns ``{channel id: [(log_time, offset of the record)]}``. Raises ValueError (or
    struct.error, UnicodeDecodeError) on a damaged record.

    """
    inner = _Cursor(records)
    messages = {}
    while inner.pos < len(records):
        offset = inner.pos
        op = inner.take(1)[0]
        rec = _Cursor(inner.take(inner.u64()))
        if op == OP_SCHEMA:
            sid = rec.u16()
            schemas[sid] = (sid, rec.string(), rec.string(), rec.blob())
        elif op == OP_CHANNEL:
            cid, sid = rec.u16(), rec.u16()
            topic, encoding = rec.string(), rec.string()
            meta = {}
            meta_data = _Cursor(rec.blob())
            while meta_data.pos < len(meta_data.data):
                key = meta_data.string()
                meta[key] = meta_data.string()
            channels[cid] = {'id': cid, 'schema_id': sid, 'topic': topic,
                             'encoding': encoding, 'metadata': meta}
        elif op == OP_MESSAGE:
            cid = rec.u16()
            rec.u32()                           # sequence
            messages.setdefault(cid, []).append((rec.u64(), offset))
    return messages


def _parse_chunk(body, schemas, channels):
    """
    Parse a chunk record's body; return its summary dict (messages per channel).

    Raises ValueError when the chunk is damaged (then it is not kept).

    """
    cur = _Cursor(body)
    start, end, usize = cur.u64(), cur.u64(), cur.u64()
    cur.u32()                                   # crc (0: not computed by rosbags)
    compression = cur.string()
    csize = cur.u64()
    records = _decompress(cur.take(csize), compression, usize)
    # parse into copies, so that a damaged chunk adds nothing
    new_schemas, new_channels = dict(schemas), dict(channels)
    messages = _parse_records(records, new_schemas, new_channels)
    schemas.update(new_schemas)
    channels.update(new_channels)
    times = [t for entries in messages.values() for t, _ in entries]
    t_min, t_max = (min(times), max(times)) if times else (MAX_TIME, 0)
    return {'start': start if times else t_min, 'end': end if times else t_max,
            'usize': usize, 'csize': csize, 'compression': compression,
            'messages': messages, 'message_start': t_min, 'message_end': t_max}


def _message_index_records(chunk):
    """Return (bytes, {channel: relative offset}) of a chunk's message index records."""
    out = io.BytesIO()
    offsets = {}
    for cid, entries in chunk['messages'].items():
        offsets[cid] = out.tell()
        body = _u16(cid) + _u32(16 * len(entries)) + b''.join(
            _u64(t) + _u64(off) for t, off in entries)
        out.write(_record(OP_MESSAGE_INDEX, body))
    return out.getvalue(), offsets


def _scan_mcap(path):
    """
    Scan an mcap file's data section.

    Returns
    -------
    dict
        ``schemas``, ``channels``, ``chunks`` (with file offsets), ``cut`` (offset after
        the last complete chunk), ``intact`` (a summary and footer were found after the
        data), ``size``.

    """
    size = path.stat().st_size
    schemas, channels, chunks = {}, {}, []
    with path.open('rb') as f:
        if f.read(8) != MAGIC:
            raise BagRecoveryError(f'{path}: not an mcap file (no magic at the start)')
        head = f.read(9)
        if len(head) < 9 or head[0] != OP_HEADER:
            raise BagRecoveryError(f'{path}: the mcap header record is missing or cut')
        (length,) = struct.unpack('<Q', head[1:])
        header = f.read(length)
        if len(header) < length:
            raise BagRecoveryError(f'{path}: the mcap header record is cut')
        pos = 8 + 9 + length
        cut = pos
        data_end = None
        while True:
            f.seek(pos)
            head = f.read(9)
            if len(head) < 9:
                break
            op = head[0]
            (length,) = struct.unpack('<Q', head[1:])
            end = pos + 9 + length
            if end > size:
                break                               # a record cut short: stop here
            if op in (OP_DATA_END, OP_FOOTER, OP_METADATA, OP_METADATA_INDEX,
                      OP_CHUNK_INDEX, OP_STATISTICS, OP_SUMMARY_OFFSET):
                data_end = pos
                break
            body = f.read(length)
            if op == OP_CHUNK:
                try:
                    chunk = _parse_chunk(body, schemas, channels)
                except (ValueError, UnicodeDecodeError, struct.error):
                    break                           # damaged: keep what came before
                chunk.update(offset=pos, length=end - pos, index_offsets={}, index_end=end)
                chunks.append(chunk)
                cut = end
            elif op == OP_MESSAGE_INDEX and chunks:
                cid = struct.unpack('<H', body[:2])[0]
                chunks[-1]['index_offsets'][cid] = pos
                chunks[-1]['index_end'] = end
            elif op in (OP_SCHEMA, OP_CHANNEL):
                # top-level definitions (rosbags puts them in the first chunk)
                try:
                    _parse_records(_record(op, body), schemas, channels)
                except (ValueError, UnicodeDecodeError, struct.error):
                    break
                cut = end
            elif op == OP_MESSAGE:
                raise BagRecoveryError(f'{path}: messages outside chunks are not supported')
            pos = end
        intact = False
        if data_end is not None and size >= 8 + 37:
            f.seek(size - 8)
            intact = f.read(8) == MAGIC
    # a chunk whose message indexes are incomplete gets them rebuilt (only the last can be)
    if chunks:
        last = chunks[-1]
        if set(last['index_offsets']) != set(last['messages']):
            last['index_offsets'] = {}
            last['index_end'] = last['offset'] + last['length']
        cut = max(cut, last['index_end'])
    return {'schemas': schemas, 'channels': channels, 'chunks': chunks, 'cut': cut,
            'intact': intact, 'size': size}


def _repair_mcap(path, scan, metadata_text):
    """Cut the file after its last complete chunk and append indexes, summary, footer."""
    schemas, channels, chunks = scan['schemas'], scan['channels'], scan['chunks']
    with path.open('r+b') as f:
        f.truncate(scan['cut'])
        f.seek(scan['cut'])
        out = io.BytesIO()
        base = scan['cut']
        if chunks and not chunks[-1]['index_offsets']:
            last = chunks[-1]
            data, rel = _message_index_records(last)
            last['index_offsets'] = {cid: base + off for cid, off in rel.items()}
            last['index_end'] = base + len(data)
            out.write(data)
        metadata_start = base + out.tell()
        pairs = _string('serialized_metadata') + _string(metadata_text)
        meta = _string('rosbag2') + _u32(len(pairs)) + pairs
        out.write(_record(OP_METADATA, meta))
        metadata_end = base + out.tell()
        out.write(_record(OP_DATA_END, _u32(0)))
        schema_start = base + out.tell()
        for sid in sorted(schemas):
            _, name, encoding, data = schemas[sid]
            out.write(_record(OP_SCHEMA, _u16(sid) + _string(name) + _string(encoding)
                              + _u32(len(data)) + data))
        channel_start = base + out.tell()
        for cid in sorted(channels):
            ch = channels[cid]
            meta_blob = b''.join(_string(k) + _string(v) for k, v in ch['metadata'].items())
            out.write(_record(OP_CHANNEL, _u16(cid) + _u16(ch['schema_id'])
                              + _string(ch['topic']) + _string(ch['encoding'])
                              + _u32(len(meta_blob)) + meta_blob))
        chunk_index_start = base + out.tell()
        for chunk in chunks:
            offsets = sorted(chunk['index_offsets'].items())
            body = (_u64(chunk['start']) + _u64(chunk['end']) + _u64(chunk['offset'])
                    + _u64(chunk['length']) + _u32(10 * len(offsets))
                    + b''.join(_u16(c) + _u64(o) for c, o in offsets)
                    + _u64(chunk['index_end'] - chunk['offset'] - chunk['length'])
                    + _string(chunk['compression']) + _u64(chunk['csize'])
                    + _u64(chunk['usize']))
            out.write(_record(OP_CHUNK_INDEX, body))
        metadata_index_start = base + out.tell()
        out.write(_record(OP_METADATA_INDEX, _u64(metadata_start)
                          + _u64(metadata_end - metadata_start) + _string('rosbag2')))
        statistics_start = base + out.tell()
        counts = _channel_counts(scan)
        t_min, t_max = _time_range(scan)
        body = (_u64(sum(counts.values())) + _u16(len(schemas)) + _u32(len(channels))
                + _u32(0) + _u32(1) + _u32(len(chunks)) + _u64(t_min) + _u64(t_max)
                + _u32(10 * len(counts))
                + b''.join(_u16(c) + _u64(n) for c, n in sorted(counts.items())))
        out.write(_record(OP_STATISTICS, body))
        summary_offset_start = base + out.tell()
        groups = ((OP_SCHEMA, schema_start, channel_start),
                  (OP_CHANNEL, channel_start, chunk_index_start),
                  (OP_CHUNK_INDEX, chunk_index_start, metadata_index_start),
                  (OP_METADATA_INDEX, metadata_index_start, statistics_start),
                  (OP_STATISTICS, statistics_start, summary_offset_start))
        for op, start, stop in groups:
            if stop != start:
                out.write(_record(OP_SUMMARY_OFFSET, bytes([op]) + _u64(start)
                                  + _u64(stop - start)))
        out.write(_record(OP_FOOTER, _u64(schema_start) + _u64(summary_offset_start)
                          + _u32(0)))
        out.write(MAGIC)
        f.write(out.getvalue())
        f.flush()
        os.fsync(f.fileno())


def _channel_counts(scan):
    counts = dict.fromkeys(scan['channels'], 0)
    for chunk in scan['chunks']:
        for cid, entries in chunk['messages'].items():
            counts[cid] = counts.get(cid, 0) + len(entries)
    return counts


def _time_range(scan):
    starts = [c['message_start'] for c in scan['chunks'] if c['messages']]
    ends = [c['message_end'] for c in scan['chunks'] if c['messages']]
    return (min(starts), max(ends)) if starts else (0, 0)


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
        if target.read_text() == text:
            return
    except OSError:
        pass
    tmp = bag / 'metadata.yaml.tmp'
    try:
        tmp.write_text(text)
        tmp.replace(target)
    except OSError as err:
        tmp.unlink(missing_ok=True)
        raise BagRecoveryError(f'{bag}: cannot write metadata.yaml: {err}') from None


def _mcap_topics(scan):
    counts = _channel_counts(scan)
    schema_names = {sid: s[1] for sid, s in scan['schemas'].items()}
    return [(ch['topic'], schema_names.get(ch['schema_id'], ''), ch['encoding'],
             ch['metadata'].get('offered_qos_profiles', ''), '', counts.get(cid, 0))
            for cid, ch in sorted(scan['channels'].items())]


def _recover_mcap(bag, file):
    scan = _scan_mcap(file)
    t_min, t_max = _time_range(scan)
    metadata = _metadata('mcap', file.name, _mcap_topics(scan), t_min, t_max)
    repaired = not scan['intact']
    if repaired:
        inner = yaml.safe_dump(metadata['rosbag2_bagfile_information'],
                               default_flow_style=False, sort_keys=False).strip()
        _repair_mcap(file, scan, inner)
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
    """Refuse, before touching anything, a file of the bag that is a link (never followed)."""
    for path in paths:
        if path.is_symlink():
            raise BagRecoveryError(f'{path} is a link (to {os.readlink(path)}); refusing to '
                                   'write through it: copy the file into the bag first')
        if path.exists() and path.resolve().parent != bag.resolve():
            raise BagRecoveryError(f'{path} lies outside the bag folder; refusing it')


def _is_intact(bag, file):
    """Return True for a bag its writer closed: metadata.yaml there, storage complete."""
    if not (bag / 'metadata.yaml').is_file() or (bag / '.disk_reserve').exists():
        return False
    if file.suffix == '.mcap':
        try:
            return _scan_mcap(file)['intact']
        except BagRecoveryError:
            return False
    # sqlite3: a writer that died leaves its journal (or write-ahead log) next to the file
    return not any(file.with_name(file.name + tail).exists() for tail in ('-journal', '-wal'))


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
                        bag / '.disk_reserve'])
    if _is_intact(bag, file):
        # a bag closed cleanly: nothing is rewritten, not even its metadata.yaml
        return {'storage': file.suffix[1:].replace('db3', 'sqlite3'), 'file': str(file),
                'repaired': False, 'dropped_bytes': 0, 'untouched': True,
                'messages': _read_counts(bag), 'total': _check_opens(bag)}
    # the space the recorder kept free for this moment (nodes.recorder, disk_reserve)
    (bag / '.disk_reserve').unlink(missing_ok=True)
    if file.suffix == '.mcap':
        report = _recover_mcap(bag, file)
    else:
        report = _recover_sqlite3(bag, file)
    report['untouched'] = False
    report['total'] = _check_opens(bag)
    return report


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
            print(f'error: {err}', file=sys.stderr)
            code = 2
            continue
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
