"""Parallel helpers: an ordered map with a bounded window, and a process pool that never outlives its owner.

Worker processes come from a fork server (the caller may have threads, which must not be forked).
Whatever ends the owning process (SIGKILL, SIGTERM, Ctrl-C, an exception), nothing is left behind:

- the fork server and each worker watch the owner's pid (:mod:`starlog._lifeline`) and exit at
  once when the owner is gone; on Linux a worker also dies with its parent, the fork server
  (``prctl(PR_SET_PDEATHSIG, SIGKILL)``, which needs no Python thread to run);
- multiprocessing's resource tracker exits by itself once they are all gone;
- if the owner leaves the pool by an exception (``KeyboardInterrupt`` included), queued tasks are
  cancelled and the workers terminated instead of waited for.

Workers ignore SIGINT: a Ctrl-C at the terminal reaches the whole process group, and the owner
alone decides how to stop.
"""

from __future__ import annotations

import ctypes
import itertools
import multiprocessing
import os
import signal
import sys
import threading
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import Executor, Future, ProcessPoolExecutor
from contextlib import contextmanager
from typing import Any, TypeVar

from starlog import _lifeline as lifeline

T = TypeVar("T")
R = TypeVar("R")

__all__ = ["guarded_process", "ordered_map", "process_pool"]

_PR_SET_PDEATHSIG = 1
# Imported first by the fork server: the lifeline ties it to its owner, and workers then start with
# this module (their initializer) loaded, so they are guarded from their first milliseconds.
_FORK_SERVER_PRELOAD = ["starlog._lifeline", "starlog.stages._parallel"]
_START_TIMEOUT = 5.0  # seconds an owner that is stopping waits for its pool's start-up thread


def ordered_map(executor: Executor, func: Callable[..., R], items: Iterable[tuple[Any, ...]], *,
                window: int, until_ready: Callable[..., R] | None = None) -> Iterator[R]:
    """``func(*item)`` for each item on ``executor``, yielded in input order; memory bounded by ``window``.

    With ``until_ready`` and a pool of :func:`process_pool`, the caller does not sit idle while the
    workers start: until they are up, items are computed here by ``until_ready(*item)``, which must
    give what ``func`` would.
    """
    items = iter(items)
    if until_ready is not None and isinstance(executor, _Pool):
        for item in items:
            if executor.started.is_set():
                items = itertools.chain([item], items)
                break
            yield until_ready(*item)
    pending: deque[Future[R]] = deque()
    for item in items:
        pending.append(executor.submit(func, *item))
        if len(pending) >= window:
            yield pending.popleft().result()
    while pending:
        yield pending.popleft().result()


class _Pool(ProcessPoolExecutor):
    """A process pool whose workers are started on a thread (:meth:`start_workers`): starting them blocks
    the caller until the fork server has imported its modules, a few tenths of a second or more.

    ``started`` is set once a worker has run a first task, or once starting them has failed (the
    pool's next use then raises the error).
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.started = threading.Event()
        self._starter = threading.Thread(target=self._start, name="starlog-pool-start", daemon=True)

    def start_workers(self) -> None:
        self._starter.start()

    def _start(self) -> None:
        try:
            self.submit(int).result()  # returns once a worker has run it
        except BaseException:  # noqa: S110 - a broken pool raises again on the owner's next use
            pass
        finally:
            self.started.set()

    def wait_started(self, timeout: float | None = None) -> None:
        """Wait for :meth:`start_workers` to be done (at most ``timeout`` seconds)."""
        if self._starter.is_alive():
            self._starter.join(timeout)


@contextmanager
def process_pool(workers: int, *, preload: Sequence[str] = ()) -> Iterator[_Pool]:
    """A ``ProcessPoolExecutor`` of ``workers`` processes that all end when the calling process ends.

    ``preload`` names modules the fork server imports once, so each worker starts with them loaded
    (it applies when the fork server starts, i.e. at the first pool of the process). The workers
    are started on a thread: the pool is returned at once (see ``until_ready`` of :func:`ordered_map`).
    """
    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload([*_FORK_SERVER_PRELOAD, *preload])
    pool = _Pool(max_workers=workers, mp_context=context, initializer=_guard_worker, initargs=(os.getpid(),))
    try:
        pool.start_workers()
        yield pool
    except BaseException:
        _stop_now(pool)
        pool.wait_started(timeout=_START_TIMEOUT)  # the stopped pool fails the starter's task
        _stop_now(pool)  # any worker started meanwhile
        raise
    pool.wait_started()
    pool.shutdown(wait=True)


def guarded_process(target: Callable[..., object], args: tuple[Any, ...], *,
                    preload: Sequence[str] = ()) -> multiprocessing.process.BaseProcess:
    """A started process of the fork server running ``target(*args)``, guarded as the pools' workers are (it ends
    when the calling process ends, however that ends)."""
    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload([*_FORK_SERVER_PRELOAD, *preload])
    process = context.Process(target=_run_guarded, args=(os.getpid(), target, args), daemon=True)
    process.start()
    return process


def _run_guarded(owner_pid: int, target: Callable[..., object], args: tuple[Any, ...]) -> None:
    _guard_worker(owner_pid)
    target(*args)


def _stop_now(pool: ProcessPoolExecutor) -> None:
    """Cancel queued tasks and terminate the workers (the owner is stopping; their results are not wanted)."""
    workers = list((getattr(pool, "_processes", None) or {}).values())  # private, but there is no public way
    pool.shutdown(wait=False, cancel_futures=True)
    for process in workers:
        if process.is_alive():
            process.terminate()
    for process in workers:
        process.join(timeout=2.0)


def _guard_worker(owner_pid: int) -> None:
    """Worker initializer: ignore Ctrl-C, die with the fork server (Linux) and with the owner process."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if sys.platform.startswith("linux"):
        try:
            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
        except (OSError, AttributeError):  # no usable libc: the lifeline below still applies
            pass
    lifeline.watch(owner_pid)
