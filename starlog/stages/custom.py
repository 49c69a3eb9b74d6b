"""Running a declared stage (:mod:`starlog.replay.declaration`) on a log, with the guarantees of the built-in stages.

The input channel is read in batches of consecutive messages, undecoded; each batch is decoded
(images to 2-D arrays, per-star tables to structured arrays), handed message by message to the
stage's function, and its records encoded — in this process, or with ``workers > 1`` in worker
processes (:mod:`starlog.replay.pool`: they die with this process), results coming back in
order. The records are written in message order by the stage's :class:`~starlog.io.LogWriter`
(through :func:`~starlog.replay.layer.extend_log`), which checks each one against its
channel's JSON Schema; so memory is bounded by a few batches, the output is written atomically
with the stage's provenance, and its bytes depend neither on ``workers`` nor on the run.
"""

from __future__ import annotations

import functools
import os
import sys
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from mcap.records import Channel, Message as McapMessage, Schema

from starlog.errors import (
    ChannelNotFoundError,
    InvalidInputError,
    InvalidParameterError,
    MessageDecodeError,
    StageFunctionError,
    StarlogError,
)
from starlog.io.frames import iter_frames
from starlog.codecs.images import choose_image_topic, is_image_schema
from starlog.codecs.json_messages import encode_json
from starlog.io.reader import ChannelSummary, LogReader, decode_payload, source_path
from starlog.codecs.star_tables import decode_table
from starlog.io.writer import LogWriter
from starlog.replay.declaration import KINDS, Message, Output, Stage
from starlog.replay.channels import check_messages_read
from starlog.replay.pool import ordered_map, process_pool
from starlog.replay.progress import progress
from starlog.replay.window import windowed
from starlog.replay.layer import extend_log

__all__ = ["StageSummary", "choose_inputs", "run_stage"]

#: Messages per batch: what a worker gets at once (and what the serial path decodes at once).
BATCH_MESSAGES = 32

Raw = tuple[Schema | None, Channel, McapMessage]


@dataclass
class StageSummary:
    """What :func:`run_stage` read and wrote."""

    stage: str
    version: str
    inputs: list[str]
    messages: int = 0
    records: dict[str, int] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return {"stage": self.stage, "version": self.version, "inputs": list(self.inputs),
                "messages": self.messages, "records": dict(self.records), "notes": list(self.notes)}


def run_stage(
    stage: Stage,
    input_path: Any,
    output_path: str | os.PathLike[str],
    *,
    options: dict[str, Any] | None = None,
    input_topic: str | None = None,
    workers: int = 1,
    force: bool = False,
    flatten: bool = False,
    compression: str = "zstd",
    show_progress: bool = False,
    start: str | int | None = None,
    end: str | int | None = None,
) -> StageSummary:
    """Run ``stage`` on every message of its input channel(s); the output is a layer holding the stage's channels
    (with ``flatten``: the whole chain as one file).

    With ``start`` / ``end`` (ns, ``"12.5s"`` or ``"frame:N"`` of the first input channel;
    :mod:`starlog.io.timerange`) the stage runs on that window of the log, as the built-in
    stages do, and its channels hold only that range.

    ``options`` override the stage's defaults; ``input_topic`` chooses the channel when the
    stage's ``reads`` matches several, or ``"all"`` reads each of them in turn (see
    :func:`choose_inputs`). ``input_path`` may be a path or a :class:`~starlog.io.LogView`.
    With ``workers > 1`` batches run in worker processes (the stage must be importable by
    :attr:`Stage.reference`, else it runs here); the bytes written do not depend on ``workers``.
    """
    def first_input(log: LogReader, _: dict[str, Any]) -> str:
        return choose_inputs(stage, log, input_topic)[0][0]

    run = windowed(first_input)(_run_whole)
    return run(input_path, output_path, stage, options=options, input_topic=input_topic, workers=workers, force=force,
               flatten=flatten, compression=compression, show_progress=show_progress, start=start, end=end)


def _run_whole(input_path: Any, output_path: str | os.PathLike[str], stage: Stage, *, options: dict[str, Any] | None,
               input_topic: str | None, workers: int, force: bool, flatten: bool, compression: str,
               show_progress: bool) -> StageSummary:
    """:func:`run_stage` on the whole of ``input_path`` (a window of the log, when a range was asked for)."""
    chosen = stage.resolve_options(options)
    with LogReader(input_path) as log:
        topics, note = choose_inputs(stage, log, input_topic)
        images = {topic: is_image_schema(log.channel(topic).schema_name) for topic in topics}
        plan = [(topic, tuple((out.topic_for(topic), out) for out in stage.outputs)) for topic in topics]
        written = [t for _, outputs in plan for t, _ in outputs]
        if len(set(written)) < len(written):
            raise InvalidParameterError(f"stage {stage.name!r}: its output topics {written} collide (to read several "
                                        "channels, its topics need {name}, the last part of the input topic).")
        parameters = {"stage_version": stage.version, "function": stage.reference,
                      "input": topics[0] if len(topics) == 1 else topics, "options": chosen}
        summary = StageSummary(stage.name, stage.version, topics, records=dict.fromkeys(written, 0),
                               notes=[note] if note else [])
        with extend_log(log, output_path, stage=stage.name, parameters=parameters, force=force, flatten=flatten,
                        compression=compression) as (_, out):
            for topic, outputs in plan:
                ids = [out.add_channel(t, o.message_type) for t, o in outputs]
                batch = _Batch(stage.reference, tuple(sys.path), str(source_path(input_path)), topic, images[topic],
                               chosen, outputs)
                summary.messages += _run_channel(log, out.writer, stage, batch, ids, summary.records, workers=workers,
                                                 show_progress=show_progress)
            summary.notes += [n for n in log.notes if n not in summary.notes]
        return summary


def _run_channel(log: LogReader, writer: LogWriter, stage: Stage, batch: _Batch, ids: list[int],
                 records_written: dict[str, int], *, workers: int, show_progress: bool) -> int:
    """Every message of ``batch.topic`` through the stage, its records written in order; the messages read."""
    total = log.channel(batch.topic).message_count
    parallel = workers > 1 and total > BATCH_MESSAGES and stage.importable()
    batches = _raw_batches(log, batch.topic, copy=parallel)
    if parallel:
        results = _run_parallel(batch, batches, workers)
    else:
        results = (batch.run(first, raws, stage) for first, raws in batches)
    read = 0
    for log_time, records in progress((r for done in results for r in done), total=total,
                                      description=f"{stage.name} {batch.topic}", enabled=show_progress):
        read += 1
        for channel_id, (topic, _), data in zip(ids, batch.outputs, records):
            if data is not None:
                writer.write(channel_id, log_time=log_time, data=data)
                records_written[topic] += 1
    return check_messages_read(log, batch.topic, read)


def choose_inputs(stage: Stage, log: LogReader, requested: str | None) -> tuple[list[str], str | None]:
    """The channel(s) a run reads, and a note when they were chosen for the user.

    ``requested`` must exist and match the stage's ``reads``; ``"all"``: every channel that
    matches. Without it: the topic ``reads`` names; for ``"image"``, ``/camera/image`` else the
    log's only image channel; for a kind or schema, its only channel (several: an error listing them).
    """
    channels = log.channels()
    reads = stage.reads
    if requested == "all":
        matching = [c.topic for c in channels if (c.topic == reads if reads.startswith("/") else _matches(c, reads))]
        if not matching:
            raise InvalidInputError(f"{log.path} has no {reads} channel for stage {stage.name!r} "
                                    f"(channels: {', '.join(c.topic for c in channels) or 'none'}).")
        return matching, None
    if reads == "image":
        topic, note = choose_image_topic(log.path, channels, requested)
        return [topic], note
    if requested is None and reads.startswith("/"):
        requested = reads
    by_topic = {c.topic: c for c in channels}
    if requested is not None:
        if requested not in by_topic:
            raise ChannelNotFoundError(log.path, requested, list(by_topic))
        if not reads.startswith("/") and not _matches(by_topic[requested], reads):
            raise InvalidParameterError(f"{log.path}: channel {requested!r} has schema "
                                        f"{by_topic[requested].schema_name!r}; stage {stage.name!r} reads {reads}.")
        return [requested], None
    matching = [c.topic for c in channels if _matches(c, reads)]
    if len(matching) == 1:
        return matching, f"{stage.name} reads {matching[0]}, the log's only {reads} channel."
    if not matching:
        raise InvalidInputError(f"{log.path} has no {reads} channel for stage {stage.name!r} "
                                f"(channels: {', '.join(by_topic) or 'none'}).")
    raise InvalidParameterError(f"{log.path} has several {reads} channels ({', '.join(matching)}); choose one for "
                                f"stage {stage.name!r} with --input-topic TOPIC, or read each with --input-topic all "
                                '(in a run config: input_topic = "TOPIC" or "all").')


def _matches(channel: ChannelSummary, reads: str) -> bool:
    if reads == "image":
        return is_image_schema(channel.schema_name)
    return channel.schema_name == KINDS.get(reads, reads)


def _raw_batches(log: LogReader, topic: str, *, copy: bool) -> Iterator[tuple[int, list[Raw]]]:
    """``(index of the first message, messages)`` of ``topic`` in time order, :data:`BATCH_MESSAGES` at a time.

    ``copy``: payloads as bytes (to send to a worker process), else views of the log's chunks.
    """
    batch: list[Raw] = []
    first = 0
    for raw in log.raw_messages([topic], views=not copy):
        batch.append(raw)
        if len(batch) == BATCH_MESSAGES:
            yield first, batch
            first += len(batch)
            batch = []
    if batch:
        yield first, batch


def _run_parallel(batch: _Batch, batches: Iterable[tuple[int, list[Raw]]], workers: int
                  ) -> Iterator[list[tuple[int, tuple[bytes | None, ...]]]]:
    with process_pool(workers, preload=["starlog.stages.custom"]) as pool:
        yield from ordered_map(pool, batch.run, ((first, raws) for first, raws in batches), window=2 * workers)


# ---------------------------------------------------------------- one batch (here or in a worker process)
#: The star tables a stage gets as the structured arrays of the built-in stages: schema name → kind.
_TABLES: dict[str, str] = {"starlog.Centroids": "centroids", "starlog.Detections": "detections",
                           "starlog.Tracks": "tracks"}


@dataclass(frozen=True)
class _Batch:
    """Decode a batch of raw messages, call the stage on each, encode its records; picklable for workers."""

    reference: str
    search_path: tuple[str, ...]
    log_name: str
    topic: str
    image: bool
    options: dict[str, Any]
    outputs: tuple[tuple[str, Output], ...]

    def run(self, first: int, raws: list[Raw], stage: Stage | None = None
            ) -> list[tuple[int, tuple[bytes | None, ...]]]:
        """``(log_time, encoded record per output or None)`` of each message of the batch."""
        if stage is None:
            from starlog.replay.plugins import cached_reference

            stage = cached_reference(self.reference, self.search_path)
        return [(m.log_time, self._records(stage, m)) for m in self._messages(first, raws)]

    def _messages(self, first: int, raws: list[Raw]) -> Iterator[Message]:
        if self.image:
            source = _BatchSource(Path(self.log_name), raws)
            for frame in iter_frames(source, self.topic, first_index=first):
                yield Message(self.topic, frame.log_time, frame.index, frame.image)
            return
        for index, (schema, channel, message) in enumerate(raws, first):
            kind = _TABLES.get(schema.name if schema else "")
            if kind is not None:
                try:
                    table = decode_table(schema, channel.message_encoding, message.data)
                except InvalidInputError as err:
                    raise MessageDecodeError(Path(self.log_name), channel.topic, message.log_time, str(err)) from err
                yield Message(self.topic, message.log_time, index, _structured(table.rows, kind), table.header)
            else:
                payload = decode_payload(Path(self.log_name), schema, channel, message)
                fields = payload if isinstance(payload, dict) else {}
                yield Message(self.topic, message.log_time, index, payload, fields)

    def _records(self, stage: Stage, message: Message) -> tuple[bytes | None, ...]:
        where = f"stage {stage.name!r} on {message.topic!r} message {message.index} (log_time {message.log_time})"
        try:
            result = stage.function(message, **self.options)
        except StarlogError:
            raise
        except Exception as err:  # the user's code: say where it failed
            raise StageFunctionError(f"{where}: {type(err).__name__}: {err}") from err
        per_output = self._split(result, where)
        return tuple(_encode(record, output, topic, where) for (topic, output), record in zip(self.outputs, per_output))

    def _split(self, result: Any, where: str) -> list[Any]:
        """The function's result as one record (or None) per output channel."""
        if len(self.outputs) == 1:
            return [result]
        if result is None:
            return [None] * len(self.outputs)
        if not isinstance(result, dict):
            raise StageFunctionError(f"{where}: a stage writing several channels returns a dict topic -> record, "
                                     f"got {type(result).__name__}.")
        names = {topic: k for k, (topic, _) in enumerate(self.outputs)}
        names.update({output.topic: k for k, (_, output) in enumerate(self.outputs)})
        unknown = sorted(set(result) - set(names))
        if unknown:
            raise StageFunctionError(f"{where}: returned records for undeclared channel(s) {unknown}.")
        records: list[Any] = [None] * len(self.outputs)
        for key, record in result.items():
            records[names[key]] = record
        return records


def _encode(record: Any, output: Output, topic: str, where: str) -> bytes | None:
    if record is None:
        return None
    if not output.is_json:
        if isinstance(record, (bytes, bytearray, memoryview)):
            return bytes(record)
        if hasattr(record, "SerializeToString"):
            return bytes(record.SerializeToString(deterministic=True))
        raise StageFunctionError(f"{where}: {topic} takes bytes or a protobuf message, got {type(record).__name__}.")
    if not isinstance(record, dict):
        raise StageFunctionError(f"{where}: a record for {topic} is a dict, got {type(record).__name__}.")
    try:
        return encode_json(record)
    except (TypeError, ValueError) as err:
        raise StageFunctionError(f"{where}: its record for {topic} cannot be written as JSON ({err}).") from err


def _structured(rows: np.ndarray | None, kind: str) -> np.ndarray:
    """A star table's decoded rows → the structured array of the built-in stages (fields copied by name)."""
    dtype = _dtype(kind)
    out = np.zeros(0 if rows is None else rows.size, dtype=dtype)
    for name in dtype.names or ():
        if rows is not None and rows.size:
            out[name] = rows[name]
    return out


@functools.cache
def _dtype(kind: str) -> np.dtype[Any]:
    if kind == "centroids":
        from starlog.centroiding.table import CENTROID_DTYPE

        return CENTROID_DTYPE
    if kind == "detections":
        from starlog.detect.detection import DETECTION_DTYPE

        return DETECTION_DTYPE
    from starlog.tracking.table import TRACK_DTYPE

    return np.dtype([*((n, TRACK_DTYPE.fields[n][0]) for n in TRACK_DTYPE.names or ()), ("brightest", np.bool_)])


@dataclass
class _BatchSource:
    """A batch of raw messages as the frame reader's message source (:func:`~starlog.io.frames.iter_frames`)."""

    path: Path
    raws: list[Raw]

    def raw_messages(self, topics: Iterable[str], *, start: int | None = None, end: int | None = None,
                     views: bool = False) -> Iterator[Raw]:
        return iter(self.raws)

    def add_note(self, note: str) -> None:
        """Notes (e.g. lossy compression) are the log reader's to give; a batch has no one to tell."""
