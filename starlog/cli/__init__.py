"""The ``starlog`` command line: a thin layer over :mod:`starlog.stages`, :mod:`starlog.io`, :mod:`starlog.facts`
and :mod:`starlog.parquet`.

Every command has ``--help`` with an example; commands that print results accept ``--json``.
Errors starlog raises on purpose are printed as one sentence with exit status 1.

One module per group of commands, each command a call of the library: :mod:`~starlog.cli.logs`
(simulate, ingest), :mod:`~starlog.cli.stages` (centroid, track, motion, compensate, solve, and the
command of each installed stage), :mod:`~starlog.cli.pipeline` (run, experiment), :mod:`~starlog.cli.live` (live),
:mod:`~starlog.cli.inspect` (info, cat, export, report; the text info and cat print is
:mod:`~starlog.cli.describe`'s) and :mod:`~starlog.cli.maintain`
(filter, flatten, recover, verify); the options they share are in :mod:`~starlog.cli.options`.
Here: the group, which also lists the stages installed packages register, and :func:`main`.
"""

from __future__ import annotations

import _thread
import atexit
import contextlib
import errno
import faulthandler
import functools
import os
import signal
import sys
import threading
import time
from typing import Any

import click

from starlog.version import __version__
from starlog.replay.lifeline import die_of
from starlog.cli.inspect import cat, export, info, report_command
from starlog.cli.live import live
from starlog.cli.logs import ingest, simulate
from starlog.cli.maintain import filter_command, flatten, recover, verify
from starlog.cli.options import CONTEXT
from starlog.cli.pipeline import experiment, run
from starlog.cli.stages import centroid, compensate, motion, solve, stage_command, track
from starlog.errors import WRITE_ERRNOS, FileAccessError, StarlogError

__all__ = ["cli", "main"]


class _StarlogGroup(click.Group):
    def invoke(self, ctx: click.Context) -> Any:
        try:
            return super().invoke(ctx)
        except StarlogError as err:
            raise click.ClickException(str(err)) from err
        except OSError as err:
            if err.errno == errno.EPIPE:  # the reader of stdout left: click ends quietly
                raise
            raise click.ClickException(str(_unattributed(err))) from err

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
    from starlog.replay.plugins import distribution_of, registered_stages

    return {name: distribution_of(point) for name, point in registered_stages().items()}


class _LazyStageCommand(click.Command):
    """An installed stage's command, listed without importing it; imported when it runs or shows its help."""

    def __init__(self, name: str) -> None:
        super().__init__(name, context_settings=CONTEXT)

    def get_short_help_str(self, limit: int = 45) -> str:
        return f"Stage from {_installed_stages().get(self.name or '', '?')} (run STAGE --help)."

    def make_context(self, info_name: str | None, args: list[str], parent: click.Context | None = None,
                     **extra: Any) -> click.Context:
        from starlog.replay.plugins import load_registered

        try:
            declared = load_registered(self.name or "")
        except StarlogError as err:
            raise click.ClickException(str(err)) from err
        return stage_command(declared, self.name or declared.name).make_context(info_name, args, parent, **extra)


def _unattributed(err: OSError) -> StarlogError:
    """An OS error that no reader or writer of starlog's named a file for: still one line."""
    if err.filename is not None:
        return FileAccessError.of(err, os.fsdecode(err.filename), "write" if err.errno in WRITE_ERRNOS else "use")
    return StarlogError(f"an operating-system error ended the command: {err.strerror or err}; check the output's "
                        "folder (space, permissions) and the inputs, then run it again.")


class _Terminated(BaseException):
    """SIGTERM arrived: unwind (abort partial outputs, stop worker pools), then die of the signal."""


_interrupted = False
_stopping = False


def _raise_terminated(signum: int, frame: Any) -> None:
    global _stopping
    _stopping = True
    raise _Terminated()


def _raise_interrupt(signum: int, frame: Any) -> None:
    """Ctrl-C: unwind as for SIGTERM; a second Ctrl-C while the command unwinds does not cut its cleanup short."""
    global _interrupted, _stopping
    _interrupted = _stopping = True
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    raise KeyboardInterrupt


def _redeliver_stop(unraisable: Any) -> None:
    """Python only reports an exception raised in code called back from C (numba's compiler cache, a finalizer);
    a Ctrl-C or SIGTERM landing there would be printed and lost. It is delivered again instead, a moment later,
    once that callback has returned. Every other report goes to Python's own hook, but for those raised once
    the command is stopping (a finalizer of an object the stop interrupted as it was made: llvmlite's, when
    the stop lands in numba's compiler)."""
    stop = unraisable.exc_value
    if not isinstance(stop, KeyboardInterrupt | _Terminated) or threading.current_thread() is not threading.main_thread():
        if not _stopping:  # once stopped, a finalizer of an object the stop left half made is no news
            sys.__unraisablehook__(unraisable)
        return
    signum = signal.SIGINT if isinstance(stop, KeyboardInterrupt) else signal.SIGTERM
    if signum == signal.SIGINT:
        signal.signal(signal.SIGINT, _raise_interrupt)  # it had turned itself off for the second Ctrl-C
    redelivery = threading.Timer(_REDELIVERY_DELAY_S, _thread.interrupt_main, args=(signum,))
    redelivery.daemon = True
    redelivery.start()


_REDELIVERY_DELAY_S = 0.01


def _handle_stops() -> None:
    """SIGTERM and Ctrl-C unwind the command, and end it of the signal once it has unwound."""
    atexit.register(_end_of_signal)  # registered first, so it runs last: after multiprocessing's own cleanup
    sys.unraisablehook = _redeliver_stop
    signal.signal(signal.SIGTERM, _raise_terminated)
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
        signal.signal(signal.SIGINT, _raise_interrupt)


def main() -> None:
    """Console-script entry point (through :func:`starlog.__main__.main`).

    SIGTERM and Ctrl-C unwind the command (partial outputs removed, worker pools stopped); the process then
    ends of that signal, as a shell expects of a stopped command.
    """
    with contextlib.suppress(Exception):  # stderr may be no file (an embedding): nothing to print the crash to
        faulthandler.enable()  # a crash in compiled code (a bug) prints where it happened instead of dying silently
    _handle_stops()
    try:
        cli(prog_name="starlog")
    except _Terminated:
        _exit_of(signal.SIGTERM)
    except Exception as err:
        signum = _stop_behind(err)
        if signum is None:
            raise
        if signum == signal.SIGINT:
            click.echo("Aborted!", err=True)  # what click says of a Ctrl-C it sees itself
        _exit_of(signum)
    except SystemExit:
        if _interrupted:
            _exit_of(signal.SIGINT)
        _flush_stdout()
        raise


def _stop_behind(err: BaseException) -> int | None:
    """The signal a stop wrapped in another exception came from, if one did. Python 3.11 wraps an exception
    raised while a class is created (in ``__set_name__``) in a ``RuntimeError``: a Ctrl-C landing as a module
    defines its classes (numba's, imported on first use) reaches the command as that error."""
    cause: BaseException | None = err
    while cause is not None:
        if isinstance(cause, KeyboardInterrupt):
            return signal.SIGINT
        if isinstance(cause, _Terminated):
            return signal.SIGTERM
        cause = cause.__cause__
    return None


_ending: list[int] = []
_EXIT_GRACE_S = 3.0


def _exit_of(signum: int) -> None:
    """Exit, the command having unwound, then end of ``signum`` (:func:`_end_of_signal`). The usual exit runs
    the exit handlers (multiprocessing's free the semaphores its pools made, which its resource tracker would
    otherwise report as leaked); should they take more than a few seconds, a watchdog ends the process."""
    for stop in (signal.SIGINT, signal.SIGTERM):  # the command is ending already
        signal.signal(stop, signal.SIG_IGN)
    _ending.append(signum)
    threading.Thread(target=_exit_later, args=(signum,), name="starlog-exit-watchdog", daemon=True).start()
    sys.exit(128 + signum)


def _exit_later(signum: int) -> None:
    time.sleep(_EXIT_GRACE_S)
    os._exit(128 + signum)


def _end_of_signal() -> None:
    if _ending:
        die_of(_ending[0])


def _flush_stdout() -> None:
    """Write out what the command printed (to a file on a full disk, say): a failure is one line and status 1."""
    try:
        sys.stdout.flush()
    except OSError as err:
        if err.errno != errno.EPIPE:
            click.echo(f"Error: {FileAccessError.of(err, 'standard output', 'write')}", err=True)
        with contextlib.suppress(OSError, ValueError):  # the interpreter's last flush must not fail again
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        sys.exit(1)
