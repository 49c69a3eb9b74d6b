"""The ``ingest`` stage: turn camera output (a folder of images, a SER or video file) into a log.

Sources (read by :mod:`starlog.stages.ingest.sources`):

* a folder of 8- and 16-bit PNG and TIFF (any compression cameras and libraries write:
  :mod:`starlog.stages.ingest.tiff`), BMP, JPEG (lossy: a warning), and FITS with the ``fits``
  extra (``pip install starlog[fits]``), in natural file-name order (``img2.png`` before ``img10.png``);
* a SER file (:mod:`starlog.stages.ingest.ser`): 8/16-bit mono, RGB/BGR and Bayer frames;
* an AVI/MP4/MOV/MKV video, decoded by OpenCV to 8 bits.

Timestamps come from a frame rate (``fps``, ``start_ns``), from the file names (``time_pattern``,
a regular expression with a named group ``t``, in ``time_unit``; folders only), or without
either, from the file itself: a SER file's timestamp trailer (UTC, as Unix-epoch ns) or the video
container's frame times (ns from the first frame), plus ``start_ns``.
"""

from __future__ import annotations

import os
import re
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from starlog.version import __version__
from starlog.errors import ImageFolderError, InvalidParameterError
from starlog.io import LogWriter, Provenance
from starlog.codecs import encode_json, encode_raw_image, json_message_type, protobuf_message_type
from starlog import topics
from starlog.io.writer import FRAME_COMPRESSION
from starlog.io.provenance import PROVENANCE_METADATA_NAME
from starlog.replay.progress import progress
from starlog.stages.ingest.sources import (
    IMAGE_SUFFIXES,
    LOSSY_SUFFIXES,
    SER_SUFFIXES,
    VIDEO_SUFFIXES,
    ColourImageWarning,
    LossyImageWarning,
    SourceFrame,
    folder_frames,
    list_images,
    lossy_warning,
    natural_key,
    read_image,
    ser_frames,
    video_frames,
)

__all__ = ["IMAGE_SUFFIXES", "SER_SUFFIXES", "VIDEO_SUFFIXES", "ColourImageWarning", "IngestSummary",
           "LossyImageWarning", "ingest_folder", "ingest_source", "list_images", "natural_key", "read_image"]

_TIME_UNITS = {"s": 1e9, "ms": 1e6, "us": 1e3, "ns": 1.0}


@dataclass
class IngestSummary:
    """What :func:`ingest_source` did."""

    output: Path
    frames: int = 0
    width: int = 0
    height: int = 0
    encoding: str = ""
    first_log_time: int = 0
    last_log_time: int = 0
    timing: str = ""
    skipped: list[tuple[str, str]] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    def lines(self) -> list[str]:
        """What ``starlog ingest`` prints: each file or frame left out, and why."""
        return [f"  skipped {name}: {reason}" for name, reason in self.skipped]

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form."""
        return {
            "output": str(self.output),
            "frames": self.frames,
            "width": self.width,
            "height": self.height,
            "encoding": self.encoding,
            "first_log_time": self.first_log_time,
            "last_log_time": self.last_log_time,
            "timing": self.timing,
            "skipped": [{"file": f, "reason": r} for f, r in self.skipped],
            "notes": list(self.notes),
        }


@dataclass
class _Source:
    kind: str  # "folder", "SER" or "video"
    total: int  # frames expected (0: unknown)
    file_times: bool
    frames: Iterator[SourceFrame]
    lossy: list[str] = field(default_factory=list)


def _open_source(source: Path, workers: int) -> _Source:
    if source.is_dir():
        files = list_images(source)
        lossy = [p.name for p in files if p.suffix.lower() in LOSSY_SUFFIXES]
        return _Source("folder", len(files), False, folder_frames(files, workers), lossy)
    if not source.exists():
        raise ImageFolderError(source, "does not exist.")
    suffix = source.suffix.lower()
    if suffix in SER_SUFFIXES:
        return _Source("SER", *ser_frames(source))
    if suffix in VIDEO_SUFFIXES:
        return _Source("video", *video_frames(source))
    if suffix in IMAGE_SUFFIXES:
        lossy = [source.name] if suffix in LOSSY_SUFFIXES else []
        return _Source("folder", 1, False, folder_frames([source], 1), lossy)
    kinds = ", ".join(sorted(SER_SUFFIXES | VIDEO_SUFFIXES | IMAGE_SUFFIXES))
    raise ImageFolderError(source, f"is not a folder, video or image file starlog reads ({kinds}).")


def _stamper(source: _Source, path: Path, *, fps: float | None, start_ns: int, time_pattern: str | None,
             time_unit: str) -> tuple[Callable[[SourceFrame], int], str]:
    """How each frame is timed, and a label saying so."""
    if time_pattern is not None:
        if source.kind != "folder":
            raise InvalidParameterError(f"--time-pattern times image files by their names; {path.name} is a "
                                        f"{source.kind} file: use --fps or its own timestamps.")
        return _from_names(time_pattern, time_unit, start_ns), "file names"
    if fps is not None:
        if not fps > 0:
            raise InvalidParameterError(f"--fps must be > 0, got {fps}.")
        return (lambda frame: start_ns + int(round(frame.position * 1e9 / fps))), f"{fps:g} fps"
    if source.file_times:
        return (lambda frame: start_ns + int(frame.file_time_ns or 0)), f"{source.kind} timestamps"
    if source.kind == "SER":
        raise InvalidParameterError(f"{path.name} has no frame timestamps (no trailer); give the frame rate "
                                    "with --fps.")
    raise InvalidParameterError("give the frame rate (--fps, > 0) or a --time-pattern to time the frames.")


def _from_names(time_pattern: str, time_unit: str, start_ns: int) -> Callable[[SourceFrame], int]:
    if time_unit not in _TIME_UNITS:
        raise InvalidParameterError(f"time unit must be one of {sorted(_TIME_UNITS)}, got {time_unit!r}.")
    try:
        regex = re.compile(time_pattern)
    except re.error as err:
        raise InvalidParameterError(f"invalid --time-pattern {time_pattern!r}: {err}.") from err
    if "t" not in regex.groupindex:
        raise InvalidParameterError("--time-pattern needs a named group 't', e.g. 'frame_(?P<t>\\d+)us'.")
    scale = _TIME_UNITS[time_unit]

    def from_name(frame: SourceFrame) -> int:
        match = regex.search(frame.path.name)
        if match is None:
            raise ImageFolderError(frame.path, f"its name does not match --time-pattern {time_pattern!r}.")
        return start_ns + int(round(float(match.group("t")) * scale))

    return from_name


def ingest_source(
    source: str | os.PathLike[str],
    output: str | os.PathLike[str],
    *,
    fps: float | None = None,
    start_ns: int = 0,
    time_pattern: str | None = None,
    time_unit: str = "ns",
    skip_bad: bool = False,
    compression: str = FRAME_COMPRESSION,
    workers: int = 1,
    force: bool = False,
    show_progress: bool = False,
) -> IngestSummary:
    """Ingest a folder of images, a SER file or a video file into a new log at ``output``.

    Every frame must have the size and pixel type of the first; a file or frame that cannot be
    read or does not match stops the ingest with an error naming it, or with ``skip_bad=True``
    is skipped and listed in the summary. Timestamps must increase strictly. Each kind of note
    (lossy compression, colour converted to mono) is warned once per run and kept in the summary.

    Returns
    -------
    IngestSummary
    """
    path = Path(source)
    opened = _open_source(path, workers)
    stamp, timing = _stamper(opened, path, fps=fps, start_ns=start_ns, time_pattern=time_pattern,
                             time_unit=time_unit)
    summary = IngestSummary(output=Path(output), timing=timing)
    warned: set[type[Warning]] = set()
    if opened.lossy:
        _note(summary, warned, lossy_warning("JPEG" if len(opened.lossy) > 1 else opened.lossy[0]))
    if opened.kind == "folder":
        parameters: dict[str, Any] = {"folder": path.name, "fps": fps, "start_ns": start_ns,
                                      "time_pattern": time_pattern, "time_unit": time_unit, "skip_bad": skip_bad,
                                      "files": opened.total}
    else:
        parameters = {"file": path.name, "kind": opened.kind, "fps": fps, "start_ns": start_ns,
                      "skip_bad": skip_bad, "timing": timing}
    with LogWriter(output, compression=compression, workers=workers, force=force) as log:
        _write_frames(log, opened, stamp, summary, warned, skip_bad=skip_bad, show_progress=show_progress)
        if summary.frames == 0:
            raise ImageFolderError(path, "no frame could be ingested (every frame was skipped as bad)."
                                   if summary.skipped else "holds no frames.")
        provenance = Provenance(stage="ingest", version=__version__, parameters=parameters,
                                channels=[topics.IMAGE, topics.FRAME_INFO])
        log.add_metadata(PROVENANCE_METADATA_NAME, provenance.to_metadata())
    return summary


ingest_folder = ingest_source  # the earlier name, kept: it takes the same folders (and now files too)


def _write_frames(log: LogWriter, source: _Source, stamp: Callable[[SourceFrame], int], summary: IngestSummary,
                  warned: set[type[Warning]], *, skip_bad: bool, show_progress: bool) -> None:
    image_ch = log.add_channel(topics.IMAGE, protobuf_message_type("foxglove.RawImage"), monotonic=True)
    info_ch = log.add_channel(topics.FRAME_INFO, json_message_type("starlog.FrameInfo"), monotonic=True)
    reference: tuple[tuple[int, ...], np.dtype[Any]] | None = None
    last_time = -1
    for frame in progress(source.frames, total=source.total or None, description="ingest", enabled=show_progress):
        for caught in frame.caught:
            _note(summary, warned, caught.message)
        image = frame.image
        if image is not None:
            if reference is None:
                reference = (image.shape, image.dtype)
            elif (image.shape, image.dtype) != reference:
                frame.problem = (f"is {image.shape[1]}x{image.shape[0]} {image.dtype}, but the first frame is "
                                 f"{reference[0][1]}x{reference[0][0]} {reference[1]}; all frames must match.")
        if frame.problem is not None or image is None:
            if skip_bad:
                summary.skipped.append((frame.name, str(frame.problem)))
                continue
            raise frame.error()
        t = stamp(frame)
        if t <= last_time:
            hint = "" if summary.timing.endswith(("fps", "names")) else "; time the frames by rate with --fps"
            frame.problem = f"its timestamp {t} ns is not after the previous frame's ({last_time} ns){hint}."
            raise frame.error()
        last_time = t
        log.write(image_ch, log_time=t, data=encode_raw_image(image, log_time=t))
        encoding = "mono16" if image.dtype == np.uint16 else "mono8"
        info = {"frame": summary.frames, "width": int(image.shape[1]), "height": int(image.shape[0]),
                "encoding": encoding, "bit_depth": frame.bit_depth or (16 if encoding == "mono16" else 8),
                "source": frame.name}
        log.write(info_ch, log_time=t, data=encode_json(info))
        if summary.frames == 0:
            summary.first_log_time = t
            summary.width, summary.height, summary.encoding = info["width"], info["height"], encoding
        summary.last_log_time = t
        summary.frames += 1


def _note(summary: IngestSummary, warned: set[type[Warning]], message: Warning | str) -> None:
    """Warn once per kind of note in a run (the first message stands for the rest), and keep it."""
    category = type(message) if isinstance(message, Warning) else UserWarning
    if category in warned:
        return
    warned.add(category)
    summary.notes.append(str(message))
    warnings.warn(message, category, stacklevel=4)
