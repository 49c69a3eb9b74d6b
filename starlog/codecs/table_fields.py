"""The fields of a table message (:mod:`starlog.codecs.table_wire`): what each one holds, how it is written on the
protobuf wire, and the wire's varints.

Shared by :mod:`starlog.codecs.table_rows` (the rows) and :mod:`starlog.codecs.table_wire` (the header and the
message). Wire format: https://protobuf.dev/programming-guides/encoding/ .
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Any

from google.protobuf.descriptor import FieldDescriptor

__all__ = ["FIXED", "FIXED32", "FIXED64", "LENGTH", "RANGES", "STRUCTS", "VARINT", "VARINTS", "Field", "Unusual",
           "UnsupportedMessage", "is_repeated", "read_varint", "signed", "varint"]

VARINT, FIXED64, LENGTH, FIXED32 = 0, 1, 2, 5
_T = FieldDescriptor

#: Fixed-width scalar types: wire type and the little-endian numpy format of the value.
FIXED: dict[int, tuple[int, str]] = {
    _T.TYPE_DOUBLE: (FIXED64, "<f8"), _T.TYPE_FLOAT: (FIXED32, "<f4"),
    _T.TYPE_FIXED32: (FIXED32, "<u4"), _T.TYPE_SFIXED32: (FIXED32, "<i4"),
    _T.TYPE_FIXED64: (FIXED64, "<u8"), _T.TYPE_SFIXED64: (FIXED64, "<i8"),
}
#: Varint scalar types and the range of their values (bool and enums are checked on their own).
VARINTS: dict[int, tuple[int, int]] = {
    _T.TYPE_INT32: (-(1 << 31), 1 << 31), _T.TYPE_INT64: (-(1 << 63), 1 << 63),
    _T.TYPE_UINT32: (0, 1 << 32), _T.TYPE_UINT64: (0, 1 << 64),
    _T.TYPE_BOOL: (0, 2), _T.TYPE_ENUM: (-(1 << 31), 1 << 31),
}
STRUCTS = {t: struct.Struct("<" + {"f8": "d", "f4": "f", "u4": "I", "i4": "i", "u8": "Q", "i8": "q"}[fmt[1:]])
            for t, (_, fmt) in FIXED.items()}
RANGES = {"<u4": (0, 1 << 32), "<i4": (-(1 << 31), 1 << 31), "<u8": (0, 1 << 64), "<i8": (-(1 << 63), 1 << 63)}


class UnsupportedMessage(ValueError):
    """The message is not a table message (a field of a kind :class:`TableCodec` does not handle)."""


class Unusual(Exception):
    """The bytes are not laid out as starlog's codec writes them: the protobuf parser decides."""


def varint(value: int) -> bytes:
    """A protobuf varint (negative values as their 64-bit two's complement)."""
    value &= (1 << 64) - 1
    out = bytearray()
    while value >= 0x80:
        out.append((value & 0x7F) | 0x80)
        value >>= 7
    out.append(value)
    return bytes(out)


def read_varint(buf: bytes | memoryview, pos: int, end: int) -> tuple[int, int]:
    """The varint at ``pos`` (below 2**64) and the position after it."""
    value = shift = 0
    while pos < end and shift < 64:
        byte = buf[pos]
        pos += 1
        value |= (byte & 0x7F) << shift
        if byte < 0x80:
            if value >> 64:
                raise Unusual
            return value, pos
        shift += 7
    raise Unusual


def signed(value: int, bits: int) -> int:
    value &= (1 << bits) - 1
    return value - (1 << bits) if value >> (bits - 1) else value


@dataclass(frozen=True)
class Field:
    """One field of a message: what its values are and how they are written."""

    name: str
    number: int
    type: int
    repeated: bool
    presence: bool
    enum: tuple[dict[int, str], dict[str, int]] | None
    wire_type: int
    tag: bytes

    @classmethod
    def of(cls, fd: FieldDescriptor) -> Field:
        if fd.type not in FIXED and fd.type not in VARINTS and fd.type != _T.TYPE_STRING:
            raise UnsupportedMessage(f"field {fd.full_name} has a type a table message does not hold")
        repeated = is_repeated(fd)
        if repeated and fd.type in (_T.TYPE_STRING, _T.TYPE_ENUM):
            raise UnsupportedMessage(f"field {fd.full_name}: repeated strings and enums are not table fields")
        if fd.containing_oneof is not None and not _synthetic_oneof(fd):
            raise UnsupportedMessage(f"field {fd.full_name} is in a oneof")
        enum = None
        if fd.type == _T.TYPE_ENUM:
            names = {v.number: v.name for v in fd.enum_type.values}
            enum = (names, {name: number for number, name in names.items()})
        if repeated or fd.type == _T.TYPE_STRING:
            wire_type = LENGTH
        else:
            wire_type = FIXED[fd.type][0] if fd.type in FIXED else VARINT
        return cls(fd.name, fd.number, fd.type, repeated, fd.has_presence and not repeated, enum, wire_type,
                   varint(fd.number << 3 | wire_type))

    def default(self) -> Any:
        if self.repeated:
            return []
        if self.type == _T.TYPE_STRING:
            return ""
        if self.type == _T.TYPE_BOOL:
            return False
        if self.enum is not None:
            return self.enum[0].get(0, 0)
        return 0.0 if self.type in (_T.TYPE_DOUBLE, _T.TYPE_FLOAT) else 0


def is_repeated(fd: FieldDescriptor) -> bool:
    """Whether the field is repeated (``label`` is gone from protobuf 7's descriptors; ``is_repeated`` is new)."""
    flag = getattr(fd, "is_repeated", None)
    return bool(flag) if flag is not None else fd.label == _T.LABEL_REPEATED


def _synthetic_oneof(fd: FieldDescriptor) -> bool:
    """Whether the field's oneof is the one protoc makes for a proto3 ``optional`` field."""
    oneof = fd.containing_oneof
    return len(oneof.fields) == 1 and fd.has_presence and oneof.name == f"_{fd.name}"
