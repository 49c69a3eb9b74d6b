"""Logs as earlier starlog versions wrote them: the star tables as JSON.

:func:`write_json_log` copies a log (a whole chain into one file, or one layer alone onto a base of
either kind), every star table rewritten as JSON with the JSON writer starlog kept for them
(:func:`~starlog.codecs.json_rows.record_encoder` for detections, centroids and tracks, as the stages
encoded them; :func:`~starlog.codecs.json_messages.encode_json` for the others); every other channel and
every metadata record is copied as it is. Used by the tests of old logs and by ``tools/bench_io.py``
(the size of a layer written both ways).
"""

from __future__ import annotations

from pathlib import Path

from mcap.records import Schema

from starlog.io import LogReader, LogWriter
from starlog.codecs import MessageType, encode_json, json_message_type
from starlog.codecs.json_rows import record_encoder
from starlog.codecs.star_tables import STAR_TABLES, decode_table, star_codec

#: The star tables the stages encoded column by column (the others were written from dicts).
_RECORDS = {"starlog.Detections", "starlog.Centroids", "starlog.Tracks"}


def _as_json(name: str, schema: Schema, encoding: str, data: bytes) -> bytes:
    header, rows = decode_table(schema, encoding, data)
    if name in _RECORDS:
        return bytes(record_encoder(name, star_codec(name).table_key).encode(header, rows))
    return encode_json(star_codec(name).as_dict(header, rows) if rows is not None else header)


def write_json_log(source: Path, output: Path, *, base: Path | None = None, compression: str = "zstd") -> Path:
    """``source`` with its star tables as JSON: with ``base``, ``source`` read alone (one layer) and written
    as a layer on ``base``; without, the whole chain of ``source`` written as one file. ``compression`` as the
    stages' (zstd by default)."""
    layer_base = None
    if base is not None:
        with LogReader(base) as below:
            layer_base = below.layer_base()
    with LogReader(source, chain=base is None) as log, \
            LogWriter(output, layer=layer_base, compression=compression, force=True) as out:
        channels = {}
        for schema, channel, message in log.raw_messages(log.topics):
            name = schema.name if schema is not None else ""
            if channel.id not in channels:
                kind = (json_message_type(name) if name in STAR_TABLES else
                        MessageType(name, schema.encoding if schema else "", schema.data if schema else b"",
                                    channel.message_encoding))
                channels[channel.id] = out.add_channel(channel.topic, kind)
            data = (_as_json(name, schema, channel.message_encoding, message.data)
                    if name in STAR_TABLES and channel.message_encoding != "json" else bytes(message.data))
            out.write(channels[channel.id], log_time=message.log_time, data=data)
        for name, record in log.metadata():
            out.add_metadata(name, record)
    return output
