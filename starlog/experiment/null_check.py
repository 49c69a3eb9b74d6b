"""The null check: what each protocol reports when there is nothing to correct.

Two series with no error a compensation could remove are compensated under every protocol,
exactly as the sweep compensates the datasets (same rates, window, burn-in and options):

``white_noise``
    Independent Gaussian samples, 0.1 px per axis about a fixed true position: no systematic
    error, no dynamics.  The truth is that position.
``motionless_star``
    The regime's camera and star field with the platform perturbations switched off
    (48×48 px, 2 stars, the window plus the start-up, at most the dataset's length), through ``centroid`` (NONE) and ``track`` (STATIC, the regime's
    tracker settings): the only errors are the centroid's noise and its fixed pixel-phase bias.

A protocol that reports a large gain on these reports the smoothing of noise about its own
mean, not an accuracy gain.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa

from starlog.compensation import MAX_BURN_IN_S, protocols_for
from starlog.compensation.protocols import evaluate
from starlog.sim import SimulationConfig
from starlog.experiment.parquet import write_rows

__all__ = ["NULL_FIELDS", "NULL_RATES", "markdown", "run_null_check", "sort_records", "text_lines", "write_parquet"]

#: Rates of the null check, Hz.
NULL_RATES: tuple[float, ...] = (10.0, 50.0)
_NOISE_PX = 0.1
_NOISE_SEED = 20240601
_CASES = ("white_noise", "motionless_star")

NULL_FIELDS: dict[str, tuple[pa.DataType, str]] = {
    "regime": (pa.string(), "dataset regime whose camera and settings were used"),
    "case": (pa.string(), "white_noise or motionless_star"),
    "rate_hz": (pa.float64(), "down-sample rate, Hz"),
    "protocol": (pa.string(), "evaluation protocol"),
    "reference": (pa.string(), "RMSE reference"),
    "n_scored": (pa.int64(), "samples scored"),
    "rmse_before": (pa.float64(), "eq. 15 before, px"),
    "rmse_after": (pa.float64(), "eq. 15 after, px"),
    "effective": (pa.float64(), "eq. 13 gain, fraction"),
    "kept": (pa.string(), "strategies kept, '>'-separated"),
}


def _white_noise(regime: str, *, window_s: float | None, compensation: dict[str, Any]) -> list[dict[str, Any]]:
    out = []
    duration = window_s if window_s is not None else 10.0
    for rate in NULL_RATES:
        n = int(np.floor(duration * rate + 0.5))
        rng = np.random.default_rng([_NOISE_SEED, int(rate)])
        truth = np.zeros(2)
        xy = truth + _NOISE_PX * rng.standard_normal((n, 2))
        for protocol in protocols_for(has_truth=True):
            truth_kw = {} if protocol.value == "paper" else {"truth_fixed": truth, "truth_series": np.zeros((n, 2))}
            ev = evaluate(xy, rate_hz=rate, protocol=protocol, **truth_kw, **compensation)
            out += [{"regime": regime, "case": "white_noise", "rate_hz": rate, "protocol": protocol.value,
                     "reference": f.reference, "n_scored": f.n_scored, "rmse_before": f.rmse_before,
                     "rmse_after": f.rmse_after, "effective": f.effective,
                     "kept": ">".join(str(s) for s in ev.result.kept)} for f in ev.figures]
    return out


def _motionless_config(dataset: dict[str, Any], window_s: float | None) -> SimulationConfig:
    config = SimulationConfig.from_dict(dataset["config"])
    seconds = (window_s if window_s is not None else 6.0) + MAX_BURN_IN_S + 0.2
    n_frames = min(config.n_frames, int(round(seconds * config.fps)))  # no longer than the dataset
    return replace(config, width=48, height=48, n_stars=2, jitter=(), random_walk_px_per_sqrt_s=0.0,
                   drift_px_per_s=(0.0, 0.0), n_frames=n_frames)


def run_null_check(dataset: dict[str, Any], logs_dir: str, *, compensation: dict[str, Any] | None = None,
                   window_s: float | None = 6.0, burn_in: str | float = "auto",
                   force: bool = False) -> list[dict[str, Any]]:
    """Task: both null cases for one regime (``dataset`` is a :meth:`Dataset.to_dict` of it); the
    motionless star's start-up is skipped per ``burn_in`` (:func:`starlog.compensation.parse_burn_in`).

    Writes ``<regime>_null_{sim,centroids,track}.mcap`` into ``logs_dir``; returns rows of
    :data:`NULL_FIELDS`.
    """
    from starlog.experiment.runner import simulate_and_centroid, track_and_score

    regime = dataset["regime"]
    options = dict(compensation or {})
    rows = _white_noise(regime, window_s=window_s, compensation=options)
    logs = Path(logs_dir)
    config = _motionless_config(dataset, window_s)
    paths = {k: str(logs / f"{regime}_null_{k}.mcap") for k in ("sim", "centroids", "track")}
    simulate_and_centroid({**dataset, "config": config.to_dict()}, paths["sim"], paths["centroids"],
                          methods=["NONE"], force=force)
    result = track_and_score(paths["centroids"], paths["track"], dataset=dataset["name"], regime=regime,
                             method="NONE", models=["STATIC"], tracker=dict(dataset.get("tracker", {})),
                             motion=dict(dataset.get("motion", {})), rates_uncompensated=[],
                             rates_compensated=list(NULL_RATES), window_s=window_s, compensation=options,
                             burn_in=burn_in, force=force)
    window = f"{window_s:g}s" if window_s is not None else "full"
    rows += [{"regime": regime, "case": "motionless_star", "rate_hz": r["rate_hz"], "protocol": r["protocol"],
              "reference": r["reference"], "n_scored": r["n_scored"], "rmse_before": r["rmse_before"],
              "rmse_after": r["rmse_after"], "effective": r["effective"], "kept": r["kept"]}
             for r in result["rows"] if r["window"] == window and r["burn_in"] == "skipped" and r["compensated"]]
    return rows


_PROTOCOL_ORDER = {"paper": 0, "truth": 1, "leakfree": 2}
_REFERENCE_ORDER = {"global_mean": 0, "heldout_mean": 1, "truth_fixed": 2, "truth_series": 3}


def sort_records(rows: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """Null-check rows in a canonical order (regime, case, rate, protocol, reference)."""
    return sorted(rows, key=lambda r: ({"paper": 0, "modern": 1}.get(r["regime"], 9), r["regime"],
                                       _CASES.index(r["case"]), r["rate_hz"], _PROTOCOL_ORDER[r["protocol"]],
                                       _REFERENCE_ORDER[r["reference"]]))


def write_parquet(rows: Sequence[dict[str, Any]], path: str | Path) -> Path:
    """The null-check rows as zstd Parquet (:data:`NULL_FIELDS`)."""
    return write_rows(rows, NULL_FIELDS, path)


def markdown(rows: Sequence[dict[str, Any]]) -> str:
    """The null check as a Markdown table (gain per case, rate, protocol and reference)."""
    lines = ["| regime | case | rate/Hz | protocol | reference | N | before | after | gain | kept |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['regime']} | {r['case']} | {r['rate_hz']:g} | {r['protocol']} | {r['reference']} | "
                     f"{r['n_scored']} | {r['rmse_before']:.4f} | {r['rmse_after']:.4f} | "
                     f"{100 * r['effective']:+.0f}% | {r['kept'] or '—'} |")
    return "\n".join(lines)


def text_lines(rows: Sequence[dict[str, Any]]) -> list[str]:
    """Command-line lines: the primary figure's gain of each case, rate and protocol."""
    primary = {"paper": "global_mean", "truth": "truth_fixed", "leakfree": "heldout_mean"}
    out = ["null check (nothing to correct): gain per protocol"] if rows else []
    for r in rows:
        if r["reference"] == primary[r["protocol"]]:
            out.append(f"  {r['regime']:7} {r['case']:16} {r['rate_hz']:>4g} Hz {r['protocol']:9} "
                       f"{100 * r['effective']:+5.0f}%  ({r['rmse_before']:.4f} -> {r['rmse_after']:.4f} px)")
    return out
