"""A log opened from Python (:func:`starlog.open`): its facts, its tables, its frames and its messages.

A :class:`Log` reads one MCAP file or a chain of layers as one log, as every command does. Its
tables are the ones ``starlog export`` writes (same columns, same types), built in memory as
``pyarrow.Table``; a time range reads only the chunks that hold it. Time bounds are written as on
the command line: log time in ns (``1234567``), seconds on the same clock (``"12.5s"``) or
``"frame:N"`` (the N-th message, 0-based, of the channel read).
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

from starlog.io.copying import frame_time_lookup
from starlog.io.reader import ChannelSummary, DecodedMessage, LogReader
from starlog.io.timerange import TimeRange

if TYPE_CHECKING:
    import numpy as np
    import pyarrow as pa

    from starlog.io.provenance import Provenance

__all__ = ["Log", "TimeBound"]

#: A time bound: log time in ns, ``"12.5s"`` (seconds on the log's clock) or ``"frame:N"``.
TimeBound = int | str | None


class Log:
    """An open starlog log. Use it as a context manager, or call :meth:`close`.

    Example::

        with starlog.open("run.mcap") as log:
            print(log.topics)
            centroids = log.table("centroids", start="1s", end="2s").to_pandas()
            for log_time, image in log.frames(end="frame:10"):
                ...
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self._reader = LogReader(self.path)

    # ------------------------------------------------------------------ facts
    @property
    def reader(self) -> LogReader:
        """The :class:`~starlog.io.reader.LogReader` underneath (raw messages, metadata, chunk counts)."""
        return self._reader

    @property
    def files(self) -> list[Path]:
        """The files of the chain, the base first, then each layer."""
        return [Path(f.path) for f in self._reader.files]

    @property
    def topics(self) -> list[str]:
        """The topics of every channel, in the order ``starlog info`` lists them."""
        return list(dict.fromkeys(c.topic for c in self._reader.channels()))

    @property
    def channels(self) -> list[ChannelSummary]:
        """Every channel: topic, schema, encoding, message count and time range."""
        return self._reader.channels()

    @property
    def time_range(self) -> tuple[int, int]:
        """``(first, last)`` log time of the log's messages, in ns."""
        return self._reader.time_range()

    @property
    def provenance(self) -> list[Provenance]:
        """What wrote each file: stage, version, parameters and inputs, oldest first."""
        return self._reader.provenance()

    def describe(self) -> dict[str, Any]:
        """Everything ``starlog info --json`` prints about the log (reads its summaries and metadata only)."""
        from starlog.io.info import describe_log

        return describe_log(self.path)

    # ------------------------------------------------------------------ tables
    def table_names(self) -> list[str]:
        """The tables of ``starlog export`` this log has channels for (``frames``, ``centroids``, ...)."""
        from starlog.parquet import TABLES
        from starlog.parquet.tables import table_of_channel

        found = {table_of_channel(c) for c in self._reader.channels()}
        return [t.name for t in TABLES if t.name in found]

    def table(self, name: str, *, start: TimeBound = None, end: TimeBound = None) -> pa.Table:
        """A table as ``starlog export`` writes it, as a ``pyarrow.Table`` (``.to_pandas()`` for pandas).

        ``name`` is a table of the export (``"centroids"``: every centroid channel, with a ``method``
        column), one channel of such a table (``"/stars/centroids/GAUSSFIT"``: its rows alone), or any
        other topic (a flat table, one row per message, as ``starlog export --topic`` writes it).
        ``start`` / ``end`` bound the log time (``end`` exclusive); ``frame:N`` counts the messages of
        the channel read (of the table's first channel). Only the chunks holding the range are read.
        """
        from starlog.parquet import TABLES
        from starlog.parquet.channels import topic_table
        from starlog.parquet.tables import family_table, table_of_channel

        if name in {t.name for t in TABLES}:
            feeding = [c.topic for c in self._reader.channels() if table_of_channel(c) == name]
            lo, hi = self._bounds(start, end, feeding[0] if feeding else None)
            return family_table(self._reader, name, start=lo, end=hi)
        channel = self._reader.channel(name)
        lo, hi = self._bounds(start, end, name)
        family = table_of_channel(channel)
        if family is not None:
            return family_table(self._reader, family, topics=[name], start=lo, end=hi)
        return topic_table(self._reader, name, start=lo, end=hi)

    # ------------------------------------------------------------------ streams
    def frames(self, topic: str | None = None, *, start: TimeBound = None, end: TimeBound = None
               ) -> Iterator[tuple[int, np.ndarray]]:
        """``(log_time, image)`` of every frame of the image channel ``topic`` (default: ``/camera/image``, else
        the log's only image channel) in ``[start, end)``, decoded to a 2-D mono array, streamed."""
        from starlog.io.images import choose_image_topic

        topic, _ = choose_image_topic(self.path, self._reader.channels(), topic)
        lo, hi = self._bounds(start, end, topic)
        for _, log_time, image in self._reader.frames(topic, start=lo, end=hi):
            yield log_time, image

    def messages(self, topic: str, *, start: TimeBound = None, end: TimeBound = None
                 ) -> Iterator[DecodedMessage]:
        """The decoded messages of ``topic`` in ``[start, end)``: each with ``log_time`` and its ``payload``
        (a dict; star tables as the dict of their JSON form), streamed."""
        lo, hi = self._bounds(start, end, topic)
        return self._reader.messages(topic, start=lo, end=hi)

    def _bounds(self, start: TimeBound, end: TimeBound, topic: str | None) -> tuple[int | None, int | None]:
        """``start`` / ``end`` in ns (None: open); ``frame:N`` counts the messages of ``topic``."""
        time_range = TimeRange.parse(start, end)
        if time_range is None:
            return None, None
        frame_time = frame_time_lookup(self._reader, topic) if topic and time_range.counts_frames else None
        resolved = time_range.resolve(frame_time, frame_topic=topic)
        return resolved.start_ns, resolved.end_ns

    # ------------------------------------------------------------------ life cycle
    def close(self) -> None:
        """Close the log's files."""
        self._reader.close()

    def __enter__(self) -> Log:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        first, last = self.time_range
        return (f"Log({str(self.path)!r}: {len(self.files)} file(s), {len(self.topics)} topics, "
                f"{(last - first) * 1e-9:.3f} s)")
