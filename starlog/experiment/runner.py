"""The sweep behind the paper's Tables 2–4 and Figure 5: independent runs as picklable tasks.

One experiment is three kinds of run, each a top-level function taking plain arguments (paths,
dicts, lists) and returning plain data, so the same code runs serially, on a
``ProcessPoolExecutor`` or on a Dask cluster (``Client.get_executor()``; the workers must see
the output directory):

1. :func:`simulate_and_centroid` — per dataset: ``simulate`` then ``centroid`` (all five
   sub-pixel methods);
2. :func:`track_and_score` — per dataset × centroid method: ``track`` (all five UKF models
   for ``NONE``; for the other methods only the model that did best in Table 2 of the same
   regime, :func:`best_table2_model` — what Table 3 uses), then, for each
   model, the brightest star's series is decimated to every rate and scored under the
   ``paper``, ``truth`` and ``leakfree`` protocols, uncompensated and compensated
   (:func:`starlog.stages.compensate.evaluate_series`, the ``compensate`` stage's own scoring);
3. :func:`compensate_showcase` — per dataset: the ``compensate`` stage on NONE and the best model
   at the paper's rates, leaving a log with every decision record and compensated series
   (for Foxglove), and a cross-check of the sweep.

Which samples are scored (``window_s``)
    The paper's "Image number" column (60 samples at 10 Hz, 300 at 50 Hz) implies about 6 s
    of data, not the 10.8 s / 15.1 s its frame counts give.  Each decimated sequence is scored
    over its first ``floor(window_s · f + 0.5)`` samples, ``f`` the requested rate (``window_s``
    = 6 s by default: 60 at 10 Hz, 300 at 50 Hz, 600 at 100 Hz; 180 at 30 Hz where the paper prints 200), and
    every run is *also* scored over the whole sequence (``window = "full"``); the tables use
    the 6 s window, ``results.parquet`` has both.

Results are rows of :data:`RESULT_FIELDS`; their order does not depend on the executor or on
completion order (they are sorted on their keys).
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from starlog.compensation import (
    MIN_SAMPLES,
    BurnInSetting,
    Evaluation,
    ScoringProtocol,
    burn_in_label,
    protocol_figures,
    protocols_for,
    sampled_rate,
    scored_start,
)
from starlog.errors import InvalidInputError
from starlog.io.reader import LogReader
from starlog.sim import SimulationConfig
from starlog.stages import simulate_log
from starlog.stages.centroid import centroid_log
from starlog.stages.compensate import BrightestSeries, compensate_log, evaluate_series, read_brightest_series
from starlog.stages.track import track_log

__all__ = [
    "COMPENSATED_RATES",
    "FIGURE5_RATES",
    "METHODS",
    "MIN_COMPENSATED",
    "MODELS",
    "PROTOCOL_REFERENCES",
    "RESULT_FIELDS",
    "TABLE2_RATES",
    "TABLE3_RATES",
    "TABLE4_RATE",
    "TIE_FRACTION",
    "UNCOMPENSATED_RATES",
    "WINDOW_S",
    "best_table2_model",
    "compensate_showcase",
    "path_str",
    "simulate_and_centroid",
    "sort_rows",
    "track_and_score",
    "uncompensated_figures",
]

#: Sub-pixel methods, in the order of the paper's Table 3 (NONE first).
METHODS: tuple[str, ...] = ("NONE", "BICUBIC", "GAUSSFIT", "GRADIENT", "MOMENT")
#: UKF motion models, in the order of the paper's Table 2.
MODELS: tuple[str, ...] = ("STATIC", "RANDOM_WALK", "BROWNIAN_MOTION", "POLYNOMIAL_TREND", "CONSTANT_VELOCITY")
#: Table 2's rates (uncompensated), Hz.
TABLE2_RATES: tuple[float, ...] = (5.0, 10.0)
#: Table 3's rates, Hz.
TABLE3_RATES: tuple[float, ...] = (10.0, 20.0, 30.0, 40.0, 50.0)
#: Table 4's rate, Hz.
TABLE4_RATE: float = 50.0
#: Figure 5's rates, Hz.
FIGURE5_RATES: tuple[float, ...] = tuple(float(r) for r in range(10, 101, 10))
#: Rates scored uncompensated only (too few samples for the leak-free calibration split).
UNCOMPENSATED_RATES: tuple[float, ...] = (5.0,)
#: Rates scored before and after compensation.
COMPENSATED_RATES: tuple[float, ...] = FIGURE5_RATES
#: Fewest samples a compensated rate needs: 16 calibration + 16 scored samples under ``leakfree``
#: (:data:`starlog.compensation.MIN_SAMPLES` each); shorter series are scored uncompensated.
MIN_COMPENSATED: int = 2 * MIN_SAMPLES
#: The two burn-in variants: (label, skip the filter's start-up); ``kept`` is scored on the
#: tables' window only.
BURN_IN_VARIANTS: tuple[tuple[str, bool], ...] = (("skipped", True), ("kept", False))
#: Table 2 means closer than this fraction to the lowest are a tie (:func:`best_table2_model`).
TIE_FRACTION: float = 1e-3
#: Default scoring window, s (the paper's "Image number" column).
WINDOW_S: float = 6.0
#: The RMSE figures of each protocol, primary first (:func:`starlog.compensation.protocol_figures`).
PROTOCOL_REFERENCES: dict[str, tuple[str, ...]] = {
    "paper": ("global_mean",),
    "truth": ("truth_fixed", "truth_series"),
    "leakfree": ("heldout_mean", "truth_fixed", "truth_series"),
}

RESULT_FIELDS: dict[str, str] = {
    "regime": "dataset regime: 'paper' (derived from the paper's numbers) or 'modern'",
    "dataset": "dataset name, '300Hz' or '200Hz' (native frame rate)",
    "method": "sub-pixel centroid method (NONE, BICUBIC, GAUSSFIT, GRADIENT, MOMENT)",
    "model": "UKF motion model",
    "window": "scored samples: '6s' (first window_s seconds, the paper's image numbers) or 'full'",
    "burn_in": "'skipped': the decimated series starts after the filter's start-up (the tables); 'kept': at frame 0",
    "burn_in_samples": "native frames skipped as the filter's start-up (0 when kept)",
    "burn_in_setting": "what 'skipped' skips (--burn-in): 'auto' (the filter's variance rule), 'off' or '<seconds> s'",
    "rate_hz": "requested down-sample rate, Hz",
    "effective_rate_hz": "mean rate of the kept samples, native rate × (N - 1) / (last - first frame index), Hz",
    "n_samples": "decimated samples in the window",
    "compensated": "True when the adaptive compensation was run (False: uncompensated rate, or fewer than 32 samples)",
    "protocol": "evaluation protocol: paper, truth or leakfree",
    "reference": "what the RMSE is measured about: global_mean, truth_fixed, truth_series, heldout_mean",
    "n_scored": "samples scored (the held-out part under leakfree)",
    "rmse_before": "eq. 15 RMSE of the uncompensated scored samples about the reference, px",
    "rmse_after": "eq. 15 RMSE after compensation, px (null when not compensated)",
    "effective": "eq. 13 improvement (before - after) / before (null when not compensated)",
    "order": "strategies run, best score first, '>'-separated ('' when not compensated)",
    "kept": "strategies kept after the 1 % rollback rule, '>'-separated",
    "accuracy_from": "A of eq. 10: where it came from ('' when not compensated)",
    "dominant_frequency_hz": "dominant error frequency f_d of the decomposition, Hz (null when not compensated)",
}
"""Fields of one result row (one dataset × method × model × window × rate × protocol × reference)."""


def simulate_and_centroid(
    dataset: dict[str, Any],
    sim_path: str,
    centroid_path: str,
    *,
    methods: Sequence[str] = METHODS,
    force: bool = False,
) -> dict[str, Any]:
    """Task 1: simulate one dataset and measure its centroids by every method.

    ``dataset`` is :meth:`Dataset.to_dict` (``name``, ``config``, optional ``centroid`` options of
    the centroid stage).  Returns the paths and the centroid stage's summary.
    """
    config = SimulationConfig.from_dict(dataset["config"])
    simulate_log(config, sim_path, force=force)
    summary = centroid_log(sim_path, centroid_path, methods=list(methods), options=dataset.get("centroid"),
                           force=force, mode="full")  # the paper extracts every frame
    return {"dataset": dataset["name"], "sim_path": sim_path, "centroid_path": centroid_path,
            "centroid": summary.to_dict()}


def _window_indices(series: BrightestSeries, *, rate: float, window_s: float | None,
                    skip_burn_in: bool, burn_in: BurnInSetting = "auto") -> npt.NDArray[np.int64]:
    """The decimated samples of one window (:meth:`BrightestSeries.indices`, then the first
    ``floor(window_s · rate + 0.5)``)."""
    idx = series.indices(rate, skip_burn_in=skip_burn_in, burn_in=burn_in)
    if window_s is None:
        return idx
    return idx[: int(math.floor(window_s * rate + 0.5))]


def uncompensated_figures(
    xy: npt.NDArray[np.float64],
    *,
    truth_fixed: npt.NDArray[np.float64] | None,
    truth_series: npt.NDArray[np.float64] | None,
    calibration_fraction: float = 0.5,
) -> dict[str, list[tuple[str, float, int]]]:
    """RMSE figures of an uncompensated series under each protocol (Table 2).

    :func:`starlog.compensation.protocol_figures` without a compensation (``evaluate`` needs at
    least 16 samples to also compensate), with the leak-free split of
    :func:`starlog.compensation.scored_start`.

    Returns
    -------
    dict
        ``protocol -> [(reference, rmse_px, n_scored), ...]`` (``truth`` only when a truth is given).
    """
    out: dict[str, list[tuple[str, float, int]]] = {}
    n = xy.shape[0]
    for protocol in protocols_for(has_truth=truth_fixed is not None or truth_series is not None):
        start = scored_start(protocol, n, calibration_fraction=calibration_fraction)
        figures = protocol_figures(xy, protocol=protocol, start=start, truth_fixed=truth_fixed,
                                   truth_series=truth_series)
        out[protocol.value] = [(f.reference, f.rmse_before, f.n_scored) for f in figures]
    return out


def _uncompensated_rows(base: dict[str, Any], series: BrightestSeries, idx: npt.NDArray[np.int64], *,
                        calibration_fraction: float) -> list[dict[str, Any]]:
    ts = None if series.truth_series is None else series.truth_series[idx]
    figures = uncompensated_figures(series.xy[idx], truth_fixed=series.truth_fixed, truth_series=ts,
                                    calibration_fraction=calibration_fraction)
    return [{**base, "compensated": False, "accuracy_from": "", "protocol": protocol, "reference": reference, "n_scored": n_scored,
             "rmse_before": value, "rmse_after": None, "effective": None, "order": "", "kept": "",
             "dominant_frequency_hz": None}
            for protocol, figs in figures.items() for reference, value, n_scored in figs]


def _compensated_rows(base: dict[str, Any], protocol: ScoringProtocol, ev: Evaluation,
                      sigma_source: str) -> list[dict[str, Any]]:
    res = ev.result
    accuracy_from = sigma_source if res.accuracy_source == "sigma" else "none (A = 0)"
    return [{**base, "compensated": True, "accuracy_from": accuracy_from, "protocol": protocol.value, "reference": fig.reference,
             "n_scored": int(fig.n_scored), "rmse_before": float(fig.rmse_before),
             "rmse_after": float(fig.rmse_after), "effective": float(fig.effective),
             "order": ">".join(str(s) for s in res.order), "kept": ">".join(str(s) for s in res.kept),
             "dominant_frequency_hz": float(res.decomposition.dominant_frequency)}
            for fig in ev.figures]


def _keep_series(kept: dict[str, Any], key: str, series: BrightestSeries, idx: npt.NDArray[np.int64],
                 protocol: ScoringProtocol, ev: Evaluation) -> None:
    """Store the series before/after (for the trajectory plot) under ``key``."""
    tf, ts = series.truth_fixed, None if series.truth_series is None else series.truth_series[idx]
    entry = kept.setdefault(key, {
        "t_s": ((series.log_time[idx] - series.log_time[0]) * 1e-9).tolist(),
        "before": series.xy[idx].tolist(),
        "truth_series": None if ts is None else ts.tolist(),
        "truth_fixed": None if tf is None else [float(v) for v in tf],
        "after": {}, "scored_start": {},
    })
    entry["after"][protocol.value] = ev.result.compensated.tolist()
    entry["scored_start"][protocol.value] = int(ev.scored_start)


def _score_series(series: BrightestSeries, *, dataset: str, regime: str, rates_uncompensated: Sequence[float],
                  rates_compensated: Sequence[float], window_s: float | None,
                  calibration_fraction: float, keep_series: Sequence[float],
                  options: dict[str, Any], burn_in: BurnInSetting = "auto") -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """Rows for one brightest-star series (burn-in skipped: every window; kept: the first window
    only — the tables' — to bound the cost), every rate; and
    the series of the ``keep_series`` rates (burn-in skipped, short window).

    A window whose samples are those of one already scored (the whole sequence is shorter than
    ``window_s``; no burn-in to skip) reuses its figures: the evaluation depends on the samples only.
    """
    rows: list[dict[str, Any]] = []
    kept_series: dict[str, Any] = {}
    scored: dict[tuple[float, bytes], list[dict[str, Any]]] = {}
    labels = ("window", "burn_in", "burn_in_samples")
    windows: list[tuple[str, float | None]] = [("full", None)]
    if window_s is not None:
        windows.insert(0, (f"{window_s:g}s", window_s))
    has_truth = series.truth_fixed is not None or series.truth_series is not None
    burn = series.burn_in(burn_in)
    setting = burn_in_label(burn_in)
    for variant, skip in BURN_IN_VARIANTS:
        for window, wsec in (windows if skip else windows[:1]):
            for rate in sorted({*rates_uncompensated, *rates_compensated}):
                idx = _window_indices(series, rate=rate, window_s=wsec, skip_burn_in=skip, burn_in=burn_in)
                rate_hz = sampled_rate(idx, native_rate=series.native_rate)
                base = {"regime": regime, "dataset": dataset, "method": series.method, "model": series.model, "window": window,
                        "burn_in": variant, "burn_in_samples": burn.samples if skip else 0,
                        "burn_in_setting": setting,
                        "rate_hz": float(rate), "effective_rate_hz": float(rate_hz), "n_samples": int(idx.size)}
                key = (rate, idx.tobytes())
                if key in scored:
                    rows += [{**r, **{k: base[k] for k in labels}} for r in scored[key]]
                    continue
                if rate not in rates_compensated or idx.size < MIN_COMPENSATED:
                    # too short to compensate (e.g. a fragmented brightest track): scored uncompensated
                    cell = _uncompensated_rows(base, series, idx, calibration_fraction=calibration_fraction)
                else:
                    cell = []
                    for protocol in protocols_for(has_truth=has_truth):
                        ev = evaluate_series(series, idx, rate_hz=rate_hz, protocol=protocol,
                                             calibration_fraction=calibration_fraction, **options)
                        cell += _compensated_rows(base, protocol, ev, series.sigma_source)
                        if window != "full" and skip and rate in keep_series:
                            name = f"{regime}/{dataset}/{series.method}/{series.model}/{rate:g}Hz/{window}"
                            _keep_series(kept_series, name, series, idx, protocol, ev)
                scored[key] = cell
                rows += cell
    return rows, kept_series


def track_and_score(
    centroid_path: str,
    track_path: str,
    *,
    dataset: str,
    regime: str = "modern",
    method: str,
    models: Sequence[str],
    tracker: dict[str, Any],
    motion: dict[str, Any] | None = None,
    rates_uncompensated: Sequence[float] = UNCOMPENSATED_RATES,
    rates_compensated: Sequence[float] = COMPENSATED_RATES,
    window_s: float | None = WINDOW_S,
    calibration_fraction: float = 0.5,
    keep_series: Sequence[float] = (),
    compensation: dict[str, Any] | None = None,
    burn_in: BurnInSetting = "auto",
    force: bool = False,
) -> dict[str, Any]:
    """Task 2: track one centroid channel under ``models`` and score every model's brightest series.

    ``compensation``: keyword options of :func:`starlog.compensation.evaluate` (``A`` of eq. 10 is
    the centroid's own ``sigma`` unless ``accuracy_source`` is given).  ``burn_in``: what the
    ``skipped`` rows skip (:func:`starlog.compensation.parse_burn_in`).

    Returns ``{"regime", "dataset", "method", "track_path", "track": TrackSummary.to_dict(), "rows": [...],
    "series": {...}}`` — plain data (rows of :data:`RESULT_FIELDS`).
    """
    summary = track_log(centroid_path, track_path, method=method, models=list(models), tracker=dict(tracker),
                        motion=dict(motion or {}), force=force)
    rows: list[dict[str, Any]] = []
    series_out: dict[str, Any] = {}
    with LogReader(track_path) as log:
        truth_cache: dict[int, Any] = {}
        for model in models:
            series = read_brightest_series(log, f"/track/{method}/{model}", truth_cache=truth_cache)
            r, s = _score_series(series, dataset=dataset, regime=regime, rates_uncompensated=rates_uncompensated,
                                 rates_compensated=rates_compensated, window_s=window_s,
                                 calibration_fraction=calibration_fraction, keep_series=keep_series,
                                 options=dict(compensation or {}), burn_in=burn_in)
            rows.extend(r)
            series_out.update(s)
    return {"regime": regime, "dataset": dataset, "method": method, "track_path": track_path,
            "track": summary.to_dict(), "rows": rows, "series": series_out}


def compensate_showcase(
    track_path: str,
    output_path: str,
    *,
    dataset: str,
    track_topic: str,
    rates: Sequence[float],
    regime: str = "modern",
    burn_in: BurnInSetting = "auto",
    force: bool = False,
) -> dict[str, Any]:
    """Task 3: the ``compensate`` stage on one track channel (whole sequence, every protocol).

    Returns ``{"dataset", "path", "records": [{method, model, rate_hz, protocol, figures}]}``.
    """
    try:
        summary = compensate_log(track_path, output_path, rates=list(rates), track=track_topic, protocols="all",
                                 burn_in=burn_in, force=force)
    except InvalidInputError as err:  # a brightest track too short to compensate (fragmented, faint star)
        return {"regime": regime, "dataset": dataset, "path": None, "records": [], "skipped": str(err)}
    records = [{"method": r["method"], "model": r["model"], "rate_hz": r["rate_hz"], "protocol": r["protocol"],
                "n_samples": r["n_samples"], "figures": r["figures"]} for r in summary.records]
    return {"regime": regime, "dataset": dataset, "path": output_path, "records": records}


_ORDER = {
    "regime": {"paper": 0, "modern": 1},
    "dataset": {"300Hz": 0, "200Hz": 1},
    "method": {m: i for i, m in enumerate(METHODS)},
    "model": {m: i for i, m in enumerate(MODELS)},
    "protocol": {"paper": 0, "truth": 1, "leakfree": 2},
    "reference": {"global_mean": 0, "heldout_mean": 1, "truth_fixed": 2, "truth_series": 3},
}


def sort_rows(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Result rows in a canonical order (independent of task completion order)."""

    def key(r: dict[str, Any]) -> tuple[Any, ...]:
        return (_ORDER["regime"].get(r["regime"], 9), r["regime"], _ORDER["dataset"].get(r["dataset"], 9), r["dataset"], _ORDER["method"].get(r["method"], 9),
                _ORDER["model"].get(r["model"], 9), r["burn_in"] != "skipped", 0 if r["window"] != "full" else 1,
                r["rate_hz"],
                _ORDER["protocol"][r["protocol"]], _ORDER["reference"][r["reference"]])

    return sorted(rows, key=key)


def best_table2_model(rows: Sequence[dict[str, Any]], *, window: str) -> str:
    """The UKF model with the lowest uncompensated RMSE in Table 2 (paper §3.2.1), as the paper picks it.

    Mean over the datasets and Table 2's rates of the ``paper`` protocol's figure (sub-pixel
    method NONE, burn-in skipped, scored ``window``); models within :data:`TIE_FRACTION` of the
    lowest mean are tied, and ties keep :data:`MODELS` order (in the ``paper`` regime every
    model's position diffusion is the same and STATIC, RANDOM_WALK and BROWNIAN_MOTION differ
    by rounding only).
    """
    values: dict[str, list[float]] = {}
    for r in rows:
        if (r["method"] == "NONE" and r["rate_hz"] in TABLE2_RATES and r["window"] == window
                and r["burn_in"] == "skipped" and r["protocol"] == "paper"):
            values.setdefault(r["model"], []).append(r["rmse_before"])
    if not values:
        raise ValueError("no Table 2 rows to choose a model from.")
    means = {m: sum(values[m]) / len(values[m]) for m in MODELS if m in values}
    lowest = min(means.values())
    return next(m for m, v in means.items() if v <= lowest * (1.0 + TIE_FRACTION))


def path_str(path: str | os.PathLike[str]) -> str:
    """Absolute path as a string (what tasks receive)."""
    return str(Path(path).resolve())
