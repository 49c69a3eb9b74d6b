"""What every replay stage shares: open the input, write a new log that extends it, record provenance."""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

from starlog import __version__
from starlog.io import LogReader, LogWriter, Provenance
from starlog.io.digest_cache import write_digest_cache
from starlog.io.provenance import PROVENANCE_METADATA_NAME, BackgroundDigest
from starlog.io.schemas import MessageType
from starlog.io.stack import StackedLog
from starlog.stages._slice import slice_origin

__all__ = ["StageOutput", "extend_log"]


@dataclass
class StageOutput:
    """The writer of a stage's output, and the channels the stage has added to it."""

    writer: LogWriter
    channels: list[str] = field(default_factory=list)

    def add_channel(self, topic: str, message_type: MessageType, *, unordered: bool = False) -> int:
        """Register a new channel and record it for the provenance.

        A stage's channels hold one message per frame, so the writer checks that their
        ``log_time`` increases strictly (``LogWriter.add_channel(monotonic=True)``); a channel whose
        messages may share or revisit a time (e.g. one record per rate and protocol) says
        ``unordered=True``.
        """
        channel_id = self.writer.add_channel(topic, message_type, monotonic=not unordered)
        self.channels.append(topic)
        return channel_id


@contextmanager
def extend_log(
    input_path: str | os.PathLike[str] | StackedLog,
    output_path: str | os.PathLike[str],
    *,
    stage: str,
    parameters: dict[str, Any],
    force: bool = False,
    compression: str = "zstd",
    workers: int = 1,
) -> Iterator[tuple[LogReader, StageOutput]]:
    """Open ``input_path`` for reading and a new log at ``output_path`` that starts as its copy.

    The input's data section is copied byte for byte (no re-compression, by the kernel); the
    stage adds its channels; on success its provenance (name, version, parameters, the input's
    SHA-256, hashed on a thread while the stage works, and the channels it added) is recorded
    and the output renamed into place. On any error the output is discarded and the input is
    untouched. The output's own SHA-256 is saved with it for the next stage
    (:mod:`starlog.io.digest_cache`). With a :class:`StackedLog` as input, the
    output is a sidecar to stack on it: the same records, without the copy of the input's data.
    An input that is a time slice (``--start``/``--end``) adds its range to the parameters and
    hashes the log the slice was cut from.
    """
    origin = slice_origin(input_path)
    if origin is not None:
        parameters = {**parameters, "range": origin.time_range.to_dict()}
    with LogReader(input_path) as reader:
        digest = BackgroundDigest(input_path if origin is None else origin.source)
        try:
            with LogWriter(output_path, base=input_path, force=force, compression=compression,
                           workers=workers) as writer:
                out = StageOutput(writer)
                yield reader, out
                record = Provenance(stage=stage, version=__version__, parameters=parameters,
                                    input_digest=digest.result(), channels=out.channels)
                writer.add_metadata(PROVENANCE_METADATA_NAME, record.to_metadata())
            # the output starts with the input's data section (not so for a slice or a sidecar)
            prefix = digest.prefix() if origin is None and not isinstance(input_path, StackedLog) else None
        finally:
            digest.cancel()
    if prefix is not None:
        write_digest_cache(output_path, prefix=prefix)

