"""JSON star rows: messages whose last property is a list of flat records, encoded from a structured array.

The star tables of earlier versions were such JSON messages (starlog writes them as protobuf now,
:mod:`starlog.codecs.star_tables`); this writes them for the old logs the tests read (``tests/json_logs.py``)
and for ``tools/bench_io.py``'s JSON side.

Per-frame messages (detections, centroids, tracks) hold one record per star. Building a dict
per record, encoding it, decoding it back and walking every value against the schema cost more
than the algorithms that made the records. :class:`RecordEncoder` writes the same bytes as
:func:`~starlog.codecs.json_messages.encode_json` of the dicts would, from the array's columns (each
column is encoded once, as one list, and cut into its values), and checks columns, not decoded
values, against the records' schema: a column's dtype gives the JSON type of all its values
(settled once per column layout), and bounds, enums and finiteness are tested on whole columns.
When a column fails, the records are encoded and checked one by one the reference way, which
raises the error naming the offending value; so what is written, and what is refused, is as before.
"""

from __future__ import annotations

import functools
import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
import orjson

from starlog.errors import InvalidInputError
from starlog.codecs.checked_json import CheckedJson, schema_checker, schema_digest
from starlog.codecs.json_schema import compile_json_schema
from starlog.codecs.json_messages import decode_json, encode_json
from starlog.codecs.schemas import MessageType, json_message_type

__all__ = ["RecordEncoder", "record_encoder", "structured_to_dicts"]

#: numpy dtype kinds whose values (``tolist``) have each JSON type, as the schema checker sees them.
_KINDS = {"integer": "iuf", "number": "iuf", "boolean": "b", "string": "U"}
_COLUMN_KEYWORDS = {"type", "enum", "minimum", "maximum", "description", "unit", "examples", "default", "title"}
_ARRAY_KEYWORDS = {"type", "items", "description", "title"}


def structured_to_dicts(array: npt.NDArray[np.void]) -> list[dict[str, Any]]:
    """Structured array → one JSON-ready dict (field name → Python scalar) per row."""
    names = array.dtype.names or ()
    return [dict(zip(names, values)) for values in array.tolist()]


@dataclass(frozen=True)
class _Plan:
    """One column layout: the row template and, per column, the value tests left (None: the dtype fails)."""

    template: bytes
    checks: list[dict[str, Any] | None]


class RecordEncoder:
    """Encode ``{header..., key: [records]}`` messages of one type from structured arrays.

    ``key`` is the message's property that holds the records; it must be an array of objects whose
    properties are scalars described by ``type``, ``enum``, ``minimum`` and ``maximum`` only.
    Raises :class:`InvalidInputError` for a schema outside that shape. Records are one 1-D
    structured array of scalar fields (plus ``extra`` columns of other names), and the header
    comes first: a repeated field name, a sub-array field or a header that does not end with
    ``key`` are refused, where a dict message would be written.
    """

    def __init__(self, message_type: MessageType, key: str) -> None:
        schema = json.loads(message_type.schema_data)
        array = schema.get("properties", {}).get(key)
        items = array.get("items") if isinstance(array, dict) else None
        if not (isinstance(items, dict) and set(array) <= _ARRAY_KEYWORDS and isinstance(items.get("properties"), dict)
                and all(set(p) <= _COLUMN_KEYWORDS for p in items["properties"].values())):
            raise InvalidInputError(f"{message_type.schema_name}: {key!r} is not an array of flat records.")
        self.message_type = message_type
        self.key = key
        self._key_json = orjson.dumps(key)
        self._properties: dict[str, dict[str, Any]] = items["properties"]
        self._required = frozenset(items.get("required", ()))
        # unknown columns: anything goes (absent or true), else the reference path decides (false, or a schema)
        self._open = items.get("additionalProperties", True) is True
        self._check_message = schema_checker(message_type.schema_data)
        self._check_record = compile_json_schema(items)
        self._digest = schema_digest(message_type.schema_data)
        self._plans: dict[tuple[tuple[str, ...], tuple[np.dtype[Any], ...]], _Plan] = {}

    def rows(self, table: npt.NDArray[np.void], extra: Mapping[str, npt.ArrayLike] | None = None) -> list[bytes]:
        """Each row of ``table`` (then the ``extra`` columns, in order) as the JSON object of its record.

        Raises :class:`InvalidInputError` when a record does not match the schema or holds NaN or infinity.
        """
        if np.ndim(table) != 1:
            raise InvalidInputError(f"{self.message_type.schema_name} records come as a 1-D array; got shape "
                                    f"{np.shape(table)}.")
        extra = extra or {}
        names = (*(table.dtype.names or ()), *extra)
        columns = [table[name] for name in table.dtype.names or ()] + [np.asarray(c) for c in extra.values()]
        n = int(table.shape[0])
        if any(c.shape != (n,) for c in columns):
            raise InvalidInputError(f"every column of {self.message_type.schema_name} records needs {n} values.")
        if n == 0:
            return []
        plan = self._plan(names, tuple(c.dtype for c in columns))
        if any(check is None for check in plan.checks):
            return self._reference_rows(names, columns)
        values = []
        for column, check in zip(columns, plan.checks, strict=True):
            try:
                if column.dtype.kind == "U":  # strings may hold commas: encoded one at a time
                    values.append([orjson.dumps(v) for v in column.tolist()])
                    text = b""
                else:
                    text = orjson.dumps(column.tolist())
                    values.append(text[1:-1].split(b","))
            except (orjson.JSONEncodeError, TypeError):
                return self._reference_rows(names, columns)
            # orjson writes NaN and infinities as null
            if b"null" in text or (check and not _values_valid(column, check)):
                return self._reference_rows(names, columns)
        return [plan.template % row for row in zip(*values)]

    def message(self, header: Mapping[str, Any], rows: Sequence[bytes]) -> CheckedJson:
        """The message ``{**header, key: rows}`` (``rows`` from :meth:`rows`), checked against the schema.

        Raises :class:`InvalidInputError` when the header does not match the schema, cannot be encoded,
        or does not end with ``key`` (the records come last).
        """
        head = encode_json({**header, self.key: []})
        if not head.endswith(b"," + self._key_json + b":[]}"):
            raise InvalidInputError(f"{self.key!r} must come last in a {self.message_type.schema_name} message, "
                                    "after a header of at least one property.")
        problem = self._check_message(orjson.loads(head))
        if problem:
            raise InvalidInputError(
                f"a {self.message_type.schema_name} message does not match its schema ({problem}).")
        return CheckedJson(head[:-2] + b",".join(rows) + b"]}", self._digest)

    def encode(self, header: Mapping[str, Any], table: npt.NDArray[np.void]) -> CheckedJson:
        """:meth:`message` of the rows of ``table``: the bytes of ``encode_json({**header, key: dicts})``."""
        return self.message(header, self.rows(table))

    def _plan(self, names: tuple[str, ...], dtypes: tuple[np.dtype[Any], ...]) -> _Plan:
        """What the columns' dtypes settle (once per layout) and what is left to test on the values."""
        plan = self._plans.get((names, dtypes))
        if plan is None:
            checks: list[dict[str, Any] | None] = []
            for name, dtype in zip(names, dtypes, strict=True):
                schema = self._properties.get(name)
                checks.append(({} if self._open else None) if schema is None else _value_checks(dtype, schema))
            if not self._required <= set(names) or len(set(names)) != len(names):
                checks = [None] * len(names)
            template = b"{" + b",".join(orjson.dumps(name).replace(b"%", b"%%") + b":%b" for name in names) + b"}"
            plan = self._plans[(names, dtypes)] = _Plan(template, checks)
        return plan

    def _reference_rows(self, names: tuple[str, ...], columns: list[npt.NDArray[Any]]) -> list[bytes]:
        """The records encoded and checked one by one as dicts, the reference way: the error names the
        first bad value (a layout the column tests do not cover, e.g. an object column, may still pass)."""
        if len(set(names)) != len(names):
            raise InvalidInputError(f"{self.message_type.schema_name} records with a repeated field: {names}.")
        # encoded first, all of them: a NaN anywhere is named before any schema violation, as for a dict message
        out = [encode_json(dict(zip(names, values))) for values in zip(*(c.tolist() for c in columns))]
        for i, data in enumerate(out):
            problem = self._check_record(decode_json(data), f"$.{self.key}[{i}]")
            if problem:
                raise InvalidInputError(
                    f"a {self.message_type.schema_name} message does not match its schema ({problem}).")
        return out


@functools.cache
def record_encoder(schema_name: str, key: str) -> RecordEncoder:
    """The :class:`RecordEncoder` of a built-in JSON message type (e.g. ``"starlog.Centroids"``, ``"stars"``),
    made once per process."""
    return RecordEncoder(json_message_type(schema_name), key)


def _value_checks(dtype: np.dtype[Any], schema: Mapping[str, Any]) -> dict[str, Any] | None:
    """The tests a column of ``dtype`` still needs on its values to satisfy ``schema`` (None: it never can)."""
    kind = dtype.kind
    if kind not in "iufbU":
        return None
    types = schema.get("type")
    types = [types] if isinstance(types, str) else list(types or [])
    if types and not any(kind in _KINDS.get(t, "") for t in types):
        return None
    checks: dict[str, Any] = {k: schema[k] for k in ("enum", "minimum", "maximum") if k in schema}
    if kind not in "iuf":  # the checker applies bounds to numbers only
        checks.pop("minimum", None)
        checks.pop("maximum", None)
    if kind == "f" and "integer" in types and "number" not in types:
        checks["integral"] = True
    return checks


def _values_valid(column: npt.NDArray[Any], checks: Mapping[str, Any]) -> bool:
    """The value tests of :func:`_value_checks` on a whole column (of finite values)."""
    if "integral" in checks and not (column == np.round(column)).all():
        return False
    if "minimum" in checks and column.min().item() < checks["minimum"]:  # Python values: exact comparisons
        return False
    if "maximum" in checks and column.max().item() > checks["maximum"]:
        return False
    return "enum" not in checks or all(v in checks["enum"] for v in set(column.tolist()))
