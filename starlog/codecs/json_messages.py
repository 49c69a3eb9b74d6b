"""starlog's JSON messages: compact UTF-8 JSON, NaN and infinities refused both ways."""

from __future__ import annotations

import json
from typing import Any

import numpy as np
import orjson

from starlog.errors import InvalidInputError

__all__ = ["decode_json", "encode_json"]


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


#: Non-string keys become strings (as the standard library does); numpy values go through ``_json_default``
#: so a float32 is written as the same Python float as before.
_ORJSON_OPTIONS = orjson.OPT_NON_STR_KEYS


def encode_json(obj: Any) -> bytes:
    """Encode a message as compact UTF-8 JSON; NaN and infinities are refused (Foxglove cannot read them).

    orjson writes NaN and infinities as ``null``; so when ``null`` appears in the output, the
    object is encoded again by the standard library, which names the offending value.
    """
    try:
        data = orjson.dumps(obj, default=_json_default, option=_ORJSON_OPTIONS)
    except (orjson.JSONEncodeError, TypeError) as err:
        raise InvalidInputError(f"message cannot be encoded as JSON: {err}") from err
    if b"null" in data:
        try:
            json.dumps(obj, allow_nan=False, default=_json_default)
        except ValueError as err:
            raise InvalidInputError(
                f"message contains a NaN or infinite number and cannot be logged: {err}") from err
    return data


def decode_json(data: bytes | memoryview) -> Any:
    """Decode a UTF-8 JSON message; ``NaN`` and ``Infinity`` are not JSON and are refused.

    Raises
    ------
    InvalidInputError
        The bytes are not UTF-8 JSON, or hold ``NaN`` / ``Infinity``.
    """
    try:
        return orjson.loads(data)
    except orjson.JSONDecodeError as err:  # a ValueError: bad UTF-8, NaN/Infinity, syntax, absurd nesting
        note = ""
        if any(word in bytes(data) for word in (b"NaN", b"Infinity")):
            note = " (NaN and Infinity are not JSON; starlog never writes them)"
        raise InvalidInputError(f"not valid UTF-8 JSON: {err}{note}") from err
