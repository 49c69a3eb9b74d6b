"""The ``solve`` stage: star identities and the camera's attitude, frame by frame, from centroid channels.

Reads ``/stars/centroids/<METHOD>`` (one or more methods, each solved on its own), identifies the
stars in cedar-solve's Hipparcos catalogue and estimates the attitude with its covariance
(:class:`starlog.attitude.identify.AttitudeTracker`: a lost-in-space plate solve, then tracking from the
previous attitude, Davenport's q-method weighted by each centroid's sigma), and writes a layer holding

* ``/attitude/<METHOD>`` (starlog.Attitude): quaternion, RA/Dec/roll, field of view, camera model,
  stars matched, residual RMS in px and arcsec, the 3 x 3 covariance, solved or why not; on a
  simulated sky field (``simulate --sky-attitude``) also the attitude error against the true attitude;
* ``/stars/identified/<METHOD>`` (starlog.IdentifiedStars): per identified star its catalogue number and
  magnitude, the catalogue position projected to pixels, and the residual;
* ``/stars/identified/<METHOD>/annotations`` (foxglove.ImageAnnotations): a circle and the catalogue
  number at each identified star, over the frames in Foxglove.

With ``compensated``, it also reads the all-star channels of ``compensate --stars all``
(``/compensated/<METHOD>/<MODEL>/stars/<RATE>Hz/<protocol>``, starlog.CompensatedStars) and solves each
twice, from the positions before and after compensation, under the names
``compensated/<METHOD>/<MODEL>/<RATE>Hz/<protocol>[/separate]/before`` and ``.../after``: the attitude before
and after compensation at the compensated rate's frames, each with its error against the truth when simulated.

With two or more centroid channels, the summary and the ``starlog.solve`` record also hold the sky's evidence
on which method to trust: each method's catalogue residual on the stars every method identified, one camera
model per log (:mod:`starlog.attitude.sky_evidence`). :func:`probe_sky` computes the same on a few frames in
memory, without writing a layer (``starlog run`` deciding which method to track).

A frame that cannot be solved (too few stars, no solution) is written with ``solved: false`` and the
reason; nothing stops the log. The image size comes from ``/camera/frame``; on a simulated sky field the
camera (field of view, no distortion) comes from the simulator's provenance unless ``camera = "fit"``.

One module of over 500 lines: the stage's three records, its summary and the probe share the reading of
centroid payloads and the tracker's settings.
"""

from __future__ import annotations

import itertools
import json
import math
import os
import time
from collections import Counter
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field, fields, replace
from typing import Any

import numpy as np
import numpy.typing as npt

from starlog.attitude.camera import focal_from_fov
from starlog.attitude.catalogue import Catalogue, load_catalogue, solver_data_file
from starlog.attitude.identify import ARCSEC_PER_RAD, AttitudeTracker, FrameAttitude, TrackerSettings
from starlog.attitude.rotation import attitude_error, matrix_from_quaternion, radec_roll
from starlog.attitude.sky_evidence import MAX_SKY_FRAMES, IdentifiedFrame, sky_evidence
from starlog.centroiding.table import CentroidFlag
from starlog.errors import InvalidInputError, InvalidParameterError
from starlog.codecs import protobuf_message_type
from starlog import topics
from starlog.io.reader import LogReader
from starlog.codecs.star_tables import star_codec
from starlog.replay.channels import check_messages_read
from starlog.replay.progress import progress
from starlog.replay.layer import StageOutput, extend_log
from starlog.replay.window import windowed

__all__ = ["PROBE_FRAMES", "MethodFigures", "SolveSummary", "add_solve_channels", "compensated_name", "probe_sky",
           "select_centroid_channels", "select_compensated_channels", "sky_frames_kept", "solve_frame", "solve_log",
           "solve_parameters", "tracker_settings", "true_attitude", "usable_centroids"]

#: The schema of the all-star channels ``compensate --stars all`` writes.
COMPENSATED_STARS = "starlog.CompensatedStars"
#: Frames :func:`probe_sky` solves at most, evenly spaced through the log.
PROBE_FRAMES = 16
#: Of them, the first ones that must solve (the first method's) for the probe to go on.
_PROBE_TRIES = 3


def select_centroid_channels(log: LogReader, centroids: str | Sequence[str] | None) -> list[str]:
    """Centroid channels named by ``centroids``: methods or topics (comma-separated or a list), ``"all"``, or
    None for the only one."""
    channels = [c.topic for c in log.channels() if c.schema_name == "starlog.Centroids"]
    if not channels:
        raise InvalidInputError(f"{log.path} has no centroid channel; run `starlog centroid` on it first.")
    names = [] if centroids is None else (centroids.split(",") if isinstance(centroids, str) else list(centroids))
    names = [n.strip() for n in names if n.strip()]
    if not names:
        if len(channels) == 1:
            return channels
        raise InvalidParameterError("the log has several centroid channels; choose with --centroids (or all): "
                                    + ", ".join(channels))
    if [n.lower() for n in names] == ["all"]:
        return channels
    chosen = []
    for name in names:
        topic = name if name.startswith("/") else topics.centroid_topic(name.upper())
        if topic not in channels:
            raise InvalidParameterError(f"{log.path} has no centroid channel {topic}; it has: {', '.join(channels)}.")
        chosen.append(topic)
    return chosen


def select_compensated_channels(log: LogReader, compensated: str | Sequence[str] | None) -> list[str]:
    """All-star compensated channels (``compensate --stars all``) named by ``compensated``: ``RATE/PROTOCOL``
    (``50/truth``, ``50Hz/paper/separate``) or topics, comma-separated or a list, or ``"all"``; None: none."""
    if compensated is None:
        return []
    channels = [c.topic for c in log.channels() if c.schema_name == COMPENSATED_STARS]
    if not channels:
        raise InvalidInputError(f"{log.path} has no all-star compensated channel; run `starlog compensate --stars all` "
                                "on it first.")
    names = compensated.split(",") if isinstance(compensated, str) else list(compensated)
    names = [n.strip() for n in names if n.strip()]
    if [n.lower() for n in names] == ["all"]:
        return channels
    chosen = []
    for name in names:
        if name.startswith("/"):
            found = [name] if name in channels else []
        else:
            rate, _, rest = name.partition("/")
            suffix = f"/stars/{rate.removesuffix('Hz')}Hz/{rest}"
            found = [c for c in channels if c.endswith(suffix)]
        if not found:
            raise InvalidParameterError(f"{log.path} has no all-star compensated channel {name!r}; it has: "
                                        + ", ".join(channels) + ".")
        chosen += [c for c in found if c not in chosen]
    return chosen


def compensated_name(topic: str, which: str) -> str:
    """``compensated/<METHOD>/<MODEL>/<RATE>Hz/<protocol>[/separate]/<before|after>``: the name the attitude of
    an all-star channel is written under (``/attitude/<name>``)."""
    return topic.strip("/").replace("/stars/", "/", 1) + "/" + which


def tracker_settings(log: LogReader, options: dict[str, Any], width: int) -> TrackerSettings:
    """:class:`TrackerSettings` from the stage's options (its fields, and ``camera``: ``"auto"``, the default,
    takes a simulated sky field's camera from the simulator's provenance; ``"fit"`` fits it)."""
    options = dict(options)
    camera = options.pop("camera", "auto")
    if camera not in ("auto", "fit"):
        raise InvalidParameterError(f"camera must be 'auto' or 'fit', got {camera!r}.")
    known = {f.name for f in fields(TrackerSettings)}
    unknown = sorted(set(options) - known)
    if unknown:
        raise InvalidParameterError(f"unknown solve option(s) {unknown}; known: {sorted(known | {'camera'})}.")
    if camera == "auto" and "focal_px" not in options:
        for record in log.provenance():
            if record.stage == "simulate" and record.parameters.get("sky_attitude") is not None:
                options["focal_px"] = focal_from_fov(float(record.parameters["fov_deg"]), width)
                options.setdefault("distortion", 0.0)
    return TrackerSettings(**options)


def _image_shape(log: LogReader) -> tuple[int, int]:
    """``(rows, cols)`` of the frames, from ``/camera/frame``."""
    if log.has_topic(topics.FRAME_INFO):
        for message in log.messages(topics.FRAME_INFO):
            return int(message.payload["height"]), int(message.payload["width"])
    raise InvalidInputError(f"{log.path} has no {topics.FRAME_INFO} channel: the image size is unknown.")


def _true_attitudes(log: LogReader) -> dict[int, npt.NDArray[np.float64]]:
    """log_time → the simulator's true attitude matrix (empty unless the log is a simulated sky field)."""
    if not log.has_topic(topics.TRUTH):
        return {}
    out = {}
    for message in log.messages(topics.TRUTH):
        attitude = true_attitude(message.payload)
        if attitude is None:
            return {}
        out[message.log_time] = attitude
    return out


def true_attitude(truth: dict[str, Any]) -> npt.NDArray[np.float64] | None:
    """The true attitude matrix in a ``/sim/truth`` message (None: not a simulated sky field)."""
    attitude = truth.get("attitude")
    return None if attitude is None else matrix_from_quaternion(attitude["quaternion"])


@dataclass(frozen=True)
class _Centroids:
    """One frame's usable centroids (finite, sigma > 0, fit not failed) as columns."""

    star: npt.NDArray[np.int64]
    x: npt.NDArray[np.float64]
    y: npt.NDArray[np.float64]
    flux: npt.NDArray[np.float64]
    sigma: npt.NDArray[np.float64]

    @classmethod
    def from_rows(cls, rows: npt.NDArray[np.void]) -> _Centroids:
        """The usable rows of a frame's centroid table (:meth:`~starlog.io.reader.LogReader.tables`)."""
        x, y, flux, sigma = (rows[name].astype(np.float64) for name in ("x", "y", "flux", "sigma"))
        ok = (np.isfinite(x) & np.isfinite(y) & np.isfinite(flux) & np.isfinite(sigma) & (sigma > 0)
              & ((rows["flags"].astype(np.int64) & int(CentroidFlag.FIT_FAILED)) == 0))
        return cls(rows["star"][ok].astype(np.int64), x[ok], y[ok], flux[ok], sigma[ok])

    @classmethod
    def from_compensated(cls, payload: dict[str, Any], which: str) -> _Centroids:
        """The stars of a ``starlog.CompensatedStars`` frame, ``before`` or ``after`` compensation (``star``: the
        track id); a row with sigma 0 (no centroid associated in that frame) is left out."""
        rows = payload["stars"]
        table = np.array([(r[f"x_{which}"], r[f"y_{which}"], r["flux"], r["sigma"], r["track"]) for r in rows],
                         dtype=np.float64).reshape(-1, 5)
        t = table[np.isfinite(table[:, :4]).all(axis=1) & (table[:, 3] > 0)]
        return cls(t[:, 4].astype(np.int64), t[:, 0], t[:, 1], t[:, 2], t[:, 3])


def _attitude_record(frame: int, method: str, result: FrameAttitude, stars: _Centroids,
                     truth: npt.NDArray[np.float64] | None) -> dict[str, Any]:
    """The ``/attitude/<METHOD>`` message of one frame (numbers 0 when unsolved)."""
    record: dict[str, Any] = {"frame": frame, "method": method, "solved": result.solved, "mode": result.mode,
                              "reason": result.reason, "n_stars": int(stars.x.size), "n_matched": result.n_matched,
                              "solver_ms": float(result.solver.get("t_solve", 0.0))}
    cam, fit = result.camera, result.fit
    if not result.solved or cam is None or fit is None:
        zero = {"quaternion": [0.0] * 4, "ra_deg": 0.0, "dec_deg": 0.0, "roll_deg": 0.0, "fov_deg": 0.0,
                "focal_px": 0.0, "distortion": 0.0, "mirrored": False, "residual_px": 0.0, "residual_arcsec": 0.0,
                "covariance": [0.0] * 9, "sigma_x_arcsec": 0.0, "sigma_y_arcsec": 0.0, "sigma_roll_arcsec": 0.0}
        return {**record, **zero}
    ra, dec, roll = radec_roll(cam.rotation)
    rms = result.residual_rms(stars.x, stars.y)
    sd = np.sqrt(np.abs(np.diag(fit.covariance))) * ARCSEC_PER_RAD
    record.update({"quaternion": [float(v) for v in fit.quaternion], "ra_deg": ra, "dec_deg": dec, "roll_deg": roll,
                   "fov_deg": cam.fov_deg, "focal_px": float(cam.focal), "distortion": float(cam.k),
                   "mirrored": bool(cam.parity < 0), "residual_px": rms, "residual_arcsec": rms / cam.focal * ARCSEC_PER_RAD,
                   "covariance": [float(v) for v in fit.covariance.reshape(-1)], "sigma_x_arcsec": float(sd[0]),
                   "sigma_y_arcsec": float(sd[1]), "sigma_roll_arcsec": float(sd[2])})
    if truth is not None:
        error = attitude_error(cam.rotation, truth) * ARCSEC_PER_RAD
        record.update({"error_x_arcsec": float(error[0]), "error_y_arcsec": float(error[1]),
                       "error_roll_arcsec": float(error[2])})
    return record


def _identified_record(frame: int, method: str, result: FrameAttitude, stars: _Centroids,
                       catalogue: Catalogue) -> dict[str, Any]:
    """The ``/stars/identified/<METHOD>`` message of one frame."""
    rows = result.centroid_rows
    cat = result.catalogue_rows
    out = []
    for k in range(rows.size):
        i = int(rows[k])
        x, y, cx, cy = float(stars.x[i]), float(stars.y[i]), float(result.cat_x[k]), float(result.cat_y[k])
        out.append({"star": int(stars.star[i]), "catalogue_id": int(catalogue.ids[cat[k]]),
                    "magnitude": float(catalogue.magnitude[cat[k]]), "x": x, "y": y, "sigma": float(stars.sigma[i]),
                    "x_catalogue": cx, "y_catalogue": cy, "residual_x": x - cx, "residual_y": y - cy})
    return {"frame": frame, "method": method, "stars": out}


def _annotations(record: dict[str, Any], log_time: int) -> bytes:
    """Circles at the identified stars and their catalogue numbers (``HIP n``) as foxglove.ImageAnnotations
    (0.5 px added: Foxglove's origin is the top-left pixel's corner)."""
    from foxglove_schemas_protobuf.ImageAnnotations_pb2 import ImageAnnotations

    message = ImageAnnotations()
    for star in record["stars"]:
        x, y = star["x"] + 0.5, star["y"] + 0.5
        circle = message.circles.add()
        circle.timestamp.FromNanoseconds(log_time)
        circle.position.x, circle.position.y = x, y
        circle.diameter, circle.thickness = 10.0, 1.0
        circle.outline_color.r, circle.outline_color.g, circle.outline_color.b, circle.outline_color.a = 1, 0.8, 0.1, 1
        text = message.texts.add()
        text.timestamp.FromNanoseconds(log_time)
        text.position.x, text.position.y = x + 7.0, y - 7.0
        text.text = f"HIP {star['catalogue_id']}"
        text.font_size = 10.0
        text.text_color.r, text.text_color.g, text.text_color.b, text.text_color.a = 1, 0.8, 0.1, 1
    return message.SerializeToString(deterministic=True)


@dataclass
class MethodFigures:
    """Running figures of one method's frames, for the summary (:meth:`add` each solved frame)."""

    frames: int = 0
    modes: Counter[str] = field(default_factory=Counter)
    reasons: Counter[str] = field(default_factory=Counter)
    matched: list[int] = field(default_factory=list)
    residuals: list[npt.NDArray[np.float64]] = field(default_factory=list)
    focal: list[float] = field(default_factory=list)
    distortion: list[float] = field(default_factory=list)
    errors: list[npt.NDArray[np.float64]] = field(default_factory=list)
    sigmas: list[npt.NDArray[np.float64]] = field(default_factory=list)
    seconds: float = 0.0
    keep_every: int = 1  # every this many frames, the identified stars are kept for the sky's evidence
    identified: list[IdentifiedFrame] = field(default_factory=list)

    def add(self, result: FrameAttitude, stars: _Centroids, record: dict[str, Any]) -> None:
        self.frames += 1
        if not result.solved or result.camera is None:
            self.reasons[record["reason"].split(" (")[0]] += 1
            return
        if (self.frames - 1) % self.keep_every == 0:
            rows = result.centroid_rows
            self.identified.append(IdentifiedFrame(int(record["frame"]), result.camera, result.catalogue_rows,
                                                   stars.x[rows], stars.y[rows]))
        self.modes[result.mode] += 1
        self.matched.append(result.n_matched)
        self.residuals.append(result.residuals(stars.x, stars.y))
        self.focal.append(result.camera.focal)
        self.distortion.append(result.camera.k)
        if "error_x_arcsec" in record:
            self.errors.append(np.array([record[f"error_{a}_arcsec"] for a in ("x", "y", "roll")]))
            self.sigmas.append(np.array([record[f"sigma_{a}_arcsec"] for a in ("x", "y", "roll")]))

    def to_dict(self, width: int) -> dict[str, Any]:
        solved = sum(self.modes.values())
        res = np.concatenate(self.residuals) if self.residuals else np.zeros((0, 2))
        focal = float(np.median(self.focal)) if self.focal else math.nan
        rms = float(np.sqrt(np.mean(res**2))) if res.size else math.nan
        out: dict[str, Any] = {
            "frames": self.frames, "solved": solved, "lost_in_space": self.modes["lost_in_space"],
            "tracking": self.modes["tracking"], "unsolved": dict(self.reasons),
            "matched_per_frame": float(np.mean(self.matched)) if self.matched else 0.0,
            "residual_px": rms, "residual_arcsec": rms / focal * ARCSEC_PER_RAD if self.focal else math.nan,
            "camera": {"focal_px": focal, "fov_deg": math.degrees(2 * math.atan(width / 2 / focal)) if self.focal
                       else math.nan, "distortion": float(np.median(self.distortion)) if self.distortion else math.nan},
        }
        if self.errors:
            err, sig = np.array(self.errors), np.array(self.sigmas)
            rms_err = np.sqrt(np.mean(err**2, axis=0))
            rms_sig = np.sqrt(np.mean(sig**2, axis=0))
            out["attitude_error"] = {
                "frames": int(err.shape[0]),
                "rms_arcsec": {"x": float(rms_err[0]), "y": float(rms_err[1]), "roll": float(rms_err[2])},
                "sigma_arcsec": {"x": float(rms_sig[0]), "y": float(rms_sig[1]), "roll": float(rms_sig[2])},
                "ratio": {"cross_boresight": float(np.sqrt(np.mean((err[:, :2] / sig[:, :2]) ** 2))),
                          "roll": float(np.sqrt(np.mean((err[:, 2] / sig[:, 2]) ** 2)))}}
        return out


@dataclass
class SolveSummary:
    """What :func:`solve_log` wrote: per centroid method, frames solved, residuals, camera model, and the
    attitude error against the truth on a simulated sky field."""

    width: int
    methods: dict[str, dict[str, Any]] = field(default_factory=dict)
    seconds: dict[str, float] = field(default_factory=dict)  # time spent solving each method's frames (not a result)
    sky_evidence: dict[str, dict[str, Any]] = field(default_factory=dict)
    """Per centroid method, its catalogue residual on the stars every method identified
    (:func:`starlog.attitude.sky_evidence.sky_evidence`); empty with fewer than two centroid channels."""

    def to_dict(self) -> dict[str, Any]:
        return {"methods": self.methods, "sky_evidence": self.sky_evidence}

    def lines(self) -> list[str]:
        """One table: per method the frames solved, stars identified, catalogue residuals and camera model;
        then the attitude error per method when the log has the true attitude."""
        w = max([10] + [len(k) + 1 for k in self.methods])
        lines = [f"{'method':<{w}}{'solved':>12}{'lis':>5}{'track':>7}{'matched':>9}{'resid px':>10}"
                 f"{'arcsec':>9}{'focal px':>10}{'fov deg':>9}{'k':>9}"]
        for method, m in self.methods.items():
            cam = m["camera"]
            lines.append(f"{method:<{w}}{m['solved']:>6}/{m['frames']:<5}{m['lost_in_space']:>5}{m['tracking']:>7}"
                         f"{m['matched_per_frame']:>9.1f}{m['residual_px']:>10.4f}{m['residual_arcsec']:>9.2f}"
                         f"{cam['focal_px']:>10.1f}{cam['fov_deg']:>9.4f}{cam['distortion']:>9.5f}")
            for reason, count in m["unsolved"].items():
                lines.append(f"  {count} frame(s) unsolved: {reason}")
        with_truth = {k: m["attitude_error"] for k, m in self.methods.items() if "attitude_error" in m}
        if with_truth:
            lines.append("attitude error against the true attitude, RMS arcsec (1-sigma from the covariance), "
                         "and RMS error / sigma")
            for method, e in with_truth.items():
                r, s = e["rms_arcsec"], e["sigma_arcsec"]
                lines.append(f"{method:<{w - 1}} x {r['x']:.3f} ({s['x']:.3f})  y {r['y']:.3f} ({s['y']:.3f})  roll "
                             f"{r['roll']:.2f} ({s['roll']:.2f});  cross-boresight {e['ratio']['cross_boresight']:.2f}, "
                             f"roll {e['ratio']['roll']:.2f}  ({e['frames']} frames)")
        return lines + self.compensation_lines() + self.sky_lines()

    def sky_lines(self) -> list[str]:
        """Per centroid method its catalogue residual on the common stars (one camera per log), 95 % interval,
        the fraction of bootstrap draws in which it is the least."""
        if not self.sky_evidence:
            return []
        lines = ["catalogue residual on the stars every method identified, one camera model per log (px per axis, "
                 "95 % bootstrap over stars, least in % of draws)"]
        for method, e in self.sky_evidence.items():
            if e.get("residual_px") is None:
                lines.append(f"  {method:<15} no star identified by every method")
                continue
            lo, hi = e["interval_px"]
            lines.append(f"  {method:<15} {e['residual_px']:.4f} ({lo:.4f}-{hi:.4f})  {100 * e['p_best']:>3.0f} %  "
                         f"{e['stars']} stars, {e['frames']} frames")
        return lines

    def compensation_lines(self) -> list[str]:
        """Per all-star compensated channel solved before and after compensation: the attitude error's RMS
        before -> after (on a simulated sky field)."""
        lines = []
        for name, m in self.methods.items():
            after = self.methods.get(name.removesuffix("/before") + "/after", {})
            if not name.endswith("/before") or "attitude_error" not in m or "attitude_error" not in after:
                continue
            b, a = m["attitude_error"]["rms_arcsec"], after["attitude_error"]["rms_arcsec"]
            lines.append(f"{name.removesuffix('/before')}: attitude error RMS arcsec before -> after compensation: "
                         f"x {b['x']:.3f} -> {a['x']:.3f}, y {b['y']:.3f} -> {a['y']:.3f}, roll {b['roll']:.2f} -> "
                         f"{a['roll']:.2f}")
        return lines


def _frames(log: LogReader, topic: str, which: str | None) -> Iterator[tuple[int, int, _Centroids]]:
    """``(log_time, frame, usable stars)`` of every message of a centroid channel, or with ``which`` of an
    all-star compensated channel."""
    kind = "starlog.Centroids" if which is None else COMPENSATED_STARS
    messages: Iterator[Any] = log.tables(topic) if which is None else log.messages(topic)
    for message in messages:
        try:
            if which is None:
                stars = _Centroids.from_rows(message.rows)
                frame = int(message.header["frame"])
            else:
                stars = _Centroids.from_compensated(message.payload, which)
                frame = int(message.payload["frame"])
        except (KeyError, TypeError, ValueError) as err:
            raise InvalidInputError(f"{topic} at log_time {message.log_time}: not a {kind} message "
                                    f"({err!r}).") from err
        yield message.log_time, frame, stars


def _solve_channel(log: LogReader, out: StageOutput, topic: str, tracker: AttitudeTracker,
                   truth: dict[int, npt.NDArray[np.float64]], *, show_progress: bool,
                   which: str | None = None) -> MethodFigures:
    """Solve every frame of one centroid channel, or with ``which`` (``before``, ``after``) of an all-star
    compensated channel, and write its three channels."""
    method = topic.rsplit("/", 1)[-1] if which is None else compensated_name(topic, which)
    channels = add_solve_channels(out, method)
    count = log.channel(topic).message_count
    figures = MethodFigures(keep_every=sky_frames_kept(count))
    for t, frame, stars in progress(_frames(log, topic, which), total=count, description=f"solve {method}",
                                    enabled=show_progress):
        for channel, data in zip(channels, solve_frame(tracker, method, frame, t, stars, truth.get(t), figures),
                                 strict=True):
            out.writer.write(channel, log_time=t, data=data)
    check_messages_read(log, topic, figures.frames)
    return figures


def add_solve_channels(out: StageOutput, method: str) -> tuple[int, int, int]:
    """The attitude, identified-stars and annotation channels of one solved method, added to ``out``."""
    return (out.add_channel(topics.attitude_topic(method), protobuf_message_type("starlog.Attitude")),
            out.add_channel(topics.identified_topic(method), protobuf_message_type("starlog.IdentifiedStars")),
            out.add_channel(topics.identified_annotations_topic(method),
                            protobuf_message_type("foxglove.ImageAnnotations")))


def usable_centroids(rows: npt.NDArray[np.void]) -> _Centroids:
    """The centroids a frame is solved from (finite, sigma > 0, fitted), of the rows of its ``starlog.Centroids``
    message (:func:`~starlog.codecs.star_tables.decode_table`, :meth:`~starlog.io.reader.LogReader.tables`)."""
    return _Centroids.from_rows(rows)


def sky_frames_kept(frames: int) -> int:
    """Every how many frames of a method's ``frames`` the identified stars are kept for the sky's evidence
    (:attr:`MethodFigures.keep_every`: at most :data:`~starlog.attitude.sky_evidence.MAX_SKY_FRAMES` frames)."""
    return max(1, -(-frames // MAX_SKY_FRAMES))


def solve_frame(tracker: AttitudeTracker, method: str, frame: int, log_time: int, stars: _Centroids,
                truth: npt.NDArray[np.float64] | None, figures: MethodFigures) -> tuple[bytes, bytes, bytes]:
    """One frame solved (:func:`usable_centroids` of its centroid message): its attitude, identified-stars and
    annotation messages, the frame added to ``figures``."""
    start = time.perf_counter()
    result = tracker.solve(stars.x, stars.y, stars.flux, stars.sigma)
    figures.seconds += time.perf_counter() - start
    record = _attitude_record(frame, method, result, stars, truth)
    identified = _identified_record(frame, method, result, stars, tracker.catalogue)
    figures.add(result, stars, record)
    return (star_codec("starlog.Attitude").encode(record),
            star_codec("starlog.IdentifiedStars").encode_dict(identified), _annotations(identified, log_time))


def _chosen_channels(log: LogReader, centroids: str | Sequence[str] | None,
                     compensated: str | Sequence[str] | None) -> list[str]:
    """The centroid channels, then the all-star compensated channels, to solve: with ``compensated`` alone,
    only those."""
    if compensated is not None and centroids is None:
        return select_compensated_channels(log, compensated)
    return select_centroid_channels(log, centroids) + select_compensated_channels(log, compensated)


def solve_parameters(centroids: list[str], options: dict[str, Any], catalogue: Catalogue,
                     compensated: list[str] | None = None) -> dict[str, Any]:
    """The parameters the solve stage records in its provenance."""
    parameters = {"centroids": centroids, "options": options, "catalogue": catalogue.name}
    if compensated is not None:
        parameters["compensated"] = compensated
    return parameters


@windowed(lambda log, options: _chosen_channels(log, options.get("centroids"), options.get("compensated"))[0])
def solve_log(
    input_path: str | os.PathLike[str],
    output_path: str | os.PathLike[str],
    *,
    centroids: str | Sequence[str] | None = None,
    compensated: str | Sequence[str] | None = None,
    options: dict[str, Any] | None = None,
    force: bool = False,
    flatten: bool = False,
    compression: str = "zstd",
    show_progress: bool = False,
) -> SolveSummary:
    """Identify the stars of centroid channel(s) and solve the attitude of every frame (module docstring).

    Parameters
    ----------
    centroids : str or sequence of str, optional
        Centroid methods or topics (``GAUSSFIT``, ``/stars/centroids/GAUSSFIT``, comma-separated), or
        ``"all"``; default: the only one (none when only ``compensated`` is given).
    compensated : str or sequence of str, optional
        All-star compensated channels (``compensate --stars all``): ``RATE/PROTOCOL`` (``50/truth``,
        ``50Hz/paper/separate``), topics, or ``"all"``. Each is solved twice, from the positions before and
        after compensation, on ``/attitude/compensated/<METHOD>/<MODEL>/<RATE>Hz/<protocol>/before`` and
        ``.../after`` (and the identified stars likewise; ``star`` is the track id); on a simulated sky field
        each reports its attitude error against the truth, at the compensated rate's frames.
    options : dict, optional
        Fields of :class:`starlog.attitude.identify.TrackerSettings` (match_radius, min_matches, min_stars,
        fov_deg, focal_px, distortion, fit_distortion, brightest, timeout_ms, try_mirrored, tracking,
        max_magnitude, reject) and ``camera`` (``"auto"``: a simulated sky field's camera from the simulator's
        provenance, else fitted; ``"fit"``).
    start, end : str or int, optional
        Only the range ``start <= log_time < end`` (``frame:N`` counts the first centroid channel).
    """
    solver_data_file()  # a clear error naming the extra before anything is read
    options = dict(options or {})
    with LogReader(input_path) as log:
        chosen = _chosen_channels(log, centroids, compensated)
        kinds = {c.topic: c.schema_name for c in log.channels()}
        rows, cols = _image_shape(log)
        settings = tracker_settings(log, options, cols)
        catalogue = load_catalogue()
        summary = SolveSummary(width=cols)
        stars = None if compensated is None else [t for t in chosen if kinds[t] == COMPENSATED_STARS]
        parameters = solve_parameters([t for t in chosen if kinds[t] != COMPENSATED_STARS], options, catalogue, stars)
        with extend_log(log, output_path, stage="solve", parameters=parameters, force=force, flatten=flatten,
                        compression=compression) as (_, out):
            truth = _true_attitudes(log)
            runs = [(t, w) for t in chosen for w in ((None,) if kinds[t] != COMPENSATED_STARS else ("before", "after"))]
            identified: dict[str, list[IdentifiedFrame]] = {}
            for topic, which in runs:
                tracker = AttitudeTracker(catalogue, (rows, cols), settings)
                figures = _solve_channel(log, out, topic, tracker, truth, show_progress=show_progress, which=which)
                name = topic.rsplit("/", 1)[-1] if which is None else compensated_name(topic, which)
                summary.methods[name] = figures.to_dict(cols)
                summary.seconds[name] = figures.seconds
                if which is None and figures.identified:
                    identified[name] = figures.identified
            if len(identified) >= 2:
                summary.sky_evidence = sky_evidence(identified, tracker.catalogue.vectors, tracker.catalogue.magnitude,
                                                    fit_distortion=settings.fit_distortion)
            out.writer.add_metadata(topics.SOLVE_METADATA, {"methods": json.dumps(summary.methods),
                                                            "sky_evidence": json.dumps(summary.sky_evidence)})
        return summary


def probe_sky(log: LogReader, centroid_topics: Sequence[str], *, frames: int = PROBE_FRAMES
              ) -> tuple[dict[str, dict[str, Any]] | None, str]:
    """The sky's evidence on a log's centroid methods without writing a layer: up to ``frames`` frames, evenly
    spaced, of each centroid channel solved in memory as :func:`solve_log` solves them, and the methods'
    catalogue residuals on the stars all identified (:func:`starlog.attitude.sky_evidence.sky_evidence`).
    ``(None, why)`` when there is none: cedar-solve is not installed, the log is a simulated field without a
    sky, or the first method's first frames do not solve."""
    if len(centroid_topics) < 2:
        return None, "one centroid method: the sky compares two or more"
    try:
        solver_data_file()
    except InvalidParameterError:
        return None, "cedar-solve is not installed (pip install 'starlog[solve]')"
    if any(r.stage == "simulate" and r.parameters.get("sky_attitude") is None for r in log.provenance()):
        return None, "a simulated star field without a sky (simulate --sky-attitude makes one)"
    rows, cols = _image_shape(log)
    settings = tracker_settings(log, {}, cols)
    catalogue = load_catalogue()
    stride = max(1, -(-log.channel(centroid_topics[0]).message_count // frames))
    identified: dict[str, list[IdentifiedFrame]] = {}
    for k, topic in enumerate(centroid_topics):
        tracker = AttitudeTracker(catalogue, (rows, cols), replace(settings, tracking=False))
        found, tried = [], 0
        for message in itertools.islice(log.tables(topic), 0, None, stride):
            stars = _Centroids.from_rows(message.rows)
            result = tracker.solve(stars.x, stars.y, stars.flux, stars.sigma)
            tried += 1
            if result.solved and result.camera is not None:
                rows_ = result.centroid_rows
                found.append(IdentifiedFrame(int(message.header["frame"]), result.camera, result.catalogue_rows,
                                             stars.x[rows_], stars.y[rows_]))
            elif k == 0 and not found and tried >= _PROBE_TRIES:
                return None, f"the first {tried} frames probed did not plate-solve ({result.reason})"
        if not found:
            return None, f"no frame probed of {topic} plate-solved"
        identified[topic.rsplit("/", 1)[-1]] = found
    return sky_evidence(identified, tracker.catalogue.vectors, tracker.catalogue.magnitude,
                        fit_distortion=settings.fit_distortion), ""
