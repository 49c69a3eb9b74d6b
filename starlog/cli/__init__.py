"""The ``starlog`` command line: a thin layer over :mod:`starlog.stages`, :mod:`starlog.io` and :mod:`starlog.export`.

Every command has ``--help`` with an example; commands that print results accept ``--json``.
Errors starlog raises on purpose are printed as one sentence with exit status 1.

One module per group of commands, each command a call of the library: :mod:`~starlog.cli.logs`
(simulate, ingest), :mod:`~starlog.cli.stages` (centroid, track, motion, compensate, solve, and the
command of each installed stage), :mod:`~starlog.cli.pipeline` (run, experiment), :mod:`~starlog.cli.live` (live),
:mod:`~starlog.cli.inspect` (info, cat, export, report) and :mod:`~starlog.cli.maintain`
(filter, flatten, recover, verify); the options they share are in :mod:`~starlog.cli.options`.
Here: the group, which also lists the stages installed packages register, and :func:`main`.
"""

from __future__ import annotations

import functools
import os
from typing import Any

import click

from starlog import __version__
from starlog.cli.inspect import cat, export, info, report_command
from starlog.cli.live import live
from starlog.cli.logs import ingest, simulate
from starlog.cli.maintain import filter_command, flatten, recover, verify
from starlog.cli.options import CONTEXT
from starlog.cli.pipeline import experiment, run
from starlog.cli.stages import centroid, compensate, motion, solve, stage_command, track
from starlog.errors import StarlogError

__all__ = ["cli", "main"]


class _StarlogGroup(click.Group):
    def invoke(self, ctx: click.Context) -> Any:
        try:
            return super().invoke(ctx)
        except StarlogError as err:
            raise click.ClickException(str(err)) from err

    def list_commands(self, ctx: click.Context) -> list[str]:
        """The built-in commands, then the stages installed packages register (not imported to list them)."""
        builtin = super().list_commands(ctx)
        return [*builtin, *sorted(set(_installed_stages()) - set(builtin))]

    def get_command(self, ctx: click.Context, cmd_name: str) -> click.Command | None:
        command = super().get_command(ctx, cmd_name)
        if command is None and cmd_name in _installed_stages():
            return _LazyStageCommand(cmd_name)
        return command

    def format_commands(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        """Built-in commands, then installed stages in a section of their own."""
        builtin = [name for name in super().list_commands(ctx) if not self.commands[name].hidden]
        limit = formatter.width - 6 - max(map(len, builtin), default=0)
        with formatter.section("Commands"):
            formatter.write_dl([(name, self.commands[name].get_short_help_str(limit)) for name in builtin])
        installed = _installed_stages()
        for name in sorted(set(installed) & set(builtin)):
            click.echo(f"warning: the stage {name!r} installed by {installed[name]} is hidden by the built-in "
                       f"command {name!r}.", err=True)
        extra = [(name, _LazyStageCommand(name).get_short_help_str()) for name in sorted(set(installed) - set(builtin))]
        if extra:
            with formatter.section("Installed stages (entry points 'starlog.stages'; STAGE --help for more)"):
                formatter.write_dl(extra)


@click.group(cls=_StarlogGroup, context_settings=CONTEXT)
@click.version_option(__version__, prog_name="starlog")
def cli() -> None:
    """starlog: star-tracker centroid extraction, with every step kept in MCAP logs.

    A log starts as image frames (simulate, ingest); each stage writes a layer on it holding
    only the channels it adds, and names the log it extends. Every command reads a layer with
    its chain as one log; open the files together in Foxglove; flatten makes one file of them;
    export tables to Parquet.

    Pixel coordinates: x = column, y = row, (0, 0) at the centre of the top-left pixel.
    Times: integer nanoseconds (log_time).

    Results print on stdout (--json: as JSON); progress bars and status lines ("wrote ...") go
    to stderr, and -q silences them.
    """


for _command in (simulate, ingest, info, export, centroid, track, motion, compensate, solve, run, live, experiment,
                 filter_command, cat, report_command, recover, verify, flatten):
    cli.add_command(_command)


# ---------------------------------------------------------------- installed stages
@functools.cache
def _installed_stages() -> dict[str, str]:
    """Name → ``"package version"`` of every stage installed packages register (their metadata only, once)."""
    from starlog.plugins import distribution_of, registered_stages

    return {name: distribution_of(point) for name, point in registered_stages().items()}


class _LazyStageCommand(click.Command):
    """An installed stage's command, listed without importing it; imported when it runs or shows its help."""

    def __init__(self, name: str) -> None:
        super().__init__(name, context_settings=CONTEXT)

    def get_short_help_str(self, limit: int = 45) -> str:
        return f"Stage from {_installed_stages().get(self.name or '', '?')} (run STAGE --help)."

    def make_context(self, info_name: str | None, args: list[str], parent: click.Context | None = None,
                     **extra: Any) -> click.Context:
        from starlog.plugins import load_registered

        try:
            declared = load_registered(self.name or "")
        except StarlogError as err:
            raise click.ClickException(str(err)) from err
        return stage_command(declared, self.name or declared.name).make_context(info_name, args, parent, **extra)


class _Terminated(BaseException):
    """SIGTERM arrived: unwind (abort partial outputs, stop worker pools), then die of the signal."""


def _raise_terminated(signum: int, frame: Any) -> None:
    raise _Terminated()


def main() -> None:
    """Console-script entry point."""
    import signal

    signal.signal(signal.SIGTERM, _raise_terminated)
    try:
        cli(prog_name="starlog")
    except _Terminated:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        os.kill(os.getpid(), signal.SIGTERM)  # exit status says "terminated by SIGTERM", as without the handler
