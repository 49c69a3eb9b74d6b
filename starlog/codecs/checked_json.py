"""JSON messages checked against their schema where they are encoded, e.g. in a worker process.

:class:`~starlog.io.writer.LogWriter` checks every JSON message against its channel's JSON
Schema before writing it. A stage that encodes its messages in worker processes can have that
check done there, in parallel: :func:`encode_checked_json` encodes a message, runs the same
compiled check on the bytes and returns them as :class:`CheckedJson`, which names the schema
text it was checked against (by its SHA-256). ``LogWriter.write`` then does not check again a
message checked against its channel's own schema; any other message it checks itself.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable
from typing import Any

from starlog.errors import InvalidInputError
from starlog.codecs.json_schema import compile_json_schema
from starlog.codecs.json_messages import decode_json, encode_json
from starlog.codecs.schemas import MessageType

__all__ = ["CheckedJson", "encode_checked_json", "schema_checker", "schema_digest"]

_CHECKERS: dict[bytes, Callable[[Any], str | None]] = {}
_DIGESTS: dict[bytes, bytes] = {}


def schema_checker(schema_data: bytes) -> Callable[[Any], str | None]:
    """The compiled checker (:func:`~starlog.codecs.json_schema.compile_json_schema`) of a JSON Schema text,
    compiled once per process."""
    checker = _CHECKERS.get(schema_data)
    if checker is None:
        checker = _CHECKERS[schema_data] = compile_json_schema(json.loads(schema_data))
    return checker


def schema_digest(schema_data: bytes) -> bytes:
    """SHA-256 of a schema text: how a :class:`CheckedJson` names the schema it satisfies."""
    digest = _DIGESTS.get(schema_data)
    if digest is None:
        digest = _DIGESTS[schema_data] = hashlib.sha256(schema_data).digest()
    return digest


class CheckedJson(bytes):
    """The bytes of a JSON message that satisfies the JSON Schema whose SHA-256 is ``schema_digest``."""

    schema_digest: bytes

    def __new__(cls, data: bytes, schema_digest: bytes) -> CheckedJson:
        message = super().__new__(cls, data)
        message.schema_digest = schema_digest
        return message

    def __reduce__(self) -> tuple[type[CheckedJson], tuple[bytes, bytes]]:
        return CheckedJson, (bytes(self), self.schema_digest)


def encode_checked_json(value: Any, message_type: MessageType) -> CheckedJson:
    """:func:`~starlog.codecs.json_messages.encode_json` of ``value``, checked against ``message_type``'s JSON Schema
    as :class:`~starlog.io.writer.LogWriter` checks what it writes (the decoded bytes, not ``value``).

    Raises :class:`InvalidInputError` when the message does not match the schema (or cannot be encoded).
    """
    data = encode_json(value)
    problem = schema_checker(message_type.schema_data)(decode_json(data))
    if problem:
        raise InvalidInputError(f"a {message_type.schema_name} message does not match its schema ({problem}).")
    return CheckedJson(data, schema_digest(message_type.schema_data))
