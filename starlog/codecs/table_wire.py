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

The rows are :mod:`starlog.codecs.table_rows`'s, the fields :mod:`starlog.codecs.table_fields`'s; the three modules
depend on numpy and the protobuf runtime only (and starlog's error type). Wire format:
https://protobuf.dev/programming-guides/encoding/ .
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Mapping, Sequence
from typing import Any, NamedTuple

import numpy as np
import numpy.typing as npt
from google.protobuf import message_factory
from google.protobuf.descriptor import Descriptor, FieldDescriptor
from google.protobuf.message import DecodeError

from starlog.errors import InvalidInputError
from starlog.codecs.table_fields import (
    FIXED,
    LENGTH,
    RANGES,
    STRUCTS,
    VARINT,
    VARINTS,
    Field,
    Unusual,
    UnsupportedMessage,
    is_repeated,
    read_varint,
    signed,
    varint,
)
from starlog.codecs.table_rows import RowLayout

__all__ = ["DecodedTable", "TableCodec", "UnsupportedMessage"]

_T = FieldDescriptor


class DecodedTable(NamedTuple):
    """A decoded table message: the header fields (a dict) and the rows (a structured array; None when the
    message type has no table)."""

    header: dict[str, Any]
    rows: npt.NDArray[np.void] | None


class TableCodec:
    """Encode and decode one table message type (module docstring), built from its protobuf descriptor.

    Raises :class:`UnsupportedMessage` when the message is not a table message.
    """

    def __init__(self, descriptor: Descriptor) -> None:
        self.name: str = descriptor.full_name
        self._class = message_factory.GetMessageClass(descriptor)
        table = [fd for fd in descriptor.fields if fd.type == _T.TYPE_MESSAGE]
        if len(table) > 1 or (table and not is_repeated(table[0])):
            raise UnsupportedMessage(f"{self.name} holds sub-messages other than one repeated table")
        self.fields = [Field.of(fd) for fd in sorted(descriptor.fields, key=lambda f: f.number) if fd not in table]
        self._by_number = {f.number: f for f in self.fields}
        self.table_key: str | None = table[0].name if table else None
        self._order = [fd.name for fd in sorted(descriptor.fields, key=lambda f: f.number)]
        self._rows = RowLayout(table[0]) if table else None
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

    def _layout(self) -> RowLayout:
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
        unknown = header.keys() - self._header_writers.keys()
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
        except Unusual:
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
            tag, pos = read_varint(buf, pos, end)
            field = self._by_number.get(tag >> 3)
            if field is None or tag & 7 != field.wire_type or (field.repeated and field.name in values):
                raise Unusual  # the parser merges a repeated field's occurrences, skips unknown fields
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


def _read_value(field: Field, buf: memoryview, pos: int, end: int) -> tuple[Any, int]:
    """The value of a header field at ``pos`` (its tag read) and the position after it."""
    wire = field.wire_type
    if wire == VARINT:
        raw, pos = read_varint(buf, pos, end)
        return _varint_value(field, raw), pos
    if wire == LENGTH:
        length, pos = read_varint(buf, pos, end)
        if pos + length > end:
            raise Unusual
        chunk = buf[pos:pos + length]
        if field.type == _T.TYPE_STRING:
            try:
                return str(chunk, "utf-8"), pos + length
            except UnicodeDecodeError:
                raise Unusual from None
        if field.type not in FIXED:  # packed varints: the parser reads them
            raise Unusual
        width = np.dtype(FIXED[field.type][1]).itemsize
        if length % width:
            raise Unusual
        return np.frombuffer(chunk, dtype=FIXED[field.type][1]).tolist(), pos + length
    reader = STRUCTS[field.type]
    if pos + reader.size > end:
        raise Unusual
    return reader.unpack_from(buf, pos)[0], pos + reader.size


def _varint_value(field: Field, raw: int) -> Any:
    if field.type == _T.TYPE_BOOL:
        return raw != 0
    if field.type in (_T.TYPE_INT32, _T.TYPE_ENUM):
        value = signed(raw, 32)
        return field.enum[0].get(value, value) if field.enum else value
    if field.type == _T.TYPE_INT64:
        return signed(raw, 64)
    if field.type == _T.TYPE_UINT32:
        return raw & 0xFFFFFFFF
    return raw


def _header_writer(field: Field) -> Callable[[Any], bytes]:
    """A function writing one header field (tag and value) from a Python or numpy value."""
    tag = field.tag
    if field.repeated:
        fmt = FIXED.get(field.type, (0, ""))[1]

        def repeated(value: Any) -> bytes:
            if isinstance(value, (str, bytes, Mapping)) or not isinstance(value, (Sequence, np.ndarray)):
                raise InvalidInputError(f"field {field.name!r} takes a list of numbers, got {value!r}.")
            items = [_checked_scalar(field, v) for v in value]
            body = np.asarray(items, dtype=fmt).tobytes() if fmt else b"".join(varint(v) for v in items)
            return tag + varint(len(body)) + body

        return repeated
    if field.type == _T.TYPE_STRING:
        def text(value: Any) -> bytes:
            if not isinstance(value, str):
                raise InvalidInputError(f"field {field.name!r} takes a string, got {value!r}.")
            body = value.encode("utf-8")
            return tag + varint(len(body)) + body

        return text
    if field.type in FIXED:
        packer = STRUCTS[field.type].pack
        return lambda value: tag + packer(_checked_scalar(field, value))
    return lambda value: tag + varint(_checked_scalar(field, value))


def _checked_scalar(field: Field, value: Any) -> Any:
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
    low, high = VARINTS.get(field.type) or RANGES[FIXED[field.type][1]]
    if not low <= int(value) < high:
        raise InvalidInputError(f"field {field.name!r}: {value} is out of its range [{low}, {high}).")
    return int(value)
