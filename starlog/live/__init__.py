"""``starlog live``: ``run``'s stages on a camera's frames while it records, served to Foxglove as they are computed.

The source is a log another program is still writing (followed until its footer), a folder that
camera software fills with image files, or a camera read through OpenCV (:mod:`starlog.live.sources`).
Each frame goes through the centroid, track and solve stages of the ``run`` config as it arrives
(:mod:`starlog.live.stages`, through the stages' own per-frame functions), every message is written to
its layer and published on a Foxglove WebSocket server (:mod:`starlog.live.server`), and when the source
ends the layers are closed on the finished base as the layers ``run`` writes: ``starlog run`` over the
same base with the same config gives the same messages (:mod:`starlog.live.session`).

:func:`live` is the whole command; :func:`simulate_realtime` writes a simulated camera's log at the
camera's rate, to try it without a camera (:mod:`starlog.live.pace`).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

from starlog.errors import InvalidParameterError
from starlog.live.pace import simulate_realtime, write_at_camera_rate
from starlog.live.session import LIVE_METADATA, LiveResult, LiveSession, frames_to_learn
from starlog.pipeline import PipelineConfig

__all__ = ["LIVE_METADATA", "LiveResult", "LiveSession", "base_path", "frames_to_learn", "live", "open_source",
           "simulate_realtime", "write_at_camera_rate"]

#: Seconds a followed log may stop growing before its writer is taken to be gone.
DEFAULT_IDLE_SECONDS = 10.0
#: Camera frames that may wait in memory for the processing.
DEFAULT_WAITING_BYTES = 1 << 30


def base_path(output: Path) -> Path:
    """Where live writes the base it records (a folder or camera source), or the part of a followed log it read
    when that log is not complete at the end: ``OUTPUT.0-base.mcap`` beside the output."""
    return output.with_name(f"{output.stem}.0-base{output.suffix}")


def open_source(source: str | None, output: Path, config: PipelineConfig, *, camera: str | None = None,
                idle_timeout: float | None = None, fps: float | None = None, force: bool = False,
                compression: str = "zstd") -> object:
    """The source ``live`` reads: a camera (``camera``), a folder, or a log (followed; it may appear later)."""
    from starlog.centroiding.tracking import DEFAULT_ACQUIRE_EVERY
    from starlog.live.sources import BaseRecorder, Camera, FollowedLog, WatchedFolder

    table = config.centroid or {}
    per_block = int(table.get("acquire_every") or DEFAULT_ACQUIRE_EVERY)
    base = base_path(output)
    if (camera is None) == (source is None):
        raise InvalidParameterError("give a SOURCE (a log or a folder) or --camera, one of them.")
    if camera is not None or Path(str(source)).is_dir():
        if base.exists() and not force:
            from starlog.errors import OutputExistsError

            raise OutputExistsError(base)
        kind = {"camera": camera} if camera is not None else {"folder": str(source), "fps": fps}
        recorder = BaseRecorder(base, force=force, compression=compression, parameters=kind)
        if camera is not None:
            return Camera(camera, recorder, per_block=per_block, max_waiting_bytes=DEFAULT_WAITING_BYTES)
        return WatchedFolder(Path(str(source)), recorder, per_block=per_block, idle_timeout=idle_timeout, fps=fps)
    timeout = DEFAULT_IDLE_SECONDS if idle_timeout is None else idle_timeout
    return FollowedLog(Path(str(source)), image_topic=table.get("image_topic"), per_block=per_block,
                       idle_timeout=timeout, snapshot=base, wait=timeout)


def live(source: str | os.PathLike[str] | None, output: str | os.PathLike[str], config: PipelineConfig, *,
         camera: str | None = None, host: str = "127.0.0.1", port: int | None = 8765,
         idle_timeout: float | None = None, fps: float | None = None, force: bool = False,
         compression: str = "zstd", workers: int = 1, say: Callable[[str], None] = lambda line: None,
         on_session: Callable[[LiveSession], None] | None = None) -> LiveResult:
    """Run ``config``'s stages on ``source`` as it records (module docstring); ``port`` None: no server;
    ``workers``: processes measuring frames (0: this one; the stages run at the end use every core).

    ``on_session`` is handed the session before it starts (its ``stop()`` ends the run as Ctrl-C does).
    """
    from starlog.live.server import LiveServer

    output = Path(output)
    server = None
    opened: Any = None
    try:
        if port is not None:
            server = LiveServer(host=host, port=port)
            say(f"serving Foxglove at {server.url} (Foxglove: Open connection, Foxglove WebSocket)")
        opened = open_source(None if source is None else str(source), output, config, camera=camera,
                             idle_timeout=idle_timeout, fps=fps, force=force, compression=compression)
        session = LiveSession(opened, output, config, server=server, force=force, compression=compression,
                              workers=os.cpu_count() or 1, frame_workers=workers, say=say)
        if on_session is not None:
            on_session(session)
        return session.run()
    except BaseException:
        if opened is not None:
            opened.close()
        raise
    finally:
        if server is not None:
            server.stop()
