"""Commands that run several stages: ``run`` (a pipeline config on logs) and ``experiment`` (the paper's tables)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import click

from starlog.cli.options import (
    BURN_IN_HELP,
    CONTEXT,
    burn_in_setting,
    echo_status,
    json_option,
    print_json,
    quiet_option,
    report_batch,
    scheduler_option,
    time_range_options,
    write_options,
)

__all__ = ["experiment", "run"]


def _batch_report(output: Path, force: bool) -> str:
    """Write the HTML report beside one output of a batch ``run``; the text saying so."""
    from starlog.report import write_report

    report = output.with_suffix(".html")
    if report.exists() and not force:
        return f"; {report.name} exists (kept; --force replaces it)"
    write_report(output, report)
    return f"; report {report}"


def _skipped_note(skipped: list[dict[str, Any]]) -> str:
    """``; log too short for compensate at 10 Hz leakfree``: what one log of a batch ``run`` left out."""
    if not skipped:
        return ""
    return "; log too short for compensate at " + ", ".join(f"{s['rate_hz']:g} Hz {s['protocol']}" for s in skipped)


@click.command(context_settings=CONTEXT)
@click.argument("logs", nargs=-1, type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option("-o", "--output", type=click.Path(path_type=Path),
              help="Output log (.mcap); with several input logs, a folder (one output per log, same name).")
@click.option("--config", "config_path", type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="Pipeline config (TOML) [default: the built-in config, see --print-config].")
@click.option("--print-config", is_flag=True, help="Print the built-in config (a starting point) and exit.")
@click.option("--table", "full_table", is_flag=True,
              help="Print every compensation row (one log), not only the short summary.")
@time_range_options("the first stage's input channel (the image channel for centroid)",
                    "The first stage reads [start, end) of every channel; the others process what it wrote.")
@scheduler_option
@json_option
@click.option("--flatten", is_flag=True, help="Write OUTPUT as one self-contained log (the input and every stage's "
                                               "channels) instead of a chain of layers (the layers are removed).")
@write_options
def run(logs: tuple[Path, ...], output: Path | None, config_path: Path | None, print_config: bool, full_table: bool,
        start: str | None, end: str | None, scheduler: str | None, as_json: bool, flatten: bool, force: bool,
        compression: str, workers: int, quiet: bool) -> None:
    """Replay logs through several stages (centroid, track, compensate, solve) from one config file.

    Each stage's parameters come from its table in the TOML config; your own stages run after
    them from [stages.NAME] tables (uses = "module:function"). Each stage writes a layer on the
    one before it: OUT.1-centroid.mcap, OUT.2-track-NONE.mcap, ... and the last one OUT itself,
    each the file the stage run alone gives; reading OUT reads them all with the input (open
    them together in Foxglove). With --flatten, OUT is then the whole chain as one
    self-contained log (what `starlog flatten` gives), and the other layers are removed. One
    log: --workers sets the cores for per-frame work, and an HTML
    report (figures of every stage, see `starlog report`) is written beside the output with
    the suffix .html; a short summary points to it. Several logs:
    they run in parallel on a Dask cluster (--scheduler, or a local one with --workers), a
    failed log is reported and the others complete.

    Before any stage runs, the [compensate] rates and protocols are checked against the log's
    length (the compensate stage's own rule): without --config, those the log is too short for
    are left out, one line each on stderr and in the summary; a --config file that names one
    is refused at once, with the log length it needs.

    \b
    Example:
      starlog run --print-config > pipeline.toml
      starlog run sim.mcap -o result.mcap --config pipeline.toml
      starlog run logs/*.mcap -o results/ --config pipeline.toml --scheduler tcp://10.0.0.5:8786
      starlog run sim.mcap -o first-second.mcap --start 0s --end 1s
    """
    from starlog.pipeline import DEFAULT_CONFIG_TOML, load_config, run_pipeline_batch

    if print_config:
        click.echo(DEFAULT_CONFIG_TOML, nl=False)
        return
    if not logs or output is None:
        raise click.UsageError("give the input LOG(s) and -o/--output (or --print-config).")
    config = load_config(config_path)
    if len(logs) > 1 or scheduler:
        outcomes = run_pipeline_batch(logs, output, config, scheduler=scheduler, workers=workers,
                                      show_progress=not quiet, force=force, flatten=flatten, compression=compression,
                                      start=start, end=end)
        reports = {o.result["output"]: _batch_report(Path(o.result["output"]), force) for o in outcomes if o.ok}
        report_batch(outcomes, as_json, lambda r: f"wrote {r['output']} ({len(r['stages'])} stages"
                     f"{_skipped_note(r['skipped'])}){reports[r['output']]}")
        return

    from starlog import api
    from starlog.compensation import Shortfall
    from starlog.pipeline import report_path, stage_line
    from starlog.stages.compensate import decision_table

    def stage_done(stage: str, result: dict[str, Any]) -> None:
        line = stage_line(stage, result)
        if line is not None:
            echo_status(quiet, line)

    def skipping(shortfall: Shortfall) -> None:
        echo_status(quiet, f"skipped, log too short: compensate {shortfall.describe()}")

    result = api.run(logs[0], output, config=config, workers=workers, force=force, flatten=flatten,
                     compression=compression, progress=not quiet, on_stage=stage_done, on_skip=skipping,
                     start=start, end=end)
    html = report_path(output)
    if result.layers:
        echo_status(quiet, f"wrote {len(result.layers)} layers on {logs[0]}: "
                           f"{', '.join(str(p) for p in result.layers)}")
    echo_status(quiet, f"wrote {output}; inspect it with: starlog info {output}; tables: starlog export {output} -o DIR")
    echo_status(quiet, f"wrote {html}")
    if as_json:
        print_json({**result.to_dict(), "report": str(html)})
        return
    if full_table:
        for stage, summary in result.stages:
            if stage == "compensate":
                click.echo(decision_table(summary["records"]))
    click.echo("\n".join(result.lines()))


@click.command(context_settings=CONTEXT)
@click.option("-o", "--output", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="Folder for the datasets, logs, tables (Markdown + Parquet), plots and report.")
@click.option("--quick", is_flag=True, help="Small frames and few frames: every table and plot in about a minute.")
@click.option("--sweep", is_flag=True, help="Instead of the paper's tables, the regime map: keep vs separate "
                                            "compensation over jitter 0-10x the centroid noise, 3/6/20 stars, 10 and "
                                            "50 Hz, every UKF model (regime_map.parquet/.md/.png).")
@click.option("--regime", "regimes", type=click.Choice(["paper", "modern"]), multiple=True,
              help="Dataset regime(s) to run (repeatable): 'paper' (conditions derived from the paper's numbers) "
                   "or 'modern'. Default: both.")
@click.option("--top-k", type=click.IntRange(1, 5), default=3, show_default=True,
              help="Most strategies run per compensation (those with an eq. 12 score > 0).")
@click.option("--force-top-k", is_flag=True,
              help="Ablation: run the top-k strategies even when their eq. 12 score is 0.")
@click.option("--workers", type=click.IntRange(1, 256), default=os.cpu_count() or 1, show_default="all cores",
              help="Local Dask workers for the independent runs (1: serial).")
@scheduler_option
@click.option("--force", is_flag=True, help="Overwrite an existing output folder's results.")
@quiet_option
@json_option
@click.option("--burn-in", "burn_in", default="auto", show_default=True, metavar="auto|off|SECONDS", help=BURN_IN_HELP)
def experiment(output: Path, quick: bool, sweep: bool, regimes: tuple[str, ...], top_k: int, force_top_k: bool,
               workers: int, scheduler: str | None, force: bool, quiet: bool, as_json: bool,
               burn_in: str = "auto") -> None:
    """Regenerate the paper's Tables 2-4 and Figure 5 on simulated "laboratory" datasets.

    Simulates the two datasets (300 Hz x 3248 frames, 200 Hz x 3027 frames; static star field,
    small platform perturbations) in each regime ('paper': one faint star, read noise and background,
    conditions derived from the paper's numbers; 'modern': six bright stars), runs centroid ->
    track -> compensate (the filter's start-up skipped; Table 3 with Table 2's best model) and
    writes each table under the paper's protocol with the paper's numbers beside ours, and again
    under the honest protocols (truth, leakfree); Table 2's cells again over 8 more simulated
    realisations of the 'paper' datasets (not with --quick; a single dataset's cell scatters by
    7-12 %); plots (Figure 4/5 analogues, trajectories) and report.md.

    \b
    Example:
      starlog experiment -o results/ --quick
      starlog experiment -o results/ --regime paper --workers 2
      starlog experiment -o ablation/ --force-top-k --workers 2
      starlog experiment -o results/ --scheduler tcp://10.0.0.5:8786
      starlog experiment -o regime/ --sweep --workers 2
    """
    from starlog.experiment import experiment_command

    compensation: dict[str, object] = {"top_k": top_k, "select_positive": not force_top_k}
    summary = experiment_command(output, quick=quick, workers=workers, scheduler=scheduler, force=force,
                                 show_progress=not quiet, sweep=sweep, regimes=regimes or ("paper", "modern"),
                                 compensation=compensation, burn_in=burn_in_setting(burn_in))
    if as_json:
        print_json(summary.to_dict())
    else:
        click.echo(summary.text())
