"""The ``motion`` stage: platform motion from all tracked stars, and each star's centroid error alone.

Reads one track channel (``/track/<METHOD>/<MODEL>``: every row with an associated
measurement gives ``meas_x``, ``meas_y`` and the track id), estimates the per-frame platform
motion jointly with every star's static position and centroid noise
(:func:`starlog.platform_motion.estimate_platform`), and writes

* ``/platform/<METHOD>/<MODEL>`` (starlog.PlatformMotion): dx, dy, roll (and scale), their
  1-sigma, the stars used and the residual RMS, one message per frame with a motion;
* ``/stars/residuals/<METHOD>/<MODEL>`` (starlog.StarResiduals): each star's measured minus
  fitted position, with its predicted sigma and whether it was used or flagged.

The channel is read once.  The joint estimate needs every measurement at once, so they are held
as flat arrays (about 50 bytes per star per frame: 10 MB for 12 stars over an hour at 50 Hz, and
the estimate's own arrays of about the same size): the stage's memory grows with the log's length,
unlike the other stages'. The outputs are written frame by frame from them.
"""

from __future__ import annotations

import os
from array import array
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from starlog.errors import InvalidInputError, InvalidParameterError
from starlog.codecs import protobuf_message_type
from starlog import topics
from starlog.io.reader import LogReader
from starlog.codecs.star_tables import star_codec
from starlog.platform_motion import Observations, PlatformEstimate, PlatformModel, estimate_platform
from starlog.replay.channels import check_messages_read, select_track_channels
from starlog.replay.window import windowed
from starlog.replay.layer import StageOutput, extend_log

__all__ = ["MotionSummary", "TrackObservations", "image_centre", "motion_log", "read_track_observations",
           "estimate_track_motion"]


@dataclass(frozen=True)
class TrackObservations:
    """Every associated measurement of one track channel: ``obs.frame`` indexes ``log_time`` and ``frame``;
    ``obs.star`` indexes ``track_ids``."""

    method: str
    model: str
    log_time: npt.NDArray[np.int64]
    frame: npt.NDArray[np.int64]
    track_ids: npt.NDArray[np.int64]
    obs: Observations


def read_track_observations(log: LogReader, topic: str) -> TrackObservations:
    """The measured positions (``meas_x``, ``meas_y``, ``meas_sigma`` > 0) of every track in ``topic``.

    The channel is read as tables (:meth:`~starlog.io.reader.LogReader.tables`), the measured rows of each
    frame kept as arrays (``log`` may skip the JSON schema check: a message without the fields used is
    reported as not a track message).
    """
    times, frames = array("q"), array("q")
    kept: list[npt.NDArray[np.void]] = []
    index: list[npt.NDArray[np.int64]] = []
    method = model = ""
    for k, message in enumerate(log.tables(topic)):
        try:
            method, model = message.header["method"], message.header["model"]
            frames.append(int(message.header["frame"]))
        except (KeyError, TypeError, ValueError) as err:
            raise InvalidInputError(f"{topic} at log_time {message.log_time}: not a starlog.Tracks message ({err!r}); "
                                    "`starlog verify` lists every problem of the log.") from err
        rows = message.rows
        if rows is not None and rows.size:
            measured = rows[rows["meas_sigma"] > 0]
            kept.append(measured)
            index.append(np.full(measured.size, k, dtype=np.int64))
        times.append(message.log_time)
    check_messages_read(log, topic, len(times))
    rows = np.concatenate(kept) if kept else np.zeros(0)
    if not rows.size:
        raise InvalidInputError(f"{topic} has no associated measurement; nothing to fit.")
    tracks = rows["track"].astype(np.int64)
    obs = Observations.build(np.concatenate(index), tracks, rows["meas_x"], rows["meas_y"], rows["meas_sigma"],
                             n_frames=len(times))
    return TrackObservations(method, model, np.frombuffer(times, dtype=np.int64), np.frombuffer(frames, dtype=np.int64),
                             np.unique(tracks), obs)


def image_centre(log: LogReader, obs: Observations) -> tuple[float, float]:
    """``((width - 1) / 2, (height - 1) / 2)`` from ``/camera/frame``; else the middle of the measurements."""
    if log.has_topic(topics.FRAME_INFO):
        for message in log.messages(topics.FRAME_INFO):
            return (message.payload["width"] - 1) / 2.0, (message.payload["height"] - 1) / 2.0
    lo, hi = obs.xy.min(axis=0), obs.xy.max(axis=0)
    return float(lo[0] + hi[0]) / 2.0, float(lo[1] + hi[1]) / 2.0


def estimate_track_motion(log: LogReader, topic: str, *, model: PlatformModel | str = PlatformModel.RIGID,
                          options: dict[str, Any] | None = None) -> tuple[TrackObservations, PlatformEstimate]:
    """Read ``topic`` and estimate its platform motion (``options``: keywords of ``estimate_platform``)."""
    data = read_track_observations(log, topic)
    try:
        estimate = estimate_platform(data.obs, centre=image_centre(log, data.obs), model=model, **(options or {}))
    except TypeError as err:
        raise InvalidParameterError(f"unknown motion option: {err}.") from err
    return data, estimate


@dataclass
class MotionSummary:
    """What :func:`motion_log` wrote, per track channel."""

    fit: str
    channels: dict[str, dict[str, Any]] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return {"fit": self.fit, "channels": self.channels}

    def lines(self) -> list[str]:
        """Per track channel: frames with a motion, stars, outliers, RMS motion, 1-sigma, each star's noise."""
        lines = []
        for topic, ch in self.channels.items():
            lines.append(f"{topic}: {ch['frames_with_motion']}/{ch['frames']} frames with a motion, {ch['stars']} "
                         f"stars, {ch['outliers']} outliers, {ch['short_tracks']} short tracks left out")
            if ch["frames_without_motion"]:
                lines.append(f"  {ch['frames_without_motion']} frames without a motion ({ch['without_motion_reason']})")
            lines.append(f"  RMS dx {ch['rms_dx']:.4f} px, dy {ch['rms_dy']:.4f} px, roll {ch['rms_roll']:.3g} rad; "
                         f"median 1-sigma dx {ch['median_sigma_dx']:.4f} px, dy {ch['median_sigma_dy']:.4f} px; "
                         f"median residual RMS {ch['median_residual_rms']:.4f} px")
            noise = ", ".join(f"{track}: {value:.4f}" for track, value in ch["star_noise"].items())
            lines.append(f"  centroid noise per track (px, 1 sigma per axis): {noise}")
        return lines


def _channel_summary(data: TrackObservations, est: PlatformEstimate, min_stars: int) -> dict[str, Any]:
    valid = est.valid

    def rms(values: npt.NDArray[np.float64]) -> float:
        return float(np.sqrt(np.mean(values[valid] ** 2))) if valid.any() else 0.0
    sd = np.sqrt(np.diagonal(est.covariance, axis1=1, axis2=2)[valid]) if valid.any() else np.zeros((0, 2))
    eligible = np.flatnonzero(est.star_eligible)
    return {
        "frames": int(data.log_time.size), "frames_with_motion": int(valid.sum()),
        "frames_without_motion": int((~valid).sum()),
        "without_motion_reason": f"fewer than {min_stars} usable stars" if (~valid).any() else "",
        "stars": int(eligible.size), "short_tracks": int((~est.star_eligible).sum()),
        "outliers": int(est.outlier.sum()), "iterations": est.iterations, "converged": est.converged,
        "rms_dx": rms(est.motion.dx), "rms_dy": rms(est.motion.dy), "rms_roll": rms(est.motion.roll),
        "median_sigma_dx": float(np.median(sd[:, 0])) if sd.size else 0.0,
        "median_sigma_dy": float(np.median(sd[:, 1])) if sd.size else 0.0,
        "median_residual_rms": float(np.nanmedian(est.residual_rms)) if valid.any() else 0.0,
        "star_noise": {int(data.track_ids[i]): float(est.star_noise[i]) for i in eligible},
    }


@windowed(lambda log, options: select_track_channels(log, options.get("track"))[0].topic)
def motion_log(
    input_path: str | os.PathLike[str],
    output_path: str | os.PathLike[str],
    *,
    track: str | Sequence[str] | None = None,
    model: PlatformModel | str = PlatformModel.RIGID,
    options: dict[str, Any] | None = None,
    force: bool = False,
    flatten: bool = False,
    compression: str = "zstd",
    workers: int = 1,
) -> MotionSummary:
    """Fit the platform motion of track channel(s) and write it with each star's residual.

    Parameters
    ----------
    track : str or sequence of str, optional
        Track channel(s) (``/track/GAUSSFIT/STATIC`` or ``GAUSSFIT/STATIC``), or ``"all"``;
        default: the only one.
    model : str
        ``translation``, ``rigid`` (default) or ``similarity``.
    options : dict, optional
        Keywords of :func:`starlog.platform_motion.estimate_platform` (k_sigma, min_stars, min_star_frames,
        max_iterations, tol, max_rejections).
    start, end : str or int, optional
        Only the range ``start <= log_time < end`` (ns, ``"12.5s"`` or ``"frame:N"`` of the first
        track channel; :mod:`starlog.io.timerange`): the layer holds its channels for that range.
    flatten : bool
        Write the whole chain as one self-contained file instead of a layer on the input.
    """
    try:
        fit = PlatformModel(str(model).lower())
    except ValueError:
        raise InvalidParameterError(f"unknown motion model {model!r}; choose translation, rigid or similarity.") from None
    options = dict(options or {})
    with LogReader(input_path, validate_messages=False) as tracks:  # the track rows starlog wrote: not re-checked
        chosen = [c.topic for c in select_track_channels(tracks, track)]
        summary = MotionSummary(fit=fit.value)
        parameters = {"tracks": chosen, "fit": fit.value, "options": options}
        with extend_log(tracks, output_path, stage="motion", parameters=parameters, force=force, flatten=flatten,
                        compression=compression) as (_, out):
            for topic in chosen:
                data, est = estimate_track_motion(tracks, topic, model=fit, options=options)
                _write_motion(out, data, est)
                summary.channels[topic] = _channel_summary(data, est, int(options.get("min_stars", 3)))
    return summary


def _write_motion(out: StageOutput, data: TrackObservations, est: PlatformEstimate) -> None:
    platform = out.add_channel(topics.platform_topic(data.method, data.model),
                               protobuf_message_type("starlog.PlatformMotion"))
    residuals = out.add_channel(topics.residuals_topic(data.method, data.model),
                                protobuf_message_type("starlog.StarResiduals"))
    platform_codec, residuals_codec = star_codec("starlog.PlatformMotion"), star_codec("starlog.StarResiduals")
    obs = data.obs
    head = {"method": data.method, "model": data.model, "fit": est.model.value}
    n_par = est.model.n_parameters
    sd = np.sqrt(np.abs(np.diagonal(est.covariance, axis1=1, axis2=2)))
    order = np.argsort(obs.frame, kind="stable")
    bounds = np.searchsorted(obs.frame[order], np.arange(obs.n_frames + 1))
    rejected = np.bincount(obs.frame[est.outlier], minlength=obs.n_frames)
    m = est.motion
    for k in np.flatnonzero(est.valid):
        t = int(data.log_time[k])
        message = {"frame": int(data.frame[k]), **head, "dx": float(m.dx[k]), "dy": float(m.dy[k]),
                   "roll": float(m.roll[k]), "scale": float(m.scale[k]), "sigma_dx": float(sd[k, 0]),
                   "sigma_dy": float(sd[k, 1]), "sigma_roll": float(sd[k, 2]) if n_par > 2 else 0.0,
                   "sigma_scale": float(sd[k, 3]) if n_par > 3 else 0.0, "n_stars": int(est.n_used[k]),
                   "n_rejected": int(rejected[k]), "residual_rms": float(est.residual_rms[k])}
        out.writer.write(platform, log_time=t, data=platform_codec.encode(message))
        rows = order[bounds[k]:bounds[k + 1]]
        stars = [_residual_row(data, est, i) for i in rows]
        out.writer.write(residuals, log_time=t,
                         data=residuals_codec.encode_dict({"frame": int(data.frame[k]), **head, "stars": stars}))


def _residual_row(data: TrackObservations, est: PlatformEstimate, i: int) -> dict[str, Any]:
    star = data.obs.star[i]
    flag = "used" if est.used[i] else ("outlier" if est.star_eligible[star] else "short_track")
    return {"track": int(data.track_ids[star]), "x": float(data.obs.xy[i, 0]), "y": float(data.obs.xy[i, 1]),
            "x_static": float(est.static[star, 0]), "y_static": float(est.static[star, 1]),
            "residual_x": float(est.residual[i, 0]), "residual_y": float(est.residual[i, 1]),
            "sigma": float(est.star_noise[star]), "flag": flag}
