# observer_ros.bag.mcap_repair: scan an mcap file left open by its writer, and complete it.
"""
Scan the records of an mcap file whose writer died, and complete it after its last chunk.

:func:`scan_mcap` reads the records from the start and stops at the first one cut short
or damaged (a length beyond :data:`MAX_CHUNK_BYTES`, records that do not parse, a CRC32
that does not match): it returns the schemas, channels and complete chunks (with their
messages' times and offsets) and where to cut. :func:`repair_mcap` cuts the file there,
rebuilds the last chunk's message indexes when they are missing, and appends a summary
(schemas, channels, chunk indexes, metadata, statistics, summary offsets) and the footer;
earlier bytes are not rewritten. Used by :mod:`observer_ros.bag.recover`
(``observer-bag-recover``). Records are read by :mod:`.mcap_records` (the MCAP parser);
this module writes the summary. https://mcap.dev/spec

"""

import io
import os
import struct

from .errors import BagRecoveryError
from .mcap_records import (decompress_chunk, iter_records, MAGIC, MAX_CHUNK_BYTES,
                           OP_CHANNEL, OP_CHUNK, OP_CHUNK_INDEX, OP_DATA_END, OP_FOOTER,
                           OP_HEADER, OP_MESSAGE, OP_MESSAGE_INDEX, OP_METADATA,
                           OP_METADATA_INDEX, OP_SCHEMA, OP_STATISTICS, OP_SUMMARY_OFFSET,
                           read_channel, read_chunk_header, read_message_time, read_schema,
                           RECORD_HEAD, record_head)

__all__ = ['MAGIC', 'MAX_CHUNK_BYTES', 'scan_mcap', 'repair_mcap', 'channel_counts',
           'time_range']

MAX_TIME = 2**63 - 1


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


# -------------------------------------------------------------------------------- scan
def _parse_records(records, schemas, channels):
    """
    Parse a run of mcap records (a chunk's content); collect schemas and channels.

    Returns ``{channel id: [(log_time, offset of the record)]}``. Raises ValueError (or
    struct.error, UnicodeDecodeError) on a damaged record.

    """
    messages = {}
    for op, offset, body, stop in iter_records(records):
        if op == OP_SCHEMA:
            schema = read_schema(records[body:stop])
            schemas[schema[0]] = schema
        elif op == OP_CHANNEL:
            channel = read_channel(records[body:stop])
            channels[channel['id']] = channel
        elif op == OP_MESSAGE:
            cid, log_time = read_message_time(records[body:stop])
            messages.setdefault(cid, []).append((log_time, offset))
    return messages


def _parse_chunk(body, schemas, channels):
    """
    Parse a chunk record's body; return its summary dict (messages per channel).

    Raises ValueError when the chunk is damaged (then it is not kept).

    """
    head = read_chunk_header(body)
    start, end, usize = head['start'], head['end'], head['usize']
    compression, csize = head['compression'], head['csize']
    if usize > MAX_CHUNK_BYTES:     # a damaged length must not ask for terabytes
        raise ValueError(f'a chunk of {usize} bytes, more than {MAX_CHUNK_BYTES}')
    data = body[head['records']:head['records'] + csize]
    if len(data) != csize:
        raise ValueError('record ends early')
    # the CRC: 0 when not computed (rosbags' own Writer)
    records = decompress_chunk(data, compression, usize, head['crc'])
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


def scan_mcap(path):
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
        head = f.read(RECORD_HEAD)
        if len(head) < RECORD_HEAD or head[0] != OP_HEADER:
            raise BagRecoveryError(f'{path}: the mcap header record is missing or cut')
        _, length = record_head(head)
        header = f.read(length)
        if len(header) < length:
            raise BagRecoveryError(f'{path}: the mcap header record is cut')
        pos = len(MAGIC) + RECORD_HEAD + length
        cut = pos
        data_end = None
        while True:
            f.seek(pos)
            head = f.read(RECORD_HEAD)
            if len(head) < RECORD_HEAD:
                break
            op, length = record_head(head)
            end = pos + RECORD_HEAD + length
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


def repair_mcap(path, scan, metadata_text):
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
        counts = channel_counts(scan)
        t_min, t_max = time_range(scan)
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


def channel_counts(scan):
    counts = dict.fromkeys(scan['channels'], 0)
    for chunk in scan['chunks']:
        for cid, entries in chunk['messages'].items():
            counts[cid] = counts.get(cid, 0) + len(entries)
    return counts


def time_range(scan):
    starts = [c['message_start'] for c in scan['chunks'] if c['messages']]
    ends = [c['message_end'] for c in scan['chunks'] if c['messages']]
    return (min(starts), max(ends)) if starts else (0, 0)
