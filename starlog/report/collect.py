"""Gather what a report shows from a log, with memory bounded whatever the log's length.

Every part is optional: a log made by some stages only yields the parts those stages wrote,
and each absent part carries a sentence saying what is missing and which stage makes it.
Long channels are sampled (tracks: at most ``MAX_TRACK_SAMPLES`` frames; the brightest star's
native series: its first ``MAX_SERIES_SAMPLES`` samples).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from starlog.errors import StarlogError
from starlog.codecs.images import choose_image_topic
from starlog.facts import evidence_summaries, solve_summaries, trust_summary
from starlog.io.provenance import Provenance
from starlog.io.reader import ChannelSummary, LogReader
from starlog.topics import FRAME_INFO
from starlog.report.attitude import AttitudeSeries, read_attitude

__all__ = ["MAX_SERIES_SAMPLES", "MAX_TRACK_SAMPLES", "ErrorSeries", "FrameView", "ReportData", "TrackPaths",
           "collect_report_data"]

MAX_TRACK_SAMPLES = 1500
MAX_SERIES_SAMPLES = 65536
MAX_TRACKS_SHOWN = 24
_PREFERRED = ("GAUSSFIT", "STATIC")


@dataclass
class FrameView:
    """One frame and the centroids measured on it."""

    topic: str
    index: int | None
    log_time: int
    image: npt.NDArray[Any]
    points: list[tuple[float, float, str]]
    overlay_topic: str | None


@dataclass
class TrackPaths:
    """Confirmed tracks of one track channel, sampled every ``stride`` frames; times in s from the log's start."""

    topic: str
    stride: int
    tracks: dict[int, tuple[npt.NDArray[np.float64], npt.NDArray[np.float64], npt.NDArray[np.float64]]]
    total_tracks: int
    brightest: int | None


@dataclass
class ErrorSeries:
    """The brightest star's position error about its mean, its sampling rate and where f_d comes from."""

    source: str
    rate_hz: float
    t: npt.NDArray[np.float64]
    ex: npt.NDArray[np.float64]
    ey: npt.NDArray[np.float64]
    dominant_frequency: float | None
    dominant_from: str
    truncated: bool = False


@dataclass
class ReportData:
    """Everything a report shows; a ``None`` part comes with its reason in ``missing``."""

    path: Path
    channels: list[ChannelSummary]
    time_range: tuple[int, int]
    provenance: list[Provenance]
    frame: FrameView | None = None
    tracks: TrackPaths | None = None
    error: ErrorSeries | None = None
    records: list[dict[str, Any]] = field(default_factory=list)
    primary_decisions: str | None = None
    #: protocol -> (t s, before (n, 2), after (n, 2)) of the series at the rate the error figures show
    compensated: dict[str, tuple[npt.NDArray[np.float64], npt.NDArray[np.float64], npt.NDArray[np.float64]]] = \
        field(default_factory=dict)
    compensated_rate_hz: float | None = None
    missing: dict[str, str] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    #: the centroid stage's records of which method to trust (``starlog info``'s ``centroid_evidence``)
    evidence: list[dict[str, Any]] = field(default_factory=list)
    #: the method to trust from whichever evidence the log holds (``starlog info``'s ``trust``), None without centroids
    trust: dict[str, Any] | None = None
    #: the last ``starlog solve`` record's catalogue residual per centroid method (empty: none)
    sky: dict[str, dict[str, Any]] = field(default_factory=dict)
    #: ``starlog solve``'s attitude channels, by centroid method
    attitude: dict[str, AttitudeSeries] = field(default_factory=dict)

    @property
    def primary_records(self) -> list[dict[str, Any]]:
        """Decision records of the channel the figures show (all records are in :attr:`records`)."""
        return [r for r in self.records if r["_topic"] == self.primary_decisions]


def _pick(topics: list[str], prefix: str, method: str = _PREFERRED[0]) -> str | None:
    """The topic under ``prefix`` naming ``method`` (the trusted one, else GAUSSFIT) and STATIC if any, else
    ``method``, else the first."""
    found = sorted(t for t in topics if t.startswith(prefix))
    for wanted in ((method, _PREFERRED[1]), (method,)):
        for t in found:
            if set(wanted) <= set(t.split("/")):
                return t
    return found[0] if found else None


def _schema_topics(channels: list[ChannelSummary], schema: str) -> list[str]:
    return [c.topic for c in channels if c.schema_name == schema]


def _read_frame(log: LogReader, data: ReportData, track_topic: str | None) -> None:
    try:
        topic, _ = choose_image_topic(log.path, data.channels, None)
    except StarlogError as err:
        data.missing["frame"] = f"No frame to show: {err} Frames come from `starlog simulate` or `starlog ingest`."
        return
    channel = log.channel(topic)
    middle = channel.first_log_time + (channel.last_log_time - channel.first_log_time) // 2
    _, log_time, image = next(log.frames(topic, start=middle))
    index: int | None = None
    method = track_topic.split("/")[2] if track_topic else "GAUSSFIT"
    centroid_topics = _schema_topics(data.channels, "starlog.Centroids")
    overlay = f"/stars/centroids/{method}" if f"/stars/centroids/{method}" in centroid_topics else \
        _pick(centroid_topics, "/stars/centroids/")
    if overlay is None and "/stars/detections" in log.topics:
        overlay = "/stars/detections"
    points: list[tuple[float, float, str]] = []
    if overlay is not None:
        for message in log.messages(overlay, start=log_time, end=log_time + 1):
            for k, star in enumerate(message.payload["stars"]):
                points.append((float(star["x"]), float(star["y"]),
                               f"star {k}: x {star['x']:.3f}, y {star['y']:.3f} px, SNR {star.get('snr', 0):.0f}"))
            index = message.payload.get("frame", index)
    else:
        data.missing["overlay"] = ("This log has no centroids (/stars/centroids/<METHOD>) to draw on the frame: "
                                   "`starlog centroid` makes them.")
    if index is None and log.has_topic(FRAME_INFO):
        index = next((m.payload["frame"] for m in log.messages(FRAME_INFO, start=log_time, end=log_time + 1)), None)
    data.frame = FrameView(topic, index, log_time, np.array(image), points, overlay)


def _read_tracks(log: LogReader, data: ReportData, topic: str) -> None:
    count = log.channel(topic).message_count
    stride = max(1, math.ceil(count / MAX_TRACK_SAMPLES))
    t0 = data.time_range[0]
    rows: dict[int, list[tuple[float, float, float]]] = {}
    brightest = None
    for message in log.messages(topic, stride=stride):  # the frames not drawn are not decoded
        t = (message.log_time - t0) * 1e-9
        for row in message.payload["tracks"]:
            if row["brightest"]:
                brightest = row["track"]
            if row["confirmed"]:
                rows.setdefault(row["track"], []).append((t, row["x"], row["y"]))
    longest = sorted(rows, key=lambda i: (-len(rows[i]), i))[:MAX_TRACKS_SHOWN]
    if brightest is not None and brightest in rows and brightest not in longest:
        longest[-1] = brightest
    tracks = {i: tuple(np.asarray(v, float) for v in zip(*rows[i], strict=True)) for i in sorted(longest)}
    data.tracks = TrackPaths(topic, stride, tracks, len(rows), brightest)  # type: ignore[arg-type]


def _error_from_record(log: LogReader, record: dict[str, Any]) -> ErrorSeries:
    t, xy = [], []
    for message in log.messages(record["series_topic"]):
        t.append(message.log_time)
        xy.append((message.payload["x_before"], message.payload["y_before"]))
    pos = np.asarray(xy, float).reshape(-1, 2)
    err = pos - pos.mean(axis=0)
    times = (np.asarray(t, np.int64) - t[0]) * 1e-9 if t else np.zeros(0)
    return ErrorSeries(record["series_topic"], float(record.get("effective_rate_hz", record["rate_hz"])), times,
                       err[:, 0], err[:, 1], float(record["compensation"]["decomposition"]["dominant_frequency"]),
                       f"the error decomposition at {record['rate_hz']:g} Hz, protocol {record['protocol']}")


def _error_from_track(log: LogReader, topic: str) -> ErrorSeries | None:
    t, xy = [], []
    truncated = False
    for message in log.tables(topic):  # rows as arrays: no dict per star of every frame
        rows = message.rows
        brightest = np.flatnonzero(rows["brightest"]) if rows is not None else ()
        if not len(brightest):
            continue
        if len(t) == MAX_SERIES_SAMPLES:
            truncated = True
            break
        t.append(message.log_time)
        xy.append((float(rows["x"][brightest[0]]), float(rows["y"][brightest[0]])))
    if len(t) < 4:
        return None
    times = (np.asarray(t, np.int64) - t[0]) * 1e-9
    pos = np.asarray(xy, float)
    err = pos - pos.mean(axis=0)
    rate = (len(t) - 1) / times[-1] if times[-1] > 0 else 0.0
    return ErrorSeries(topic, rate, times, err[:, 0], err[:, 1], None, "", truncated)


def _read_compensated(log: LogReader, data: ReportData, shown: dict[str, Any]) -> None:
    """Before/after series of every protocol at the rate and motion mode of the ``shown`` record."""
    data.compensated_rate_hz = float(shown["rate_hz"])
    for record in data.primary_records:
        same = record["rate_hz"] == shown["rate_hz"] and record.get("motion", "keep") == shown.get("motion", "keep")
        if not same or not log.has_topic(record["series_topic"]):
            continue
        t, before, after = [], [], []
        for message in log.messages(record["series_topic"]):
            p = message.payload
            t.append((message.log_time - data.time_range[0]) * 1e-9)
            before.append((p["x_before"], p["y_before"]))
            after.append((p["x_after"], p["y_after"]))
        data.compensated[record["protocol"]] = (np.asarray(t, float), np.asarray(before, float).reshape(-1, 2),
                                                np.asarray(after, float).reshape(-1, 2))


def _read_records(log: LogReader, data: ReportData, method: str) -> None:
    decision_topics = _schema_topics(data.channels, "starlog.CompensationRecord")
    for topic in sorted(decision_topics):
        for message in log.messages(topic):
            data.records.append({**message.payload, "_topic": topic})
    data.primary_decisions = _pick(decision_topics, "/compensated/", method)


def _primary_record(records: list[dict[str, Any]]) -> dict[str, Any] | None:
    """The record whose series the error figures show: the paper protocol (else the first), highest rate, keep."""
    if not records:
        return None
    return max(records, key=lambda r: (r.get("motion", "keep") == "keep", r["protocol"] == "paper", r["rate_hz"]))


def collect_report_data(path: str | os.PathLike[str]) -> ReportData:
    """Read what :func:`~starlog.report.render_report` shows from the log at ``path``."""
    with LogReader(path) as log:
        channels = log.channels()
        data = ReportData(Path(path), channels, log.time_range(), log.provenance())
        data.trust = trust_summary(log).get("trust")
        method = (data.trust or {}).get("method") or _PREFERRED[0]
        _read_records(log, data, method)
        record = _primary_record(data.primary_records)
        track_topics = _schema_topics(channels, "starlog.Tracks")
        track_topic = record["track_topic"] if record and record.get("track_topic") in track_topics \
            else _pick(track_topics, "/track/", method)
        _read_frame(log, data, track_topic)
        if track_topic is None:
            data.missing["tracks"] = ("This log has no track channel (/track/<METHOD>/<MODEL>): "
                                      "`starlog track` makes one from the centroids.")
        else:
            _read_tracks(log, data, track_topic)
        if record is not None and log.has_topic(record["series_topic"]):
            data.error = _error_from_record(log, record)
            _read_compensated(log, data, record)
        elif track_topic is not None:
            data.error = _error_from_track(log, track_topic)
        if data.error is None:
            data.missing["error"] = ("The brightest star's error series needs a track channel "
                                     "(/track/<METHOD>/<MODEL>): `starlog track` makes it.")
        if not data.records:
            data.missing["decisions"] = ("This log has no compensation records (/compensated/<METHOD>/<MODEL>/decisions): "
                                         "`starlog compensate` makes them from a track channel.")
        data.notes.extend(log.notes)
        data.evidence = evidence_summaries(log).get("centroid_evidence", [])
        solved = [r for r in solve_summaries(log).get("solve", []) if "error" not in r]
        data.sky = solved[-1].get("sky_evidence") or {} if solved else {}
        data.attitude = read_attitude(log, channels, data.time_range[0])
    return data
