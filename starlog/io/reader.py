"""Reading starlog logs: channel summaries, decoded messages streamed in constant memory, provenance."""

from __future__ import annotations

import os
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any, BinaryIO

import numpy as np
from mcap.exceptions import McapError
from mcap.reader import SeekingReader, make_reader
from mcap.records import Channel, Message, Schema
from mcap.summary import Summary

from starlog.errors import (
    ChannelNotFoundError,
    CorruptLogError,
    InvalidInputError,
    LogNotFoundError,
    MessageDecodeError,
    TruncatedLogError,
)
from starlog.io.messages import decode_json, decode_raw_image
from starlog.io.provenance import PROVENANCE_METADATA_NAME, Provenance
from starlog.io.writer import locate_data_end

__all__ = ["ChannelSummary", "DecodedMessage", "LogReader"]


@dataclass(frozen=True)
class ChannelSummary:
    """One channel of a log, as :meth:`LogReader.channels` lists it.

    ``rate_hz`` is ``(count - 1) / (last - first)`` in Hz (0 for fewer than two messages).
    """

    topic: str
    schema_name: str
    schema_encoding: str
    message_encoding: str
    message_count: int
    first_log_time: int
    last_log_time: int

    @property
    def rate_hz(self) -> float:
        span = self.last_log_time - self.first_log_time
        return (self.message_count - 1) / (span * 1e-9) if self.message_count > 1 and span > 0 else 0.0

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form."""
        return {
            "topic": self.topic,
            "schema": self.schema_name,
            "schema_encoding": self.schema_encoding,
            "message_encoding": self.message_encoding,
            "message_count": self.message_count,
            "first_log_time": self.first_log_time,
            "last_log_time": self.last_log_time,
            "rate_hz": self.rate_hz,
        }


@dataclass(frozen=True)
class DecodedMessage:
    """A message and its decoded payload: a dict (JSON), a 2-D array (RawImage) or a protobuf object."""

    topic: str
    log_time: int
    sequence: int
    payload: Any


def decode_payload(path: Path, schema: Schema | None, channel: Channel, message: Message) -> Any:
    """Decode one message by its schema (JSON → dict, foxglove.RawImage → ndarray)."""
    try:
        if channel.message_encoding == "json":
            return decode_json(message.data)
        if schema is not None and schema.name == "foxglove.RawImage":
            return decode_raw_image(message.data)
        if schema is not None and schema.name == "foxglove.ImageAnnotations":
            from foxglove_schemas_protobuf.ImageAnnotations_pb2 import ImageAnnotations

            annotations = ImageAnnotations()
            annotations.ParseFromString(message.data)
            return annotations
    except (InvalidInputError, ValueError) as err:
        raise MessageDecodeError(path, channel.topic, message.log_time, str(err)) from err
    except Exception as err:  # protobuf's DecodeError is not a ValueError subclass on every backend
        raise MessageDecodeError(path, channel.topic, message.log_time, f"{type(err).__name__}: {err}") from err
    return bytes(message.data)


class LogReader:
    """Open a starlog log for reading.

    Parameters
    ----------
    path : path-like
        An MCAP file with a summary section (every file starlog writes has one).
    validate_crcs : bool
        Check every chunk's CRC as it is read (default). A mismatch raises :class:`CorruptLogError`.

    Raises
    ------
    LogNotFoundError, TruncatedLogError, CorruptLogError

    Examples
    --------
    >>> with LogReader("sim.mcap") as log:  # doctest: +SKIP
    ...     for message in log.messages("/camera/image"):
    ...         image = message.payload  # 2-D uint16 array
    """

    def __init__(self, path: str | os.PathLike[str], *, validate_crcs: bool = True) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise LogNotFoundError(self.path)
        self._file: BinaryIO = open(self.path, "rb")
        try:
            locate_data_end(self.path, self._file)
            self._file.seek(0)
            self._reader = make_reader(self._file, validate_crcs=validate_crcs)
            assert isinstance(self._reader, SeekingReader)
            summary = self._reader.get_summary()
        except (TruncatedLogError, CorruptLogError):
            self._file.close()
            raise
        except (McapError, ValueError, EOFError, OSError) as err:
            self._file.close()
            raise CorruptLogError(self.path, f"its summary cannot be read ({err}); try starlog recover.") from err
        if summary is None:
            self._file.close()
            raise TruncatedLogError(self.path, "it has no summary section")
        self._summary: Summary = summary

    def __enter__(self) -> LogReader:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def close(self) -> None:
        """Close the file."""
        self._file.close()

    @property
    def summary(self) -> Summary:
        """The MCAP summary (schemas, channels, chunk indexes, statistics)."""
        return self._summary

    @property
    def topics(self) -> list[str]:
        """Topics of every channel, in channel-id order."""
        return [self._summary.channels[k].topic for k in sorted(self._summary.channels)]

    def has_topic(self, topic: str) -> bool:
        """Whether the log has a channel named ``topic``."""
        return topic in self.topics

    def channels(self) -> list[ChannelSummary]:
        """Every channel with its schema, message count and time range (from the indexes)."""
        summary = self._summary
        counts = summary.statistics.channel_message_counts if summary.statistics else {}
        first: dict[int, int] = {}
        last: dict[int, int] = {}
        for index in summary.chunk_indexes:
            for cid in index.message_index_offsets:
                first[cid] = min(first.get(cid, index.message_start_time), index.message_start_time)
                last[cid] = max(last.get(cid, index.message_end_time), index.message_end_time)
        out = []
        for cid in sorted(summary.channels):
            ch = summary.channels[cid]
            schema = summary.schemas.get(ch.schema_id)
            out.append(
                ChannelSummary(
                    topic=ch.topic,
                    schema_name=schema.name if schema else "",
                    schema_encoding=schema.encoding if schema else "",
                    message_encoding=ch.message_encoding,
                    message_count=int(counts.get(cid, 0)),
                    first_log_time=first.get(cid, 0),
                    last_log_time=last.get(cid, 0),
                )
            )
        return out

    def channel(self, topic: str) -> ChannelSummary:
        """The :class:`ChannelSummary` of ``topic``; :class:`ChannelNotFoundError` if absent."""
        for ch in self.channels():
            if ch.topic == topic:
                return ch
        raise ChannelNotFoundError(self.path, topic, self.topics)

    def time_range(self) -> tuple[int, int]:
        """First and last ``log_time`` of the whole log (0, 0 when empty)."""
        stats = self._summary.statistics
        if stats is None or stats.message_count == 0:
            return (0, 0)
        return (stats.message_start_time, stats.message_end_time)

    def raw_messages(
        self, topics: Iterable[str], *, start: int | None = None, end: int | None = None
    ) -> Iterator[tuple[Schema | None, Channel, Message]]:
        """Undecoded messages of ``topics`` in ``log_time`` order, streamed chunk by chunk."""
        wanted = list(topics)
        for topic in wanted:
            if topic not in self.topics:
                raise ChannelNotFoundError(self.path, topic, self.topics)
        import zstandard

        try:
            yield from self._reader.iter_messages(topics=wanted, start_time=start, end_time=end)
        except (ValueError, zstandard.ZstdError, RuntimeError) as err:  # CRC mismatch; zstd / lz4 damage
            raise CorruptLogError(
                self.path, f"a damaged chunk cannot be read ({type(err).__name__}: {err}); "
                f"starlog recover {self.path} -o RECOVERED.mcap keeps every intact chunk."
            ) from err
        except (McapError, EOFError) as err:
            raise CorruptLogError(self.path, f"unreadable record: {err}") from err

    def messages(
        self, topic: str | Iterable[str], *, start: int | None = None, end: int | None = None
    ) -> Iterator[DecodedMessage]:
        """Decoded messages of one topic (or several, interleaved by ``log_time``), streamed."""
        topics = [topic] if isinstance(topic, str) else list(topic)
        for schema, channel, message in self.raw_messages(topics, start=start, end=end):
            yield DecodedMessage(
                channel.topic, message.log_time, message.sequence, decode_payload(self.path, schema, channel, message)
            )

    def frames(self, topic: str = "/camera/image") -> Iterator[tuple[int, int, np.ndarray]]:
        """``(frame_index, log_time, image)`` for every image of ``topic``, in time order."""
        for index, message in enumerate(self.messages(topic)):
            yield index, message.log_time, message.payload

    def metadata(self, name: str | None = None) -> list[tuple[str, dict[str, str]]]:
        """MCAP Metadata records ``(name, map)`` in file order, optionally only those named ``name``."""
        out = []
        try:
            for record in self._reader.iter_metadata():
                if name is None or record.name == name:
                    out.append((record.name, dict(record.metadata)))
        except (McapError, ValueError, EOFError) as err:
            raise CorruptLogError(self.path, f"a metadata record is unreadable: {err}") from err
        return out

    def provenance(self) -> list[Provenance]:
        """Every stage recorded in the log, oldest first."""
        return [Provenance.from_metadata(data) for _, data in self.metadata(PROVENANCE_METADATA_NAME)]
