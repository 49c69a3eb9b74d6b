"""The series the ``compensate`` stage compensates: a track's rows as arrays, with its truth and its reference.

:func:`read_brightest_series` reads the brightest star's track (the paper's centroid sequence),
:func:`read_track_series` every confirmed track; each sample's accuracy ``A`` (eq. 10) is the centroid's own
``sigma`` where the log has the centroid channel. On a simulated log the true positions of the star a track
follows are attached; :func:`with_platform_reference` attaches the platform motion fitted to the other stars
(:mod:`starlog.platform_motion`). :func:`evaluate_series` runs :func:`starlog.compensation.evaluate` on the
samples of one rate.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from starlog.compensation import (
    BurnIn,
    BurnInSetting,
    Evaluation,
    MotionMode,
    ScoringProtocol,
    burn_in,
    burn_in_cap,
    decimation_indices,
    evaluate,
    fixed_burn_in,
)
from starlog.errors import InvalidInputError
from starlog import topics
from starlog.io.reader import LogReader
from starlog.platform_motion import star_reference
from starlog.stages.compensate.track_rows import CentroidSigmas, TrackRows, centroid_sigmas, collect_track_rows
from starlog.stages.motion import estimate_track_motion

__all__ = ["BrightestSeries", "StarTruth", "attach_reference", "evaluate_series", "read_brightest_series",
           "read_track_series", "with_platform_reference"]


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
    return attach_reference(series, data, est, topic)


def attach_reference(series: BrightestSeries, data: Any, est: Any, topic: str) -> BrightestSeries:
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


