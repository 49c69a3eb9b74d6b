"""One ``starlog live`` run: a source followed frame by frame through ``run``'s stages, served and recorded.

1. **Learning.** The centroid stage learns its parameters from a log's first frames (PSF width,
   phase calibration, mode): live waits for as many (:func:`frames_to_learn`), writes them as a log
   of their own (:class:`~starlog.live.layers.PrefixLog`) and resolves the parameters from it as the
   stage resolves them from the whole log, so both start from the same parameters.
2. **Live.** Each frame, in the source's order: the centroid stage, the track stage of each method
   and model, the solve stage (:mod:`starlog.live.stages`); every message written to its layer and
   published on the Foxglove server as written; the layers flushed at least every half second.
   Falling behind is said on stderr and on ``/live/status``; a frame that cannot be used is listed
   with why (``starlog.live`` metadata record of the centroid layer, and the stage's summary).
3. **Closing**, when the source ends, at the first Ctrl-C or SIGTERM (a second Ctrl-C drops the
   frames still waiting, each listed): the base becomes complete (:meth:`~starlog.live.sources.Source.finish`),
   the live layers are closed on it as the layers ``run`` writes (same file names, same messages), and
   the stages that need the whole series (compensate, your own stages) run on them as ``run`` runs them.
   ``"trusted"`` in ``[track]`` is decided on the closed centroid layer, as ``run`` decides it
   (:func:`~starlog.trusted.resolve_trusted`); live tracks meanwhile the method it stands for without
   evidence, and when the evidence names another, that one's layer is the track stage's on the finished log.
"""

from __future__ import annotations

import json
import math
import signal
import tempfile
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from starlog.errors import InvalidInputError, InvalidParameterError, OutputExistsError
from starlog import topics
from starlog.io.frames import SkippedFrame, reuse_frame_buffers
from starlog.io.reader import LogReader
from starlog.live.extraction import Handle
from starlog.live.layers import PrefixLog, PublishingWriter, relayer
from starlog.live.sources import Camera, Source, SourceMessage, SourceProblem
from starlog.live.stages import LiveCentroid, LiveSolve, LiveTrack, centroid_rows
from starlog.live.status import StatusBoard
from starlog.pipeline import PipelineConfig, fit_to_log, layer_paths, possible_layers, stage_steps
from starlog.stages.centroid.frames import opencv_threads
from starlog.stages.centroid.parameters import PHASE_MAX_FRAMES
from starlog.replay.layer import StageOutput
from starlog.stages.centroid import resolve_centroid_parameters
from starlog.trusted import TRUSTED, default_tracked, resolve_trusted, tracks_trusted

__all__ = ["LIVE_METADATA", "LiveResult", "LiveSession", "frames_to_learn"]

#: The metadata record of the centroid layer that says how the live run went.
LIVE_METADATA = "starlog.live"
#: Frames a source may have read ahead of the processing (the rest waits in the source).
_READ_AHEAD = 64
#: The frames the centroid stage's first-frame estimates read when the phase calibration is not learnt.
_FIRST_FRAMES = 20


def frames_to_learn(table: dict[str, Any]) -> int:
    """How many first frames the centroid stage's parameters are learnt from, for its ``[centroid]`` table."""
    phase = table.get("phase_correction", "auto")
    return PHASE_MAX_FRAMES if isinstance(phase, str) and phase == "auto" else _FIRST_FRAMES


@dataclass
class LiveResult:
    """What a live run did: the base and layers written, each stage's report, the frames and latencies."""

    output: Path
    base: Path | None = None
    layers: list[Path] = field(default_factory=list)
    stages: list[tuple[str, dict[str, Any]]] = field(default_factory=list)
    status: dict[str, Any] = field(default_factory=dict)
    end_reason: str = ""
    url: str = ""
    trusted: dict[str, Any] | None = None
    """What ``"trusted"`` in ``[track]`` stood for and why, as ``run`` decides it; None without it."""

    def to_dict(self) -> dict[str, Any]:
        return {"output": str(self.output), "base": None if self.base is None else str(self.base),
                "layers": [str(p) for p in self.layers], "stages": [{"stage": s, **r} for s, r in self.stages],
                "end": self.end_reason, "server": self.url, "trusted": self.trusted, **self.status}


class LiveSession:
    """A live run of ``config`` on ``source`` into the layers of ``output`` (module docstring).

    ``server``: a :class:`~starlog.live.server.LiveServer` or None; ``say``: where status lines go;
    ``frame_workers``: processes measuring frames (0: this one); ``workers``: cores of the stages run at the end.
    """

    def __init__(self, source: Source, output: Path, config: PipelineConfig, *, server: Any, force: bool,
                 compression: str = "zstd", workers: int = 1, frame_workers: int = 1,
                 say: Callable[[str], None] = lambda line: None, show_progress: bool = False) -> None:
        if config.centroid is None:
            raise InvalidParameterError(f"{config.source}: starlog live runs the centroid stage first; the config "
                                        "has no [centroid] table.")
        self.source, self.output, self.config, self.server = source, output, config, server
        self.compression, self.workers, self.say, self.show_progress = compression, workers, say, show_progress
        self.names = [name for name, _ in stage_steps(config)]
        self.paths = layer_paths(output, self.names)
        for path in possible_layers(output, config):
            if path.exists() and not force:
                raise OutputExistsError(path)
        self.board = StatusBoard()
        self.result = LiveResult(output=output, url=server.url if server is not None else "")
        self.frame_workers = frame_workers
        self._queue: deque[SourceMessage | SourceProblem] = deque()
        self._inflight: deque[tuple[SourceMessage, Handle]] = deque()
        self._frames_waiting = 0
        self._limit = 2 * frame_workers + 1
        self._outlets: dict[str, Callable[[bytes, int], None]] = {}
        self._stop = threading.Event()
        self._stop_now = threading.Event()
        self._truth: dict[int, Any] = {}
        self._truth_seen = -1
        self._writers: list[PublishingWriter] = []
        self.centroid: LiveCentroid | None = None
        self.tracks: list[LiveTrack] = []
        self.solve: LiveSolve | None = None

    # ------------------------------------------------------------------ the run
    def run(self) -> LiveResult:
        """Learn, process frames as they arrive, close the layers; the result."""
        reuse_frame_buffers()
        with tempfile.TemporaryDirectory(prefix=f".{self.output.name}.live-", dir=self.output.parent or ".") as tmp, \
                opencv_threads(1), _stop_signals(self._stop, self._stop_now), ExitStack() as workers:
            try:
                self._learn(Path(tmp), workers)
                self._follow()
                self._close()
            except BaseException:
                self._abort()
                raise
            finally:
                for track in self.tracks:
                    track.close()
                if self.solve is not None:
                    self.solve.close()
        return self.result

    def stop(self) -> None:
        """End the run as Ctrl-C does (the frames read are processed, the layers closed)."""
        self._stop.set()

    def _learn(self, folder: Path, workers: ExitStack) -> None:
        """Read the first frames, learn the centroid parameters from them, open the live layers."""
        table = dict(self.config.centroid or {})
        prefix = PrefixLog(folder / "first-frames.mcap", frames_to_learn(table))
        self.say(f"learning the centroid parameters from the first {prefix.frames} frames of the {self.source.description}")
        while not prefix.full and not self.source.ended and not self._stop.is_set():
            for event in self._read():
                if isinstance(event, SourceMessage):
                    prefix.add(event.schema, event.channel, event.log_time, event.data, frame=event.frame is not None)
        if prefix.seen == 0:
            prefix.abort()
            raise InvalidParameterError(f"the {self.source.description} gave no frame"
                                        + (f" ({self.source.end_reason})." if self.source.end_reason else "."))
        probe = prefix.close(self.source.metadata())
        with LogReader(probe) as log:
            parameters = resolve_centroid_parameters(
                log, methods=table.get("methods", "all"), gain=table.get("gain"), read_noise=table.get("read_noise"),
                options=table.get("options"), image_topic=table.get("image_topic"), psf=table.get("psf"),
                phase_correction=table.get("phase_correction", "auto"), mode=table.get("mode", "auto"),
                acquire_every=table.get("acquire_every"))
        self._open_layers(parameters, probe, folder, workers)
        self.say(f"live: {parameters.provenance['mode']} mode, methods {', '.join(m.value for m in parameters.methods)}"
                 + (f"; Foxglove: {self.server.url}" if self.server is not None else ""))

    def _open_layers(self, parameters: Any, probe: Path, folder: Path, workers: ExitStack) -> None:
        first_ids = self.source.next_ids()
        writer = self._writer(self.paths[0], first_ids)
        self.centroid = LiveCentroid(parameters, StageOutput(writer), workers=self.frame_workers, stack=workers)
        methods = [m.value for m in parameters.methods]
        self._open_tracks(methods, folder)
        solve = self.config.solve
        if solve is not None and solve.get("compensated") is None:
            path = self.paths[self.names.index("solve")]
            with LogReader(probe) as log:
                shape = next(log.frames(parameters.image_topic))[2].shape
                self.solve = LiveSolve(solve, methods, log, shape, StageOutput(self._writer(path, (1, 1))), folder)

    def _open_tracks(self, methods: list[str], folder: Path) -> None:
        """A live track stage per ``[track]`` method; ``"trusted"``, decided only when the source ends, is tracked
        meanwhile as the method it stands for without evidence (:func:`~starlog.trusted.default_tracked`)."""
        track = self.config.track
        for k, method in enumerate(_names(track.get("methods", ["GAUSSFIT"])) if track is not None else []):
            name = default_tracked(methods) if method.lower() == TRUSTED else method.upper()
            if name not in methods:
                raise InvalidParameterError(f"{self.config.source}: [track] methods names {method}, which [centroid] "
                                            f"does not measure ({', '.join(methods)}).")
            if any(t.method == name for t in self.tracks):
                continue
            out = StageOutput(self._writer(self.paths[1 + k], (1, 1)))
            self.tracks.append(LiveTrack(name, track or {}, out, folder))

    def _writer(self, path: Path, first_ids: tuple[int, int]) -> PublishingWriter:
        writer = PublishingWriter(path, publish=self._outlet, force=True, compression=self.compression,
                                  first_ids=first_ids)
        self._writers.append(writer)
        return writer

    def _outlet(self, topic: str, message_type: Any) -> Callable[[bytes, int], None] | None:
        return self.server.outlet(topic, message_type) if self.server is not None else None

    # ------------------------------------------------------------------ frames as they arrive
    def _read(self) -> list[SourceMessage | SourceProblem]:
        """New events of the source, each other channel's messages published at once, problems said."""
        events = self.source.poll()
        for event in events:
            self._queue.append(event)
            if isinstance(event, SourceProblem):
                continue
            if event.frame is not None:
                self.board.seen += 1
                self._frames_waiting += 1
            elif event.channel.topic == topics.TRUTH and self.config.solve is not None:
                self._truth_seen = max(self._truth_seen, event.log_time)
                self._truth[event.log_time] = _true_attitude(event)
            outlet = self._source_outlet(event)
            if outlet is not None:
                outlet(bytes(event.data), event.log_time)
        if not events:
            time.sleep(0.0005)
        return events

    def _source_outlet(self, event: SourceMessage) -> Callable[[bytes, int], None] | None:
        if self.server is None:
            return None
        topic = event.channel.topic
        if topic not in self._outlets:
            from starlog.codecs.schemas import MessageType

            schema = event.schema
            self._outlets[topic] = self.server.outlet(topic, MessageType(
                schema.name if schema else "", schema.encoding if schema else "", bytes(schema.data) if schema else b"",
                event.channel.message_encoding))
        return self._outlets[topic]

    def _follow(self) -> None:
        """Process frames as they arrive until the source ends or the run is stopped."""
        next_status = time.monotonic() + 1.0
        while True:
            if self._stop_now.is_set() and self._queue:
                self._drop_waiting("the run was stopped before it was processed")
            stopping = self._stop.is_set() or self.source.ended
            if not stopping and self._waiting() < _READ_AHEAD:
                self._read()
            elif stopping and isinstance(self.source, Camera) and not self.source.ended:
                self.source.stop()
                self._read()
            busy = self._dispatch() | self._collect()
            if not busy and not self._queue and not self._inflight and stopping and \
                    (self.source.ended or not isinstance(self.source, Camera)):
                break
            if not busy and self._inflight:
                self._inflight[0][1].wait(0.001)
            now = time.monotonic()
            for writer in self._writers:
                writer.tick(now)
            if now >= next_status:
                next_status = now + 1.0
                self._status("live")
        self.result.end_reason = self.source.end_reason if self.source.ended else "stopped (Ctrl-C or SIGTERM)"
        self.say(f"source ended: {self.result.end_reason}; closing the layers")

    def _waiting(self) -> int:
        return self._frames_waiting

    def _dispatch(self) -> bool:
        """Hand the frames at the head of the queue to the centroid stage (up to the frames in flight allowed);
        whether any event was taken."""
        assert self.centroid is not None
        took = False
        while self._queue and len(self._inflight) < self._limit:
            event = self._queue[0]
            if isinstance(event, SourceMessage) and event.frame is not None and not self._ready(event):
                break
            self._queue.popleft()
            took = True
            if isinstance(event, SourceProblem):
                self.say(f"source: {event.what}")
                self.board.problems.append(event.what)
                for frame in event.frames:
                    self._skip(frame, event.log_time, event.what)
            elif event.frame is not None:
                self._frames_waiting -= 1
                self._inflight.append((event, self.centroid.submit(event)))
        return took

    def _collect(self) -> bool:
        """Complete the frames measured, in order; whether any was."""
        done = False
        while self._inflight and self._inflight[0][1].done():
            message, future = self._inflight.popleft()
            self._frame(message, future.result())
            done = True
        return done

    def _ready(self, frame: SourceMessage) -> bool:
        """Whether a frame can be processed: the solve stage needs its true attitude when the source has one."""
        return (self.solve is None or self._truth_seen < 0 or self._truth_seen >= frame.log_time
                or self.source.ended or self._stop.is_set())

    def _frame(self, message: SourceMessage, result: Any) -> None:
        """A measured frame: its centroid messages written, tracked, solved."""
        assert self.centroid is not None and message.frame is not None
        encoded = self.centroid.write(message.frame, result)
        if isinstance(encoded, SkippedFrame):
            self.board.skip(message.frame, message.log_time, encoded.reason)
            self.say(f"frame {message.frame} skipped: {encoded.reason}")
            return
        wanted = {t.topic for t in self.tracks} | set(self.solve.topics if self.solve is not None else ())
        rows = {}
        for method, data in zip(self.centroid.parameters.methods, encoded.centroids, strict=True):
            topic = topics.centroid_topic(method.value)
            if topic in wanted:
                rows[topic] = centroid_rows(data)
        for track in self.tracks:
            track.frame(message.frame, message.log_time, rows[track.topic])
        if self.solve is not None:
            self.solve.frame(message.frame, message.log_time, rows, self._truth.pop(message.log_time, None))
        self.board.frame_done(time.monotonic_ns(), message.seen_ns)

    def _skip(self, frame: int, log_time: int | None, reason: str) -> None:
        self.board.skip(frame, log_time, reason)
        if self.centroid is not None and log_time is not None:
            self.centroid.skip(frame, log_time, reason)

    def _drop_waiting(self, reason: str) -> None:
        """Every frame still waiting, listed as skipped (the second Ctrl-C)."""
        dropped = 0
        while self._queue:
            event = self._queue.popleft()
            if isinstance(event, SourceMessage) and event.frame is not None:
                self._skip(event.frame, event.log_time, reason)
                self._frames_waiting -= 1
                dropped += 1
        self.say(f"stopped at once: {dropped} frames waiting listed as skipped")

    def _status(self, state: str) -> None:
        waiting = [e for e in self._queue if isinstance(e, SourceMessage) and e.frame is not None]
        now = time.monotonic_ns()
        was_behind = self.board.behind
        record = self.board.record(now, len(waiting), waiting[0].seen_ns if waiting else None, state)
        warning = None
        if record["behind"]:
            warning = (f"behind the source: {record['frames_waiting']} frames waiting, the oldest for "
                       f"{(now - waiting[0].seen_ns) * 1e-9:.1f} s; latency {record['latency_ms_median']:.1f} ms")
            self.say(warning)
        elif was_behind and state == "live":
            self.say("caught up with the source")
        if self.server is not None:
            self.server.status(record, time.time_ns(), warning)

    # ------------------------------------------------------------------ the end
    def _close(self) -> None:
        """The base completed, the live layers closed on it, the remaining stages run (module docstring)."""
        self._status("finishing")
        base = self.source.finish(stopped=self._stop.is_set())
        self.result.base = base
        self.say(f"base: {base}")
        config, skipped = fit_to_log(base, self.config)
        for shortfall in skipped:
            self.say(f"skipped, log too short: compensate {shortfall.describe()}")
        keywords = {"workers": self.workers, "compression": self.compression, "show_progress": self.show_progress}
        steps = stage_steps(config, **keywords)
        below = layer_paths(self.output, [name for name, _ in steps])[0]
        self._closed(*steps[0], base, below)
        if tracks_trusted(config.track):  # decided on the centroid layer, as run decides it
            track, self.result.trusted = resolve_trusted(config.track or {}, below)
            self.say(f"trusted: {self.result.trusted['method']} ({self.result.trusted['reason']})")
            config = replace(config, track=track)
            steps = stage_steps(config, **keywords)
        for (name, step), path in zip(steps[1:], layer_paths(self.output, [name for name, _ in steps])[1:],
                                      strict=True):
            self._closed(name, step, below, path)
            below = path
        for track in self.tracks:  # a method tracked as "trusted" that the evidence did not name
            self._abandon(track.out.writer)
        self.result.status = self.board.to_dict()

    def _closed(self, name: str, step: Any, below: Path, path: Path) -> None:
        """One stage's layer written (:meth:`_close_stage`) and added to the result."""
        report = self._close_stage(name, step, below, path)
        self.result.layers.append(path)
        self.result.stages.append((name, report))

    def _close_stage(self, name: str, step: Any, below: Path, path: Path) -> dict[str, Any]:
        """One stage's layer: a live one closed on ``below``, or the stage run on it as ``run`` runs it."""
        assert self.centroid is not None
        if name == "centroid":
            writer = self.centroid.layer.out.writer
            assert isinstance(writer, PublishingWriter)
            if writer.path != path:
                raise InvalidParameterError(f"the centroid layer was written as {writer.path}, not {path}.")
            try:
                self.centroid.finish(writer, below, [], [(LIVE_METADATA, self._live_record())])
            except InvalidInputError as err:  # the base's ids grew into the layer's: its messages go to a new layer
                self.say(f"{err} Writing its messages again on {below}.")
                relayer(writer.close(), below, path, stage="centroid", parameters=self.centroid.provenance,
                        metadata=[], compression=self.compression)
            self._writers.remove(writer)
            return self.centroid.summary.to_dict()
        track = next((t for t in self.tracks if name == f"track {t.method}"), None)
        if track is not None:
            self._abandon(track.out.writer)
            why = (self.result.trusted or {}).get("method") == track.method
            track.selected_by = self.result.trusted if why else None
            return track.finish(below, path, self.compression).to_dict() | (
                {"selected_by": self.result.trusted} if why else {})
        if name == "solve" and self.solve is not None:
            writer = self.solve.out.writer
            provisional = writer.close()
            self._writers.remove(writer)  # type: ignore[arg-type]
            return self.solve.finish(provisional, below, path, self.compression)
        self.say(f"running {name} on the finished log")
        return step(below, path)

    def _abandon(self, writer: Any) -> None:
        writer.abort()
        if writer in self._writers:
            self._writers.remove(writer)

    def _live_record(self) -> dict[str, str]:
        status = self.board.to_dict()
        return {"source": self.source.description, "end": self.source.end_reason or "stopped",
                "frames_seen": str(status["frames_seen"]), "frames_done": str(status["frames_done"]),
                "skipped": json.dumps(status["skipped"]), "problems": json.dumps(status["problems"]),
                "latency_ms": json.dumps({k: (None if isinstance(v, float) and math.isnan(v) else v)
                                          for k, v in status["latency"].items()})}

    def _abort(self) -> None:
        """Something failed: every live file is discarded (the base the source records too)."""
        for writer in self._writers:
            writer.abort()
        for track in self.tracks:
            track.close()
        self.source.close()


def _names(value: Any) -> list[str]:
    return [value] if isinstance(value, str) else list(value)


def _true_attitude(event: SourceMessage) -> Any:
    from starlog.codecs.json_messages import decode_json
    from starlog.stages.solve import true_attitude

    return true_attitude(decode_json(event.data))


@contextmanager
def _stop_signals(stop: threading.Event, stop_now: threading.Event) -> Iterator[None]:
    """SIGINT and SIGTERM end the run gracefully (``stop``); a second SIGINT drops what waits (``stop_now``)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum: int, frame: Any) -> None:
        if stop.is_set() and signum == signal.SIGINT:
            stop_now.set()
        stop.set()

    before = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for s, previous in before.items():
            signal.signal(s, previous)


