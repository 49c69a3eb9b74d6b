"""The MCAP log layer: reading and writing starlog logs, one file or a chain of layers.

A starlog log is an MCAP file, or a chain of them: a stage never modifies its input, it writes
a *layer* — a complete MCAP file holding only the channels, metadata and provenance it adds,
and a record naming the log it extends (:mod:`starlog.io.chain`). :class:`LogReader` reads a
chain as one log; ``starlog flatten`` writes it as one file (:mod:`starlog.io.copying`). Images
use the Foxglove well-known protobuf schemas (``foxglove.RawImage``,
``foxglove.ImageAnnotations``); starlog's star tables are protobuf too, from ``schemas/starlog/``
(:mod:`starlog.io.star_tables`; JSON in logs of earlier versions), and its other messages JSON with
JSON Schemas from ``schemas/``. Every output appears only once complete (temp file + rename).
"""

from __future__ import annotations

from starlog.io.messages import (
    decode_json,
    decode_raw_image,
    encode_image_annotations,
    encode_json,
    encode_raw_image,
)
from starlog.io.provenance import PROVENANCE_METADATA_NAME, Provenance, file_digest
from starlog.io.reader import ChannelSummary, LogReader, LogSource, LogView
from starlog.io.schemas import MessageType, json_message_type, load_json_schema, protobuf_message_type
from starlog.io.writer import Compression, LogWriter

__all__ = [
    "PROVENANCE_METADATA_NAME",
    "ChannelSummary",
    "Compression",
    "LogReader",
    "LogSource",
    "LogView",
    "LogWriter",
    "MessageType",
    "Provenance",
    "decode_json",
    "decode_raw_image",
    "encode_image_annotations",
    "encode_json",
    "encode_raw_image",
    "file_digest",
    "json_message_type",
    "load_json_schema",
    "protobuf_message_type",
]
