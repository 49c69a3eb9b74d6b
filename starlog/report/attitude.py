"""The report's attitude section: per centroid method the attitude series, the catalogue residuals with the
camera model, and the attitude error against the truth on simulated sky (from ``starlog solve``'s channels)."""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from html import escape

import numpy as np
import numpy.typing as npt

from starlog.io.reader import ChannelSummary, LogReader
from starlog.report.figures import PALETTE, Series, line_chart
from starlog.report.page import figure, missing, table

__all__ = ["AttitudeSeries", "attitude_section", "read_attitude"]

_COLUMNS = ("ra_deg", "dec_deg", "roll_deg", "n_matched", "residual_px", "residual_arcsec", "focal_px", "distortion",
            "fov_deg", "sigma_x_arcsec", "sigma_y_arcsec", "sigma_roll_arcsec")
_ERRORS = ("error_x_arcsec", "error_y_arcsec", "error_roll_arcsec")


@dataclass
class AttitudeSeries:
    """One ``/attitude/<METHOD>`` channel as columns (solved frames only), with the unsolved frames' reasons."""

    frames: int
    t: npt.NDArray[np.float64]  # s from the log's start
    columns: dict[str, npt.NDArray[np.float64]]
    modes: Counter[str]
    unsolved: Counter[str]

    @property
    def has_truth(self) -> bool:
        return all(k in self.columns for k in _ERRORS)


def read_attitude(log: LogReader, channels: list[ChannelSummary], t0: int) -> dict[str, AttitudeSeries]:
    """Every ``starlog.Attitude`` channel of the log, by method."""
    out = {}
    for channel in channels:
        if channel.schema_name != "starlog.Attitude":
            continue
        times, rows, modes, unsolved, frames = [], [], Counter(), Counter(), 0
        for message in log.messages(channel.topic):
            r = message.payload
            frames += 1
            if not r["solved"]:
                unsolved[r["reason"].split(" (")[0]] += 1
                continue
            modes[r["mode"]] += 1
            times.append((message.log_time - t0) * 1e-9)
            rows.append([r[k] for k in _COLUMNS] + [r.get(k, np.nan) for k in _ERRORS])
        table_ = np.array(rows, dtype=np.float64).reshape(-1, len(_COLUMNS) + len(_ERRORS))
        columns = {k: table_[:, i] for i, k in enumerate(_COLUMNS)}
        if table_.shape[0] and np.isfinite(table_[:, len(_COLUMNS):]).all():
            columns.update({k: table_[:, len(_COLUMNS) + i] for i, k in enumerate(_ERRORS)})
        out[channel.topic.rsplit("/", 1)[-1]] = AttitudeSeries(frames, np.array(times), columns, modes, unsolved)
    return out


def _rms(values: npt.NDArray[np.float64]) -> float:
    return float(np.sqrt(np.mean(values**2))) if values.size else float("nan")


def _residual_table(series: dict[str, AttitudeSeries]) -> str:
    rows = []
    for method, s in series.items():
        c = s.columns
        solved = int(c["ra_deg"].size)
        weights = c["n_matched"]
        pooled = float(np.sqrt(np.sum(weights * c["residual_px"] ** 2) / weights.sum())) if solved else float("nan")
        pooled_arcsec = (float(np.sqrt(np.sum(weights * c["residual_arcsec"] ** 2) / weights.sum())) if solved
                         else float("nan"))
        median = (lambda k: round(float(np.median(c[k])), 6) if solved else "—")  # noqa: E731
        why = "; ".join(f"{n} {escape(reason)}" for reason, n in s.unsolved.items()) or "—"
        rows.append([method, f"{solved}/{s.frames}", s.modes["lost_in_space"], s.modes["tracking"],
                     round(float(weights.mean()), 1) if solved else "—", round(pooled, 4), round(pooled_arcsec, 3),
                     median("focal_px"), median("fov_deg"), median("distortion"), why])
    return table(["method", "solved", "lost in space", "tracked", "stars matched / frame", "residual RMS (px)",
                  "residual RMS (arcsec)", "focal length (px)", "field of view (deg)", "distortion k", "unsolved"],
                 rows)


def _error_table(series: dict[str, AttitudeSeries]) -> str:
    rows = []
    for method, s in series.items():
        if not s.has_truth:
            continue
        c = s.columns
        cross = np.concatenate([c["error_x_arcsec"] / c["sigma_x_arcsec"], c["error_y_arcsec"] / c["sigma_y_arcsec"]])
        rows.append([method, round(_rms(c["error_x_arcsec"]), 4), round(_rms(c["error_y_arcsec"]), 4),
                     round(_rms(c["error_roll_arcsec"]), 3), round(_rms(c["sigma_x_arcsec"]), 4),
                     round(_rms(c["sigma_y_arcsec"]), 4), round(_rms(c["sigma_roll_arcsec"]), 3), round(_rms(cross), 2),
                     round(_rms(c["error_roll_arcsec"] / c["sigma_roll_arcsec"]), 2)])
    if not rows:
        return ""
    return ("<p>Attitude error against the simulator's true attitude (RMS over the solved frames) beside the "
            "1-sigma the q-method's covariance predicts from the centroids' sigmas; a ratio near 1 means the "
            "centroids' sigmas describe their errors.</p>"
            + table(["method", "error x (arcsec)", "error y (arcsec)", "error roll (arcsec)", "sigma x (arcsec)",
                     "sigma y (arcsec)", "sigma roll (arcsec)", "cross-boresight error / sigma", "roll error / sigma"],
                    rows))


def _series_figure(method: str, s: AttitudeSeries) -> str:
    c = s.columns
    cos_dec = np.cos(np.radians(np.median(c["dec_deg"])))
    ra = (c["ra_deg"] - np.median(c["ra_deg"]) + 180.0) % 360.0 - 180.0
    roll = (c["roll_deg"] - np.median(c["roll_deg"]) + 180.0) % 360.0 - 180.0
    series = [Series("RA cos(Dec)", s.t, ra * cos_dec * 3600.0, PALETTE[0]),
              Series("Dec", s.t, (c["dec_deg"] - np.median(c["dec_deg"])) * 3600.0, PALETTE[1]),
              Series("roll / 10", s.t, roll * 360.0, PALETTE[2])]
    title = f"attitude from {method} centroids, about its median"
    return figure(line_chart(series, title=title, x_label="time (s)", y_label="arcsec", robust=True),
                  f"RA (times cos Dec), Dec and roll (divided by 10) of every solved frame from {escape(method)} "
                  "centroids, about their medians.", f"attitude_{method}")


def attitude_section(series: dict[str, AttitudeSeries]) -> str:
    """The section's HTML: the attitude series of the first method, the residual table, the error table."""
    if not series:
        return missing("This log has no attitude channel (/attitude/<METHOD>): `starlog solve` identifies the stars "
                       "of centroid channels in a catalogue and solves the attitude.")
    first = next((m for m in ("GAUSSFIT", *series) if m in series and series[m].columns["ra_deg"].size), None)
    out = _series_figure(first, series[first]) if first else ""
    out += ("<p>Catalogue residuals per centroid method: the identified stars' measured positions minus the "
            "catalogue's projected through each frame's attitude and the fitted camera, pooled over the frames "
            "(per axis, weighted by the stars matched): a truth-free accuracy figure of each method.</p>")
    return out + _residual_table(series) + _error_table(series)
