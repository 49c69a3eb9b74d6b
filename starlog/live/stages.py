"""``run``'s per-frame stages, one frame at a time as it arrives, through the stages' own per-frame functions.

* :class:`LiveCentroid` — the centroid stage's :class:`~starlog.stages.centroid.CentroidLayer` fed by its
  :class:`~starlog.stages.centroid.frames.FrameExtractor` (a new block's extractor where the source's
  chunks start a block, as the stage cuts them);
* :class:`LiveTrack` — one :class:`~starlog.tracking.StarTracker` per motion model of a centroid method, fed
  by :func:`~starlog.stages.track.track_frame` from the rows of the centroid message as the layer holds it
  (:func:`centroid_rows`). Which track is the brightest star's is known only at the end: live marks the
  brightest *so far* (looked again every second) and spools every frame's rows; when the source ends, the
  layer is written from the spool with the log's brightest track marked, as the track stage marks it
  (:func:`~starlog.stages.track.encode_tracks`);
* :class:`LiveSolve` — the solve stage's :func:`~starlog.stages.solve.solve_frame` on each centroid channel;
  the identified stars the sky's evidence may use are spooled, and that evidence computed at the end on the
  frames the stage keeps (:func:`~starlog.stages.solve.sky_frames_kept`).

Each writes its messages as frames arrive (a provisional file, published on the Foxglove server as written)
and closes its layer on the finished log below it when the source ends (:meth:`finish`).
"""

from __future__ import annotations

import pickle
import tempfile
import time
from contextlib import ExitStack
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
import numpy.typing as npt

from starlog.errors import InvalidInputError
from starlog import topics
from starlog.io.frames import SkippedFrame
from starlog.io.reader import LogReader
from starlog.codecs.star_tables import star_codec
from starlog.live.extraction import CentroidWorkers, Done, FrameResult, Handle, extract_frame
from starlog.live.layers import PublishingWriter, close_on_base, relayer
from starlog.live.sources import SourceMessage
from starlog.stages.centroid.frames import FrameMessages
from starlog.replay.spool import read_blocks, write_block
from starlog.replay.layer import StageOutput, extend_log
from starlog.stages.centroid import CentroidLayer, CentroidParameters, CentroidSummary
from starlog.stages.track import (
    BLOCK_FRAMES,
    NisSum,
    TrackSummary,
    encode_tracks,
    model_statistics,
    parse_models,
    track_frame,
    track_parameters,
    tracker_configs,
    tracks_message_type,
)
from starlog.tracking import NoTrackError, StarTracker

__all__ = ["LiveCentroid", "LiveSolve", "LiveTrack", "centroid_rows", "star_columns"]

_COLUMNS = ("x", "y", "sigma", "flux")


def centroid_rows(data: bytes) -> npt.NDArray[np.void]:
    """The rows of a ``starlog.Centroids`` message the centroid stage wrote (none: an empty table)."""
    codec = star_codec("starlog.Centroids")
    rows = codec.decode(data).rows
    return rows if rows is not None else np.zeros(0, codec.row_dtype)


def star_columns(rows: npt.NDArray[np.void]) -> npt.NDArray[np.float64]:
    """The ``(k, 4)`` x/y/sigma/flux of a frame's centroid rows, as the track stage reads them."""
    out = np.empty((rows.size, len(_COLUMNS)), dtype=np.float64)
    for k, name in enumerate(_COLUMNS):
        out[:, k] = rows[name]
    return out


class LiveCentroid:
    """The centroid stage on frames as they arrive (module docstring): :meth:`submit` a frame (measured here, or by
    a worker process: :mod:`starlog.live.extraction`), then :meth:`write` its result, frames in order."""

    def __init__(self, parameters: CentroidParameters, out: StageOutput, *, workers: int = 0,
                 stack: ExitStack | None = None) -> None:
        self.parameters = parameters
        self.provenance = dict(parameters.provenance)
        self.summary = CentroidSummary.of(parameters)
        self.out = out
        self.layer = CentroidLayer.start(out, parameters, self.summary)
        self.workers = None
        if workers and stack is not None:
            self.workers = CentroidWorkers(parameters.extract, workers)
            stack.callback(self.workers.close)
        self._state: dict[str, Any] = {"extract": parameters.extract}
        self._first: tuple[tuple[int, ...], str, int] | None = None
        self._last = -1

    def submit(self, message: SourceMessage) -> Handle:
        """Start measuring one frame (frames in order)."""
        assert message.frame is not None
        if message.log_time <= self._last:
            return Done((SkippedFrame(message.frame, message.log_time, (
                f"frame {message.frame} does not come after the previous frame (log_time {self._last}); frame "
                "timestamps must increase strictly.")), (), ""))
        self._last = message.log_time
        args = (message.block_start, message.frame, message.log_time, message.schema,
                message.channel.message_encoding, message.data)
        if self.workers is not None:
            return self.workers.submit(*args)
        return Done(extract_frame(self._state, None, *args))

    def write(self, index: int, result: FrameResult) -> FrameMessages | SkippedFrame:
        """Frame ``index``'s messages, written (a frame that cannot be used is skipped, and listed)."""
        encoded, shape, dtype = result
        if isinstance(encoded, FrameMessages):
            if self._first is None:
                self._first = (shape, dtype, index)
            elif (shape, dtype) != self._first[:2]:
                first = self._first
                encoded = SkippedFrame(index, encoded.log_time, (
                    f"frame {index} is {shape[1]}x{shape[0]} {dtype}, but frame {first[2]} is {first[0][1]}x"
                    f"{first[0][0]} {first[1]}; every frame of a log must match."))
        self.layer.write(encoded)
        return encoded

    def skip(self, frame: int, log_time: int, reason: str) -> None:
        """A frame of the source that was not processed, listed as skipped with why."""
        self.layer.write(SkippedFrame(frame, log_time, reason))

    def finish(self, writer: PublishingWriter, base: Path, notes: list[str], metadata: list[tuple[str, dict[str, str]]]
               ) -> None:
        """Close the layer on the finished ``base`` (its closing records and provenance)."""
        self.layer.finish(notes, self.provenance)
        with LogReader(base) as log:
            close_on_base(writer, self.out, log, stage="centroid", parameters=self.provenance, metadata=metadata)


class LiveTrack:
    """The track stage of one centroid method on frames as they arrive (module docstring)."""

    def __init__(self, method: str, table: dict[str, Any], out: StageOutput, spool_folder: Path) -> None:
        self.method = method.upper()
        self.selected_by: dict[str, Any] | None = None  # why the method was tracked, when "trusted" named it
        self.models = parse_models(table.get("models", "all"))
        self.options = (table.get("tracker"), table.get("motion"))
        configs = tracker_configs(self.models, *self.options)
        self.trackers = {m: StarTracker(configs[m]) for m in self.models}
        self.nis = {m: NisSum() for m in self.models}
        self.out = out
        self.channels = {m: out.add_channel(topics.track_topic(self.method, m.value), tracks_message_type())
                         for m in self.models}
        self.spools: dict[Any, BinaryIO] = {m: tempfile.TemporaryFile(dir=spool_folder) for m in self.models}
        self._rows: dict[Any, list[npt.NDArray[np.void]]] = {m: [] for m in self.models}
        self._frames: list[int] = []
        self._times: list[int] = []
        self.frames = 0
        self.brightest = dict.fromkeys(self.models, -1)
        self._looked = 0.0

    @property
    def topic(self) -> str:
        """The centroid channel this stage tracks."""
        return topics.centroid_topic(self.method)

    def frame(self, frame: int, log_time: int, centroids: npt.NDArray[np.void]) -> None:
        """Track one frame (``centroids``: the rows of its centroid message) under every model; write its
        messages."""
        stars = star_columns(centroids)
        now = time.monotonic()
        if now - self._looked >= 1.0:
            self._looked = now
            self.brightest = {m: _brightest_so_far(t) for m, t in self.trackers.items()}
        frames, counts = np.array([frame], dtype=np.int64), np.zeros(1, dtype=np.int64)
        for model, tracker in self.trackers.items():
            rows = track_frame(tracker, log_time, stars, self.nis[model])
            counts[0] = rows.size
            data = encode_tracks(frames, counts, rows, self.method, model.value, rows["track"] == self.brightest[model])
            self.out.writer.write(self.channels[model], log_time=log_time, data=data[0])
            self._rows[model].append(rows)
        self._frames.append(frame)
        self._times.append(log_time)
        self.frames += 1
        if len(self._frames) == BLOCK_FRAMES:
            self._spill()

    def _spill(self) -> None:
        """The rows of the frames held, to each model's spool (blocks as the track stage spools them)."""
        if not self._frames:
            return
        frames, times = np.array(self._frames, dtype=np.int64), np.array(self._times, dtype=np.int64)
        for model in self.models:
            rows = self._rows[model]
            counts = np.array([r.size for r in rows], dtype=np.int64)
            joined = np.empty(int(counts.sum()), dtype=rows[0].dtype)
            np.concatenate(rows, out=joined)
            write_block(self.spools[model], frames, times, counts, joined)
            self._rows[model] = []
        self._frames, self._times = [], []

    def finish(self, base: Path, output: Path, compression: str) -> TrackSummary:
        """The track layer on the finished ``base``, the log's brightest track marked, as the track stage writes it."""
        self._spill()
        summary = TrackSummary(method=self.method, frames=self.frames, channel_messages=self.frames)
        stats = {m: model_statistics(self.trackers[m], self.topic, self.nis[m]) for m in self.models}
        for model, figures in stats.items():
            for key, target in (("brightest", summary.brightest), ("tracks", summary.tracks),
                                ("confirmed", summary.confirmed), ("gated", summary.gated),
                                ("mean_nis", summary.mean_nis)):
                target[model.value] = figures[key]
        parameters = track_parameters(self.method, self.models, *self.options, self.selected_by)
        with extend_log(base, output, stage="track", parameters=parameters, force=True,
                        compression=compression) as (_, out):
            channels = [out.add_channel(topics.track_topic(self.method, m.value), tracks_message_type())
                        for m in self.models]
            blocks = [read_blocks(self.spools[m], 4) for m in self.models]
            for parts in zip(*blocks, strict=True):
                encoded = [encode_tracks(frames, counts, rows, self.method, m.value, rows["track"] == stats[m]["brightest"])
                           for m, (frames, _, counts, rows) in zip(self.models, parts, strict=True)]
                for k, t in enumerate(parts[0][1].tolist()):
                    for channel, messages in zip(channels, encoded, strict=True):
                        out.writer.write(channel, log_time=t, data=messages[k])
        return summary

    def close(self) -> None:
        for spool in self.spools.values():
            spool.close()


def _brightest_so_far(tracker: StarTracker) -> int:
    """The brightest track of the frames so far (-1: none confirmed yet)."""
    try:
        return tracker.brightest_track()
    except NoTrackError:
        return -1


class LiveSolve:
    """The solve stage on each frame's centroid messages as they arrive (module docstring)."""

    def __init__(self, table: dict[str, Any], methods: list[str], probe: LogReader, shape: tuple[int, int],
                 out: StageOutput, spool_folder: Path) -> None:
        from starlog.attitude.catalogue import load_catalogue, solver_data_file
        from starlog.attitude.identify import AttitudeTracker
        from starlog.stages.solve import MethodFigures, add_solve_channels, tracker_settings

        solver_data_file()
        self.options = dict(table.get("options") or {})
        self.settings = tracker_settings(probe, self.options, shape[1])
        self.catalogue = load_catalogue()
        self.topics = _solved_topics(table.get("centroids", "all"), methods)
        self.width = shape[1]
        self.trackers = {t: AttitudeTracker(self.catalogue, shape, self.settings) for t in self.topics}
        self.figures = {t: MethodFigures() for t in self.topics}
        self.channels = {t: add_solve_channels(out, t.rsplit("/", 1)[-1]) for t in self.topics}
        self.out = out
        self.spool: BinaryIO = tempfile.TemporaryFile(dir=spool_folder)

    def frame(self, frame: int, log_time: int, centroids: dict[str, npt.NDArray[np.void]],
              truth: npt.NDArray[np.float64] | None) -> None:
        """Solve one frame from each chosen centroid channel's message (``centroids``: topic → its rows)."""
        from starlog.stages.solve import solve_frame, usable_centroids

        for topic in self.topics:
            method, figures = topic.rsplit("/", 1)[-1], self.figures[topic]
            stars = usable_centroids(centroids[topic])
            messages = solve_frame(self.trackers[topic], method, frame, log_time, stars, truth, figures)
            for channel, data in zip(self.channels[topic], messages, strict=True):
                self.out.writer.write(channel, log_time=log_time, data=data)
            for identified in figures.identified:  # every solved frame's (keep_every 1): spooled, chosen at the end
                pickle.dump((topic, figures.frames - 1, identified), self.spool)
            figures.identified.clear()

    def _identified(self) -> dict[str, list[Any]]:
        """Per method, the identified stars of the frames the stage keeps for the sky's evidence (every
        :func:`~starlog.stages.solve.sky_frames_kept` frames of its channel), from the spool."""
        from starlog.stages.solve import sky_frames_kept

        every = {t: sky_frames_kept(f.frames) for t, f in self.figures.items()}
        kept: dict[str, list[Any]] = {t.rsplit("/", 1)[-1]: [] for t in self.topics}
        self.spool.seek(0)
        while True:
            try:
                topic, index, identified = pickle.load(self.spool)
            except EOFError:
                break
            if index % every[topic] == 0:
                kept[topic.rsplit("/", 1)[-1]].append(identified)
        return {name: frames for name, frames in kept.items() if frames}

    def finish(self, provisional: Path, base: Path, output: Path, compression: str) -> dict[str, Any]:
        """The solve layer on the finished ``base``, from the messages written live (``provisional``, closed), with
        the stage's record (each method's figures and the sky's evidence) as the stage writes it."""
        import json

        from starlog.attitude.sky_evidence import sky_evidence
        from starlog.stages.solve import SolveSummary, solve_parameters

        summary = SolveSummary(width=self.width)
        summary.methods = {t.rsplit("/", 1)[-1]: f.to_dict(self.width) for t, f in self.figures.items()}
        summary.seconds = {t.rsplit("/", 1)[-1]: f.seconds for t, f in self.figures.items()}
        identified = self._identified()
        if len(identified) >= 2:
            summary.sky_evidence = sky_evidence(identified, self.catalogue.vectors, self.catalogue.magnitude,
                                                fit_distortion=self.settings.fit_distortion)
        relayer(provisional, base, output, stage="solve",
                parameters=solve_parameters(self.topics, self.options, self.catalogue),
                metadata=[(topics.SOLVE_METADATA, {"methods": json.dumps(summary.methods),
                                                   "sky_evidence": json.dumps(summary.sky_evidence)})],
                compression=compression)
        return summary.to_dict()

    def close(self) -> None:
        self.spool.close()


def _solved_topics(centroids: Any, methods: list[str]) -> list[str]:
    """The centroid channels ``[solve] centroids`` names, as the solve stage chooses them."""
    available = [topics.centroid_topic(m) for m in methods]
    names = [] if centroids is None else (centroids.split(",") if isinstance(centroids, str) else list(centroids))
    names = [n.strip() for n in names if n.strip()]
    if not names:
        if len(available) == 1:
            return available
        raise InvalidInputError("the centroid layer has several centroid channels; choose in [solve] centroids "
                                "(or \"all\"): " + ", ".join(available))
    if [n.lower() for n in names] == ["all"]:
        return available
    chosen = [n if n.startswith("/") else topics.centroid_topic(n.upper()) for n in names]
    missing = [c for c in chosen if c not in available]
    if missing:
        raise InvalidInputError(f"[solve] centroids names {missing}, which the centroid stage does not write; it "
                                f"writes {', '.join(available)}.")
    return chosen

