"""The ``track`` stage: UKF tracks of every star from one centroid channel, one channel per motion model.

Reads ``/stars/centroids/<METHOD>`` and writes ``/track/<METHOD>/<MODEL>`` (``starlog.Tracks``,
one message per frame). The brightest star's track — the paper's centroid sequence — is
marked in every row (``brightest``). Finding it needs the whole log (it is the confirmed track
with the most measurements and the highest mean flux, see
:meth:`starlog.track.StarTracker.brightest_track`), so the centroid channel, which is small, is
read twice: once to find it, once to write. Memory does not grow with the log's length.
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from starlog.errors import InvalidParameterError
from starlog.io import encode_json, json_message_type, topics
from starlog.io.reader import LogReader
from starlog.stages._progress import progress
from starlog.stages._stage import extend_log
from starlog.track import MotionModel, MotionModelConfig, NoTrackError, StarTracker, TrackerConfig

__all__ = ["TrackSummary", "track_log", "parse_models"]


def parse_models(spec: str | Sequence[str]) -> list[MotionModel]:
    """``"all"``, ``"STATIC,CONSTANT_VELOCITY"`` or a list of names → motion models, in the paper's order."""
    names = spec.split(",") if isinstance(spec, str) else list(spec)
    if [n.strip().lower() for n in names] == ["all"]:
        return list(MotionModel)
    models = [MotionModel.parse(n) for n in names if n.strip()]
    if not models:
        raise InvalidParameterError("give at least one motion model (or 'all').")
    return list(dict.fromkeys(models))


@dataclass
class TrackSummary:
    """What :func:`track_log` wrote: per model, the brightest track and the track statistics."""

    method: str
    frames: int = 0
    brightest: dict[str, int] = field(default_factory=dict)
    tracks: dict[str, int] = field(default_factory=dict)
    confirmed: dict[str, int] = field(default_factory=dict)
    gated: dict[str, int] = field(default_factory=dict)
    mean_nis: dict[str, float] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return {
            "method": self.method,
            "frames": self.frames,
            "models": {
                model: {
                    "brightest_track": self.brightest[model],
                    "tracks": self.tracks[model],
                    "confirmed_tracks": self.confirmed[model],
                    "gated_measurements": self.gated[model],
                    "mean_nis": self.mean_nis[model],
                }
                for model in self.brightest
            },
        }


def _centroid_frames(log: LogReader, topic: str) -> Iterator[tuple[int, int, np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    for message in log.messages(topic):
        stars = message.payload["stars"]
        x = np.array([s["x"] for s in stars], dtype=np.float64)
        y = np.array([s["y"] for s in stars], dtype=np.float64)
        sigma = np.array([s["sigma"] for s in stars], dtype=np.float64)
        flux = np.array([s["flux"] for s in stars], dtype=np.float64)
        yield message.payload["frame"], message.log_time, x, y, sigma, flux


def track_log(
    input_path: str | os.PathLike[str],
    output_path: str | os.PathLike[str],
    *,
    method: str,
    models: str | Sequence[str] = "all",
    tracker: dict[str, Any] | None = None,
    motion: dict[str, Any] | None = None,
    force: bool = False,
    compression: str = "zstd",
    show_progress: bool = False,
) -> TrackSummary:
    """Track every star of ``/stars/centroids/<method>`` under each motion model.

    Parameters
    ----------
    method : str
        Centroid method whose channel is tracked (e.g. ``"GAUSSFIT"``).
    models : str or sequence of str
        ``"all"`` or motion model names.
    tracker : dict, optional
        :class:`~starlog.track.TrackerConfig` fields (gate_probability, association_radius,
        confirm_hits, max_missed, sigma_floor).
    motion : dict, optional
        :class:`~starlog.track.MotionModelConfig` fields (process-noise intensities).
    """
    chosen = parse_models(models)
    options = dict(tracker or {})
    try:
        motion_config = MotionModelConfig(**(motion or {}))
        configs = {m: TrackerConfig(model=m, motion=motion_config, **options) for m in chosen}
    except TypeError as err:
        raise InvalidParameterError(f"unknown tracker option: {err}.") from err
    method = method.upper()
    source = topics.centroid_topic(method)
    parameters = {"method": method, "models": [m.value for m in chosen], "tracker": options,
                  "motion": dict(motion or {})}
    summary = TrackSummary(method=method)
    with extend_log(input_path, output_path, stage="track", parameters=parameters, force=force,
                    compression=compression) as (log, out):
        n_frames = log.channel(source).message_count
        # pass 1: which track is the brightest star's, per model
        trackers = {m: StarTracker(configs[m]) for m in chosen}
        frames = _centroid_frames(log, source)
        for _, t, x, y, sigma, flux in progress(frames, total=n_frames, description="track (pass 1/2)",
                                                enabled=show_progress):
            for tr in trackers.values():
                tr.update(t, x, y, sigma, flux)
        brightest = {}
        for m, tr in trackers.items():
            try:
                brightest[m] = tr.brightest_track()
            except NoTrackError as err:
                raise NoTrackError(
                    f"{m.value} on {source}: {err} If the stars move more than their centroid sigma "
                    "(platform jitter), the gate rejects them: raise the measurement-noise floor, e.g. "
                    "--set sigma_floor=0.05 (px), or use a model with process noise.") from err
        # pass 2: the same (deterministic) tracking, written out
        channels = {m: out.add_channel(topics.track_topic(method, m.value), json_message_type("starlog.Tracks"))
                    for m in chosen}
        trackers = {m: StarTracker(configs[m]) for m in chosen}
        nis_sum = dict.fromkeys(chosen, 0.0)
        nis_n = dict.fromkeys(chosen, 0)
        frames = _centroid_frames(log, source)
        for frame, t, x, y, sigma, flux in progress(frames, total=n_frames, description="track (pass 2/2)",
                                                    enabled=show_progress):
            for m, tr in trackers.items():
                rows = tr.update(t, x, y, sigma, flux)
                names = rows.dtype.names
                assert names is not None
                applied = rows["measured"] & (rows["age"] > 0)
                nis_sum[m] += float(rows["nis"][applied].sum())
                nis_n[m] += int(applied.sum())
                tracks = [dict(zip(names, values)) | {"brightest": values[0] == brightest[m]}
                          for values in rows.tolist()]
                message = {"frame": frame, "method": method, "model": m.value, "tracks": tracks}
                out.writer.write(channels[m], log_time=t, data=encode_json(message))
            summary.frames += 1
        for m, tr in trackers.items():
            stats = tr.track_stats()
            summary.brightest[m.value] = brightest[m]
            summary.tracks[m.value] = int(stats.size)
            summary.confirmed[m.value] = int(stats["confirmed"].sum())
            summary.gated[m.value] = int(stats["gated"].sum())
            summary.mean_nis[m.value] = nis_sum[m] / nis_n[m] if nis_n[m] else 0.0
    return summary
