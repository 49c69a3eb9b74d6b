"""Parallel helpers: an ordered map with a bounded window, and a process pool that never outlives its owner.

Worker processes come from a fork server (the caller may have threads, which must not be forked).
Whatever ends the owning process (SIGKILL, SIGTERM, Ctrl-C, an exception), nothing is left behind:

- the fork server and each worker watch the owner's pid (:mod:`starlog.replay.lifeline`) and exit at
  once when the owner is gone; on Linux a worker also dies with its parent, the fork server
  (``prctl(PR_SET_PDEATHSIG, SIGKILL)``, which needs no Python thread to run);
- multiprocessing's resource tracker exits by itself once they are all gone;
- if the owner leaves the pool by an exception (``KeyboardInterrupt`` included), queued tasks are
  cancelled and the workers terminated instead of waited for, within a bounded time whatever they
  were doing (see :func:`_stop_now`: a worker ended while it sent a result must not leave the pool's
  manager thread, which the owner's exit waits for, blocked on the rest of it).

:func:`guarded_process` starts one such worker running a function of the caller's, with the same guards.

Workers ignore SIGINT: a Ctrl-C at the terminal reaches the whole process group, and the owner
alone decides how to stop. In the owner, SIGINT and SIGTERM are held back while multiprocessing makes
the pool's queues and their named semaphores, and while it stops the pool and frees them (:func:`signals_held`): an
exception raised inside those steps would leave a semaphore registered for ever (the resource tracker
then warns of it) or a worker unstopped. Stopping waits at most for a worker being started (the fork
server's first start imports its modules) and a few seconds more.
"""

from __future__ import annotations

import ctypes
import itertools
import multiprocessing
import multiprocessing.util
import os
import signal
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import Executor, Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from contextlib import contextmanager
from multiprocessing.synchronize import SemLock
from typing import Any, TypeVar

from starlog.errors import WorkerProcessError
from starlog.replay import lifeline

T = TypeVar("T")
R = TypeVar("R")

__all__ = ["guarded_process", "ordered_map", "process_pool", "signals_held"]

_PR_SET_PDEATHSIG = 1
# Imported first by the fork server: the lifeline ties it to its owner, and workers then start with
# this module (their initializer) loaded, so they are guarded from their first milliseconds.
_FORK_SERVER_PRELOAD = ["starlog.replay.lifeline", "starlog.replay.pool"]
_START_TIMEOUT = 5.0  # seconds an owner that is stopping waits for its pool's start-up thread
_STOP_TIMEOUT = 2.0  # seconds for terminated workers to exit before they are killed


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
    _end_if_importing_a_script()
    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload([*_FORK_SERVER_PRELOAD, *preload])
    with signals_held():  # the pool's queues and their semaphores, made whole or not at all
        _start_fork_server()
        pool = _Pool(max_workers=workers, mp_context=context, initializer=_guard_worker, initargs=(os.getpid(),))
        semaphores = _named_semaphores(pool)
        pool.start_workers()
    try:
        yield pool
    except BaseException as err:
        with signals_held():
            _stop_now(pool)
            pool.wait_started(timeout=_START_TIMEOUT)  # the stopped pool fails the starter's task
            _free_now(semaphores)
        if isinstance(err, BrokenProcessPool):
            raise WorkerProcessError() from err
        raise
    with signals_held():
        pool.wait_started()
        pool.shutdown(wait=True)
        _free_now(semaphores)


@contextmanager
def signals_held() -> Iterator[None]:
    """SIGINT and SIGTERM held back while the block runs, then handled: the block is a step of multiprocessing's
    own (making queues and their named semaphores, starting or stopping workers), which an exception raised
    in its middle would leave half done (a semaphore never freed, a worker never stopped). In the main thread
    only, where Python runs signal handlers; elsewhere the block runs as it is."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held: list[tuple[int, Any]] = []
    handlers = {}
    for signum in (signal.SIGINT, signal.SIGTERM):
        if callable(signal.getsignal(signum)):
            handlers[signum] = signal.signal(signum, lambda number, frame: held.append((number, frame)))
    try:
        yield
    finally:
        for signum, handler in handlers.items():
            signal.signal(signum, handler)
        for signum, frame in held[:1]:
            handlers[signum](signum, frame)


def _start_fork_server() -> None:
    """Start the fork server (if it is not running) with SIGINT blocked, as multiprocessing starts its resource
    tracker: a Ctrl-C to the process group while the server's interpreter starts, before it ignores SIGINT
    (:mod:`starlog.replay.lifeline`), would end it with a traceback. Its workers inherit the blocked signal too."""
    from multiprocessing import forkserver, resource_tracker

    if not hasattr(signal, "pthread_sigmask"):
        forkserver.ensure_running()
        return
    resource_tracker.ensure_running()  # first: starting it unblocks SIGINT in this thread
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    previous = os.environ.get(lifeline.OWNER_VARIABLE)
    os.environ[lifeline.OWNER_VARIABLE] = str(os.getpid())  # whom the server watches, even if killed meanwhile
    try:
        forkserver.ensure_running()
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)
        if previous is None:
            del os.environ[lifeline.OWNER_VARIABLE]
        else:
            os.environ[lifeline.OWNER_VARIABLE] = previous


def _end_if_importing_a_script() -> None:
    """A worker being started imports the script that started it again (a script without an ``if __name__ ==
    "__main__":`` guard then calls starlog once more, from the worker): it ends there, and its owner says why
    (:class:`~starlog.errors.WorkerProcessError`)."""
    if getattr(multiprocessing.process.current_process(), "_inheriting", False):
        os._exit(1)


def guarded_process(target: Callable[..., object], args: tuple[Any, ...], *,
                    preload: Sequence[str] = ()) -> multiprocessing.process.BaseProcess:
    """A started process of the fork server running ``target(*args)``, guarded as the pools' workers are (it ends
    when the calling process ends, however that ends; the fork server is started and the process made with
    SIGINT and SIGTERM held back, as a pool's workers are)."""
    _end_if_importing_a_script()
    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload([*_FORK_SERVER_PRELOAD, *preload])
    process = context.Process(target=_run_guarded, args=(os.getpid(), target, args), daemon=True)
    with signals_held():
        _start_fork_server()
        process.start()
    return process


def _run_guarded(owner_pid: int, target: Callable[..., object], args: tuple[Any, ...]) -> None:
    _guard_worker(owner_pid)
    target(*args)


def _named_semaphores(pool: ProcessPoolExecutor) -> set[str]:
    """The names of the named semaphores behind the pool's queues (their locks and bounded semaphore)."""
    queues = (getattr(pool, "_call_queue", None), getattr(pool, "_result_queue", None))
    locks = [value for queue in queues if queue is not None for value in vars(queue).values()]
    return {lock._semlock.name for lock in locks if isinstance(lock, SemLock) and lock._semlock.name}


def _free_now(names: set[str]) -> None:
    """Free the pool's named semaphores now, in this thread and with signals held, rather than whenever the
    garbage collector reaches them, in whichever thread. multiprocessing frees one in two steps (unlink it, then
    tell its resource tracker); a process that ends between the two, as it does of Ctrl-C while another thread
    is in them, leaves the tracker warning of a leak. Each is freed once: its finalizer then leaves the registry."""
    for finalizer in list(multiprocessing.util._finalizer_registry.values()):
        args = getattr(finalizer, "_args", None) or ()
        if getattr(finalizer, "_callback", None) is SemLock._cleanup and args and args[0] in names:
            finalizer()


def _stop_now(pool: ProcessPoolExecutor) -> None:
    """Cancel queued tasks, end the workers and free the pool's manager thread (the owner is stopping; the
    results are not wanted). Bounded in time whatever the workers were doing.

    A worker ended while it was sending a result leaves the manager thread reading the rest of it; the owner's
    exit waits for that thread, and the rest never comes while this process holds its own copy of the result
    pipe's write end. Closing that copy once every worker is gone ends the read (end of file): the manager
    thread then marks the pool broken and exits. The pool's internals are private, but there is no public way.
    """
    processes = getattr(pool, "_processes", None) or {}  # the dict the manager thread shares: workers added late
    call_queue, results = getattr(pool, "_call_queue", None), getattr(pool, "_result_queue", None)
    pool.shutdown(wait=False, cancel_futures=True)  # waits for a worker being started: none is started after
    workers = {*processes.values(), *_unlisted_workers(call_queue)}
    for process in workers:
        if process.is_alive():
            process.terminate()
    deadline = time.monotonic() + _STOP_TIMEOUT
    for process in workers:
        process.join(timeout=max(0.0, deadline - time.monotonic()))
        if process.is_alive():
            process.kill()
            process.join(timeout=_STOP_TIMEOUT)
    writer = getattr(results, "_writer", None)
    if writer is not None:
        writer.close()


def _unlisted_workers(call_queue: Any) -> list[multiprocessing.process.BaseProcess]:
    """Workers of this pool that are not in its list: a Ctrl-C between a worker's start and its listing
    (``ProcessPoolExecutor._spawn_process``) leaves one, which the owner's exit would wait for forever."""
    if call_queue is None:
        return []
    return [p for p in multiprocessing.active_children()
            if getattr(p, "_args", None) and p._args[0] is call_queue]  # type: ignore[attr-defined]


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
