"""The centroid stage's per-frame work for ``starlog live``, in this process or in worker processes.

:func:`extract_frame` decodes one frame's image message and measures it with the stage's
:class:`~starlog.stages.centroid.frames.FrameExtractor` — a new block's extractor when the frame starts
a block (tracking mode's :class:`~starlog.stages.centroid.frames.TrackedFrames` keeps its state within a
block). :class:`CentroidWorkers` runs it in worker processes that never outlive this one
(:func:`~starlog.replay.pool.guarded_process`), each block on one worker (its state stays there), so
a worker measures a frame while this process tracks, writes and publishes the frame before it; with
several workers, blocks go round-robin. A worker is fed through a pipe of its own, the frame's bytes as
they are (no executor threads in this process to compete with its own work). The messages are those of
the stage either way: the same function, the same extractor, the same blocks.
"""

from __future__ import annotations

import multiprocessing
from multiprocessing.connection import Connection
from typing import Any

from mcap.records import Schema

from starlog.errors import InvalidInputError, StarlogError
from starlog.io.frames import SkippedFrame, decode_image_message, reuse_frame_buffers
from starlog.stages.centroid.frames import FrameExtractor, FrameMessages, opencv_threads
from starlog.replay.pool import guarded_process

__all__ = ["CentroidWorkers", "Done", "FrameResult", "Handle", "extract_frame"]

#: ``(messages or the frame skipped, the image's shape and pixel type)``.
FrameResult = tuple[FrameMessages | SkippedFrame, tuple[int, ...], str]


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


class Done:
    """A result at hand (what a worker's pending result is once read)."""

    def __init__(self, result: FrameResult) -> None:
        self._result = result

    def done(self) -> bool:
        return True

    def wait(self, timeout: float) -> bool:
        return True

    def result(self) -> FrameResult:
        return self._result


class _Pending:
    """A frame sent to a worker: its result is the worker's next answer (a worker answers in the order it is sent)."""

    def __init__(self, connection: Connection, process: Any) -> None:
        self._connection = connection
        self._process = process

    def done(self) -> bool:
        return self._connection.poll(0)

    def wait(self, timeout: float) -> bool:
        return self._connection.poll(timeout)

    def result(self) -> FrameResult:
        try:
            answer = self._connection.recv()
        except (EOFError, OSError) as err:
            raise StarlogError(f"the worker process measuring frames ended unexpectedly (exit status "
                               f"{self._process.exitcode}).") from err
        if isinstance(answer, BaseException):
            raise answer
        return answer  # type: ignore[no-any-return]


def _serve(connection: Connection) -> None:
    """A worker: frames from ``connection`` measured, each answered in order, until told to stop (None)."""
    reuse_frame_buffers()
    state: dict[str, Any] = {}
    with opencv_threads(1):
        while True:
            header = connection.recv()
            if header is None:
                return
            data = connection.recv_bytes()
            try:
                connection.send(extract_frame(state, *header[:6], data))
            except Exception as err:  # noqa: BLE001 - handed to the owner, which raises it
                connection.send(err)


Handle = Done | _Pending


class CentroidWorkers:
    """Worker processes measuring frames (module docstring); :meth:`close` ends them (and so does this process
    ending, however it ends)."""

    def __init__(self, extract: FrameExtractor, workers: int) -> None:
        self.extract = extract
        self._connections: list[Connection] = []
        self._processes: list[Any] = []
        try:
            for _ in range(workers):
                mine, theirs = multiprocessing.Pipe()
                self._processes.append(guarded_process(_serve, (theirs,), preload=["starlog.stages.centroid"]))
                theirs.close()
                self._connections.append(mine)
        except BaseException:
            self.close(wait=False)
            raise
        self._given = [False] * workers
        self._block = -1
        self._frames = 0

    def submit(self, block_start: bool, frame: int, log_time: int, schema: Schema | None, encoding: str,
               data: bytes) -> _Pending:
        """Send one frame to the worker of its block (tracking) or to the next worker (full mode)."""
        if block_start or self._block < 0:
            self._block += 1
        tracking = self.extract.tracking is not None
        k = (self._block if tracking else self._frames) % len(self._connections)
        self._frames += 1
        extract = None if self._given[k] else self.extract
        self._given[k] = True
        connection = self._connections[k]
        connection.send((extract, block_start or not tracking, frame, log_time, schema, encoding))
        connection.send_bytes(data)
        return _Pending(connection, self._processes[k])

    def close(self, *, wait: bool = True) -> None:
        """Stop the workers: after the frames sent (``wait``), or at once."""
        for connection in self._connections:
            try:
                if wait:
                    connection.send(None)
                connection.close()
            except OSError:
                pass
        for process in self._processes:
            process.join(timeout=5 if wait else 0.1)
            if process.is_alive():
                process.terminate()
                process.join(timeout=2)

