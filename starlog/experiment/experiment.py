"""``run_experiment``: the whole reproduction (datasets → stages → sweep → tables, plots, report)."""

from __future__ import annotations

import json
import os
import time
from concurrent.futures import FIRST_COMPLETED, Executor, Future, wait
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.parquet as pq
from tqdm import tqdm

from starlog.batch import executor_for
from starlog.errors import InvalidParameterError, OutputExistsError
from starlog.experiment import plots, report, tables
from starlog.experiment.datasets import JITTER, SIGMA_FLOOR_PX, Dataset, jitter_rms_px, paper_datasets
from starlog.experiment.regime import RegimeSummary, run_regime_map
from starlog.experiment.runner import (
    COMPENSATED_RATES,
    METHODS,
    MODELS,
    RESULT_FIELDS,
    TABLE4_RATE,
    UNCOMPENSATED_RATES,
    WINDOW_S,
    compensate_showcase,
    path_str,
    simulate_and_centroid,
    sort_rows,
    track_and_score,
)

__all__ = ["ExperimentSummary", "experiment_command", "run_experiment"]

_SHOWCASE_RATES = (10.0, 50.0)
_TRAJECTORY = ("300Hz", "NONE", ("STATIC", "RANDOM_WALK"), 50.0)


@dataclass
class ExperimentSummary:
    """What :func:`run_experiment` produced.

    Attributes
    ----------
    output_dir : Path
        Where everything was written.
    quick : bool
        CI-sized datasets.
    wall_time_s : float
        Wall time of the whole run, s.
    executor : str
        ``serial`` or the executor's class name.
    files : dict
        Output name → path relative to ``output_dir`` (tables, Parquet, PNGs, logs, report).
    rows : list of dict
        Every result row (:data:`starlog.experiment.runner.RESULT_FIELDS`), canonical order.
    tables : dict
        ``table2`` / ``table3`` / ``table4`` / ``figure5`` → long-format rows
        (:data:`starlog.experiment.tables.TABLE_FIELDS`).
    headline : list of dict
        :func:`starlog.experiment.report.headline_rows`.
    """

    output_dir: Path
    quick: bool
    wall_time_s: float
    executor: str
    datasets: list[dict[str, Any]]
    sigma_floor_px: float
    window_s: float | None
    files: dict[str, str] = field(default_factory=dict)
    tracks: dict[str, Any] = field(default_factory=dict)
    rows: list[dict[str, Any]] = field(default_factory=list)
    tables: dict[str, list[dict[str, Any]]] = field(default_factory=dict)
    headline: list[dict[str, Any]] = field(default_factory=list)
    showcase_check: float | None = None

    @property
    def window_note(self) -> str:
        if self.window_s is None:
            return "every decimated sample (whole sequence)"
        return (f"the first {self.window_s:g} s of each decimated sequence (floor({self.window_s:g} s × f + 0.5) "
                "samples: 60 at 10 Hz, 300 at 50 Hz — the paper's 'Image number'); results.parquet also has "
                "every run scored over the whole sequence (window = full)")

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary (no per-row data; see ``results.parquet`` for that)."""
        return {
            "output_dir": str(self.output_dir), "quick": self.quick, "wall_time_s": self.wall_time_s,
            "executor": self.executor, "datasets": self.datasets, "sigma_floor_px": self.sigma_floor_px,
            "jitter_rms_px": jitter_rms_px(JITTER), "window_s": self.window_s, "window_note": self.window_note,
            "files": dict(self.files), "tracks": self.tracks, "headline": self.headline,
            "showcase_check": self.showcase_check, "n_rows": len(self.rows),
        }

    def text(self) -> str:
        """A short plain-text summary for the command line."""
        lines = [f"experiment ({'quick' if self.quick else 'full'}) in {self.wall_time_s:.0f} s "
                 f"[{self.executor}] -> {self.output_dir}",
                 f"{'table':7} {'protocol':9} {'reference':13} {'ours before':>11} {'after':>7} "
                 f"{'paper before':>12} {'after':>7}"]
        for h in self.headline:
            if h["table"] == "table2":
                continue

            def f(v: float | None) -> str:
                return "—" if v is None else f"{v:.4f}"

            lines.append(f"{h['table']:7} {h['protocol']:9} {h['reference']:13} {f(h['before']):>11} "
                         f"{f(h['after']):>7} {f(h['paper_before']):>12} {f(h['paper_after']):>7}")
        lines.append(f"report: {self.output_dir / self.files.get('report', 'report.md')}")
        return "\n".join(lines)


class _Serial:
    """Runs a submitted call at once and hands back a finished future."""

    def submit(self, fn: Any, /, *args: Any, **kwargs: Any) -> Future[Any]:
        fut: Future[Any] = Future()
        try:
            fut.set_result(fn(*args, **kwargs))
        except BaseException as err:  # noqa: BLE001 - re-raised by fut.result()
            fut.set_exception(err)
        return fut


def run_experiment(
    output_dir: str | os.PathLike[str],
    *,
    quick: bool = False,
    executor: Executor | None = None,
    force: bool = False,
    show_progress: bool = True,
    window_s: float | None = WINDOW_S,
    sigma_floor: float = SIGMA_FLOOR_PX,
    plot: bool = True,
) -> ExperimentSummary:
    """Regenerate the paper's Tables 2–4 and Figure 5 under the ``paper``, ``truth`` and ``leakfree`` protocols.

    Parameters
    ----------
    output_dir : path
        Created if needed. Receives ``logs/`` (simulated, centroid, track and compensate
        logs), ``table2.md/.parquet``, ``table3.*``, ``table4.*``, ``figure5.md/.parquet``,
        ``results.parquet`` (every row), ``figure4.png``, ``figure5.png``, ``trajectory.png``,
        ``summary.json`` and ``report.md``.
    quick : bool
        CI-sized datasets (48×48 px, 2 stars, 3.2 s): every table and plot, in well under a minute
        on 2 cores.
    executor : concurrent.futures.Executor, optional
        Runs the independent tasks (per dataset, per dataset × centroid method); e.g.
        ``ProcessPoolExecutor(2)`` or a Dask ``Client(...).get_executor()`` whose workers
        share ``output_dir``'s file system. ``None``: serial. Results do not depend on it.
    force : bool
        Overwrite existing outputs (otherwise :class:`~starlog.errors.OutputExistsError`).
    show_progress : bool
        A tqdm bar over the sweep's tasks (stderr).
    window_s : float or None
        Scoring window in seconds (the paper's image numbers; default 6 s); ``None`` scores the
        whole sequence only.
    sigma_floor : float
        Trackers' measurement-sigma floor, px (default ≈ the simulated jitter RMS).
    plot : bool
        Write the PNGs (needs matplotlib).
    """
    t0 = time.perf_counter()
    if window_s is not None and not window_s > 0:
        raise InvalidParameterError(f"window_s must be > 0 s or None, got {window_s!r}.")
    out = Path(output_dir)
    datasets = paper_datasets(quick=quick)
    _prepare_output(out, datasets, force=force)
    track_results, showcases = _run_sweep(
        executor if executor is not None else _Serial(), datasets, out / "logs",
        tracker={"sigma_floor": float(sigma_floor)}, window_s=window_s, force=force, show_progress=show_progress)

    rows = sort_rows([r for t in track_results for r in t["rows"]])
    series: dict[str, Any] = {}
    for t in track_results:
        series.update(t["series"])
    summary = ExperimentSummary(
        output_dir=out, quick=quick, wall_time_s=0.0,
        executor="serial" if executor is None else type(executor).__name__,
        datasets=[d.to_dict() for d in datasets], sigma_floor_px=float(sigma_floor), window_s=window_s,
        rows=rows,
        tracks={f"{t['dataset']}/{t['method']}": t["track"] for t in sorted(
            track_results, key=lambda t: (t["dataset"], t["method"]))},
    )
    summary.showcase_check = _cross_check(rows, showcases)
    _write_results(rows, out / "results.parquet")
    files: dict[str, str] = {"results": "results.parquet"}
    tables_md = _write_tables(summary, out, files)
    if plot:
        _write_plots(summary, series, out, files)
    files.update(_log_files(datasets))
    files["summary"] = "summary.json"
    files["report"] = "report.md"
    summary.files = files
    summary.headline = report.headline_rows(summary.tables)
    summary.wall_time_s = time.perf_counter() - t0
    data = summary.to_dict()
    (out / "summary.json").write_text(json.dumps(data, indent=1), encoding="utf-8")
    (out / "report.md").write_text(report.render_report(data, tables_md, summary.headline), encoding="utf-8")
    return summary


def _prepare_output(out: Path, datasets: list[Dataset], *, force: bool) -> None:
    """Create ``out/logs``; refuse to overwrite a previous run's outputs unless ``force``."""
    logs = out / "logs"
    out.mkdir(parents=True, exist_ok=True)
    logs.mkdir(exist_ok=True)
    guard = [out / "report.md", out / "results.parquet"]
    for ds in datasets:
        guard += [logs / f"{ds.name}_sim.mcap", logs / f"{ds.name}_centroids.mcap"]
    if not force:
        for p in guard:
            if p.exists():
                raise OutputExistsError(p)


def _run_sweep(pool: Any, datasets: list[Dataset], logs: Path, *, tracker: dict[str, Any],
               window_s: float | None, force: bool,
               show_progress: bool) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """Every task on ``pool``: each finished centroid run submits its track runs, each ``NONE``
    track run its compensate showcase.  Returns the track results and the showcases."""
    n_tasks = len(datasets) * (2 + len(METHODS))
    bar = tqdm(total=n_tasks, desc="experiment", unit="run", disable=None if show_progress else True,
               dynamic_ncols=True)
    futures: dict[Future[Any], tuple[str, str, str]] = {}

    def submit(kind: str, ds: str, key: str, fn: Any, *args: Any, **kwargs: Any) -> None:
        futures[pool.submit(fn, *args, **kwargs)] = (kind, ds, key)

    centroid_paths = {ds.name: path_str(logs / f"{ds.name}_centroids.mcap") for ds in datasets}
    track_results: list[dict[str, Any]] = []
    showcases: list[dict[str, Any]] = []
    try:
        for ds in datasets:
            submit("centroid", ds.name, "", simulate_and_centroid, ds.to_dict(), path_str(logs / f"{ds.name}_sim.mcap"),
                   centroid_paths[ds.name], methods=list(METHODS), force=force)
        while futures:
            done, _ = wait(list(futures), return_when=FIRST_COMPLETED)
            for fut in sorted(done, key=lambda f: futures[f]):
                kind, ds_name, key = futures.pop(fut)
                result = fut.result()
                bar.update(1)
                bar.set_postfix_str(f"{kind} {ds_name} {key}".strip())
                if kind == "centroid":
                    for method in METHODS:
                        models = list(MODELS) if method == "NONE" else ["STATIC"]
                        keep = (TABLE4_RATE,) if (ds_name, method) == _TRAJECTORY[:2] else ()
                        submit("track", ds_name, method, track_and_score, centroid_paths[ds_name],
                               path_str(logs / f"{ds_name}_track_{method}.mcap"), dataset=ds_name, method=method,
                               models=models, tracker=tracker, rates_uncompensated=list(UNCOMPENSATED_RATES),
                               rates_compensated=list(COMPENSATED_RATES), window_s=window_s,
                               keep_series=list(keep), force=force)
                elif kind == "track":
                    track_results.append(result)
                    if key == "NONE":
                        submit("compensate", ds_name, "NONE/STATIC", compensate_showcase, result["track_path"],
                               path_str(logs / f"{ds_name}_compensated.mcap"), dataset=ds_name,
                               track_topic="/track/NONE/STATIC", rates=list(_SHOWCASE_RATES), force=force)
                else:
                    showcases.append(result)
    except BaseException:
        for fut in futures:
            fut.cancel()
        raise
    finally:
        bar.close()
    return track_results, showcases


def _write_tables(summary: ExperimentSummary, out: Path, files: dict[str, str]) -> dict[str, str]:
    """Tables 2-4 and Figure 5 as Parquet and Markdown; returns the Markdown by table name."""
    tables_md: dict[str, str] = {}
    for name in ("table2", "table3", "table4", "figure5"):
        trows = tables.build_table(name, summary.rows)
        summary.tables[name] = trows
        tables.write_parquet(trows, out / f"{name}.parquet", description=tables.TABLE_TITLES[name])
        tables_md[name] = tables.table_markdown(name, trows, note=f"Scored samples: {summary.window_note}.")
        (out / f"{name}.md").write_text(tables_md[name], encoding="utf-8")
        files[f"{name}.parquet"] = f"{name}.parquet"
        files[f"{name}.md"] = f"{name}.md"
    return tables_md


def _write_plots(summary: ExperimentSummary, series: dict[str, Any], out: Path, files: dict[str, str]) -> None:
    """Figures 4 and 5, and the trajectory of the brightest star (before/after) per model."""
    files["figure4"] = plots.plot_figure4(summary.tables["table3"], out / "figure4.png").name
    files["figure5"] = plots.plot_figure5(summary.tables["figure5"], out / "figure5.png").name
    ds_name, method, models, rate = _TRAJECTORY
    window_s = summary.window_s
    for m in models:
        key = f"{ds_name}/{method}/{m}/{rate:g}Hz/{window_s:g}s" if window_s is not None else ""
        if key not in series:
            continue
        name = f"trajectory_{m.lower()}"
        files[name] = plots.plot_trajectory(
            series[key], out / f"{name}.png",
            title=f"{ds_name} dataset, {method} centroids, {m} UKF, {rate:g} Hz — brightest star").name


def _log_files(datasets: list[Dataset]) -> dict[str, str]:
    """Output name → path of every log the experiment writes."""
    files: dict[str, str] = {}
    for ds in datasets:
        for kind in ("sim", "centroids"):
            files[f"{ds.name}_{kind}"] = f"logs/{ds.name}_{kind}.mcap"
        for method in METHODS:
            files[f"{ds.name}_track_{method}"] = f"logs/{ds.name}_track_{method}.mcap"
        files[f"{ds.name}_compensated"] = f"logs/{ds.name}_compensated.mcap"
    return files


def _cross_check(rows: list[dict[str, Any]], showcases: list[dict[str, Any]]) -> float | None:
    """Largest |difference| between the compensate stage's figures and the sweep's (full window)."""
    index = {(r["dataset"], r["method"], r["model"], r["rate_hz"], r["protocol"], r["reference"]): r
             for r in rows if r["window"] == "full" and r["compensated"]}
    worst: float | None = None
    for sc in showcases:
        for rec in sc["records"]:
            for fig in rec["figures"]:
                r = index.get((sc["dataset"], rec["method"], rec["model"], rec["rate_hz"], rec["protocol"],
                               fig["reference"]))
                if r is None:
                    continue
                d = max(abs(r["rmse_before"] - fig["rmse_before"]), abs(r["rmse_after"] - fig["rmse_after"]))
                worst = d if worst is None else max(worst, d)
    return worst


def _write_results(rows: list[dict[str, Any]], path: Path) -> None:
    types = {"rate_hz": pa.float64(), "effective_rate_hz": pa.float64(), "n_samples": pa.int64(),
             "compensated": pa.bool_(), "n_scored": pa.int64(), "rmse_before": pa.float64(),
             "rmse_after": pa.float64(), "effective": pa.float64(), "dominant_frequency_hz": pa.float64()}
    fields = [pa.field(n, types.get(n, pa.string()), metadata={"description": d}) for n, d in RESULT_FIELDS.items()]
    table = pa.table({n: [r[n] for r in rows] for n in RESULT_FIELDS}, schema=pa.schema(fields))
    pq.write_table(table, path, compression="zstd")


def experiment_command(
    output_dir: str | os.PathLike[str],
    *,
    quick: bool = False,
    workers: int = 1,
    scheduler: str | None = None,
    force: bool = False,
    show_progress: bool = True,
    sweep: bool = False,
) -> ExperimentSummary | RegimeSummary:
    """What ``starlog experiment -o DIR [--quick] [--sweep] [--workers N] [--scheduler ADDR] [--force]`` calls.

    ``sweep`` runs the regime map (:mod:`starlog.experiment.regime`) instead of the paper's tables.

    ``scheduler`` sends the independent runs to that Dask cluster; otherwise ``workers > 1``
    starts a local Dask cluster of that many processes (:func:`starlog.batch.executor_for`);
    ``workers == 1`` runs serially. The results do not depend on which.
    """
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise InvalidParameterError(f"workers must be an integer >= 1, got {workers!r}.")
    with executor_for(scheduler=scheduler, workers=workers) as executor:
        if sweep:
            return run_regime_map(output_dir, quick=quick, executor=executor, force=force,
                                  show_progress=show_progress)
        return run_experiment(output_dir, quick=quick, executor=executor, force=force, show_progress=show_progress)
