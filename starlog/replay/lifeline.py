"""Processes that end when their owner ends: a watchdog on the owner's pid; and :func:`die_of`, how a
command stopped by a signal ends once it has cleaned up.

:func:`watch` starts a daemon thread that ends the calling process the moment the owner process
has exited (a pidfd on Linux, which becomes readable at exit even before the owner is reaped;
polling every 0.2 s elsewhere). The worker pools of :mod:`starlog.replay.pool` use it.

Imported by multiprocessing's fork server (as its first preload module), this module also ties the
fork server to the process that started it: nothing else would stop a fork server whose owner was
killed while it still had workers or was importing its other preload modules. It also makes the fork
server ignore SIGINT from then on (its workers inherit that from their first instruction; the server
starts with SIGINT blocked, see :func:`starlog.replay.pool.process_pool`): a Ctrl-C at the terminal
reaches the whole process group, and the owner alone decides how to stop.
"""

from __future__ import annotations

import os
import select
import sys
import threading
import time

__all__ = ["die_of", "watch"]

_POLL_SECONDS = 0.2


def watch(owner_pid: int) -> None:
    """End this process (``os._exit``, no cleanup) as soon as ``owner_pid`` has exited."""
    threading.Thread(target=_exit_when_gone, args=(owner_pid,), name="starlog-lifeline", daemon=True).start()


def die_of(signum: int) -> None:
    """End this process of the signal ``signum``, its exit status saying so, without running exit handlers
    (a command that unwound after SIGTERM or Ctrl-C: its outputs are cleaned up, its workers stopped)."""
    import signal

    try:
        sys.stdout.flush()
    except (OSError, ValueError):  # stdout is gone or closed: nothing more to print
        pass
    signal.signal(signum, signal.SIG_DFL)
    os.kill(os.getpid(), signum)
    os._exit(128 + signum)  # not reached unless this thread blocks the signal


def _exit_when_gone(owner_pid: int) -> None:
    try:
        pidfd = os.pidfd_open(owner_pid)  # type: ignore[attr-defined,unused-ignore]  # Linux >= 5.3
    except (AttributeError, OSError):  # not Linux, or the owner is gone already
        pidfd = None
    if pidfd is not None:
        select.select([pidfd], [], [])
    else:
        while _is_alive(owner_pid):
            time.sleep(_POLL_SECONDS)
    os._exit(1)


def _is_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except (ProcessLookupError, PermissionError):  # gone (a PermissionError: the pid now names another's process)
        return False
    return True


def _imported_by_fork_server() -> bool:
    forkserver = sys.modules.get("multiprocessing.forkserver")
    if forkserver is None:
        return False
    frame = sys._getframe()
    while frame is not None:
        if frame.f_code is forkserver.main.__code__:
            return True
        frame = frame.f_back  # type: ignore[assignment]
    return False


#: Set by the owner when it starts its fork server (:func:`starlog.replay.pool.process_pool`): its pid.
#: The fork server's parent pid would name init instead if the owner were killed before this module loads.
OWNER_VARIABLE = "STARLOG_FORK_SERVER_OWNER"

if _imported_by_fork_server():
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # a Ctrl-C reaches the whole process group: the owner decides
    _owner = int(os.environ.get(OWNER_VARIABLE) or os.getppid())
    if sys.platform.startswith("linux"):  # the kernel ends it with its owner: no thread (no GIL) needed
        try:
            import ctypes

            ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL, 0, 0, 0)  # PR_SET_PDEATHSIG
        except (OSError, AttributeError):
            pass
        if os.getppid() != _owner:  # the owner died before that
            os._exit(1)
    watch(_owner)
