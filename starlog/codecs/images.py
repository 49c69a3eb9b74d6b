"""Camera frames of any common MCAP image type, decoded to 2-D mono arrays.

Image types read (schema name → how):

=====================================  ==========  ===========================================
``foxglove.RawImage``                  protobuf    wire format read directly; also ``json``
``foxglove.CompressedImage``           protobuf    PNG / JPEG / TIFF via OpenCV; also ``json``
``sensor_msgs/msg/Image``              cdr         ROS 2, via mcap-ros2-support
``sensor_msgs/msg/CompressedImage``    cdr         ROS 2
``sensor_msgs/Image``                  ros1        ROS 1, via mcap-ros1-support
``sensor_msgs/CompressedImage``        ros1        ROS 1
=====================================  ==========  ===========================================

Pixel encodings: ``mono8``, ``mono16``, ``8UC1``, ``16UC1`` (big-endian when a ROS message says
``is_bigendian``), ``rgb8``/``bgr8``/``rgba8``/``bgra8`` (and their 16-bit forms) converted to
luma, and the Bayer patterns ``bayer_{rggb,bggr,gbrg,grbg}{8,16}`` demosaiced to grey by
OpenCV. A colour frame turned into mono carries a one-line note (:attr:`DecodedImage.note`).
A mono frame without row padding is a read-only view of the message's bytes (no copy); no
stage writes into a frame it reads.
"""

from __future__ import annotations

import base64
import os
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
from mcap.records import Schema

from starlog.errors import ChannelNotFoundError, InvalidInputError, InvalidParameterError
from starlog.codecs.foreign_decoders import message_decoder
from starlog.codecs.json_messages import decode_json
from starlog.codecs.rawimage_wire import parse_raw_image

__all__ = [
    "IMAGE_SCHEMAS",
    "DecodedImage",
    "image_decoder",
    "is_image_schema",
    "choose_image_topic",
    "image_fields",
]

RAW = "raw"
COMPRESSED = "compressed"

#: Image schema name → raw pixels or compressed bytes.
IMAGE_SCHEMAS: dict[str, str] = {
    "foxglove.RawImage": RAW,
    "foxglove.CompressedImage": COMPRESSED,
    "sensor_msgs/msg/Image": RAW,
    "sensor_msgs/msg/CompressedImage": COMPRESSED,
    "sensor_msgs/Image": RAW,
    "sensor_msgs/CompressedImage": COMPRESSED,
}

DEFAULT_IMAGE_TOPIC = "/camera/image"

_MONO = {"mono8": 1, "8uc1": 1, "mono16": 2, "16uc1": 2}
_COLOUR = {  # encoding -> (channels, OpenCV conversion to grey)
    "rgb8": (3, "RGB2GRAY"), "bgr8": (3, "BGR2GRAY"), "rgba8": (4, "RGBA2GRAY"), "bgra8": (4, "BGRA2GRAY"),
    "rgb16": (3, "RGB2GRAY"), "bgr16": (3, "BGR2GRAY"), "rgba16": (4, "RGBA2GRAY"), "bgra16": (4, "BGRA2GRAY"),
}
_BAYER = {"rggb": "BayerRGGB2GRAY", "bggr": "BayerBGGR2GRAY", "gbrg": "BayerGBRG2GRAY", "grbg": "BayerGRBG2GRAY"}
#: Encodings that announce a big-endian layout in a type with no ``is_bigendian`` field.
_FOREIGN_BYTE_ORDER = {"mono16be", "16uc1be", "mono16_be", "16uc1_be", ">u2", "big_endian", "bigendian"}


@dataclass(frozen=True)
class DecodedImage:
    """One decoded frame: the 2-D mono ``image``, the message's own ``stamp`` (ns, None when unset),
    its ``frame_id`` and a ``note`` when the pixels were converted (colour or Bayer to mono)."""

    image: npt.NDArray[Any]
    stamp: int | None
    frame_id: str
    note: str | None = None


def is_image_schema(schema_name: str) -> bool:
    """Whether a channel of this schema holds camera frames starlog can read."""
    return schema_name in IMAGE_SCHEMAS


# ---------------------------------------------------------------- pixels
def _bit_depth(encoding: str) -> int:
    return 16 if "16" in encoding else 8


def pixels_to_mono(data: bytes | memoryview, width: int, height: int, step: int, encoding: str,
                   big_endian: bool = False) -> tuple[npt.NDArray[Any], str | None]:
    """Raw pixel rows → 2-D native-endian uint8/uint16 array and a note if converted.

    Mono rows without padding in the machine's byte order come back as a view of ``data``
    (read-only when ``data`` is); every other layout as a new array.
    Raises :class:`InvalidInputError` for an unsupported encoding or a geometry that does not fit the data.
    """
    key = encoding.lower()
    if key in _MONO:
        channels, bayer, colour = 1, None, None
    elif key in _COLOUR:
        channels, colour = _COLOUR[key][0], _COLOUR[key][1]
        bayer = None
    elif key.startswith("bayer_") and key[6:10] in _BAYER and key[10:] in ("8", "16"):
        channels, bayer, colour = 1, _BAYER[key[6:10]], None
    else:
        if key in _FOREIGN_BYTE_ORDER:
            raise InvalidInputError(
                f"image encoding {encoding!r} is big-endian; foxglove.RawImage mono16/16UC1 is little-endian. "
                "Swap the bytes when recording (numpy: image.astype('<u2')).")
        known = sorted(set(_MONO) | set(_COLOUR)) + ["bayer_rggb8/16 (and bggr, gbrg, grbg)"]
        raise InvalidInputError(f"unsupported image encoding {encoding!r}; starlog reads {', '.join(known)}.")
    depth = 2 if _bit_depth(key) == 16 else 1
    row_bytes = width * channels * depth
    if width <= 0 or height <= 0 or step < row_bytes:
        raise InvalidInputError(f"invalid image geometry: {width}x{height}, step {step}.")
    if depth > 1 and step % depth:
        raise InvalidInputError(f"row step {step} is not a whole number of {depth}-byte pixels ({encoding}).")
    if len(data) != step * height:
        raise InvalidInputError(f"image data has {len(data)} bytes, expected step × height = {step} × {height}"
                                f" = {step * height}.")
    dtype = np.dtype(">u2" if big_endian else "<u2") if depth == 2 else np.dtype("u1")
    if channels == 1 and bayer is None and step == row_bytes and dtype.isnative:
        return np.frombuffer(data, dtype=dtype).reshape(height, width), None  # the message's own bytes, no copy
    rows = np.frombuffer(data, dtype=np.uint8).reshape(height, step)[:, :row_bytes]
    pixels = rows.copy().view(dtype).astype(dtype.newbyteorder("="), copy=False)
    if channels == 1 and bayer is None:
        return pixels.reshape(height, width), None
    import cv2

    if bayer is not None:
        grey = cv2.cvtColor(pixels.reshape(height, width), getattr(cv2, f"COLOR_{bayer}"))
        return grey, f"Bayer frames ({encoding}) are demosaiced to grey by OpenCV before centroiding."
    grey = cv2.cvtColor(pixels.reshape(height, width, channels), getattr(cv2, f"COLOR_{colour}"))
    return grey, f"colour frames ({encoding}) are converted to grey (luma) before centroiding."


def decompress_to_mono(data: bytes | memoryview, fmt: str) -> tuple[npt.NDArray[Any], str | None]:
    """PNG / JPEG / TIFF bytes → 2-D uint8/uint16 array (colour converted to grey, with a note)."""
    import cv2

    buffer = np.frombuffer(data, dtype=np.uint8)
    image = cv2.imdecode(buffer, cv2.IMREAD_UNCHANGED) if buffer.size else None
    if image is None:
        raise InvalidInputError(f"the compressed image ({fmt or 'format not given'}) cannot be decoded.")
    if image.dtype not in (np.uint8, np.uint16):
        raise InvalidInputError(f"compressed images must hold 8- or 16-bit pixels; got {image.dtype}.")
    if image.ndim == 2:
        return image, None
    if image.ndim == 3 and image.shape[2] in (3, 4):
        code = cv2.COLOR_BGR2GRAY if image.shape[2] == 3 else cv2.COLOR_BGRA2GRAY
        return cv2.cvtColor(image, code), f"colour compressed frames ({fmt}) are converted to grey (luma)."
    if image.ndim == 3 and image.shape[2] == 1:
        return image[:, :, 0], None
    raise InvalidInputError(f"the compressed image has shape {image.shape}; starlog reads mono or colour frames.")


# ---------------------------------------------------------------- message fields
def _ns(sec: int, nsec: int) -> int | None:
    total = int(sec) * 1_000_000_000 + int(nsec)
    return total if total > 0 else None


def _foxglove_stamp(timestamp: Any) -> int | None:
    if isinstance(timestamp, dict):  # JSON encoding: {"sec": .., "nsec": ..}
        return _ns(timestamp.get("sec", 0), timestamp.get("nsec", 0))
    return _ns(timestamp.seconds, timestamp.nanos)


def _ros_stamp(header: Any) -> int | None:
    stamp = header.stamp
    if hasattr(stamp, "nanosec"):  # ROS 2 builtin_interfaces/Time
        return _ns(stamp.sec, stamp.nanosec)
    return _ns(stamp.secs, stamp.nsecs)  # ROS 1 time


def _json_bytes(value: Any) -> bytes:
    if isinstance(value, str):
        return base64.b64decode(value, validate=True)
    if isinstance(value, list):
        return bytes(value)
    raise InvalidInputError("the JSON image's data is neither base64 text nor a list of bytes.")


def image_fields(msg: Any, schema_name: str) -> dict[str, Any]:
    """Common fields of one decoded image message (foxglove protobuf/JSON or ROS 1/2 object)."""
    if isinstance(msg, dict):
        out = {"stamp": _foxglove_stamp(msg.get("timestamp", {})), "frame_id": str(msg.get("frame_id", "")),
               "data": _json_bytes(msg.get("data", ""))}
        for key in ("width", "height", "step"):
            out[key] = int(msg.get(key, 0))
        out["encoding"] = str(msg.get("encoding", ""))
        out["format"] = str(msg.get("format", ""))
        out["big_endian"] = False
        return out
    if schema_name.startswith("foxglove."):
        out = {"stamp": _foxglove_stamp(msg.timestamp), "frame_id": msg.frame_id, "data": msg.data}
        if IMAGE_SCHEMAS[schema_name] == RAW:
            out.update(width=msg.width, height=msg.height, step=msg.step, encoding=msg.encoding, big_endian=False)
        else:
            out["format"] = msg.format
        return out
    out = {"stamp": _ros_stamp(msg.header), "frame_id": msg.header.frame_id, "data": msg.data}
    if IMAGE_SCHEMAS[schema_name] == RAW:
        out.update(width=msg.width, height=msg.height, step=msg.step, encoding=msg.encoding,
                   big_endian=bool(msg.is_bigendian))
    else:
        out["format"] = msg.format
    return out


def image_decoder(schema: Schema | None, message_encoding: str
                  ) -> Callable[[bytes | memoryview], DecodedImage] | None:
    """A function decoding one message of this image schema to a :class:`DecodedImage` (None if not an image).

    A protobuf ``foxglove.RawImage`` is read from the wire format (:mod:`starlog.codecs.rawimage_wire`)
    and a mono frame comes back as a read-only view of the message's bytes; whatever that
    reader does not take goes to the protobuf parser, as every other type does.
    """
    if schema is None or schema.name not in IMAGE_SCHEMAS:
        return None
    kind = IMAGE_SCHEMAS[schema.name]
    if message_encoding == "json":
        parse: Callable[[bytes], Any] = decode_json
    else:
        found = message_decoder(schema, message_encoding)
        if found is None:
            return None
        parse = found

    def decode(data: bytes | memoryview) -> DecodedImage:
        try:
            f = image_fields(parse(data if isinstance(data, bytes) else bytes(data)), schema.name)
        except InvalidInputError:
            raise
        except Exception as err:  # protobuf DecodeError, struct.error, ROS deserialisation errors, binascii
            raise InvalidInputError(f"not a valid {schema.name}: {type(err).__name__}: {err}") from err
        if kind == RAW:
            image, note = pixels_to_mono(f["data"], f["width"], f["height"], f["step"], f["encoding"],
                                         f["big_endian"])
        else:
            image, note = decompress_to_mono(f["data"], f["format"])
        return DecodedImage(image, f["stamp"], f["frame_id"], note)

    if schema.name == "foxglove.RawImage" and message_encoding == "protobuf" and schema.encoding == "protobuf":
        return _raw_image_from_wire(decode)
    return decode


def _raw_image_from_wire(fallback: Callable[[bytes | memoryview], DecodedImage]
                         ) -> Callable[[bytes | memoryview], DecodedImage]:
    """Decode a protobuf ``foxglove.RawImage`` from its wire format; ``fallback`` (the protobuf parser's path)
    for anything the wire reader leaves to it. Both give the same image, stamp, frame id and errors."""

    def decode(data: bytes | memoryview) -> DecodedImage:
        f = parse_raw_image(data)
        if f is None:
            return fallback(data)
        image, note = pixels_to_mono(f.data, f.width, f.height, f.step, f.encoding)
        return DecodedImage(image, _ns(f.seconds, f.nanos), f.frame_id, note)

    return decode


# ---------------------------------------------------------------- choosing the channel
def choose_image_topic(path: str | os.PathLike[str], channels: list[Any], requested: str | None
                       ) -> tuple[str, str | None]:
    """The image topic a stage reads, and a note when it was chosen for the user.

    ``requested`` (``--image-topic``) must be an image channel of the log. Without it:
    ``/camera/image`` if present, else the only image channel, else an error listing them.
    ``channels`` are :class:`~starlog.io.reader.ChannelSummary` objects.
    """
    images = [c.topic for c in channels if is_image_schema(c.schema_name)]
    listing = ", ".join(f"{c.topic} ({c.schema_name})" for c in channels if is_image_schema(c.schema_name))
    if requested is not None:
        match = next((c for c in channels if c.topic == requested), None)
        if match is None:
            raise ChannelNotFoundError(path, requested, [c.topic for c in channels])
        if not is_image_schema(match.schema_name):
            raise InvalidParameterError(
                f"{path}: channel {requested!r} has schema {match.schema_name or 'none'!r}, not an image type; "
                f"image channels: {listing or 'none'}.")
        return requested, None
    if DEFAULT_IMAGE_TOPIC in images:
        return DEFAULT_IMAGE_TOPIC, None
    if len(images) == 1:
        return images[0], f"reading frames from {images[0]}, the log's only image channel."
    if not images:
        known = ", ".join(f"{c.topic} ({c.schema_name or 'no schema'})" for c in channels) or "none"
        raise InvalidParameterError(f"{path}: the log has no image channel starlog reads (channels: {known}); "
                                    f"image types read: {', '.join(IMAGE_SCHEMAS)}.")
    raise InvalidParameterError(f"{path}: the log has several image channels ({listing}); "
                                "choose one with --image-topic TOPIC.")
