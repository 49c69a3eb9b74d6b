"""The ``track`` stage: UKF tracks of every star from one centroid channel, one channel per motion model.

Reads ``/stars/centroids/<METHOD>`` and writes ``/track/<METHOD>/<MODEL>`` (``starlog.Tracks``,
one message per frame). The brightest star's track — the paper's centroid sequence — is
marked in every row (``brightest``). Finding it needs the whole log (it is the confirmed track
with the most measurements and the highest mean flux, see
:meth:`starlog.track.StarTracker.brightest_track`), so the stage runs in passes, each streaming
block by block so that memory does not grow with the log's length:

1. **read** — the centroid channel is decoded into numpy blocks (by worker processes, each
   reading whole chunks of the log itself, when ``workers > 1``);
2. **track** — each motion model's tracker runs once over the blocks and spools its rows to a
   temporary file next to the output. One model tracks the blocks as they are decoded; several
   run in parallel worker processes over the blocks spooled once;
3. **write** — the rows are encoded (the brightest track now known) block by block, in
   parallel when ``workers > 1``, and written in frame order, model after model.

The bytes written do not depend on ``workers``.
"""

from __future__ import annotations

import functools
import os
import tempfile
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import Executor, Future
from contextlib import ExitStack, contextmanager, nullcontext
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
import numpy.typing as npt

from starlog.errors import InvalidParameterError
from starlog.io import json_message_type, topics
from starlog.io.reader import LogReader
from starlog.stages._blocks import LogSource, channel_blocks
from starlog.stages._channels import check_messages_read
from starlog.stages._parallel import ordered_map, process_pool
from starlog.stages._progress import progress
from starlog.stages._spool import Spool, opened, read_blocks, write_block
from starlog.stages._track_blocks import (
    CentroidArrays,
    centroid_blocks,
    centroid_range,
    decode_centroid_range,
    encode_track_block,
    encode_track_block_to,
    read_encoded,
)
from starlog.stages._slice import time_sliced
from starlog.stages._stage import StageOutput, extend_log
from starlog.track import (
    MotionModel,
    MotionModelConfig,
    NoTrackError,
    StarTracker,
    TrackerConfig,
)

__all__ = ["TrackSummary", "track_log", "parse_models"]

#: Frames per spooled block: bounds the memory of every pass.
BLOCK_FRAMES = 64


def parse_models(spec: str | Sequence[str]) -> list[MotionModel]:
    """``"all"``, ``"STATIC,CONSTANT_VELOCITY"`` or a list of names → motion models, in the paper's order."""
    names = spec.split(",") if isinstance(spec, str) else list(spec)
    if [n.strip().lower() for n in names] == ["all"]:
        return list(MotionModel)
    models = [MotionModel.parse(n) for n in names if n.strip()]
    if not models:
        raise InvalidParameterError("give at least one motion model (or 'all').")
    return list(dict.fromkeys(models))


@dataclass
class TrackSummary:
    """What :func:`track_log` wrote: per model, the brightest track and the track statistics."""

    method: str
    frames: int = 0
    channel_messages: int = 0
    brightest: dict[str, int] = field(default_factory=dict)
    tracks: dict[str, int] = field(default_factory=dict)
    confirmed: dict[str, int] = field(default_factory=dict)
    gated: dict[str, int] = field(default_factory=dict)
    mean_nis: dict[str, float] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return {
            "method": self.method,
            "frames": self.frames,
            "channel_messages": self.channel_messages,
            "models": {
                model: {
                    "brightest_track": self.brightest[model],
                    "tracks": self.tracks[model],
                    "confirmed_tracks": self.confirmed[model],
                    "gated_measurements": self.gated[model],
                    "mean_nis": self.mean_nis[model],
                }
                for model in self.brightest
            },
        }


# ---------------------------------------------------------------- pass 1: read
def _centroid_arrays(log: LogReader, source: LogSource, topic: str, pool: Executor | None,
                     workers: int) -> Iterator[CentroidArrays]:
    """Pass 1: the centroid channel as blocks of arrays, in order; decoded by the pool's workers when there
    is one and the log's chunks are all indexed (each worker reads whole chunks), and here until they are up."""
    if pool is None or not log.fully_indexed:
        return centroid_blocks(log.messages(topic), BLOCK_FRAMES)
    ranges = ((source, topic, start, end) for start, end, _ in channel_blocks(log, topic, BLOCK_FRAMES))
    return ordered_map(pool, decode_centroid_range, ranges, window=2 * workers,
                       until_ready=lambda _, topic, start, end: centroid_range(log, topic, start, end))


def _spool_blocks(blocks: Iterable[CentroidArrays], spool: Spool) -> None:
    """The decoded blocks written to ``spool``, for the models tracked in worker processes to read."""
    with opened(spool, "wb") as file:
        for block in blocks:
            write_block(file, *block)


# ---------------------------------------------------------------- pass 2: track
@dataclass(frozen=True)
class _ModelRun:
    """One model's tracking: its row spool (and block offsets) and statistics."""

    brightest: int
    frames: int
    spool: Spool
    offsets: list[int]
    tracks: int
    confirmed: int
    gated: int
    mean_nis: float


def _no_track_hint(model: MotionModel, source: str, err: NoTrackError) -> NoTrackError:
    return NoTrackError(
        f"{model.value} on {source}: {err} If the stars move more than their centroid sigma "
        "(platform jitter), the gate rejects them: raise the measurement-noise floor, e.g. "
        "--set sigma_floor=0.05 (px), or use a model with process noise.")


def _track_model(config: TrackerConfig, source: str, blocks: Iterable[CentroidArrays], spool: Spool,
                 on_block: Callable[[StarTracker, int], None] | None = None) -> _ModelRun:
    """Pass 2 for one model: track every frame of ``blocks``, spool the rows, find the brightest track.

    ``on_block(tracker, offset)`` is called when a block of rows is in the spool (flushed).
    """
    tracker = StarTracker(config)
    nis_sum, nis_n, n_frames = 0.0, 0, 0
    offsets = []
    with opened(spool, "wb") as file:
        for frames, times, counts, table in blocks:
            ends = np.cumsum(counts).tolist()
            starts = [0, *ends[:-1]]
            out = []
            for t, a, b in zip(times.tolist(), starts, ends, strict=True):
                rows = tracker.update(t, table[a:b, 0], table[a:b, 1], table[a:b, 2], table[a:b, 3])
                applied = rows["measured"] & (rows["age"] > 0)
                nis_sum += float(rows["nis"][applied].sum())
                nis_n += int(applied.sum())
                out.append(rows)
            n_frames += len(out)
            row_counts = np.array([r.size for r in out], dtype=np.int64)
            offsets.append(write_block(file, frames, times, row_counts, _concatenated(out)))
            if on_block is not None:
                file.flush()
                on_block(tracker, offsets[-1])
    try:
        brightest = tracker.brightest_track()
    except NoTrackError as err:
        raise _no_track_hint(tracker.model, source, err) from err
    stats = tracker.track_stats()
    return _ModelRun(brightest=brightest, frames=n_frames, spool=spool, offsets=offsets, tracks=int(stats.size),
                     confirmed=int(stats["confirmed"].sum()), gated=int(stats["gated"].sum()),
                     mean_nis=nis_sum / nis_n if nis_n else 0.0)


def _concatenated(tables: list[npt.NDArray[np.void]]) -> npt.NDArray[np.void]:
    """The row tables of one block, of one dtype, joined (``np.concatenate`` would promote the record
    dtype of every pair of tables, a cost per frame)."""
    out = np.empty(sum(t.size for t in tables), dtype=tables[0].dtype)
    np.concatenate(tables, out=out)
    return out


def _track_spooled(config: TrackerConfig, source: str, centroids: Spool, spool: Spool) -> _ModelRun:
    """Pass 2 for one model in a worker process: the blocks read from the centroid spool."""
    return _track_model(config, source, read_blocks(centroids, 4), spool)


# ---------------------------------------------------------------- pass 3: write
class _Speculation:
    """Pass 3 done ahead, during pass 2, for one model: each block of rows is encoded by the pool's
    workers as soon as it is spooled, marking the brightest track known so far. A block whose guess
    was the final brightest track is then read back; any other is encoded again. The bytes written
    are the same either way. The guess is refreshed after blocks 0, 1, 2, 4, 8, ... then every 64th
    (finding the brightest track costs more as the lost tracks accumulate)."""

    def __init__(self, pool: Executor, folder: Path, method: str, model: str) -> None:
        self._pool, self._folder, self._method, self._model = pool, folder, method, model
        self._guess: int | None = None
        self.guesses: list[tuple[int | None, Future[None] | None]] = []

    def _path(self, block: int) -> Path:
        return self._folder / f"encoded-{self._model}-{block}"

    @staticmethod
    def guess(tracker: StarTracker) -> int | None:
        """The brightest track so far (None while no track is confirmed)."""
        try:
            return tracker.brightest_track()
        except NoTrackError:
            return None

    def block_spooled(self, spool: Spool, tracker: StarTracker, offset: int) -> None:
        """Submit the encoding of the block of rows at ``offset`` of ``spool``, just written."""
        block = len(self.guesses)
        if block & (block - 1) == 0 or block % 64 == 0:
            self._guess = self.guess(tracker)
        future = None
        if self._guess is not None:
            future = self._pool.submit(encode_track_block_to, self._path(block), spool, offset, self._method,
                                       self._model, self._guess)
        self.guesses.append((self._guess, future))

    def encoded(self, run: _ModelRun) -> Iterator[tuple[list[int], list[bytes]]]:
        """Every block's ``(log_time, message)`` lists for the final brightest track, in order."""
        for block, (guess, future) in enumerate(self.guesses):
            if guess == run.brightest and future is not None and future.exception() is None:
                path = self._path(block)
                yield read_encoded(path)
                path.unlink()
            else:
                yield encode_track_block(run.spool, run.offsets[block], self._method, self._model, run.brightest)


def _frames_out(encoded: Iterator[tuple[list[int], list[bytes]]], n_models: int,
                n_blocks: int) -> Iterator[tuple[int, list[bytes]]]:
    """``(log_time, one message per model)`` of every frame, from per-(block, model) encodings."""
    for _ in range(n_blocks):
        blocks = [next(encoded) for _ in range(n_models)]
        times = blocks[0][0]
        for i, t in enumerate(times):
            yield t, [messages[i] for _, messages in blocks]


def _track_models(configs: dict[MotionModel, TrackerConfig], source: str, blocks: Iterable[CentroidArrays],
                  spools: _Spools, pool: Executor | None,
                  speculation: _Speculation | None) -> dict[MotionModel, _ModelRun]:
    """Pass 2 for every model: one model tracks the blocks as they come (its rows encoded ahead with
    ``speculation``); several are tracked from the blocks spooled once, in worker processes when there is a pool."""
    models = list(configs)
    if len(models) == 1:
        rows = spools.rows[models[0]]
        on_block = functools.partial(speculation.block_spooled, rows) if speculation else None
        return {models[0]: _track_model(configs[models[0]], source, blocks, rows, on_block)}
    _spool_blocks(blocks, spools.centroids)
    args = ([configs[m] for m in models], [source] * len(models), [spools.centroids] * len(models),
            [spools.rows[m] for m in models])
    runs = (pool.map if pool else map)(_track_spooled, *args)
    return dict(zip(models, runs, strict=True))


def _encoded_blocks(runs: dict[MotionModel, _ModelRun], method: str, pool: Executor | None, workers: int,
                    speculation: _Speculation | None) -> Iterator[tuple[list[int], list[bytes]]]:
    """Every (block, model)'s messages, block by block, the models of a block in order."""
    if speculation is not None:
        return speculation.encoded(next(iter(runs.values())))
    n_blocks = len(next(iter(runs.values())).offsets)
    items = [(run.spool, run.offsets[block], method, m.value, run.brightest)
             for block in range(n_blocks) for m, run in runs.items()]
    if pool is None:
        return (encode_track_block(*item) for item in items)
    return ordered_map(pool, encode_track_block, items, window=2 * max(workers, len(runs)))


def _write_tracks(out: StageOutput, runs: dict[MotionModel, _ModelRun], method: str, n_frames: int,
                  encoded: Iterator[tuple[list[int], list[bytes]]], *, show_progress: bool) -> None:
    """Pass 3: write every model's encoded rows frame by frame, the models of one frame in order."""
    n_blocks = len(next(iter(runs.values())).offsets)
    channels = [out.add_channel(topics.track_topic(method, m.value), json_message_type("starlog.Tracks"))
                for m in runs]
    frames = _frames_out(encoded, len(runs), n_blocks)
    for t, messages in progress(frames, total=n_frames, description="track (write)", enabled=show_progress):
        for channel, message in zip(channels, messages, strict=True):
            out.writer.write(channel, log_time=t, data=message)


# ---------------------------------------------------------------- the stage
@dataclass(frozen=True)
class _Spools:
    """Where the centroids and each model's rows are spooled (``folder``: of the shared ones)."""

    centroids: Spool
    rows: dict[MotionModel, Spool]
    folder: Path | None = None


@contextmanager
def _spools(models: list[MotionModel], output_path: Path, *, shared: bool) -> Iterator[_Spools]:
    """Spools next to the output (on disk, not in memory): anonymous files, which a killed run
    cannot leave behind, or, when ``shared`` with worker processes, files in a temporary folder."""
    if not shared:
        with ExitStack() as stack:
            def anonymous() -> BinaryIO:
                return stack.enter_context(tempfile.TemporaryFile(dir=output_path.parent))

            yield _Spools(anonymous(), {m: anonymous() for m in models})
        return
    with tempfile.TemporaryDirectory(prefix=f".{output_path.name}.track-", dir=output_path.parent) as tmp:
        yield _Spools(Path(tmp) / "centroids", {m: Path(tmp) / f"rows-{m.value}" for m in models}, Path(tmp))


def _configs(chosen: list[MotionModel], tracker: dict[str, Any] | None,
             motion: dict[str, Any] | None) -> dict[MotionModel, TrackerConfig]:
    try:
        motion_config = MotionModelConfig(**(motion or {}))
        return {m: TrackerConfig(model=m, motion=motion_config, **(tracker or {})) for m in chosen}
    except TypeError as err:
        raise InvalidParameterError(f"unknown tracker option: {err}.") from err


@time_sliced(lambda log, options: topics.centroid_topic(str(options["method"]).upper()))
def track_log(
    input_path: str | os.PathLike[str],
    output_path: str | os.PathLike[str],
    *,
    method: str,
    models: str | Sequence[str] = "all",
    tracker: dict[str, Any] | None = None,
    motion: dict[str, Any] | None = None,
    force: bool = False,
    compression: str = "zstd",
    workers: int = 1,
    show_progress: bool = False,
) -> TrackSummary:
    """Track every star of ``/stars/centroids/<method>`` under each motion model.

    Parameters
    ----------
    method : str
        Centroid method whose channel is tracked (e.g. ``"GAUSSFIT"``).
    models : str or sequence of str
        ``"all"`` or motion model names.
    tracker : dict, optional
        :class:`~starlog.track.TrackerConfig` fields (gate_probability, association_radius,
        confirm_hits, max_missed, sigma_floor).
    motion : dict, optional
        :class:`~starlog.track.MotionModelConfig` fields (process-noise intensities).
    workers : int
        With more than one: worker processes that decode the centroids and encode the messages
        while this process tracks (one model), or that track the models in parallel (several);
        and threads compressing the output's chunks. The output does not depend on it.
    start, end : str or int, optional
        Only the range ``start <= log_time < end`` (ns, ``"12.5s"`` or ``"frame:N"`` of the centroid
        channel; :mod:`starlog.io.timerange`): the output holds that range of every channel.
    """
    chosen = parse_models(models)
    configs = _configs(chosen, tracker, motion)
    method = method.upper()
    source = topics.centroid_topic(method)
    parameters = {"method": method, "models": [m.value for m in chosen], "tracker": dict(tracker or {}),
                  "motion": dict(motion or {})}
    summary = TrackSummary(method=method)
    # one model: the workers only decode and encode, and start quicker without the tracker's imports
    preload = "starlog.stages.track" if len(chosen) > 1 else "starlog.stages._track_blocks"
    with extend_log(input_path, output_path, stage="track", parameters=parameters, force=force,
                    compression=compression, workers=workers) as (log, out), \
            _spools(chosen, Path(output_path), shared=workers > 1) as spools, \
            (process_pool(workers, preload=[preload]) if workers > 1 else nullcontext()) as pool:
        blocks = progress(_centroid_arrays(log, input_path, source, pool, workers),
                          total=log.channel(source).message_count, description="track (read)",
                          enabled=show_progress, weight=lambda block: block[0].size)
        speculation = (_Speculation(pool, spools.folder, method, chosen[0].value)
                       if pool is not None and spools.folder is not None and len(chosen) == 1 else None)
        runs = _track_models(configs, source, blocks, spools, pool, speculation)
        summary.frames = next(iter(runs.values())).frames
        summary.channel_messages = check_messages_read(log, source, summary.frames)
        encoded = _encoded_blocks(runs, method, pool, workers, speculation)
        _write_tracks(out, runs, method, summary.frames, encoded, show_progress=show_progress)
    for m, run in runs.items():
        summary.brightest[m.value] = run.brightest
        summary.tracks[m.value] = run.tracks
        summary.confirmed[m.value] = run.confirmed
        summary.gated[m.value] = run.gated
        summary.mean_nis[m.value] = run.mean_nis
    return summary
