"""The centroid stage's parameters, resolved from its options and the log before any frame is written.

:func:`resolve_centroid_parameters` chooses the image channel, takes the camera's gain and read
noise from the options or the simulator's provenance, estimates the PSF sigma once for the log,
builds the empirical PSF, the hot-pixel map and the pixel-phase calibrations when asked for, and
gathers what the provenance records: a :class:`CentroidParameters`, which
:func:`starlog.stages.centroid.centroid_log` then runs on every frame.
"""

from __future__ import annotations

import inspect
import json
import os
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import numpy.typing as npt

from starlog.centroiding import CentroidMethod, artefact_detections, estimate_psf_sigma, measure_centroids
from starlog.centroiding.epsf import EPSF, epsf_from_frames
from starlog.centroiding.extract import detect_options_for_psf, window_half_size
from starlog.centroiding.hotpixels import describe_hot_pixels, learn_hot_pixels, load_hot_pixels
from starlog.centroiding.tracking import DEFAULT_ACQUIRE_EVERY, TrackingSettings, is_image_sequence
from starlog.centroiding.phase import (
    DISTINCT_CELL,
    PhaseCalibration,
    estimate_phase_calibration,
    load_phase_calibrations,
    phase_samples,
)
from starlog.detect import detect_stars
from starlog.errors import InvalidInputError, InvalidParameterError
from starlog import topics
from starlog.codecs.images import choose_image_topic
from starlog.io.reader import LogReader
from starlog.replay.blocks import source_of
from starlog.stages.centroid.frames import FrameExtractor, opencv_threads
from starlog.replay.progress import progress

__all__ = ["HOT_PIXEL_FRAMES", "MODES", "MODE_FRAMES", "PHASE_MAX_FRAMES", "PHASE_MIN_FRAMES", "CentroidParameters",
           "PhaseCorrection", "extract_options", "parse_methods", "resolve_centroid_parameters", "ALL_METHODS"]

MODES = ("auto", "tracking", "full")
"""The centroid stage's modes: ``full`` searches every frame, ``tracking`` measures known stars in windows
(:mod:`starlog.centroiding.tracking`), ``auto`` chooses tracking for a sequence of one field, else full."""
MODE_FRAMES = 8
"""Frames at the log's start whose stars ``mode="auto"`` compares (:func:`starlog.centroiding.tracking.is_image_sequence`)."""


ALL_METHODS = (CentroidMethod.NONE, CentroidMethod.MOMENT, CentroidMethod.BICUBIC, CentroidMethod.GAUSSFIT,
               CentroidMethod.GRADIENT, CentroidMethod.PSFFIT, CentroidMethod.WINPOS)
"""The methods ``"all"`` names: every method that is the most accurate on some camera of the benchmarks (real sky,
its degraded copies, the simulator's PSFs; docs/BENCHMARKS.md), and GRADIENT, which ``"all"`` named before.
MOMENT_SQUARED is the most accurate on none (on faint stars its squared weights are the least accurate)."""


def parse_methods(spec: str | Sequence[str]) -> list[CentroidMethod]:
    """``"all"`` (:data:`ALL_METHODS`), ``"GAUSSFIT,MOMENT"`` or a list of names → centroid methods (order kept,
    no repeats)."""
    names = spec.split(",") if isinstance(spec, str) else list(spec)
    if [n.strip().lower() for n in names] == ["all"]:
        return list(ALL_METHODS)
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


#: Options the stage passes to :func:`starlog.centroiding.extract_stars` as they are.
_EXTRACT_KEYS = ("psf_sigma", "window", "saturation", "drop_artefacts", "detect_options", "centroid_options")
#: Keywords the stage sets itself (``--gain``, ``--read-noise``, ``--method``, ``--psf``, ``--hot-pixels``).
_STAGE_KEYS = {"image", "detections", "method", "methods", "gain", "read_noise", "epsf", "hot_pixels", "background"}


def _keywords(function: Any) -> list[str]:
    return [name for name, p in inspect.signature(function).parameters.items()
            if p.kind is inspect.Parameter.KEYWORD_ONLY and name not in _STAGE_KEYS and name not in _EXTRACT_KEYS]


def extract_options(options: dict[str, Any] | None) -> dict[str, Any]:
    """Flat ``KEY=VALUE`` options (``--set``) → keyword options of :func:`starlog.centroiding.extract_stars`.

    A key of :func:`starlog.detect.detect_stars` (``threshold``, ``min_area``, …) goes into
    ``detect_options``, a key of :func:`starlog.centroiding.measure_centroids` (``debias``,
    ``robust``, …) into ``centroid_options``; ``psf_sigma``, ``window``, ``saturation`` and the two
    mappings themselves stay as they are. Any other key is an error that lists the valid ones.
    """
    detect_keys, centroid_keys = _keywords(detect_stars), _keywords(measure_centroids)
    out: dict[str, Any] = {}
    for key, value in (options or {}).items():
        if key in _EXTRACT_KEYS:
            if key.endswith("_options"):
                if not isinstance(value, dict):
                    raise InvalidParameterError(f"{key} must be a mapping of options, e.g. {{\"threshold\": 5}}; "
                                                f"got {value!r}.")
                out[key] = {**out.get(key, {}), **value}
            else:
                out[key] = value
        elif key in detect_keys:
            out.setdefault("detect_options", {})[key] = value
        elif key in centroid_keys:
            out.setdefault("centroid_options", {})[key] = value
        else:
            raise InvalidParameterError(
                f"unknown centroid option {key!r}. Detection: {', '.join(detect_keys)}; centroiding: "
                f"{', '.join(centroid_keys)}; also {', '.join(_EXTRACT_KEYS)}.")
    return out


@dataclass(frozen=True)
class CentroidParameters:
    """What the centroid stage runs with, resolved from its options and the log."""

    methods: list[CentroidMethod]
    image_topic: str
    gain: float
    read_noise: float | None
    options: dict[str, Any]
    """Keyword options of :func:`starlog.centroiding.extract_stars`, ``psf_sigma`` included."""
    epsf: EPSF | None
    hot_pixels: npt.NDArray[np.bool_] | None
    phase: PhaseCorrection | None
    extract: FrameExtractor
    """One frame's work: detection, centroids (phase-corrected) and messages."""
    provenance: dict[str, Any]
    """The parameters the stage's provenance record holds."""
    notes: list[str]
    """What the run should say: how the image channel was chosen, an unused ePSF, uncorrected methods."""


def resolve_centroid_parameters(
    log: LogReader,
    *,
    methods: str | Sequence[str] = "all",
    gain: float | None = None,
    read_noise: float | None = None,
    options: dict[str, Any] | None = None,
    image_topic: str | None = None,
    psf: str | None = None,
    hot_pixels: str | os.PathLike[str] | None = None,
    phase_correction: str | os.PathLike[str] | None = "auto",
    show_progress: bool = False,
    mode: str = "auto",
    acquire_every: int | None = None,
) -> CentroidParameters:
    """The parameters of :func:`starlog.stages.centroid.centroid_log` (its options, same meanings), with what
    the open ``log`` gives where an option is not set; reads the first frames of the log for the PSF sigma, the
    ePSF, the hot-pixel map, the phase calibrations and (``mode="auto"``) whether its frames are one sequence."""
    chosen = parse_methods(methods)
    options = extract_options(options)
    if mode not in MODES:
        raise InvalidParameterError(f"mode must be one of {', '.join(MODES)}; got {mode!r}.")
    tracking = _tracking_settings(options.get("detect_options"), acquire_every)
    with opencv_threads(1):
        topic, chosen_note = choose_image_topic(source_of(log), log.channels(), image_topic)
        gain, read_noise = _camera(log, gain, read_noise)
        if options.get("psf_sigma") is None:
            options["psf_sigma"] = _log_psf_sigma(log, topic, gain=gain, detect_options=options.get("detect_options"))
        detect_options = detect_options_for_psf(options["psf_sigma"], options.get("detect_options"))
        if detect_options != (options.get("detect_options") or {}):
            options["detect_options"] = detect_options  # an undersampled PSF: recorded in the provenance
        hot_map = _hot_pixel_map(log, topic, hot_pixels)
        mode_record = _choose_mode(log, topic, mode, tracking, options.get("detect_options"))
        epsf, epsf_note = _epsf_for(log, topic, chosen, psf, gain=gain, read_noise=read_noise, options=options)
        notes = [note for note in (chosen_note, epsf_note) if note]
        if epsf is not None and CentroidMethod.PSFFIT not in chosen:
            notes.append("the empirical PSF is stored, but only PSFFIT fits it and it is not among the methods.")
        extract = FrameExtractor(methods=tuple(chosen), gain=gain, read_noise=read_noise, options=options, epsf=epsf,
                                 hot_pixels=hot_map)
        phase = _phase_correction_for(log, topic, extract, phase_correction, show_progress=show_progress)
    if phase is not None:
        extract = replace(extract, phase=phase.active())
        notes += phase.notes
    if mode_record["mode"] == "tracking":
        extract = replace(extract, tracking=tracking)
    provenance: dict[str, Any] = {"methods": [m.value for m in chosen], "options": options, "gain": gain,
                                  "read_noise": read_noise}
    if psf is not None:
        provenance["psf"] = psf
    if epsf is not None:
        provenance["epsf"] = epsf.summary()
    if hot_map is not None:
        provenance["hot_pixels"] = describe_hot_pixels(hot_map, _hot_pixel_source(hot_pixels))
    if topic != topics.IMAGE:  # a foreign log: the provenance names the channel the stars come from
        provenance["image_topic"] = topic
    if phase is not None:
        provenance["phase_correction"] = phase.record()
    provenance.update(mode_record)
    return CentroidParameters(methods=chosen, image_topic=topic, gain=gain, read_noise=read_noise, options=options,
                              epsf=epsf, hot_pixels=hot_map, phase=phase, extract=extract, provenance=provenance,
                              notes=notes)


def _camera(log: LogReader, gain: float | None, read_noise: float | None) -> tuple[float, float | None]:
    """Gain and read noise: as given, else as ``simulate`` recorded them, else gain 1 and no read noise."""
    camera = _camera_from_provenance(log)
    gain = gain if gain is not None else camera.get("gain", 1.0)
    if read_noise is None:
        read_noise = camera.get("read_noise")
    if not (gain > 0):
        raise InvalidParameterError(f"gain must be > 0 e-/DN, got {gain}.")
    return gain, read_noise


def _tracking_settings(detect_options: dict[str, Any] | None, acquire_every: int | None) -> TrackingSettings:
    """Tracking's settings with the detection's threshold, matched filter and border (its defaults unless set)."""
    defaults = {name: p.default for name, p in inspect.signature(detect_stars).parameters.items()}
    given = {**defaults, **(detect_options or {})}
    return TrackingSettings(acquire_every=DEFAULT_ACQUIRE_EVERY if acquire_every is None else int(acquire_every),
                            threshold=float(given["threshold"]), filter_sigma=float(given["filter_sigma"]),
                            border=int(given["border"]))


def _choose_mode(log: LogReader, topic: str, mode: str, tracking: TrackingSettings,
                 detect_options: dict[str, Any] | None) -> dict[str, Any]:
    """The mode the stage runs in and why (the provenance's ``mode``, ``mode_reason`` and, tracking, ``tracking``):
    ``auto`` is tracking when the stars of the log's first :data:`MODE_FRAMES` frames are one field moving
    little from frame to frame (:func:`starlog.centroiding.tracking.is_image_sequence`), else full."""
    if mode == "auto":
        positions = []
        for index, _, image in log.frames(topic, on_bad=lambda skipped: None):
            if index >= MODE_FRAMES:
                break
            found = detect_stars(image, **(detect_options or {}))
            positions.append((np.asarray(found["x"], np.float64), np.asarray(found["y"], np.float64)))
        sequence, why = is_image_sequence(positions, tracking.search)
        chosen, reason = ("tracking" if sequence else "full"), f"auto: {why}"
    else:
        chosen, reason = mode, "asked for"
    record: dict[str, Any] = {"mode": chosen, "mode_reason": reason}
    if chosen == "tracking":
        record["tracking"] = tracking.to_dict()
    return record


def _camera_from_provenance(log: LogReader) -> dict[str, float]:
    """Gain and read noise recorded by ``simulate`` (empty for other logs)."""
    for record in log.provenance():
        if record.stage == "simulate":
            camera = record.parameters.get("camera", {})
            return {k: float(camera[k]) for k in ("gain", "read_noise") if k in camera}
    return {}


def _epsf_for(log: LogReader, topic: str, chosen: list[CentroidMethod], psf: str | None, *,
              gain: float, read_noise: float | None, options: dict[str, Any]) -> tuple[EPSF | None, str]:
    """The log's ePSF when ``psf`` asks for it, or by default when PSFFIT is chosen
    (see :func:`starlog.stages.centroid.centroid_log`), and a note. By default, a log without a star to build
    one from gets none (PSFFIT fits the Gaussian, said in the note); asked for, that is an error."""
    if psf not in (None, "gaussian", "empirical"):
        raise InvalidParameterError(f"psf must be 'gaussian' or 'empirical', got {psf!r}.")
    if psf == "gaussian" or (psf is None and CentroidMethod.PSFFIT not in chosen):
        return None, ""
    try:
        return _log_epsf(log, topic, gain=gain, read_noise=read_noise, psf_sigma=float(options["psf_sigma"]),
                         window=options.get("window"), saturation=options.get("saturation"),
                         detect_options=options.get("detect_options")), ""
    except InvalidInputError as err:
        if psf == "empirical":
            raise
        return None, f"PSFFIT fits the Gaussian of the log's PSF width: {err}"


def _log_epsf(log: LogReader, topic: str, *, gain: float, read_noise: float | None, psf_sigma: float,
              window: int | None, saturation: float | None, detect_options: dict[str, Any] | None,
              max_frames: int = 20, max_stars: int = 2000) -> EPSF:
    """The ePSF of the first ``max_frames`` frames' bright, isolated, unsaturated stars (at most
    ``max_stars``; detections only an artefact made left out), on windows of the centroid window's
    half-size (an ePSF one pixel wider)."""

    def frames() -> Iterator[tuple[npt.NDArray[Any], npt.NDArray[Any]]]:
        for index, _, image in log.frames(topic, on_bad=lambda skipped: None):
            if index >= max_frames:
                break
            found = detect_stars(image, saturation=saturation, **(detect_options or {}))
            yield image, found[~artefact_detections(image, found, psf_sigma=psf_sigma, gain=gain, read_noise=read_noise,
                                                    window=window, saturation=saturation,
                                                    detect_options=detect_options)]

    try:
        return epsf_from_frames(frames(), psf_sigma=psf_sigma, half_size=window_half_size(psf_sigma, window), gain=gain,
                                read_noise=read_noise, saturation=saturation, max_stars=max_stars)
    except InvalidInputError as err:
        raise InvalidInputError(f"cannot build an empirical PSF from the first {max_frames} frames of {topic}: "
                                f"{err} Use psf='gaussian' (--psf gaussian) or other methods.") from None


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
class PhaseCorrection:
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


def _phase_correction_for(log: LogReader, topic: str, extract: FrameExtractor, spec: str | os.PathLike[str] | None,
                          *, show_progress: bool = False) -> PhaseCorrection | None:
    """The phase calibrations ``spec`` asks for: learnt from the log (``"auto"``), read from a file, or none."""
    if spec is None or (isinstance(spec, str) and spec == "off"):
        return None
    methods = [m.value for m in extract.methods]
    if isinstance(spec, str) and spec == "auto":
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
    # learnt by default, a calibration declined for want of stars is routine: recorded (``info`` shows it), not a note
    notes = [] if source.startswith("auto") else [f"phase correction: {m} left uncorrected: {why}"
                                                  for m, why in declined.items()]
    return PhaseCorrection(source, calibrations, declined, notes)


def _phase_samples(log: LogReader, topic: str, extract: FrameExtractor, *,
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
