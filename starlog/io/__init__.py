"""The MCAP container: reading and writing starlog logs, one file or a chain of layers.

A starlog log is an MCAP file, or a chain of them: a stage never modifies its input, it writes
a *layer* — a complete MCAP file holding only the channels, metadata and provenance it adds,
and a record naming the log it extends (:mod:`starlog.io.chain`). :class:`LogReader` reads a
chain as one log; ``starlog flatten`` writes it as one file (:mod:`starlog.io.copying`). Every
output appears only once complete (temp file + rename). Each stage's provenance is a metadata
record of the container (:mod:`starlog.io.provenance`).

What the messages hold, and how they are encoded, is :mod:`starlog.codecs`' (star tables, images,
JSON messages and their schemas, other tools' messages): the reader hands each payload to its codec.
The channel names are :mod:`starlog.topics`'.
"""

from __future__ import annotations

from starlog.io.provenance import PROVENANCE_METADATA_NAME, Provenance, file_digest
from starlog.io.reader import ChannelSummary, LogReader, LogSource, LogView
from starlog.io.writer import Compression, LogWriter

__all__ = [
    "PROVENANCE_METADATA_NAME",
    "ChannelSummary",
    "Compression",
    "LogReader",
    "LogSource",
    "LogView",
    "LogWriter",
    "Provenance",
    "file_digest",
]
