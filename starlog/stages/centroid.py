"""The ``centroid`` stage: detection and sub-pixel centroids of every frame.

Reads ``/camera/image`` and writes ``/stars/detections`` (starlog.Detections),
``/stars/centroids/<METHOD>`` per method (starlog.Centroids) and ``/stars/annotations``
(foxglove.ImageAnnotations: circles at the first method's centroids, so the stars show over
the frames in Foxglove), each message at its frame's ``log_time``. Frames are processed one at
a time (memory flat in log length); with ``workers > 1`` frames are extracted on a thread
pool and written in order, so the output does not depend on the number of workers.
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from starlog.centroid import CentroidMethod, extract_stars
from starlog.errors import InvalidParameterError
from starlog.export import TableSpec, register_table
from starlog.io import encode_image_annotations, encode_json, json_message_type, protobuf_message_type, topics
from starlog.io.reader import ChannelSummary, LogReader
from starlog.stages._progress import progress
from starlog.stages._stage import extend_log

__all__ = ["CentroidSummary", "centroid_log", "parse_methods", "rows"]


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


def rows(array: npt.NDArray[np.void]) -> list[dict[str, Any]]:
    """Structured array → list of JSON-ready dicts (Python scalars)."""
    names = array.dtype.names or ()
    return [dict(zip(names, values)) for values in array.tolist()]


@dataclass
class CentroidSummary:
    """What :func:`centroid_log` wrote."""

    methods: list[str]
    frames: int = 0
    detections: int = 0
    centroids: dict[str, int] = field(default_factory=dict)
    failed: dict[str, int] = field(default_factory=dict)
    gain: float = 1.0

    def to_dict(self) -> dict[str, Any]:
        return {
            "methods": self.methods,
            "frames": self.frames,
            "detections": self.detections,
            "detections_per_frame": self.detections / self.frames if self.frames else 0.0,
            "centroids": dict(self.centroids),
            "fit_failed": dict(self.failed),
            "gain": self.gain,
        }


def _camera_from_provenance(log: LogReader) -> dict[str, float]:
    """Gain and read noise recorded by ``simulate`` (empty for other logs)."""
    for record in log.provenance():
        if record.stage == "simulate":
            camera = record.parameters.get("camera", {})
            return {k: float(camera[k]) for k in ("gain", "read_noise") if k in camera}
    return {}


def centroid_log(
    input_path: str | os.PathLike[str],
    output_path: str | os.PathLike[str],
    *,
    methods: str | Sequence[str] = "all",
    gain: float | None = None,
    read_noise: float | None = None,
    options: dict[str, Any] | None = None,
    workers: int = 1,
    force: bool = False,
    compression: str = "zstd",
    show_progress: bool = False,
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
        Keyword options of :func:`starlog.centroid.extract_stars` (detection threshold,
        window, ...).
    workers : int
        Frames extracted in parallel (threads); the output bytes do not depend on it.
    """
    chosen = parse_methods(methods)
    options = dict(options or {})
    digest_params: dict[str, Any] = {"methods": [m.value for m in chosen], "options": options}
    with LogReader(input_path) as probe:
        camera = _camera_from_provenance(probe)
    gain = gain if gain is not None else camera.get("gain", 1.0)
    if read_noise is None:
        read_noise = camera.get("read_noise")
    if not (gain > 0):
        raise InvalidParameterError(f"gain must be > 0 e-/DN, got {gain}.")
    digest_params.update({"gain": gain, "read_noise": read_noise})
    summary = CentroidSummary(methods=[m.value for m in chosen], gain=gain)
    summary.centroids = {m.value: 0 for m in chosen}
    summary.failed = {m.value: 0 for m in chosen}

    def extract(image: npt.NDArray[Any]) -> tuple[npt.NDArray[np.void], dict[Any, npt.NDArray[np.void]]]:
        return extract_stars(image, methods=chosen, gain=gain, read_noise=read_noise, **options)

    with extend_log(input_path, output_path, stage="centroid", parameters=digest_params, force=force,
                    compression=compression, workers=workers) as (log, out):
        n_frames = log.channel(topics.IMAGE).message_count
        det_ch = out.add_channel(topics.DETECTIONS, json_message_type("starlog.Detections"))
        ann_ch = out.add_channel(topics.ANNOTATIONS, protobuf_message_type("foxglove.ImageAnnotations"))
        cen_ch = {m: out.add_channel(topics.centroid_topic(m.value), json_message_type("starlog.Centroids"))
                  for m in chosen}
        results = _extract_in_order(log.frames(), extract, workers)
        for frame, t, (detections, centroids) in progress(results, total=n_frames, description="centroid",
                                                          enabled=show_progress):
            out.writer.write(det_ch, log_time=t, data=encode_json({"frame": frame, "stars": rows(detections)}))
            first = centroids[chosen[0]]
            diameter = float(max(6.0, 6.0 * np.median(first["psf_sigma"]))) if first.size else 6.0
            out.writer.write(ann_ch, log_time=t, data=encode_image_annotations(
                first["x"], first["y"], log_time=t, diameter=diameter))
            for m in chosen:
                c = centroids[m]
                out.writer.write(cen_ch[m], log_time=t,
                                 data=encode_json({"frame": frame, "method": m.value, "stars": rows(c)}))
                summary.centroids[m.value] += int(c.size)
                summary.failed[m.value] += int(np.count_nonzero(c["flags"] & 4))
            summary.frames += 1
            summary.detections += int(detections.size)
    return summary


def _extract_in_order(
    frames: Iterator[tuple[int, int, npt.NDArray[Any]]], extract: Any, workers: int
) -> Iterator[tuple[int, int, Any]]:
    if workers <= 1:
        for frame, t, image in frames:
            yield frame, t, extract(image)
        return
    with ThreadPoolExecutor(max_workers=workers) as pool:
        window: list[tuple[int, int, Any]] = []
        for frame, t, image in frames:
            window.append((frame, t, pool.submit(extract, image)))
            if len(window) >= 2 * workers:
                f, tt, fut = window.pop(0)
                yield f, tt, fut.result()
        for f, tt, fut in window:
            yield f, tt, fut.result()


def _centroid_rows(ch: ChannelSummary, log_time: int, msg: Any) -> Iterator[dict[str, Any]]:
    for star in msg["stars"]:
        yield {"log_time": log_time, "frame": msg["frame"], "method": msg["method"], **star}


def _detection_rows(ch: ChannelSummary, log_time: int, msg: Any) -> Iterator[dict[str, Any]]:
    for star in msg["stars"]:
        yield {"log_time": log_time, "frame": msg["frame"], **star}


register_table(TableSpec("detections", lambda ch: ch.topic == topics.DETECTIONS, _detection_rows))
register_table(TableSpec("centroids", lambda ch: ch.schema_name == "starlog.Centroids", _centroid_rows))
