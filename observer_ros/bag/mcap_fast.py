# observer_ros.bag.mcap_fast: the raw messages of an indexed MCAP bag, read chunk by chunk.
"""
Raw messages of an indexed MCAP file in rosbags' order, without rosbags' per-message reads.

rosbags' MCAP reader reads every record through ``BytesIO`` calls and merges the chunks
with ``heapq``: about 4 us per message, most of observer-eval's time on a large bag
(benchmarks/README.md, P3). When the chunks do not overlap in time (every bag rosbags
or ``ros2 bag record`` writes), the merged order is the file order with each chunk
stably sorted by log time, so a chunk can be decompressed (by rosbags' own
``decompress``, which checks the CRC) and its record headers scanned in one loop.
:func:`fast_messages` returns None when it cannot give exactly rosbags' stream
(unindexed file, overlapping chunks, per-message compression, an unknown rosbags
layout), and the caller reads through rosbags.

"""

import struct

import numpy as np

__all__ = ['fast_messages', 'fast_chunks']

_RECORD = struct.Struct('<BQ')          # opcode, length
_MESSAGE = 0x05
_HEADER = 1 + 8 + 2 + 4 + 8 + 8         # op, len, channel, sequence, log_time, publish_time


def _storage(reader):
    """Return the one McapReader behind a rosbags rosbag2.Reader, or None."""
    inner = getattr(reader, 'storage', reader)          # rosbags 0.11: a DirectoryReader
    storages = getattr(inner, 'storages', None)
    if not storages or len(storages) != 1:
        return None
    storage = storages[0]
    if type(storage).__name__ != 'McapReader' or not getattr(storage, 'chunks', None) or \
            getattr(storage, 'bio', None) is None:
        return None
    meta = getattr(inner, 'metadata', None)
    if meta is None or getattr(meta, 'compression_mode', None) == 'message':
        return None
    return storage


def _connection_map(storage, connections):
    """Channel id -> the caller's Connection, matched as rosbags' Reader.messages does."""
    out = {}
    for x in storage.connections:
        for y in connections:
            if y.topic == x.topic and y.msgtype == x.msgtype and y.ext == x.ext and \
                    (not x.digest or not y.digest or y.digest == x.digest):
                out[x.id] = y
                break
    return out


def fast_chunks(reader, connections, start=None, pad=512):
    """
    Return a generator of the raw messages chunk by chunk, as arrays, or None.

    The same messages in the same order as :func:`fast_messages`, without a ``bytes``
    object per message: each item is ``(conns, log_ns, flat, starts, lengths)`` for one
    chunk, where message i is ``flat[starts[i]:starts[i] + lengths[i]]`` (``flat`` a
    uint8 array of the decompressed chunk followed by ``pad`` zero bytes), received at
    ``log_ns[i]`` on connection ``conns[i]``.

    """
    plan = _plan(reader, connections)
    if plan is None or not plan[2]:
        return plan if plan is None else iter(())
    return _generate_arrays(*plan, start, pad)


def _plan(reader, connections):
    """(storage, chunks, channels, decompress) for reading chunk by chunk, or None."""
    try:
        from rosbags.rosbag2.storage_mcap import decompress
    except ImportError:
        return None
    storage = _storage(reader)
    if storage is None:
        return None
    chunks = list(storage.chunks)
    for a, b in zip(chunks, chunks[1:]):
        if b.message_start_time < a.message_end_time or \
                b.chunk_start_offset < a.chunk_start_offset:
            return None                 # overlapping chunks: rosbags merges them
    return storage, chunks, _connection_map(storage, connections), decompress


def fast_messages(reader, connections, start=None):
    """
    Return a generator of ``(connection, log_ns, raw)`` like rosbags, or None.

    Parameters
    ----------
    reader : rosbags.rosbag2.Reader
        An open reader of one MCAP file.
    connections : list of Connection
        The connections to read (from the reader).
    start : int, optional
        Only messages logged at or after this time (ns).

    Returns
    -------
    messages : generator or None
        None when the file cannot be read this way (the caller uses rosbags).

    """
    plan = _plan(reader, connections)
    if plan is None or not plan[2]:
        return plan if plan is None else iter(())
    return _generate(*plan, start)


def _chunk_buffers(storage, chunks, channels, decompress, start):
    """Yield (decompressed chunk, message offsets from its index or None) of the chunks."""
    bio = storage.bio
    for chunk in chunks:
        if start is not None and chunk.message_end_time < start:
            continue
        present = [cid for cid in channels if chunk.channel_count.get(cid, 0)]
        if not present:
            continue
        bio.seek(chunk.chunk_start_offset + 9 + 24)
        (crc,) = struct.unpack('<I', bio.read(4))
        bio.seek(chunk.chunk_start_offset + 9 + 40 + len(chunk.compression))
        data = bio.read(chunk.compressed_size)
        if len(data) != chunk.compressed_size:
            raise ValueError(f'truncated chunk at offset {chunk.chunk_start_offset}')
        try:
            buf = decompress(data, chunk.compression, chunk.uncompressed_size, crc)
        except Exception as err:   # noqa: BLE001 - rosbags' ReaderError
            raise ValueError(f'chunk at byte {chunk.chunk_start_offset}: {err}') from None
        yield buf, _indexed_offsets(bio, chunk, present)


def _generate(storage, chunks, channels, decompress, start):
    wanted = np.array(sorted(channels), dtype=np.int64)
    for buf, offsets in _chunk_buffers(storage, chunks, channels, decompress, start):
        yield from _chunk_messages(buf, channels, wanted, start, offsets)


def _generate_arrays(storage, chunks, channels, decompress, start, pad):
    wanted = np.array(sorted(channels), dtype=np.int64)
    for buf, offsets in _chunk_buffers(storage, chunks, channels, decompress, start):
        flat = np.frombuffer(buf, dtype=np.uint8)
        channel, log, begin, length = _chunk_arrays(flat, buf, wanted, start, offsets)
        if not begin.size:
            continue
        padded = np.zeros(flat.size + pad, dtype=np.uint8)
        padded[:flat.size] = flat
        conns = [channels[c] for c in channel.tolist()]
        yield conns, log, padded, begin, length


def _indexed_offsets(bio, chunk, present):
    """Offsets (in the chunk) of the present channels' messages, from the MessageIndex records."""
    index = chunk.message_index_offsets
    if not all(cid in index for cid in present):
        return None
    parts = []
    for cid in present:
        bio.seek(index[cid])
        head = bio.read(9 + 2 + 4)
        if len(head) != 15 or head[0] != 0x07:
            return None
        (size,) = struct.unpack_from('<I', head, 11)
        body = bio.read(size)
        if len(body) != size or size % 16:
            return None
        parts.append(np.frombuffer(body, dtype='<u8').reshape(-1, 2)[:, 1])
    return np.concatenate(parts).astype(np.int64) if parts else None


def _scan(buf):
    """Offsets of the message records of a chunk, by walking the record headers."""
    unpack = _RECORD.unpack_from
    end = len(buf)
    offsets = []
    pos = 0
    while pos < end:
        op, length = unpack(buf, pos)
        if op == _MESSAGE:
            offsets.append(pos)
        pos += 9 + length
    if pos != end:
        raise ValueError('truncated record in a chunk')
    return np.array(offsets, dtype=np.int64)


def _chunk_messages(buf, channels, wanted, start, offsets=None):
    """Messages of one decompressed chunk, as a list of (connection, log_ns, raw)."""
    flat = np.frombuffer(buf, dtype=np.uint8)
    channel, log, begin, length = _chunk_arrays(flat, buf, wanted, start, offsets)
    stop = (begin + length).tolist()
    conns = [channels[c] for c in channel.tolist()]
    return list(zip(conns, log.tolist(), [buf[b:e] for b, e in zip(begin.tolist(), stop)]))


def _chunk_arrays(flat, buf, wanted, start, offsets=None):
    """
    Return the wanted messages of a chunk in rosbags' order: channel, log, start, length.

    rosbags sorts the messages of a chunk stably by log time.

    """
    off = _scan(buf) if offsets is None else np.sort(offsets)
    if not off.size:
        empty = np.zeros(0, dtype=np.int64)
        return empty, empty, empty, empty
    if offsets is not None and (off[-1] + _HEADER > flat.size or
                                np.any(flat[off] != _MESSAGE)):
        off = _scan(buf)                # an index that does not match: walk the chunk
    length = np.ascontiguousarray(flat[off[:, None] + np.arange(1, 9)]).view('<u8')
    length = length.reshape(-1).astype(np.int64)
    channel = np.ascontiguousarray(flat[off[:, None] + np.arange(9, 11)]).view('<u2')
    channel = channel.reshape(-1).astype(np.int64)
    log = np.ascontiguousarray(flat[off[:, None] + np.arange(15, 23)]).view('<u8')
    log = log.reshape(-1).astype(np.int64)
    if np.any(off + 9 + length > flat.size):
        raise ValueError('truncated message record in a chunk')
    keep = np.isin(channel, wanted)
    if start is not None:
        keep &= log >= start
    sel = np.flatnonzero(keep)
    if sel.size > 1 and np.any(np.diff(log[sel]) < 0):
        sel = sel[np.argsort(log[sel], kind='stable')]      # rosbags sorts each chunk
    begin = off[sel] + _HEADER
    return channel[sel], log[sel], begin, off[sel] + 9 + length[sel] - begin
