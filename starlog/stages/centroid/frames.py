"""The centroid stage's per-frame work: detect, centroid and encode one frame, and every frame of a log in order.

:class:`FrameExtractor` does one frame's whole work and is picklable, so worker processes run it
on blocks of frames they read themselves (no image crosses a process boundary);
:func:`extract_parallel` gives their results in frame order, so the output does not depend on
the number of workers.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from starlog.centroiding import CentroidFlag, CentroidMethod, extract_stars
from starlog.centroiding.epsf import EPSF
from starlog.centroiding.evidence import FrameEvidence, frame_evidence
from starlog.centroiding.extract import measure_methods, window_half_size
from starlog.centroiding.hotpixels import without_hot_pixels
from starlog.centroiding.phase import PhaseCalibration
from starlog.centroiding.tracked_frame import WindowFit, track_frame
from starlog.centroiding.tracking import TrackingSettings, TrackState, finish_tracked, start_tracking
from starlog.codecs import encode_image_annotations
from starlog.io.frames import SkippedFrame
from starlog.io.reader import LogReader, LogSource
from starlog.codecs.star_tables import star_codec
from starlog.replay.blocks import source_of, worker_log
from starlog.replay.pool import ordered_map, process_pool

__all__ = ["FrameExtractor", "FrameMessages", "TrackedFrames", "annotation_diameter", "extract_blocks_serial",
           "extract_parallel", "extract_serial", "opencv_threads"]


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
    """Each method's differences to the other methods' median (:mod:`starlog.centroiding.evidence`)."""
    acquired: bool = True
    """Whether the whole frame was searched (always in full mode; in tracking mode, an acquisition)."""


@dataclass(frozen=True)
class FrameExtractor:
    """Detect, centroid and encode one frame; picklable, so worker processes do the whole per-frame work
    (the star tables are encoded, and their columns checked, there too, not by the writer in the main process)."""

    methods: tuple[CentroidMethod, ...]
    gain: float
    read_noise: float | None
    options: dict[str, Any]
    epsf: EPSF | None = None
    hot_pixels: npt.NDArray[np.bool_] | None = None
    phase: dict[str, PhaseCalibration] | None = None

    tracking: TrackingSettings | None = None
    """Tracking mode's settings (:mod:`starlog.centroiding.tracking`); None: every frame searched in full."""

    def centroids(self, image: npt.NDArray[Any]) -> tuple[npt.NDArray[Any], dict[CentroidMethod, npt.NDArray[Any]]]:
        """Detections and centroids per method of one frame, before any phase correction."""
        return extract_stars(image, methods=self.methods, gain=self.gain, read_noise=self.read_noise, epsf=self.epsf,
                             hot_pixels=self.hot_pixels, **self.options)

    def prepared(self, image: npt.NDArray[Any]) -> tuple[npt.NDArray[Any], float | None]:
        """The frame as :meth:`centroids` measures it (hot pixels missing) and its saturation level (None: the
        frame's type decides)."""
        raw = np.asarray(image)
        saturation = self.options.get("saturation")
        if self.hot_pixels is None:
            return raw, saturation
        if saturation is None:
            saturation = float(np.iinfo(raw.dtype).max) if raw.dtype.kind in "ui" else float("inf")
        return without_hot_pixels(raw, self.hot_pixels), saturation

    def measure(self, prepared: npt.NDArray[Any], saturation: float | None, detections: npt.NDArray[Any],
                methods: tuple[CentroidMethod, ...] | None = None) -> dict[CentroidMethod, npt.NDArray[Any]]:
        """Centroids per method (``methods``: these only) of given detections in a :meth:`prepared` frame (before
        any phase correction), measured as :meth:`centroids` measures its own detections."""
        return measure_methods(prepared, detections, self.methods if methods is None else methods, gain=self.gain,
                               read_noise=self.read_noise,
                               psf_sigma=self.options.get("psf_sigma"), window=self.options.get("window"),
                               saturation=saturation, **dict(self.options.get("centroid_options") or {}),
                               **({"epsf": self.epsf} if self.epsf is not None else {}))

    def block(self) -> FrameExtractor | TrackedFrames:
        """What extracts one block of consecutive frames: this extractor, or in tracking mode a
        :class:`TrackedFrames` that starts the block with a full search."""
        return self if self.tracking is None else TrackedFrames(self)

    def __call__(self, frame: int, log_time: int, image: npt.NDArray[Any], stamp: int | None = None
                 ) -> FrameMessages:
        """``stamp``: the image message's own time, given to the annotations so Foxglove pairs them with it."""
        return self.encode(frame, log_time, stamp, *self.centroids(image))

    def encode(self, frame: int, log_time: int, stamp: int | None, detections: npt.NDArray[Any],
               centroids: dict[CentroidMethod, npt.NDArray[Any]], acquired: bool = True) -> FrameMessages:
        """One frame's messages from its detections and centroids (phase-corrected here)."""
        for m, calibration in (self.phase or {}).items():
            table = centroids[CentroidMethod(m)]
            table["x"], table["y"] = calibration.apply(table["x"], table["y"])
        first = centroids[self.methods[0]]
        diameter = annotation_diameter(first)
        per_method = [centroids[m] for m in self.methods]
        return FrameMessages(
            log_time=log_time,
            detections=star_codec("starlog.Detections").encode({"frame": frame}, detections),
            annotations=encode_image_annotations(first["x"], first["y"], log_time=log_time if stamp is None else stamp,
                                                 diameter=diameter),
            centroids=tuple(star_codec("starlog.Centroids").encode({"frame": frame, "method": m.value}, c)
                            for m, c in zip(self.methods, per_method)),
            n_detections=int(detections.size),
            n_centroids=tuple(int(c.size) for c in per_method),
            n_failed=tuple(int(np.count_nonzero(c["flags"] & CentroidFlag.FIT_FAILED)) for c in per_method),
            n_artefacts=int(np.count_nonzero(detections["flags"] & CentroidFlag.ARTEFACT)),
            evidence=frame_evidence(per_method),
            acquired=acquired,
        )


def annotation_diameter(centroids: npt.NDArray[Any]) -> float:
    """The diameter (px) of the circles drawn at a frame's centroids: 6 PSF sigmas (their median), at least 6.

    The median is ``np.median``'s value (NaN included) without its overhead, a tenth of a frame's encoding
    at 50 stars.
    """
    if not centroids.size:
        return 6.0
    ordered = np.sort(centroids["psf_sigma"])
    half = ordered.size // 2
    median = float("nan") if np.isnan(ordered[-1]) else \
        float(ordered[half] if ordered.size % 2 else (ordered[half - 1] + ordered[half]) / 2)
    return float(max(6.0, 6.0 * median))


class TrackedFrames:
    """Tracking mode over one block of consecutive frames (:mod:`starlog.centroiding.tracking`).

    The block's first frame is searched in full (an acquisition), and so is every ``acquire_every``-th after
    it, a frame where a tracked star is not found or is lost, and one where light appeared outside the
    windows and was there in the frame before. A star lost in the frame right after an acquisition becomes *quiet* instead: still looked for
    and measured whenever found, but its loss calls for no search (the search just done did not make it
    measurable), so a star at the detection's threshold cannot force a search every frame.
    A tracked frame is compiled (:func:`~starlog.centroiding.tracked_frame.track_frame`): GAUSSFIT as the first
    method with the PSF width given is measured there; other methods, and a frame where a window needs the robust
    re-measurement, are measured by numpy from the located rows.
    Blocks never share state: the output does not depend on how blocks are spread over workers.
    """

    def __init__(self, extract: FrameExtractor) -> None:
        if extract.tracking is None:
            raise ValueError("TrackedFrames needs an extractor with tracking settings.")
        self.extract = extract
        self.settings: TrackingSettings = extract.tracking
        self.state: TrackState | None = None
        self.risen: npt.NDArray[np.bool_] | None = None
        """The cells where light appeared in the frame before (:func:`~starlog.centroiding.tracking.new_light`)."""
        psf = extract.options.get("psf_sigma")
        self.half_size = window_half_size(float(psf) if psf is not None else 1.0, extract.options.get("window"))
        self.fit = _window_fit(extract)
        """How the compiled frame measures the first method (None: numpy measures every tracked frame)."""

    def __call__(self, frame: int, log_time: int, image: npt.NDArray[Any], stamp: int | None = None
                 ) -> FrameMessages:
        detections, centroids, acquired = self.measure(image)
        return self.extract.encode(frame, log_time, stamp, detections, centroids, acquired)

    def measure(self, image: npt.NDArray[Any]) -> tuple[npt.NDArray[Any], dict[CentroidMethod, npt.NDArray[Any]],
                                                        bool]:
        """One frame's detections and centroids (before phase correction), and whether it was searched in full."""
        state = self.state
        if state is not None and state.since_acquisition + 1 < self.settings.acquire_every:
            tracked = self._tracked(image, state)
            if tracked is not None:
                return tracked[0], tracked[1], False
        detections, centroids = self.extract.centroids(image)
        self.risen = None
        first = centroids[self.extract.methods[0]]
        measured = detections[np.isin(detections["star"], first["star"])]  # those only an artefact made have none
        self.state = start_tracking(self.extract.prepared(image)[0], measured, first, self.settings, previous=state)
        return detections, centroids, True

    def _tracked(self, image: npt.NDArray[Any], state: TrackState
                 ) -> tuple[npt.NDArray[Any], dict[CentroidMethod, npt.NDArray[Any]]] | None:
        """The tracked stars measured in their windows (:func:`~starlog.centroiding.tracked_frame.track_frame`); None
        when the frame must be searched in full."""
        prepared, saturation = self.extract.prepared(image)
        frame = track_frame(prepared, state, self.settings, self.risen, self.half_size, self.fit, saturation)
        self.risen = frame.risen
        if frame.search:
            return None
        methods = self.extract.methods
        if frame.centroids is None:  # numpy measures the frame (see track_frame)
            centroids = self.extract.measure(prepared, saturation, frame.detections)
            frame = finish_tracked(frame, centroids[methods[0]], state, self.settings, self.half_size, prepared.shape)
            if frame.search:
                return None
        else:
            centroids = {methods[0]: frame.centroids}
            if len(methods) > 1:
                centroids.update(self.extract.measure(prepared, saturation, frame.detections, methods[1:]))
        assert frame.lost is not None and frame.state is not None
        keep = ~frame.lost
        self.state = frame.state
        return frame.detections[keep], {m: centroids[m][keep] for m in methods}


def _window_fit(extract: FrameExtractor) -> WindowFit | None:
    """The compiled frame's measurement of ``extract``'s first method: GAUSSFIT with the PSF width given."""
    psf = extract.options.get("psf_sigma")
    if extract.methods[0] is not CentroidMethod.GAUSSFIT or psf is None:
        return None
    options = dict(extract.options.get("centroid_options") or {})
    return WindowFit(half_size=window_half_size(float(psf), extract.options.get("window")), psf_sigma=float(psf),
                     gain=extract.gain, read_noise=extract.read_noise,
                     fit_psf_sigma=bool(options.get("fit_psf_sigma", False)), robust=bool(options.get("robust", True)))


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
    block = extract.block()
    for frame in frames:
        yield from skipped
        skipped.clear()
        yield block(frame.index, frame.log_time, frame.image, frame.stamp)
    yield from skipped


def extract_blocks_serial(log: LogReader, topic: str, blocks: list[tuple[int, int, int]], extract: FrameExtractor,
                          skip_bad: bool) -> Iterator[FrameMessages | SkippedFrame]:
    """The frames of ``blocks`` in this process, each block extracted on its own as a worker would."""
    for start, end, first in blocks:
        yield from extract_serial(log, topic, extract, skip_bad, start=start, end=end, first_index=first)


def _extract_block(source: LogSource, topic: str, start: int, end: int, first_index: int, extract: FrameExtractor,
                   skip_bad: bool) -> list[FrameMessages | SkippedFrame]:
    """Worker: every frame with ``start <= log_time < end`` (reads the log itself; no image crosses processes)."""
    with opencv_threads(1):
        log = worker_log(source)
        return list(extract_serial(log, topic, extract, skip_bad, start=start, end=end, first_index=first_index))


def extract_parallel(log: LogReader, topic: str, blocks: list[tuple[int, int, int]], extract: FrameExtractor,
                     workers: int, skip_bad: bool) -> Iterator[FrameMessages | SkippedFrame]:
    """The frames of ``blocks`` (:func:`~starlog.replay.blocks.channel_blocks`) extracted by worker processes, each
    reading its blocks from the log itself (:func:`~starlog.replay.blocks.source_of`), and by this process (from
    ``log``) until they are up."""
    source = source_of(log)
    items = ((source, topic, start, end, first, extract, skip_bad) for start, end, first in blocks)

    def in_this_process(_: LogSource, topic: str, start: int, end: int, first: int, extract: FrameExtractor,
                        skip_bad: bool) -> list[FrameMessages | SkippedFrame]:
        return list(extract_serial(log, topic, extract, skip_bad, start=start, end=end, first_index=first))

    with process_pool(workers, preload=["starlog.stages.centroid"]) as pool:
        for done in ordered_map(pool, _extract_block, items, window=2 * workers, until_ready=in_this_process):
            yield from done
