"""Topics of several channels (two recorders, a restarted publisher): when they read as one series.

MCAP lets channels share a topic, each with its own schema. A topic is read as the union of its
channels' messages in ``log_time`` order, each message decoded by its own channel's schema, as
the ``mcap`` library and Foxglove read it. Whatever takes a topic as one series of one type of
message (frames, tables, the stages' inputs) needs its channels to carry one type: their schemas
have one name and encoding, or are all image types (:mod:`starlog.codecs.images`; each frame decoded
by its own schema). :func:`topic_conflict` says, in one line, when they do not (of the channels
that hold messages: an empty channel has nothing to merge); the readers refuse such a topic as a
series with that line, and ``starlog verify`` reports the same line.
"""

from __future__ import annotations

from collections.abc import Iterable

from mcap.records import Channel, Schema

from starlog.codecs.images import is_image_schema

__all__ = ["message_kind", "topic_conflict"]

#: What the ``mcap`` library and Foxglove do with a topic whose channels' schemas differ.
OTHER_READERS = ("the mcap library and Foxglove read every channel's messages on the topic, each by its own schema "
                 "(Foxglove lists the topic under its first channel's schema)")


def message_kind(schema: Schema | None, message_encoding: str) -> tuple[str, str]:
    """The type of message a channel carries, as far as reading its topic as one series goes: ``("image", "")``
    for an image type, else the schema's name and encoding (no schema: ``""`` and the message encoding)."""
    if schema is None:
        return "", message_encoding
    if is_image_schema(schema.name):
        return "image", ""
    return schema.name, schema.encoding


def _describe(schema: Schema | None, message_encoding: str, ids: list[int]) -> str:
    what = f"{schema.name!r} ({schema.encoding}" if schema is not None else f"no schema ({message_encoding}"
    return f"{what}; channel{'s' if len(ids) > 1 else ''} {', '.join(map(str, ids))})"


def topic_conflict(topic: str, channels: Iterable[tuple[Channel, Schema | None]]) -> str | None:
    """One line naming ``topic`` and its channels' schemas when they cannot be read as one series; else None.

    ``channels``: each channel of the topic with its schema (None: schemaless).
    """
    kinds: dict[tuple[str, str], tuple[Schema | None, str, list[int]]] = {}
    for channel, schema in sorted(channels, key=lambda pair: pair[0].id):
        kind = message_kind(schema, channel.message_encoding)
        kinds.setdefault(kind, (schema, channel.message_encoding, []))[2].append(channel.id)
    if len(kinds) < 2:
        return None
    listed = [_describe(*found) for found in kinds.values()]
    return (f"the channels of topic {topic!r} have schemas that cannot be read as one series: "
            f"{', '.join(listed[:-1])} and {listed[-1]}; starlog reads them message by message (info, cat, filter, "
            "flatten), not as one series of frames or table rows (export, the stages)")
