"""starlog's star tables in either encoding: protobuf (what starlog writes) and the JSON of earlier logs.

The star tables are the messages of :data:`STAR_TABLES`: a header (frame, method, ...) and, for most,
one row per star under one key (``stars`` or ``tracks``). starlog writes them as protobuf
(``schemas/starlog/*.proto``) with :func:`star_codec` (:class:`~starlog.codecs.table_wire.TableCodec`:
the rows as one numpy array). Logs of earlier versions hold them as JSON, described by
``schemas/starlog.*.json``, with the same fields, names and meanings.

Readers get either encoding in two shapes:

* the dict of the JSON form (``payload["stars"]``, a list of dicts): :func:`schema_codec`'s
  ``to_dict`` for a protobuf channel (what :class:`~starlog.io.reader.LogReader` gives as a
  payload, ``cat`` prints and ``export --topic`` flattens), the JSON itself for a JSON channel;
* a :class:`~starlog.codecs.table_wire.DecodedTable`, the header as a dict and the rows as a
  structured array, no dict per star (:func:`decode_table`, ``LogReader.tables``): for the
  readers that go through every star of every frame.

A protobuf channel is decoded with the codec of the schema embedded in its log (the built-in one
when the schema is starlog's own), so a log written by another version reads by its own schema.
"""

from __future__ import annotations

from functools import cache
from typing import Any

from google.protobuf.descriptor_pb2 import FileDescriptorSet
from google.protobuf.descriptor_pool import DescriptorPool
from google.protobuf.message import DecodeError
from mcap.records import Schema

from starlog.errors import InvalidInputError
from starlog.codecs.json_messages import decode_json
from starlog.codecs.schemas import load_json_schema, protobuf_message_type, starlog_descriptor_set
from starlog.codecs.table_wire import DecodedTable, TableCodec, UnsupportedMessage

__all__ = ["STAR_TABLES", "DecodedTable", "decode_table", "json_table", "schema_codec", "star_codec"]

#: starlog's star tables: schema name → the key of its rows (None: a header-only message).
STAR_TABLES: dict[str, str | None] = {
    "starlog.Detections": "stars",
    "starlog.Centroids": "stars",
    "starlog.Tracks": "tracks",
    "starlog.PlatformMotion": None,
    "starlog.StarResiduals": "stars",
    "starlog.Attitude": None,
    "starlog.IdentifiedStars": "stars",
}


@cache
def _pool() -> DescriptorPool:
    pool = DescriptorPool()
    for file in starlog_descriptor_set().file:
        pool.Add(file)
    return pool


@cache
def star_codec(name: str) -> TableCodec:
    """The codec of the star table ``name`` (e.g. ``"starlog.Centroids"``), made once per process."""
    if name not in STAR_TABLES:
        raise InvalidInputError(f"{name!r} is not a star table; they are {', '.join(STAR_TABLES)}.")
    return TableCodec(_pool().FindMessageTypeByName(name))


_SCHEMA_CODECS: dict[tuple[str, bytes], TableCodec | None] = {}


def schema_codec(schema: Schema | None) -> TableCodec | None:
    """The codec of a log's protobuf star-table schema (None for any other schema, or one that does not give a
    table message: the generic protobuf decoder reads those)."""
    if schema is None or schema.encoding != "protobuf" or schema.name not in STAR_TABLES:
        return None
    key = (schema.name, bytes(schema.data))
    if key not in _SCHEMA_CODECS:
        _SCHEMA_CODECS[key] = _codec_of(schema.name, key[1])
    return _SCHEMA_CODECS[key]


def _codec_of(name: str, data: bytes) -> TableCodec | None:
    if data == protobuf_message_type(name).schema_data:
        return star_codec(name)
    try:
        pool = DescriptorPool()
        for file in FileDescriptorSet.FromString(data).file:
            pool.Add(file)
        return TableCodec(pool.FindMessageTypeByName(name))
    except (UnsupportedMessage, DecodeError, KeyError, TypeError, ValueError):  # not a table, or a broken set
        return None


@cache
def _optional_row_fields(name: str) -> frozenset[str]:
    """The row fields a JSON message of ``name`` may lack (not required by its JSON Schema: ``n_masked``)."""
    codec = star_codec(name)
    items = load_json_schema(name)["properties"][codec.table_key]["items"]
    return frozenset(codec.row_dtype.names or ()) - set(items.get("required", ()))


def json_table(name: str, value: Any) -> DecodedTable:
    """A star table's JSON message (decoded) as its header and rows; a row field that its JSON Schema does not
    require reads as its default when missing (``n_masked`` of logs written before it: 0).

    Raises :class:`InvalidInputError` when a row lacks a required field.
    """
    codec = star_codec(name)
    if not isinstance(value, dict):
        raise InvalidInputError(f"a {name} message is a JSON object, got {type(value).__name__}.")
    key = codec.table_key
    header = {k: v for k, v in value.items() if k != key}
    if key is None:
        return DecodedTable(header, None)
    rows = value.get(key)
    if not isinstance(rows, list):
        raise InvalidInputError(f"a {name} message needs its list {key!r}.")
    return DecodedTable(header, codec.rows_from_dicts(rows, optional=_optional_row_fields(name)))


def decode_table(schema: Schema | None, message_encoding: str, data: bytes | memoryview) -> DecodedTable:
    """One star-table message of either encoding as its header and rows.

    Raises :class:`InvalidInputError` when the channel is not a star table or the message does not decode.
    """
    name = schema.name if schema is not None else ""
    if name not in STAR_TABLES:
        raise InvalidInputError(f"schema {name!r} is not a star table; they are {', '.join(STAR_TABLES)}.")
    if message_encoding == "json":
        return json_table(name, decode_json(data))
    codec = schema_codec(schema) if message_encoding == "protobuf" else None
    if codec is None:
        raise InvalidInputError(f"a {name} channel in {message_encoding!r} with a {schema.encoding!r} schema is "
                                "not one starlog reads as a table.")
    return codec.decode(data)
