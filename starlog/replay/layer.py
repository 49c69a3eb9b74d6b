"""What every replay stage shares: open the input, write a layer on it, record provenance."""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from starlog.version import __version__
from starlog.errors import OutputExistsError, file_errors
from starlog.io import LogReader, LogWriter, Provenance
from starlog.io.provenance import PROVENANCE_METADATA_NAME
from starlog.io.reader import LogSource
from starlog.codecs.schemas import MessageType
from starlog.io.copying import flatten_log
from starlog.io.output_files import temporary_folder

__all__ = ["StageOutput", "extend_log", "layer_path_for", "record_provenance"]


@dataclass
class StageOutput:
    """The writer of a stage's output, and the channels the stage has added to it."""

    writer: LogWriter
    channels: list[str] = field(default_factory=list)
    results: dict[str, Any] = field(default_factory=dict)
    """What the stage found that its provenance records beside its parameters (key ``results``)."""

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
    input_path: LogSource | LogReader,
    output_path: str | os.PathLike[str],
    *,
    stage: str,
    parameters: dict[str, Any],
    force: bool = False,
    compression: str = "zstd",
    flatten: bool = False,
) -> Iterator[tuple[LogReader, StageOutput]]:
    """Open ``input_path`` for reading (or take the reader a stage has already opened, which stays open) and a
    layer on it at ``output_path`` (:mod:`starlog.io.chain`).

    The stage adds its channels; on success its provenance (name, version, parameters with the
    stage's ``results`` when it gave any, the input file's SHA-256, hashed on a thread while the
    stage works, and the channels it added) is
    recorded, the layer names its base, and it is renamed into place. On any error the output is
    discarded and the input is untouched; an OS error only a write meets (a full disk, say, in a stage's
    scratch files beside the output) names the output. A :class:`~starlog.io.reader.LogView` input (``--start`` /
    ``--end``) adds its range to the parameters. With ``flatten``, the output is the flattened
    chain instead: one self-contained file. ``parameters`` is read when the stage ends, so a stage may add
    what it learns while it runs (the centroid stage's count of full-frame searches).

    The layer's chunks are compressed on the calling thread: what a stage derives is small beside the
    images it reads, and compression threads would hold several chunks of it in memory at once.
    """
    with file_errors(output_path, only_writes=True), \
            layer_path_for(Path(output_path), flatten=flatten, force=force) as layer_path, \
            (nullcontext(input_path) if isinstance(input_path, LogReader) else LogReader(input_path)) as reader:
        window = {"range": reader.window.to_dict()} if reader.window is not None else {}
        base = reader.layer_base()
        with LogWriter(layer_path, layer=base, force=force or flatten, compression=compression) as writer:
            out = StageOutput(writer)
            yield reader, out
            record_provenance(out, stage, {**parameters, **window}, base.digest())


def record_provenance(out: StageOutput, stage: str, parameters: dict[str, Any], input_digest: str) -> None:
    """Write the stage's provenance record into its layer: its name, version, ``parameters`` with the stage's
    ``results`` when it gave any, the SHA-256 of its input and the channels it added."""
    recorded = {**parameters, **({"results": dict(out.results)} if out.results else {})}
    record = Provenance(stage=stage, version=__version__, parameters=recorded, input_digest=input_digest,
                        channels=out.channels)
    out.writer.add_metadata(PROVENANCE_METADATA_NAME, record.to_metadata())


@contextmanager
def layer_path_for(output: Path, *, flatten: bool, force: bool) -> Iterator[Path]:
    """Where to write a layer meant for ``output``: ``output`` itself, or (``flatten``) a file in a hidden
    folder beside it, whose chain is flattened into ``output`` once the block succeeds; the folder is
    removed whatever happens."""
    if not flatten:
        yield output
        return
    if output.exists() and not force:
        raise OutputExistsError(output)
    with temporary_folder(output) as folder:
        layer = folder / output.name
        yield layer
        flatten_log(layer, output, force=True)
