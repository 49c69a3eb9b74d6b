"""Reading starlog logs: channel summaries, decoded messages streamed in constant memory, provenance.

A log is one MCAP file or a chain of them (a base and the layers stages wrote on it, see
:mod:`starlog.io.chain`); :class:`LogReader` reads a chain as the one log its files make together,
each file checked as :class:`~starlog.io.mcap_file.McapFile` checks it. A message whose payload
does not decode or does not satisfy its schema raises :class:`~starlog.errors.MessageDecodeError`
/ :class:`~starlog.errors.InvalidMessageError` naming its topic and ``log_time``. Messages that
starlog's writer checked against their schema (their channel is marked ``starlog.validated``) are
not checked again when their chunk's CRC and the summary's CRC were verified: the bytes are those
that passed the check. Every other JSON message (foreign logs, logs of older versions,
``validate_crcs=False``) is checked as it is decoded.

A topic may have several channels (two recorders, a restarted publisher): it reads as the union of
their messages in ``log_time`` order, each decoded by its own channel's schema, and its
:class:`ChannelSummary` counts them all. A topic whose channels carry messages of different types
(:mod:`starlog.io.shared_topics`) is refused as a series (:class:`~starlog.errors.MixedTopicError`);
:meth:`LogReader.raw_messages` with ``mixed=True`` still hands out its messages one by one.

Star tables (:mod:`starlog.codecs.star_tables`) are protobuf in the logs starlog writes and JSON in older
ones; either way :meth:`LogReader.messages` gives them as the dict of their JSON form and
:meth:`LogReader.tables` as a header and a structured array of rows. A protobuf message is checked
by decoding it.

A :class:`LogView` reads a log through a time window (a stage run with ``--start``/``--end``):
every read, channel counts included, keeps only the messages inside it.
"""

from __future__ import annotations

import heapq
import itertools
import json
import os
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np
from mcap.records import Channel, Message, Schema

from starlog.errors import (
    ChannelNotFoundError,
    CorruptLogError,
    InvalidInputError,
    InvalidMessageError,
    InvalidParameterError,
    MessageDecodeError,
    MixedTopicError,
)
from starlog.io.chain import BASE_METADATA_NAME, LayerBase, base_reference, open_chain
from starlog.codecs.foreign_decoders import message_decoder
from starlog.io.frames import Frame, SkippedFrame, decode_image_message, iter_frames
from starlog.codecs.images import is_image_schema
from starlog.io.channel_summary import ChannelSummary, channel_summaries
from starlog.io.mcap_file import McapFile
from starlog.codecs.json_schema import compile_json_schema
from starlog.codecs.json_messages import decode_json
from starlog.io.provenance import PROVENANCE_METADATA_NAME, Provenance
from starlog.io.shared_topics import topic_conflict
from starlog.codecs.star_tables import STAR_TABLES, decode_table, json_table
from starlog.io.timerange import END_OF_TIME, ResolvedRange
from starlog.io.writer import VALIDATED_METADATA_KEY

__all__ = ["ChannelSummary", "DecodedMessage", "LogReader", "LogSource", "LogView", "TableMessage"]

@dataclass(frozen=True)
class LogView:
    """The log at ``path`` seen through ``window``: only its messages with ``start_ns <= log_time < end_ns``."""

    path: Path
    window: ResolvedRange

    def __str__(self) -> str:
        return f"{self.path} [{self.window.describe()}]"


#: What names a log to read: a path (a whole log, or the newest layer of a chain) or a :class:`LogView`.
LogSource = str | os.PathLike[str] | LogView


def source_path(source: LogSource) -> Path:
    """The file a log source names (the newest of its chain)."""
    return source.path if isinstance(source, LogView) else Path(source)


@dataclass(frozen=True)
class DecodedMessage:
    """A message and its decoded payload: a dict (JSON), a 2-D array (an image; read-only when it is a view of
    the log's bytes) or a protobuf object."""

    topic: str
    log_time: int
    sequence: int
    payload: Any


@dataclass(frozen=True)
class TableMessage:
    """A star-table message (:data:`~starlog.codecs.star_tables.STAR_TABLES`) as its header fields and its rows
    (a structured array; None for a header-only type), whatever its encoding."""

    topic: str
    log_time: int
    sequence: int
    header: dict[str, Any]
    rows: np.ndarray | None


def decode_payload(
    path: Path, schema: Schema | None, channel: Channel, message: Message,
    check: Callable[[Any], str | None] | None = None,
) -> Any:
    """Decode one message by its schema.

    JSON → dict; an image type (:mod:`starlog.codecs.images`) → 2-D mono ndarray; other protobuf,
    ROS 2 (cdr) and ROS 1 messages → the object their support library decodes; anything else → bytes.
    ``check`` (a :func:`~starlog.codecs.json_schema.compile_json_schema` checker) validates a JSON
    payload; a violation raises :class:`InvalidMessageError`.
    """
    try:
        if schema is not None and is_image_schema(schema.name):
            decoded = decode_image_message(schema, channel.message_encoding, message.data)
            if decoded is not None:
                return decoded.image
        if channel.message_encoding == "json":
            value = decode_json(message.data)
            if check is not None:
                problem = check(value)
                if problem:
                    raise InvalidMessageError(path, channel.topic, message.log_time,
                                              f"it does not match its schema {schema.name if schema else ''!r} "
                                              f"({problem}).")
            return value
        decoder = message_decoder(schema, channel.message_encoding)
        if decoder is not None:
            return decoder(bytes(message.data))
    except InvalidMessageError:
        raise
    except (InvalidInputError, ValueError) as err:
        raise MessageDecodeError(path, channel.topic, message.log_time, str(err)) from err
    except Exception as err:  # protobuf's DecodeError is not a ValueError subclass on every backend
        raise MessageDecodeError(path, channel.topic, message.log_time, f"{type(err).__name__}: {err}") from err
    return bytes(message.data)


def _decoded(path: Path, channel: Channel, message: Message, decode: Callable[[], Any]) -> Any:
    """``decode()``, its InvalidInputError raised as the MessageDecodeError naming the message."""
    try:
        return decode()
    except InvalidInputError as err:
        raise MessageDecodeError(path, channel.topic, message.log_time, str(err)) from err


class LogReader:
    """Open a starlog log (one file, or the newest layer of a chain) for reading.

    Parameters
    ----------
    source : path-like or LogView
        An MCAP file, or a :class:`LogView` of one. A layer is read with every file of its chain.
    validate_crcs : bool
        Check the summary's and every chunk's CRC (default). A mismatch raises
        :class:`CorruptLogError` / :class:`CorruptChunkError`.
    validate_messages : bool or "all"
        Check JSON messages against their embedded JSON Schema as they are decoded (default):
        those that starlog checked when writing them only when their CRCs could not be verified;
        ``"all"``: every one, whoever wrote it.
    chain : bool
        Read a layer with its chain (default); False reads the one file alone.

    Raises
    ------
    LogNotFoundError, TruncatedLogError, CorruptLogError, BaseMismatchError

    Examples
    --------
    >>> with LogReader("sim.mcap") as log:  # doctest: +SKIP
    ...     for message in log.messages("/camera/image"):
    ...         image = message.payload  # 2-D uint16 array
    """

    def __init__(self, source: LogSource, *, validate_crcs: bool = True, validate_messages: bool | str = True,
                 chain: bool = True) -> None:
        if validate_messages not in (True, False, "all"):
            raise ValueError(f"validate_messages must be True, False or 'all', got {validate_messages!r}.")
        self.path = source_path(source)
        self.window = source.window if isinstance(source, LogView) else None
        self._lo, self._hi = (self.window.start_ns, self.window.end_ns) if self.window else (0, END_OF_TIME)
        self._validate_messages = validate_messages
        self._checkers: dict[int, Callable[[Any], str | None] | None] = {}
        self._extents: dict[int, list[int]] | None = None
        self.files: list[McapFile] = open_chain(self.path, validate_crcs=validate_crcs, follow=chain)
        self._whole_chain = chain
        self._file_of: dict[int, McapFile] = {}
        self._schemas: dict[int, Schema] = {}
        self._channels: dict[int, Channel] = {}
        for file in self.files:
            self._schemas.update(file.summary.schemas)
            self._channels.update(file.summary.channels)
            self._file_of.update(dict.fromkeys(file.summary.channels, file))
        self._by_topic: dict[str, list[int]] = {}  # topic -> its channels' ids, ascending
        for cid in sorted(self._channels):
            self._by_topic.setdefault(self._channels[cid].topic, []).append(cid)
        self._conflicts: dict[str, str | None] = {}
        self.notes: list[str] = []
        for file in self.files:
            for note in file.notes:
                self.add_note(note if len(self.files) == 1 else f"{file.path.name}: {note}")

    def add_note(self, note: str) -> None:
        """Record a one-line note about how the log was read (shown once, in reading order)."""
        if note not in self.notes:
            self.notes.append(note)

    def __enter__(self) -> LogReader:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    def close(self) -> None:
        """Close every file."""
        for file in self.files:
            file.close()

    # ------------------------------------------------------------------ what the log holds
    @property
    def fully_indexed(self) -> bool:
        """Whether every message is reachable through the files' indexes (chunk and message indexes).

        False for valid but unusual files: no summary, chunks without message indexes, messages
        outside chunks. Such files are read in full all the same, by scanning.
        """
        return all(file.fully_indexed for file in self.files)

    @property
    def topics(self) -> list[str]:
        """Every topic once, in the order of their first channels' ids."""
        return list(self._by_topic)

    def has_topic(self, topic: str) -> bool:
        """Whether the log has a channel named ``topic``."""
        return topic in self._by_topic

    def topic_conflict(self, topic: str) -> str | None:
        """One line naming ``topic`` and its channels' schemas when they cannot be read as one series
        (:func:`~starlog.io.shared_topics.topic_conflict`; channels without messages in the file do not
        count); None for a topic of one channel or one type."""
        if topic not in self._conflicts:
            ids = self._channel_ids(topic)
            if len(ids) > 1:
                held = {cid for file in self.files for cid, e in file.channel_extents().items() if e[0]}
                ids = [cid for cid in ids if cid in held]
            channels = [self._channels[cid] for cid in ids]
            self._conflicts[topic] = None if len(channels) < 2 else topic_conflict(
                topic, [(c, self._schemas.get(c.schema_id) if c.schema_id else None) for c in channels])
        return self._conflicts[topic]

    def _series_ids(self, topic: str) -> list[int]:
        """The channel ids of ``topic`` read as one series; :class:`MixedTopicError` when their schemas differ."""
        conflict = self.topic_conflict(topic)
        if conflict is not None:
            raise MixedTopicError(self.path, topic, conflict)
        return self._by_topic[topic]

    def _channel_extents(self) -> dict[int, list[int]]:
        if self._extents is None:
            self._extents = {}
            for file in self.files:
                self._extents.update(file.channel_extents(self._lo, self._hi))
        return self._extents

    def channels(self) -> list[ChannelSummary]:
        """Every topic with its schema, message count and time range (in the window, for a view), in the order of
        :attr:`topics`; a topic of several channels counts all of them (:meth:`ChannelSummary.union`)."""
        extents = self._channel_extents()
        summaries: dict[int, ChannelSummary] = {}
        for file in self.files:
            summaries.update(channel_summaries(file.summary, extents))
        return [ChannelSummary.union([summaries[cid] for cid in ids]) for ids in self._by_topic.values()]

    def channel(self, topic: str) -> ChannelSummary:
        """The :class:`ChannelSummary` of ``topic``; :class:`ChannelNotFoundError` if absent."""
        self._channel_ids(topic)
        return next(ch for ch in self.channels() if ch.topic == topic)

    def time_range(self) -> tuple[int, int]:
        """First and last ``log_time`` of the whole log (0, 0 when empty)."""
        extents = [e for e in self._channel_extents().values() if e[0]]
        return (min(e[1] for e in extents), max(e[2] for e in extents)) if extents else (0, 0)

    def message_count(self) -> int:
        """Messages of every channel (in the window, for a view)."""
        return sum(e[0] for e in self._channel_extents().values())

    def _channel_ids(self, topic: str) -> list[int]:
        if topic not in self._by_topic:
            raise ChannelNotFoundError(self.path, topic, self.topics)
        return self._by_topic[topic]

    # ------------------------------------------------------------------ messages
    def raw_messages(
        self, topics: Iterable[str], *, start: int | None = None, end: int | None = None, views: bool = False,
        mixed: bool = False,
    ) -> Iterator[tuple[Schema | None, Channel, Message]]:
        """Undecoded messages of ``topics`` (every channel of each) in ``log_time`` order (ties: file order, the
        chain's first file first), streamed chunk by chunk, each with its own channel and schema.

        ``start`` is inclusive, ``end`` exclusive. Only the chunks holding these topics are read,
        and only those whose time ranges overlap are held in memory at once. A damaged chunk
        raises :class:`CorruptChunkError` naming it. Each ``message.data`` is ``bytes``; with
        ``views``, a read-only ``memoryview`` into the decompressed chunk instead (no copy; it
        keeps the chunk's bytes alive as long as it lives). A topic whose channels' schemas cannot be
        read as one series raises :class:`MixedTopicError`, unless ``mixed`` (the caller handles each
        message by its own schema).
        """
        for schema, channel, message, _ in self._merged_messages(topics, start=start, end=end, mixed=mixed):
            if not views and not isinstance(message.data, bytes):
                message.data = bytes(message.data)
            yield schema, channel, message

    def _merged_messages(
        self, topics: Iterable[str], *, start: int | None, end: int | None, mixed: bool = False,
    ) -> Iterator[tuple[Schema | None, Channel, Message, bool]]:
        """:meth:`raw_messages`, each with whether its chunk's CRC was verified."""
        ids = {cid for topic in topics for cid in (self._channel_ids(topic) if mixed else self._series_ids(topic))}
        lo = max(self._lo, 0 if start is None else start)
        hi = min(self._hi, END_OF_TIME if end is None else end)
        streams = [file.messages(mine, lo, hi) for file in self.files
                   if (mine := {cid for cid in ids if self._file_of[cid] is file})]
        if not streams:
            return
        merged = streams[0] if len(streams) == 1 else heapq.merge(*streams, key=lambda item: item[0][0])
        for (_, _, cid, message), verified in merged:
            channel = self._channels[cid]
            yield (self._schemas.get(channel.schema_id) if channel.schema_id else None), channel, message, verified

    def _trusted(self, channel: Channel) -> bool:
        """Whether the channel's messages were checked by starlog's writer and the summary saying so is intact."""
        return (self._validate_messages is True and self._file_of[channel.id].summary_verified
                and channel.metadata.get(VALIDATED_METADATA_KEY) == "jsonschema")

    def _checker(self, schema: Schema | None) -> Callable[[Any], str | None] | None:
        if not self._validate_messages or schema is None or schema.encoding != "jsonschema":
            return None
        if schema.id not in self._checkers:
            try:
                schema_value = json.loads(schema.data)
            except ValueError as err:
                raise CorruptLogError(self.path, f"the JSON Schema {schema.name!r} in the log cannot be read "
                                                 f"({err}).") from err
            try:
                self._checkers[schema.id] = compile_json_schema(schema_value)
            except (InvalidInputError, ValueError, TypeError, KeyError) as err:  # keywords of other tools' schemas
                self._checkers[schema.id] = None
                self.add_note(f"messages of schema {schema.name!r} are not checked against it ({err}).")
        return self._checkers[schema.id]

    def messages(
        self, topic: str | Iterable[str], *, start: int | None = None, end: int | None = None, stride: int = 1,
    ) -> Iterator[DecodedMessage]:
        """Decoded messages of one topic (or several, interleaved by ``log_time``), streamed.

        A topic of several channels gives all their messages, each decoded by its own channel's schema
        (:class:`MixedTopicError` when their schemas cannot be read as one series). JSON payloads are
        checked against their channel's schema (see ``validate_messages``). With ``stride`` n, only every
        n-th message (the first, the n+1-th, ...) is decoded and yielded.
        """
        if stride < 1:
            raise InvalidParameterError(f"stride must be >= 1; got {stride}.")
        topics = [topic] if isinstance(topic, str) else list(topic)
        trusted = {cid: self._trusted(c) for cid, c in self._channels.items()}
        merged = self._merged_messages(topics, start=start, end=end)
        for schema, channel, message, verified in itertools.islice(merged, 0, None, stride):
            check = None if verified and trusted[channel.id] else self._checker(schema)
            yield DecodedMessage(
                channel.topic, message.log_time, message.sequence,
                decode_payload(self._file_of[channel.id].path, schema, channel, message, check),
            )

    def tables(self, topic: str | Iterable[str], *, start: int | None = None, end: int | None = None
               ) -> Iterator[TableMessage]:
        """Messages of star-table channels (:data:`~starlog.codecs.star_tables.STAR_TABLES`) as
        :class:`TableMessage`: the rows as one structured array, no dict per star; JSON messages are
        checked as :meth:`messages` checks them. A row field an older log lacks reads as its default.

        Raises :class:`InvalidInputError` when a channel is not a star table.
        """
        topics = [topic] if isinstance(topic, str) else list(topic)
        for name in topics:
            for cid in self._series_ids(name):
                schema = self._schemas.get(self._channels[cid].schema_id)
                if schema is None or schema.name not in STAR_TABLES:
                    raise InvalidInputError(f"{name} is not a star table ({schema.name if schema else 'no schema'}); "
                                            f"they are {', '.join(STAR_TABLES)}.")
        trusted = {cid: self._trusted(c) for cid, c in self._channels.items()}
        for schema, channel, message, verified in self._merged_messages(topics, start=start, end=end):
            path = self._file_of[channel.id].path
            if channel.message_encoding == "json":
                check = None if verified and trusted[channel.id] else self._checker(schema)
                value = decode_payload(path, schema, channel, message, check)
                table = _decoded(path, channel, message, lambda: json_table(schema.name, value))
            else:
                table = _decoded(path, channel, message,
                                 lambda: decode_table(schema, channel.message_encoding, message.data))
            yield TableMessage(channel.topic, message.log_time, message.sequence, table.header, table.rows)

    def chunk_message_counts(self, topic: str) -> list[tuple[int, int, int]]:
        """``(message_start_time, message_end_time, count)`` of ``topic`` in each chunk holding it, in time order
        (in the window, for a view).

        Read from the message index records (a few bytes per chunk; no chunk is decompressed but those
        across a bound of the window). A topic of several channels counts them together per chunk.
        """
        ids = self._channel_ids(topic)
        return sorted(count for file in self.files if (mine := {c for c in ids if self._file_of[c] is file})
                      for count in file.chunk_message_counts(mine, self._lo, self._hi))

    def frames(self, topic: str = "/camera/image", *, start: int | None = None, end: int | None = None,
               first_index: int = 0, on_bad: Callable[[SkippedFrame], None] | None = None,
               ) -> Iterator[tuple[int, int, np.ndarray]]:
        """``(frame_index, log_time, image)`` for every image of ``topic`` (``start <= log_time < end``), in time order.

        Any image type of :mod:`starlog.codecs.images` is decoded to a 2-D mono array.
        ``first_index`` numbers the first frame returned (for a block read out of a longer log).
        Raises :class:`InvalidMessageError` when a frame is not 2-D, has another size or pixel type
        than the first, or does not come strictly after the previous frame; with ``on_bad``,
        such a frame is handed to it and left out instead.
        """
        for frame in self.frame_records(topic, start=start, end=end, first_index=first_index, on_bad=on_bad):
            yield frame.index, frame.log_time, frame.image

    def frame_records(self, topic: str = "/camera/image", *, start: int | None = None, end: int | None = None,
                      first_index: int = 0, on_bad: Callable[[SkippedFrame], None] | None = None,
                      ) -> Iterator[Frame]:
        """Like :meth:`frames`, as :class:`~starlog.io.frames.Frame` records (with the message's own stamp)."""
        return iter_frames(self, topic, start=start, end=end, first_index=first_index, on_bad=on_bad)

    # ------------------------------------------------------------------ metadata
    def metadata(self, name: str | None = None) -> list[tuple[str, dict[str, str]]]:
        """MCAP Metadata records ``(name, map)`` of the chain's files in order, each file's in file order,
        optionally only those named ``name``. The records by which layers name their bases are not listed
        (:func:`~starlog.io.chain.base_reference`)."""
        return [record for file in self.files for record in file.metadata(name) if record[0] != BASE_METADATA_NAME]

    def provenance(self) -> list[Provenance]:
        """Every stage recorded in the log, oldest first."""
        out = []
        for _, data in self.metadata(PROVENANCE_METADATA_NAME):
            try:
                record = Provenance.from_metadata(data)
                if not isinstance(record.parameters, dict) or not isinstance(record.channels, list):
                    raise ValueError("parameters must be an object and channels a list")
            except (ValueError, TypeError, RecursionError) as err:
                raise CorruptLogError(self.path, f"a provenance record is damaged ({err}).") from err
            out.append(record)
        return out

    # ------------------------------------------------------------------ the chain
    def layer_base(self) -> LayerBase:
        """What a layer written on this log needs (:class:`~starlog.io.chain.LayerBase`); the SHA-256 of the
        newest file is computed on a thread from now on."""
        if not self._whole_chain and base_reference(self.files[-1]) is not None:
            raise InvalidParameterError(f"{self.path} was opened without its chain: a layer cannot be written on it.")
        return LayerBase.of(self.files)
