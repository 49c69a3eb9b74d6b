"""``starlog verify``'s checks of message contents, channel by channel, and of the channels that share a topic.

Every message is decoded as its channel's schema says: JSON against its JSON Schema, protobuf,
ROS 1 and ROS 2 messages by their decoders, images with one size per topic; each channel's
``log_time`` order is counted, and frames of a topic must not share a ``log_time``.
"""

from __future__ import annotations

import json
from array import array
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from mcap.records import Channel, Schema

from starlog.codecs.foreign_decoders import message_decoder
from starlog.io.frames import cached_image_decoder
from starlog.codecs.images import is_image_schema
from starlog.codecs.json_schema import compile_json_schema
from starlog.codecs.json_messages import decode_json
from starlog.io.shared_topics import OTHER_READERS, topic_conflict
from starlog.io.verify_report import VerifyReport

__all__ = ["ChannelChecks", "ChannelState"]

#: ``problem(kind, detail, severity=..., offset=..., channel=..., log_time=...)``: reports one problem.
Report = Callable[..., None]


@dataclass
class ChannelState:
    """What the messages of one channel read so far tell, and how its next ones are checked."""

    topic: str
    count: int = 0
    last: int = -1
    out_of_order: int = 0
    frame_times: array | None = None  # an image channel's log_times, to compare with its topic's other channels
    checker: Callable[[Any], str | None] | None = None
    decode: Callable[[bytes], Any] | None = None
    kind: str = "bytes"


class ChannelChecks:
    """The checks of each message's contents, with the state of each channel (its schema and channel records
    are those of ``schemas`` and ``channels``, filled as the file is read)."""

    def __init__(self, schemas: dict[int, Schema], channels: dict[int, Channel], report: VerifyReport,
                 problem: Report) -> None:
        self.schemas, self.channels, self.report, self.problem = schemas, channels, report, problem
        self.states: dict[int, ChannelState] = {}
        self.counted: dict[int, int] = {}  # messages per channel id
        self.times: list[int] = []  # [first, last] over every message
        self.unknown_channels: set[int] = set()
        self.frame_shapes: dict[str, tuple[Any, ...]] = {}  # per image topic: its first frame's shape and dtype

    def state(self, cid: int, offset: int) -> ChannelState | None:
        if cid in self.states:
            return self.states[cid]
        channel = self.channels.get(cid)
        if channel is None:
            if cid not in self.unknown_channels:
                self.unknown_channels.add(cid)
                self.problem("unknown_channel", f"messages of channel id {cid}, which no channel record defines",
                             offset=offset)
            return None
        state = self.states[cid] = ChannelState(channel.topic)
        schema = self.schemas.get(channel.schema_id)
        if channel.schema_id != 0 and schema is None:
            self.problem("missing_schema", f"the channel refers to schema {channel.schema_id}, which is not defined",
                         offset=offset, channel=channel.topic)
            return state
        try:
            self.prepare(state, schema, channel.message_encoding)
        except Exception as err:
            self.problem("bad_schema", f"its schema {schema.name if schema else ''!r} cannot be used to decode "
                         f"({type(err).__name__}: {err})", offset=offset, channel=channel.topic)
        return state

    def prepare(self, state: ChannelState, schema: Schema | None, encoding: str) -> None:
        if schema is not None and is_image_schema(schema.name):
            state.decode, state.kind = cached_image_decoder(schema, encoding), "image"
            if state.decode is not None:
                state.frame_times = array("q")
                return
        if encoding == "json":
            state.kind = "json"
            if schema is not None and schema.encoding == "jsonschema":
                try:
                    state.checker = compile_json_schema(json.loads(schema.data))
                except (ValueError, TypeError, KeyError) as err:
                    self.problem("schema_not_checked", f"JSON messages are decoded but not checked against schema "
                                 f"{schema.name!r} ({err})", severity="note", channel=state.topic)
            return
        state.decode = message_decoder(schema, encoding)
        state.kind = "decoded" if state.decode is not None else "bytes"
        if state.decode is None:
            self.problem("not_decoded", f"message encoding {encoding!r} with schema "
                         f"{schema.name if schema else 'none'!r}: starlog checks only the container",
                         severity="note", channel=state.topic)

    def message(self, cid: int, log_time: int, data: bytes, offset: int) -> None:
        self.report.messages += 1
        self.counted[cid] = self.counted.get(cid, 0) + 1
        self.times = [min(self.times[0], log_time), max(self.times[1], log_time)] if self.times else [log_time] * 2
        state = self.state(cid, offset)
        if state is None:
            return
        state.count += 1
        if log_time < state.last:
            state.out_of_order += 1
        elif log_time == state.last and state.kind == "image":
            self.problem("duplicate_frame_time", "two frames at one log_time (stages need strictly increasing "
                         "frame times)", offset=offset, channel=state.topic, log_time=log_time)
        state.last = max(state.last, log_time)
        if state.frame_times is not None:
            state.frame_times.append(log_time)
        try:
            self.content(state, data, offset, log_time)
        except Exception as err:  # protobuf DecodeError, ROS deserialisation errors, InvalidInputError ...
            self.problem("decode_error", f"the message does not decode: {type(err).__name__}: {err}", offset=offset,
                         channel=state.topic, log_time=log_time)

    def content(self, state: ChannelState, data: bytes, offset: int, log_time: int) -> None:
        if state.kind == "image" and state.decode is not None:
            image = state.decode(data).image
            shape = (image.shape, image.dtype)
            first = self.frame_shapes.setdefault(state.topic, shape)  # a topic's channels are one series of frames
            if image.ndim != 2:
                self.problem("image_size", "the frame is not a 2-D image", offset=offset, channel=state.topic,
                             log_time=log_time)
            elif shape != first:
                self.problem("image_size_changed", f"a {image.shape[1]}x{image.shape[0]} {image.dtype} frame in a "
                             f"channel of {first[0][1]}x{first[0][0]} {first[1]} frames",
                             offset=offset, channel=state.topic, log_time=log_time)
        elif state.kind == "json":
            value = decode_json(data)
            if state.checker is not None:
                problem = state.checker(value)
                if problem:
                    self.problem("json_schema", f"the message does not match its schema ({problem})", offset=offset,
                                 channel=state.topic, log_time=log_time)
        elif state.decode is not None:
            state.decode(data)

    def check_topics(self) -> None:
        """Channels sharing a topic: an error when the schemas of those with messages cannot be read as one series
        (the readers refuse such a topic as a series, :mod:`starlog.io.shared_topics`), else a note; image
        channels' frames of one topic must not share a log_time (the stages read them as one series of strictly
        increasing times)."""
        by_topic: dict[str, list[int]] = {}
        for cid in sorted(self.channels):
            by_topic.setdefault(self.channels[cid].topic, []).append(cid)
        for topic, ids in by_topic.items():
            if len(ids) < 2:
                continue
            channels = [self.channels[cid] for cid in ids if self.counted.get(cid)]  # as the readers count them
            conflict = topic_conflict(topic, [(c, self.schemas.get(c.schema_id) if c.schema_id else None)
                                              for c in channels])
            if conflict is not None:
                self.problem("topic_schemas_differ", f"{conflict}; {OTHER_READERS}", channel=topic)
                continue
            self.problem("shared_topic", f"channels {', '.join(map(str, ids))} share the topic (valid; read as one "
                         "series in log_time order, each message by its own channel's schema, as the mcap library "
                         "and Foxglove read it)", severity="note", channel=topic)
            self.check_frame_times(topic, [self.states[c] for c in ids if c in self.states])

    def check_frame_times(self, topic: str, states: list[ChannelState]) -> None:
        """Frames of two channels of one image topic at one log_time (each channel's own are checked as read)."""
        times = [np.unique(np.frombuffer(s.frame_times, dtype=np.int64)) for s in states if s.frame_times]
        if len(times) < 2:
            return
        values, counts = np.unique(np.concatenate(times), return_counts=True)
        shared = counts > 1
        if np.any(shared):
            self.problem("duplicate_frame_time", f"{int(np.sum(counts[shared] - 1))} frames share a log_time with a "
                         "frame of another channel of the topic (stages read its channels' frames as one series, "
                         "whose times must increase strictly)", channel=topic, log_time=int(values[shared][0]))
