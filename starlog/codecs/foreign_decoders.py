"""Decoding protobuf, ROS 2 (``cdr``) and ROS 1 (``ros1msg``) messages, starlog's own and other tools'.

The decoders come from the mcap support libraries (``mcap-protobuf-support``,
``mcap-ros2-support``, ``mcap-ros1-support``), built once per schema and cached process-wide
(keyed by the schema's name, encoding and bytes, so two logs with different schemas under one
id never share a decoder). Foxglove's own protobuf types use the compiled classes of
``foxglove-schemas-protobuf``, which parse faster than classes built from a descriptor set.
starlog's protobuf star tables decode to the dict of their JSON form (:mod:`starlog.codecs.star_tables`),
so every reader sees them as it sees the JSON tables of earlier logs.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from typing import Any

import numpy as np
from mcap.records import Schema

from starlog.codecs.star_tables import schema_codec

__all__ = ["message_decoder", "schema_key", "to_plain"]

_DECODERS: dict[tuple[str, str, str, bytes], Callable[[bytes], Any] | None] = {}


def schema_key(schema: Schema | None, message_encoding: str) -> tuple[str, str, str, bytes]:
    """What identifies a decoder: message encoding, schema name, schema encoding and schema bytes."""
    if schema is None:
        return (message_encoding, "", "", b"")
    return (message_encoding, schema.name, schema.encoding, bytes(schema.data))


def _foxglove_class(name: str) -> type | None:
    """The compiled ``foxglove_schemas_protobuf`` class of ``foxglove.X`` (None if there is none)."""
    if not name.startswith("foxglove."):
        return None
    short = name.split(".", 1)[1]
    try:
        module = importlib.import_module(f"foxglove_schemas_protobuf.{short}_pb2")
    except ImportError:
        return None
    return getattr(module, short, None)


def _protobuf_decoder(schema: Schema) -> Callable[[bytes], Any]:
    cls = _foxglove_class(schema.name)
    if cls is not None:

        def decode(data: bytes) -> Any:
            message = cls()
            message.ParseFromString(bytes(data))
            return message

        return decode
    from mcap_protobuf.decoder import DecoderFactory

    decoder = DecoderFactory().decoder_for("protobuf", schema)
    if decoder is None:
        raise ValueError(f"the protobuf schema {schema.name!r} cannot be loaded")
    return decoder


def _build(schema: Schema | None, message_encoding: str) -> Callable[[bytes], Any] | None:
    if schema is None:
        return None
    if message_encoding == "protobuf" and schema.encoding == "protobuf":
        codec = schema_codec(schema)
        return codec.to_dict if codec is not None else _protobuf_decoder(schema)
    if message_encoding == "cdr" and schema.encoding == "ros2msg":
        from mcap_ros2.decoder import DecoderFactory as Ros2Factory

        return Ros2Factory().decoder_for("cdr", schema)
    if message_encoding == "ros1" and schema.encoding == "ros1msg":
        from mcap_ros1.decoder import DecoderFactory as Ros1Factory

        return Ros1Factory().decoder_for("ros1", schema)
    return None


def message_decoder(schema: Schema | None, message_encoding: str) -> Callable[[bytes], Any] | None:
    """A function decoding one message's bytes of this schema to an object, or None for unknown encodings.

    Raises ``ValueError`` (or the support library's error) when the schema itself cannot be parsed.
    """
    key = schema_key(schema, message_encoding)
    if key not in _DECODERS:
        _DECODERS[key] = _build(schema, message_encoding)
    return _DECODERS[key]


def to_plain(value: Any) -> Any:
    """A decoded message (protobuf, ROS 1/2 object, dict) as dicts, lists, bytes and Python scalars."""
    if isinstance(value, dict):
        return {str(k): to_plain(v) for k, v in value.items()}
    if isinstance(value, (bytes, bytearray, memoryview)):
        return bytes(value)
    if isinstance(value, (list, tuple)):
        return [to_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, (str, int, float, bool)) or value is None:
        return value
    descriptor = getattr(value, "DESCRIPTOR", None)
    if descriptor is not None and hasattr(descriptor, "fields"):  # protobuf message
        return {f.name: to_plain(getattr(value, f.name)) for f in descriptor.fields}
    slots = getattr(value, "__slots__", None)
    if slots:  # ROS 1 (genpy) and ROS 2 (mcap-ros2-support) messages
        return {name: to_plain(getattr(value, name)) for name in slots if not name.startswith("_")}
    if hasattr(value, "__iter__"):  # protobuf repeated containers
        return [to_plain(v) for v in value]
    return str(value)
