"""The ``track`` stage: UKF tracks of every star from one centroid channel, one channel per motion model.

Reads ``/stars/centroids/<METHOD>`` and writes ``/track/<METHOD>/<MODEL>`` (``starlog.Tracks``,
one message per frame). The brightest star's track — the paper's centroid sequence — is
marked in every row (``brightest``). Finding it needs the whole log (it is the confirmed track
with the most measurements and the highest mean flux, see
:meth:`starlog.tracking.StarTracker.brightest_track`), so the stage runs in three passes, each
streaming block by block so that memory does not grow with the log's length:

1. **read** — the centroid channel is decoded once into numpy blocks, spooled to a temporary
   file next to the output;
2. **track** — each motion model's tracker runs once over the spooled centroids and spools its
   rows (models run in parallel worker processes when ``workers > 1``);
3. **write** — the rows are encoded (the brightest track now known) block by block, in
   parallel when ``workers > 1``, and written in frame order, model after model.

One model on several workers goes another way, with the tracker alone on this process's critical
path: worker processes decode the centroid blocks ahead of it and encode each tracked block while
it tracks the next — every row as not the brightest, to a file; once the brightest track is known,
its rows are marked in the encoded messages as they are written (:func:`_track_pipelined`): every row
of a ``starlog.Tracks`` message has the same length, so its ``brightest`` byte is at a known place.

The centroids are read as tables (:meth:`~starlog.io.reader.LogReader.tables`, no dict per star), and
the rows of a whole block are encoded at once (:func:`~starlog.codecs.star_tables.star_codec`).

The bytes written do not depend on ``workers``.

One module of over 500 lines: the two ways of running (passes; one model pipelined) write the
same bytes and share the spool and encoding helpers, so they stay together.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterator, Sequence
from concurrent.futures import Executor, Future
from contextlib import ExitStack, contextmanager, nullcontext
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO, NamedTuple

import numpy as np
import numpy.typing as npt

from starlog.errors import InvalidParameterError
from starlog.codecs import protobuf_message_type
from starlog import topics
from starlog.io.reader import LogReader, LogSource, TableMessage
from starlog.codecs.schemas import MessageType
from starlog.codecs.star_tables import star_codec
from starlog.replay.blocks import channel_blocks, worker_log
from starlog.replay.channels import check_messages_read
from starlog.replay.pool import ordered_map, process_pool
from starlog.replay.progress import progress
from starlog.replay.spool import Spool, opened, read_block, read_blocks, write_block
from starlog.replay.window import windowed
from starlog.replay.layer import StageOutput, extend_log
from starlog.tracking import (
    MotionModel,
    MotionModelConfig,
    NoTrackError,
    StarTracker,
    TrackerConfig,
)

__all__ = ["NisSum", "TrackSummary", "encode_tracks", "model_statistics", "parse_models", "track_frame", "track_log",
           "track_parameters", "tracker_configs", "tracks_message_type"]

#: Frames per spooled block: bounds the memory of every pass.
BLOCK_FRAMES = 64
#: The centroid columns the tracker takes, in order.
_STAR_FIELDS = ("x", "y", "sigma", "flux")


def tracks_message_type() -> MessageType:
    """The message type of a ``/track/<METHOD>/<MODEL>`` channel."""
    return protobuf_message_type("starlog.Tracks")


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

    def lines(self) -> list[str]:
        """A table of the models: tracks, confirmed tracks, gated measurements, mean NIS, brightest track."""
        lines = [f"  {'model':<18} {'tracks':>7} {'confirmed':>9} {'gated':>6} {'mean NIS':>9} {'brightest':>9}"]
        for model, m in self.to_dict()["models"].items():
            lines.append(f"  {model:<18} {m['tracks']:>7} {m['confirmed_tracks']:>9} {m['gated_measurements']:>6} "
                         f"{m['mean_nis']:>9.2f} {m['brightest_track']:>9}")
        return lines


# ---------------------------------------------------------------- pass 1: read
class _CentroidBlock:
    """Centroid messages gathered into arrays."""

    def __init__(self) -> None:
        self.frames: list[int] = []
        self.times: list[int] = []
        self.counts: list[int] = []
        self.tables: list[npt.NDArray[np.void]] = []

    def add(self, message: TableMessage) -> None:
        rows = message.rows if message.rows is not None else np.zeros(0, star_codec("starlog.Centroids").row_dtype)
        self.frames.append(message.header["frame"])
        self.times.append(message.log_time)
        self.counts.append(rows.size)
        self.tables.append(rows)

    def table(self) -> npt.NDArray[np.float64]:
        """The ``(k, 4)`` x/y/sigma/flux of every star of the block."""
        rows = np.concatenate(self.tables) if self.tables else np.zeros(0, star_codec("starlog.Centroids").row_dtype)
        out = np.empty((rows.size, len(_STAR_FIELDS)), dtype=np.float64)
        for k, name in enumerate(_STAR_FIELDS):
            out[:, k] = rows[name]
        return out

    def write(self, file: BinaryIO) -> None:
        """Spool ``(frame, log_time, stars per frame, (k, 4) x/y/sigma/flux)``."""
        write_block(file, np.array(self.frames, dtype=np.int64), np.array(self.times, dtype=np.int64),
                    np.array(self.counts, dtype=np.int64), self.table())


class _DecodedBlock(NamedTuple):
    """A block of centroid messages as arrays: what a worker sends back (numpy arrays pickle compactly, and
    leave no Python objects per star behind in the tracking process)."""

    frames: npt.NDArray[np.int64]
    times: npt.NDArray[np.int64]
    counts: npt.NDArray[np.int64]
    table: npt.NDArray[np.float64]


def _decode_centroid_block(source: LogSource, topic: str, start: int, end: int) -> _DecodedBlock:
    """Worker: the centroid messages with ``start <= log_time < end`` as arrays (the worker reads them itself)."""
    block = _CentroidBlock()
    for message in worker_log(source).tables(topic, start=start, end=end):
        block.add(message)
    return _DecodedBlock(np.array(block.frames, dtype=np.int64), np.array(block.times, dtype=np.int64),
                         np.array(block.counts, dtype=np.int64), block.table())


def _spool_centroids(log: LogReader, topic: str, spool: Spool, *, show_progress: bool) -> int:
    """Pass 1: the centroid channel → blocks of arrays in ``spool``; the number of frames."""
    n_frames = 0
    messages = progress(log.tables(topic), total=log.channel(topic).message_count,
                        description="track (read)", enabled=show_progress)
    block = _CentroidBlock()
    with opened(spool, "wb") as file:
        for message in messages:
            block.add(message)
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
    tracker, nis = StarTracker(config), NisSum()
    offsets = []
    with opened(spool, "wb") as file:
        for frames, times, counts, table in read_blocks(centroids, 4):
            rows, row_counts = _track_block(tracker, times, counts, table, nis)
            offsets.append(write_block(file, frames, times, row_counts, rows))
    return _model_run(tracker, source, nis, spool, offsets)


def _model_run(tracker: StarTracker, source: str, nis: NisSum, spool: Spool, offsets: list[int]) -> _ModelRun:
    """What one model's tracking found: the brightest track and the statistics."""
    return _ModelRun(spool=spool, offsets=offsets, **model_statistics(tracker, source, nis))


def model_statistics(tracker: StarTracker, source: str, nis: NisSum) -> dict[str, Any]:
    """What one model's tracker found over the log (``brightest``, ``tracks``, ``confirmed``, ``gated``,
    ``mean_nis``); :class:`NoTrackError`, saying what to change, when no track was confirmed."""
    try:
        brightest = tracker.brightest_track()
    except NoTrackError as err:
        raise _no_track_hint(tracker.model, source, err) from err
    stats = tracker.track_stats()
    return {"brightest": brightest, "tracks": int(stats.size), "confirmed": int(stats["confirmed"].sum()),
            "gated": int(stats["gated"].sum()), "mean_nis": nis.total / nis.count if nis.count else 0.0}


# ---------------------------------------------------------------- one model on several cores
def _track_pipelined(log: LogReader, source: LogSource, config: TrackerConfig, method: str, folder: Path,
                     blocks: list[tuple[int, int, int]], pool: Executor, workers: int, *,
                     show_progress: bool) -> tuple[int, _ModelRun, list[Path]]:
    """Passes 1 and 2 of one model with the reading and the encoding done by worker processes around the
    tracker: workers decode the centroid blocks ahead of it, and encode each tracked block (every row not the
    brightest, which is known only at the end: :func:`_write_patched` marks it) into a file while it tracks
    the next. Returns the frames read, the model's run and the encoded blocks' files, in order."""
    topic = topics.centroid_topic(method)
    decoded = ordered_map(pool, _decode_centroid_block, ((source, topic, start, end) for start, end, _ in blocks),
                          window=2 * workers)
    tracker, stats = StarTracker(config), NisSum()
    encoded: list[Future[None]] = []
    files: list[Path] = []
    n_frames = 0
    for k, block in enumerate(progress(decoded, total=len(blocks), description="track", enabled=show_progress,
                                       unit="block")):
        rows, row_counts = _track_block(tracker, block.times, block.counts, block.table, stats)
        spool = folder / f"rows-{k}"
        with open(spool, "wb") as file:
            write_block(file, block.frames, block.times, row_counts, rows)
        files.append(folder / f"encoded-{k}")
        encoded.append(pool.submit(_encode_unmarked, spool, method, config.model.value, files[-1]))
        n_frames += block.frames.size
    for future in encoded:
        future.result()
    return n_frames, _model_run(tracker, topic, stats, folder, []), files


@dataclass
class NisSum:
    """The NIS of every applied measurement, summed, for the model's mean NIS (:func:`track_frame` adds to it)."""

    total: float = 0.0
    count: int = 0

    def add(self, rows: npt.NDArray[np.void]) -> None:
        """The NIS of the measurements applied in tracker rows (``TRACK_DTYPE``)."""
        applied = rows["measured"] & (rows["age"] > 0)
        self.total += float(rows["nis"][applied].sum())
        self.count += int(applied.sum())


def _track_block(tracker: StarTracker, times: npt.NDArray[np.int64], counts: npt.NDArray[np.int64],
                 table: npt.NDArray[np.float64], nis: NisSum) -> tuple[npt.NDArray[np.void], npt.NDArray[np.int64]]:
    """Each frame of a block through the tracker (:meth:`~starlog.tracking.StarTracker.update_block`): the block's
    rows, one table, and each frame's number of rows."""
    rows, row_counts = tracker.update_block(times, counts, table)
    nis.add(rows)
    return rows, row_counts


def track_frame(tracker: StarTracker, log_time: int, stars: npt.NDArray[np.float64], nis: NisSum
                ) -> npt.NDArray[np.void]:
    """One frame through the tracker, a block of one frame for :func:`_track_block`: ``stars`` is its ``(k, 4)``
    x/y/sigma/flux; its rows (``TRACK_DTYPE``), the NIS of each applied measurement added to ``nis``."""
    rows, _ = _track_block(tracker, np.array([log_time], dtype=np.int64), np.array([stars.shape[0]], dtype=np.int64),
                           stars, nis)
    return rows


def _encode_unmarked(spool: Path, method: str, model: str, out: Path) -> None:
    """Worker: one spooled block of rows encoded as :func:`_encode_block` does, no row marked the brightest, to
    ``out``: each message's ``log_time``, length and header length, and each row's track."""
    frames, times, counts, rows = read_block(spool, 0, 4)
    messages = encode_tracks(frames, counts, rows, method, model, np.zeros(rows.size, dtype=bool))
    heads = [len(m) - n * star_codec("starlog.Tracks").row_size for m, n in zip(messages, counts.tolist())]
    with open(out, "wb") as file:
        write_block(file, np.array(times, dtype=np.int64), np.array([len(m) for m in messages], dtype=np.int64),
                    np.array(heads, dtype=np.int64), counts, rows["track"],
                    np.frombuffer(b"".join(messages), dtype=np.uint8))
    spool.unlink()


def _write_patched(out: StageOutput, channel: int, files: list[Path], brightest: int, n_frames: int, *,
                   show_progress: bool) -> None:
    """Pass 3 of :func:`_track_pipelined`: each encoded message, the brightest track's rows marked, written."""
    codec = star_codec("starlog.Tracks")
    size, at = codec.row_size, codec.value_offset("brightest")

    def messages() -> Iterator[tuple[int, bytes]]:
        for path in files:
            times, lengths, heads, counts, tracks, data = read_block(path, 0, 6)
            starts = np.concatenate([[0], np.cumsum(lengths)[:-1]])
            row_starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
            for t, start, length, head, r0, n in zip(times.tolist(), starts.tolist(), lengths.tolist(),
                                                     heads.tolist(), row_starts.tolist(), counts.tolist()):
                message = bytearray(data[start:start + length])
                for k in np.flatnonzero(tracks[r0:r0 + n] == brightest).tolist():
                    assert message[head + k * size + at] == 0
                    message[head + k * size + at] = 1
                yield t, bytes(message)
            path.unlink()

    for t, message in progress(messages(), total=n_frames, description="track (write)", enabled=show_progress):
        out.writer.write(channel, log_time=t, data=message)


# ---------------------------------------------------------------- pass 3: write
def _encode_block(spool: Spool, offset: int, method: str, model: str,
                  brightest: int) -> tuple[list[int], list[bytes]]:
    """One spooled block of rows → ``(log_time, starlog.Tracks message)`` of each frame (in a worker process
    when there is a pool)."""
    frames, times, counts, rows = read_block(spool, offset, 4)
    return times.tolist(), encode_tracks(frames, counts, rows, method, model, rows["track"] == brightest)


def encode_tracks(frames: npt.NDArray[np.int64], counts: npt.NDArray[np.int64], rows: npt.NDArray[np.void],
                  method: str, model: str, brightest: npt.NDArray[np.bool_]) -> list[bytes]:
    """The ``starlog.Tracks`` message of each frame of a block, ``counts`` rows each, in order (``brightest``:
    which rows are the brightest track's): the block's rows encoded at once (their columns checked), then cut
    per frame behind each frame's header."""
    codec = star_codec("starlog.Tracks")
    encoded = codec.encode_rows(rows, {"brightest": brightest})
    size = codec.row_size
    ends = np.cumsum(counts).tolist()
    return [codec.encode_header({"frame": frame, "method": method, "model": model}) + encoded[a * size:b * size]
            for frame, a, b in zip(frames.tolist(), [0, *ends[:-1]], ends, strict=True)]


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
    channels = [out.add_channel(topics.track_topic(method, m.value), tracks_message_type()) for m in runs]
    frames = _frames_out(encoded, len(runs), n_blocks)
    for t, messages in progress(frames, total=n_frames, description="track (write)", enabled=show_progress):
        for channel, message in zip(channels, messages, strict=True):
            out.writer.write(channel, log_time=t, data=message)


# ---------------------------------------------------------------- the stage
def _track_every_model(log: LogReader, out: StageOutput, configs: dict[MotionModel, TrackerConfig], method: str,
                       summary: TrackSummary, workers: int, *, show_progress: bool) -> dict[MotionModel, _ModelRun]:
    """The three passes, each model tracked in a worker process when there are several workers."""
    source = topics.centroid_topic(method)
    processes = min(workers, len(configs))
    with _spools(list(configs), Path(out.writer.path), shared=processes > 1) as spools, \
            (process_pool(processes, preload=["starlog.stages.track"]) if processes > 1 else nullcontext()) as pool:
        summary.frames = _spool_centroids(log, source, spools.centroids, show_progress=show_progress)
        summary.channel_messages = check_messages_read(log, source, summary.frames)
        runs = _track_models(configs, source, spools, pool)
        _write_tracks(out, runs, method, summary.frames, pool, show_progress=show_progress)
    return runs


def _track_one_model(log: LogReader, input_path: LogSource, out: StageOutput, config: TrackerConfig, method: str,
                     summary: TrackSummary, blocks: list[tuple[int, int, int]], workers: int, *,
                     show_progress: bool) -> dict[MotionModel, _ModelRun]:
    """One model on several cores (:func:`_track_pipelined`), written as :func:`_track_every_model` writes it."""
    channel = out.add_channel(topics.track_topic(method, config.model.value), tracks_message_type())
    with tempfile.TemporaryDirectory(prefix=f".{out.writer.path.name}.track-", dir=out.writer.path.parent) as tmp, \
            process_pool(workers, preload=["starlog.stages.track"]) as pool:
        summary.frames, run, files = _track_pipelined(log, input_path, config, method, Path(tmp), blocks, pool,
                                                      workers, show_progress=show_progress)
        summary.channel_messages = check_messages_read(log, topics.centroid_topic(method), summary.frames)
        _write_patched(out, channel, files, run.brightest, summary.frames, show_progress=show_progress)
    return {config.model: run}


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


def tracker_configs(chosen: list[MotionModel], tracker: dict[str, Any] | None,
                    motion: dict[str, Any] | None) -> dict[MotionModel, TrackerConfig]:
    """Each model's :class:`TrackerConfig` from the stage's ``tracker`` and ``motion`` options."""
    try:
        motion_config = MotionModelConfig(**(motion or {}))
        return {m: TrackerConfig(model=m, motion=motion_config, **(tracker or {})) for m in chosen}
    except TypeError as err:
        raise InvalidParameterError(f"unknown tracker option: {err}.") from err


def track_parameters(method: str, chosen: list[MotionModel], tracker: dict[str, Any] | None,
                     motion: dict[str, Any] | None, selected_by: dict[str, Any] | None = None) -> dict[str, Any]:
    """The parameters the track stage records in its provenance (``selected_by``: why ``method`` was chosen)."""
    return {"method": method, "models": [m.value for m in chosen], "tracker": dict(tracker or {}),
            "motion": dict(motion or {})} | ({"selected_by": selected_by} if selected_by is not None else {})


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
    selected_by: dict[str, Any] | None = None,
) -> TrackSummary:
    """Track every star of ``/stars/centroids/<method>`` under each motion model.

    Parameters
    ----------
    method : str
        Centroid method whose channel is tracked (e.g. ``"GAUSSFIT"``).
    models : str or sequence of str
        ``"all"`` or motion model names.
    tracker : dict, optional
        :class:`~starlog.tracking.TrackerConfig` fields (gate_probability, association_radius,
        confirm_hits, max_missed, sigma_floor).
    motion : dict, optional
        :class:`~starlog.tracking.MotionModelConfig` fields (process-noise intensities).
    workers : int
        Processes tracking the models (at most one per model; with several, they also encode
        the messages; with one model, they read and encode around the tracker). The output does not
        depend on it.
    start, end : str or int, optional
        Only the range ``start <= log_time < end`` (ns, ``"12.5s"`` or ``"frame:N"`` of the centroid
        channel; :mod:`starlog.io.timerange`): the layer holds its channels for that range.
    flatten : bool
        Write the whole chain as one self-contained file instead of a layer on the input.
    selected_by : dict, optional
        Why ``method`` was chosen (``starlog run``'s ``"trusted"``: the evidence that named it), recorded in the
        provenance as it is.
    """
    chosen = parse_models(models)
    configs = tracker_configs(chosen, tracker, motion)
    method = method.upper()
    source = topics.centroid_topic(method)
    parameters = track_parameters(method, chosen, tracker, motion, selected_by)
    summary = TrackSummary(method=method)
    with extend_log(input_path, output_path, stage="track", parameters=parameters, force=force, flatten=flatten,
                    compression=compression) as (log, out):
        blocks = channel_blocks(log, source, BLOCK_FRAMES) if workers > 1 and len(chosen) == 1 else None
        if blocks is not None and log.fully_indexed:
            runs = _track_one_model(log, input_path, out, configs[chosen[0]], method, summary, blocks, workers,
                                    show_progress=show_progress)
        else:
            runs = _track_every_model(log, out, configs, method, summary, workers, show_progress=show_progress)
    for m, run in runs.items():
        summary.brightest[m.value] = run.brightest
        summary.tracks[m.value] = run.tracks
        summary.confirmed[m.value] = run.confirmed
        summary.gated[m.value] = run.gated
        summary.mean_nis[m.value] = run.mean_nis
    return summary
