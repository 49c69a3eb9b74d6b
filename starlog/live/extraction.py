"""The centroid stage's per-frame work for ``starlog live``, in this process or in worker processes.

:func:`extract_frame` decodes one frame's image message and measures it with the stage's
:class:`~starlog.stages._centroid_frames.FrameExtractor` — a new block's extractor when the frame starts
a block (tracking mode's :class:`~starlog.stages._centroid_frames.TrackedFrames` keeps its state within a
block). :class:`CentroidWorkers` runs it in worker processes that never outlive this one
(:func:`~starlog.stages._parallel.process_pool`), each block on one worker (its state stays there), so
a worker measures a frame while this process tracks, writes and publishes the frame before it; with
several workers, blocks go round-robin. The messages are those of the stage either way: the same
function, the same extractor, the same blocks.
"""

from __future__ import annotations

from concurrent.futures import Future
from contextlib import ExitStack
from typing import Any

from mcap.records import Schema

from starlog.errors import InvalidInputError
from starlog.io.frames import SkippedFrame, decode_image_message
from starlog.stages._centroid_frames import FrameExtractor, FrameMessages, opencv_threads, reuse_frame_buffers
from starlog.stages._parallel import process_pool

__all__ = ["CentroidWorkers", "FrameResult", "extract_frame"]

#: ``(messages or the frame skipped, the image's shape and pixel type)``.
FrameResult = tuple[FrameMessages | SkippedFrame, tuple[int, ...], str]

_WORKER: dict[str, Any] = {}  # in a worker: the extractor and the block being measured


def extract_frame(state: dict[str, Any], extract: FrameExtractor | None, block_start: bool, frame: int,
                  log_time: int, schema: Schema | None, encoding: str, data: bytes) -> FrameResult:
    """One frame measured (``extract``: the stage's extractor, given once; ``state`` keeps it and the block)."""
    if extract is not None:
        state["extract"] = extract
    if block_start or "block" not in state:
        state["block"] = state["extract"].block()
    try:
        decoded = decode_image_message(schema, encoding, data)
    except InvalidInputError as err:
        return SkippedFrame(frame, log_time, str(err)), (), ""
    if decoded is None or decoded.image.ndim != 2:
        return SkippedFrame(frame, log_time, "it is not a 2-D image."), (), ""
    image = decoded.image
    return state["block"](frame, log_time, image, decoded.stamp), image.shape, str(image.dtype)


def _in_worker(extract: FrameExtractor | None, block_start: bool, frame: int, log_time: int, schema: Schema | None,
               encoding: str, data: bytes) -> FrameResult:
    if "ready" not in _WORKER:
        reuse_frame_buffers()
        opencv_threads(1).__enter__()  # for the worker's life: one core per worker
        _WORKER["ready"] = True
    return extract_frame(_WORKER, extract, block_start, frame, log_time, schema, encoding, data)


class CentroidWorkers:
    """Worker processes measuring frames (module docstring); ``stack`` ends them."""

    def __init__(self, extract: FrameExtractor, workers: int, stack: ExitStack) -> None:
        self.extract = extract
        self.pools = [stack.enter_context(process_pool(1, preload=["starlog.stages.centroid"])) for _ in range(workers)]
        self._given = [False] * workers
        self._block = -1
        self._frames = 0

    def submit(self, block_start: bool, frame: int, log_time: int, schema: Schema | None, encoding: str,
               data: bytes) -> Future[FrameResult]:
        """Measure one frame on the worker of its block (tracking) or the next worker (full mode)."""
        if block_start or self._block < 0:
            self._block += 1
        tracking = self.extract.tracking is not None
        k = (self._block if tracking else self._frames) % len(self.pools)
        self._frames += 1
        extract = None if self._given[k] else self.extract
        self._given[k] = True
        return self.pools[k].submit(_in_worker, extract, block_start or not tracking, frame, log_time, schema,
                                    encoding, data)
