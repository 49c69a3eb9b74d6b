"""``starlog live``: the pipeline on a camera while it records, served to Foxglove (:mod:`starlog.live`)."""

from __future__ import annotations

from pathlib import Path

import click

from starlog.cli.options import CONTEXT, echo_status, json_option, print_json, quiet_option

__all__ = ["live"]


@click.command(context_settings=CONTEXT)
@click.argument("source", required=False, type=click.Path(path_type=Path))
@click.option("-o", "--output", required=True, type=click.Path(path_type=Path),
              help="Output log (.mcap): the last layer; the others beside it, named as `run` names them.")
@click.option("--camera", metavar="DEVICE|URL", help="Read a camera through OpenCV instead of SOURCE: a device "
                                                     "number (0: the first UVC/V4L2 camera) or a stream URL.")
@click.option("--config", "config_path", type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="Pipeline config (TOML), as for `run` [default: the built-in config].")
@click.option("--port", type=click.IntRange(0, 65535), default=8765, show_default=True,
              help="Port of the Foxglove WebSocket server (0: any free port).")
@click.option("--host", default="127.0.0.1", show_default=True,
              help="Address the server listens on (0.0.0.0: every interface; the default is this machine only).")
@click.option("--no-server", is_flag=True, help="Record only: no Foxglove server.")
@click.option("--idle-timeout", type=click.FloatRange(min=0), metavar="SECONDS",
              help="The source has ended when it has not grown for this long [default: 10 s for a log; a folder "
                   "waits for Ctrl-C].")
@click.option("--fps", type=click.FloatRange(min=0, min_open=True),
              help="Folder: time frame n at n / FPS (from 0) instead of its file's modification time.")
@click.option("--workers", type=click.IntRange(0, 64), default=1, show_default=True,
              help="Processes measuring frames, beside this one (which reads, tracks, writes and publishes); 0: "
                   "all in this process. Tracking mode gives each worker whole blocks of frames.")
@click.option("--force", is_flag=True, help="Overwrite the outputs if they exist.")
@click.option("--compression", type=click.Choice(["zstd", "lz4", "none"]), default="zstd", show_default=True,
              help="Chunk compression of the logs written.")
@json_option
@quiet_option
def live(source: Path | None, output: Path, camera: str | None, config_path: Path | None, port: int, host: str,
         no_server: bool, idle_timeout: float | None, fps: float | None, workers: int, force: bool, compression: str,
         as_json: bool, quiet: bool) -> None:
    """Run `run`'s stages on frames as they are recorded, and show them in Foxglove as they are computed.

    SOURCE is an MCAP log another program is still writing (followed until its footer), or a
    folder camera software fills with image files (PNG, TIFF, FITS, ... each new file once
    whole, in name order); --camera reads a camera through OpenCV instead. Each frame goes
    through the centroid, track and solve stages of the config as it arrives, and every
    message is published on a Foxglove WebSocket server (ws://HOST:PORT: in Foxglove, Open
    connection, Foxglove WebSocket) as it is written to its layer. When the source ends (or at
    Ctrl-C or SIGTERM) the layers are closed on the finished log, with the names `run` gives
    them, and the stages that need the whole series (compensate, your own stages) run:
    `starlog run BASE -o X --config FILE` gives the same messages. A folder's or camera's frames
    are recorded into OUTPUT.0-base.mcap, the base of the layers.

    If the processing falls behind, the frames waiting and the latency are said on stderr and
    on /live/status; a frame that cannot be used is listed with why (`starlog info` shows the
    centroid layer's starlog.live record). A second Ctrl-C stops at once, listing the frames
    still waiting as skipped.

    \b
    Example:
      starlog simulate -o camera.mcap --size 512x512 --stars 40 --duration 30 --realtime &
      starlog live camera.mcap -o live.mcap --config live.toml
      starlog live frames/ -o live.mcap --idle-timeout 5
      starlog live --camera 0 -o bench.mcap --port 8765
    """
    from starlog.live import live as run_live
    from starlog.pipeline import load_config, stage_line

    result = run_live(None if source is None else str(source), output, load_config(config_path), camera=camera,
                      host=host, port=None if no_server else port, idle_timeout=idle_timeout, fps=fps, force=force,
                      compression=compression, workers=workers, say=lambda line: echo_status(quiet, line))
    for stage, report in result.stages:
        line = stage_line(stage, report)
        if line is not None:
            echo_status(quiet, line)
    latency = result.status.get("latency", {})
    echo_status(quiet, f"latency from a frame's arrival to its last message: median "
                       f"{latency.get('median_ms', float('nan')):.1f} ms, p99 {latency.get('p99_ms', float('nan')):.1f} "
                       f"ms, largest {latency.get('max_ms', float('nan')):.1f} ms")
    echo_status(quiet, f"wrote {len(result.layers)} layers on {result.base}: {', '.join(map(str, result.layers))}")
    echo_status(quiet, f"wrote {output}; replay it with: starlog run {result.base} -o OTHER.mcap"
                       + (f" --config {config_path}" if config_path else ""))
    if as_json:
        print_json(result.to_dict())
        return
    click.echo(f"{output}: {result.status.get('frames_done', 0)} frames processed live of "
               f"{result.status.get('frames_seen', 0)} seen, {len(result.status.get('skipped', []))} skipped; "
               f"{result.end_reason}")
