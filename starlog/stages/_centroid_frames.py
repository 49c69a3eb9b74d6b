"""The centroid stage's per-frame work: detect, centroid and encode one frame, and every frame of a log in order.

:class:`FrameExtractor` does one frame's whole work and is picklable, so worker processes run it
on blocks of frames they read themselves (no image crosses a process boundary);
:func:`extract_parallel` gives their results in frame order, so the output does not depend on
the number of workers.
"""

from __future__ import annotations

import ctypes
import ctypes.util
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from starlog.centroid import CentroidFlag, CentroidMethod, extract_stars
from starlog.centroid.epsf import EPSF
from starlog.centroid.evidence import FrameEvidence, frame_evidence
from starlog.centroid.phase import PhaseCalibration
from starlog.io import encode_image_annotations
from starlog.io.frames import SkippedFrame
from starlog.io.reader import LogReader, LogSource
from starlog.io.records import record_encoder
from starlog.stages._blocks import worker_log
from starlog.stages._parallel import ordered_map, process_pool

__all__ = ["FrameExtractor", "FrameMessages", "extract_parallel", "extract_serial", "opencv_threads",
           "reuse_frame_buffers"]


@dataclass(frozen=True)
class FrameMessages:
    """One frame's encoded messages (detections, annotations, centroids per method) and counts
    (``n_artefacts``: detections flagged ``ARTEFACT``, in the detections only)."""

    log_time: int
    detections: bytes
    annotations: bytes
    centroids: tuple[bytes, ...]
    n_detections: int
    n_centroids: tuple[int, ...]
    n_failed: tuple[int, ...]
    n_artefacts: int = 0
    evidence: FrameEvidence | None = None
    """Each method's differences to the other methods' median (:mod:`starlog.centroid.evidence`)."""


@dataclass(frozen=True)
class FrameExtractor:
    """Detect, centroid and encode one frame; picklable, so worker processes do the whole per-frame work
    (the JSON messages are checked against their schemas there too, not by the writer in the main process)."""

    methods: tuple[CentroidMethod, ...]
    gain: float
    read_noise: float | None
    options: dict[str, Any]
    epsf: EPSF | None = None
    hot_pixels: npt.NDArray[np.bool_] | None = None
    phase: dict[str, PhaseCalibration] | None = None

    def centroids(self, image: npt.NDArray[Any]) -> tuple[npt.NDArray[Any], dict[CentroidMethod, npt.NDArray[Any]]]:
        """Detections and centroids per method of one frame, before any phase correction."""
        return extract_stars(image, methods=self.methods, gain=self.gain, read_noise=self.read_noise, epsf=self.epsf,
                             hot_pixels=self.hot_pixels, **self.options)

    def __call__(self, frame: int, log_time: int, image: npt.NDArray[Any], stamp: int | None = None
                 ) -> FrameMessages:
        """``stamp``: the image message's own time, given to the annotations so Foxglove pairs them with it."""
        detections, centroids = self.centroids(image)
        for m, calibration in (self.phase or {}).items():
            table = centroids[CentroidMethod(m)]
            table["x"], table["y"] = calibration.apply(table["x"], table["y"])
        first = centroids[self.methods[0]]
        diameter = float(max(6.0, 6.0 * np.median(first["psf_sigma"]))) if first.size else 6.0
        per_method = [centroids[m] for m in self.methods]
        return FrameMessages(
            log_time=log_time,
            detections=record_encoder("starlog.Detections", "stars").encode({"frame": frame}, detections),
            annotations=encode_image_annotations(first["x"], first["y"], log_time=log_time if stamp is None else stamp,
                                                 diameter=diameter),
            centroids=tuple(record_encoder("starlog.Centroids", "stars").encode({"frame": frame, "method": m.value}, c)
                            for m, c in zip(self.methods, per_method)),
            n_detections=int(detections.size),
            n_centroids=tuple(int(c.size) for c in per_method),
            n_failed=tuple(int(np.count_nonzero(c["flags"] & CentroidFlag.FIT_FAILED)) for c in per_method),
            n_artefacts=int(np.count_nonzero(detections["flags"] & CentroidFlag.ARTEFACT)),
            evidence=frame_evidence(per_method),
        )


_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3


def reuse_frame_buffers() -> None:
    """Let the C allocator (glibc) recycle the frame-sized arrays each frame allocates and frees.

    By default every block above ~128 KiB is mapped from the system on allocation and returned
    on release, so each frame's images (decoded frame, float copy, filtered image, maps, masks)
    arrive as fresh zero pages: thousands of page faults a frame, a third of detection's time
    at 1024x1024. Blocks below 64 MiB now come from the heap and stay there for the next
    frame (the working set, hence the peak memory, does not grow with the log). Elsewhere than
    glibc nothing changes. The setting is process-wide and kept.
    """
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return
    mallopt(_M_MMAP_THRESHOLD, 64 << 20)
    mallopt(_M_TRIM_THRESHOLD, 256 << 20)


@contextmanager
def opencv_threads(count: int) -> Iterator[None]:
    """OpenCV's own thread pool limited to ``count`` while the block runs.

    Each process does its frames on one core (``workers`` sets the number of cores): OpenCV's
    threads would only add overhead there, or compete with the other workers.
    """
    before = cv2.getNumThreads()
    cv2.setNumThreads(count)
    try:
        yield
    finally:
        cv2.setNumThreads(before)


def extract_serial(log: LogReader, topic: str, extract: FrameExtractor, skip_bad: bool, *,
                   start: int | None = None, end: int | None = None, first_index: int = 0,
                   ) -> Iterator[FrameMessages | SkippedFrame]:
    """Every frame's messages in order; with ``skip_bad``, a bad frame comes out as a :class:`SkippedFrame`."""
    skipped: list[SkippedFrame] = []
    frames = log.frame_records(topic, start=start, end=end, first_index=first_index,
                               on_bad=skipped.append if skip_bad else None)
    for frame in frames:
        yield from skipped
        skipped.clear()
        yield extract(frame.index, frame.log_time, frame.image, frame.stamp)
    yield from skipped


def _extract_block(source: LogSource, topic: str, start: int, end: int, first_index: int, extract: FrameExtractor,
                   skip_bad: bool) -> list[FrameMessages | SkippedFrame]:
    """Worker: every frame with ``start <= log_time < end`` (reads the log itself; no image crosses processes)."""
    reuse_frame_buffers()
    with opencv_threads(1):
        log = worker_log(source)
        return list(extract_serial(log, topic, extract, skip_bad, start=start, end=end, first_index=first_index))


def extract_parallel(log: LogReader, source: LogSource, topic: str, blocks: list[tuple[int, int, int]],
                     extract: FrameExtractor, workers: int, skip_bad: bool) -> Iterator[FrameMessages | SkippedFrame]:
    """The frames of ``blocks`` (:func:`~starlog.stages._blocks.channel_blocks`) extracted by worker processes,
    and by this process until they are up."""
    items = ((source, topic, start, end, first, extract, skip_bad) for start, end, first in blocks)

    def in_this_process(_: LogSource, topic: str, start: int, end: int, first: int, extract: FrameExtractor,
                        skip_bad: bool) -> list[FrameMessages | SkippedFrame]:
        return list(extract_serial(log, topic, extract, skip_bad, start=start, end=end, first_index=first))

    with process_pool(workers, preload=["starlog.stages.centroid"]) as pool:
        for done in ordered_map(pool, _extract_block, items, window=2 * workers, until_ready=in_this_process):
            yield from done
