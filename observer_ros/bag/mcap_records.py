# observer_ros.bag.mcap_records: the MCAP parser (records, chunks, CRCs) of the bag tools.
"""
The records of an MCAP file: their layout, iteration, chunk decompression and CRCs.

The one place that knows the byte layout of MCAP (https://mcap.dev/spec). The chunk by
chunk reader (:mod:`.mcap_fast`), the chunk checksums (:mod:`.integrity`) and the
completion of a file whose writer died (:mod:`.mcap_repair`) all read records through
it. Every record is an opcode (1 byte), the length of its body (u64) and the body;
integers are little-endian, strings and byte arrays carry a u32 length. A Chunk holds
other records, compressed (``''``, ``'lz4'`` or ``'zstd'``), and the CRC32 of the
uncompressed records (0: none).

Damage is reported as :class:`ValueError` (``struct.error`` or ``UnicodeDecodeError``
where a field itself does not parse); the callers decide what it means for them.

"""

from binascii import crc32
import struct
import sys

import numpy as np

__all__ = ['MAGIC', 'OP_HEADER', 'OP_FOOTER', 'OP_SCHEMA', 'OP_CHANNEL', 'OP_MESSAGE',
           'OP_CHUNK', 'OP_MESSAGE_INDEX', 'OP_CHUNK_INDEX', 'OP_METADATA',
           'OP_METADATA_INDEX', 'OP_STATISTICS', 'OP_SUMMARY_OFFSET', 'OP_DATA_END',
           'RECORD_HEAD', 'CRC_OFFSET', 'MESSAGE_HEAD', 'MAX_CHUNK_BYTES', 'Cursor',
           'record_head', 'iter_records', 'message_offsets', 'message_fields',
           'read_schema', 'read_channel', 'read_message_time', 'read_chunk_header',
           'records_offset', 'chunk_crc', 'decompress_chunk', 'read_chunk_crc',
           'read_chunk', 'read_message_index']

MAGIC = b'\x89MCAP0\r\n'
OP_HEADER, OP_FOOTER, OP_SCHEMA, OP_CHANNEL, OP_MESSAGE = 0x01, 0x02, 0x03, 0x04, 0x05
OP_CHUNK, OP_MESSAGE_INDEX, OP_CHUNK_INDEX = 0x06, 0x07, 0x08
OP_METADATA, OP_METADATA_INDEX, OP_STATISTICS = 0x0C, 0x0D, 0x0B
OP_SUMMARY_OFFSET, OP_DATA_END = 0x0E, 0x0F

_RECORD = struct.Struct('<BQ')          # opcode, length of the body
RECORD_HEAD = _RECORD.size              # 9
# a Chunk record: opcode, length, message_start_time, message_end_time, uncompressed_size,
# then uncompressed_crc (u32) at this offset from the record's start, compression (string),
# compressed_size (u64), records
CRC_OFFSET = 1 + 8 + 8 + 8 + 8
# a Message record: opcode, length, channel_id (u16), sequence (u32), log_time,
# publish_time, then the message's bytes at this offset from the record's start
MESSAGE_HEAD = 1 + 8 + 2 + 4 + 8 + 8
# a chunk's records, uncompressed: rosbags and rosbag2 write chunks of about 1 MiB; a
# length beyond this is damage, and is not allocated
MAX_CHUNK_BYTES = 1 << 30


class Cursor:
    """Read little-endian MCAP fields from a bytes object, from ``pos`` on."""

    def __init__(self, data, pos=0):
        self.data = data
        self.pos = pos

    def take(self, n):
        """Return the next ``n`` bytes; ValueError when the data ends first."""
        if self.pos + n > len(self.data):
            raise ValueError('record ends early')
        out = self.data[self.pos:self.pos + n]
        self.pos += n
        return out

    def u16(self):
        """Return the next uint16."""
        return struct.unpack('<H', self.take(2))[0]

    def u32(self):
        """Return the next uint32."""
        return struct.unpack('<I', self.take(4))[0]

    def u64(self):
        """Return the next uint64."""
        return struct.unpack('<Q', self.take(8))[0]

    def string(self):
        """Return the next string: a u32 length, then UTF-8."""
        return self.take(self.u32()).decode()

    def blob(self):
        """Return the next byte array (u32 length)."""
        return self.take(self.u32())


# --------------------------------------------------------------------------- records
def record_head(head):
    """Return ``(opcode, body length)`` of the 9 bytes that start a record."""
    return _RECORD.unpack(head)


def iter_records(buf, pos=0):
    """
    Yield ``(opcode, offset, body start, body end)`` of the records in ``buf[pos:]``.

    Raises ValueError when a record runs past the end of ``buf``.

    """
    unpack = _RECORD.unpack_from
    end = len(buf)
    while pos < end:
        if pos + RECORD_HEAD > end:
            raise ValueError('truncated record in a chunk')
        op, length = unpack(buf, pos)
        body = pos + RECORD_HEAD
        stop = body + length
        if stop > end:
            raise ValueError('truncated record in a chunk')
        yield op, pos, body, stop
        pos = stop


def message_offsets(buf):
    """Offsets of the Message records of a chunk's records, as an int64 array."""
    return np.array([pos for op, pos, _, _ in iter_records(buf) if op == OP_MESSAGE],
                    dtype=np.int64)


def message_fields(flat, offsets):
    """
    Return the channel id, log time and record length of the Message records at offsets.

    Parameters
    ----------
    flat : numpy.ndarray
        The chunk's records as uint8.
    offsets : numpy.ndarray
        int64 offsets of Message records in ``flat``.

    Returns
    -------
    channel, log, length : numpy.ndarray
        int64 each; a message's bytes are ``flat[off + MESSAGE_HEAD:off + 9 + length]``.

    """
    length = np.ascontiguousarray(flat[offsets[:, None] + np.arange(1, 9)]).view('<u8')
    length = length.reshape(-1).astype(np.int64)
    channel = np.ascontiguousarray(flat[offsets[:, None] + np.arange(9, 11)]).view('<u2')
    channel = channel.reshape(-1).astype(np.int64)
    log = np.ascontiguousarray(flat[offsets[:, None] + np.arange(15, 23)]).view('<u8')
    log = log.reshape(-1).astype(np.int64)
    if np.any(offsets + RECORD_HEAD + length > flat.size):
        raise ValueError('truncated message record in a chunk')
    return channel, log, length


def read_schema(body):
    """Return ``(id, name, encoding, data)`` of a Schema record's body."""
    rec = Cursor(body)
    sid = rec.u16()
    return sid, rec.string(), rec.string(), rec.blob()


def read_channel(body):
    """Return a Channel record's body as a dict (id, schema_id, topic, encoding, metadata)."""
    rec = Cursor(body)
    cid, sid = rec.u16(), rec.u16()
    topic, encoding = rec.string(), rec.string()
    meta = {}
    meta_data = Cursor(rec.blob())
    while meta_data.pos < len(meta_data.data):
        key = meta_data.string()
        meta[key] = meta_data.string()
    return {'id': cid, 'schema_id': sid, 'topic': topic, 'encoding': encoding,
            'metadata': meta}


def read_message_time(body):
    """Return ``(channel id, log time)`` of a Message record's body."""
    rec = Cursor(body)
    cid = rec.u16()
    rec.u32()                               # sequence
    return cid, rec.u64()


# ---------------------------------------------------------------------------- chunks
def read_chunk_header(body):
    """
    Return the fields of a Chunk record's body and where its compressed records start.

    Returns
    -------
    dict
        ``start``, ``end`` (message times), ``usize``, ``crc``, ``compression``,
        ``csize`` and ``records`` (the offset in ``body`` of the compressed records).

    """
    cur = Cursor(body)
    start, end, usize = cur.u64(), cur.u64(), cur.u64()
    crc = cur.u32()
    compression = cur.string()
    csize = cur.u64()
    return {'start': start, 'end': end, 'usize': usize, 'crc': crc,
            'compression': compression, 'csize': csize, 'records': cur.pos}


def records_offset(chunk_offset, compression):
    """File offset of a chunk's compressed records, from the chunk record's offset."""
    return chunk_offset + RECORD_HEAD + 40 + len(compression)


def chunk_crc(records):
    """Return the CRC32 of a chunk's uncompressed records, as the Chunk record stores it."""
    return crc32(records)


def _zstd():
    if sys.version_info >= (3, 14):
        from compression import zstd
    else:
        from backports import zstd
    return zstd


def decompress_chunk(data, compression, size, crc=0):
    """
    Return a chunk's uncompressed records, checked against its size and CRC32.

    Parameters
    ----------
    data : bytes
        The compressed records.
    compression : str
        ``''``, ``'lz4'`` or ``'zstd'``.
    size : int
        The uncompressed size the chunk states.
    crc : int, optional
        The CRC32 the chunk states; 0 (none) is not checked.

    Raises
    ------
    ValueError
        An unknown compression, a size or a checksum that does not match ("chunk
        checksum mismatch").

    """
    if compression == '':
        out = data
    elif compression == 'zstd':
        out = _zstd().decompress(data)
    elif compression == 'lz4':
        import lz4.frame
        out = lz4.frame.decompress(data)
    else:
        raise ValueError(f'unsupported chunk compression {compression!r}')
    if len(out) != size:
        raise ValueError(f'chunk size mismatch: expected {size} bytes, got {len(out)}')
    if crc and chunk_crc(out) != crc:
        raise ValueError('chunk checksum mismatch: the records do not match the CRC32 '
                         'in the chunk')
    return out


def read_chunk_crc(f, chunk_offset):
    """Return the ``uncompressed_crc`` field of the chunk record at ``chunk_offset``."""
    f.seek(chunk_offset + CRC_OFFSET)
    raw = f.read(4)
    if len(raw) != 4:
        raise ValueError(f'truncated chunk header at offset {chunk_offset}')
    return struct.unpack('<I', raw)[0]


def read_chunk(f, chunk_offset, compression, compressed_size, size, check_crc=True):
    """
    Return the uncompressed records of the chunk record at ``chunk_offset`` of a file.

    The chunk's compression and sizes are those of its index (or header); the CRC is
    read from the chunk and checked unless ``check_crc`` is false.

    """
    crc = read_chunk_crc(f, chunk_offset) if check_crc else 0
    f.seek(records_offset(chunk_offset, compression))
    data = f.read(compressed_size)
    if len(data) != compressed_size:
        raise ValueError('the chunk is cut short')
    return decompress_chunk(data, compression, size, crc)


def read_message_index(f, offset):
    """
    Return the message offsets of the MessageIndex record at ``offset`` of a file, or None.

    None when no such record is there (the caller walks the chunk instead).

    """
    f.seek(offset)
    head = f.read(RECORD_HEAD + 2 + 4)
    if len(head) != 15 or head[0] != OP_MESSAGE_INDEX:
        return None
    (size,) = struct.unpack_from('<I', head, 11)
    body = f.read(size)
    if len(body) != size or size % 16:
        return None
    return np.frombuffer(body, dtype='<u8').reshape(-1, 2)[:, 1]
