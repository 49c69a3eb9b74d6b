"""Reading a track channel track by track, and the centroid channel's sigmas, for the ``compensate`` stage.

:func:`collect_track_rows` reads the rows of a track channel per track (the brightest track alone, or every
track), :func:`centroid_sigmas` the centroid channel's sigmas once for many tracks; both read the channels as
tables (:meth:`~starlog.io.reader.LogReader.tables`: a structured array per frame, no dict per star).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from starlog import topics
from starlog.io.reader import LogReader
from starlog.replay.channels import check_messages_read

__all__ = ["CentroidSigmas", "TrackRows", "centroid_sigmas", "collect_track_rows"]

#: log_time → (x, y) of a centroid → its sigma (the first centroid at that position).
CentroidSigmas = dict[int, dict[tuple[float, float], float]]


@dataclass
class TrackRows:
    """One track's rows in frame order: time, frame, filtered position, flux, the associated measurement
    ``(meas_x, meas_y, meas_sigma, measured or gated)`` and the posterior position variance."""

    times: list[int] = field(default_factory=list)
    frames: list[int] = field(default_factory=list)
    xy: list[tuple[float, float]] = field(default_factory=list)
    flux: list[float] = field(default_factory=list)
    meas: list[tuple[float, float, float, bool]] = field(default_factory=list)
    var: list[float] = field(default_factory=list)
    confirmed: bool = False


def collect_track_rows(log: LogReader, topic: str,
                       keep: Callable[[npt.NDArray[np.void]], npt.NDArray[np.bool_]]
                       ) -> tuple[str, str, dict[int, TrackRows], npt.NDArray[np.int64]]:
    """The method, the motion model, the rows ``keep`` accepts (a mask of a frame's rows) of every track of
    ``topic`` and the times of the channel's messages (one pass)."""
    method = model = ""
    kept: list[npt.NDArray[np.void]] = []
    when: list[npt.NDArray[np.int64]] = []
    times: list[int] = []
    for message in log.tables(topic):
        times.append(message.log_time)
        method, model = message.header["method"], message.header["model"]
        if message.rows is None or not message.rows.size:
            continue
        rows = message.rows[keep(message.rows)]
        kept.append(rows)
        when.append(np.repeat(np.array([[message.log_time, message.header["frame"]]], dtype=np.int64), rows.size, 0))
    check_messages_read(log, topic, len(times))
    tracks: dict[int, TrackRows] = {}
    if kept:
        rows, at = np.concatenate(kept), np.concatenate(when)
        order = np.argsort(rows["track"], kind="stable")
        ids, starts = np.unique(rows["track"][order], return_index=True)
        for track, chunk in zip(ids.tolist(), np.split(order, starts[1:])):
            tracks[track] = _track_rows(rows[chunk], at[chunk])
    return method, model, tracks, np.asarray(times, dtype=np.int64)


def _track_rows(rows: npt.NDArray[np.void], at: npt.NDArray[np.int64]) -> TrackRows:
    """One track's rows (in frame order) and their ``(log_time, frame)``."""
    return TrackRows(times=at[:, 0].tolist(), frames=at[:, 1].tolist(),
                     xy=list(zip(rows["x"].tolist(), rows["y"].tolist())), flux=rows["flux"].tolist(),
                     meas=list(zip(rows["meas_x"].tolist(), rows["meas_y"].tolist(), rows["meas_sigma"].tolist(),
                                   (rows["measured"] | rows["gated"]).tolist())),
                     var=(0.5 * (rows["cov_xx"] + rows["cov_yy"])).tolist(), confirmed=bool(rows["confirmed"].any()))


def centroid_sigmas(log: LogReader, method: str, *,
                    only: dict[int, set[tuple[float, float]]] | None = None) -> CentroidSigmas:
    """The sigma of every centroid of ``/stars/centroids/<METHOD>`` by frame time and position (empty without
    that channel); ``only``: those frame times, and in each only the centroids at those positions (one track's
    measurements: memory then grows with the track, not with the stars of every frame)."""
    topic = topics.centroid_topic(method)
    out: CentroidSigmas = {}
    if not log.has_topic(topic):
        return out
    for message in log.tables(topic):
        wanted = None if only is None else only.get(message.log_time)
        if only is not None and wanted is None:
            continue
        frame = out.setdefault(message.log_time, {})
        rows = message.rows if message.rows is not None else np.zeros(0, dtype=[("x", "f8"), ("y", "f8"),
                                                                               ("sigma", "f8")])
        for x, y, sigma in zip(rows["x"].tolist(), rows["y"].tolist(), rows["sigma"].tolist()):
            if wanted is None or (x, y) in wanted:
                frame.setdefault((x, y), sigma)
    return out
