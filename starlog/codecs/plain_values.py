"""Any message of any log as plain Python values (what ``starlog cat`` prints, as JSON).

* starlog's own (JSON) channels → the decoded object, as written;
* camera frames (``foxglove.RawImage`` / ``CompressedImage``, ROS 1 and ROS 2 ``sensor_msgs``
  ``Image`` / ``CompressedImage``) → ``{width, height, encoding, bytes, sha256}`` of the pixel
  (or compressed) data instead of the pixels: ``encoding`` is the pixel encoding (``mono16``) or
  the compression format (``png``), ``bytes`` its size and ``sha256`` its checksum;
* other protobuf, ROS 2 (``cdr``) and ROS 1 messages → their fields as dicts, lists and scalars,
  decoded by the support libraries (byte fields as ``bytes``, floats as they are, NaN included);
* anything else (or a message that does not decode) → ``{schema, encoding, bytes}`` (plus ``error``).

Turning the values into strict JSON (bytes, NaN) is the command's: :mod:`starlog.cli.describe`.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from typing import Any

from mcap.records import Channel, Schema

from starlog.codecs.foreign_decoders import message_decoder, to_plain
from starlog.codecs.images import IMAGE_SCHEMAS, RAW, decompress_to_mono, image_fields
from starlog.codecs.json_messages import decode_json
from starlog.codecs.rawimage_wire import parse_raw_image

__all__ = ["PlainValues", "image_summary"]


def _digest(data: bytes | memoryview) -> str:
    return "sha256:" + hashlib.sha256(data).hexdigest()


def image_summary(schema: Schema, message_encoding: str, data: bytes | memoryview) -> dict[str, Any]:
    """``{width, height, encoding, bytes, sha256}`` of one image message (pixels not kept).

    A compressed frame is decoded for its size (``encoding`` is its format).
    """
    if schema.name == "foxglove.RawImage" and message_encoding == "protobuf":
        wire = parse_raw_image(data)
        if wire is not None:
            return {"width": wire.width, "height": wire.height, "encoding": wire.encoding,
                    "bytes": len(wire.data), "sha256": _digest(wire.data)}
    parse = decode_json if message_encoding == "json" else message_decoder(schema, message_encoding)
    if parse is None:
        raise ValueError(f"no decoder for {schema.name} in {message_encoding}")
    fields = image_fields(parse(bytes(data)), schema.name)
    pixels = fields["data"]
    if IMAGE_SCHEMAS[schema.name] == RAW:
        width, height, encoding = int(fields["width"]), int(fields["height"]), str(fields["encoding"])
    else:
        image, _ = decompress_to_mono(pixels, fields["format"])
        height, width = image.shape[:2]
        encoding = str(fields["format"])
    return {"width": int(width), "height": int(height), "encoding": encoding, "bytes": len(pixels),
            "sha256": _digest(pixels)}


class PlainValues:
    """Turns messages into plain Python values, with one decoder per channel built on first use."""

    def __init__(self) -> None:
        self._decoders: dict[int, Callable[[bytes | memoryview], Any]] = {}

    def __call__(self, schema: Schema | None, channel: Channel, data: bytes | memoryview) -> Any:
        decode = self._decoders.get(channel.id)
        if decode is None:
            decode = self._decoders[channel.id] = self._decoder(schema, channel)
        try:
            return decode(data)
        except Exception as err:  # a message that does not decode: say so, keep streaming
            return {**_opaque(schema, channel, data), "error": f"{type(err).__name__}: {err}"}

    @staticmethod
    def _decoder(schema: Schema | None, channel: Channel) -> Callable[[bytes | memoryview], Any]:
        encoding = channel.message_encoding
        if schema is not None and schema.name in IMAGE_SCHEMAS:
            return lambda data: image_summary(schema, encoding, data)
        if encoding == "json":
            return decode_json
        try:
            decode = message_decoder(schema, encoding)
        except Exception:  # a schema its support library cannot parse
            decode = None
        if decode is None:
            return lambda data: _opaque(schema, channel, data)
        return lambda data: to_plain(decode(bytes(data)))


def _opaque(schema: Schema | None, channel: Channel, data: bytes | memoryview) -> dict[str, Any]:
    return {"schema": schema.name if schema is not None else "", "encoding": channel.message_encoding,
            "bytes": len(data)}
