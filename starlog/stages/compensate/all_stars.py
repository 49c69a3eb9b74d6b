"""``compensate --stars all``: every confirmed track compensated with the brightest track's pipeline, each with its
own decomposition and strategy selection, on a common frame grid per rate; the stars of each (track channel, rate,
protocol, motion mode) are written per frame (:class:`StarFrames`: one ``starlog.CompensatedStars`` message
per frame, the rows :mod:`starlog.stages.solve` reads to solve the attitude before and after compensation), with one
decision record per star."""

from __future__ import annotations

from collections.abc import Iterator
from concurrent.futures import Executor
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from starlog.compensation import (
    CALIBRATION_FRACTION,
    MotionMode,
    ScoringProtocol,
    decimation_indices,
    enough_samples,
    sampled_rate,
)
from starlog.errors import InvalidInputError
from starlog.codecs import encode_json, json_message_type
from starlog import topics
from starlog.io.reader import ChannelSummary, LogReader
from starlog.replay.layer import StageOutput
from starlog.replay.progress import progress
from starlog.stages.compensate.jobs import Job, Plan, decision_record, evaluated
from starlog.stages.compensate.series import BrightestSeries, StarTruth, attach_reference, read_track_series
from starlog.stages.motion import estimate_track_motion

__all__ = ["StarFrames", "compensate_all_stars"]


@dataclass
class StarFrames:
    """The compensated samples of every star of one (track channel, rate, protocol, motion mode), by frame."""

    topic: str
    rate_hz: float
    protocol: str
    rows: dict[int, list[dict[str, Any]]] = field(default_factory=dict)
    frames: dict[int, int] = field(default_factory=dict)
    tracks: list[int] = field(default_factory=list)

    def add(self, track: int, log_time: npt.NDArray[np.int64], frame: npt.NDArray[np.int64],
            before: npt.NDArray[np.float64], after: npt.NDArray[np.float64], sigma: npt.NDArray[np.float64],
            flux: npt.NDArray[np.float64], scored: npt.NDArray[np.bool_]) -> None:
        """One star's decimated samples before and after compensation."""
        self.tracks.append(track)
        for k, t in enumerate(log_time.tolist()):
            self.frames[t] = int(frame[k])
            self.rows.setdefault(t, []).append({
                "track": track, "x_before": float(before[k, 0]), "y_before": float(before[k, 1]),
                "x_after": float(after[k, 0]), "y_after": float(after[k, 1]), "sigma": float(sigma[k]),
                "flux": float(flux[k]), "scored": bool(scored[k])})

    def write(self, out: StageOutput) -> int:
        """One ``starlog.CompensatedStars`` message per frame, in time order; returns the messages written."""
        if not self.rows:
            return 0
        channel = out.add_channel(self.topic, json_message_type("starlog.CompensatedStars"))
        for sample, t in enumerate(sorted(self.rows)):
            record = {"sample": sample, "frame": self.frames[t], "rate_hz": self.rate_hz, "protocol": self.protocol,
                      "stars": sorted(self.rows[t], key=lambda r: r["track"])}
            out.writer.write(channel, log_time=t, data=encode_json(record))
        return len(self.rows)


@dataclass
class _StarGroup:
    """The stars of one (track channel, rate, protocol, motion mode): their frames and what was left out."""

    frames: StarFrames
    decisions: str
    tracks: int
    left_out: dict[str, int] = field(default_factory=lambda: {"too short": 0, "without truth": 0,
                                                              "without motion": 0})
    figures: list[tuple[float, float, str]] = field(default_factory=list)

    def to_dict(self, written: int) -> dict[str, Any]:
        before = [f[0] for f in self.figures]
        after = [f[1] for f in self.figures]
        return {"topic": self.frames.topic, "rate_hz": self.frames.rate_hz, "protocol": self.frames.protocol,
                "tracks": self.tracks, "compensated": len(self.figures), "left_out": dict(self.left_out),
                "frames": written, "reference": self.figures[0][2] if self.figures else "",
                "median_rmse_before": float(np.median(before)) if before else float("nan"),
                "median_rmse_after": float(np.median(after)) if after else float("nan")}


def _star_series(log: LogReader, topic: str, plan: Plan,
                 truth_cache: dict[int, StarTruth]) -> tuple[list[BrightestSeries], npt.NDArray[np.int64]]:
    """Every confirmed track of ``topic`` (with its platform reference when the plan fits a motion: a track the
    fit has no measurement of keeps none) and the channel's frame times."""
    with_truth = any(p is not ScoringProtocol.PAPER for p in plan.protocols)
    all_series, frame_times = read_track_series(log, topic, truth_cache=truth_cache, with_truth=with_truth)
    if plan.fit is None:
        return all_series, frame_times
    data, est = estimate_track_motion(log, topic, model=plan.fit)
    out = []
    for series in all_series:
        try:
            out.append(attach_reference(series, data, est, topic))
        except InvalidInputError:
            out.append(series)
    return out, frame_times


def _star_jobs(log: LogReader, channels: list[ChannelSummary], plan: Plan,
               groups: dict[tuple[str, float, str, str], _StarGroup]) -> Iterator[Job]:
    """One job per confirmed track, channel, rate, protocol and motion mode, grouped in that order; each group
    added to ``groups`` (with the tracks it leaves out) before its first job. The frames of a rate are the
    channel's frames decimated from its first frame; a track keeps those after its own filter start-up."""
    truth_cache: dict[int, StarTruth] = {}
    fraction = plan.options.get("calibration_fraction", CALIBRATION_FRACTION)
    for channel in channels:
        all_series, frame_times = _star_series(log, channel.topic, plan, truth_cache)
        if not all_series:
            continue
        native = all_series[0].native_rate
        method, model = all_series[0].method, all_series[0].model
        for rate in plan.rates:
            grid_idx = decimation_indices(frame_times.size, native_rate=native, target_rate=rate)
            rate_hz = sampled_rate(grid_idx, native_rate=native)
            kept = []
            for series in all_series:
                start = series.burn_in(plan.burn_in).samples
                on_grid = np.isin(series.log_time, frame_times[grid_idx])
                kept.append(np.flatnonzero(on_grid & (np.arange(series.log_time.size) >= start)).astype(np.int64))
            for protocol in plan.protocols:
                if (float(rate), protocol) in plan.skipped:
                    continue
                for mode in plan.modes:
                    topic = topics.compensated_stars_topic(method, model, rate, protocol.value)
                    topic += "/separate" if mode is MotionMode.SEPARATE else ""
                    group = _StarGroup(StarFrames(topic, float(rate), protocol.value),
                                       topics.stars_decisions_topic(method, model), len(all_series))
                    groups[(channel.topic, float(rate), protocol.value, mode.value)] = group
                    for series, idx in zip(all_series, kept):
                        why = _left_out(series, idx, protocol, mode, fraction)
                        if why:
                            group.left_out[why] += 1
                            continue
                        yield Job(channel.topic, series, float(rate), idx, rate_hz, protocol, mode, plan.burn_in)


def _left_out(series: BrightestSeries, idx: npt.NDArray[np.int64], protocol: ScoringProtocol, mode: MotionMode,
              fraction: float) -> str:
    """Why a track is not compensated at these samples under ``protocol`` and ``mode`` ("" when it is)."""
    if not enough_samples(protocol, int(idx.size), calibration_fraction=fraction):
        return "too short"
    if protocol is ScoringProtocol.TRUTH and series.truth_series is None:
        return "without truth"
    if protocol is ScoringProtocol.RELATIVE or mode is MotionMode.SEPARATE:
        if series.displacement is None or not np.isfinite(series.displacement[idx]).all(axis=1).any():
            return "without motion"
    return ""


def compensate_all_stars(log: LogReader, out: StageOutput, channels: list[ChannelSummary], plan: Plan,
                          pool: Executor | None, *, window: int, show_progress: bool) -> list[dict[str, Any]]:
    """Compensate every confirmed track (:func:`_star_jobs`) and write each group's frames once it is complete,
    and a decision record per star; returns one summary entry per group."""
    groups: dict[tuple[str, float, str, str], _StarGroup] = {}
    decisions: dict[str, int] = {}
    written: dict[tuple[str, float, str, str], int] = {}
    current: tuple[str, float, str, str] | None = None
    done = evaluated(_star_jobs(log, channels, plan, groups), plan.options, pool, window=window)
    for job, evaluation in progress(done, total=None, description="compensate stars", enabled=show_progress,
                                    unit="star"):
        key = (job.track_topic, job.rate, job.protocol.value, job.motion.value)
        if current is not None and key != current:
            written[current] = groups[current].frames.write(out)
        current = key
        group = groups[key]
        series, idx = job.series, job.idx
        scored = np.arange(idx.size) >= evaluation.scored_start
        group.frames.add(series.track, series.log_time[idx], series.frame[idx], series.xy[idx],
                         evaluation.compensated, series.sigma[idx], series.flux[idx], scored)
        first = evaluation.figures[0]
        group.figures.append((first.rmse_before, first.rmse_after, first.reference))
        if group.decisions not in decisions:
            decisions[group.decisions] = out.add_channel(group.decisions, json_message_type("starlog.CompensationRecord"),
                                                         unordered=True)
        record = decision_record(job, evaluation, group.frames.topic)
        out.writer.write(decisions[group.decisions], log_time=int(series.log_time[idx[-1]]), data=encode_json(record))
    if current is not None:
        written[current] = groups[current].frames.write(out)
    return [group.to_dict(written.get(key, 0)) for key, group in groups.items()]
