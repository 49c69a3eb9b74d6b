"""Work shared with worker processes: a channel cut into blocks of whole chunks, the pool that
starts its workers on a thread (the caller computing meanwhile), and a stacked log sent to a worker."""

from __future__ import annotations

import contextlib
import multiprocessing.util
import operator
import pickle
from pathlib import Path
from multiprocessing.synchronize import SemLock
from types import SimpleNamespace

import pytest

from starlog.io import LogReader, LogView
from starlog import topics
from starlog.io.timerange import TimeRange
from starlog.stages import simulate_log
# private module _blocks: how the stages split a channel among workers; its edge cases need stand-in logs
from starlog.replay.blocks import channel_blocks
# _Pool is private to the pool module: only a pool never started (process_pool starts it) runs every item here
from starlog.replay.pool import _Pool, ordered_map, process_pool
from starlog.stages.centroid import centroid_log
from tests.foreign_logs import write_plain
from tests.helpers import small_config


def _log_of_chunks(*chunks: tuple[int, int, int]) -> LogReader:
    """A stand-in for a log whose channel has these ``(start, end, messages)`` chunks."""
    return SimpleNamespace(chunk_message_counts=lambda topic: sorted(chunks))  # type: ignore[return-value]


def test_blocks_are_whole_chunks_of_about_the_frames_asked_for() -> None:
    log = _log_of_chunks((0, 9, 10), (10, 19, 10), (20, 29, 10), (30, 34, 5))
    assert channel_blocks(log, "/t", 20) == [(0, 20, 0), (20, 35, 20)]
    assert channel_blocks(log, "/t", 1) == [(0, 10, 0), (10, 20, 10), (20, 30, 20), (30, 35, 30)]
    assert channel_blocks(_log_of_chunks(), "/t", 20) == []


@pytest.mark.parametrize("chunks", [((0, 1000, 50), (10, 20, 5)), ((0, 10, 5), (10, 20, 5))])
def test_chunks_that_overlap_or_touch_in_time_cannot_be_split(chunks: tuple[tuple[int, int, int], ...]) -> None:
    """Overlapping (a log not written in time order), or sharing a time: no split into time ranges
    would number the messages of each block right."""
    assert channel_blocks(_log_of_chunks(*chunks), "/t", 1) is None


def test_centroid_workers_read_a_log_written_out_of_time_order_in_full(tmp_path: Path) -> None:
    simulate_log(small_config(width=32, height=32, n_stars=2, n_frames=80, margin=8.0), tmp_path / "sim.mcap")
    shuffled = write_plain(tmp_path / "sim.mcap", tmp_path / "shuffled.mcap", shuffle=True, chunk_size=4096)
    with LogReader(shuffled) as log:
        assert log.fully_indexed and channel_blocks(log, topics.IMAGE, 32) is None
    for workers in (1, 2):
        summary = centroid_log(shuffled, tmp_path / f"w{workers}.mcap", methods="MOMENT", workers=workers)
        assert summary.channel_messages == 80
    assert (tmp_path / "w1.mcap").read_bytes() == (tmp_path / "w2.mcap").read_bytes()


def test_ordered_map_computes_here_until_the_workers_are_up() -> None:
    items = [(2, k) for k in range(7)]
    not_started = _Pool(max_workers=1)  # its workers are never started: every item is computed here
    here: list[tuple[int, ...]] = []

    def locally(*item: int) -> int:
        here.append(item)
        return operator.pow(*item)

    assert list(ordered_map(not_started, operator.pow, items, window=2, until_ready=locally)) == [2**k for k in range(7)]
    assert here == items
    not_started.shutdown()
    with process_pool(1) as pool:
        results = list(ordered_map(pool, operator.pow, items, window=2, until_ready=operator.pow))
    assert results == [2**k for k in range(7)]
    assert pool.started.is_set()  # the pool waited for its workers' start before shutting down


def test_an_error_while_the_workers_start_stops_them() -> None:
    with pytest.raises(KeyboardInterrupt), process_pool(2) as pool:
        raise KeyboardInterrupt
    # private _processes (concurrent.futures'): no public way lists a pool's processes, as _parallel says too
    processes = list((pool._processes or {}).values())
    assert all(not p.is_alive() for p in processes)


def _semaphores_to_free() -> set[str]:
    """Named semaphores multiprocessing still has to unlink and tell its resource tracker of (its finalizers)."""
    # private _finalizer_registry (multiprocessing's): no public way lists what the process still has to free
    return {f._args[0] for f in multiprocessing.util._finalizer_registry.values()
            if getattr(f, "_callback", None) is SemLock._cleanup}


@pytest.mark.parametrize("stopped", [False, True])
def test_a_pool_frees_its_semaphores_as_it_ends_not_whenever_they_are_collected(stopped: bool) -> None:
    """Freed by the thread that ends the pool, with signals held, even while something still holds its queues (here
    the test; in a command, a thread or a reference cycle): left to the garbage collector, a semaphore can be freed
    in another thread while Ctrl-C ends the process, and the resource tracker then warns of a leak."""
    before = _semaphores_to_free()
    with contextlib.suppress(KeyboardInterrupt), process_pool(2) as pool:
        made = _semaphores_to_free() - before
        # private queues (concurrent.futures'): held here as a lingering reference would hold them
        held = (pool._call_queue, pool._result_queue)
        assert pool.submit(int).result() == 0
        if stopped:
            raise KeyboardInterrupt
    assert len(made) >= 3 and not made & _semaphores_to_free()
    del held


def test_a_log_view_pickles_for_a_worker_to_read_the_same_window(tmp_path: Path) -> None:
    simulate_log(small_config(width=32, height=32, n_stars=2, n_frames=5, fps=100.0), tmp_path / "sim.mcap")
    view = LogView(tmp_path / "sim.mcap", TimeRange.parse("frame:1", "frame:4").resolve(
        lambda n: n * 10_000_000, frame_topic="/camera/image"))
    copy = pickle.loads(pickle.dumps(view))
    assert copy == view
    with LogReader(view) as a, LogReader(copy) as b:
        assert [t for _, t, _ in a.frames()] == [t for _, t, _ in b.frames()] == [10_000_000, 20_000_000, 30_000_000]
        assert a.channel("/camera/image").message_count == 3


