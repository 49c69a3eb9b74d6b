"""The ``compensate`` stage: error decomposition, adaptive strategy selection and compensation (paper §2.2–2.5).

Reads one track channel (``/track/<METHOD>/<MODEL>``), takes the brightest star's track (the
paper's centroid sequence: its filtered ``x``, ``y``, flux and centroid ``sigma``), decimates
it to each requested rate (the frame nearest each ideal sample time,
:func:`starlog.compensation.decimation_indices`), and runs :func:`starlog.compensation.evaluate` under
each protocol (``paper``; ``truth`` when the log has ``/sim/truth``; ``leakfree``; ``relative`` when
asked for) and each motion mode (``keep``, the paper's; ``separate``: compensate the star's
residual from the platform motion fitted to the other stars, :mod:`starlog.platform_motion`). It writes

* ``/compensated/<METHOD>/<MODEL>/<RATE>Hz/<protocol>`` (starlog.CompensatedSample): one message
  per decimated sample at its frame's ``log_time``, the series before and after (``.../separate``
  under ``--motion separate``);
* ``/compensated/<METHOD>/<MODEL>/decisions`` (starlog.CompensationRecord): one message per (rate, protocol)
  with the error magnitudes, the dominant frequency, every strategy's score, the order run,
  RMSE before/after each pass, what was rolled back, and the protocol's RMSE figures.

With ``stars="all"`` (``--stars all``) it also compensates every confirmed track of the channel with the same
pipeline (each star its own decomposition and strategy selection) at the channel's frames decimated to each
rate, and writes ``/compensated/<METHOD>/<MODEL>/stars/<RATE>Hz/<protocol>`` (starlog.CompensatedStars): one
message per frame holding every star before and after, with its centroid sigma, which ``solve --compensated``
turns into the attitude before and after compensation; one decision record per star goes to
``/compensated/<METHOD>/<MODEL>/stars/decisions``. Tracks too short for a rate and protocol (or without the truth
or the motion it needs) are left out and counted in the summary.

The sequence of one track is held in memory (the method needs its global mean); at ≤ 100 Hz
that is a few MB per hour of recording.  The evaluations of one track (every rate × protocol)
are independent: with ``workers > 1`` they run in worker processes, and are written in the
same order, so the output does not depend on ``workers``.

Before anything is written, the stage checks that the track gives every rate and protocol the samples
it needs (:func:`track_shortfalls`): it refuses a track too short for any of them, naming each with the
log length it needs, or with ``skip_short`` leaves those out.

Its parts: :mod:`~starlog.stages.compensate.track_rows` (reading a track channel per track),
:mod:`~starlog.stages.compensate.series` (the series and their truth and reference),
:mod:`~starlog.stages.compensate.jobs` (the brightest track's evaluations and their records) and
:mod:`~starlog.stages.compensate.all_stars` (``stars="all"``).
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Sequence
from contextlib import nullcontext
from dataclasses import dataclass, field
from typing import Any

from starlog.compensation import (
    Evaluation,
    CALIBRATION_FRACTION,
    BurnInSetting,
    MotionMode,
    ScoringProtocol,
    Shortfall,
    burn_in_label,
    parse_burn_in,
    protocols_for,
    shortfalls,
)
from starlog.errors import InvalidInputError, InvalidParameterError
from starlog.codecs import json_message_type
from starlog import topics
from starlog.io.reader import ChannelSummary, LogReader
from starlog.replay.channels import select_track_channels
from starlog.replay.layer import StageOutput, extend_log
from starlog.replay.pool import process_pool
from starlog.replay.progress import progress
from starlog.replay.window import windowed
from starlog.stages.compensate.all_stars import compensate_all_stars
from starlog.stages.compensate.jobs import Job, Plan, evaluated, plan_jobs, write_evaluation
from starlog.stages.compensate.series import (
    BrightestSeries,
    evaluate_series,
    read_brightest_series,
    read_track_series,
    with_platform_reference,
)

__all__ = ["BrightestSeries", "CompensateSummary", "compensate_log", "decision_table", "evaluate_series",
           "parse_motion_modes", "parse_protocols", "read_brightest_series", "read_track_series",
           "select_track_channels", "too_short_message", "track_shortfalls", "with_platform_reference"]


def parse_motion_modes(spec: str | Sequence[str]) -> list[MotionMode]:
    """``"keep"``, ``"separate"``, ``"keep,separate"`` (or a list) → motion modes."""
    names = spec.split(",") if isinstance(spec, str) else list(spec)
    out = []
    for name in names:
        try:
            out.append(MotionMode(name.strip().lower()))
        except ValueError:
            raise InvalidParameterError(f"unknown motion mode {name!r}; choose keep, separate or both.") from None
    if not out:
        raise InvalidParameterError("give a motion mode: keep, separate or keep,separate.")
    return list(dict.fromkeys(out))


@dataclass
class CompensateSummary:
    """Every evaluation :func:`compensate_log` ran: ``records[i]`` is one decision record; ``skipped``: the rates
    and protocols the track was too short for (with ``skip_short``)."""

    records: list[dict[str, Any]] = field(default_factory=list)
    skipped: list[Shortfall] = field(default_factory=list)
    stars: list[dict[str, Any]] = field(default_factory=list)
    """With ``stars="all"``: per all-star channel, the tracks compensated and those left out, and why."""

    def to_dict(self) -> dict[str, Any]:
        out = {"records": self.records, "skipped": [s.to_dict() for s in self.skipped]}
        return out | ({"stars": self.stars} if self.stars else {})

    def lines(self) -> list[str]:
        """What ``starlog compensate`` prints: the decision table, then the all-star lines (``stars="all"``)."""
        return [*decision_table(self.records).splitlines(), *self.star_lines()]

    def star_lines(self) -> list[str]:
        """One line per all-star channel: tracks compensated, left out, frames and the median RMSE."""
        lines = []
        for g in self.stars:
            left = ", ".join(f"{n} {why}" for why, n in g["left_out"].items() if n)
            lines.append(f"{g['topic']}: {g['compensated']} of {g['tracks']} confirmed tracks compensated"
                         + (f" ({left})" if left else "") + f", {g['frames']} frames; median RMSE px "
                         f"{g['median_rmse_before']:.4f} -> {g['median_rmse_after']:.4f} ({g['reference']})")
        return lines


def decision_table(records: list[dict[str, Any]]) -> str:
    """Readable table of compensation decision records: one row per protocol figure, the passes run on the first."""
    motion = any(r.get("motion", "keep") != "keep" for r in records)
    lines = [f"{'method':<9} {'model':<17} {'Hz':>5} {'protocol':<9} " + ("motion   " if motion else "")
             + f"{'reference':<13} {'RMSE before':>11} {'after':>8} {'gain':>6}  passes (x = rolled back)"]
    for r in records:
        for k, fig in enumerate(r["figures"]):
            passes = " > ".join(p["strategy"] + ("" if p["kept"] else " x") for p in r["compensation"]["passes"])
            head = (f"{r['method']:<9} {r['model']:<17} {r['rate_hz']:>5g} {r['protocol']:<9}" if k == 0
                    else " " * 43)
            if motion:
                head += f" {r.get('motion', 'keep'):<8}" if k == 0 else " " * 9
            lines.append(f"{head} {fig['reference']:<13} {fig['rmse_before']:>11.4f} {fig['rmse_after']:>8.4f} "
                         f"{100 * fig['effective']:>5.1f}%  {passes if k == 0 else ''}")
    return "\n".join(lines)


def parse_protocols(spec: str | Sequence[str], *, has_truth: bool) -> list[ScoringProtocol]:
    """``"all"`` (paper, truth when simulated, leakfree) or names (also ``relative``) → protocols."""
    names = spec.split(",") if isinstance(spec, str) else list(spec)
    if [n.strip().lower() for n in names] == ["all"]:
        return list(protocols_for(has_truth=has_truth))
    out = []
    for name in names:
        try:
            out.append(ScoringProtocol(name.strip().lower()))
        except ValueError:
            raise InvalidParameterError(
                f"unknown protocol {name!r}; choose paper, truth, leakfree, relative or all.") from None
    if ScoringProtocol.TRUTH in out and not has_truth:
        raise InvalidInputError("the truth protocol needs /sim/truth: this log was not simulated.")
    return list(dict.fromkeys(out))


@windowed(lambda log, options: select_track_channels(log, options.get("track"))[0].topic)
def compensate_log(
    input_path: str | os.PathLike[str],
    output_path: str | os.PathLike[str],
    *,
    rates: Sequence[float],
    track: str | Sequence[str] | None = None,
    protocols: str | Sequence[str] = "all",
    options: dict[str, Any] | None = None,
    motion: str | Sequence[str] = "keep",
    motion_fit: str = "rigid",
    skip_burn_in: bool = True,
    burn_in: BurnInSetting = "auto",
    skip_short: bool = False,
    stars: str = "brightest",
    workers: int = 1,
    show_progress: bool = False,
    force: bool = False,
    flatten: bool = False,
    compression: str = "zstd",
) -> CompensateSummary:
    """Decompose, select and compensate the brightest track at each rate under each protocol.

    Parameters
    ----------
    rates : sequence of float
        Target rates in Hz (nearest-frame equidistant decimation from the frame rate).
    track : str or sequence of str, optional
        Track channel(s) (``/track/GAUSSFIT/STATIC`` or ``GAUSSFIT/STATIC``), or ``"all"``;
        default: the only one.
    protocols : str or sequence of str
        ``"all"`` (paper, truth when simulated, leakfree) or any of ``paper``, ``truth``,
        ``leakfree``, ``relative``.
    options : dict, optional
        Keyword options of :func:`starlog.compensation.evaluate` (accuracy_source,
        calibration_fraction, top_k, rollback_threshold, leakfree_reference, select_positive).
        ``A`` of eq. 10 is the centroid's own ``sigma`` unless ``accuracy_source`` is given.
    motion : str or sequence of str
        ``keep`` (default, the paper's), ``separate``, or both: what the strategies compensate.
    motion_fit : str
        Platform motion fitted to the other stars for ``relative`` and ``separate``:
        ``translation``, ``rigid`` (default) or ``similarity``.
    skip_burn_in : bool
        Start each decimated series after the filter's start-up
        (:meth:`BrightestSeries.burn_in`; default), or at the first frame.
    burn_in : str or float
        What the start-up is when ``skip_burn_in``: ``"auto"`` (the filter's variance rule,
        default), ``"off"`` (nothing skipped) or a number of seconds; recorded in every
        decision record.
    skip_short : bool
        Leave out the rates and protocols the track is too short for (:func:`starlog.compensation.shortfalls`,
        listed in the summary's ``skipped`` and the stage's parameters) instead of refusing the log, before
        anything is written.
    stars : str
        ``"brightest"`` (default): the brightest track alone. ``"all"``: also every confirmed track, each with
        the same pipeline and its own strategy selection, on a common frame grid per rate, written per frame on
        ``/compensated/<METHOD>/<MODEL>/stars/<RATE>Hz/<protocol>`` (what ``solve`` reads to solve the attitude
        before and after compensation), with one decision record per star on ``.../stars/decisions``; tracks
        too short for a rate and protocol are left out and counted (:attr:`CompensateSummary.stars`).
    workers : int
        Processes for the evaluations (1: in this process) and threads for chunk compression;
        the output does not depend on it.
    show_progress : bool
        A progress bar over the evaluations (stderr).
    start, end : str or int, optional
        Only the range ``start <= log_time < end`` (ns, ``"12.5s"`` or ``"frame:N"`` of the first
        track channel; :mod:`starlog.io.timerange`): the layer holds its channels for that range.
    flatten : bool
        Write the whole chain as one self-contained file instead of a layer on the input.
    """
    _check_arguments(rates, workers, stars)
    options = dict(options or {})
    setting = parse_burn_in(burn_in) if skip_burn_in else "off"
    summary = CompensateSummary()
    with LogReader(input_path) as log:
        channels = select_track_channels(log, track)
        chosen = parse_protocols(protocols, has_truth=log.has_topic(topics.TRUTH))
        summary.skipped = _check_length(log, channels, rates, chosen, options, setting, skip_short=skip_short)
        modes = parse_motion_modes(motion)
        fit = motion_fit if (ScoringProtocol.RELATIVE in chosen or MotionMode.SEPARATE in modes) else None
        plan = Plan(rates=list(rates), protocols=list(chosen), modes=modes, fit=fit, burn_in=setting,
                    skipped={(s.rate_hz, s.protocol) for s in summary.skipped}, options=options)
        parameters = _parameters(plan, channels, summary.skipped, skip_burn_in=skip_burn_in, stars=stars)
        n_jobs = len(channels) * sum((float(r), p) not in plan.skipped for r in rates for p in chosen) * len(modes)
        parallel = workers > 1 and (n_jobs > 1 or stars == "all")
        with extend_log(log, output_path, stage="compensate", parameters=parameters, force=force, flatten=flatten,
                        compression=compression) as (_, out), \
                (process_pool(workers, preload=[plan_jobs.__module__]) if parallel else nullcontext()) as pool:
            done = evaluated(plan_jobs(log, channels, plan), options, pool, window=2 * workers)
            summary.records = _write_brightest(out, done, total=n_jobs, show_progress=show_progress)
            if stars == "all":
                summary.stars = compensate_all_stars(log, out, channels, plan, pool, window=2 * workers,
                                                     show_progress=show_progress)
    return summary


def _check_arguments(rates: Sequence[float], workers: int, stars: str) -> None:
    if not rates:
        raise InvalidParameterError("give at least one rate (--rate HZ).")
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise InvalidParameterError(f"workers must be an integer >= 1, got {workers!r}.")
    if stars not in ("brightest", "all"):
        raise InvalidParameterError(f"stars must be 'brightest' or 'all', got {stars!r}.")


def _check_length(log: LogReader, channels: list[ChannelSummary], rates: Sequence[float],
                  chosen: list[ScoringProtocol], options: dict[str, Any], setting: BurnInSetting, *,
                  skip_short: bool) -> list[Shortfall]:
    """The rates and protocols the track is too short for (:func:`track_shortfalls`), left out with
    ``skip_short`` while some are left; else an error naming each."""
    short = track_shortfalls(log, channels, rates, chosen, options=options, burn_in=setting)
    skipped = {(s.rate_hz, s.protocol) for s in short}
    pairs_left = sum((float(r), p) not in skipped for r in rates for p in chosen)
    if short and (not skip_short or not pairs_left):
        raise InvalidParameterError(too_short_message(
            f"{channels[0].topic} ({_length(channels[0])})", short, "Give a longer log or range, higher --rate or "
            "other --protocol values" + (", or --skip-short to leave these out." if pairs_left else ".")))
    return short


def _parameters(plan: Plan, channels: list[ChannelSummary], short: list[Shortfall], *, skip_burn_in: bool,
                stars: str) -> dict[str, Any]:
    """What the stage's provenance records."""
    parameters: dict[str, Any] = {"tracks": [c.topic for c in channels], "rates": [float(r) for r in plan.rates],
                                  "protocols": [p.value for p in plan.protocols], "options": plan.options,
                                  "skip_burn_in": skip_burn_in, "burn_in": burn_in_label(plan.burn_in)}
    if short:
        parameters["skipped"] = [s.to_dict() for s in short]
    if plan.modes != [MotionMode.KEEP] or plan.fit is not None:
        parameters |= {"motion": [m.value for m in plan.modes], "motion_fit": plan.fit}
    if stars == "all":
        parameters["stars"] = "all"
    return parameters


def _write_brightest(out: StageOutput, done: Iterable[tuple[Job, Evaluation]], *, total: int,
                     show_progress: bool) -> list[dict[str, Any]]:
    """Write each evaluation of the brightest track, a decision channel per track channel; returns the records."""
    decisions: dict[str, int] = {}
    records = []
    for job, evaluation in progress(done, total=total, description="compensate", enabled=show_progress, unit="run"):
        if job.track_topic not in decisions:
            decisions[job.track_topic] = out.add_channel(
                topics.decisions_topic(job.series.method, job.series.model),
                json_message_type("starlog.CompensationRecord"), unordered=True)
        records.append(write_evaluation(out, decisions[job.track_topic], job, evaluation))
    return records


def track_shortfalls(log: LogReader, channels: Sequence[ChannelSummary], rates: Sequence[float],
                     protocols: Sequence[ScoringProtocol], *, options: dict[str, Any],
                     burn_in: BurnInSetting = "auto") -> list[Shortfall]:
    """The rates and protocols the shortest of ``channels`` gives too few samples for
    (:func:`starlog.compensation.shortfalls`), at the frame rate :func:`read_brightest_series` uses."""
    image_rate = log.channel(topics.IMAGE).rate_hz if log.has_topic(topics.IMAGE) else 0.0
    shortest = min(channels, key=lambda c: c.message_count)
    native = image_rate if image_rate > 0 else shortest.rate_hz
    fraction = options.get("calibration_fraction", CALIBRATION_FRACTION)
    return shortfalls(shortest.message_count, native_rate=native, rates=rates, protocols=protocols,
                      calibration_fraction=fraction, burn_in=burn_in)


def too_short_message(what: str, short: Sequence[Shortfall], ways_out: str) -> str:
    """The error for a channel too short for some rates and protocols: ``what`` (the channel), one line per
    shortfall, ``ways_out``."""
    lines = "".join(f"\n  {s.describe()}" for s in short)
    return (f"{what} is too short for {len(short)} of the rates and protocols asked for (the samples left after "
            f"the longest filter start-up the burn-in allows):{lines}\n{ways_out}")


def _length(channel: ChannelSummary) -> str:
    """``300 messages, 1.00 s``: a channel's length."""
    return f"{channel.message_count} messages, {(channel.last_log_time - channel.first_log_time) * 1e-9:.2f} s"


