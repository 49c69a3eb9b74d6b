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

One module of over 500 lines: checking the track's length, reading the brightest series, the
evaluations and the decision records are the stage's steps, each short, and the summary the command
prints; the all-star run reuses those same steps (its jobs, evaluations and records), so it lives beside them.
"""

from __future__ import annotations

import os
from collections import deque
from collections.abc import Iterable, Iterator, Sequence
from concurrent.futures import Executor
from contextlib import nullcontext
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from starlog.compensation import (
    CALIBRATION_FRACTION,
    RATE_TOLERANCE,
    BurnIn,
    Evaluation,
    MotionMode,
    BurnInSetting,
    burn_in,
    burn_in_cap,
    burn_in_label,
    fixed_burn_in,
    parse_burn_in,
    ScoringProtocol,
    Shortfall,
    decimation_indices,
    enough_samples,
    evaluate,
    protocols_for,
    sampled_rate,
    shortfalls,
)
from starlog.errors import InvalidInputError, InvalidParameterError
from starlog.io import encode_json, json_message_type, topics
from starlog.io.reader import ChannelSummary, LogReader
from starlog.platform_motion import star_reference
from starlog.replay.pool import ordered_map, process_pool
from starlog.replay.progress import progress
from starlog.replay.channels import select_track_channels
from starlog.stages.compensate.stars import (CentroidSigmas, StarFrames, TrackRows, centroid_sigmas,
                                              collect_track_rows)
from starlog.replay.window import windowed
from starlog.replay.layer import StageOutput, extend_log
from starlog.stages.motion import estimate_track_motion

__all__ = ["BrightestSeries", "CompensateSummary", "compensate_log", "decision_table", "evaluate_series",
           "read_brightest_series", "read_track_series", "select_track_channels", "too_short_message",
           "track_shortfalls"]


@dataclass(frozen=True)
class BrightestSeries:
    """The brightest star's track over the whole log (native rate), with its truth when simulated, and
    with (:func:`with_platform_reference`) its static position, its displacement by the platform motion
    fitted from the other stars (NaN where they give none) and that reference's radial variance (px²)."""

    method: str
    model: str
    track: int
    log_time: npt.NDArray[np.int64]
    frame: npt.NDArray[np.int64]
    xy: npt.NDArray[np.float64]
    flux: npt.NDArray[np.float64]
    sigma: npt.NDArray[np.float64]
    native_rate: float
    truth_fixed: npt.NDArray[np.float64] | None = None
    truth_series: npt.NDArray[np.float64] | None = None
    static: npt.NDArray[np.float64] | None = None
    displacement: npt.NDArray[np.float64] | None = None
    reference_variance: npt.NDArray[np.float64] | None = None
    sigma_source: str = "track meas_sigma (floored)"
    """Where ``sigma`` (``A`` of eq. 10) comes from: the centroid channel or the track's ``meas_sigma``."""
    position_var: npt.NDArray[np.float64] | None = None
    """The filter's posterior position variance per sample, ``(cov_xx + cov_yy) / 2``, px²."""

    def burn_in(self, setting: BurnInSetting = "auto") -> BurnIn:
        """The filter's start-up (:func:`starlog.compensation.burn_in`, capped by :func:`~starlog.compensation.burn_in_cap`);
        no burn-in when the variances are unknown.  ``setting``: ``"auto"`` (that rule), ``"off"``
        (none) or a fixed number of seconds (:func:`starlog.compensation.parse_burn_in`)."""
        if setting == "off":
            return BurnIn(samples=0, steady_variance=0.0, capped=False)
        if not isinstance(setting, str):
            return fixed_burn_in(self.xy.shape[0], native_rate=self.native_rate, seconds=float(setting))
        if self.position_var is None:
            return BurnIn(samples=0, steady_variance=0.0, capped=False)
        return burn_in(self.position_var, max_samples=burn_in_cap(self.xy.shape[0], native_rate=self.native_rate))

    def indices(self, rate: float, *, skip_burn_in: bool = True,
                burn_in: BurnInSetting = "auto") -> npt.NDArray[np.int64]:
        """The samples kept at ``rate`` Hz (:func:`starlog.compensation.decimation_indices`), starting
        after the filter's burn-in (per ``burn_in``) when ``skip_burn_in``."""
        start = self.burn_in(burn_in).samples if skip_burn_in else 0
        return decimation_indices(self.xy.shape[0], native_rate=self.native_rate, target_rate=rate, start=start)

    @property
    def has_motion(self) -> bool:
        """The platform motion from the other stars is attached (:func:`with_platform_reference`)."""
        return self.displacement is not None


#: Truth of one simulated star: its fixed position (2,), and the times (n,) and positions (n, 2) of every frame.
StarTruth = tuple[npt.NDArray[np.float64], npt.NDArray[np.int64], npt.NDArray[np.float64]]


def read_brightest_series(log: LogReader, topic: str, *, truth_cache: dict[int, StarTruth] | None = None,
                          with_truth: bool = True) -> BrightestSeries:
    """The brightest star's track from ``topic``, and its true positions when ``/sim/truth`` exists.

    Pass the same ``truth_cache`` dict for several track channels of one log: the truth of each
    star is then read from the log once, not once per channel. ``with_truth=False`` leaves the
    truth unread (only the ``paper`` protocol runs: it never sees the truth).
    """
    method, model, rows, _ = collect_track_rows(log, topic, lambda rows: rows["brightest"])
    if not rows:
        raise InvalidInputError(f"{topic} has no row of a brightest track; nothing to compensate.")
    track_id, kept = next(iter(rows.items()))
    t = np.asarray(kept.times, dtype=np.int64)
    span = (t[-1] - t[0]) * 1e-9
    image_rate = log.channel(topics.IMAGE).rate_hz if log.has_topic(topics.IMAGE) else 0.0
    native = image_rate if image_rate > 0 else ((t.size - 1) / span if span > 0 else 0.0)
    if native <= 0:
        raise InvalidInputError(f"{topic}: cannot tell the frame rate from fewer than two samples.")
    series = _series_from_rows(log, method, model, track_id, kept, float(native))
    if not with_truth or not log.has_topic(topics.TRUTH):
        return series
    return _with_truth(log, series, {} if truth_cache is None else truth_cache)


def _series_from_rows(log: LogReader, method: str, model: str, track_id: int, rows: TrackRows, native: float, *,
                      sigmas: CentroidSigmas | None = None) -> BrightestSeries:
    """One track's rows as a series (``sigmas``: the centroid channel's sigmas, read once for many tracks)."""
    t = np.asarray(rows.times, dtype=np.int64)
    sigma, sigma_source = _accuracy(log, method, t, rows.meas, sigmas=sigmas)
    return BrightestSeries(method=method, model=model, track=track_id, log_time=t,
                           frame=np.asarray(rows.frames, dtype=np.int64), xy=np.asarray(rows.xy, dtype=np.float64),
                           flux=np.asarray(rows.flux, dtype=np.float64), sigma=sigma, sigma_source=sigma_source,
                           native_rate=native, position_var=np.asarray(rows.var, dtype=np.float64))


def read_track_series(log: LogReader, topic: str, *, truth_cache: dict[int, StarTruth] | None = None,
                      with_truth: bool = True) -> tuple[list[BrightestSeries], npt.NDArray[np.int64]]:
    """Every confirmed track of ``topic`` as a series (in track id order), read as
    :func:`read_brightest_series` reads the brightest one, and the times of the channel's frames; the frame
    rate is the image channel's, else the track channel's."""
    method, model, rows, frame_times = collect_track_rows(log, topic, lambda rows: np.ones(rows.size, dtype=bool))
    confirmed = {k: r for k, r in rows.items() if r.confirmed}
    image_rate = log.channel(topics.IMAGE).rate_hz if log.has_topic(topics.IMAGE) else 0.0
    native = image_rate if image_rate > 0 else log.channel(topic).rate_hz
    if native <= 0:
        raise InvalidInputError(f"{topic}: cannot tell the frame rate from fewer than two samples.")
    sigmas = centroid_sigmas(log, method)
    cache = {} if truth_cache is None else truth_cache
    out = []
    for track_id in sorted(confirmed):
        series = _series_from_rows(log, method, model, track_id, confirmed[track_id], float(native), sigmas=sigmas)
        out.append(_with_truth(log, series, cache) if with_truth and log.has_topic(topics.TRUTH) else series)
    return out, frame_times


def _accuracy(log: LogReader, method: str, times: npt.NDArray[np.int64],
              meas: list[tuple[float, float, float, bool]], *,
              sigmas: CentroidSigmas | None = None) -> tuple[npt.NDArray[np.float64], str]:
    """``A`` of eq. 10 per sample and where it came from.

    The centroid's own ``sigma`` (``/stars/centroids/<METHOD>``, the centroid at the track's
    ``meas_x``, ``meas_y`` in the same frame) when the log has that channel; otherwise the
    track's ``meas_sigma`` (the tracker's ``sigma_floor`` applied).  0 where no centroid was
    associated.  ``sigmas``: that channel's sigmas already read (:func:`centroid_sigmas`).
    """
    fallback = np.array([m[2] for m in meas], dtype=np.float64)
    topic = topics.centroid_topic(method)
    if not log.has_topic(topic):
        return fallback, "track meas_sigma (floored)"
    if sigmas is None:
        wanted: dict[int, set[tuple[float, float]]] = {}
        for t, m in zip(times.tolist(), meas):
            wanted.setdefault(t, set()).update([(m[0], m[1])] if m[3] else [])
        sigmas = centroid_sigmas(log, method, only=wanted)
    out = np.zeros(len(meas))
    for k, t in enumerate(times.tolist()):
        if not meas[k][3]:
            continue
        if t not in sigmas:
            continue
        found = sigmas[t].get((meas[k][0], meas[k][1]))
        if found is None:
            return fallback, "track meas_sigma (floored)"
        out[k] = found
    return out, f"{topic} sigma"


def _nearest_star(log: LogReader, point: npt.NDArray[np.float64]) -> int | None:
    """Id of the simulated star whose fixed position is nearest ``point`` (from the first truth message)."""
    for message in log.messages(topics.TRUTH):
        stars = message.payload["stars"]
        if stars:
            static = np.array([(s["x_static"], s["y_static"]) for s in stars])
            return int(stars[int(np.argmin(np.hypot(*(static - point).T)))]["star"])
    return None


def _star_truth(log: LogReader, star_id: int) -> StarTruth:
    """Fixed position, and time-sorted instantaneous positions, of one simulated star (one pass over the truth)."""
    fixed = np.full(2, np.nan)
    times: list[int] = []
    xy: list[tuple[float, float]] = []
    for message in log.messages(topics.TRUTH):
        for s in message.payload["stars"]:
            if s["star"] == star_id:
                fixed = np.array([s["x_static"], s["y_static"]])
                times.append(message.log_time)
                xy.append((s["x"], s["y"]))
                break
    return fixed, np.asarray(times, dtype=np.int64), np.asarray(xy, dtype=np.float64).reshape(-1, 2)


def _with_truth(log: LogReader, series: BrightestSeries, cache: dict[int, StarTruth]) -> BrightestSeries:
    """Attach the true positions of the simulated star that the track follows (nearest fixed position)."""
    star_id = _nearest_star(log, series.xy.mean(axis=0))
    if star_id is None:
        return series
    if star_id not in cache:
        cache[star_id] = _star_truth(log, star_id)
    fixed, times, xy = cache[star_id]
    at = np.searchsorted(times, series.log_time)
    if times.size == 0 or np.any(at >= times.size) or np.any(times[np.minimum(at, times.size - 1)] != series.log_time):
        return series  # some sample has no truth: the truth protocol is not offered for this series
    return BrightestSeries(**{**series.__dict__, "truth_fixed": fixed, "truth_series": xy[at]})


def with_platform_reference(log: LogReader, series: BrightestSeries, topic: str, *,
                            fit: str = "rigid") -> BrightestSeries:
    """``series`` with its reference from the other stars of ``topic`` (:func:`starlog.platform_motion.star_reference`)."""
    data, est = estimate_track_motion(log, topic, model=fit)
    return _attach_reference(series, data, est, topic)


def _attach_reference(series: BrightestSeries, data: Any, est: Any, topic: str) -> BrightestSeries:
    """``series`` with its reference from the motion ``est`` fitted to the tracks ``data`` of ``topic``."""
    slot = int(np.searchsorted(data.track_ids, series.track))
    if slot >= data.track_ids.size or data.track_ids[slot] != series.track:
        raise InvalidInputError(f"{topic}: the track {series.track} has no measurement to fit.")
    frames = np.searchsorted(data.log_time, series.log_time).astype(np.int64)
    reference, variance = star_reference(data.obs, est, slot, frames)
    static = est.static[slot].copy()
    return BrightestSeries(**{**series.__dict__, "static": static, "displacement": reference - static,
                              "reference_variance": variance})


def evaluate_series(series: BrightestSeries, idx: npt.NDArray[np.int64], *, rate_hz: float,
                    protocol: ScoringProtocol, motion: MotionMode | str = MotionMode.KEEP,
                    **options: Any) -> Evaluation:
    """:func:`starlog.compensation.evaluate` on the samples ``idx`` of ``series`` (sampled at ``rate_hz``).

    The truth goes with every protocol but ``paper`` when the series has it, the platform
    reference whenever it is attached; ``options`` are :func:`~starlog.compensation.evaluate`'s
    keyword options.  ``A`` of eq. 10 is the series' ``sigma`` (the centroid's own,
    :attr:`BrightestSeries.sigma_source`) unless ``accuracy_source`` says otherwise.
    """
    options = {"accuracy_source": "sigma", **options}
    truth: dict[str, Any] = {}
    if protocol is not ScoringProtocol.PAPER and series.truth_series is not None:
        truth = {"truth_fixed": series.truth_fixed, "truth_series": series.truth_series[idx]}
    if series.displacement is not None and series.reference_variance is not None:
        truth |= {"static_position": series.static, "platform_displacement": series.displacement[idx],
                  "reference_variance": series.reference_variance[idx]}
    return evaluate(series.xy[idx], rate_hz=rate_hz, protocol=protocol, flux=series.flux[idx],
                    sigma=series.sigma[idx], motion=motion, **truth, **options)


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
    if not rates:
        raise InvalidParameterError("give at least one rate (--rate HZ).")
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise InvalidParameterError(f"workers must be an integer >= 1, got {workers!r}.")
    if stars not in ("brightest", "all"):
        raise InvalidParameterError(f"stars must be 'brightest' or 'all', got {stars!r}.")
    options = dict(options or {})
    setting = parse_burn_in(burn_in) if skip_burn_in else "off"
    summary = CompensateSummary()
    with LogReader(input_path) as probe:
        channels = select_track_channels(probe, track)
        has_truth = probe.has_topic(topics.TRUTH)
        chosen = parse_protocols(protocols, has_truth=has_truth)
        short = track_shortfalls(probe, channels, rates, chosen, options=options, burn_in=setting)
    skipped = {(s.rate_hz, s.protocol) for s in short}
    pairs_left = sum((float(r), p) not in skipped for r in rates for p in chosen)
    if short and (not skip_short or not pairs_left):
        raise InvalidParameterError(too_short_message(
            f"{channels[0].topic} ({_length(channels[0])})", short, "Give a longer log or range, higher --rate or "
            "other --protocol values" + (", or --skip-short to leave these out." if pairs_left else ".")))
    summary.skipped = short
    modes = parse_motion_modes(motion)
    parameters = {"tracks": [c.topic for c in channels], "rates": [float(r) for r in rates],
                  "protocols": [p.value for p in chosen], "options": options, "skip_burn_in": skip_burn_in,
                  "burn_in": burn_in_label(setting)}
    if short:
        parameters["skipped"] = [s.to_dict() for s in short]
    fit = motion_fit if (ScoringProtocol.RELATIVE in chosen or MotionMode.SEPARATE in modes) else None
    if modes != [MotionMode.KEEP] or fit is not None:
        parameters |= {"motion": [m.value for m in modes], "motion_fit": fit}
    if stars == "all":
        parameters["stars"] = "all"
    n_jobs = len(channels) * pairs_left * len(modes)
    parallel = workers > 1 and (n_jobs > 1 or stars == "all")
    with extend_log(input_path, output_path, stage="compensate", parameters=parameters, force=force, flatten=flatten,
                    compression=compression) as (log, out), \
            (process_pool(workers, preload=[__name__]) if parallel else nullcontext()) as pool:
        jobs = _plan_jobs(log, channels, rates, chosen, modes, fit, burn_in=setting, skipped=skipped)
        done = _evaluated(jobs, options, pool, window=2 * workers)
        decisions: dict[str, int] = {}
        for job, evaluation in progress(done, total=n_jobs, description="compensate", enabled=show_progress,
                                        unit="run"):
            if job.track_topic not in decisions:
                decisions[job.track_topic] = out.add_channel(
                    topics.decisions_topic(job.series.method, job.series.model),
                    json_message_type("starlog.CompensationRecord"), unordered=True)
            summary.records.append(_write_evaluation(out, decisions[job.track_topic], job, evaluation))
        if stars == "all":
            plan = _StarPlan(rates=list(rates), protocols=[p for p in chosen], modes=modes, fit=fit, burn_in=setting,
                             skipped=skipped, options=options)
            summary.stars = _compensate_all_stars(log, out, channels, plan, pool, window=2 * workers,
                                                  show_progress=show_progress)
    return summary


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


@dataclass(frozen=True)
class _Job:
    """One evaluation: the brightest series of ``track_topic`` at one rate, under one protocol and motion mode."""

    track_topic: str
    series: BrightestSeries
    rate: float
    idx: npt.NDArray[np.int64]
    rate_hz: float
    protocol: ScoringProtocol
    motion: MotionMode = MotionMode.KEEP
    burn_in: BurnInSetting = "auto"


def _plan_jobs(log: LogReader, channels: list[ChannelSummary], rates: Sequence[float],
               chosen: list[ScoringProtocol], modes: list[MotionMode], fit: str | None, *,
               burn_in: BurnInSetting, skipped: set[tuple[float, ScoringProtocol]]) -> Iterator[_Job]:
    """Every (track channel, rate, protocol, motion mode) but the ``skipped`` (rate, protocol) pairs, in output
    order; each channel's series read when reached (with its platform reference when ``fit`` is given)."""
    truth_cache: dict[int, StarTruth] = {}
    with_truth = any(p is not ScoringProtocol.PAPER for p in chosen)
    for channel in channels:
        series = read_brightest_series(log, channel.topic, truth_cache=truth_cache, with_truth=with_truth)
        if fit is not None:
            series = with_platform_reference(log, series, channel.topic, fit=fit)
        jobs = []
        for rate in rates:
            if not rate > 0 or rate > series.native_rate * (1 + RATE_TOLERANCE):
                raise InvalidParameterError(
                    f"rate {rate} Hz must be > 0 and at most the frame rate {series.native_rate:g} Hz.")
            idx = series.indices(rate, burn_in=burn_in)
            rate_hz = sampled_rate(idx, native_rate=series.native_rate)
            jobs += [_Job(channel.topic, series, float(rate), idx, rate_hz, p, m, burn_in) for p in chosen
                     if (float(rate), p) not in skipped for m in modes]
        yield from jobs


def _evaluate_job(job: _Job, options: dict[str, Any]) -> Evaluation:
    """Run one job (in a worker process when parallel); errors say which job failed."""
    try:
        return evaluate_series(job.series, job.idx, rate_hz=job.rate_hz, protocol=job.protocol, motion=job.motion,
                               **options)
    except (InvalidInputError, InvalidParameterError) as err:
        raise type(err)(f"{job.track_topic} at {job.rate:g} Hz ({job.idx.size} samples), protocol "
                        f"{job.protocol.value}, motion {job.motion.value}: {err}{_ways_out(job)}") from err


def _ways_out(job: _Job) -> str:
    """What a user of the command can do when a protocol lacks samples: the options that give more."""
    others = ",".join(p.value for p in ScoringProtocol if p is not job.protocol)
    calibration = " or --set calibration_fraction=F (the leak-free calibration's share)" \
        if job.protocol is ScoringProtocol.LEAKFREE else ""
    return (f" With the command: give a longer log or range, a higher --rate, --protocol {others}{calibration}.")


def _evaluated(jobs: Iterable[_Job], options: dict[str, Any], pool: Executor | None, *,
               window: int) -> Iterator[tuple[_Job, Evaluation]]:
    """Each job with its evaluation, in job order; on ``pool`` when given."""
    if pool is None:
        for job in jobs:
            yield job, _evaluate_job(job, options)
        return
    submitted: deque[_Job] = deque()

    def feed() -> Iterator[tuple[_Job, dict[str, Any]]]:
        for job in jobs:
            submitted.append(job)  # ordered_map yields results in this same order
            yield job, options

    for evaluation in ordered_map(pool, _evaluate_job, feed(), window=window):
        yield submitted.popleft(), evaluation


def _write_evaluation(out: StageOutput, decision_channel: int, job: _Job, evaluation: Evaluation) -> dict[str, Any]:
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
    record = _decision_record(job, evaluation, topic)
    out.writer.write(decision_channel, log_time=int(series.log_time[idx[-1]]), data=encode_json(record))
    return record


def _decision_record(job: _Job, evaluation: Evaluation, topic: str) -> dict[str, Any]:
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


@dataclass
class _StarPlan:
    """What ``--stars all`` runs for every confirmed track: the stage's rates, protocols, motion modes, motion fit,
    burn-in setting, the (rate, protocol) pairs left out for the whole log, and evaluate's options."""

    rates: list[float]
    protocols: list[ScoringProtocol]
    modes: list[MotionMode]
    fit: str | None
    burn_in: BurnInSetting
    skipped: set[tuple[float, ScoringProtocol]]
    options: dict[str, Any]


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


def _star_series(log: LogReader, topic: str, plan: _StarPlan,
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
            out.append(_attach_reference(series, data, est, topic))
        except InvalidInputError:
            out.append(series)
    return out, frame_times


def _star_jobs(log: LogReader, channels: list[ChannelSummary], plan: _StarPlan,
               groups: dict[tuple[str, float, str, str], _StarGroup]) -> Iterator[_Job]:
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
                        yield _Job(channel.topic, series, float(rate), idx, rate_hz, protocol, mode, plan.burn_in)


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


def _compensate_all_stars(log: LogReader, out: StageOutput, channels: list[ChannelSummary], plan: _StarPlan,
                          pool: Executor | None, *, window: int, show_progress: bool) -> list[dict[str, Any]]:
    """Compensate every confirmed track (:func:`_star_jobs`) and write each group's frames once it is complete,
    and a decision record per star; returns one summary entry per group."""
    groups: dict[tuple[str, float, str, str], _StarGroup] = {}
    decisions: dict[str, int] = {}
    written: dict[tuple[str, float, str, str], int] = {}
    current: tuple[str, float, str, str] | None = None
    done = _evaluated(_star_jobs(log, channels, plan, groups), plan.options, pool, window=window)
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
        record = _decision_record(job, evaluation, group.frames.topic)
        out.writer.write(decisions[group.decisions], log_time=int(series.log_time[idx[-1]]), data=encode_json(record))
    if current is not None:
        written[current] = groups[current].frames.write(out)
    return [group.to_dict(written.get(key, 0)) for key, group in groups.items()]
