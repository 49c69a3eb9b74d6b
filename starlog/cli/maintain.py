"""Commands that copy or repair a log: ``filter`` (channels and a time range), ``flatten`` (a chain into one
file), ``recover`` (a damaged log) and ``verify`` (every record checked)."""

from __future__ import annotations

import sys
from pathlib import Path

import click

from starlog.cli.options import (
    CONTEXT,
    COPY_RANGE,
    echo_status,
    input_log,
    json_option,
    output_option,
    print_json,
    quiet_option,
    time_range_options,
    topic_selection_options,
)

__all__ = ["filter_command", "flatten", "recover", "verify"]


@click.command(name="filter", context_settings=CONTEXT)
@input_log
@output_option()
@topic_selection_options
@time_range_options("--frame-topic", COPY_RANGE)
@click.option("--force", is_flag=True, help="Overwrite the output if it exists.")
@click.option("--compression", type=click.Choice(["zstd", "lz4", "none"]), default="zstd", show_default=True,
              help="Compression of the chunks that must be re-encoded (those only partly kept); chunks kept whole "
                   "are copied as they are.")
@quiet_option
@json_option
def filter_command(log: Path, output: Path, topics: tuple[str, ...], exclude_topics: tuple[str, ...],
                   frame_topic: str | None, start: str | None, end: str | None, force: bool, compression: str,
                   quiet: bool, as_json: bool) -> None:
    """Copy some channels and a time range of any MCAP log into a new log.

    Keeps the schemas, metadata and provenance records (and attachments in the range) and adds
    a provenance record of its own (stage "filter"). A chunk whose every message is kept is
    copied byte for byte, never re-compressed; a chunk only partly kept is re-encoded. The
    range is half-open: [start, end). Works on ROS 2 bags, Foxglove logs and logs without
    indexes as on starlog logs; the output is fully indexed.

    \b
    Example:
      starlog filter sim.mcap -o images.mcap --topic '/camera/*'
      starlog filter trk.mcap -o small.mcap --exclude-topic '/camera/image' --start 1s --end 2.5s
      starlog filter bag.mcap -o first100.mcap --end frame:100
    """
    from starlog.excerpt import filter_log

    report = filter_log(log, output, topics=topics, exclude_topics=exclude_topics, start=start, end=end,
                        frame_topic=frame_topic, force=force, compression=compression)
    d = report.to_dict()
    echo_status(quiet, f"wrote {output}: {sum(d['messages'].values())} messages of {len(d['messages'])} topics; "
                       f"{d['chunks_copied']} chunks copied as they are, {d['chunks_reencoded']} re-encoded")
    if as_json:
        print_json(d)
    else:
        for topic, count in d["messages"].items():
            click.echo(f"  {topic}: {count} messages")


@click.command(context_settings=CONTEXT)
@input_log
@output_option("Output log (.mcap): one self-contained file. Written atomically.")
@click.option("--force", is_flag=True, help="Overwrite the output if it exists.")
@quiet_option
@json_option
def flatten(log: Path, output: Path, force: bool, quiet: bool, as_json: bool) -> None:
    """Write a layer and its chain (the log it extends, and so on) as one self-contained log.

    Every message, schema, metadata and attachment record of the chain's files is kept; chunks are
    copied byte for byte (nothing is decompressed or re-compressed). The records by which layers
    name their bases are left out: the output holds the bases. Use it for the file to share or
    archive, or for tools that read one file; every starlog command reads a chain as it is.

    \b
    Example:
      starlog flatten result.mcap -o result-all.mcap
    """
    from starlog import api

    report = api.flatten(log, output, force=force)
    for line in report.lines():
        echo_status(quiet, line)
    if as_json:
        print_json(report.to_dict())


@click.command(context_settings=CONTEXT)
@input_log
@output_option("Output log (.mcap), complete and fully indexed.")
@click.option("--force", is_flag=True, help="Overwrite the output if it exists.")
@json_option
@quiet_option
def recover(log: Path, output: Path, force: bool, as_json: bool, quiet: bool) -> None:
    """Rebuild a readable, indexed log from a truncated, unfinished or damaged one.

    Keeps every complete message (chunks whose bytes are whole and whose CRC checks) and the
    provenance records, and reports what was lost: damaged or cut-off chunks with their time
    range and, where the file still says, the channels and message counts they held. A layer
    stays a layer on its base when the base is there, unchanged; else its own records are
    recovered into a file that opens alone.

    \b
    Example:
      starlog recover crashed.mcap -o recovered.mcap
      starlog recover crashed.mcap -o recovered.mcap --json
    """
    from starlog.io.recover import recover_log

    report = recover_log(log, output, force=force)
    if as_json:
        print_json(report.to_dict())
        return
    echo_status(quiet, f"wrote {output}")
    for line in report.lines():
        click.echo(line)


@click.command(context_settings=CONTEXT)
@input_log
@click.option("--file-only", is_flag=True, help="Check this one file alone, not the bases of a layer.")
@json_option
@quiet_option
def verify(log: Path, file_only: bool, as_json: bool, quiet: bool) -> None:
    """Check every record of an MCAP log and report every problem found (like `mcap doctor`).

    Checks magic, header, footer, the summary and its CRC, every chunk (CRC, decompression),
    message and chunk indexes against the contents, statistics, schema/channel references,
    JSON messages against their schemas, protobuf/ROS decoding, image decoding and size, and
    log_time order per channel, channels sharing a topic. Valid but unusual layouts (no message
    indexes, no summary, channels of one schema sharing a topic) are notes; channels of schemas
    starlog cannot read as one series on one topic are an error; a file starlog reads in full but
    that breaks a rule of the MCAP specification (a summary without the schema and channel
    records its chunk indexes name) is a warning, and `starlog filter LOG -o OUT` rewrites it.
    A layer is checked with every file of its chain: each base must be where the layer says,
    with the size, summary CRC and SHA-256 it recorded, and ids and topics must be unique across
    the chain (--file-only: the one file).

    \b
    Exit status: 0 valid (notes at most); 3 starlog reads it in full, but it does not conform to
    the MCAP specification (warnings); 1 damaged, or a part starlog refuses (errors).

    \b
    Example:
      starlog verify sim.mcap
      starlog verify result.mcap --file-only
      starlog verify bag.mcap --json | jq '.files[].problems[] | select(.severity == "error")'
    """
    from starlog import api

    report = api.verify(log, file_only=file_only, progress=not quiet)
    if as_json:
        print_json(report.to_dict())
    else:
        for line in report.lines():
            click.echo(line)
    if report.exit_status:
        sys.exit(report.exit_status)
