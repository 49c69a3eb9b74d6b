"""Frames of an image channel, in time order, each checked before a stage sees it.

A frame's time is its message's ``log_time`` (the time the recorder received it); the stamp
inside the message (a ROS header, a Foxglove ``timestamp``) is kept beside it, so derived
messages such as annotations can carry the stamp Foxglove pairs them by.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt
from mcap.records import Channel, Message, Schema

from starlog.errors import InvalidInputError, InvalidMessageError, LogError, MessageDecodeError
from starlog.codecs.foreign_decoders import schema_key
from starlog.codecs.images import DecodedImage, image_decoder

__all__ = ["Frame", "SkippedFrame", "cached_image_decoder", "decode_image_message", "iter_frames", "reuse_frame_buffers",
           "stamp_disagreement"]

class MessageSource(Protocol):
    """What frame reading needs of a log (:class:`~starlog.io.reader.LogReader` is one)."""

    path: Path

    def raw_messages(self, topics: Iterable[str], *, start: int | None = None, end: int | None = None,
                     views: bool = False) -> Iterator[tuple[Schema | None, Channel, Message]]: ...

    def add_note(self, note: str) -> None: ...


_IMAGE_DECODERS: dict[tuple[str, str, str, bytes], Callable[[bytes | memoryview], DecodedImage] | None] = {}


@dataclass(frozen=True)
class Frame:
    """One frame: its index in the channel, ``log_time``, 2-D mono ``image``, the message's own ``stamp``
    (ns; None when unset) and ``frame_id``."""

    index: int
    log_time: int
    image: npt.NDArray[Any]
    stamp: int | None = None
    frame_id: str = ""


@dataclass(frozen=True)
class SkippedFrame:
    """A frame left out under ``skip_bad``: its index, ``log_time`` and why."""

    index: int
    log_time: int
    reason: str

    def to_dict(self) -> dict[str, Any]:
        return {"index": self.index, "log_time": self.log_time, "reason": self.reason}


def cached_image_decoder(schema: Schema | None, message_encoding: str
                         ) -> Callable[[bytes | memoryview], DecodedImage] | None:
    """:func:`~starlog.codecs.images.image_decoder`, built once per schema (process-wide).

    Raises :class:`InvalidInputError` when the schema itself cannot be parsed.
    """
    key = schema_key(schema, message_encoding)
    if key not in _IMAGE_DECODERS:
        try:
            _IMAGE_DECODERS[key] = image_decoder(schema, message_encoding)
        except Exception as err:  # a ROS/protobuf schema text the support libraries cannot parse
            raise InvalidInputError(f"its schema {schema.name if schema else ''!r} cannot be parsed "
                                    f"({type(err).__name__}: {err})") from err
    return _IMAGE_DECODERS[key]


def decode_image_message(schema: Schema | None, message_encoding: str, data: bytes | memoryview
                         ) -> DecodedImage | None:
    """Decode one message of an image channel (None when the schema is no image type starlog reads).

    Raises :class:`InvalidInputError` when the bytes (or the schema) do not decode.
    """
    decode = cached_image_decoder(schema, message_encoding)
    return None if decode is None else decode(data)


_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3


@functools.cache
def reuse_frame_buffers() -> None:
    """Let the C allocator (glibc) recycle the frame-sized buffers each frame allocates and frees.

    :func:`iter_frames` calls it before its first frame: chunks are read and decompressed into memory the
    allocator takes back and hands out again for the next chunk, so a frame costs its copy or decompression
    and nothing more.

    By default every block above ~128 KiB is mapped from the system on allocation and returned
    on release, so each frame's images (decoded frame, float copy, filtered image, maps, masks)
    arrive as fresh zero pages: thousands of page faults a frame, a third of detection's time
    at 1024x1024. Blocks below 64 MiB now come from the heap and stay there for the next
    frame (the working set, hence the peak memory, does not grow with the log). Elsewhere than
    glibc nothing changes. The setting is process-wide and kept.
    """
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return
    mallopt(_M_MMAP_THRESHOLD, 64 << 20)
    mallopt(_M_TRIM_THRESHOLD, 256 << 20)


def iter_frames(log: MessageSource, topic: str, *, start: int | None = None, end: int | None = None,
                first_index: int = 0, on_bad: Callable[[SkippedFrame], None] | None = None) -> Iterator[Frame]:
    """Every frame of ``topic`` with ``start <= log_time < end``, in time order, numbered from ``first_index``
    (a topic of several image channels: all their frames, each decoded by its own channel's schema).

    A frame that does not decode, is not 2-D, differs in size or pixel type from the first, or
    does not come strictly after the previous one raises :class:`MessageDecodeError` /
    :class:`InvalidMessageError` naming it; with ``on_bad`` it is handed to ``on_bad`` instead
    and left out (its index stays taken, so frame numbers do not depend on what was skipped).
    An image may be a read-only view of the log's bytes (:mod:`starlog.codecs.images`): copy it to write into it.
    """
    reuse_frame_buffers()
    first: tuple[tuple[int, ...], np.dtype[Any], int] | None = None
    last = -1
    index = first_index - 1
    decoders: dict[int, Callable[[bytes | memoryview], DecodedImage] | None] = {}
    for schema, channel, message in log.raw_messages([topic], start=start, end=end, views=True):
        index += 1
        t = message.log_time
        try:
            try:
                if channel.id not in decoders:
                    decoders[channel.id] = cached_image_decoder(schema, channel.message_encoding)
                decode = decoders[channel.id]
                decoded = None if decode is None else decode(message.data)
            except InvalidInputError as err:
                raise MessageDecodeError(log.path, topic, t, str(err)) from err
            if decoded is None or decoded.image.ndim != 2:
                raise InvalidMessageError(log.path, topic, t, "it is not a 2-D image.")
            image = decoded.image
            if first is None:
                first = (image.shape, image.dtype, index)
            elif (image.shape, image.dtype) != first[:2]:
                raise InvalidMessageError(
                    log.path, topic, t,
                    f"frame {index} is {image.shape[1]}x{image.shape[0]} {image.dtype}, but frame {first[2]} is "
                    f"{first[0][1]}x{first[0][0]} {first[1]}; every frame of a log must match.")
            if t <= last:
                raise InvalidMessageError(log.path, topic, t,
                                          f"frame {index} does not come after the previous frame (log_time {last}); "
                                          "frame timestamps must increase strictly.")
        except LogError as err:
            if on_bad is None:
                raise
            on_bad(SkippedFrame(index, t, getattr(err, "reason", str(err))))
            continue
        last = t
        if decoded.note:
            log.add_note(decoded.note)
        yield Frame(index, t, image, decoded.stamp, decoded.frame_id)


def stamp_disagreement(log: MessageSource, topic: str, *, sample: int = 64) -> str | None:
    """A note when the frames' own stamps differ from their ``log_time`` by more than one frame period.

    Looks at the first ``sample`` frames only (``info`` reads no more than that).
    """
    times: list[int] = []
    offsets: list[int] = []
    for schema, channel, message in log.raw_messages([topic], views=True):
        if len(times) >= sample:
            break
        try:
            decoded = decode_image_message(schema, channel.message_encoding, message.data)
        except InvalidInputError:
            continue
        if decoded is None:
            return None
        times.append(message.log_time)
        if decoded.stamp is not None:
            offsets.append(decoded.stamp - message.log_time)
    if len(times) < 2 or not offsets:
        return None
    period = float(np.median(np.diff(times)))
    worst = max(offsets, key=abs)
    if period > 0 and abs(worst) > period:
        return (f"{topic}: header stamps differ from log_time by up to {worst * 1e-9:+.6f} s "
                f"(more than one frame period, {period * 1e-9:.6f} s); starlog times frames by log_time.")
    return None
