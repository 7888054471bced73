# observer_ros.bag.mcap_fast: the raw messages of an indexed MCAP bag, read chunk by chunk.
"""
Raw messages of an indexed MCAP file in rosbags' order, without rosbags' per-message reads.

rosbags' MCAP reader reads every record through ``BytesIO`` calls and merges the chunks
with ``heapq``: about 4 us per message, most of observer-eval's time on a large bag
(benchmarks/README.md, P3). When the chunks do not overlap in time (every bag rosbags
or ``ros2 bag record`` writes), the merged order is the file order with each chunk
stably sorted by log time, so a chunk can be decompressed (its CRC checked) and its
message records found from its MessageIndex records, or one walk over its records
(:mod:`.mcap_records`, the MCAP parser). :func:`fast_messages` returns None when it
cannot give exactly rosbags' stream (unindexed file, overlapping chunks, per-message
compression, an unknown rosbags layout), and the caller reads through rosbags.

"""

import numpy as np

from .mcap_records import (message_fields, MESSAGE_HEAD, message_offsets, OP_MESSAGE,
                           read_chunk, read_message_index)

__all__ = ['fast_messages', 'fast_chunks']


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
    """(storage, chunks, channels) for reading chunk by chunk, or None."""
    storage = _storage(reader)
    if storage is None:
        return None
    chunks = list(storage.chunks)
    for a, b in zip(chunks, chunks[1:]):
        if b.message_start_time < a.message_end_time or \
                b.chunk_start_offset < a.chunk_start_offset:
            return None                 # overlapping chunks: rosbags merges them
    return storage, chunks, _connection_map(storage, connections)


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


def _chunk_buffers(storage, chunks, channels, start):
    """Yield (decompressed chunk, message offsets from its index or None) of the chunks."""
    bio = storage.bio
    for chunk in chunks:
        if start is not None and chunk.message_end_time < start:
            continue
        present = [cid for cid in channels if chunk.channel_count.get(cid, 0)]
        if not present:
            continue
        try:
            buf = read_chunk(bio, chunk.chunk_start_offset, chunk.compression,
                             chunk.compressed_size, chunk.uncompressed_size)
        except Exception as err:   # noqa: BLE001 - the decompressors raise their own types
            raise ValueError(f'chunk at byte {chunk.chunk_start_offset}: {err}') from None
        yield buf, _indexed_offsets(bio, chunk, present)


def _generate(storage, chunks, channels, start):
    wanted = np.array(sorted(channels), dtype=np.int64)
    for buf, offsets in _chunk_buffers(storage, chunks, channels, start):
        yield from _chunk_messages(buf, channels, wanted, start, offsets)


def _generate_arrays(storage, chunks, channels, start, pad):
    wanted = np.array(sorted(channels), dtype=np.int64)
    for buf, offsets in _chunk_buffers(storage, chunks, channels, start):
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
        offsets = read_message_index(bio, index[cid])
        if offsets is None:
            return None
        parts.append(offsets)
    return np.concatenate(parts).astype(np.int64) if parts else None


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
    off = message_offsets(buf) if offsets is None else np.sort(offsets)
    if not off.size:
        empty = np.zeros(0, dtype=np.int64)
        return empty, empty, empty, empty
    if offsets is not None and (off[-1] + MESSAGE_HEAD > flat.size or
                                np.any(flat[off] != OP_MESSAGE)):
        off = message_offsets(buf)      # an index that does not match: walk the chunk
    channel, log, length = message_fields(flat, off)
    keep = np.isin(channel, wanted)
    if start is not None:
        keep &= log >= start
    sel = np.flatnonzero(keep)
    if sel.size > 1 and np.any(np.diff(log[sel]) < 0):
        sel = sel[np.argsort(log[sel], kind='stable')]      # rosbags sorts each chunk
    begin = off[sel] + MESSAGE_HEAD
    return channel[sel], log[sel], begin, off[sel] + 9 + length[sel] - begin
