"""Ordered parallel map with a bounded window: results in input order, at most ``window`` in flight."""

from __future__ import annotations

import multiprocessing
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import Executor, Future, ProcessPoolExecutor
from typing import Any, TypeVar

T = TypeVar("T")
R = TypeVar("R")

__all__ = ["ordered_map", "process_pool"]


def ordered_map(executor: Executor, func: Callable[..., R], items: Iterable[tuple[Any, ...]], *,
                window: int) -> Iterator[R]:
    """``func(*item)`` for each item on ``executor``, yielded in input order; memory bounded by ``window``."""
    pending: deque[Future[R]] = deque()
    for item in items:
        pending.append(executor.submit(func, *item))
        if len(pending) >= window:
            yield pending.popleft().result()
    while pending:
        yield pending.popleft().result()


def process_pool(workers: int, *, preload: Sequence[str] = ()) -> ProcessPoolExecutor:
    """Worker processes started by a fork server (the caller may have threads, which must not be forked).

    ``preload`` names modules the fork server imports once, so each worker starts with them loaded
    (it applies when the fork server starts, i.e. at the first pool of the process).
    """
    context = multiprocessing.get_context("forkserver")
    if preload:
        context.set_forkserver_preload(list(preload))
    return ProcessPoolExecutor(max_workers=workers, mp_context=context)
