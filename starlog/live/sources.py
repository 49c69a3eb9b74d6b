"""Where ``starlog live`` gets its frames: a log another program is writing, a folder a camera fills, a camera.

Every source gives the same events, in arrival order: :class:`SourceMessage` (a message of the log
the layers will be written on: the frames, and any other channel the source records) and
:class:`SourceProblem` (what could not be used, in one line). Each frame carries its index in the
image channel and whether it starts a *block*: the centroid stage cuts a log into blocks of whole
chunks of at most ``acquire_every`` frames, each starting with a full search
(:func:`starlog.replay.blocks.channel_blocks`), and :class:`BlockCutter` cuts the chunks as they
arrive by the same rule, so that live and a replay of the finished log search the same frames.

* :class:`FollowedLog` — an MCAP file being written (:class:`~starlog.live.follow.McapFollower`); it
  is the base of the layers once complete. Stopped before its footer (Ctrl-C, or a writer that
  stalls), the part read becomes a complete log of its own (:mod:`starlog.live.snapshot`).
* :class:`WatchedFolder` and :class:`Camera` — frames that starlog records itself into the base
  (:class:`BaseRecorder`: ``/camera/image`` and ``/camera/frame``, as ``ingest`` writes them), one
  chunk per frame, so every frame reaches the disk at once and the blocks are ``acquire_every`` frames.
"""

from __future__ import annotations

import os
import queue
import threading
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
from mcap.records import Channel, Schema

from starlog.version import __version__
from starlog.errors import ImageFolderError, InvalidParameterError, LogError
from starlog.codecs import encode_json, encode_raw_image, json_message_type, protobuf_message_type
from starlog import topics
from starlog.codecs.images import choose_image_topic, is_image_schema
from starlog.io.provenance import PROVENANCE_METADATA_NAME, Provenance
from starlog.io.writer import LogWriter
from starlog.live.follow import DamagedChunk, FollowedChunk, FollowedMessage, FollowedMetadata, McapFollower
from starlog.live.snapshot import snapshot_log
from starlog.stages.ingest.sources import IMAGE_SUFFIXES, luma, natural_key, read_image

__all__ = ["BaseRecorder", "BlockCutter", "Camera", "FollowedLog", "Source", "SourceMessage", "SourceProblem",
           "WatchedFolder"]


@dataclass
class SourceMessage:
    """A message of the base log, when it was seen (monotonic ns); a frame has its index in the image channel
    and whether it starts a block."""

    schema: Schema | None
    channel: Channel
    log_time: int
    data: bytes
    seen_ns: int
    frame: int | None = None
    block_start: bool = False


@dataclass
class SourceProblem:
    """Something of the source that no stage will see, in one line, and the frames it held when known."""

    what: str
    log_time: int | None = None
    frames: list[int] = field(default_factory=list)


Event = SourceMessage | SourceProblem


class BlockCutter:
    """The centroid stage's blocks, cut as the image channel's chunks arrive: a block is whole chunks holding at
    most ``per_block`` frames (more only when one chunk holds more), the next starting once it has them."""

    def __init__(self, per_block: int) -> None:
        self.per_block = per_block
        self._count = 0
        self._next_starts = True
        self.last_end: int | None = None

    def chunk(self, frames: int, start: int, end: int) -> bool:
        """Whether the first of a chunk's ``frames`` starts a block."""
        if frames == 0:
            return False
        starts = self._next_starts or self._count + frames > self.per_block
        if starts:
            self._count = 0
        self._next_starts = False
        self._count += frames
        if self._count >= self.per_block:
            self._next_starts = True
        self.last_end = end
        return starts


class Source:
    """What every source gives: :meth:`poll` for new events, whether it has ended and why, and :meth:`finish`,
    the complete base log of the layers."""

    description = ""
    ended = False
    end_reason = ""

    def poll(self) -> list[Event]:
        raise NotImplementedError

    def metadata(self) -> list[tuple[str, dict[str, str]]]:
        """The metadata records of the base seen so far (the simulator's provenance)."""
        return []

    def next_ids(self) -> tuple[int, int]:
        """The schema and channel ids after the base's (as far as it is written)."""
        return 1, 1

    def finish(self, *, stopped: bool) -> Path:
        """The base log, complete: the frames handed over and nothing after them."""
        raise NotImplementedError

    def close(self) -> None:
        """Release what the source holds (files, threads); the base stays."""


# ---------------------------------------------------------------- a log another program writes
class FollowedLog(Source):
    """An MCAP file another program is writing, followed until its footer (module docstring).

    ``idle_timeout``: seconds without growth after which the source has ended (its writer is gone);
    ``snapshot``: where the part read goes when the file is not complete at the end.
    """

    def __init__(self, path: Path, *, image_topic: str | None, per_block: int, idle_timeout: float,
                 snapshot: Path, wait: float = 0.0) -> None:
        self.path = path
        self.description = f"log {path} (followed as it is written)"
        self.image_topic = image_topic
        self.idle_timeout = idle_timeout
        self.snapshot = snapshot
        self.cutter = BlockCutter(per_block)
        self._metadata: list[tuple[str, dict[str, str]]] = []
        self._frames = 0
        self._image: int | None = None
        self._serial = False
        self._damaged: set[int] = set()
        self.follower = _open_follower(path, wait)

    def metadata(self) -> list[tuple[str, dict[str, str]]]:
        return list(self._metadata)

    def next_ids(self) -> tuple[int, int]:
        return max(self.follower.schemas, default=0) + 1, max(self.follower.channels, default=0) + 1

    def poll(self) -> list[Event]:
        if self.ended:
            return []
        try:
            events = self.follower.poll()
        except LogError as err:
            self.ended, self.end_reason = True, f"the log cannot be followed further: {err.reason}"
            return [SourceProblem(self.end_reason)]
        out: list[Event] = []
        for event in events:
            out.extend(self._events(event))
        if self.follower.finished:
            self.ended, self.end_reason = True, "the log is complete (its footer was written)"
        elif not events and time.monotonic() - self.follower.stalled_since > self.idle_timeout:
            self.ended = True
            cut = self.follower.pending()
            self.end_reason = (f"the log stopped growing {self.idle_timeout:g} s ago without its footer"
                               + (f", {cut} bytes of an unfinished record at its end" if cut else "")
                               + ("" if self.path.exists() else "; its file was removed"))
        return out

    def _events(self, event: Any) -> list[Event]:
        now = time.monotonic_ns()
        if isinstance(event, FollowedMetadata):
            self._metadata.append((event.name, event.metadata))
            return []
        if isinstance(event, DamagedChunk):
            self._damaged.add(event.offset)
            return [SourceProblem(f"the chunk at offset {event.offset} (log_time {event.start}..{event.end}) is "
                                  f"damaged and skipped: {event.reason}", event.start)]
        if isinstance(event, FollowedMessage):
            if self._is_image(event.channel) and not self._serial:
                self._serial = True
                return [self._message(event, now, block_start=self._frames == 0),
                        SourceProblem("frames written outside chunks: a replay reads this log as one block (its "
                                      "full searches may fall on other frames than live's)")]
            return [self._message(event, now, block_start=self._frames == 0)]
        assert isinstance(event, FollowedChunk)
        images = [m for m in event.messages if self._is_image(m.channel)]
        out: list[Event] = []
        if images and self.cutter.last_end is not None and event.start <= self.cutter.last_end:
            out.append(SourceProblem(f"the chunk at offset {event.offset} overlaps the one before in time: a replay "
                                     "reads this log as one block (its full searches may fall on other frames)"))
        starts = self.cutter.chunk(len(images), event.start, event.end) and not self._serial
        first = images[0] if images else None
        return out + [self._message(m, now, block_start=starts and m is first) for m in event.messages]

    def _is_image(self, channel: Channel) -> bool:
        if self._image is None:
            schema = self.follower.schemas.get(channel.schema_id)
            if schema is None or not is_image_schema(schema.name):
                return False
            seen = [_Named(c.topic, self.follower.schemas.get(c.schema_id)) for c in self.follower.channels.values()]
            topic, _ = choose_image_topic(self.path, seen, self.image_topic)
            self._image = next(c.id for c in self.follower.channels.values() if c.topic == topic)
        return channel.id == self._image

    def _message(self, event: FollowedMessage, now: int, *, block_start: bool) -> SourceMessage:
        message = event.message
        frame = None
        if self._is_image(event.channel):
            frame, self._frames = self._frames, self._frames + 1
        return SourceMessage(event.schema, event.channel, message.log_time, message.data, now, frame, block_start)

    def finish(self, *, stopped: bool) -> Path:
        if self.follower.finished:
            return self.path
        return snapshot_log(self.follower.file, self.follower.position, self.snapshot,
                            damaged=frozenset(self._damaged))

    def close(self) -> None:
        self.follower.close()


@dataclass(frozen=True)
class _Named:
    """A channel as :func:`~starlog.codecs.images.choose_image_topic` reads it."""

    topic: str
    schema: Schema | None

    @property
    def schema_name(self) -> str:
        return self.schema.name if self.schema is not None else ""


def _open_follower(path: Path, wait: float) -> McapFollower:
    """The follower of ``path``, waiting up to ``wait`` seconds for the file to appear."""
    deadline = time.monotonic() + wait
    while not path.exists():
        if time.monotonic() > deadline:
            raise InvalidParameterError(f"{path} does not exist (waited {wait:g} s for it to appear).")
        time.sleep(0.05)
    return McapFollower(path)


# ---------------------------------------------------------------- the base starlog records itself
class BaseRecorder:
    """The base log of a folder or camera source: each frame as ``foxglove.RawImage`` on ``/camera/image`` and
    its ``starlog.FrameInfo`` on ``/camera/frame``, flushed as it is written (one chunk per frame and channel)."""

    def __init__(self, path: Path, *, force: bool, compression: str, parameters: dict[str, Any]) -> None:
        self.path = path
        self.parameters = parameters
        self.writer = LogWriter(path, force=force, compression=compression)
        self._image_type = protobuf_message_type("foxglove.RawImage")
        self._info_type = json_message_type("starlog.FrameInfo")
        self.image = self.writer.add_channel(topics.IMAGE, self._image_type, monotonic=True)
        self.info = self.writer.add_channel(topics.FRAME_INFO, self._info_type, monotonic=True)
        self.frames = 0
        self.last_time = -1
        self._shape: tuple[tuple[int, ...], np.dtype[Any]] | None = None

    def check(self, image: npt.NDArray[Any]) -> str | None:
        """Why ``image`` cannot be the next frame (another size or pixel type than the first), or None."""
        if self._shape is not None and (image.shape, image.dtype) != self._shape:
            first = self._shape
            return (f"is {image.shape[1]}x{image.shape[0]} {image.dtype}, but the first frame is "
                    f"{first[0][1]}x{first[0][0]} {first[1]}; every frame of a log must match")
        return None

    def record(self, image: npt.NDArray[Any], log_time: int, source: str) -> tuple[SourceMessage, SourceMessage]:
        """Write one frame (its time made to follow the previous frame's); its two messages."""
        self._shape = self._shape or (image.shape, image.dtype)
        t = max(int(log_time), self.last_time + 1)
        data = encode_raw_image(image, log_time=t)
        encoding = "mono16" if image.dtype == np.uint16 else "mono8"
        info = encode_json({"frame": self.frames, "width": int(image.shape[1]), "height": int(image.shape[0]),
                            "encoding": encoding, "bit_depth": 16 if encoding == "mono16" else 8, "source": source})
        self.writer.write(self.image, log_time=t, data=data)
        self.writer.write(self.info, log_time=t, data=info)
        self.writer.flush()
        now = time.monotonic_ns()
        frame, self.frames, self.last_time = self.frames, self.frames + 1, t
        return (SourceMessage(*self._records(self.image, self._image_type), t, data, now, frame, True),
                SourceMessage(*self._records(self.info, self._info_type), t, info, now))

    def _records(self, channel_id: int, message_type: Any) -> tuple[Schema, Channel]:
        channel = Channel(id=channel_id, topic=self._topic(channel_id), message_encoding=message_type.message_encoding,
                          schema_id=channel_id, metadata={})
        return Schema(id=channel_id, name=message_type.schema_name, encoding=message_type.schema_encoding,
                      data=message_type.schema_data), channel

    def _topic(self, channel_id: int) -> str:
        return topics.IMAGE if channel_id == self.image else topics.FRAME_INFO

    def close(self) -> Path:
        """The base, complete (its provenance: how it was recorded)."""
        record = Provenance(stage="live", version=__version__, parameters=self.parameters,
                            channels=[topics.IMAGE, topics.FRAME_INFO])
        self.writer.add_metadata(PROVENANCE_METADATA_NAME, record.to_metadata())
        return self.writer.close()

    def abort(self) -> None:
        self.writer.abort()


class _Recorded(Source):
    """A source whose frames starlog records into the base (:class:`BaseRecorder`); with one chunk per frame,
    every frame starts a block of the cutter's count."""

    def __init__(self, recorder: BaseRecorder, per_block: int) -> None:
        self.recorder = recorder
        self.per_block = per_block

    def next_ids(self) -> tuple[int, int]:
        last = max(self.recorder.writer.topics.values())  # one schema per channel
        return last + 1, last + 1

    def _record(self, image: npt.NDArray[Any], log_time: int, name: str) -> list[Event]:
        problem = self.recorder.check(image)
        if problem is not None:
            return [SourceProblem(f"{name} {problem}: left out", log_time)]
        image_message, info = self.recorder.record(image, log_time, name)
        image_message.block_start = image_message.frame is not None and image_message.frame % self.per_block == 0
        return [image_message, info]

    def finish(self, *, stopped: bool) -> Path:
        return self.recorder.close()

    def close(self) -> None:
        self.recorder.abort()


class WatchedFolder(_Recorded):
    """A folder a camera's software fills with image files (PNG, TIFF, FITS, ... as ``ingest`` reads them): each
    new file once it is whole, in natural name order. A file that does not decode is looked at again while it
    changes; one that stays unreadable for ``settle`` seconds is left out with a line. A frame's time is its
    file's modification time (one ns after the previous frame's when not later), or ``START + n / fps``."""

    def __init__(self, folder: Path, recorder: BaseRecorder, *, per_block: int, idle_timeout: float | None,
                 fps: float | None = None, start_ns: int = 0, settle: float = 0.5) -> None:
        super().__init__(recorder, per_block)
        if not folder.is_dir():
            raise InvalidParameterError(f"{folder} is not a folder.")
        self.folder = folder
        self.description = f"folder {folder} (each new image file)"
        self.idle_timeout, self.fps, self.start_ns, self.settle = idle_timeout, fps, start_ns, settle
        self._done: set[str] = set()
        self._waiting: dict[str, tuple[tuple[int, int], float]] = {}  # name -> ((size, mtime), since)
        self._last_new = time.monotonic()

    def poll(self) -> list[Event]:
        if self.ended:
            return []
        names = sorted((e.name for e in os.scandir(self.folder) if e.is_file() and e.name not in self._done
                        and Path(e.name).suffix.lower() in IMAGE_SUFFIXES), key=natural_key)
        out: list[Event] = []
        for name in names[:8]:
            events = self._try(self.folder / name)
            if events is None:
                break  # not whole yet: the files after it wait for it, in name order
            out.extend(events)
        if out:
            self._last_new = time.monotonic()
        elif self.idle_timeout is not None and time.monotonic() - self._last_new > self.idle_timeout:
            self.ended, self.end_reason = True, f"no new file for {self.idle_timeout:g} s"
        return out

    def _try(self, path: Path) -> list[Event] | None:
        """The file's events once it is whole and read (or given up); None while it may still be written."""
        try:
            info = path.stat()
        except OSError:  # gone (renamed by its writer): the listing after will say
            return []
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                image = read_image(path)
        except (ImageFolderError, OSError) as err:
            state = (info.st_size, info.st_mtime_ns)
            seen = self._waiting.get(path.name)
            if seen is None or seen[0] != state:
                self._waiting[path.name] = (state, time.monotonic())
                return None
            if time.monotonic() - seen[1] < self.settle:
                return None
            self._done.add(path.name)
            reason = err.reason if isinstance(err, ImageFolderError) else str(err)
            return [SourceProblem(f"{path.name} cannot be read ({reason}): left out")]
        self._done.add(path.name)
        self._waiting.pop(path.name, None)
        t = (self.start_ns + round(self.recorder.frames * 1e9 / self.fps)) if self.fps else info.st_mtime_ns
        return self._record(image, t, path.name)


class Camera(_Recorded):
    """A camera through OpenCV (a device number for UVC/V4L2, or a stream URL or video file), read on a thread
    of its own so that no frame waits for the processing; a frame's time is the clock's when it was read.

    Frames wait in memory for the processing up to ``max_waiting_bytes``; past that, a frame is still recorded
    in the base but not processed live, and is reported as skipped (a replay of the base processes it)."""

    def __init__(self, spec: str, recorder: BaseRecorder, *, per_block: int, max_waiting_bytes: int) -> None:
        super().__init__(recorder, per_block)
        import cv2

        self.spec = spec
        self.description = f"camera {spec} (OpenCV)"
        self.capture = cv2.VideoCapture(int(spec) if spec.isdigit() else spec)
        if not self.capture.isOpened():
            self.capture.release()
            raise InvalidParameterError(f"the camera {spec!r} cannot be opened by OpenCV (no such device, or a "
                                        "stream it cannot read).")
        self.max_waiting_bytes = max_waiting_bytes
        self._queue: queue.Queue[list[Event] | None] = queue.Queue()
        self._waiting = 0
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._capture, name="starlog-camera", daemon=True)
        self._thread.start()

    def _capture(self) -> None:
        try:
            while not self._stop.is_set():
                ok, image = self.capture.read()
                if not ok or image is None:
                    break
                t = time.time_ns()
                events = self._record(_mono(image), t, f"{self.spec} frame {self.recorder.frames}")
                size = sum(len(e.data) for e in events if isinstance(e, SourceMessage))
                with self._lock:
                    if self._waiting + size > self.max_waiting_bytes:
                        frames = [e.frame for e in events if isinstance(e, SourceMessage) and e.frame is not None]
                        events = [SourceProblem(f"processing fell behind ({self._waiting >> 20} MiB of frames "
                                                "waiting): frame recorded, not processed live", t, frames)]
                    else:
                        self._waiting += size
                self._queue.put(events)
        except Exception as err:  # noqa: BLE001 - whatever stops the camera ends the source with its reason
            self._queue.put([SourceProblem(f"the camera stopped: {type(err).__name__}: {err}")])
        self._queue.put(None)

    def poll(self) -> list[Event]:
        out: list[Event] = []
        try:
            while len(out) < 64:
                item = self._queue.get(timeout=0.002 if not out else 0)
                if item is None:
                    self.ended = True
                    self.end_reason = self.end_reason or "the camera delivers no more frames"
                    break
                out.extend(item)
        except queue.Empty:
            pass
        with self._lock:
            self._waiting -= sum(len(e.data) for e in out if isinstance(e, SourceMessage))
        return out

    def stop(self) -> None:
        """Stop reading frames (the frames read are still handed over)."""
        self._stop.set()

    def finish(self, *, stopped: bool) -> Path:
        self._stop.set()
        self._thread.join()
        self.capture.release()
        return super().finish(stopped=stopped)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self.capture.release()
        super().close()


def _mono(image: npt.NDArray[Any]) -> npt.NDArray[Any]:
    """A camera frame as a 2-D mono array (grey delivered as three equal channels taken as one; colour as luma)."""
    if image.ndim == 2:
        return image
    if image.shape[2] == 1 or (np.array_equal(image[..., 0], image[..., 1])
                               and np.array_equal(image[..., 1], image[..., 2])):
        return np.ascontiguousarray(image[..., 0])
    return luma(image[..., 2::-1])

