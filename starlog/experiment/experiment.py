"""``run_experiment``: the whole reproduction (datasets → stages → sweep; then :mod:`~starlog.experiment.outputs`
writes the tables, figures and reports)."""

from __future__ import annotations

import os
import time
from concurrent.futures import FIRST_COMPLETED, Executor, Future, wait
from pathlib import Path
from typing import Any

from tqdm import tqdm

from starlog.batch import executor_for
from starlog.compensation import BurnInSetting, burn_in_label, parse_burn_in
from starlog.errors import InvalidParameterError, OutputExistsError
from starlog.experiment import null_check, realisations, tables
from starlog.experiment.datasets import REGIMES, SIGMA_FLOOR_PX, Dataset, regime_datasets
from starlog.experiment.outputs import (
    TRAJECTORY,
    log_files,
    write_plots,
    write_realisations,
    write_reports,
    write_results,
    write_tables,
)
from starlog.experiment.regime import RegimeSummary, run_regime_map
from starlog.experiment.runner import (
    COMPENSATED_RATES,
    METHODS,
    MODELS,
    TABLE4_RATE,
    UNCOMPENSATED_RATES,
    WINDOW_S,
    best_table2_model,
    compensate_showcase,
    path_str,
    simulate_and_centroid,
    sort_rows,
    track_and_score,
)
from starlog.experiment.summary import ExperimentSummary

__all__ = ["ExperimentSummary", "experiment_command", "run_experiment"]

_SHOWCASE_RATES = (10.0, 50.0)
_Key = tuple[str, str, str, str]  # kind, regime, dataset, detail


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
    regimes: tuple[str, ...] | list[str] = REGIMES,
    compensation: dict[str, Any] | None = None,
    burn_in: BurnInSetting = "auto",
) -> ExperimentSummary:
    """Regenerate the paper's Tables 2–4 and Figure 5 under the ``paper``, ``truth`` and ``leakfree`` protocols.

    Parameters
    ----------
    output_dir : path
        Created if needed. Receives ``logs/`` (simulated, centroid, track and compensate
        logs), ``table2.md/.parquet``, ``table3.*``, ``table4.*``, ``figure5.md/.parquet``,
        ``results.parquet`` (every row), ``figure4_<regime>.png``, ``figure5_<regime>.png``,
        ``trajectory_<regime>_<model>.png``, ``summary.json`` and ``report.md``.
    quick : bool
        CI-sized datasets (48×48 px, 2 stars, 3.7 s): every table and plot, in about a minute
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
    regimes : sequence of str
        Dataset regimes to run, ``paper`` and/or ``modern`` (default both;
        :mod:`starlog.experiment.datasets`).
    compensation : dict, optional
        Keyword options of :func:`starlog.compensation.evaluate` for every run (e.g.
        ``{"top_k": 3, "select_positive": False}`` for the forced-three ablation).
    burn_in : str or float
        The filter's start-up skipped before scoring: ``"auto"`` (default), ``"off"`` or seconds
        (:func:`starlog.compensation.parse_burn_in`); recorded in ``summary.json`` and in every row
        (``burn_in_setting``).
    """
    t0 = time.perf_counter()
    if window_s is not None and not window_s > 0:
        raise InvalidParameterError(f"window_s must be > 0 s or None, got {window_s!r}.")
    chosen = _check_regimes(regimes)
    setting = parse_burn_in(burn_in)
    out = Path(output_dir)
    datasets = list(regime_datasets(chosen, quick=quick, sigma_floor=sigma_floor))
    _prepare_output(out, datasets, force=force)
    summary = ExperimentSummary(
        output_dir=out, quick=quick, wall_time_s=0.0,
        executor="serial" if executor is None else type(executor).__name__,
        datasets=[d.to_dict() for d in datasets], sigma_floor_px=float(sigma_floor), window_s=window_s,
        regimes=chosen, compensation=dict(compensation or {}), burn_in=burn_in_label(setting),
    )
    sweep = _Sweep(datasets, out / "logs", window_s=window_s, compensation=summary.compensation,
                   quick=quick, burn_in=setting)
    sweep.run(executor if executor is not None else _Serial(), show_progress=show_progress)
    summary.rows = sort_rows([r for t in sweep.track_results for r in t["rows"]])
    summary.tracks = {f"{t['regime']}/{t['dataset']}/{t['method']}": t["track"] for t in sorted(
        sweep.track_results, key=lambda t: (t["regime"], t["dataset"], t["method"]))}
    summary.table3_models = dict(sorted(sweep.best_models.items()))
    summary.null_checks = null_check.sort_records([r for n in sweep.null_results for r in n])
    summary.showcase_check = _cross_check(summary.rows, sweep.showcases)
    write_results(summary.rows, out / "results.parquet")
    files: dict[str, str] = {"results": "results.parquet"}
    tables_md = write_tables(summary, out, files)
    files["null_check"] = null_check.write_parquet(summary.null_checks, out / "null_check.parquet").name
    write_realisations(summary, sweep.realisation_rows, out, files)
    if plot:
        write_plots(summary, sweep.series, out, files, executor)
    files.update({k: v for k, v in log_files(datasets).items() if (out / v).exists()})
    files["summary"] = "summary.json"
    files["report"] = "report.md"
    files["report_html"] = "report.html"
    summary.files = files
    summary.headline = tables.headline_rows(summary.tables)
    summary.wall_time_s = time.perf_counter() - t0
    write_reports(summary, tables_md, out)
    return summary


def _check_regimes(regimes: tuple[str, ...] | list[str]) -> tuple[str, ...]:
    chosen = tuple(dict.fromkeys(str(r) for r in regimes))
    bad = [r for r in chosen if r not in REGIMES]
    if not chosen or bad:
        raise InvalidParameterError(f"regimes must be a non-empty subset of {list(REGIMES)}; got {list(regimes)!r}.")
    return tuple(r for r in REGIMES if r in chosen)


def _prepare_output(out: Path, datasets: list[Dataset], *, force: bool) -> None:
    """Create ``out/logs``; refuse to overwrite a previous run's outputs unless ``force``."""
    logs = out / "logs"
    out.mkdir(parents=True, exist_ok=True)
    logs.mkdir(exist_ok=True)
    guard = [out / "report.md", out / "results.parquet"]
    for ds in datasets:
        guard += [logs / f"{ds.stem}_sim.mcap", logs / f"{ds.stem}_centroids.mcap"]
    if not force:
        for p in guard:
            if p.exists():
                raise OutputExistsError(p)


#: The tasks overwrite what they write. A previous run's outputs are refused before the sweep starts
#: (:func:`_prepare_output`, unless ``force``), and Dask runs a task more than once at times (a lost
#: worker, a work-stealing race): a task must not fail on the files of its own earlier attempt.
_OVERWRITE = True


def _centroid_cost(ds: Dataset) -> int:
    """A dataset's centroid task cost, in star-frames: the longest tasks are submitted first
    (longest-processing-time-first), so the workers do not idle at the end of the sweep."""
    return ds.config.n_frames * ds.config.n_stars


class _Sweep:
    """Every task of one experiment, submitted as its inputs become ready.

    Per dataset: centroid → NONE track (all models) → once both datasets of a regime have
    their NONE tracks, Table 2's best model is known: the other methods are tracked with it,
    and the ``compensate`` showcase runs on NONE/best.  Per regime: the null check.
    """

    def __init__(self, datasets: list[Dataset], logs: Path, *, window_s: float | None,
                 compensation: dict[str, Any], quick: bool, burn_in: BurnInSetting = "auto") -> None:
        self.datasets = {(d.regime, d.name): d for d in datasets}
        self.burn_in = burn_in
        self.logs, self.window_s, self.compensation, self.quick = logs, window_s, compensation, quick
        self.track_results: list[dict[str, Any]] = []
        self.showcases: list[dict[str, Any]] = []
        self.null_results: list[list[dict[str, Any]]] = []
        self.realisation_rows: list[dict[str, Any]] = []
        self.series: dict[str, Any] = {}
        self.best_models: dict[str, str] = {}
        self._none_rows: dict[str, dict[str, list[dict[str, Any]]]] = {}
        self._futures: dict[Future[Any], _Key] = {}

    def _path(self, ds: Dataset, kind: str) -> str:
        return path_str(self.logs / f"{ds.stem}_{kind}.mcap")

    def run(self, pool: Any, *, show_progress: bool) -> None:
        regimes = sorted({d.regime for d in self.datasets.values()})
        extra = self._realisation_tasks()
        n_tasks = len(self.datasets) * (2 + len(METHODS)) + len(regimes) + len(extra)
        bar = tqdm(total=n_tasks, desc="experiment", unit="run", disable=None if show_progress else True,
                   dynamic_ncols=True)
        self._pool = pool
        try:
            for ds in sorted(self.datasets.values(), key=_centroid_cost, reverse=True):
                self._submit(("centroid", ds.regime, ds.name, ""), simulate_and_centroid,
                             ds.to_dict(),
                             self._path(ds, "sim"), self._path(ds, "centroids"), methods=list(METHODS),
                             force=_OVERWRITE)
            for regime in regimes:
                first = next(d for d in self.datasets.values() if d.regime == regime)
                self._submit(("null", regime, first.name, ""), null_check.run_null_check, first.to_dict(),
                             path_str(self.logs), compensation=self.compensation, window_s=self.window_s,
                             burn_in=self.burn_in, force=_OVERWRITE)
            for ds, seed in extra:
                self._submit(("realisation", ds.regime, ds.name, str(seed)), realisations.run_realisation,
                             ds.to_dict(), seed, path_str(self.logs), window_s=self.window_s, burn_in=self.burn_in)
            while self._futures:
                done, _ = wait(list(self._futures), return_when=FIRST_COMPLETED)
                for fut in sorted(done, key=lambda f: self._futures[f]):
                    key = self._futures.pop(fut)
                    result = fut.result()
                    bar.update(1)
                    bar.set_postfix_str(" ".join(k for k in key if k))
                    self._on_done(key, result)
        except BaseException:
            for fut in self._futures:
                fut.cancel()
            raise
        finally:
            bar.close()

    def _realisation_tasks(self) -> list[tuple[Dataset, int]]:
        """(dataset, seed) of every extra realisation: the ``paper`` regime's full-size datasets only."""
        count = 0 if self.quick else realisations.REALISATIONS
        return [(ds, seed) for ds in self.datasets.values() if ds.regime == "paper"
                for seed in realisations.realisation_seeds(ds.config, count)]

    def _submit(self, key: _Key, fn: Any, *args: Any, **kwargs: Any) -> None:
        self._futures[self._pool.submit(fn, *args, **kwargs)] = key

    def _track(self, ds: Dataset, method: str, models: list[str]) -> None:
        keep = (TABLE4_RATE,) if (ds.name, method) == TRAJECTORY[:2] else ()
        self._submit(("track", ds.regime, ds.name, method), track_and_score, self._path(ds, "centroids"),
                     self._path(ds, f"track_{method}"), dataset=ds.name, regime=ds.regime, method=method,
                     models=models, tracker=dict(ds.tracker), motion=dict(ds.motion),
                     rates_uncompensated=list(UNCOMPENSATED_RATES), rates_compensated=list(COMPENSATED_RATES),
                     window_s=self.window_s, keep_series=list(keep), compensation=self.compensation,
                     burn_in=self.burn_in, force=_OVERWRITE)

    def _on_done(self, key: _Key, result: Any) -> None:
        kind, regime, name, detail = key
        if kind == "centroid":
            self._track(self.datasets[(regime, name)], "NONE", list(MODELS))
        elif kind == "track":
            self.track_results.append(result)
            self.series.update(result["series"])
            if detail == "NONE":
                self._none_done(regime, name, result["rows"])
        elif kind == "compensate":
            self.showcases.append(result)
        elif kind == "realisation":
            self.realisation_rows.extend(result)
        else:
            self.null_results.append(result)

    def _none_done(self, regime: str, name: str, rows: list[dict[str, Any]]) -> None:
        """Once every dataset of ``regime`` has its NONE rows: pick Table 2's best model, run the rest."""
        done = self._none_rows.setdefault(regime, {})
        done[name] = rows
        members = [d for d in self.datasets.values() if d.regime == regime]
        if len(done) < len(members):
            return
        window = f"{self.window_s:g}s" if self.window_s is not None else "full"
        best = best_table2_model([r for v in done.values() for r in v], window=window)
        self.best_models[regime] = best
        for ds in members:
            for method in METHODS[1:]:
                self._track(ds, method, [best])
            self._submit(("compensate", regime, ds.name, f"NONE/{best}"), compensate_showcase,
                         self._path(ds, "track_NONE"), self._path(ds, "compensated"), dataset=ds.name,
                         regime=regime, track_topic=f"/track/NONE/{best}", rates=list(_SHOWCASE_RATES),
                         burn_in=self.burn_in, force=_OVERWRITE)


def _cross_check(rows: list[dict[str, Any]], showcases: list[dict[str, Any]]) -> float | None:
    """Largest |difference| between the compensate stage's figures and the sweep's (full window)."""
    index = {(r["regime"], r["dataset"], r["method"], r["model"], r["rate_hz"], r["protocol"], r["reference"]): r
             for r in rows if r["window"] == "full" and r["compensated"] and r["burn_in"] == "skipped"}
    worst: float | None = None
    for sc in showcases:
        for rec in sc["records"]:
            for fig in rec["figures"]:
                r = index.get((sc["regime"], sc["dataset"], rec["method"], rec["model"], rec["rate_hz"],
                               rec["protocol"], fig["reference"]))
                if r is None:
                    continue
                d = max(abs(r["rmse_before"] - fig["rmse_before"]), abs(r["rmse_after"] - fig["rmse_after"]))
                worst = d if worst is None else max(worst, d)
    return worst


def experiment_command(
    output_dir: str | os.PathLike[str],
    *,
    quick: bool = False,
    workers: int = 1,
    scheduler: str | None = None,
    force: bool = False,
    show_progress: bool = True,
    sweep: bool = False,
    regimes: tuple[str, ...] | list[str] = REGIMES,
    compensation: dict[str, Any] | None = None,
    burn_in: BurnInSetting = "auto",
) -> ExperimentSummary | RegimeSummary:
    """What ``starlog experiment -o DIR [--quick] [--sweep] [--regime R] [--top-k K] [--force-top-k] [--workers N]
    [--scheduler ADDR] [--force] [--burn-in auto|off|S]`` calls.

    ``sweep`` runs the regime map (:mod:`starlog.experiment.regime`) instead of the paper's tables
    (``regimes`` and ``compensation`` are then not used).

    ``scheduler`` sends the independent runs to that Dask cluster; otherwise ``workers > 1``
    starts a local Dask cluster of that many processes (:func:`starlog.batch.executor_for`);
    ``workers == 1`` runs serially. The results do not depend on which.
    """
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise InvalidParameterError(f"workers must be an integer >= 1, got {workers!r}.")
    try:
        with executor_for(scheduler=scheduler, workers=workers) as executor:
            if sweep:
                return run_regime_map(output_dir, quick=quick, executor=executor, force=force,
                                      show_progress=show_progress)
            return run_experiment(output_dir, quick=quick, executor=executor, force=force,
                                  show_progress=show_progress, regimes=regimes, compensation=compensation,
                                  burn_in=burn_in)
    except BaseException:
        if not scheduler:  # the local workers are stopped: their unfinished outputs are nobody's now
            _remove_partial_outputs(Path(output_dir))
        raise


def _remove_partial_outputs(out: Path) -> None:
    """Delete the temporary files of outputs a stopped worker left unfinished (``.NAME.XXXX.partial``):
    a worker that is terminated does not run the cleanup a stage does on an error or Ctrl-C."""
    for folder in (out, out / "logs"):
        for path in folder.glob(".*.partial"):
            path.unlink(missing_ok=True)
