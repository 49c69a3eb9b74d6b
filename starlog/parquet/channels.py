"""Export of any channel as a flat table, and of any image channel as ``frames.parquet``.

A message (JSON, protobuf, ROS 1 or ROS 2) becomes one row: ``log_time`` first, then its fields
with nested fields as ``a.b`` columns and arrays as list columns (an array of messages becomes a
list of structs). Rows are written in row groups as they are read (memory flat in log length).
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from starlog.errors import (
    ChannelNotFoundError,
    InvalidInputError,
    InvalidParameterError,
    MessageDecodeError,
    OutputExistsError,
)
from starlog.io.foreign import message_decoder, to_plain
from starlog.io.frames import cached_image_decoder
from starlog.io.images import IMAGE_SCHEMAS, is_image_schema
from starlog.io.messages import decode_json
from starlog.io.reader import LogReader
from starlog.io.writer import atomic_output

__all__ = ["flatten", "export_topic", "export_image_frames", "parquet_writer", "topic_file_name", "topic_table"]


@contextmanager
def parquet_writer(path: Path, schema: pa.Schema) -> Iterator[pq.ParquetWriter]:
    """A ``ParquetWriter`` on ``path``, closed at the end; on an error in the block, closed without raising
    again (its last bytes may not be writable either: the block's error is the one to report)."""
    writer = pq.ParquetWriter(path, schema, compression="zstd")
    try:
        yield writer
    except BaseException:
        with suppress(Exception):
            writer.close()
        raise
    writer.close()


def flatten(plain: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """Nested dicts → ``a.b`` keys; lists stay lists."""
    out: dict[str, Any] = {}
    for key, value in plain.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            out.update(flatten(value, f"{name}."))  # an empty message adds no column
        else:
            out[name] = value
    return out


def topic_file_name(topic: str) -> str:
    """``/camera/info`` → ``camera.info`` (the Parquet file's stem)."""
    return topic.strip("/").replace("/", ".") or "root"


def _rows(log: LogReader, topic: str, start: int | None = None, end: int | None = None
          ) -> Iterator[dict[str, Any]]:
    decoders: dict[int, Any] = {}
    for schema, channel, message in log.raw_messages([topic], start=start, end=end):
        if channel.id not in decoders:
            decoder = decode_json if channel.message_encoding == "json" else \
                message_decoder(schema, channel.message_encoding)
            if decoder is None:
                raise InvalidParameterError(
                    f"{log.path}: channel {topic!r} has message encoding {channel.message_encoding!r} "
                    f"(schema {schema.name if schema else 'none'!r}); starlog exports JSON, protobuf, ROS 1 and ROS 2.")
            decoders[channel.id] = decoder
        try:
            value = to_plain(decoders[channel.id](message.data))
        except Exception as err:
            raise MessageDecodeError(log.path, topic, message.log_time, f"{type(err).__name__}: {err}") from err
        if not isinstance(value, dict):
            value = {"value": value}
        yield {"log_time": message.log_time, **flatten(value)}


def _row_tables(rows: Iterator[dict[str, Any]], row_group_rows: int, where: str) -> Iterator[pa.Table]:
    """Rows in tables of ``row_group_rows`` (columns fixed by the first; later new keys are an error)."""
    schema: pa.Schema | None = None
    batch: list[dict[str, Any]] = []
    try:
        for row in rows:
            batch.append(row)
            if len(batch) >= row_group_rows:
                table = pa.Table.from_pylist(batch, schema=schema)
                schema = table.schema
                batch.clear()
                yield table
        if batch:
            yield pa.Table.from_pylist(batch, schema=schema)
    except (pa.ArrowInvalid, pa.ArrowTypeError) as err:
        raise InvalidInputError(f"{where}: the messages do not fit one table ({err}).") from err


def _write_rows(rows: Iterator[dict[str, Any]], path: Path, row_group_rows: int, force: bool) -> int:
    """Stream rows into a Parquet file, a row group at a time."""
    writer: pq.ParquetWriter | None = None
    written = 0
    with atomic_output(path, force=force) as tmp:
        try:
            for table in _row_tables(rows, row_group_rows, path.name):
                if writer is None:
                    writer = pq.ParquetWriter(tmp, table.schema, compression="zstd")
                writer.write_table(table)
                written += table.num_rows
        except BaseException:
            if writer is not None:
                with suppress(Exception):  # the block's error is the one to report
                    writer.close()
            raise
        if writer is None:
            pq.write_table(_EMPTY, tmp)
        else:
            writer.close()
    return written


_EMPTY = pa.table({"log_time": pa.array([], pa.int64())})
_ROW_GROUP_ROWS = 16_384


def topic_table(log: LogReader, topic: str, *, start: int | None = None, end: int | None = None,
                row_group_rows: int = _ROW_GROUP_ROWS) -> pa.Table:
    """The flat table ``export --topic`` writes for ``topic``, in memory: messages with ``start <= log_time <
    end`` only (the rest of the log is not read). Columns are typed as the export types them."""
    if topic not in log.topics:
        raise ChannelNotFoundError(log.path, topic, log.topics)
    tables = list(_row_tables(_rows(log, topic, start, end), row_group_rows, topic))
    return pa.concat_tables(tables) if tables else _EMPTY


def export_topic(log: LogReader, topic: str, output_dir: Path, *, force: bool = False,
                 row_group_rows: int = _ROW_GROUP_ROWS) -> tuple[str, int]:
    """Write ``<topic>.parquet`` (see :func:`topic_file_name`) with one flattened row per message."""
    if topic not in log.topics:
        raise ChannelNotFoundError(log.path, topic, log.topics)
    name = topic_file_name(topic)
    path = output_dir / f"{name}.parquet"
    if path.exists() and not force:
        raise OutputExistsError(path)
    return name, _write_rows(_rows(log, topic), path, row_group_rows, force)


def _frame_rows(log: LogReader, topics: list[str]) -> Iterator[dict[str, Any]]:
    index: dict[str, int] = {}
    for schema, channel, message in log.raw_messages(topics):
        decode = cached_image_decoder(schema, channel.message_encoding)
        n = index[channel.topic] = index.get(channel.topic, -1) + 1
        try:
            decoded = decode(message.data) if decode is not None else None
        except InvalidInputError as err:
            raise MessageDecodeError(log.path, channel.topic, message.log_time, str(err)) from err
        image = decoded.image if decoded is not None else np.zeros((0, 0))
        yield {"log_time": message.log_time, "topic": channel.topic, "frame": n,
               "width": int(image.shape[1]), "height": int(image.shape[0]),
               "dtype": str(image.dtype), "schema": schema.name if schema else "",
               "kind": IMAGE_SCHEMAS.get(schema.name if schema else "", ""),
               "frame_id": decoded.frame_id if decoded else "",
               "stamp": decoded.stamp if decoded and decoded.stamp is not None else -1}


def export_image_frames(log: LogReader, output_dir: Path, *, force: bool = False,
                        row_group_rows: int = 16_384) -> int | None:
    """``frames.parquet`` from every image channel of a log without starlog's frame channel (None if it has none).

    Columns: log_time, topic, frame (index in its channel), width, height, dtype (of the decoded
    mono frame), schema, kind (raw / compressed), frame_id, stamp (the message's own time in ns, -1 if unset).
    """
    topics = [c.topic for c in log.channels() if is_image_schema(c.schema_name)]
    if not topics:
        return None
    path = output_dir / "frames.parquet"
    if path.exists() and not force:
        raise OutputExistsError(path)
    return _write_rows(_frame_rows(log, topics), path, row_group_rows, force)
