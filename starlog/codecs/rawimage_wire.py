"""``foxglove.RawImage`` read straight from the protobuf wire format, the pixels left where they are.

A RawImage is a handful of scalar fields and one large ``data`` field. The protobuf parser
copies ``data`` into a new bytes object; reading the few scalars here and handing back a
view of ``data`` saves that copy (2 MB a frame at 1024x1024 mono16).

The parse follows protobuf's rules for the message it accepts: fields in any order, the last
occurrence of a scalar or string wins, occurrences of ``timestamp`` merge, unknown fields are
skipped. Anything outside the plain case (a group, a known field with another wire type, a
string that is not UTF-8, a varint longer than ten bytes, a field running past the end)
makes :func:`parse_raw_image` return None, and the caller hands the bytes to the protobuf
parser, whose result or error is the reference.

Wire format: https://protobuf.dev/programming-guides/encoding/ ; the message:
``timestamp = 1`` (google.protobuf.Timestamp: ``int64 seconds = 1``, ``int32 nanos = 2``),
``fixed32 width = 2``, ``fixed32 height = 3``, ``string encoding = 4``, ``fixed32 step = 5``,
``bytes data = 6``, ``string frame_id = 7``.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

__all__ = ["RawImageFields", "parse_raw_image"]

_VARINT, _FIXED64, _LENGTH, _FIXED32 = 0, 1, 2, 5
_U32 = struct.Struct("<I")
_TIMESTAMP, _WIDTH, _HEIGHT, _ENCODING, _STEP, _DATA, _FRAME_ID = 1, 2, 3, 4, 5, 6, 7
_WIRE_TYPE = {_TIMESTAMP: _LENGTH, _WIDTH: _FIXED32, _HEIGHT: _FIXED32, _ENCODING: _LENGTH, _STEP: _FIXED32,
              _DATA: _LENGTH, _FRAME_ID: _LENGTH}


class _Unusual(Exception):
    """The bytes are not a plain RawImage this parser reads: the protobuf parser decides."""


@dataclass(frozen=True)
class RawImageFields:
    """The fields of one ``foxglove.RawImage``; ``data`` is a read-only view of the message's bytes."""

    seconds: int
    nanos: int
    width: int
    height: int
    encoding: str
    step: int
    data: memoryview
    frame_id: str


def _varint(buf: memoryview, pos: int, end: int) -> tuple[int, int]:
    """The unsigned varint at ``pos`` (at most ten bytes, the tenth 0 or 1: below 2**64) and the position after it."""
    value = shift = 0
    while pos < end:
        byte = buf[pos]
        pos += 1
        if shift == 63 and byte > 1:
            raise _Unusual
        value |= (byte & 0x7F) << shift
        if byte < 0x80:
            return value, pos
        shift += 7
        if shift > 63:
            raise _Unusual
    raise _Unusual


def _signed(value: int, bits: int) -> int:
    """Two's-complement reading of the low ``bits`` bits (protobuf's int64 / int32 from a varint)."""
    value &= (1 << bits) - 1
    return value - (1 << bits) if value >> (bits - 1) else value


def _skip(buf: memoryview, pos: int, end: int, wire_type: int) -> int:
    """The position after an unknown field's value."""
    if wire_type == _VARINT:
        return _varint(buf, pos, end)[1]
    if wire_type == _FIXED64:
        pos += 8
    elif wire_type == _FIXED32:
        pos += 4
    elif wire_type == _LENGTH:
        length, pos = _varint(buf, pos, end)
        pos += length
    else:  # groups (3, 4) and the invalid wire types 6, 7
        raise _Unusual
    if pos > end:
        raise _Unusual
    return pos


def _next_field(buf: memoryview, pos: int, end: int) -> tuple[int, int, int, int]:
    """``(field number, wire type, value start, value end)`` of the next field; for a varint, the value itself
    is returned in place of the value start."""
    tag, after = _varint(buf, pos, end)
    number, wire_type = tag >> 3, tag & 7
    if number == 0 or tag >> 32 or after - pos > 5:  # a tag is a 32-bit varint
        raise _Unusual
    pos = after
    if wire_type == _LENGTH:
        length, pos = _varint(buf, pos, end)
        if pos + length > end:
            raise _Unusual
        return number, wire_type, pos, pos + length
    if wire_type == _VARINT:
        value, after = _varint(buf, pos, end)
        return number, wire_type, value, after
    return number, wire_type, pos, _skip(buf, pos, end, wire_type)


def _timestamp(buf: memoryview, pos: int, end: int, seconds: int, nanos: int) -> tuple[int, int]:
    """Merge one occurrence of the ``timestamp`` submessage into ``(seconds, nanos)``."""
    while pos < end:
        number, wire_type, start, pos = _next_field(buf, pos, end)
        if number in (1, 2):
            if wire_type != _VARINT:
                raise _Unusual
            if number == 1:
                seconds = _signed(start, 64)
            else:
                nanos = _signed(start, 32)
    return seconds, nanos


def _text(buf: memoryview, start: int, end: int) -> str:
    try:
        return str(buf[start:end], "utf-8")
    except UnicodeDecodeError:
        raise _Unusual from None


def parse_raw_image(data: bytes | memoryview) -> RawImageFields | None:
    """The fields of a serialized ``foxglove.RawImage``, or None when the protobuf parser must decide.

    Equal to what ``RawImage.FromString(data)`` holds whenever it returns fields.
    """
    buf = memoryview(data).toreadonly()
    if buf.format != "B" or buf.ndim != 1 or not buf.contiguous:
        return None
    seconds = nanos = width = height = step = 0
    encoding = frame_id = ""
    pixels = buf[0:0]
    pos, end = 0, len(buf)
    try:
        while pos < end:
            number, wire_type, start, pos = _next_field(buf, pos, end)
            expected = _WIRE_TYPE.get(number)
            if expected is None:
                continue
            if wire_type != expected:
                raise _Unusual
            if number == _DATA:
                pixels = buf[start:pos]
            elif number == _WIDTH:
                (width,) = _U32.unpack_from(buf, start)
            elif number == _HEIGHT:
                (height,) = _U32.unpack_from(buf, start)
            elif number == _STEP:
                (step,) = _U32.unpack_from(buf, start)
            elif number == _ENCODING:
                encoding = _text(buf, start, pos)
            elif number == _FRAME_ID:
                frame_id = _text(buf, start, pos)
            else:
                seconds, nanos = _timestamp(buf, start, pos, seconds, nanos)
    except _Unusual:
        return None
    return RawImageFields(seconds, nanos, width, height, encoding, step, pixels, frame_id)
