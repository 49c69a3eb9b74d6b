"""The ``simulate`` stage: write a simulated star-camera log."""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path
from dataclasses import asdict, dataclass
from typing import Any

from starlog.version import __version__
from starlog.io import LogWriter, Provenance
from starlog.codecs import encode_json, encode_raw_image, json_message_type, protobuf_message_type
from starlog import topics
from starlog.io.writer import FRAME_COMPRESSION
from starlog.attitude.rotation import quaternion_from_matrix, radec_roll
from starlog.io.provenance import PROVENANCE_METADATA_NAME
from starlog.sim import SimulatedFrame, SimulationConfig, Simulator
from starlog.replay.pool import ordered_map, process_pool
from starlog.replay.progress import progress

__all__ = ["SimulationSummary", "simulate_log", "simulation_summary"]


def simulate_log(
    config: SimulationConfig,
    output: str | os.PathLike[str],
    *,
    compression: str = FRAME_COMPRESSION,
    workers: int = 1,
    force: bool = False,
    show_progress: bool = False,
    chunk_per_frame: bool = False,
) -> Path:
    """Render ``config`` into a new log at ``output``.

    Channels: ``/camera/image`` (foxglove.RawImage mono16, ``log_time`` = exposure time),
    ``/camera/frame`` (starlog.FrameInfo) and ``/sim/truth`` (starlog.SimTruth: true positions
    in the pixel-centre convention). The configuration is recorded as provenance. Same
    configuration → identical bytes, whatever ``workers`` is: frames are rendered in worker
    processes (each frame's noise depends only on the seed and its index) and written in order.
    With ``chunk_per_frame`` every frame's messages close their chunks (each channel's chunk holds one
    frame's message), as a camera's log that is read while it is written (``simulate --realtime``).
    """
    simulator = Simulator(config)
    with LogWriter(output, compression=compression, workers=workers, force=force) as log:
        image_ch = log.add_channel(topics.IMAGE, protobuf_message_type("foxglove.RawImage"), monotonic=True)
        info_ch = log.add_channel(topics.FRAME_INFO, json_message_type("starlog.FrameInfo"), monotonic=True)
        truth_ch = log.add_channel(topics.TRUTH, json_message_type("starlog.SimTruth"), monotonic=True)
        frames = _render_parallel(config, workers) if workers > 1 and config.n_frames >= 64 else simulator.frames()
        for frame in progress(frames, total=config.n_frames, description="simulate", enabled=show_progress):
            t = frame.log_time
            log.write(image_ch, log_time=t, data=encode_raw_image(frame.image, log_time=t))
            info = {"frame": frame.index, "width": config.width, "height": config.height, "encoding": "mono16",
                    "bit_depth": config.camera.adc_bits, "source": ""}
            log.write(info_ch, log_time=t, data=encode_json(info))
            log.write(truth_ch, log_time=t, data=encode_json(_truth(config, simulator, frame)))
            if chunk_per_frame:
                log.flush()
        provenance = Provenance(stage="simulate", version=__version__, parameters=config.to_dict(),
                                channels=[topics.IMAGE, topics.FRAME_INFO, topics.TRUTH])
        log.add_metadata(PROVENANCE_METADATA_NAME, provenance.to_metadata())
    return Path(output)


def _truth(config: SimulationConfig, simulator: Simulator, frame: SimulatedFrame) -> dict[str, Any]:
    """The frame's ``/sim/truth`` record: true positions, platform motion, and for a sky field the true attitude
    and each star's catalogue number and magnitude."""
    field = simulator.field
    stars = [
        {"star": i, "x": float(frame.x[i]), "y": float(frame.y[i]), "x_static": float(field.x[i]),
         "y_static": float(field.y[i]), "flux": float(frame.flux[i])}
        for i in range(len(frame.x))
    ]
    if field.catalogue_id is not None and field.magnitude is not None:
        for row, number, magnitude in zip(stars, field.catalogue_id.tolist(), field.magnitude.tolist()):
            row["catalogue_id"], row["magnitude"] = int(number), float(magnitude)
    truth: dict[str, Any] = {"frame": frame.index, "platform_dx": frame.platform_dx,
                             "platform_dy": frame.platform_dy, "stars": stars}
    if config.roll_amplitude_rad:
        truth["platform_roll"] = frame.platform_roll
    if frame.attitude is not None:
        ra, dec, roll = radec_roll(frame.attitude)
        truth["attitude"] = {"quaternion": quaternion_from_matrix(frame.attitude).tolist(), "ra_deg": ra,
                             "dec_deg": dec, "roll_deg": roll}
    return truth


def _render_block(config: SimulationConfig, start: int, stop: int) -> list[SimulatedFrame]:
    """Worker: render frames ``start..stop-1``."""
    return list(Simulator(config).frames(start, stop))


def _render_parallel(config: SimulationConfig, workers: int, block: int = 16) -> Iterator[SimulatedFrame]:
    blocks = ((config, start, min(start + block, config.n_frames)) for start in range(0, config.n_frames, block))
    with process_pool(workers) as pool:
        for frames in ordered_map(pool, _render_block, blocks, window=2 * workers):
            yield from frames


@dataclass(frozen=True)
class SimulationSummary:
    """What ``simulate`` wrote: the log, its frames (count, size, rate) and its stars."""

    output: str
    frames: int
    width: int
    height: int
    fps: float
    stars: int
    catalogue: bool

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    def lines(self) -> list[str]:
        stars = f"{self.stars} catalogue" if self.catalogue else str(self.stars)
        return [f"wrote {self.output}: {self.frames} frames of {self.width}x{self.height} at {self.fps:g} Hz, "
                f"{stars} stars"]


def simulation_summary(config: SimulationConfig, output: str | os.PathLike[str]) -> SimulationSummary:
    """The summary of a log simulated from ``config``."""
    catalogue = config.sky_attitude is not None
    stars = Simulator(config).field.x.size if catalogue else config.n_stars
    return SimulationSummary(str(output), config.n_frames, config.width, config.height, config.fps, int(stars),
                             catalogue)
