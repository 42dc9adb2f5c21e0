"""
Messages appended to a rosbags MCAP bag in ~1 µs each: the bytes rosbags writes, faster.

rosbags' ``Writer.write`` costs ~4.5 µs per message here (a connection lookup that
compares dataclasses, a BytesIO and five small writes per record, min/max and counts
on two objects), more than the filter step of a replay that writes three messages per
measurement. :class:`MessageAppender` writes the same MCAP Message record (opcode
0x05: channel id, sequence 0, log and publish time both the record time, the data)
into rosbags' own open chunk with one ``struct`` call, keeps the chunk's message
index as rosbags does, closes a chunk by rosbags' own ``close_chunk`` at the same
size rosbags does (more than 2^20 bytes), and hands the counts and time bounds to
the writer and its storage in bulk (:meth:`MessageAppender.flush`, called before
the writer is closed). Everything else (schemas, channels, chunk and summary
records, metadata.yaml) is rosbags' own code, so the file is byte for byte the one
rosbags writes for the same calls (a test compares them).

The appender leans on rosbags' MCAP writer internals (``chunk``, ``channel_stats``,
``close_chunk``; rosbags is pinned in constraints.txt). When the open storage is not
the MCAP writer it knows (another rosbags version, another storage, per-message
compression), :attr:`MessageAppender.fast` is False and every message goes through
``Writer.write``.
"""

import struct
from typing import Dict, Union

from rosbags.rosbag2 import Writer
from rosbags.rosbag2.enums import CompressionMode

try:  # the MCAP storage writer of the rosbags version kf_train is pinned to
    from rosbags.rosbag2.storage_mcap import McapWriter
except ImportError:  # pragma: no cover - another rosbags: the slow path
    McapWriter = None

MESSAGE_OPCODE = 0x05
# opcode, record length; channel id, sequence, log time, publish time (MCAP Message).
_RECORD_HEADER = struct.Struct('<BQHIQQ')
_RECORD_FIELDS = _RECORD_HEADER.size - 9   # the Message fields before its data: 22 bytes
CHUNK_BYTES = 2 ** 20
"""rosbags closes a chunk once it holds more than this many bytes."""
NO_START = 2 ** 63 - 1
"""rosbags' 'no message yet' start time (its end time starts at 0)."""


def _supported(writer: Writer) -> bool:
    """Return whether the writer's storage is the rosbags MCAP writer this module knows."""
    storage = writer.storage
    if McapWriter is None or type(storage) is not McapWriter:
        return False
    if writer.compression_mode == CompressionMode.MESSAGE:
        return False
    chunk = getattr(storage, 'chunk', None)
    return all(hasattr(chunk, name) for name in ('bio', 'msgs', 'message_start_time',
                                                 'message_end_time')) and all(
        hasattr(storage, name) for name in ('channel_stats', 'close_chunk',
                                            'message_start_time', 'message_end_time'))


class MessageAppender:
    """Writes messages to an open rosbags ``Writer`` (see the module doc)."""

    def __init__(self, writer: Writer):
        """Append to ``writer`` (open, its connections added); call :meth:`flush` before close."""
        self._writer = writer
        self.fast = _supported(writer)
        self._counts: Dict[int, int] = {}
        self._start = NO_START
        self._end = 0
        if self.fast:
            self._storage = writer.storage
            self._take_chunk()

    def _take_chunk(self) -> None:
        """Start filling rosbags' current chunk (after its earlier messages, if any)."""
        chunk = self._storage.chunk
        self._chunk = chunk
        self._bio_write = chunk.bio.write
        self._offset = chunk.bio.tell()
        self._index = chunk.msgs
        self._chunk_start = chunk.message_start_time
        self._chunk_end = chunk.message_end_time

    def write(self, connection, timestamp: int, data: Union[bytes, bytearray, memoryview]
              ) -> None:
        """Write a serialized message on ``connection`` (one of the writer's) at ``timestamp``."""
        if not self.fast:
            self._writer.write(connection, timestamp, data)
            return
        cid = connection.id
        offset = self._offset
        self._index[cid].append((timestamp, offset))
        size = len(data)
        self._bio_write(_RECORD_HEADER.pack(MESSAGE_OPCODE, _RECORD_FIELDS + size, cid, 0,
                                            timestamp, timestamp))
        self._bio_write(data)
        self._offset = offset = offset + _RECORD_HEADER.size + size
        self._counts[cid] = self._counts.get(cid, 0) + 1
        if timestamp < self._chunk_start:
            self._chunk_start = timestamp
        if timestamp > self._chunk_end:
            self._chunk_end = timestamp
        if offset > CHUNK_BYTES:
            self._sync_chunk()
            self._storage.close_chunk()
            self._take_chunk()

    def _sync_chunk(self) -> None:
        """Give rosbags' chunk and storage the time bounds kept here."""
        chunk = self._chunk
        chunk.message_start_time = self._chunk_start
        chunk.message_end_time = self._chunk_end
        self._start = min(self._start, self._chunk_start)
        self._end = max(self._end, self._chunk_end)

    def flush(self) -> None:
        """Hand the counts and time bounds to rosbags (before ``writer.close()``)."""
        if not self.fast:
            return
        self._sync_chunk()
        writer, storage = self._writer, self._storage
        for cid, count in self._counts.items():
            writer.counts[cid] += count
            storage.channel_stats[cid] += count
        if self._counts:
            storage.message_start_time = min(storage.message_start_time, self._start)
            storage.message_end_time = max(storage.message_end_time, self._end)
            writer.min_timestamp = min(writer.min_timestamp, self._start)
            writer.max_timestamp = max(writer.max_timestamp, self._end)
        self._counts = {}
        self._start, self._end = NO_START, 0
