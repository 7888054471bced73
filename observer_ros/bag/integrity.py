# observer_ros.bag.integrity: chunk CRCs in the MCAP bags this project writes, and their check.
"""
Chunk checksums (CRC32) of MCAP bags: write them, and say whether a bag has them.

rosbags' MCAP writer (0.11) leaves the ``uncompressed_crc`` field of every Chunk record
at 0, which the MCAP specification reads as "no checksum", so a value changed on disk
is read back silently. :class:`CrcWriter` is rosbags' ``Writer`` whose MCAP storage fills
that field in: it computes the CRC32 of each chunk's records (the uncompressed bytes, as
the specification defines it) and writes it into the chunk's header once rosbags has
written the chunk. The file is otherwise byte for byte rosbags' own, so it opens with
rosbags and any MCAP reader, and the readers (rosbags' and :mod:`.mcap_records`, the
MCAP parser behind the chunk by chunk reader) then check it.

:func:`chunk_crcs` reads the field of every chunk of a bag, for the evaluation's
"this bag has no checksums" note.

"""

from pathlib import Path
import struct

from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.rosbag2.storage_mcap import McapWriter

from .mcap_records import chunk_crc, CRC_OFFSET, read_chunk, read_chunk_crc

__all__ = ['CrcWriter', 'CrcMcapWriter', 'chunk_crcs', 'fill_chunk_crcs', 'checksum_note',
           'CRC_OFFSET']


class CrcMcapWriter(McapWriter):
    """rosbags' MCAP storage writer that writes the CRC32 of each chunk."""

    def close_chunk(self):
        """Close the pending chunk as rosbags does, then write its CRC into its header."""
        crc = chunk_crc(self.chunk.bio.getbuffer())
        start = self.bio.tell()
        super().close_chunk()
        end = self.bio.tell()
        self.bio.seek(start + CRC_OFFSET)
        self.bio.write(struct.pack('<I', crc))
        self.bio.seek(end)


class CrcWriter(Writer):
    """
    rosbags' ``Writer`` whose MCAP files carry chunk CRCs (sqlite3 bags are unchanged).

    Used exactly as ``rosbags.rosbag2.Writer``.

    """

    STORAGE_PLUGINS = {**Writer.STORAGE_PLUGINS, StoragePlugin.MCAP: CrcMcapWriter}


def chunk_crcs(storage):
    """
    Return the ``uncompressed_crc`` field of every chunk of an open MCAP storage.

    Parameters
    ----------
    storage : rosbags.rosbag2.storage_mcap.McapReader
        An open MCAP storage reader (it has ``bio`` and the chunk index ``chunks``).

    Returns
    -------
    crcs : list of int
        One per chunk, in file order; 0 means the chunk has no checksum.

    """
    return [read_chunk_crc(storage.bio, chunk.chunk_start_offset) for chunk in storage.chunks]


def fill_chunk_crcs(path):
    """
    Write the CRC32 of every chunk of an MCAP file whose CRC field is 0, in place.

    The CRC is that of the chunk's uncompressed records, as :class:`CrcMcapWriter`
    writes it; nothing else in the file changes (the 4 bytes of each chunk's field).
    A chunk that already has a CRC keeps it. Returns the number of chunks filled.

    """
    from rosbags.rosbag2.storage_mcap import McapReader
    reader = McapReader(Path(path))
    reader.open()
    try:
        todo = []
        bio = reader.bio
        for chunk, crc in zip(reader.chunks, chunk_crcs(reader)):
            if crc:
                continue
            data = read_chunk(bio, chunk.chunk_start_offset, chunk.compression,
                              chunk.compressed_size, chunk.uncompressed_size,
                              check_crc=False)
            todo.append((chunk.chunk_start_offset + CRC_OFFSET, chunk_crc(data)))
    finally:
        reader.close()
    with open(path, 'r+b') as f:
        for at, crc in todo:
            f.seek(at)
            f.write(struct.pack('<I', crc))
    return len(todo)


def checksum_note(path, storage, crcs):
    """
    Return a note for the evaluation when a bag's data is not checksummed, else ''.

    Parameters
    ----------
    path : str or Path
        The bag (for the message).
    storage : str
        ``'mcap'`` or ``'sqlite3'``.
    crcs : list of int or None
        :func:`chunk_crcs` of an MCAP bag (None when they could not be read).

    """
    path = Path(path)
    if storage != 'mcap':
        return (f'{path}: a {storage} bag has no chunk checksums: a value changed on disk '
                'would not be detected')
    if crcs is None or not crcs:
        return ''
    missing = sum(1 for c in crcs if c == 0)
    if missing == len(crcs):
        return (f'{path}: the bag has no chunk CRCs (written by rosbags or a recorder that '
                'leaves them 0): a value changed on disk would not be detected')
    if missing:
        return (f'{path}: {missing} of {len(crcs)} chunks have no CRC: a value changed in '
                'them would not be detected')
    return ''
