"""The ``centroid`` stage: detection and sub-pixel centroids of every frame.

Reads an image channel (``/camera/image`` by default; any image type of
:mod:`starlog.codecs.images`, chosen with ``image_topic``) and writes ``/stars/detections`` (starlog.Detections),
``/stars/centroids/<METHOD>`` per method (starlog.Centroids) and ``/stars/annotations``
(foxglove.ImageAnnotations: circles at the first method's centroids, so the stars show over
the frames in Foxglove), each message at its frame's ``log_time``. A detection that exists only
because of an artefact (flag ``ARTEFACT``, :mod:`starlog.centroiding.artefacts`) stays in the
detections and is left out of the centroids and annotations; the summary and the provenance
(``results.artefacts``) count them. Frames are processed one at
a time (memory flat in log length). With ``workers > 1`` the log is split into blocks of
consecutive image chunks; each worker process opens the log itself, decodes and extracts its
block (so no image crosses a process boundary), and the results are written in frame order:
the output does not depend on the number of workers. With PSFFIT (or ``psf="empirical"``) an
empirical PSF is built once from the log's first frames before that, stored as the metadata
record ``starlog.epsf`` (:meth:`starlog.centroiding.epsf.EPSF.to_metadata`) and fitted by PSFFIT
in every frame. In tracking mode (``mode``; :mod:`starlog.centroiding.tracking`) the blocks are cut
whatever the number of workers, each starts with a full search, and known stars are measured in
windows around their predicted positions in between. The summary says how many frames were
read against how many messages the channel holds; they must agree unless ``skip_bad`` names
every frame left out.

The input is opened once: :func:`~starlog.stages.centroid.parameters.resolve_centroid_parameters` reads the first
frames it needs from the open log (PSF sigma, hot pixels, mode, ePSF, phase calibration) and :func:`write_centroids`
writes the layer from the same reader (workers open the log themselves). Its parts:
:mod:`~starlog.stages.centroid.parameters` (the parameters, resolved before any frame is written) and
:mod:`~starlog.stages.centroid.frames` (one frame's work, and every frame in order, serial or on workers).
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any

from starlog.centroiding.evidence import EvidenceAccumulator, recommend
from starlog.codecs import protobuf_message_type
from starlog import topics
from starlog.io.frames import SkippedFrame
from starlog.codecs.images import choose_image_topic
from starlog.io.reader import LogReader
from starlog.io.writer import LogWriter
from starlog.replay.blocks import channel_blocks
from starlog.stages.centroid.frames import (
    FrameMessages,
    extract_blocks_serial,
    extract_parallel,
    extract_serial,
    opencv_threads,
)
from starlog.stages.centroid.parameters import CentroidParameters, parse_methods, resolve_centroid_parameters
from starlog.replay.channels import check_messages_read
from starlog.replay.progress import progress
from starlog.replay.window import windowed
from starlog.replay.layer import StageOutput, extend_log

__all__ = ["CentroidLayer", "CentroidParameters", "CentroidSummary", "centroid_log", "parse_methods",
           "resolve_centroid_parameters", "write_centroids"]


@dataclass
class CentroidSummary:
    """What :func:`centroid_log` wrote."""

    methods: list[str]
    frames: int = 0
    detections: int = 0
    centroids: dict[str, int] = field(default_factory=dict)
    failed: dict[str, int] = field(default_factory=dict)
    artefacts: int = 0
    gain: float = 1.0
    image_topic: str = topics.IMAGE
    channel_messages: int = 0
    skipped: list[SkippedFrame] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    epsf: dict[str, Any] | None = None
    phase_correction: dict[str, Any] | None = None
    evidence: dict[str, dict[str, Any]] = field(default_factory=dict)
    recommended: str | None = None
    reason: str = ""
    mode: str = "full"
    acquisitions: int = 0
    """Frames searched in full (every frame in full mode; in tracking mode, the acquisitions)."""

    @classmethod
    def of(cls, p: CentroidParameters) -> CentroidSummary:
        """An empty summary of a run with the resolved parameters ``p``."""
        return cls(methods=[m.value for m in p.methods], gain=p.gain, image_topic=p.image_topic, notes=list(p.notes),
                   epsf=p.epsf.summary() if p.epsf is not None else None,
                   phase_correction=p.provenance.get("phase_correction"),
                   centroids={m.value: 0 for m in p.methods}, failed={m.value: 0 for m in p.methods})

    def to_dict(self) -> dict[str, Any]:
        extra: dict[str, Any] = {"epsf": self.epsf} if self.epsf is not None else {}
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
            "artefacts": self.artefacts,
            "gain": self.gain,
            "evidence": self.evidence,
            "recommended": {"method": self.recommended, "reason": self.reason},
            "mode": self.mode,
            "acquisitions": self.acquisitions,
        } | extra

    def lines(self) -> list[str]:
        """Per method: the centroids written and those not measured; the detections dropped as artefacts."""
        return [f"  {method:<15} {count:>8} centroids, {self.failed[method]} not measured (flag FIT_FAILED: the "
                "detection's position kept)" for method, count in self.centroids.items()] + [
                f"  {self.artefacts} detections only an artefact made, left out of the centroids (flag ARTEFACT "
                f"in {topics.DETECTIONS})"]


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
    phase_correction: str | os.PathLike[str] | None = "auto",
    mode: str = "auto",
    acquire_every: int | None = None,
) -> CentroidSummary:
    """Detect stars and measure their centroids by each method, for every frame of the log.

    Parameters
    ----------
    methods : str or sequence of str
        ``"all"`` (every method but MOMENT_SQUARED:
        :data:`~starlog.stages.centroid.parameters.ALL_METHODS`) or names.
    gain, read_noise : float, optional
        Camera gain (e-/DN) and read noise (e-), used for the shot-noise part of each
        centroid's ``sigma``. Default: the values recorded by ``simulate`` in the log's
        provenance, else gain 1 and read noise estimated from the frame.
    options : dict, optional
        Keyword options of :func:`starlog.centroiding.extract_stars` (``psf_sigma``, ``window``,
        ``detect_options``, ...). Without ``psf_sigma``, the PSF width is estimated once for
        the whole log, from the first frames with measurable stars, and recorded in the
        provenance (one optics, one PSF; re-estimating it per frame costs time and adds noise).
    image_topic : str, optional
        The image channel to read. Default: ``/camera/image`` if present, else the log's only
        image channel (with a note), else an error listing the image channels.
    skip_bad : bool
        Leave out frames that do not decode or do not fit (named in the summary) instead of stopping.
    workers : int
        Processes extracting blocks of frames in parallel; the output bytes do not depend on it.
    start, end : str or int, optional
        Only the frames with ``start <= log_time < end`` (ns, ``"12.5s"`` or ``"frame:N"`` of the
        image channel; :mod:`starlog.io.timerange`): the layer holds its channels for that range.
    flatten : bool
        Write the whole chain as one self-contained file instead of a layer on the input.
    psf : {"gaussian", "empirical"}, optional
        The PSF model PSFFIT fits. ``"empirical"``: an ePSF built once from the bright,
        isolated, unsaturated stars of the log's first frames
        (:mod:`starlog.stages.centroid.parameters`), stored in the output (metadata
        ``starlog.epsf``) and recorded in the provenance, even when PSFFIT is not among the
        methods. ``"gaussian"``: PSFFIT fits the pixel-integrated Gaussian of the PSF sigma.
        Default: empirical when PSFFIT is among the methods, else none.
    hot_pixels : "auto" or path, optional
        A hot-pixel map (:mod:`starlog.centroiding.hotpixels`): ``"auto"`` learns it from the
        log's first frames, a path reads it (``.npy`` boolean mask or ``x,y`` text lines). Hot
        pixels are never detections and are left out of the star windows; the map (source,
        count, SHA-256, pixels) is recorded in the provenance.
    phase_correction : "auto", "off" or path, optional
        Remove each method's pixel-phase bias (S-curve, :mod:`starlog.centroiding.phase`) from
        every centroid. ``"auto"`` learns it from the log's own stars (the first
        :data:`~starlog.stages.centroid.parameters.PHASE_MIN_FRAMES` frames and more while they
        show new phases, each distinct star once; no catalogue), per method; a method with too
        few distinct bright stars is left uncorrected, with a note. A path reads the calibrations
        (JSON: ``--json`` output of an earlier run, or its ``phase_correction`` records). The
        calibrations are recorded in the provenance and stored as the metadata record
        ``starlog.phase_correction`` (shown by ``info``). Default ``"auto"``; ``"off"`` (or None): no
        correction. On a log whose stars already match starlog's model (pixel-integrated Gaussians) the
        estimated amplitudes stay below their significance and nothing changes.
    mode : {"auto", "tracking", "full"}
        ``"full"`` searches every frame for stars. ``"tracking"`` searches the first frame of every block of
        about ``acquire_every`` frames, then measures each known star in a window around its predicted
        position and searches the whole frame again every ``acquire_every`` frames, whenever a star is not
        found or is lost, and whenever light appears outside the windows (:mod:`starlog.centroiding.tracking`);
        its centroids carry the flag ``TRACKED``. ``"auto"`` (default): tracking when the stars of the log's
        first frames are one field moving little from frame to frame, else full. The mode, why, and the
        number of full searches are recorded in the provenance.
    acquire_every : int, optional
        Tracking: frames between two full searches (default
        :data:`~starlog.centroiding.tracking.DEFAULT_ACQUIRE_EVERY`).
    """
    with LogReader(input_path) as log:  # opened once: the parameters' first frames and the frames written
        parameters = resolve_centroid_parameters(log, methods=methods, gain=gain, read_noise=read_noise,
                                                 options=options, image_topic=image_topic, psf=psf,
                                                 hot_pixels=hot_pixels, phase_correction=phase_correction,
                                                 show_progress=show_progress, mode=mode, acquire_every=acquire_every)
        return write_centroids(log, output_path, parameters, skip_bad=skip_bad, workers=workers, force=force,
                               flatten=flatten, compression=compression, show_progress=show_progress)


def write_centroids(log: LogReader, output_path: str | os.PathLike[str], parameters: CentroidParameters, *,
                    skip_bad: bool = False, workers: int = 1, force: bool = False, flatten: bool = False,
                    compression: str = "zstd", show_progress: bool = False) -> CentroidSummary:
    """Write the layer of :func:`centroid_log` on the open ``log`` with resolved ``parameters``: every frame's
    detections, annotations and centroids, and the ePSF and phase calibrations as metadata."""
    p = parameters
    summary = CentroidSummary.of(p)
    provenance = dict(p.provenance)  # completed with the count of full searches when the frames are done
    with opencv_threads(1), extend_log(log, output_path, stage="centroid", parameters=provenance,
                                       force=force, flatten=flatten, compression=compression) as (_, out):
        summary.channel_messages = n_frames = log.channel(p.image_topic).message_count
        layer = CentroidLayer.start(out, p, summary)
        results = _frame_results(log, p, workers, skip_bad)
        for encoded in progress(results, total=n_frames, description="centroid", enabled=show_progress):
            layer.write(encoded)
        _check_frame_count(log, p.image_topic, summary)
        layer.finish(log.notes, provenance)
    return summary


@dataclass
class CentroidLayer:
    """The centroid layer being written, frame by frame: its channels, the summary's counts and the evidence on
    which method to trust. :func:`write_centroids` and ``starlog live`` write it through this class alone."""

    out: StageOutput
    parameters: CentroidParameters
    summary: CentroidSummary
    detections: int
    annotations: int
    centroids: list[int]
    evidence: EvidenceAccumulator

    @classmethod
    def start(cls, out: StageOutput, parameters: CentroidParameters, summary: CentroidSummary) -> CentroidLayer:
        """Add the layer's channels to ``out``."""
        methods = parameters.methods
        return cls(out, parameters, summary,
                   out.add_channel(topics.DETECTIONS, protobuf_message_type("starlog.Detections")),
                   out.add_channel(topics.ANNOTATIONS, protobuf_message_type("foxglove.ImageAnnotations")),
                   [out.add_channel(topics.centroid_topic(m.value), protobuf_message_type("starlog.Centroids"))
                    for m in methods], EvidenceAccumulator(summary.methods))

    def write(self, encoded: FrameMessages | SkippedFrame) -> None:
        """One frame's messages (a skipped frame is listed in the summary)."""
        summary, writer = self.summary, self.out.writer
        if isinstance(encoded, SkippedFrame):
            summary.skipped.append(encoded)
            return
        if encoded.evidence is not None:
            self.evidence.add(encoded.evidence)
        summary.acquisitions += encoded.acquired
        t = encoded.log_time
        writer.write(self.detections, log_time=t, data=encoded.detections)
        writer.write(self.annotations, log_time=t, data=encoded.annotations)
        for k, m in enumerate(self.parameters.methods):
            writer.write(self.centroids[k], log_time=t, data=encoded.centroids[k])
            summary.centroids[m.value] += encoded.n_centroids[k]
            summary.failed[m.value] += encoded.n_failed[k]
        summary.frames += 1
        summary.detections += encoded.n_detections
        summary.artefacts += encoded.n_artefacts

    def finish(self, notes: list[str], provenance: dict[str, Any]) -> None:
        """The layer's closing records: the ePSF, the phase calibrations, the evidence; the count of full
        searches into ``provenance`` (read when the layer's provenance is written)."""
        p, summary, writer = self.parameters, self.summary, self.out.writer
        self.out.results["artefacts"] = summary.artefacts
        summary.notes += [n for n in notes if n not in summary.notes]
        if p.epsf is not None:
            writer.add_metadata(topics.EPSF_METADATA, p.epsf.to_metadata())
        if p.phase is not None:
            writer.add_metadata(topics.PHASE_METADATA, p.phase.to_metadata())
        _record_evidence(writer, summary, self.evidence, p)
        summary.mode = provenance["mode"]
        provenance["acquisitions"] = summary.acquisitions


def _frame_results(log: LogReader, p: CentroidParameters, workers: int, skip_bad: bool
                   ) -> Iterator[FrameMessages | SkippedFrame]:
    """Every frame's messages in order. Full mode cuts the log into blocks of ~32 frames for the workers; tracking
    mode always cuts it into blocks of at most ``acquire_every`` frames (whole chunks), each starting with a full search, whatever the
    number of workers, so that the output does not depend on it."""
    tracking = p.extract.tracking
    n_frames = log.channel(p.image_topic).message_count
    frames_per_block = 32 if tracking is None else tracking.acquire_every
    blocks = (channel_blocks(log, p.image_topic, frames_per_block, at_most=tracking is not None)
              if log.fully_indexed else None)
    if blocks and workers > 1 and n_frames >= 64:  # below 64 frames, a pool's start-up costs more than it saves
        return extract_parallel(log, p.image_topic, blocks, p.extract, workers, skip_bad)
    if blocks and tracking is not None:
        return extract_blocks_serial(log, p.image_topic, blocks, p.extract, skip_bad)
    return extract_serial(log, p.image_topic, p.extract, skip_bad)


def _record_evidence(writer: LogWriter, summary: CentroidSummary, evidence: EvidenceAccumulator,
                     p: CentroidParameters) -> None:
    """The evidence on which method to trust (:mod:`starlog.centroiding.evidence`), each method's phase
    calibration beside it, and the method recommended: into the summary and the metadata record."""
    summary.evidence = evidence.result()
    calibrations = p.phase.calibrations if p.phase is not None else {}
    for method, figures in summary.evidence.items():
        cal = calibrations.get(method)
        figures["phase_amplitude_px"] = None if cal is None else [cal.amplitude_x[0], cal.amplitude_y[0]]
        figures["phase_error_px"] = None if cal is None else [cal.error_x[0], cal.error_y[0]]
    summary.recommended, summary.reason = recommend(summary.evidence)
    writer.add_metadata(topics.EVIDENCE_METADATA, {"methods": json.dumps(summary.evidence),
                                                   "recommended": summary.recommended or "",
                                                   "reason": summary.reason})


def _check_frame_count(log: LogReader, topic: str, summary: CentroidSummary) -> None:
    """Frames read plus frames skipped (each named) must be every message of the channel."""
    check_messages_read(log, topic, summary.frames + len(summary.skipped), what="frames")
