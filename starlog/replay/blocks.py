"""A channel cut into blocks of whole chunks, for worker processes that each read their blocks themselves.

A block is a time range ``start <= log_time < end`` covering whole chunks of the channel, so a
worker decompresses each chunk it needs once, and no message crosses processes on its way in.
"""

from __future__ import annotations

import os
from pathlib import Path

from starlog.io.reader import LogReader, LogSource, LogView, source_path

__all__ = ["channel_blocks", "source_of", "worker_log"]


def channel_blocks(log: LogReader, topic: str, frames_per_block: int, *, at_most: bool = False
                   ) -> list[tuple[int, int, int]] | None:
    """Split ``topic`` into ``(start, end, first_message)`` time ranges of whole chunks (~``frames_per_block``
    messages each; with ``at_most``, no more than that unless one chunk holds more), in time order; None when
    its chunks overlap in time (not written in time order), which no split into time ranges of whole chunks
    can serve."""
    chunks = log.chunk_message_counts(topic)
    for (_, end, _), (nxt, _, _) in zip(chunks, chunks[1:]):
        if nxt <= end:
            return None
    blocks: list[tuple[int, int, int]] = []
    start, first, count = chunks[0][0] if chunks else 0, 0, 0
    for i, (chunk_start, end, n) in enumerate(chunks):
        if at_most and count and count + n > frames_per_block:
            blocks.append((start, chunk_start, first))
            start, first, count = chunk_start, first + count, 0
        count += n
        if count >= frames_per_block or i == len(chunks) - 1:
            blocks.append((start, end + 1, first))
            start, first, count = end + 1, first + count, 0
    return blocks


_WORKER_LOG: dict[tuple[object, ...], LogReader] = {}


def _identity(source: LogSource) -> tuple[object, ...]:
    """The file ``source`` names (path, device, inode, size, modification time) and its window: a chain's
    other files are checked against it when it is opened."""
    path = source_path(source)
    info = os.stat(path)
    window = source.window if isinstance(source, LogView) else None
    return os.path.abspath(path), info.st_dev, info.st_ino, info.st_size, info.st_mtime_ns, window


def source_of(log: LogReader) -> LogSource:
    """What ``log`` reads (its newest file, seen through its window if any): what a worker opens to read its
    blocks itself."""
    return LogView(Path(log.path), log.window) if log.window is not None else log.path


def worker_log(source: LogSource) -> LogReader:
    """The log a worker process reads its blocks from, opened once per process and log.

    Opening reads the log's summary, whose size grows with the log (one index per chunk): opened for
    every block, a worker's time per frame grew with the log's length. The file is closed when the
    worker moves to another log, or ends.
    """
    key = _identity(source)
    log = _WORKER_LOG.get(key)
    if log is None:
        for old in _WORKER_LOG.values():
            old.close()
        _WORKER_LOG.clear()
        log = _WORKER_LOG[key] = LogReader(source)
    return log
