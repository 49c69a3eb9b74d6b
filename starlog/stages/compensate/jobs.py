"""The ``compensate`` stage's evaluations of the brightest track: one :class:`Job` per (track channel, rate,
protocol, motion mode), run in this process or in worker processes and written in job order, each with its
samples before and after and its decision record."""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable, Iterator
from concurrent.futures import Executor
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from starlog.compensation import (
    RATE_TOLERANCE,
    BurnInSetting,
    Evaluation,
    MotionMode,
    ScoringProtocol,
    burn_in_label,
    sampled_rate,
)
from starlog.errors import InvalidInputError, InvalidParameterError
from starlog.codecs import encode_json, json_message_type
from starlog import topics
from starlog.io.reader import ChannelSummary, LogReader
from starlog.replay.layer import StageOutput
from starlog.replay.pool import ordered_map
from starlog.stages.compensate.series import (
    BrightestSeries,
    StarTruth,
    evaluate_series,
    read_brightest_series,
    with_platform_reference,
)

__all__ = ["Job", "Plan", "decision_record", "evaluate_job", "evaluated", "plan_jobs", "write_evaluation"]


@dataclass
class Plan:
    """What the stage runs, for the brightest track and (``--stars all``) every confirmed track: its rates,
    protocols, motion modes, motion fit, burn-in setting, the (rate, protocol) pairs left out for the whole log,
    and evaluate's options."""

    rates: list[float]
    protocols: list[ScoringProtocol]
    modes: list[MotionMode]
    fit: str | None
    burn_in: BurnInSetting
    skipped: set[tuple[float, ScoringProtocol]]
    options: dict[str, Any]


@dataclass(frozen=True)
class Job:
    """One evaluation: the brightest series of ``track_topic`` at one rate, under one protocol and motion mode."""

    track_topic: str
    series: BrightestSeries
    rate: float
    idx: npt.NDArray[np.int64]
    rate_hz: float
    protocol: ScoringProtocol
    motion: MotionMode = MotionMode.KEEP
    burn_in: BurnInSetting = "auto"


def plan_jobs(log: LogReader, channels: list[ChannelSummary], plan: Plan) -> Iterator[Job]:
    """Every (track channel, rate, protocol, motion mode) of the brightest track but the plan's ``skipped``
    (rate, protocol) pairs, in output order; each channel's series read when reached (with its platform reference
    when the plan fits a motion)."""
    truth_cache: dict[int, StarTruth] = {}
    with_truth = any(p is not ScoringProtocol.PAPER for p in plan.protocols)
    for channel in channels:
        series = read_brightest_series(log, channel.topic, truth_cache=truth_cache, with_truth=with_truth)
        if plan.fit is not None:
            series = with_platform_reference(log, series, channel.topic, fit=plan.fit)
        jobs = []
        for rate in plan.rates:
            if not rate > 0 or rate > series.native_rate * (1 + RATE_TOLERANCE):
                raise InvalidParameterError(
                    f"rate {rate} Hz must be > 0 and at most the frame rate {series.native_rate:g} Hz.")
            idx = series.indices(rate, burn_in=plan.burn_in)
            rate_hz = sampled_rate(idx, native_rate=series.native_rate)
            jobs += [Job(channel.topic, series, float(rate), idx, rate_hz, p, m, plan.burn_in) for p in plan.protocols
                     if (float(rate), p) not in plan.skipped for m in plan.modes]
        yield from jobs


def evaluate_job(job: Job, options: dict[str, Any]) -> Evaluation:
    """Run one job (in a worker process when parallel); errors say which job failed."""
    try:
        return evaluate_series(job.series, job.idx, rate_hz=job.rate_hz, protocol=job.protocol, motion=job.motion,
                               **options)
    except (InvalidInputError, InvalidParameterError) as err:
        raise type(err)(f"{job.track_topic} at {job.rate:g} Hz ({job.idx.size} samples), protocol "
                        f"{job.protocol.value}, motion {job.motion.value}: {err}{_ways_out(job)}") from err


def _ways_out(job: Job) -> str:
    """What a user of the command can do when a protocol lacks samples: the options that give more."""
    others = ",".join(p.value for p in ScoringProtocol if p is not job.protocol)
    calibration = " or --set calibration_fraction=F (the leak-free calibration's share)" \
        if job.protocol is ScoringProtocol.LEAKFREE else ""
    return (f" With the command: give a longer log or range, a higher --rate, --protocol {others}{calibration}.")


def evaluated(jobs: Iterable[Job], options: dict[str, Any], pool: Executor | None, *,
               window: int) -> Iterator[tuple[Job, Evaluation]]:
    """Each job with its evaluation, in job order; on ``pool`` when given."""
    if pool is None:
        for job in jobs:
            yield job, evaluate_job(job, options)
        return
    submitted: deque[Job] = deque()

    def feed() -> Iterator[tuple[Job, dict[str, Any]]]:
        for job in jobs:
            submitted.append(job)  # ordered_map yields results in this same order
            yield job, options

    for evaluation in ordered_map(pool, evaluate_job, feed(), window=window):
        yield submitted.popleft(), evaluation


def write_evaluation(out: StageOutput, decision_channel: int, job: Job, evaluation: Evaluation) -> dict[str, Any]:
    """Write the series before/after and the decision record of one job; return the record."""
    series, idx = job.series, job.idx
    topic = topics.compensated_topic(series.method, series.model, job.rate, job.protocol.value)
    if job.motion is MotionMode.SEPARATE:
        topic += "/separate"
    sample_ch = out.add_channel(topic, json_message_type("starlog.CompensatedSample"))
    after = evaluation.compensated
    for k, i in enumerate(idx):
        sample = {"sample": k, "frame": int(series.frame[i]), "track": series.track,
                  "x_before": float(series.xy[i, 0]), "y_before": float(series.xy[i, 1]),
                  "x_after": float(after[k, 0]), "y_after": float(after[k, 1]),
                  "scored": bool(k >= evaluation.scored_start)}
        out.writer.write(sample_ch, log_time=int(series.log_time[i]), data=encode_json(sample))
    record = decision_record(job, evaluation, topic)
    out.writer.write(decision_channel, log_time=int(series.log_time[idx[-1]]), data=encode_json(record))
    return record


def decision_record(job: Job, evaluation: Evaluation, topic: str) -> dict[str, Any]:
    """The decision record of one job whose series went to ``topic``."""
    series, idx = job.series, job.idx
    return {
        "method": series.method, "model": series.model, "track": series.track,
        "track_topic": job.track_topic, "series_topic": topic, "rate_hz": job.rate,
        "effective_rate_hz": job.rate_hz, "native_rate_hz": series.native_rate,
        "n_samples": int(idx.size), "first_log_time": int(series.log_time[idx[0]]),
        "last_log_time": int(series.log_time[idx[-1]]),
        "burn_in": {**series.burn_in(job.burn_in).to_dict(), "skipped": bool(idx[0] > 0),
                    "setting": burn_in_label(job.burn_in)},
        "accuracy_from": series.sigma_source if evaluation.result.accuracy_source == "sigma" else "none (A = 0)",
        **evaluation.to_dict(),
    }


