"""The regime map: where the paper's compensation helps, where it harms, and what ``separate`` changes.

A sweep over simulated logs (``starlog experiment --sweep``): platform jitter from 0 to 10 times
the centroid noise, 3, 6 and 20 stars, decimated to 10 and 50 Hz, every UKF model; for each,
the compensation gain (eq. 13) of ``keep`` (the paper's method) and ``separate`` (compensate the
residual from the motion fitted to the other stars, :mod:`starlog.platform_motion`) under ``truth``
(``truth_series``, ``truth_fixed``), ``leakfree`` (``heldout_mean``) and ``relative``.

One task per (star count, jitter ratio): simulate → centroid (GAUSSFIT) → track (all models) →
score; tasks are plain functions of plain data, run serially or on the experiment's executor.

The centroid noise ``σ`` (per axis) is measured once on a jitter-free calibration log with the
same stars; a jitter ratio ``r`` puts two sinusoids (2.3 Hz and 13 Hz, equal power) of total
RMS ``r σ`` per axis on the platform.  The tracker's ``sigma_floor`` is ``max(0.05 px, 2 ×
jitter RMS)`` so the STATIC model does not gate the star away.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from concurrent.futures import Executor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
from tqdm import tqdm

from starlog.compensation import MotionMode, ScoringProtocol, sampled_rate
from starlog.errors import OutputExistsError
from starlog.experiment.parquet import write_rows
from starlog.experiment.runner import MODELS
from starlog.io.reader import LogReader
from starlog.report.experiment_figures import plot_regime_map
from starlog.report.log_report import write_text_atomic
from starlog.sim import Jitter, SimulationConfig, Simulator
from starlog.stages import simulate_log
from starlog.stages.centroid import centroid_log
from starlog.stages.compensate import evaluate_series, read_brightest_series, with_platform_reference
from starlog.stages.track import track_log

__all__ = ["REGIME_FIELDS", "RegimeSummary", "centroid_noise", "regime_configs", "regime_task", "run_regime_map",
           "write_regime_parquet"]

RATIOS: tuple[float, ...] = (0.0, 0.5, 1.0, 2.0, 5.0, 10.0)
STARS: tuple[int, ...] = (3, 6, 20)
RATES: tuple[float, ...] = (10.0, 50.0)
PROTOCOLS = (ScoringProtocol.TRUTH, ScoringProtocol.LEAKFREE, ScoringProtocol.RELATIVE)
#: The four figures the map shows: (protocol, reference).
FIGURES = (("truth", "truth_series"), ("truth", "truth_fixed"), ("leakfree", "heldout_mean"),
           ("relative", "relative"))
_JITTER_HZ = (2.3, 13.0)

REGIME_FIELDS: dict[str, tuple[pa.DataType, str]] = {
    "stars": (pa.int64(), "stars in the simulated field"),
    "jitter_ratio": (pa.float64(), "platform jitter RMS per axis / centroid noise per axis"),
    "jitter_rms_px": (pa.float64(), "platform jitter RMS per axis, px"),
    "noise_px": (pa.float64(), "centroid noise per axis (GAUSSFIT, jitter-free calibration log), px"),
    "model": (pa.string(), "UKF motion model"),
    "rate_hz": (pa.float64(), "down-sample rate, Hz"),
    "motion": (pa.string(), "keep (the paper's method) or separate"),
    "protocol": (pa.string(), "truth, leakfree or relative"),
    "reference": (pa.string(), "truth_series, truth_fixed, heldout_mean or relative"),
    "n_scored": (pa.int64(), "samples scored"),
    "rmse_before": (pa.float64(), "eq. 15 before compensation, px"),
    "rmse_after": (pa.float64(), "eq. 15 after compensation, px"),
    "effective": (pa.float64(), "eq. 13 gain, fraction (negative: compensation made it worse)"),
}
"""Columns of ``regime_map.parquet``: name -> (Arrow type, description with unit)."""


def _base(n_stars: int, quick: bool) -> dict[str, Any]:
    size = 96 if quick else (128 if n_stars < 20 else 192)
    return {"width": size, "height": size, "n_stars": n_stars, "fps": 100.0, "n_frames": 400 if quick else 600,
            "flux_min": 20_000.0, "flux_max": 20_000.0, "margin": 12.0}


def _separated_seed(base: dict[str, Any], min_px: float = 12.0) -> int:
    """The first seed whose stars are all ``min_px`` apart (blended stars swap tracks)."""
    for seed in range(200):
        sim = Simulator(SimulationConfig(**{**base, "n_frames": 1}, seed=seed))
        p = np.column_stack([sim.field.x, sim.field.y])
        d = np.hypot(*(p[:, None] - p[None]).transpose(2, 0, 1)) + np.eye(len(p)) * 1e9
        if d.min() >= min_px:
            return seed
    return 0


def centroid_noise(work: Path, *, quick: bool) -> float:
    """Per-axis GAUSSFIT centroid noise of a jitter-free field of the sweep's stars, px (vs the truth)."""
    base = {**_base(6, quick), "n_frames": 100}
    config = SimulationConfig(**base, seed=_separated_seed(base))
    sim, cen = work / "noise-sim.mcap", work / "noise-cen.mcap"
    simulate_log(config, sim, force=True)
    centroid_log(sim, cen, methods=["GAUSSFIT"], force=True, mode="full")  # the paper extracts every frame
    errors = []
    with LogReader(cen) as log:
        truth = {m.log_time: m.payload["stars"] for m in log.messages("/sim/truth")}
        for message in log.messages("/stars/centroids/GAUSSFIT"):
            true = np.array([(s["x"], s["y"]) for s in truth[message.log_time]])
            for s in message.payload["stars"]:
                d = true - (s["x"], s["y"])
                errors.append(d[np.argmin(np.hypot(*d.T))])
    sim.unlink()
    cen.unlink()
    return float(np.sqrt(np.mean(np.square(errors))))


def regime_configs(noise_px: float, *, quick: bool) -> list[dict[str, Any]]:
    """One task spec per (stars, jitter ratio): the simulation config and the tracker floor."""
    specs = []
    ratios = (0.0, 1.0, 5.0) if quick else RATIOS
    for n_stars in ((3, 6) if quick else STARS):
        base = _base(n_stars, quick)
        seed = _separated_seed(base)
        for ratio in ratios:
            rms = ratio * noise_px
            amplitude = rms  # two sinusoids of peak a each: RMS per axis a (a²/2 + a²/2)
            jitter = tuple(Jitter(f, amplitude) for f in _JITTER_HZ) if rms > 0 else ()
            config = SimulationConfig(**base, seed=seed, jitter=jitter)
            specs.append({"stars": n_stars, "jitter_ratio": ratio, "jitter_rms_px": rms, "noise_px": noise_px,
                          "sigma_floor": max(0.05, 2.0 * rms), "config": config.to_dict()})
    return specs


def regime_task(spec: dict[str, Any], work: str) -> list[dict[str, Any]]:
    """Simulate, centroid, track and score one (stars, jitter ratio) cell of the map; return its rows."""
    config = SimulationConfig.from_dict(spec["config"])
    name = f"regime-{spec['stars']}stars-{spec['jitter_ratio']:g}"
    sim, cen, trk = (Path(work) / f"{name}-{s}.mcap" for s in ("sim", "cen", "trk"))
    simulate_log(config, sim, force=True)
    centroid_log(sim, cen, methods=["GAUSSFIT"], force=True, mode="full")
    track_log(cen, trk, method="GAUSSFIT", models=list(MODELS), tracker={"sigma_floor": spec["sigma_floor"]},
              force=True)
    head = {k: spec[k] for k in ("stars", "jitter_ratio", "jitter_rms_px", "noise_px")}
    rows: list[dict[str, Any]] = []
    with LogReader(trk) as log:
        cache: dict[int, Any] = {}
        for model in MODELS:
            topic = f"/track/GAUSSFIT/{model}"
            series = with_platform_reference(log, read_brightest_series(log, topic, truth_cache=cache), topic)
            rows += _score(series, {**head, "model": model})
    for path in (sim, cen, trk):
        path.unlink()
    return rows


def _score(series: Any, head: dict[str, Any]) -> list[dict[str, Any]]:
    rows = []
    for rate in RATES:
        idx = series.indices(rate)
        rate_hz = sampled_rate(idx, native_rate=series.native_rate)
        for protocol in PROTOCOLS:
            for motion in MotionMode:
                ev = evaluate_series(series, idx, rate_hz=rate_hz, protocol=protocol, motion=motion,
                                     accuracy_source="sigma")
                rows += [{**head, "rate_hz": rate, "motion": motion.value, "protocol": protocol.value,
                          "reference": f.reference, "n_scored": f.n_scored, "rmse_before": f.rmse_before,
                          "rmse_after": f.rmse_after, "effective": f.effective}
                         for f in ev.figures if (protocol.value, f.reference) in FIGURES]
    return rows


def write_regime_parquet(rows: Sequence[dict[str, Any]], path: str | os.PathLike[str]) -> Path:
    """``regime_map.parquet`` with :data:`REGIME_FIELDS` (descriptions as field metadata)."""
    return write_rows(rows, REGIME_FIELDS, path)


def median_gains(rows: Sequence[dict[str, Any]]) -> dict[tuple[Any, ...], float]:
    """Median gain over the UKF models per (protocol, reference, rate, motion, stars, ratio)."""
    cells: dict[tuple[Any, ...], list[float]] = {}
    for r in rows:
        key = (r["protocol"], r["reference"], r["rate_hz"], r["motion"], r["stars"], r["jitter_ratio"])
        cells.setdefault(key, []).append(r["effective"])
    return {k: float(np.median(v)) for k, v in cells.items()}


def regime_markdown(rows: Sequence[dict[str, Any]]) -> str:
    """One table per figure: median gain over the UKF models, keep / separate, per stars × jitter ratio."""
    gains = median_gains(rows)
    ratios = sorted({r["jitter_ratio"] for r in rows})
    stars = sorted({r["stars"] for r in rows})
    out = ["# Regime map: median compensation gain over the five UKF models (keep / separate)", ""]
    for protocol, reference in FIGURES:
        for rate in RATES:
            out += [f"## {protocol} / {reference}, {rate:g} Hz", "",
                    "| stars | " + " | ".join(f"jitter {x:g}σ" for x in ratios) + " |",
                    "| --- |" + " --- |" * len(ratios)]
            for n in stars:
                cells = []
                for x in ratios:
                    k, s = (gains.get((protocol, reference, rate, m, n, x), math.nan) for m in ("keep", "separate"))
                    cells.append(f"{100 * k:.0f} % / {100 * s:.0f} %")
                out.append(f"| {n} | " + " | ".join(cells) + " |")
            out.append("")
    return "\n".join(out)


@dataclass
class RegimeSummary:
    """What :func:`run_regime_map` wrote: the noise it measured, the cells, the files and the gains."""

    output_dir: Path
    noise_px: float
    cells: int
    rows: list[dict[str, Any]] = field(default_factory=list)
    files: dict[str, str] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return {"output_dir": str(self.output_dir), "noise_px": self.noise_px, "cells": self.cells,
                "files": self.files, "rows": self.rows}

    def text(self) -> str:
        return (f"regime map: {self.cells} logs, centroid noise {self.noise_px:.4f} px per axis; "
                f"{len(self.rows)} rows\n" + "\n".join(f"  {k}: {v}" for k, v in self.files.items()))


def run_regime_map(output_dir: str | os.PathLike[str], *, quick: bool = False, executor: Executor | None = None,
                   force: bool = False, show_progress: bool = False) -> RegimeSummary:
    """Run the sweep; write ``regime_map.parquet``, ``regime_map.md`` and ``regime_map.png`` in ``output_dir``."""
    out = Path(output_dir)
    if (out / "regime_map.parquet").exists() and not force:
        raise OutputExistsError(out / "regime_map.parquet")
    work = out / "regime_logs"
    work.mkdir(parents=True, exist_ok=True)
    noise = centroid_noise(work, quick=quick)
    specs = regime_configs(noise, quick=quick)
    rows: list[dict[str, Any]] = []
    with tqdm(total=len(specs), desc="regime map", unit="log", disable=None if show_progress else True) as bar:
        if executor is None:
            for spec in specs:
                rows += regime_task(spec, str(work))
                bar.update()
        else:
            for future in [executor.submit(regime_task, spec, str(work.resolve())) for spec in specs]:
                rows += future.result()
                bar.update()
    rows.sort(key=lambda r: (r["stars"], r["jitter_ratio"], MODELS.index(r["model"]), r["rate_hz"], r["protocol"],
                             r["reference"], r["motion"]))
    files = {"parquet": str(write_regime_parquet(rows, out / "regime_map.parquet")),
             "markdown": str(out / "regime_map.md"),
             "plot": str(plot_regime_map(rows, median_gains(rows), FIGURES, RATES, out / "regime_map.png"))}
    write_text_atomic(out / "regime_map.md", regime_markdown(rows) + "\n")
    work.rmdir()
    return RegimeSummary(out, noise, len(specs), rows, files)
