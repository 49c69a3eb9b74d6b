"""Protobuf messages made of a header and one table, written and read as numpy structured arrays.

A *table message* has scalar fields (the header: numbers, bools, strings, enums, proto3 ``optional``
numbers, packed repeated numbers) and at most one repeated sub-message (the table) whose fields are
all fixed-width: ``double``, ``float``, ``fixed32``, ``sfixed32``, ``fixed64``, ``sfixed64``, and
``bool`` or an enum as a one-byte varint. With every field written, every row of such a table has
the same length and the same bytes but for its values (the row's tag and length, each field's
tag), so :class:`TableCodec` writes the whole table as one numpy array of that layout (``tobytes``)
and reads it with ``np.frombuffer`` once every row's tag bytes match the template (and each bool
or enum value is a one-byte varint). Any other valid encoding of the message (fields left out,
in another order, unknown fields, rows followed by header fields: a message another tool wrote) is
handed to the protobuf runtime's parser, whose result is the reference; so is anything the fast
path does not recognise, and the parser's error is the error.

Decoded, a message is its header as a dict (field-number order, proto3 defaults filled in, an
``optional`` field only when present, enums by name) and its table as a packed structured array
(one field per row field, native byte order; enums as strings); :meth:`TableCodec.to_dict` gives the
whole message as the JSON-shaped dict, ``{header..., table: [row dicts]}``.

Wire format: https://protobuf.dev/programming-guides/encoding/ . This module depends on numpy and
the protobuf runtime only (and starlog's error type).
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Collection, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
import numpy.typing as npt
from google.protobuf import message_factory
from google.protobuf.descriptor import Descriptor, FieldDescriptor
from google.protobuf.message import DecodeError

from starlog.errors import InvalidInputError

__all__ = ["DecodedTable", "TableCodec", "UnsupportedMessage"]

_VARINT, _FIXED64, _LENGTH, _FIXED32 = 0, 1, 2, 5
_T = FieldDescriptor

#: Fixed-width scalar types: wire type and the little-endian numpy format of the value.
_FIXED: dict[int, tuple[int, str]] = {
    _T.TYPE_DOUBLE: (_FIXED64, "<f8"), _T.TYPE_FLOAT: (_FIXED32, "<f4"),
    _T.TYPE_FIXED32: (_FIXED32, "<u4"), _T.TYPE_SFIXED32: (_FIXED32, "<i4"),
    _T.TYPE_FIXED64: (_FIXED64, "<u8"), _T.TYPE_SFIXED64: (_FIXED64, "<i8"),
}
#: Varint scalar types and the range of their values (bool and enums are checked on their own).
_VARINTS: dict[int, tuple[int, int]] = {
    _T.TYPE_INT32: (-(1 << 31), 1 << 31), _T.TYPE_INT64: (-(1 << 63), 1 << 63),
    _T.TYPE_UINT32: (0, 1 << 32), _T.TYPE_UINT64: (0, 1 << 64),
    _T.TYPE_BOOL: (0, 2), _T.TYPE_ENUM: (-(1 << 31), 1 << 31),
}
_STRUCTS = {t: struct.Struct("<" + {"f8": "d", "f4": "f", "u4": "I", "i4": "i", "u8": "Q", "i8": "q"}[fmt[1:]])
            for t, (_, fmt) in _FIXED.items()}
_RANGES = {"<u4": (0, 1 << 32), "<i4": (-(1 << 31), 1 << 31), "<u8": (0, 1 << 64), "<i8": (-(1 << 63), 1 << 63)}


class UnsupportedMessage(ValueError):
    """The message is not a table message (a field of a kind :class:`TableCodec` does not handle)."""


class _Unusual(Exception):
    """The bytes are not laid out as this codec writes them: the protobuf parser decides."""


class DecodedTable(NamedTuple):
    """A decoded table message: the header fields (a dict) and the rows (a structured array; None when the
    message type has no table)."""

    header: dict[str, Any]
    rows: npt.NDArray[np.void] | None


def _varint(value: int) -> bytes:
    """A protobuf varint (negative values as their 64-bit two's complement)."""
    value &= (1 << 64) - 1
    out = bytearray()
    while value >= 0x80:
        out.append((value & 0x7F) | 0x80)
        value >>= 7
    out.append(value)
    return bytes(out)


def _read_varint(buf: bytes | memoryview, pos: int, end: int) -> tuple[int, int]:
    """The varint at ``pos`` (below 2**64) and the position after it."""
    value = shift = 0
    while pos < end and shift < 64:
        byte = buf[pos]
        pos += 1
        value |= (byte & 0x7F) << shift
        if byte < 0x80:
            if value >> 64:
                raise _Unusual
            return value, pos
        shift += 7
    raise _Unusual


def _signed(value: int, bits: int) -> int:
    value &= (1 << bits) - 1
    return value - (1 << bits) if value >> (bits - 1) else value


@dataclass(frozen=True)
class _Field:
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
    def of(cls, fd: FieldDescriptor) -> _Field:
        if fd.type not in _FIXED and fd.type not in _VARINTS and fd.type != _T.TYPE_STRING:
            raise UnsupportedMessage(f"field {fd.full_name} has a type a table message does not hold")
        repeated = _is_repeated(fd)
        if repeated and fd.type in (_T.TYPE_STRING, _T.TYPE_ENUM):
            raise UnsupportedMessage(f"field {fd.full_name}: repeated strings and enums are not table fields")
        if fd.containing_oneof is not None and not _synthetic_oneof(fd):
            raise UnsupportedMessage(f"field {fd.full_name} is in a oneof")
        enum = None
        if fd.type == _T.TYPE_ENUM:
            names = {v.number: v.name for v in fd.enum_type.values}
            enum = (names, {name: number for number, name in names.items()})
        if repeated or fd.type == _T.TYPE_STRING:
            wire_type = _LENGTH
        else:
            wire_type = _FIXED[fd.type][0] if fd.type in _FIXED else _VARINT
        return cls(fd.name, fd.number, fd.type, repeated, fd.has_presence and not repeated, enum, wire_type,
                   _varint(fd.number << 3 | wire_type))

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


def _is_repeated(fd: FieldDescriptor) -> bool:
    """Whether the field is repeated (``label`` is gone from protobuf 7's descriptors; ``is_repeated`` is new)."""
    flag = getattr(fd, "is_repeated", None)
    return bool(flag) if flag is not None else fd.label == _T.LABEL_REPEATED


def _synthetic_oneof(fd: FieldDescriptor) -> bool:
    """Whether the field's oneof is the one protoc makes for a proto3 ``optional`` field."""
    oneof = fd.containing_oneof
    return len(oneof.fields) == 1 and fd.has_presence and oneof.name == f"_{fd.name}"


class TableCodec:
    """Encode and decode one table message type (module docstring), built from its protobuf descriptor.

    Raises :class:`UnsupportedMessage` when the message is not a table message.
    """

    def __init__(self, descriptor: Descriptor) -> None:
        self.name: str = descriptor.full_name
        self._class = message_factory.GetMessageClass(descriptor)
        table = [fd for fd in descriptor.fields if fd.type == _T.TYPE_MESSAGE]
        if len(table) > 1 or (table and not _is_repeated(table[0])):
            raise UnsupportedMessage(f"{self.name} holds sub-messages other than one repeated table")
        self.fields = [_Field.of(fd) for fd in sorted(descriptor.fields, key=lambda f: f.number) if fd not in table]
        self._by_number = {f.number: f for f in self.fields}
        self.table_key: str | None = table[0].name if table else None
        self._order = [fd.name for fd in sorted(descriptor.fields, key=lambda f: f.number)]
        self._rows = _RowLayout(table[0]) if table else None
        self._header_writers = {f.name: _header_writer(f) for f in self.fields}

    # ------------------------------------------------------------------ what the rows look like
    @property
    def row_dtype(self) -> np.dtype[Any] | None:
        """The dtype of decoded rows (None without a table)."""
        return self._rows.dtype if self._rows is not None else None

    @property
    def row_size(self) -> int:
        """Bytes of one encoded row, its tag and length included (0 without a table)."""
        return self._rows.size if self._rows is not None else 0

    def value_offset(self, name: str) -> int:
        """Where the value of the row field ``name`` starts in an encoded row."""
        return self._layout().offsets[name]

    def _layout(self) -> _RowLayout:
        if self._rows is None:
            raise InvalidInputError(f"{self.name} has no table.")
        return self._rows

    # ------------------------------------------------------------------ encoding
    def encode(self, header: Mapping[str, Any], rows: npt.NDArray[np.void] | None = None,
               extra: Mapping[str, npt.ArrayLike] | None = None) -> bytes:
        """The message of ``header`` (every header field; proto3 ``optional`` ones may be left out) and the rows
        of ``rows`` plus the ``extra`` columns (every row field, by name).

        Raises :class:`InvalidInputError` for a missing, unknown or mistyped field, or a value out of its range.
        """
        head = self.encode_header(header)
        if self._rows is None:
            if rows is not None or extra:
                raise InvalidInputError(f"{self.name} has no table.")
            return head
        return head + self.encode_rows(rows if rows is not None else np.zeros(0, self._rows.dtype), extra)

    def encode_header(self, header: Mapping[str, Any]) -> bytes:
        """The header fields' bytes (which come first in a message :meth:`encode` writes)."""
        unknown = set(header) - set(self._header_writers)
        if unknown:
            raise InvalidInputError(f"{self.name} has no field {sorted(unknown)[0]!r}.")
        out = []
        for f in self.fields:
            if f.name in header:
                out.append(self._header_writers[f.name](header[f.name]))
            elif not f.presence:
                raise InvalidInputError(f"a {self.name} message needs its field {f.name!r}.")
        return b"".join(out)

    def encode_rows(self, rows: npt.NDArray[np.void], extra: Mapping[str, npt.ArrayLike] | None = None) -> bytes:
        """The bytes of the table's rows, :attr:`row_size` each (appended to a header, they make a message)."""
        return self._layout().encode(rows, extra or {}, self.name)

    def encode_dict(self, message: Mapping[str, Any]) -> bytes:
        """The message of a JSON-shaped dict: header fields and, under :attr:`table_key`, a list of row dicts."""
        if self.table_key is None:
            return self.encode(message)
        header = {k: v for k, v in message.items() if k != self.table_key}
        if self.table_key not in message:
            raise InvalidInputError(f"a {self.name} message needs its field {self.table_key!r}.")
        return self.encode(header, self.rows_from_dicts(message[self.table_key]))

    def rows_from_dicts(self, rows: Sequence[Mapping[str, Any]], *,
                        optional: Collection[str] | None = None) -> npt.NDArray[np.void]:
        """Row dicts as the decoded rows' structured array. A row must hold every field and no other; with
        ``optional`` (rows of older logs), the fields named there may be missing (they read as their default)
        and fields the rows do not have are ignored."""
        return self._layout().from_dicts(rows, optional, self.name)

    # ------------------------------------------------------------------ decoding
    def decode(self, data: bytes | memoryview) -> DecodedTable:
        """The header and rows of one message (module docstring).

        Raises :class:`InvalidInputError` when the bytes are not a valid message of this type.
        """
        try:
            return self._decode_fast(memoryview(data))
        except _Unusual:
            return self._decode_reference(bytes(data))

    def to_dict(self, data: bytes | memoryview) -> dict[str, Any]:
        """The message as the dict of its JSON form: ints as int, floats as float, rows as dicts."""
        header, rows = self.decode(data)
        if self.table_key is None:
            return header
        return self.as_dict(header, rows)

    def as_dict(self, header: Mapping[str, Any], rows: npt.NDArray[np.void] | None) -> dict[str, Any]:
        """A decoded header and rows as one JSON-shaped dict, in field-number order."""
        names = (rows.dtype.names or ()) if rows is not None else ()
        table = [dict(zip(names, values)) for values in rows.tolist()] if rows is not None else []
        return {k: (table if k == self.table_key else header[k]) for k in self._order
                if k in header or k == self.table_key}

    def _decode_fast(self, buf: memoryview) -> DecodedTable:
        values: dict[str, Any] = {}
        pos, end = 0, len(buf)
        row_tag = self._rows.tag if self._rows is not None else b"\x00"
        while pos < end:
            if buf[pos] == row_tag[0] and buf[pos:pos + len(row_tag)] == row_tag:
                break
            tag, pos = _read_varint(buf, pos, end)
            field = self._by_number.get(tag >> 3)
            if field is None or tag & 7 != field.wire_type:
                raise _Unusual
            value, pos = _read_value(field, buf, pos, end)
            values[field.name] = value
        rows = self._rows.decode(buf, pos) if self._rows is not None else None
        return DecodedTable(self._header(values), rows)

    def _header(self, values: dict[str, Any]) -> dict[str, Any]:
        out = {}
        for f in self.fields:
            if f.name in values:
                out[f.name] = values[f.name]
            elif not f.presence:
                out[f.name] = f.default()
        return out

    def _decode_reference(self, data: bytes) -> DecodedTable:
        message = self._class()
        try:
            message.ParseFromString(data)
        except DecodeError as err:
            raise InvalidInputError(f"not a valid {self.name}: {err}") from err
        values: dict[str, Any] = {}
        for f in self.fields:
            if f.presence and not message.HasField(f.name):
                continue
            value = getattr(message, f.name)
            values[f.name] = list(value) if f.repeated else (f.enum[0].get(value, value) if f.enum else value)
        rows = self._rows.from_messages(getattr(message, self.table_key)) if self._rows is not None else None
        return DecodedTable(self._header(values), rows)


def _read_value(field: _Field, buf: memoryview, pos: int, end: int) -> tuple[Any, int]:
    """The value of a header field at ``pos`` (its tag read) and the position after it."""
    wire = field.wire_type
    if wire == _VARINT:
        raw, pos = _read_varint(buf, pos, end)
        return _varint_value(field, raw), pos
    if wire == _LENGTH:
        length, pos = _read_varint(buf, pos, end)
        if pos + length > end:
            raise _Unusual
        chunk = buf[pos:pos + length]
        if field.type == _T.TYPE_STRING:
            try:
                return str(chunk, "utf-8"), pos + length
            except UnicodeDecodeError:
                raise _Unusual from None
        if field.type not in _FIXED:  # packed varints: the parser reads them
            raise _Unusual
        width = np.dtype(_FIXED[field.type][1]).itemsize
        if length % width:
            raise _Unusual
        return np.frombuffer(chunk, dtype=_FIXED[field.type][1]).tolist(), pos + length
    reader = _STRUCTS[field.type]
    if pos + reader.size > end:
        raise _Unusual
    return reader.unpack_from(buf, pos)[0], pos + reader.size


def _varint_value(field: _Field, raw: int) -> Any:
    if field.type == _T.TYPE_BOOL:
        return raw != 0
    if field.type in (_T.TYPE_INT32, _T.TYPE_ENUM):
        value = _signed(raw, 32)
        return field.enum[0].get(value, value) if field.enum else value
    if field.type == _T.TYPE_INT64:
        return _signed(raw, 64)
    if field.type == _T.TYPE_UINT32:
        return raw & 0xFFFFFFFF
    return raw


def _header_writer(field: _Field) -> Callable[[Any], bytes]:
    """A function writing one header field (tag and value) from a Python or numpy value."""
    tag = field.tag
    if field.repeated:
        fmt = _FIXED.get(field.type, (0, ""))[1]

        def repeated(value: Any) -> bytes:
            if isinstance(value, (str, bytes, Mapping)) or not isinstance(value, (Sequence, np.ndarray)):
                raise InvalidInputError(f"field {field.name!r} takes a list of numbers, got {value!r}.")
            items = [_checked_scalar(field, v) for v in value]
            body = np.asarray(items, dtype=fmt).tobytes() if fmt else b"".join(_varint(v) for v in items)
            return tag + _varint(len(body)) + body

        return repeated
    if field.type == _T.TYPE_STRING:
        def text(value: Any) -> bytes:
            if not isinstance(value, str):
                raise InvalidInputError(f"field {field.name!r} takes a string, got {value!r}.")
            body = value.encode("utf-8")
            return tag + _varint(len(body)) + body

        return text
    if field.type in _FIXED:
        packer = _STRUCTS[field.type].pack
        return lambda value: tag + packer(_checked_scalar(field, value))
    return lambda value: tag + _varint(_checked_scalar(field, value))


def _checked_scalar(field: _Field, value: Any) -> Any:
    """``value`` as the Python value a field of this type writes; InvalidInputError when it does not fit."""
    if field.enum is not None and isinstance(value, str):
        if value not in field.enum[1]:
            raise InvalidInputError(f"field {field.name!r} takes one of {sorted(field.enum[1])}, got {value!r}.")
        return field.enum[1][value]
    is_bool = isinstance(value, (bool, np.bool_))
    if field.type == _T.TYPE_BOOL:
        if not is_bool:
            raise InvalidInputError(f"field {field.name!r} takes a boolean, got {value!r}.")
        return int(value)
    if field.type in (_T.TYPE_DOUBLE, _T.TYPE_FLOAT):
        if is_bool or not isinstance(value, (int, float, np.integer, np.floating)):
            raise InvalidInputError(f"field {field.name!r} takes a number, got {value!r}.")
        return float(value)
    if is_bool or not isinstance(value, (int, np.integer)):
        if isinstance(value, (float, np.floating)) and float(value).is_integer():
            value = int(value)
        else:
            raise InvalidInputError(f"field {field.name!r} takes an integer, got {value!r}.")
    low, high = _VARINTS.get(field.type) or _RANGES[_FIXED[field.type][1]]
    if not low <= int(value) < high:
        raise InvalidInputError(f"field {field.name!r}: {value} is out of its range [{low}, {high}).")
    return int(value)


class _RowLayout:
    """The rows of a table field: the template of one encoded row, where each value lies, the decoded dtype."""

    def __init__(self, table: FieldDescriptor) -> None:
        self.fields = [_Field.of(fd) for fd in sorted(table.message_type.fields, key=lambda f: f.number)]
        if any(f.repeated or f.presence or f.type in _VARINTS and f.type not in (_T.TYPE_BOOL, _T.TYPE_ENUM)
               or f.type == _T.TYPE_STRING for f in self.fields):
            raise UnsupportedMessage(f"the rows of {table.full_name} are not all fixed-width scalars")
        if any(f.enum is not None and not all(0 <= n < 0x80 for n in f.enum[0]) for f in self.fields):
            raise UnsupportedMessage(f"an enum of {table.full_name} has values outside 0..127")
        body, offsets, formats, mask = bytearray(), {}, [], bytearray()
        for f in self.fields:
            body += f.tag
            mask += b"\xff" * len(f.tag)
            fmt = _FIXED[f.type][1] if f.type in _FIXED else "u1"
            offsets[f.name] = len(body)
            formats.append(fmt)
            width = np.dtype(fmt).itemsize
            body += bytes(width)
            # a bool is written 0 or 1, an enum as a one-byte varint; other values are not checked
            mask += b"\xfe" if f.type == _T.TYPE_BOOL else b"\x80" if fmt == "u1" else bytes(width)
        head = _varint(table.number << 3 | _LENGTH) + _varint(len(body))
        self.tag = _varint(table.number << 3 | _LENGTH)
        self.template = head + bytes(body)
        self.size = len(self.template)
        self.offsets = {name: at + len(head) for name, at in offsets.items()}
        names = [f.name for f in self.fields]
        self.wire = np.dtype({"names": names, "formats": formats, "offsets": list(self.offsets.values()),
                              "itemsize": self.size})
        self.dtype = np.dtype([(f.name, _decoded_format(f, fmt)) for f, fmt in zip(self.fields, formats)])
        self._mask = np.frombuffer(len(head) * b"\xff" + bytes(mask), dtype=np.uint8)
        self._expected = np.frombuffer(self.template, dtype=np.uint8) & self._mask
        self._plans: dict[Any, list[tuple[_Field, bool]]] = {}
        self._enums = {f.name: (np.array([f.enum[0].get(k, "") for k in range(0x80)], dtype=self.dtype[f.name]),
                                np.array([k in f.enum[0] for k in range(0x80)]))
                       for f in self.fields if f.enum is not None}

    def encode(self, rows: npt.NDArray[np.void], extra: Mapping[str, npt.ArrayLike], what: str) -> bytes:
        if not isinstance(rows, np.ndarray) or rows.ndim != 1 or rows.dtype.names is None:
            raise InvalidInputError(f"{what} rows come as a 1-D structured array; got {np.shape(rows)} "
                                    f"of {getattr(rows, 'dtype', type(rows).__name__)}.")
        n = int(rows.shape[0])
        extras = {name: np.asarray(column) for name, column in extra.items()}
        if any(c.shape != (n,) for c in extras.values()):
            raise InvalidInputError(f"every column of {what} rows needs {n} values.")
        plan = self._plan(rows.dtype, tuple((name, c.dtype) for name, c in extras.items()), what)
        buffer = bytearray(self.template * n)
        if n:
            view = np.frombuffer(buffer, dtype=self.wire)
            for f, direct in plan:
                column = extras[f.name] if f.name in extras else rows[f.name]
                view[f.name] = column if direct else _column(f, column, n, what)
        return bytes(buffer)

    def _plan(self, dtype: np.dtype[Any], extra: tuple[tuple[str, np.dtype[Any]], ...], what: str
              ) -> list[tuple[_Field, bool]]:
        """Per row field, whether its column is written as it is (a safe cast) or checked value by value first;
        settled once per column layout. Raises InvalidInputError for a missing, unknown or repeated column."""
        key = (dtype, extra)
        plan = self._plans.get(key)
        if plan is None:
            types = {name: dtype.fields[name][0] for name in dtype.names or ()}
            if any(name in types for name, _ in extra):
                raise InvalidInputError(f"{what} rows with a repeated field {next(n for n, _ in extra if n in types)!r}.")
            types.update(extra)
            unknown = sorted(set(types) - set(self.offsets))
            missing = [f.name for f in self.fields if f.name not in types]
            if unknown:
                raise InvalidInputError(f"{what} has no field {unknown[0]!r}.")
            if missing:
                raise InvalidInputError(f"{what} rows need the field {missing[0]!r}.")
            plan = self._plans[key] = [(f, _direct(f, types[f.name])) for f in self.fields]
        return plan

    def decode(self, buf: memoryview, start: int) -> npt.NDArray[np.void]:
        """The rows from ``start`` to the end of ``buf``, when every one is laid out as the template."""
        length = len(buf) - start
        if length % self.size:
            raise _Unusual
        n = length // self.size
        raw = np.frombuffer(buf, dtype=np.uint8, offset=start).reshape(n, self.size)
        if not ((raw & self._mask) == self._expected).all():
            raise _Unusual
        view = np.frombuffer(buf, dtype=self.wire, count=n, offset=start)
        out = np.empty(n, dtype=self.dtype)
        if not self._enums:
            out[...] = view
            return out
        for f in self.fields:
            if f.name not in self._enums:
                out[f.name] = view[f.name]
                continue
            names, known = self._enums[f.name]
            codes = view[f.name]
            if not known[codes].all():  # a value without a name: the parser's reading keeps its number
                raise _Unusual
            out[f.name] = names[codes]
        return out

    def from_messages(self, rows: Any) -> npt.NDArray[np.void]:
        """Parsed row messages (the protobuf runtime's) as the decoded dtype (an enum number without a name as
        its decimal text)."""
        values = [tuple(_row_value(f, getattr(r, f.name)) for f in self.fields) for r in rows]
        return np.array(values, dtype=self.dtype) if values else np.zeros(0, dtype=self.dtype)

    def from_dicts(self, rows: Sequence[Mapping[str, Any]], optional: Collection[str] | None,
                   what: str) -> npt.NDArray[np.void]:
        names = {f.name for f in self.fields}
        needed = names - set(optional or ())
        for row in rows:
            if not isinstance(row, Mapping):
                raise InvalidInputError(f"a row of {what} is an object, got {type(row).__name__}.")
            missing = sorted(needed - set(row))
            extra = sorted(set(row) - names) if optional is None else []
            if missing or extra:
                raise InvalidInputError(f"{what} has no field {extra[0]!r}." if extra else
                                        f"{what} rows need the field {missing[0]!r}.")
        columns = {f.name: [row.get(f.name, f.default()) for row in rows] for f in self.fields}
        out = np.zeros(len(rows), dtype=self.dtype)
        for f in self.fields:
            if rows:
                out[f.name] = _column(f, columns[f.name], len(rows), what, decoded=True)
        return out


def _direct(field: _Field, dtype: np.dtype[Any]) -> bool:
    """Whether a column of ``dtype`` goes into the field's wire values by a plain (safe) numpy cast."""
    if field.enum is not None:
        return False
    if field.type == _T.TYPE_BOOL:
        return dtype.kind == "b"
    fmt = _FIXED[field.type][1]
    if fmt[1] == "f":
        return dtype.kind in "iuf"
    return dtype.kind in "iu" and np.can_cast(dtype, fmt, "safe")


def _row_value(field: _Field, value: Any) -> Any:
    return field.enum[0].get(value, str(value)) if field.enum is not None else value


def _decoded_format(field: _Field, wire_format: str) -> np.dtype[Any]:
    """The dtype of a row field decoded: native byte order; bool; an enum's names as strings."""
    if field.type == _T.TYPE_BOOL:
        return np.dtype(np.bool_)
    if field.enum is not None:
        return np.dtype(f"U{max(11, *(len(n) for n in field.enum[0].values()))}")  # 11: any int32 as text
    return np.dtype(wire_format).newbyteorder("=")


def _column(field: _Field, values: npt.ArrayLike, n: int, what: str, *, decoded: bool = False) -> npt.NDArray[Any]:
    """One column's values, checked and converted for its wire field (``decoded``: for the decoded dtype)."""
    column = np.asarray(values)
    if column.shape != (n,):
        raise InvalidInputError(f"{what}: column {field.name!r} needs {n} values; got shape {column.shape}.")
    kind = column.dtype.kind
    if field.enum is not None:
        return _enum_column(field, column, what, decoded)
    if field.type == _T.TYPE_BOOL:
        if kind != "b":
            raise InvalidInputError(f"{what}: column {field.name!r} takes booleans, got {column.dtype}.")
        return column
    fmt = _FIXED[field.type][1]
    if kind not in "iuf":
        wanted = "numbers" if fmt[1] == "f" else "integers"
        raise InvalidInputError(f"{what}: column {field.name!r} takes {wanted}, got {column.dtype}.")
    if fmt[1] == "f" or (kind != "f" and np.can_cast(column.dtype, fmt, "safe")):
        return column
    # a float column, or integers wider than the field: their values must fit
    low, high = _RANGES[fmt]
    if kind == "f" and not (np.isfinite(column).all() and (column == np.round(column)).all()):
        raise InvalidInputError(f"{what}: column {field.name!r} takes integers; it holds fractions or non-finite "
                                "values.")
    if column.size and not (low <= int(column.min()) and int(column.max()) < high):
        raise InvalidInputError(f"{what}: column {field.name!r} holds values outside [{low}, {high}).")
    return column.astype(fmt)


def _enum_column(field: _Field, column: npt.NDArray[Any], what: str, decoded: bool) -> npt.NDArray[Any]:
    """An enum column (names, or numbers of defined values) as its codes, or with ``decoded`` as its names."""
    assert field.enum is not None
    names, numbers = field.enum
    if column.dtype.kind == "U":
        unknown = set(column.tolist()) - set(numbers)
        if unknown:
            raise InvalidInputError(f"{what}: column {field.name!r} takes one of {sorted(numbers)}; got "
                                    f"{sorted(unknown)[0]!r}.")
        return column if decoded else np.array([numbers[v] for v in column.tolist()], dtype=np.uint8)
    if column.dtype.kind not in "iu" or not set(column.tolist()) <= set(names):
        raise InvalidInputError(f"{what}: column {field.name!r} takes the names or numbers of {sorted(numbers)}.")
    return np.array([names[v] for v in column.tolist()]) if decoded else column.astype(np.uint8)
