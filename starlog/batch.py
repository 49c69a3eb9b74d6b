"""Batches of independent work (many logs, an experiment's runs) on Dask, or serially.

``scheduler="tcp://host:8786"`` sends the tasks to a running Dask distributed cluster
(``dask scheduler`` and ``dask worker tcp://host:8786`` on the machines); ``workers=N`` without
a scheduler starts a local Dask cluster of N single-threaded worker processes; neither runs the
tasks one after the other in this process. The results are the same either way: every task is
a pure function of its arguments (paths and plain options), and results are returned in task
order, not completion order.

A task that fails is reported with its error and does not stop the others.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Executor
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

from tqdm import tqdm

from starlog.errors import InvalidParameterError, StarlogError

__all__ = ["BatchOutcome", "BatchTask", "dask_client", "executor_for", "run_batch"]


@dataclass(frozen=True)
class BatchTask:
    """One independent piece of work: ``func(*args, **kwargs)`` named ``name`` (e.g. the log's file name)."""

    name: str
    func: Callable[..., Any]
    args: tuple[Any, ...] = ()
    kwargs: dict[str, Any] | None = None


@dataclass(frozen=True)
class BatchOutcome:
    """What became of one task: its result, or the error that stopped it."""

    name: str
    ok: bool
    result: Any = None
    error: str = ""


def _call(func: Callable[..., Any], args: tuple[Any, ...], kwargs: dict[str, Any]) -> tuple[bool, Any]:
    # The batch boundary: one task's failure, whatever it is, must not stop the others.
    try:
        return True, func(*args, **kwargs)
    except StarlogError as err:
        return False, str(err)
    except Exception as err:  # noqa: BLE001 - reported per task, with its type
        return False, f"{type(err).__name__}: {err}"


@contextmanager
def dask_client(*, scheduler: str | None, workers: int) -> Iterator[Any]:
    """A Dask client on ``scheduler``, or on a local cluster of ``workers`` processes."""
    try:
        import dask
        from distributed import Client, LocalCluster
    except ImportError as err:  # pragma: no cover - distributed is a dependency
        raise InvalidParameterError("Dask distributed is not installed: pip install 'dask[distributed]'.") from err
    if scheduler:
        try:
            client = Client(scheduler, timeout="10s")
        except (OSError, TimeoutError) as err:
            raise InvalidParameterError(f"cannot reach the Dask scheduler at {scheduler}: {err}.") from err
        try:
            yield client
        finally:
            client.close()
        return
    if workers < 1:
        raise InvalidParameterError(f"workers must be >= 1, got {workers}.")
    # No dashboard, and the scheduler's HTTP server (metrics) on a free loopback port, not 8787:
    # two runs on one machine must not collide. A task's failure reaches the caller through its
    # future; what the workers log at ERROR is their shutdown race (a heartbeat to the scheduler
    # that has just closed), printed as a traceback on the user's terminal, so only CRITICAL passes.
    # The workers run without Dask's statistical profiler (a sample of every task's stack every
    # 10 ms): on starlog's pure-Python tasks it costs as much CPU again as the tasks themselves.
    with dask.config.set({"distributed.worker.profile.enabled": False}):
        cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None,
                               scheduler_kwargs={"dashboard": False, "dashboard_address": "127.0.0.1:0"},
                               silence_logs=logging.CRITICAL)
        client = Client(cluster)
        try:
            yield client
        finally:
            client.close()
            cluster.close()


@contextmanager
def executor_for(*, scheduler: str | None, workers: int) -> Iterator[Executor | None]:
    """A ``concurrent.futures.Executor`` on Dask (scheduler or local cluster), or None for serial."""
    if not scheduler and workers <= 1:
        yield None
        return
    with dask_client(scheduler=scheduler, workers=workers) as client:
        yield client.get_executor(pure=False)


def run_batch(
    tasks: Sequence[BatchTask],
    *,
    scheduler: str | None = None,
    workers: int = 1,
    show_progress: bool = False,
    description: str = "batch",
) -> list[BatchOutcome]:
    """Run independent tasks; return one :class:`BatchOutcome` per task, in task order."""
    outcomes: list[BatchOutcome | None] = [None] * len(tasks)
    bar = tqdm(total=len(tasks), desc=description, unit="log", disable=None if show_progress else True, leave=False)
    try:
        if not scheduler and workers <= 1:
            for i, task in enumerate(tasks):
                ok, value = _call(task.func, task.args, task.kwargs or {})
                outcomes[i] = BatchOutcome(task.name, ok, value if ok else None, "" if ok else value)
                bar.update()
        else:
            from distributed import as_completed

            with dask_client(scheduler=scheduler, workers=workers) as client:
                futures = {client.submit(_call, t.func, t.args, t.kwargs or {}, pure=False): i
                           for i, t in enumerate(tasks)}
                for future in as_completed(futures):
                    i = futures[future]
                    ok, value = future.result()
                    outcomes[i] = BatchOutcome(tasks[i].name, ok, value if ok else None, "" if ok else value)
                    bar.update()
    finally:
        bar.close()
    return [o for o in outcomes if o is not None]
