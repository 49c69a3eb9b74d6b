"""Encoding and decoding of message payloads (JSON, foxglove.RawImage, foxglove.ImageAnnotations)."""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import numpy.typing as npt

from starlog.errors import InvalidInputError

__all__ = [
    "encode_json",
    "decode_json",
    "encode_raw_image",
    "decode_raw_image",
    "encode_image_annotations",
    "IMAGE_ENCODINGS",
]

#: foxglove.RawImage encodings starlog reads and writes: name -> (numpy dtype, bytes per pixel).
IMAGE_ENCODINGS: dict[str, np.dtype[Any]] = {
    "mono8": np.dtype("u1"),
    "mono16": np.dtype("<u2"),  # Foxglove: mono16 is little-endian
}


def _json_default(value: Any) -> Any:
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, np.floating):
        return float(value)
    if isinstance(value, np.bool_):
        return bool(value)
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"{type(value).__name__} is not JSON serializable")


def encode_json(obj: Any) -> bytes:
    """Encode a message as compact UTF-8 JSON; NaN and infinities are refused (Foxglove cannot read them)."""
    try:
        return json.dumps(obj, separators=(",", ":"), allow_nan=False, default=_json_default).encode()
    except ValueError as err:
        raise InvalidInputError(f"message contains a NaN or infinite number and cannot be logged: {err}") from err


def decode_json(data: bytes | memoryview) -> Any:
    """Decode a JSON message."""
    return json.loads(bytes(data))


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


def decode_raw_image(data: bytes | memoryview) -> npt.NDArray[Any]:
    """Decode a ``foxglove.RawImage`` (mono8 / mono16) to a 2-D native-endian array.

    Raises
    ------
    InvalidInputError
        Unsupported encoding, or data length that does not match width × height × depth.
    """
    from foxglove_schemas_protobuf.RawImage_pb2 import RawImage

    msg = RawImage()
    try:
        msg.ParseFromString(bytes(data))
    except Exception as err:  # protobuf raises its own DecodeError hierarchy
        raise InvalidInputError(f"not a valid foxglove.RawImage: {err}") from err
    dtype = IMAGE_ENCODINGS.get(msg.encoding)
    if dtype is None:
        raise InvalidInputError(
            f"unsupported image encoding {msg.encoding!r}; starlog reads {', '.join(IMAGE_ENCODINGS)}."
        )
    row_bytes = msg.width * dtype.itemsize
    if msg.width == 0 or msg.height == 0 or msg.step < row_bytes:
        raise InvalidInputError(f"invalid image geometry: {msg.width}x{msg.height}, step {msg.step}.")
    if len(msg.data) != msg.step * msg.height:
        raise InvalidInputError(
            f"image data has {len(msg.data)} bytes, expected step × height = {msg.step} × {msg.height}"
            f" = {msg.step * msg.height}."
        )
    rows = np.frombuffer(msg.data, dtype=np.uint8).reshape(msg.height, msg.step)[:, :row_bytes]
    return rows.copy().view(dtype).astype(dtype.newbyteorder("="), copy=False).reshape(msg.height, msg.width)


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
    origin is the top-left *corner* of the top-left pixel, so 0.5 is added here.
    """
    from foxglove_schemas_protobuf.ImageAnnotations_pb2 import ImageAnnotations

    msg = ImageAnnotations()
    seconds, nanos = _timestamp(log_time)
    for xi, yi in zip(x, y):
        if not (math.isfinite(xi) and math.isfinite(yi)):
            continue
        circle = msg.circles.add()
        circle.timestamp.seconds = seconds
        circle.timestamp.nanos = nanos
        circle.position.x = float(xi) + 0.5
        circle.position.y = float(yi) + 0.5
        circle.diameter = diameter
        circle.thickness = thickness
        circle.outline_color.r, circle.outline_color.g, circle.outline_color.b, circle.outline_color.a = rgba
    return msg.SerializeToString(deterministic=True)
