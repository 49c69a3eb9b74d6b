"""Writing a finished log again at its camera's rate, as a camera's recorder would write it.

``starlog simulate --realtime`` renders its frames first (a 512² frame takes longer to render than
a 300 Hz camera takes to expose it) and then hands them to :func:`write_at_camera_rate`, which
copies the log into its output chunk by chunk, each frame's chunks when the frame's ``log_time``
has come (measured from the first frame), flushed to the system at once: a reader following the
output (``starlog live``) sees each frame when a camera would have delivered it. The output is
written under its own name from the start and is a complete log once the last frame is written
(or the writing is stopped: it then ends with the frames written so far). The metadata records
(the simulator's provenance: its camera's gain and read noise) are written before the first
frame, as a recorder that knows its camera would, so a reader learns the camera before the frames.
"""

from __future__ import annotations

import itertools
import os
import threading
import time
from collections.abc import Callable
from pathlib import Path

from mcap.records import MetadataIndex

from starlog.errors import OutputExistsError
from starlog.io.chain import BASE_METADATA_NAME
from starlog.io.mcap_file import McapFile
from starlog.io.output_files import temporary_folder
from starlog.io.writer import LogWriter
from starlog.sim import SimulationConfig
from starlog.stages.simulate import simulate_log

__all__ = ["simulate_realtime", "write_at_camera_rate"]


def simulate_realtime(config: SimulationConfig, output: str | os.PathLike[str], *, compression: str = "zstd",
                      workers: int = 1, force: bool = False, show_progress: bool = False,
                      on_rendered: Callable[[], None] | None = None) -> int:
    """``simulate --realtime``: render ``config`` into a hidden file beside ``output`` (a chunk per frame), then
    write it to ``output`` at the camera's rate (:func:`write_at_camera_rate`); the hidden file is removed
    whatever happens. ``on_rendered`` is called between the two. Returns the frames written."""
    target = Path(output)
    if target.exists() and not force:
        raise OutputExistsError(target)
    with temporary_folder(target) as folder:
        rendered = folder / target.name
        simulate_log(config, rendered, compression=compression, workers=workers, show_progress=show_progress,
                     chunk_per_frame=True)
        if on_rendered is not None:
            on_rendered()
        return write_at_camera_rate(rendered, target, force=force)


def write_at_camera_rate(source: str | os.PathLike[str], output: str | os.PathLike[str], *, force: bool = False,
                         speed: float = 1.0, on_frame: Callable[[int, int], None] | None = None,
                         stop: threading.Event | None = None, max_frames: int | None = None) -> int:
    """Copy the finished log ``source`` into ``output`` at the pace of its frames (module docstring).

    Chunks are copied byte for byte, grouped by their first ``log_time`` (a frame's chunks of every
    channel), each group flushed when its time has come. ``speed`` divides every wait (2: twice the
    camera's rate). ``on_frame(log_time, monotonic_ns)`` is called once a group is flushed. Setting
    ``stop`` (or Ctrl-C), or ``max_frames`` groups written, ends the output after the groups written so far.
    Returns the groups written.
    """
    written = 0
    with McapFile(source) as log, LogWriter(output, force=force, in_place=True, profile=log.profile()) as out:
        for schema in sorted(log.summary.schemas.values(), key=lambda s: s.id):
            out.copy_schema(schema)
        for channel in sorted(log.summary.channels.values(), key=lambda c: c.id):
            out.copy_channel(channel)
        for index in log.metadata_indexes():
            if index.name != BASE_METADATA_NAME:
                offset = out.copy_record(log, index.offset, index.length)
                out.index_metadata(MetadataIndex(offset=offset, length=index.length, name=index.name))
        out.flush()
        chunks = sorted(log.summary.chunk_indexes, key=lambda ci: (ci.message_start_time, ci.chunk_start_offset))
        groups = [list(g) for _, g in itertools.groupby(chunks, key=lambda ci: ci.message_start_time)]
        first = chunks[0].message_start_time if chunks else 0
        begin = time.monotonic_ns()
        try:
            for group in groups[:max_frames]:
                if stop is not None and stop.is_set():
                    break
                start = group[0].message_start_time
                _wait_until(begin + int((start - first) / speed))
                for ci in group:
                    out.copy_chunk(log, ci, log.index_counts(ci))
                out.flush()
                written += 1
                if on_frame is not None:
                    on_frame(start, time.monotonic_ns())
        except KeyboardInterrupt:
            pass  # the camera stopped: the output ends with the frames written
    return written


def _wait_until(deadline_ns: int) -> None:
    """Sleep until the monotonic clock reaches ``deadline_ns`` (at once when it has)."""
    remaining = deadline_ns - time.monotonic_ns()
    if remaining > 0:
        time.sleep(remaining * 1e-9)
