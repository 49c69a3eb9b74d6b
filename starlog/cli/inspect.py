"""Commands that read a log without changing it: ``info``, ``cat``, ``export`` (Parquet) and ``report`` (HTML)."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import click

from starlog.errors import FileAccessError, file_errors

from starlog.cli.options import (
    CONTEXT,
    COPY_RANGE,
    echo_status,
    input_log,
    json_option,
    output_option,
    print_json,
    quiet_option,
    report_batch,
    scheduler_option,
    time_range_options,
    topic_selection_options,
)

__all__ = ["cat", "export", "info", "report_command"]


@click.command(context_settings=CONTEXT)
@input_log
@json_option
@quiet_option
def info(log: Path, as_json: bool, quiet: bool) -> None:
    """Show a log's channels, time range and the provenance of every stage.

    \b
    Example:
      starlog info sim.mcap
      starlog info sim.mcap --json | jq '.channels[].topic'
    """
    from starlog.cli.describe import info_text
    from starlog.facts import log_facts

    facts = log_facts(log)
    if as_json:
        print_json(facts)
        return
    click.echo(info_text(facts))
    for note in facts["notes"]:  # how the log was read, not what it holds
        echo_status(quiet, f"note: {note}")


@click.command(context_settings=CONTEXT)
@input_log
@topic_selection_options
@time_range_options("--frame-topic", COPY_RANGE)
@click.option("--limit", type=click.IntRange(0), help="Stop after this many messages.")
@quiet_option
def cat(log: Path, topics: tuple[str, ...], exclude_topics: tuple[str, ...], frame_topic: str | None,
        start: str | None, end: str | None, limit: int | None, quiet: bool) -> None:
    """Print messages as JSON lines, in log_time order, for jq and scripts.

    Each line is {"topic", "log_time", "publish_time", "sequence", "message"}. starlog's JSON
    messages come out as they are; images as {width, height, encoding, bytes, sha256} instead of
    pixels; other protobuf, ROS 1 and ROS 2 messages decoded to objects (long byte fields as
    {bytes, sha256}); anything else as {schema, encoding, bytes}.

    \b
    Example:
      starlog cat sim.mcap --topic /sim/truth --limit 3
      starlog cat cen.mcap --topic '/stars/centroids/*' --start frame:10 --end frame:20 | jq '.message.stars | length'
      starlog cat bag.mcap --topic /camera/image_raw | head -n 5
    """
    from starlog.cli.describe import json_line
    from starlog.excerpt import cat_messages

    notes: list[str] = []
    lines = cat_messages(log, topics=topics, exclude_topics=exclude_topics, start=start, end=end,
                         frame_topic=frame_topic, limit=limit, notes=notes)
    out = sys.stdout
    try:
        for line in lines:
            with file_errors("standard output"):
                out.write(json_line(line))
                out.write("\n")
        with file_errors("standard output"):
            out.flush()
        for note in notes:  # how the log was read
            echo_status(quiet, f"note: {note}")
    except FileAccessError as err:
        if not isinstance(err.__cause__, BrokenPipeError):
            raise
        # the reader (head, jq ...) has what it wanted: stop quietly
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, out.fileno())  # the interpreter's final flush must not fail again
        lines.close()


@click.command(context_settings=CONTEXT)
@click.argument("logs", nargs=-1, required=True, type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option("-o", "--output", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="Folder for the Parquet files (created if missing); with several logs, one sub-folder each.")
@click.option("--table", "tables", multiple=True, help="Only this table (repeatable); default: every table the log has.")
@click.option("--topic", "export_topics", multiple=True, metavar="TOPIC",
              help="Also export this channel (any JSON, protobuf, ROS 1/2 channel) as a flat table <topic>.parquet: "
                   "log_time first, nested fields as a.b columns, arrays as lists. Repeatable.")
@click.option("--force", is_flag=True, help="Overwrite existing Parquet files.")
@click.option("--workers", type=click.IntRange(1, 256), default=1, show_default=True,
              help="With several logs: local Dask workers.")
@scheduler_option
@quiet_option
@json_option
def export(logs: tuple[Path, ...], output: Path, tables: tuple[str, ...], export_topics: tuple[str, ...], force: bool,
           workers: int, scheduler: str | None, quiet: bool, as_json: bool) -> None:
    """Export a log's channels to Parquet tables (one file per table).

    Tables: frames, truth (simulated logs), detections, centroids, tracks, compensation,
    decisions — each written when the log has its channels. Columns are documented in
    schemas/tables.json and docs/FORMATS.md. A log from another tool gets a frames table of its
    image channels (topic column); --topic exports any channel as a flat table. With nothing
    to export, the command says so, lists the channels and fails. Several logs go to one
    sub-folder each, in parallel on a Dask cluster with --scheduler or --workers.

    \b
    Example:
      starlog export sim.mcap -o tables/
      starlog export runs/*.mcap -o tables/ --workers 2
      starlog export bag.mcap -o tables/ --topic /imu/data
      python -c "import pyarrow.parquet as pq; print(pq.read_table('tables/truth.parquet'))"
    """
    from starlog import api
    from starlog.batch import BatchTask, run_batch

    selected = tables or None
    if len(logs) == 1 and not scheduler:
        written = api.export(logs[0], output, tables=selected, force=force, topics=export_topics)
        if as_json:
            print_json({"output": str(output), "tables": written})
        else:
            for name, rows in written.items():
                click.echo(f"{output / (name + '.parquet')}: {rows} rows")
        return
    tasks = [BatchTask(str(log), api.export, (str(log.absolute()), str((output / log.stem).absolute())),
                       {"tables": selected, "force": force, "topics": export_topics}) for log in logs]
    outcomes = run_batch(tasks, scheduler=scheduler, workers=workers, show_progress=not quiet, description="export")
    report_batch(outcomes, as_json, lambda r: ", ".join(f"{k} {v} rows" for k, v in r.items()))


@click.command(name="report", context_settings=CONTEXT)
@input_log
@output_option("Output HTML file; one self-contained file (no network needed to view it). Written atomically.")
@click.option("--force", is_flag=True, help="Overwrite the output if it exists.")
@json_option
@quiet_option
def report_command(log: Path, output: Path, force: bool, as_json: bool, quiet: bool) -> None:
    """Write an HTML report of a log: figures and tables of every stage it holds.

    A frame with its centroids, the tracks of every star, the brightest star's error and its
    amplitude spectrum (dominant frequency marked), the error decomposition, RMSE before/after
    compensation per protocol, the strategy decisions and the provenance of every stage. A
    section whose channels the log lacks says so and names the stage that makes them. Long
    logs are sampled, so the file stays small; it needs no network to view.

    \b
    Example:
      starlog report result.mcap -o result.html
      starlog report sim.mcap -o sim.html --force
    """
    from starlog.report import collect_report_data, render_report
    from starlog.report.log_report import write_text_atomic

    data = collect_report_data(log)
    write_text_atomic(output, render_report(data), force=force)
    echo_status(quiet, f"wrote {output}" + (f" ({len(data.missing)} parts missing: {', '.join(data.missing)})"
                                            if data.missing else ""))
    if as_json:
        print_json({"output": str(output), "missing": data.missing})
