"""The ``track`` stage: UKF tracks of every star from one centroid channel, one channel per motion model.

Reads ``/stars/centroids/<METHOD>`` and writes ``/track/<METHOD>/<MODEL>`` (``starlog.Tracks``,
one message per frame). The brightest star's track — the paper's centroid sequence — is
marked in every row (``brightest``). Finding it needs the whole log (it is the confirmed track
with the most measurements and the highest mean flux, see
:meth:`starlog.track.StarTracker.brightest_track`), so the stage runs in three passes, each
streaming block by block so that memory does not grow with the log's length:

1. **read** — the centroid channel is decoded once into numpy blocks, spooled to a temporary
   file next to the output;
2. **track** — each motion model's tracker runs once over the spooled centroids and spools its
   rows (models run in parallel worker processes when ``workers > 1``);
3. **write** — the rows are encoded (the brightest track now known) block by block, in
   parallel when ``workers > 1``, and written in frame order, model after model.

The bytes written do not depend on ``workers``.
"""

from __future__ import annotations

import itertools
import operator
import os
import tempfile
from collections.abc import Iterator, Sequence
from concurrent.futures import Executor
from contextlib import ExitStack, contextmanager, nullcontext
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
import numpy.typing as npt

from starlog.errors import InvalidParameterError
from starlog.io import json_message_type, topics
from starlog.io.reader import LogReader
from starlog.io.records import record_encoder
from starlog.stages._channels import check_messages_read
from starlog.stages._parallel import ordered_map, process_pool
from starlog.stages._progress import progress
from starlog.stages._spool import Spool, opened, read_block, read_blocks, write_block
from starlog.stages.window import windowed
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
_STAR_FIELDS = operator.itemgetter("x", "y", "sigma", "flux")


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
class _CentroidBlock:
    """Centroid messages gathered into arrays, each message's star dicts dropped once converted."""

    def __init__(self) -> None:
        self.frames: list[int] = []
        self.times: list[int] = []
        self.counts: list[int] = []
        self.values: list[tuple[float, float, float, float]] = []

    def add(self, log_time: int, payload: dict[str, Any]) -> None:
        stars = payload["stars"]
        self.frames.append(payload["frame"])
        self.times.append(log_time)
        self.counts.append(len(stars))
        self.values.extend(map(_STAR_FIELDS, stars))

    def write(self, file: BinaryIO) -> None:
        """Spool ``(frame, log_time, stars per frame, (k, 4) x/y/sigma/flux)``."""
        table = np.fromiter(itertools.chain.from_iterable(self.values), dtype=np.float64,
                            count=4 * len(self.values)).reshape(len(self.values), 4)
        write_block(file, np.array(self.frames, dtype=np.int64), np.array(self.times, dtype=np.int64),
                    np.array(self.counts, dtype=np.int64), table)


def _spool_centroids(log: LogReader, topic: str, spool: Spool, *, show_progress: bool) -> int:
    """Pass 1: the centroid channel → blocks of arrays in ``spool``; the number of frames."""
    n_frames = 0
    messages = progress(log.messages(topic), total=log.channel(topic).message_count,
                        description="track (read)", enabled=show_progress)
    block = _CentroidBlock()
    with opened(spool, "wb") as file:
        for message in messages:
            block.add(message.log_time, message.payload)
            n_frames += 1
            if len(block.frames) == BLOCK_FRAMES:
                block.write(file)
                block = _CentroidBlock()
        if block.frames:
            block.write(file)
    return n_frames


# ---------------------------------------------------------------- pass 2: track
@dataclass(frozen=True)
class _ModelRun:
    """One model's tracking: its row spool (and block offsets) and statistics."""

    brightest: int
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


def _track_model(config: TrackerConfig, source: str, centroids: Spool, spool: Spool) -> _ModelRun:
    """Pass 2 for one model: track every spooled frame, spool the rows, find the brightest track."""
    tracker = StarTracker(config)
    nis_sum, nis_n = 0.0, 0
    offsets = []
    with opened(spool, "wb") as file:
        for frames, times, counts, table in read_blocks(centroids, 4):
            ends = np.cumsum(counts).tolist()
            starts = [0, *ends[:-1]]
            out = []
            for t, a, b in zip(times.tolist(), starts, ends, strict=True):
                rows = tracker.update(t, table[a:b, 0], table[a:b, 1], table[a:b, 2], table[a:b, 3])
                applied = rows["measured"] & (rows["age"] > 0)
                nis_sum += float(rows["nis"][applied].sum())
                nis_n += int(applied.sum())
                out.append(rows)
            row_counts = np.array([r.size for r in out], dtype=np.int64)
            offsets.append(write_block(file, frames, times, row_counts, _concatenated(out)))
    try:
        brightest = tracker.brightest_track()
    except NoTrackError as err:
        raise _no_track_hint(tracker.model, source, err) from err
    stats = tracker.track_stats()
    return _ModelRun(brightest=brightest, spool=spool, offsets=offsets, tracks=int(stats.size),
                     confirmed=int(stats["confirmed"].sum()), gated=int(stats["gated"].sum()),
                     mean_nis=nis_sum / nis_n if nis_n else 0.0)


def _concatenated(tables: list[npt.NDArray[np.void]]) -> npt.NDArray[np.void]:
    """The row tables of one block, all of one record dtype, joined (without ``out``, ``np.concatenate``
    promotes the record dtypes of every pair of tables: a cost per frame)."""
    out = np.empty(sum(t.size for t in tables), dtype=tables[0].dtype)
    np.concatenate(tables, out=out)
    return out


# ---------------------------------------------------------------- pass 3: write
def _encode_block(spool: Spool, offset: int, method: str, model: str,
                  brightest: int) -> tuple[list[int], list[bytes]]:
    """One spooled block of rows → ``(log_time, starlog.Tracks message)`` of each frame.

    The block's rows are encoded, and checked against their schema, column by column
    (:class:`~starlog.io.records.RecordEncoder`; in a worker process when there is a pool), not by the writer.
    """
    frames, times, counts, rows = read_block(spool, offset, 4)
    encoder = record_encoder("starlog.Tracks", "tracks")
    records = encoder.rows(rows, {"brightest": rows["track"] == brightest})
    ends = np.cumsum(counts).tolist()
    messages: list[bytes] = [
        encoder.message({"frame": frame, "method": method, "model": model}, records[a:b])
        for frame, a, b in zip(frames.tolist(), [0, *ends[:-1]], ends, strict=True)
    ]
    return times.tolist(), messages


def _frames_out(encoded: Iterator[tuple[list[int], list[bytes]]], n_models: int,
                n_blocks: int) -> Iterator[tuple[int, list[bytes]]]:
    """``(log_time, one message per model)`` of every frame, from per-(block, model) encodings."""
    for _ in range(n_blocks):
        blocks = [next(encoded) for _ in range(n_models)]
        times = blocks[0][0]
        for i, t in enumerate(times):
            yield t, [messages[i] for _, messages in blocks]


def _track_models(configs: dict[MotionModel, TrackerConfig], source: str, spools: _Spools,
                  pool: Executor | None) -> dict[MotionModel, _ModelRun]:
    """Pass 2 for every model, in worker processes when there is a pool."""
    models = list(configs)
    args = ([configs[m] for m in models], [source] * len(models), [spools.centroids] * len(models),
            [spools.rows[m] for m in models])
    runs = (pool.map if pool else map)(_track_model, *args)
    return dict(zip(models, runs, strict=True))


def _write_tracks(out: StageOutput, runs: dict[MotionModel, _ModelRun], method: str, n_frames: int,
                  pool: Executor | None, *, show_progress: bool) -> None:
    """Pass 3: encode every model's rows (blocks in worker processes when there is a pool) and
    write them frame by frame, the models of one frame in order."""
    n_blocks = -(-n_frames // BLOCK_FRAMES)
    items = [(run.spool, run.offsets[block], method, m.value, run.brightest)
             for block in range(n_blocks) for m, run in runs.items()]
    encoded = (ordered_map(pool, _encode_block, items, window=2 * len(runs)) if pool
               else (_encode_block(*item) for item in items))
    channels = [out.add_channel(topics.track_topic(method, m.value), json_message_type("starlog.Tracks"))
                for m in runs]
    frames = _frames_out(encoded, len(runs), n_blocks)
    for t, messages in progress(frames, total=n_frames, description="track (write)", enabled=show_progress):
        for channel, message in zip(channels, messages, strict=True):
            out.writer.write(channel, log_time=t, data=message)


# ---------------------------------------------------------------- the stage
@dataclass(frozen=True)
class _Spools:
    """Where the centroids and each model's rows are spooled."""

    centroids: Spool
    rows: dict[MotionModel, Spool]


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
        yield _Spools(Path(tmp) / "centroids", {m: Path(tmp) / f"rows-{m.value}" for m in models})


def _configs(chosen: list[MotionModel], tracker: dict[str, Any] | None,
             motion: dict[str, Any] | None) -> dict[MotionModel, TrackerConfig]:
    try:
        motion_config = MotionModelConfig(**(motion or {}))
        return {m: TrackerConfig(model=m, motion=motion_config, **(tracker or {})) for m in chosen}
    except TypeError as err:
        raise InvalidParameterError(f"unknown tracker option: {err}.") from err


@windowed(lambda log, options: topics.centroid_topic(str(options["method"]).upper()))
def track_log(
    input_path: str | os.PathLike[str],
    output_path: str | os.PathLike[str],
    *,
    method: str,
    models: str | Sequence[str] = "all",
    tracker: dict[str, Any] | None = None,
    motion: dict[str, Any] | None = None,
    force: bool = False,
    flatten: bool = False,
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
        Processes tracking the models (at most one per model; with several, they also encode
        the messages) and threads compressing the output's chunks. The output does not depend on it.
    start, end : str or int, optional
        Only the range ``start <= log_time < end`` (ns, ``"12.5s"`` or ``"frame:N"`` of the centroid
        channel; :mod:`starlog.io.timerange`): the layer holds its channels for that range.
    flatten : bool
        Write the whole chain as one self-contained file instead of a layer on the input.
    """
    chosen = parse_models(models)
    configs = _configs(chosen, tracker, motion)
    method = method.upper()
    source = topics.centroid_topic(method)
    parameters = {"method": method, "models": [m.value for m in chosen], "tracker": dict(tracker or {}),
                  "motion": dict(motion or {})}
    summary = TrackSummary(method=method)
    processes = min(workers, len(chosen))
    with extend_log(input_path, output_path, stage="track", parameters=parameters, force=force, flatten=flatten,
                    compression=compression, workers=workers) as (log, out), \
            _spools(chosen, Path(output_path), shared=processes > 1) as spools, \
            (process_pool(processes, preload=["starlog.stages.track"]) if processes > 1 else nullcontext()) as pool:
        summary.frames = _spool_centroids(log, source, spools.centroids, show_progress=show_progress)
        summary.channel_messages = check_messages_read(log, source, summary.frames)
        runs = _track_models(configs, source, spools, pool)
        _write_tracks(out, runs, method, summary.frames, pool, show_progress=show_progress)
    for m, run in runs.items():
        summary.brightest[m.value] = run.brightest
        summary.tracks[m.value] = run.tracks
        summary.confirmed[m.value] = run.confirmed
        summary.gated[m.value] = run.gated
        summary.mean_nis[m.value] = run.mean_nis
    return summary
