"""The MCAP log layer: reading, writing and appending starlog logs.

A starlog log is one MCAP file. Images use the Foxglove well-known protobuf schemas
(``foxglove.RawImage``, ``foxglove.ImageAnnotations``); starlog's own messages are JSON with
JSON Schemas from ``schemas/``. A stage never modifies its input: it writes a new file that
starts with a byte-for-byte copy of the input's data section (so images are not
re-compressed), followed by the stage's new chunks and a merged summary (see
:class:`LogWriter`). The output appears only once complete (temp file + rename). Stages run
one after another (``starlog run``) write only their new records instead, read together with
their input as one :class:`StackedLog`, and the output is written once.
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
from starlog.io.reader import ChannelSummary, LogReader
from starlog.io.schemas import MessageType, json_message_type, load_json_schema, protobuf_message_type
from starlog.io.stack import StackedLog
from starlog.io.writer import Compression, LogWriter

__all__ = [
    "PROVENANCE_METADATA_NAME",
    "ChannelSummary",
    "Compression",
    "LogReader",
    "LogWriter",
    "MessageType",
    "Provenance",
    "StackedLog",
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
