"""The rows of a table message: one fixed-width layout, written and read as numpy structured arrays.

Every field of a row is fixed-width (``double``, ``float``, ``fixed32``, ``sfixed32``, ``fixed64``,
``sfixed64``; ``bool`` and enums as one-byte varints), so with every field written each row has the same
bytes but for its values. :class:`RowLayout` keeps one row's template (the row's tag and length, each
field's tag), writes a table as copies of it with the values filled in column by column, and reads one
back with ``np.frombuffer`` once every row's tag bytes match the template; a column's type is settled
once per column layout (a safe numpy cast), and only other columns are checked value by value.
"""

from __future__ import annotations

from collections.abc import Collection, Mapping, Sequence
from typing import Any

import numpy as np
import numpy.typing as npt
from google.protobuf.descriptor import FieldDescriptor

from starlog.errors import InvalidInputError
from starlog.codecs.table_fields import FIXED, LENGTH, RANGES, VARINTS, Field, Unusual, UnsupportedMessage, varint

__all__ = ["RowLayout"]

_T = FieldDescriptor

class RowLayout:
    """The rows of a table field: the template of one encoded row, where each value lies, the decoded dtype."""

    def __init__(self, table: FieldDescriptor) -> None:
        self.fields = [Field.of(fd) for fd in sorted(table.message_type.fields, key=lambda f: f.number)]
        if any(f.repeated or f.presence or f.type in VARINTS and f.type not in (_T.TYPE_BOOL, _T.TYPE_ENUM)
               or f.type == _T.TYPE_STRING for f in self.fields):
            raise UnsupportedMessage(f"the rows of {table.full_name} are not all fixed-width scalars")
        if any(f.enum is not None and not all(0 <= n < 0x80 for n in f.enum[0]) for f in self.fields):
            raise UnsupportedMessage(f"an enum of {table.full_name} has values outside 0..127")
        body, offsets, formats, mask = bytearray(), {}, [], bytearray()
        for f in self.fields:
            body += f.tag
            mask += b"\xff" * len(f.tag)
            fmt = FIXED[f.type][1] if f.type in FIXED else "u1"
            offsets[f.name] = len(body)
            formats.append(fmt)
            width = np.dtype(fmt).itemsize
            body += bytes(width)
            # a bool is written 0 or 1, an enum as a one-byte varint; other values are not checked
            mask += b"\xfe" if f.type == _T.TYPE_BOOL else b"\x80" if fmt == "u1" else bytes(width)
        head = varint(table.number << 3 | LENGTH) + varint(len(body))
        self.tag = varint(table.number << 3 | LENGTH)
        self.template = head + bytes(body)
        self.size = len(self.template)
        self.offsets = {name: at + len(head) for name, at in offsets.items()}
        names = [f.name for f in self.fields]
        self.wire = np.dtype({"names": names, "formats": formats, "offsets": list(self.offsets.values()),
                              "itemsize": self.size})
        self.dtype = np.dtype([(f.name, _decoded_format(f, fmt)) for f, fmt in zip(self.fields, formats)])
        self._mask = np.frombuffer(len(head) * b"\xff" + bytes(mask), dtype=np.uint8)
        self._expected = np.frombuffer(self.template, dtype=np.uint8) & self._mask
        self._plans: dict[Any, list[tuple[Field, bool]]] = {}
        self._defaults = {f.name: f.default() for f in self.fields}
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
              ) -> list[tuple[Field, bool]]:
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
            raise Unusual
        n = length // self.size
        raw = np.frombuffer(buf, dtype=np.uint8, offset=start).reshape(n, self.size)
        if not ((raw & self._mask) == self._expected).all():
            raise Unusual
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
                raise Unusual
            out[f.name] = names[codes]
        return out

    def from_messages(self, rows: Any) -> npt.NDArray[np.void]:
        """Parsed row messages (the protobuf runtime's) as the decoded dtype (an enum number without a name as
        its decimal text)."""
        values = [tuple(_row_value(f, getattr(r, f.name)) for f in self.fields) for r in rows]
        return np.array(values, dtype=self.dtype) if values else np.zeros(0, dtype=self.dtype)

    def from_dicts(self, rows: Sequence[Mapping[str, Any]], optional: Collection[str] | None,
                   what: str) -> npt.NDArray[np.void]:
        names = self.offsets.keys()
        needed = names - set(optional or ())
        for row in rows:
            keys = row.keys() if isinstance(row, Mapping) else None
            if keys is None or (keys != names if optional is None else not needed <= keys):
                raise InvalidInputError(_row_problem(row, names, needed, optional is None, what))
        out = np.zeros(len(rows), dtype=self.dtype)
        if not rows:
            return out
        for f in self.fields:
            values = ([row[f.name] for row in rows] if f.name in needed else
                      [row.get(f.name, self._defaults[f.name]) for row in rows])
            if optional is None:
                out[f.name] = _column(f, values, len(rows), what, decoded=True)
                continue
            try:  # rows read from a log: numpy converts them (the JSON reader checked their types)
                out[f.name] = values
            except (TypeError, ValueError, OverflowError) as err:
                raise InvalidInputError(f"{what} rows hold a {f.name!r} of the wrong type ({err}).") from err
        return out


def _row_problem(row: Any, names: Collection[str], needed: Collection[str], strict: bool, what: str) -> str:
    """What is wrong with a row dict that :meth:`RowLayout.from_dicts` refuses."""
    if not isinstance(row, Mapping):
        return f"a row of {what} is an object, got {type(row).__name__}."
    extra = sorted(set(row) - set(names)) if strict else []
    if extra:
        return f"{what} has no field {extra[0]!r}."
    return f"{what} rows need the field {sorted(set(needed) - set(row))[0]!r}."


def _direct(field: Field, dtype: np.dtype[Any]) -> bool:
    """Whether a column of ``dtype`` goes into the field's wire values by a plain (safe) numpy cast."""
    if field.enum is not None:
        return False
    if field.type == _T.TYPE_BOOL:
        return dtype.kind == "b"
    fmt = FIXED[field.type][1]
    if fmt[1] == "f":
        return dtype.kind in "iuf"
    return dtype.kind in "iu" and np.can_cast(dtype, fmt, "safe")


def _row_value(field: Field, value: Any) -> Any:
    return field.enum[0].get(value, str(value)) if field.enum is not None else value


def _decoded_format(field: Field, wire_format: str) -> np.dtype[Any]:
    """The dtype of a row field decoded: native byte order; bool; an enum's names as strings."""
    if field.type == _T.TYPE_BOOL:
        return np.dtype(np.bool_)
    if field.enum is not None:
        return np.dtype(f"U{max(11, *(len(n) for n in field.enum[0].values()))}")  # 11: any int32 as text
    return np.dtype(wire_format).newbyteorder("=")


def _column(field: Field, values: npt.ArrayLike, n: int, what: str, *, decoded: bool = False) -> npt.NDArray[Any]:
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
    fmt = FIXED[field.type][1]
    if kind not in "iuf":
        wanted = "numbers" if fmt[1] == "f" else "integers"
        raise InvalidInputError(f"{what}: column {field.name!r} takes {wanted}, got {column.dtype}.")
    if fmt[1] == "f" or (kind != "f" and np.can_cast(column.dtype, fmt, "safe")):
        return column
    # a float column, or integers wider than the field: their values must fit
    low, high = RANGES[fmt]
    if kind == "f" and not (np.isfinite(column).all() and (column == np.round(column)).all()):
        raise InvalidInputError(f"{what}: column {field.name!r} takes integers; it holds fractions or non-finite "
                                "values.")
    if column.size and not (low <= int(column.min()) and int(column.max()) < high):
        raise InvalidInputError(f"{what}: column {field.name!r} holds values outside [{low}, {high}).")
    return column.astype(fmt)


def _enum_column(field: Field, column: npt.NDArray[Any], what: str, decoded: bool) -> npt.NDArray[Any]:
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
