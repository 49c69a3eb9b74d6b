"""What the commands share: the options every command group uses, and how results and status lines print."""

from __future__ import annotations

import json
import os
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import click

__all__ = ["BURN_IN_HELP", "CONTEXT", "COPY_RANGE", "burn_in_setting", "echo_status", "flatten_option",
           "image_topic_option", "input_log", "json_option", "key_values", "output_option", "overwrite_options",
           "print_json", "quiet_option", "report_batch", "scheduler_option", "time_range_options",
           "topic_selection_options", "write_options", "frame_write_options"]

F = TypeVar("F", bound=Callable[..., Any])
CONTEXT = {"help_option_names": ["-h", "--help"], "max_content_width": 100}
#: ``starlog.io.writer.FRAME_COMPRESSION``, named here so that ``--help`` does not import the log layer (a test
#: keeps the two equal).
FRAME_COMPRESSION_DEFAULT = "lz4"
QUIET_HELP = "No progress bar and no status lines on stderr; results (stdout, --json) still print."


def print_json(data: Any) -> None:
    click.echo(json.dumps(data, indent=2, allow_nan=False))


def print_result(summary: Any, as_json: bool, data: dict[str, Any] | None = None) -> None:
    """A stage's result on stdout: ``data`` (default ``summary.to_dict()``) as JSON, or ``summary.lines()``."""
    if as_json:
        print_json(summary.to_dict() if data is None else data)
        return
    for line in summary.lines():
        click.echo(line)


def echo_status(quiet: bool, text: str) -> None:
    """A status line (what was written where) on stderr, unless ``--quiet``; results go to stdout."""
    if not quiet:
        click.echo(text, err=True)


def key_values(values: tuple[str, ...], option: str) -> dict[str, Any]:
    """``KEY=VALUE`` options → dict (values parsed as JSON when they can be, else strings)."""
    out: dict[str, Any] = {}
    for item in values:
        key, sep, raw = item.partition("=")
        if not sep or not key:
            raise click.BadParameter(f"{item!r}: expected KEY=VALUE", param_hint=option)
        try:
            out[key.strip()] = json.loads(raw)
        except json.JSONDecodeError:
            out[key.strip()] = raw
    return out


def report_batch(outcomes: list[Any], as_json: bool, describe: Callable[[Any], str]) -> None:
    """Each log of a batch done or failed (``--json``: as JSON), and a count; exit status 1 when one failed."""
    failed = [o for o in outcomes if not o.ok]
    if as_json:
        print_json([{"log": o.name, "ok": o.ok, "result": o.result, "error": o.error} for o in outcomes])
    else:
        for o in outcomes:
            click.echo(f"{o.name}: {describe(o.result)}" if o.ok else f"{o.name}: FAILED: {o.error}")
        click.echo(f"{len(outcomes) - len(failed)} of {len(outcomes)} logs done, {len(failed)} failed.")
    if failed:
        sys.exit(1)


# ---------------------------------------------------------------- shared options
def output_option(help_text: str = "Output log (.mcap). Written atomically.") -> Callable[[F], F]:
    return click.option("-o", "--output", required=True, type=click.Path(dir_okay=False, path_type=Path),
                        help=help_text)


def quiet_option(f: F) -> F:
    return click.option("--quiet", "-q", is_flag=True, help=QUIET_HELP)(f)


def _overwrite_options(f: F, compression: str, compression_help: str) -> F:
    f = click.option("--compression", type=click.Choice(["zstd", "lz4", "none"]), default=compression,
                     show_default=True, help=compression_help)(f)
    return click.option("--force", is_flag=True, help="Overwrite the output if it exists.")(f)


def overwrite_options(f: F) -> F:
    """--force, --compression (of the output log's chunks)."""
    return _overwrite_options(f, "zstd", "Chunk compression of the output log.")


def _workers_option(f: F) -> F:
    return click.option("--workers", type=click.IntRange(1, 256), default=os.cpu_count() or 1,
                        show_default="all cores",
                        help="Cores for per-frame work, image decoding and chunk compression; the output "
                             "does not depend on it.")(f)


def write_options(f: F) -> F:
    """--force, --compression, --workers, --quiet."""
    return overwrite_options(_workers_option(quiet_option(f)))


def frame_write_options(f: F) -> F:
    """:func:`write_options` of a command that writes camera frames: their chunks in lz4 by default, which the
    stages reading every frame decode fastest for their size."""
    return _overwrite_options(_workers_option(quiet_option(f)), FRAME_COMPRESSION_DEFAULT,
                              "Chunk compression of the output log: lz4 decodes fastest for its size (zstd: smaller "
                              "files, slower to read; none: the largest, fastest to read).")


FLATTEN_HELP = ("Write one self-contained log (every file of the input's chain and this stage's channels) instead "
                "of a layer on the input: the file to share or archive.")


def flatten_option(f: F) -> F:
    return click.option("--flatten", is_flag=True, help=FLATTEN_HELP)(f)


def json_option(f: F) -> F:
    return click.option("--json", "as_json", is_flag=True, help="Print the result as JSON.")(f)


input_log = click.argument("log", type=click.Path(exists=True, dir_okay=False, path_type=Path))


RANGE_HELP = ("log time in ns (1234567), seconds on the same clock with an 's' suffix (12.5s), or frame:N "
              "(the N-th message, 0-based, of {what})")


STAGE_RANGE = "The stage reads [start, end) of every channel; its channels hold that range."
COPY_RANGE = "Every channel's messages in [start, end) are kept."


def time_range_options(what: str, effect: str = STAGE_RANGE) -> Callable[[F], F]:
    """--start / --end: the half-open range [start, end) of log_time to process (``effect`` says how)."""

    def add(f: F) -> F:
        f = click.option("--end", metavar="TIME",
                         help=f"Only messages before this time (exclusive): {RANGE_HELP.format(what=what)}. "
                              "Default: after the last message.")(f)
        f = click.option("--start", metavar="TIME",
                         help=f"Only messages from this time on (inclusive): {RANGE_HELP.format(what=what)}. "
                              f"{effect} Default: the first message.")(f)
        return f

    return add


def image_topic_option(f: F) -> F:
    return click.option("--image-topic", metavar="TOPIC",
                        help="Image channel to read [default: /camera/image, else the log's only image channel]. "
                             "Any foxglove.RawImage/CompressedImage or ROS 1/2 sensor_msgs Image/CompressedImage.")(f)


def scheduler_option(f: F) -> F:
    return click.option("--scheduler", metavar="ADDRESS",
                        help="Dask scheduler (tcp://host:8786) to run several logs on; without it, --workers N > 1 "
                             "starts a local Dask cluster for several logs.")(f)


def topic_selection_options(f: F) -> F:
    """--topic / --exclude-topic globs and --frame-topic."""
    f = click.option("--frame-topic", metavar="TOPIC",
                     help="Channel whose messages frame:N counts [default: the only channel selected, else the log's "
                          "image channel].")(f)
    f = click.option("--exclude-topic", "exclude_topics", multiple=True, metavar="GLOB",
                     help="Leave out the channels matching this glob (fnmatch: * matches / too). Repeatable.")(f)
    f = click.option("--topic", "topics", multiple=True, metavar="GLOB",
                     help="Keep the channels matching this glob, e.g. '/camera/*' (fnmatch: * matches / too). "
                          "Repeatable. Default: every channel.")(f)
    return f


BURN_IN_HELP = ("The tracking filter's start-up skipped before scoring: auto (until its position variance is within "
                "2x of the steady state, capped at 0.5 s), off (score from the first frame), or a number of seconds. "
                "Recorded in every decision record.")


def burn_in_setting(value: str) -> object:
    """``--burn-in`` as a :data:`starlog.compensation.BurnInSetting` (a bad value is a usage error)."""
    from starlog.compensation import parse_burn_in
    from starlog.errors import InvalidParameterError

    try:
        return parse_burn_in(value)
    except InvalidParameterError as err:
        raise click.BadParameter(str(err), param_hint="--burn-in") from None
