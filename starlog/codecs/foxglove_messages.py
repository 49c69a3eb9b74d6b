"""The Foxglove messages starlog writes, as protobuf bytes: ``foxglove.RawImage`` (mono8 / mono16 frames,
both ways) and ``foxglove.ImageAnnotations`` (circles at centroids)."""

from __future__ import annotations

import functools
import math
import struct
from collections.abc import Sequence
from typing import Any

import numpy as np
import numpy.typing as npt

from starlog.errors import InvalidInputError
from starlog.codecs.rawimage_wire import parse_raw_image
from starlog.codecs.table_fields import varint

__all__ = ["IMAGE_ENCODINGS", "decode_raw_image", "encode_image_annotations", "encode_raw_image"]

#: foxglove.RawImage encodings starlog reads (and, for mono8 / mono16, writes): name -> numpy dtype.
#: ``8UC1`` / ``16UC1`` are the OpenCV names Foxglove also accepts for the same layouts.
IMAGE_ENCODINGS: dict[str, np.dtype[Any]] = {
    "mono8": np.dtype("u1"),
    "mono16": np.dtype("<u2"),  # Foxglove: mono16 is little-endian
    "8UC1": np.dtype("u1"),
    "16UC1": np.dtype("<u2"),
}

#: Encodings that announce a big-endian (or otherwise foreign) 16-bit layout: rejected with a clear message.
_FOREIGN_BYTE_ORDER = {"mono16be", "16uc1be", "mono16_be", "16uc1_be", ">u2", "big_endian", "bigendian"}


def _timestamp(log_time: int) -> tuple[int, int]:
    return divmod(int(log_time), 1_000_000_000)


def encode_raw_image(image: npt.NDArray[Any], *, log_time: int, frame_id: str = "camera") -> bytes:
    """Encode a 2-D uint8 or uint16 array as ``foxglove.RawImage`` (mono8 / little-endian mono16)."""
    from foxglove_schemas_protobuf.RawImage_pb2 import RawImage

    if image.ndim != 2:
        raise InvalidInputError(f"a frame must be a 2-D mono image; got shape {image.shape}.")
    if image.dtype == np.uint8:
        encoding = "mono8"
    elif image.dtype == np.uint16:
        encoding = "mono16"
    else:
        raise InvalidInputError(f"frames must be uint8 or uint16; got {image.dtype}.")
    height, width = image.shape
    pixels = np.ascontiguousarray(image, dtype=IMAGE_ENCODINGS[encoding])
    seconds, nanos = _timestamp(log_time)
    msg = RawImage(width=width, height=height, encoding=encoding, step=width * pixels.itemsize, frame_id=frame_id)
    msg.timestamp.seconds = seconds
    msg.timestamp.nanos = nanos
    msg.data = pixels.tobytes()
    return msg.SerializeToString()


def _raw_image_fields(data: bytes | memoryview) -> tuple[int, int, int, str, bytes | memoryview]:
    """``(width, height, step, encoding, data)`` of a serialized ``foxglove.RawImage``."""
    fields = parse_raw_image(data)
    if fields is not None:
        return fields.width, fields.height, fields.step, fields.encoding, fields.data
    from foxglove_schemas_protobuf.RawImage_pb2 import RawImage

    msg = RawImage()
    try:
        msg.ParseFromString(bytes(data))
    except Exception as err:  # protobuf raises its own DecodeError hierarchy
        raise InvalidInputError(f"not a valid foxglove.RawImage: {err}") from err
    return msg.width, msg.height, msg.step, msg.encoding, msg.data


def decode_raw_image(data: bytes | memoryview) -> npt.NDArray[Any]:
    """Decode a ``foxglove.RawImage`` (mono8 / mono16) to a 2-D native-endian array.

    Rows without padding, in the machine's byte order, come back as a read-only view of ``data``.

    Raises
    ------
    InvalidInputError
        Unsupported encoding, or data length that does not match width × height × depth.
    """
    width, height, step, encoding, pixels = _raw_image_fields(data)
    dtype = IMAGE_ENCODINGS.get(encoding)
    if dtype is None:
        if encoding.lower() in _FOREIGN_BYTE_ORDER:
            raise InvalidInputError(
                f"image encoding {encoding!r} is big-endian; foxglove.RawImage mono16/16UC1 is little-endian. "
                "Swap the bytes when recording (numpy: image.astype('<u2'))."
            )
        raise InvalidInputError(
            f"unsupported image encoding {encoding!r}; starlog reads {', '.join(IMAGE_ENCODINGS)}."
        )
    row_bytes = width * dtype.itemsize
    if width == 0 or height == 0 or step < row_bytes:
        raise InvalidInputError(f"invalid image geometry: {width}x{height}, step {step}.")
    if dtype.itemsize > 1 and step % dtype.itemsize:
        raise InvalidInputError(
            f"row step {step} is not a whole number of {dtype.itemsize}-byte pixels ({encoding})."
        )
    if len(pixels) != step * height:
        raise InvalidInputError(
            f"image data has {len(pixels)} bytes, expected step × height = {step} × {height}"
            f" = {step * height}."
        )
    if step == row_bytes and dtype.isnative:
        return np.frombuffer(pixels, dtype=dtype).reshape(height, width)
    rows = np.frombuffer(pixels, dtype=np.uint8).reshape(height, step)[:, :row_bytes]
    return rows.copy().view(dtype).astype(dtype.newbyteorder("="), copy=False).reshape(height, width)


def encode_image_annotations(
    x: Sequence[float] | npt.NDArray[np.float64],
    y: Sequence[float] | npt.NDArray[np.float64],
    *,
    log_time: int,
    diameter: float = 8.0,
    thickness: float = 1.0,
    rgba: tuple[float, float, float, float] = (0.1, 1.0, 0.2, 1.0),
) -> bytes:
    """Encode circles at centroids as ``foxglove.ImageAnnotations``.

    ``x``, ``y`` follow the starlog convention (pixel-centre origin); Foxglove's annotation
    origin is the top-left *corner* of the top-left pixel, so 0.5 is added here. Non-finite
    positions are left out. The protobuf wire format is written directly (the bytes protobuf's
    deterministic serialization gives, field by field: ``circles = 1`` of ``CircleAnnotation``
    ``timestamp = 1``, ``position = 2`` (``Point2`` ``x = 1``, ``y = 2``), ``diameter = 3``,
    ``thickness = 4``, ``outline_color = 6`` (``Color`` ``r, g, b, a = 1..4``)): the parts shared
    by every circle of a frame are encoded once.
    """
    seconds, nanos = _timestamp(log_time)
    stamp = _wire_message(0x0A, (b"\x08" + varint(seconds) if seconds else b"")
                          + (b"\x10" + varint(nanos) if nanos else b""))
    shared = _circle_look(struct.pack("<6d", diameter, thickness, *rgba))
    xs, ys = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    if xs.ndim == 1 and xs.shape == ys.shape:
        keep = np.isfinite(xs) & np.isfinite(ys)
        if not keep.all():
            xs, ys = xs[keep], ys[keep]
        xs, ys = xs + 0.5, ys + 0.5
        if xs.all() and ys.all():  # no position is 0: every circle then has the same layout
            return _same_layout_circles(stamp, shared, xs, ys)
    circles = []
    for xi, yi in zip(x, y):
        if not (math.isfinite(xi) and math.isfinite(yi)):
            continue
        position = _wire_message(0x12, _wire_double(0x09, float(xi) + 0.5) + _wire_double(0x11, float(yi) + 0.5))
        circles.append(_wire_message(0x0A, stamp + position + shared))
    return b"".join(circles)


@functools.lru_cache(maxsize=64)
def _circle_look(packed: bytes) -> bytes:
    """The fields every circle of a frame shares: diameter, thickness and outline colour (``packed`` as six
    doubles: the bytes tell -0.0 from 0.0, which protobuf writes differently)."""
    diameter, thickness, *rgba = struct.unpack("<6d", packed)
    colour = b"".join(_wire_double(tag, c) for tag, c in zip((0x09, 0x11, 0x19, 0x21), rgba, strict=True))
    return _wire_double(0x19, diameter) + _wire_double(0x21, thickness) + _wire_message(0x32, colour)


def _same_layout_circles(stamp: bytes, shared: bytes, xs: npt.NDArray[np.float64],
                         ys: npt.NDArray[np.float64]) -> bytes:
    """Circles whose positions are all non-zero: one template row repeated, the positions written in by numpy."""
    head = stamp + b"\x12\x12\x09"
    body_length = len(head) + 8 + 1 + 8 + len(shared)
    template = b"\x0a" + varint(body_length) + head + bytes(8) + b"\x11" + bytes(8) + shared
    rows = bytearray(template * xs.size)
    positions = np.frombuffer(rows, dtype=_position_layout(len(template), len(template) - len(shared) - 17))
    positions["x"] = xs
    positions["y"] = ys
    return bytes(rows)


@functools.lru_cache(maxsize=64)
def _position_layout(size: int, at_x: int) -> np.dtype[Any]:
    """A circle's x and y (little-endian doubles, 9 bytes apart) in a row of ``size`` bytes."""
    return np.dtype({"names": ["x", "y"], "formats": ["<f8", "<f8"], "offsets": [at_x, at_x + 9], "itemsize": size})


_WIRE_DOUBLE = struct.Struct("<d")
_WIRE_ZERO = bytes(8)


def _wire_double(tag: int, value: float) -> bytes:
    """A proto3 ``double`` field: left out when it is +0.0, as protobuf does (-0.0 is written)."""
    packed = _WIRE_DOUBLE.pack(value)
    return b"" if packed == _WIRE_ZERO else bytes((tag,)) + packed


def _wire_message(tag: int, body: bytes) -> bytes:
    """A submessage field (present even when empty, as a submessage whose fields were set is)."""
    return bytes((tag,)) + varint(len(body)) + body
