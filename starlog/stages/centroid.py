"""The ``centroid`` stage: detection and sub-pixel centroids of every frame.

Reads an image channel (``/camera/image`` by default; any image type of
:mod:`starlog.io.images`, chosen with ``image_topic``) and writes ``/stars/detections`` (starlog.Detections),
``/stars/centroids/<METHOD>`` per method (starlog.Centroids) and ``/stars/annotations``
(foxglove.ImageAnnotations: circles at the first method's centroids, so the stars show over
the frames in Foxglove), each message at its frame's ``log_time``. Frames are processed one at
a time (memory flat in log length). With ``workers > 1`` the log is split into blocks of
consecutive image chunks; each worker process opens the log itself, decodes and extracts its
block (so no image crosses a process boundary), and the results are written in frame order:
the output does not depend on the number of workers. With PSFFIT (or ``psf="empirical"``) an
empirical PSF is built once from the log's first frames before that, stored as the metadata
record ``starlog.epsf`` (:meth:`starlog.centroid.epsf.EPSF.to_metadata`) and fitted by PSFFIT
in every frame. The summary says how many frames were
read against how many messages the channel holds; they must agree unless ``skip_bad`` names
every frame left out.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import json
import os
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from starlog.centroid import CentroidFlag, CentroidMethod, estimate_psf_sigma, extract_stars
from starlog.centroid.epsf import EPSF, epsf_from_frames
from starlog.centroid.extract import window_half_size
from starlog.centroid.hotpixels import describe_hot_pixels, learn_hot_pixels, load_hot_pixels
from starlog.centroid.phase import (
    DISTINCT_CELL,
    PhaseCalibration,
    estimate_phase_calibration,
    load_phase_calibrations,
    phase_samples,
)
from starlog.detect import detect_stars
from starlog.errors import InvalidInputError, InvalidParameterError
from starlog.io import encode_image_annotations, json_message_type, protobuf_message_type, topics
from starlog.io.frames import SkippedFrame
from starlog.io.images import choose_image_topic
from starlog.io.reader import LogReader
from starlog.io.records import record_encoder
from starlog.stages._blocks import channel_blocks, worker_log
from starlog.stages._channels import check_messages_read
from starlog.stages._parallel import ordered_map, process_pool
from starlog.stages._progress import progress
from starlog.io.reader import LogSource
from starlog.stages.window import windowed
from starlog.stages._stage import extend_log

__all__ = ["CentroidSummary", "centroid_log", "parse_methods"]


def parse_methods(spec: str | Sequence[str]) -> list[CentroidMethod]:
    """``"all"``, ``"GAUSSFIT,MOMENT"`` or a list of names → centroid methods (order kept, no repeats)."""
    names = spec.split(",") if isinstance(spec, str) else list(spec)
    if [n.strip().lower() for n in names] == ["all"]:
        return [CentroidMethod.NONE, CentroidMethod.MOMENT, CentroidMethod.BICUBIC, CentroidMethod.GAUSSFIT,
                CentroidMethod.GRADIENT]
    out = []
    for name in names:
        key = name.strip().upper().replace("-", "_")
        if not key:
            continue
        try:
            out.append(CentroidMethod(key))
        except ValueError:
            known = ", ".join(m.value for m in CentroidMethod)
            raise InvalidParameterError(f"unknown centroid method {name!r}; choose from {known} or 'all'.") from None
    if not out:
        raise InvalidParameterError("give at least one centroid method (or 'all').")
    return list(dict.fromkeys(out))


@dataclass
class CentroidSummary:
    """What :func:`centroid_log` wrote."""

    methods: list[str]
    frames: int = 0
    detections: int = 0
    centroids: dict[str, int] = field(default_factory=dict)
    failed: dict[str, int] = field(default_factory=dict)
    gain: float = 1.0
    image_topic: str = topics.IMAGE
    channel_messages: int = 0
    skipped: list[SkippedFrame] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    epsf: dict[str, Any] | None = None
    phase_correction: dict[str, Any] | None = None

    def to_dict(self) -> dict[str, Any]:
        extra = {"epsf": self.epsf} if self.epsf is not None else {}
        if self.phase_correction is not None:
            extra["phase_correction"] = self.phase_correction
        return {
            "methods": self.methods,
            "image_topic": self.image_topic,
            "frames": self.frames,
            "channel_messages": self.channel_messages,
            "skipped_frames": [s.to_dict() for s in self.skipped],
            "notes": list(self.notes),
            "detections": self.detections,
            "detections_per_frame": self.detections / self.frames if self.frames else 0.0,
            "centroids": dict(self.centroids),
            "fit_failed": dict(self.failed),
            "gain": self.gain,
        } | extra


def _camera_from_provenance(log: LogReader) -> dict[str, float]:
    """Gain and read noise recorded by ``simulate`` (empty for other logs)."""
    for record in log.provenance():
        if record.stage == "simulate":
            camera = record.parameters.get("camera", {})
            return {k: float(camera[k]) for k in ("gain", "read_noise") if k in camera}
    return {}


@windowed(lambda log, options: choose_image_topic(log.path, log.channels(), options.get("image_topic"))[0])
def centroid_log(
    input_path: str | os.PathLike[str],
    output_path: str | os.PathLike[str],
    *,
    methods: str | Sequence[str] = "all",
    gain: float | None = None,
    read_noise: float | None = None,
    options: dict[str, Any] | None = None,
    image_topic: str | None = None,
    skip_bad: bool = False,
    workers: int = 1,
    force: bool = False,
    flatten: bool = False,
    compression: str = "zstd",
    show_progress: bool = False,
    psf: str | None = None,
    hot_pixels: str | os.PathLike[str] | None = None,
    phase_correction: str | os.PathLike[str] | None = None,
) -> CentroidSummary:
    """Detect stars and measure their centroids by each method, for every frame of the log.

    Parameters
    ----------
    methods : str or sequence of str
        ``"all"`` (NONE, MOMENT, BICUBIC, GAUSSFIT, GRADIENT) or names.
    gain, read_noise : float, optional
        Camera gain (e-/DN) and read noise (e-), used for the shot-noise part of each
        centroid's ``sigma``. Default: the values recorded by ``simulate`` in the log's
        provenance, else gain 1 and read noise estimated from the frame.
    options : dict, optional
        Keyword options of :func:`starlog.centroid.extract_stars` (``psf_sigma``, ``window``,
        ``detect_options``, ...). Without ``psf_sigma``, the PSF width is estimated once for
        the whole log, from the first frames with measurable stars, and recorded in the
        provenance (one optics, one PSF; re-estimating it per frame costs time and adds noise).
    image_topic : str, optional
        The image channel to read. Default: ``/camera/image`` if present, else the log's only
        image channel (with a note), else an error listing the image channels.
    skip_bad : bool
        Leave out frames that do not decode or do not fit (named in the summary) instead of stopping.
    workers : int
        Processes extracting blocks of frames in parallel (and threads compressing chunks);
        the output bytes do not depend on it.
    start, end : str or int, optional
        Only the frames with ``start <= log_time < end`` (ns, ``"12.5s"`` or ``"frame:N"`` of the
        image channel; :mod:`starlog.io.timerange`): the layer holds its channels for that range.
    flatten : bool
        Write the whole chain as one self-contained file instead of a layer on the input.
    psf : {"gaussian", "empirical"}, optional
        The PSF model PSFFIT fits. ``"empirical"``: an ePSF built once from the bright,
        isolated, unsaturated stars of the log's first frames (:func:`_log_epsf`), stored in
        the output (metadata ``starlog.epsf``) and recorded in the provenance, even when PSFFIT
        is not among the methods. ``"gaussian"``: PSFFIT fits the pixel-integrated Gaussian of
        the PSF sigma. Default: empirical when PSFFIT is among the methods, else none.
    hot_pixels : "auto" or path, optional
        A hot-pixel map (:mod:`starlog.centroid.hotpixels`): ``"auto"`` learns it from the
        log's first frames, a path reads it (``.npy`` boolean mask or ``x,y`` text lines). Hot
        pixels are never detections and are left out of the star windows; the map (source,
        count, SHA-256, pixels) is recorded in the provenance.
    phase_correction : "auto", "off" or path, optional
        Remove each method's pixel-phase bias (S-curve, :mod:`starlog.centroid.phase`) from
        every centroid. ``"auto"`` learns it from the log's own stars (the first
        :data:`PHASE_MIN_FRAMES` frames and more while they show new phases, each distinct star
        once; no catalogue), per method; a method with too few distinct bright stars is left
        uncorrected, with a note. A path
        reads the calibrations (JSON: ``--json`` output of an earlier run, or its
        ``phase_correction`` records). The calibrations are recorded in the provenance and
        stored as the metadata record ``starlog.phase_correction`` (shown by ``info``).
        Default (or ``"off"``): no correction.
    """
    chosen = parse_methods(methods)
    options = dict(options or {})
    _reuse_frame_buffers()
    digest_params: dict[str, Any] = {"methods": [m.value for m in chosen], "options": options}
    with _opencv_threads(1), LogReader(input_path) as probe:
        topic, chosen_note = choose_image_topic(input_path, probe.channels(), image_topic)
        camera = _camera_from_provenance(probe)
        gain = gain if gain is not None else camera.get("gain", 1.0)
        if read_noise is None:
            read_noise = camera.get("read_noise")
        if not (gain > 0):
            raise InvalidParameterError(f"gain must be > 0 e-/DN, got {gain}.")
        if options.get("psf_sigma") is None:
            options["psf_sigma"] = _log_psf_sigma(probe, topic, gain=gain,
                                                  detect_options=options.get("detect_options"))
        hot_map = _hot_pixel_map(probe, topic, hot_pixels)
    digest_params.update({"gain": gain, "read_noise": read_noise})
    epsf = _epsf_for(input_path, topic, chosen, psf, gain=gain, read_noise=read_noise, options=options)
    if psf is not None:
        digest_params["psf"] = psf
    if epsf is not None:
        digest_params["epsf"] = epsf.summary()
    if hot_map is not None:
        digest_params["hot_pixels"] = describe_hot_pixels(hot_map, _hot_pixel_source(hot_pixels))
    if topic != topics.IMAGE:  # a foreign log: the provenance names the channel the stars come from
        digest_params["image_topic"] = topic
    summary = CentroidSummary(methods=[m.value for m in chosen], gain=gain, image_topic=topic)
    summary.notes = [chosen_note] if chosen_note else []
    if epsf is not None:
        summary.epsf = epsf.summary()
        if CentroidMethod.PSFFIT not in chosen:
            summary.notes.append("the empirical PSF is stored, but only PSFFIT fits it and it is not among the methods.")
    summary.centroids = {m.value: 0 for m in chosen}
    summary.failed = {m.value: 0 for m in chosen}

    extract = _Extractor(methods=tuple(chosen), gain=gain, read_noise=read_noise, options=options, epsf=epsf,
                         hot_pixels=hot_map)
    phase = _phase_correction_for(input_path, topic, extract, phase_correction, show_progress=show_progress)
    if phase is not None:
        extract = replace(extract, phase=phase.active())
        summary.phase_correction = digest_params["phase_correction"] = phase.record()
        summary.notes += phase.notes

    with _opencv_threads(1), extend_log(input_path, output_path, stage="centroid", parameters=digest_params,
                                        force=force, flatten=flatten, compression=compression,
                                        workers=workers) as (log, out):
        summary.channel_messages = n_frames = log.channel(topic).message_count
        det_ch = out.add_channel(topics.DETECTIONS, json_message_type("starlog.Detections"))
        ann_ch = out.add_channel(topics.ANNOTATIONS, protobuf_message_type("foxglove.ImageAnnotations"))
        cen_ch = {m: out.add_channel(topics.centroid_topic(m.value), json_message_type("starlog.Centroids"))
                  for m in chosen}
        # below 64 frames, a pool's start-up costs more than it saves
        blocks = channel_blocks(log, topic, 32) if workers > 1 and n_frames >= 64 and log.fully_indexed else None
        if blocks:
            results = _extract_parallel(log, input_path, topic, blocks, extract, workers, skip_bad)
        else:
            results = _extract_serial(log, topic, extract, skip_bad)
        for encoded in progress(results, total=n_frames, description="centroid", enabled=show_progress):
            if isinstance(encoded, SkippedFrame):
                summary.skipped.append(encoded)
                continue
            t = encoded.log_time
            out.writer.write(det_ch, log_time=t, data=encoded.detections)
            out.writer.write(ann_ch, log_time=t, data=encoded.annotations)
            for k, m in enumerate(chosen):
                out.writer.write(cen_ch[m], log_time=t, data=encoded.centroids[k])
                summary.centroids[m.value] += encoded.n_centroids[k]
                summary.failed[m.value] += encoded.n_failed[k]
            summary.frames += 1
            summary.detections += encoded.n_detections
        _check_frame_count(log, topic, summary)
        summary.notes += [n for n in log.notes if n not in summary.notes]
        if epsf is not None:
            out.writer.add_metadata(topics.EPSF_METADATA, epsf.to_metadata())
        if phase is not None:
            out.writer.add_metadata(topics.PHASE_METADATA, phase.to_metadata())
    return summary


def _epsf_for(path: str | os.PathLike[str], topic: str, chosen: list[CentroidMethod], psf: str | None, *,
              gain: float, read_noise: float | None, options: dict[str, Any]) -> EPSF | None:
    """The log's ePSF when ``psf`` asks for it, or by default when PSFFIT is chosen (see :func:`centroid_log`)."""
    if psf not in (None, "gaussian", "empirical"):
        raise InvalidParameterError(f"psf must be 'gaussian' or 'empirical', got {psf!r}.")
    if psf == "gaussian" or (psf is None and CentroidMethod.PSFFIT not in chosen):
        return None
    with _opencv_threads(1), LogReader(path) as log:
        return _log_epsf(log, topic, gain=gain, read_noise=read_noise, psf_sigma=float(options["psf_sigma"]),
                         window=options.get("window"), saturation=options.get("saturation"),
                         detect_options=options.get("detect_options"))


def _log_epsf(log: LogReader, topic: str, *, gain: float, read_noise: float | None, psf_sigma: float,
              window: int | None, saturation: float | None, detect_options: dict[str, Any] | None,
              max_frames: int = 20, max_stars: int = 2000) -> EPSF:
    """The ePSF of the first ``max_frames`` frames' bright, isolated, unsaturated stars (at most
    ``max_stars``), on windows of the centroid window's half-size (an ePSF one pixel wider)."""

    def frames() -> Iterator[tuple[npt.NDArray[Any], npt.NDArray[Any]]]:
        for index, _, image in log.frames(topic, on_bad=lambda skipped: None):
            if index >= max_frames:
                break
            yield image, detect_stars(image, saturation=saturation, **(detect_options or {}))

    try:
        return epsf_from_frames(frames(), psf_sigma=psf_sigma, half_size=window_half_size(psf_sigma, window), gain=gain,
                                read_noise=read_noise, saturation=saturation, max_stars=max_stars)
    except InvalidInputError as err:
        raise InvalidInputError(f"cannot build an empirical PSF from the first {max_frames} frames of {topic}: "
                                f"{err} Use psf='gaussian' (--psf gaussian) or other methods.") from None


def _check_frame_count(log: LogReader, topic: str, summary: CentroidSummary) -> None:
    """Frames read plus frames skipped (each named) must be every message of the channel."""
    check_messages_read(log, topic, summary.frames + len(summary.skipped), what="frames")


def _log_psf_sigma(log: LogReader, topic: str, *, gain: float, detect_options: dict[str, Any] | None,
                   max_frames: int = 10) -> float:
    """Median PSF sigma over the first ``max_frames`` frames that have measurable stars (1.0 px if none)."""
    estimates = []
    for index, _, image in log.frames(topic, on_bad=lambda skipped: None):
        if index >= max_frames:
            break
        detections = detect_stars(image, **(detect_options or {}))
        if detections.size:
            estimates.append(estimate_psf_sigma(image, detections, gain=gain, default=float("nan")))
    finite = [e for e in estimates if np.isfinite(e)]
    return float(np.median(finite)) if finite else 1.0


HOT_PIXEL_FRAMES = 16
"""Frames ``--hot-pixels auto`` learns the map from (the log's first ones)."""


def _hot_pixel_source(spec: str | os.PathLike[str] | None) -> str:
    if isinstance(spec, str) and spec == "auto":
        return f"auto: spikes in most of the first {HOT_PIXEL_FRAMES} frames"
    return f"file: {os.fspath(spec)}" if spec is not None else ""


def _hot_pixel_map(log: LogReader, topic: str, spec: str | os.PathLike[str] | None) -> npt.NDArray[np.bool_] | None:
    """The hot-pixel map asked for: learnt from the log's first frames (``"auto"``), read from a file, or none."""
    if spec is None:
        return None
    first = (image for index, _, image in log.frames(topic, on_bad=lambda skipped: None) if index < HOT_PIXEL_FRAMES)
    if isinstance(spec, str) and spec == "auto":
        return learn_hot_pixels(first)
    image = next(first, None)
    if image is None:
        raise InvalidParameterError(f"the log has no frame on {topic} to apply the hot-pixel map to.")
    return load_hot_pixels(spec, image.shape)


PHASE_MIN_FRAMES = 16
PHASE_MAX_FRAMES = 256
"""``--phase-correction auto`` learns from the log's first frames: at least ``PHASE_MIN_FRAMES``, at most
``PHASE_MAX_FRAMES``, stopping when half of ``PHASE_MIN_FRAMES`` frames add under 2 % new distinct stars."""


@dataclass
class _PhaseCorrection:
    """The calibrations a run applies, per method, where they came from, and the methods left uncorrected."""

    source: str
    calibrations: dict[str, PhaseCalibration]
    declined: dict[str, str]
    notes: list[str]

    def active(self) -> dict[str, PhaseCalibration]:
        return {m: c for m, c in self.calibrations.items() if c.active}

    def record(self) -> dict[str, Any]:
        return {"source": self.source, "calibrations": [c.to_dict() for c in self.calibrations.values()],
                "declined": dict(self.declined)}

    def to_metadata(self) -> dict[str, str]:
        return {"source": self.source, "calibrations": json.dumps([c.to_dict() for c in self.calibrations.values()]),
                "declined": json.dumps(self.declined)}


def _phase_correction_for(path: str | os.PathLike[str], topic: str, extract: _Extractor,
                          spec: str | os.PathLike[str] | None, *, show_progress: bool = False) -> _PhaseCorrection | None:
    """The phase calibrations ``spec`` asks for: learnt from the log (``"auto"``), read from a file, or none."""
    if spec is None or (isinstance(spec, str) and spec == "off"):
        return None
    methods = [m.value for m in extract.methods]
    if isinstance(spec, str) and spec == "auto":
        with _opencv_threads(1), LogReader(path) as log:
            samples, frames = _phase_samples(log, topic, extract, show_progress=show_progress)
        calibrations, declined = {}, {}
        for m in methods:
            try:
                calibrations[m] = estimate_phase_calibration(*samples[m], method=m)
            except InvalidInputError as err:
                declined[m] = str(err)
        source = f"auto: the stars of the log's first {frames} frames"
    else:
        loaded = load_phase_calibrations(spec)
        calibrations = {m: loaded[m] for m in methods if m in loaded}
        declined = {m: f"no calibration for {m} in {os.fspath(spec)}" for m in methods if m not in loaded}
        source = f"file: {os.fspath(spec)}"
    notes = [f"phase correction: {m} left uncorrected: {why}" for m, why in declined.items()]
    return _PhaseCorrection(source, calibrations, declined, notes)


def _phase_samples(log: LogReader, topic: str, extract: _Extractor, *,
                   show_progress: bool = False) -> tuple[dict[str, tuple[Any, Any, Any]], int]:
    """Per method: (x, y, sigma) of the usable stars of the log's first frames, pooled; and the frames read.

    Frames are read while they bring new distinct stars (:func:`distinct_samples`: a drifting
    field shows new phases in every frame, a static one none after its first frame), up to
    :data:`PHASE_MAX_FRAMES`, and never fewer than :data:`PHASE_MIN_FRAMES`.
    """
    pooled: dict[str, list[tuple[Any, Any, Any]]] = {m.value: [] for m in extract.methods}
    seen: set[tuple[int, int]] = set()
    recent: list[int] = []
    frames = 0
    frames_read = log.frames(topic, on_bad=lambda skipped: None)
    for index, _, image in progress(frames_read, total=min(PHASE_MAX_FRAMES, log.channel(topic).message_count),
                                    description="phase calibration", enabled=show_progress):
        if index >= PHASE_MAX_FRAMES:
            break
        _, centroids = extract.centroids(image)
        frames += 1
        for m, table in centroids.items():
            pooled[m.value].append(phase_samples(table))
        x, y, _ = pooled[extract.methods[0].value][-1]
        before = len(seen)
        cells = np.floor(np.column_stack([x, y]) / DISTINCT_CELL).astype(int)
        seen.update(map(tuple, cells.tolist()))
        recent.append(len(seen) - before)
        if len(recent) >= PHASE_MIN_FRAMES and sum(recent[-PHASE_MIN_FRAMES // 2:]) < 0.02 * len(seen):
            break  # the last frames brought (almost) no new phase: a static field
    samples = {m: tuple(np.concatenate([s[i] for s in parts]) if parts else np.zeros(0) for i in range(3))
               for m, parts in pooled.items()}
    return samples, frames


@dataclass(frozen=True)
class _FrameMessages:
    """One frame's encoded messages (detections, annotations, centroids per method) and counts."""

    log_time: int
    detections: bytes
    annotations: bytes
    centroids: tuple[bytes, ...]
    n_detections: int
    n_centroids: tuple[int, ...]
    n_failed: tuple[int, ...]


@dataclass(frozen=True)
class _Extractor:
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
                 ) -> _FrameMessages:
        """``stamp``: the image message's own time, given to the annotations so Foxglove pairs them with it."""
        detections, centroids = self.centroids(image)
        for m, calibration in (self.phase or {}).items():
            table = centroids[CentroidMethod(m)]
            table["x"], table["y"] = calibration.apply(table["x"], table["y"])
        first = centroids[self.methods[0]]
        diameter = float(max(6.0, 6.0 * np.median(first["psf_sigma"]))) if first.size else 6.0
        per_method = [centroids[m] for m in self.methods]
        return _FrameMessages(
            log_time=log_time,
            detections=record_encoder("starlog.Detections", "stars").encode({"frame": frame}, detections),
            annotations=encode_image_annotations(first["x"], first["y"], log_time=log_time if stamp is None else stamp,
                                                 diameter=diameter),
            centroids=tuple(record_encoder("starlog.Centroids", "stars").encode({"frame": frame, "method": m.value}, c)
                            for m, c in zip(self.methods, per_method)),
            n_detections=int(detections.size),
            n_centroids=tuple(int(c.size) for c in per_method),
            n_failed=tuple(int(np.count_nonzero(c["flags"] & CentroidFlag.FIT_FAILED)) for c in per_method),
        )


_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3


def _reuse_frame_buffers() -> None:
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
def _opencv_threads(count: int) -> Iterator[None]:
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


def _extract_serial(log: LogReader, topic: str, extract: _Extractor, skip_bad: bool, *,
                    start: int | None = None, end: int | None = None, first_index: int = 0,
                    ) -> Iterator[_FrameMessages | SkippedFrame]:
    """Every frame's messages in order; with ``skip_bad``, a bad frame comes out as a :class:`SkippedFrame`."""
    skipped: list[SkippedFrame] = []
    frames = log.frame_records(topic, start=start, end=end, first_index=first_index,
                               on_bad=skipped.append if skip_bad else None)
    for frame in frames:
        yield from skipped
        skipped.clear()
        yield extract(frame.index, frame.log_time, frame.image, frame.stamp)
    yield from skipped


def _extract_block(source: LogSource, topic: str, start: int, end: int, first_index: int, extract: _Extractor,
                   skip_bad: bool) -> list[_FrameMessages | SkippedFrame]:
    """Worker: every frame with ``start <= log_time < end`` (reads the log itself; no image crosses processes)."""
    _reuse_frame_buffers()
    with _opencv_threads(1):
        log = worker_log(source)
        return list(_extract_serial(log, topic, extract, skip_bad, start=start, end=end, first_index=first_index))


def _extract_parallel(log: LogReader, source: LogSource, topic: str, blocks: list[tuple[int, int, int]],
                      extract: _Extractor, workers: int, skip_bad: bool) -> Iterator[_FrameMessages | SkippedFrame]:
    """The frames of ``blocks`` (:func:`~starlog.stages._blocks.channel_blocks`) extracted by worker processes,
    and by this process until they are up."""
    items = ((source, topic, start, end, first, extract, skip_bad) for start, end, first in blocks)

    def in_this_process(_: LogSource, topic: str, start: int, end: int, first: int, extract: _Extractor,
                        skip_bad: bool) -> list[_FrameMessages | SkippedFrame]:
        return list(_extract_serial(log, topic, extract, skip_bad, start=start, end=end, first_index=first))

    with process_pool(workers, preload=["starlog.stages.centroid"]) as pool:
        for done in ordered_map(pool, _extract_block, items, window=2 * workers, until_ready=in_this_process):
            yield from done
