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
    "compile_json_schema",
]

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


def _refuse_constant(name: str) -> Any:
    raise InvalidInputError(f"JSON message contains {name}, which starlog never writes (NaN/infinity).")


def decode_json(data: bytes | memoryview) -> Any:
    """Decode a UTF-8 JSON message; NaN and infinities are refused like in :func:`encode_json`.

    Raises
    ------
    InvalidInputError
        The bytes are not UTF-8 JSON, or hold ``NaN`` / ``Infinity``.
    """
    try:
        return json.loads(bytes(data).decode("utf-8"), parse_constant=_refuse_constant)
    except InvalidInputError:
        raise
    except (ValueError, RecursionError) as err:  # JSONDecodeError, UnicodeDecodeError; absurd nesting
        raise InvalidInputError(f"not valid UTF-8 JSON: {err}") from err


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
        if msg.encoding.lower() in _FOREIGN_BYTE_ORDER:
            raise InvalidInputError(
                f"image encoding {msg.encoding!r} is big-endian; foxglove.RawImage mono16/16UC1 is little-endian. "
                "Swap the bytes when recording (numpy: image.astype('<u2'))."
            )
        raise InvalidInputError(
            f"unsupported image encoding {msg.encoding!r}; starlog reads {', '.join(IMAGE_ENCODINGS)}."
        )
    row_bytes = msg.width * dtype.itemsize
    if msg.width == 0 or msg.height == 0 or msg.step < row_bytes:
        raise InvalidInputError(f"invalid image geometry: {msg.width}x{msg.height}, step {msg.step}.")
    if dtype.itemsize > 1 and msg.step % dtype.itemsize:
        raise InvalidInputError(
            f"row step {msg.step} is not a whole number of {dtype.itemsize}-byte pixels ({msg.encoding})."
        )
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


# ---------------------------------------------------------------- JSON Schema checks
_JSON_TYPES: dict[str, Any] = {
    "object": lambda v: isinstance(v, dict),
    "array": lambda v: isinstance(v, list),
    "string": lambda v: isinstance(v, str),
    "boolean": lambda v: isinstance(v, bool),
    "null": lambda v: v is None,
    "number": lambda v: isinstance(v, (int, float)) and not isinstance(v, bool),
    "integer": lambda v: (isinstance(v, int) and not isinstance(v, bool)) or (isinstance(v, float) and v.is_integer()),
}

_SUPPORTED = {"$schema", "$id", "title", "description", "type", "properties", "required", "additionalProperties",
              "items", "minItems", "maxItems", "minimum", "maximum", "enum", "unit", "examples", "default"}


def compile_json_schema(schema: dict[str, Any]) -> Any:
    """A fast checker for the subset of JSON Schema starlog's schemas use.

    Returns a function ``check(value) -> str | None`` giving the first violation (with its JSON
    path) or ``None``. Supported keywords: type, properties, required, additionalProperties, items,
    minItems, maxItems, minimum, maximum, enum (about 20x faster than a general validator, so
    every message can be checked as it is read). Raises :class:`InvalidInputError` for a schema
    that uses anything else.
    """
    if not isinstance(schema, dict):
        raise InvalidInputError(f"a JSON Schema must be an object, got {type(schema).__name__}.")
    unknown = set(schema) - _SUPPORTED
    if unknown:
        raise InvalidInputError(f"JSON Schema keyword(s) {sorted(unknown)} are not supported by the fast checker.")
    checks: list[Any] = []
    kind = schema.get("type")
    if kind is not None:
        kinds = [kind] if isinstance(kind, str) else list(kind)
        tests = [_JSON_TYPES[k] for k in kinds]
        checks.append(lambda v, p: None if any(t(v) for t in tests) else f"{p}: expected {'/'.join(kinds)}, "
                      f"got {type(v).__name__}")
    if "enum" in schema:
        allowed = list(schema["enum"])
        checks.append(lambda v, p: None if v in allowed else f"{p}: {v!r} is not one of {allowed}")
    if "minimum" in schema:
        lo = schema["minimum"]
        checks.append(lambda v, p: f"{p}: {v!r} < minimum {lo}" if _JSON_TYPES["number"](v) and v < lo else None)
    if "maximum" in schema:
        hi = schema["maximum"]
        checks.append(lambda v, p: f"{p}: {v!r} > maximum {hi}" if _JSON_TYPES["number"](v) and v > hi else None)
    props = {k: compile_json_schema(v) for k, v in schema.get("properties", {}).items()}
    required = list(schema.get("required", []))
    extra = schema.get("additionalProperties", True)
    extra_check = compile_json_schema(extra) if isinstance(extra, dict) else None
    if props or required or extra is not True:

        def check_object(v: Any, p: str) -> str | None:
            if not isinstance(v, dict):
                return None
            for key in required:
                if key not in v:
                    return f"{p}: missing required property {key!r}"
            for key, item in v.items():
                sub = props.get(key)
                if sub is not None:
                    problem = sub(item, f"{p}.{key}")
                elif extra is False:
                    problem = f"{p}: unexpected property {key!r}"
                elif extra_check is not None:
                    problem = extra_check(item, f"{p}.{key}")
                else:
                    problem = None
                if problem:
                    return problem
            return None

        checks.append(check_object)
    items = schema.get("items")
    item_check = compile_json_schema(items) if isinstance(items, dict) else None
    min_items, max_items = schema.get("minItems"), schema.get("maxItems")
    if item_check is not None or min_items is not None or max_items is not None:

        def check_array(v: Any, p: str) -> str | None:
            if not isinstance(v, list):
                return None
            if min_items is not None and len(v) < min_items:
                return f"{p}: {len(v)} items, fewer than {min_items}"
            if max_items is not None and len(v) > max_items:
                return f"{p}: {len(v)} items, more than {max_items}"
            if item_check is not None:
                for i, item in enumerate(v):
                    problem = item_check(item, f"{p}[{i}]")
                    if problem:
                        return problem
            return None

        checks.append(check_array)

    def check(value: Any, path: str = "$") -> str | None:
        for c in checks:
            problem = c(value, path)
            if problem:
                return problem
        return None

    return check
