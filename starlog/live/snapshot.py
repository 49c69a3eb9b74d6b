"""The part of a growing log that ``starlog live`` read, as a complete log of its own.

When the following stops before the log's footer (Ctrl-C while its writer goes on, or a writer
that stopped mid-record), the layers need a complete base holding exactly the frames they were
computed from. :func:`snapshot_log` copies the file's records up to that offset into a new log:
schemas, channels and metadata, and every chunk **byte for byte** with its message index records
(rebuilt from the chunk when it had none), so the new log is cut into the same chunks, and hence
into the same blocks, as the frames live processed; its summary is built from what was copied.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import BinaryIO

from mcap.opcode import Opcode
from mcap.records import Channel, ChunkIndex, Metadata, Schema

from starlog.io.chunks import decode_chunk
from starlog.io.layout import MAGIC, MESSAGE_HEADER, RECORD_HEADER, chunk_header, parse_message_index, parse_record
from starlog.io.record_walk import walk_records
from starlog.io.writer import LogWriter

__all__ = ["snapshot_log"]


def snapshot_log(source: BinaryIO, end: int, output: str | os.PathLike[str], *,
                 damaged: frozenset[int] = frozenset()) -> Path:
    """Copy the records of the open file ``source`` before offset ``end`` (a record boundary) into a complete log
    at ``output`` (module docstring), but the chunks at the offsets ``damaged``; returns ``output``."""
    f = source
    with LogWriter(output, force=True) as out:
        pending: tuple[int, int, dict[int, list[tuple[int, int]]]] | None = None
        schemas: set[int] = set()
        channels: set[int] = set()
        for offset, opcode, length, body in walk_records(f, len(MAGIC), end, bodies=_BODIES):
            if opcode == Opcode.MESSAGE_INDEX and pending is not None and body is not None:
                channel_id, entries = parse_message_index(body)
                pending[2][channel_id] = entries
                continue
            if pending is not None:
                _copy_chunk(f, out, *pending, known=(schemas, channels))
                pending = None
            if opcode == Opcode.CHUNK and offset not in damaged:
                pending = (offset, RECORD_HEADER.size + length, {})
            elif opcode == Opcode.MESSAGE and body is not None:
                channel_id, _, log_time, _ = MESSAGE_HEADER.unpack_from(body, 0)
                out.copy_messages(RECORD_HEADER.pack(opcode, length) + body, {channel_id: [(log_time, 0)]})
            elif opcode == Opcode.SCHEMA and body is not None:
                schema = parse_record(body, Schema)
                if schema.id not in schemas:
                    schemas.add(schema.id)
                    out.copy_schema(schema)
            elif opcode == Opcode.CHANNEL and body is not None:
                channel = parse_record(body, Channel)
                if channel.id not in channels:
                    channels.add(channel.id)
                    out.copy_channel(channel)
            elif opcode == Opcode.METADATA and body is not None:
                record = parse_record(body, Metadata)
                out.add_metadata(record.name, dict(record.metadata))
        if pending is not None:
            _copy_chunk(f, out, *pending, known=(schemas, channels))
    return Path(output)


_BODIES = {Opcode.SCHEMA, Opcode.CHANNEL, Opcode.METADATA, Opcode.MESSAGE_INDEX, Opcode.MESSAGE}


def _copy_chunk(f: BinaryIO, out: LogWriter, offset: int, length: int, indices: dict[int, list[tuple[int, int]]], *,
                known: tuple[set[int], set[int]]) -> None:
    """One chunk record copied as it is, with its message index records (rebuilt when it had none); the schemas
    and channels it defines that are new, copied before it (a log's first chunk of a channel may define it)."""
    f.seek(offset)
    raw = f.read(length)
    body = memoryview(raw)[RECORD_HEADER.size:]
    start, end, size, _, compression, data_len, _ = chunk_header(body)
    schemas, channels = known
    rebuild = not indices
    if rebuild or not set(indices) <= channels:
        contents = decode_chunk(body)
        for at, opcode, _, record in walk_records(contents.data):
            if record is None:
                continue
            if opcode == Opcode.MESSAGE and rebuild:
                channel_id, _, log_time, _ = MESSAGE_HEADER.unpack_from(record, 0)
                indices.setdefault(channel_id, []).append((log_time, at))
            elif opcode == Opcode.SCHEMA and (schema := parse_record(record, Schema)).id not in schemas:
                schemas.add(schema.id)
                out.copy_schema(schema)
            elif opcode == Opcode.CHANNEL and (channel := parse_record(record, Channel)).id not in channels:
                channels.add(channel.id)
                out.copy_channel(channel)
    ci = ChunkIndex(message_start_time=start, message_end_time=end, chunk_start_offset=0, chunk_length=length,
                    message_index_offsets={}, message_index_length=0, compression=compression,
                    compressed_size=data_len, uncompressed_size=size)
    out.copy_chunk_record(raw, ci, indices)
