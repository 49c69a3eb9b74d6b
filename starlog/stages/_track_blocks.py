"""The ``track`` stage's work on blocks of frames that worker processes can take: centroid messages
decoded into arrays, and track rows encoded into messages.

The tracker itself runs frame after frame in one process; these steps around it do not depend
on each other's frames. The module imports only the log layer, so a worker process that is
sent one of these tasks starts without importing the tracker (scipy).
"""

from __future__ import annotations

import operator
import pickle
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from starlog.io.reader import DecodedMessage, LogReader
from starlog.io.records import record_encoder
from starlog.stages._blocks import LogSource, worker_log
from starlog.stages._spool import Spool, read_block

__all__ = ["CentroidArrays", "centroid_blocks", "centroid_range", "decode_centroid_range", "encode_track_block",
           "encode_track_block_to", "read_encoded"]

#: ``(frame numbers, log times, stars per frame, (stars, 4) x/y/sigma/flux)`` of consecutive frames.
CentroidArrays = tuple[npt.NDArray[np.int64], npt.NDArray[np.int64], npt.NDArray[np.int64], npt.NDArray[np.float64]]

_STAR_FIELDS = operator.itemgetter("x", "y", "sigma", "flux")


class _CentroidBlock:
    """Centroid messages gathered into arrays, each message's star dicts dropped once converted."""

    def __init__(self) -> None:
        self.frames: list[int] = []
        self.times: list[int] = []
        self.counts: list[int] = []
        self.values: list[tuple[float, float, float, float]] = []

    def add(self, log_time: int, payload: dict[str, Any]) -> None:
        stars = payload["stars"]
        self.frames.append(payload["frame"])
        self.times.append(log_time)
        self.counts.append(len(stars))
        self.values.extend(map(_STAR_FIELDS, stars))

    def arrays(self) -> CentroidArrays:
        table = np.array(self.values, dtype=np.float64).reshape(len(self.values), 4)
        return (np.array(self.frames, dtype=np.int64), np.array(self.times, dtype=np.int64),
                np.array(self.counts, dtype=np.int64), table)


def centroid_blocks(messages: Iterable[DecodedMessage], frames_per_block: int) -> Iterator[CentroidArrays]:
    """``starlog.Centroids`` messages → blocks of at most ``frames_per_block`` frames, in order."""
    block = _CentroidBlock()
    for message in messages:
        block.add(message.log_time, message.payload)
        if len(block.frames) == frames_per_block:
            yield block.arrays()
            block = _CentroidBlock()
    if block.frames:
        yield block.arrays()


def centroid_range(log: LogReader, topic: str, start: int, end: int) -> CentroidArrays:
    """The messages of ``topic`` with ``start <= log_time < end`` as one block."""
    messages = log.messages(topic, start=start, end=end)
    return next(centroid_blocks(messages, frames_per_block=2**62), _CentroidBlock().arrays())


def decode_centroid_range(source: LogSource, topic: str, start: int, end: int) -> CentroidArrays:
    """Worker: :func:`centroid_range`, the log read by this process."""
    return centroid_range(worker_log(source), topic, start, end)


def encode_track_block(spool: Spool, offset: int, method: str, model: str,
                       brightest: int) -> tuple[list[int], list[bytes]]:
    """One spooled block of track rows → ``(log_time, starlog.Tracks message)`` of each frame.

    The block's rows are encoded, and checked against their schema, column by column
    (:class:`~starlog.io.records.RecordEncoder`; in a worker process when there is a pool), not by the writer.
    """
    frames, times, counts, rows = read_block(spool, offset, 4)
    encoder = record_encoder("starlog.Tracks", "tracks")
    records = encoder.rows(rows, {"brightest": rows["track"] == brightest})
    ends = np.cumsum(counts).tolist()
    messages: list[bytes] = [
        encoder.message({"frame": frame, "method": method, "model": model}, records[a:b])
        for frame, a, b in zip(frames.tolist(), [0, *ends[:-1]], ends, strict=True)
    ]
    return times.tolist(), messages


def encode_track_block_to(path: Path, spool: Spool, offset: int, method: str, model: str, brightest: int) -> None:
    """Worker: :func:`encode_track_block` saved to ``path`` (read back by :func:`read_encoded`)."""
    encoded = encode_track_block(spool, offset, method, model, brightest)
    with open(path, "wb") as file:
        pickle.dump(encoded, file, protocol=pickle.HIGHEST_PROTOCOL)


def read_encoded(path: Path) -> tuple[list[int], list[bytes]]:
    """What :func:`encode_track_block_to` saved to ``path`` (a file of this stage's own temporary folder)."""
    with open(path, "rb") as file:
        encoded: tuple[list[int], list[bytes]] = pickle.load(file)  # noqa: S301 - written by this stage
    return encoded
