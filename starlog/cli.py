"""The ``starlog`` command line: a thin layer over :mod:`starlog.stages`, :mod:`starlog.io` and :mod:`starlog.export`.

Every command has ``--help`` with an example; commands that print results accept ``--json``.
Errors starlog raises on purpose are printed as one sentence with exit status 1.
"""

from __future__ import annotations

import functools
import json
import os
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import click

from starlog import __version__
from starlog.errors import StarlogError

__all__ = ["cli", "main"]

F = TypeVar("F", bound=Callable[..., Any])
CONTEXT = {"help_option_names": ["-h", "--help"], "max_content_width": 100}
QUIET_HELP = "No progress bar and no status lines on stderr; results (stdout, --json) still print."


class _StarlogGroup(click.Group):
    def invoke(self, ctx: click.Context) -> Any:
        try:
            return super().invoke(ctx)
        except StarlogError as err:
            raise click.ClickException(str(err)) from err

    def list_commands(self, ctx: click.Context) -> list[str]:
        """The built-in commands, then the stages installed packages register (not imported to list them)."""
        builtin = super().list_commands(ctx)
        return [*builtin, *sorted(set(_installed_stages()) - set(builtin))]

    def get_command(self, ctx: click.Context, cmd_name: str) -> click.Command | None:
        command = super().get_command(ctx, cmd_name)
        if command is None and cmd_name in _installed_stages():
            return _LazyStageCommand(cmd_name)
        return command

    def format_commands(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        """Built-in commands, then installed stages in a section of their own."""
        builtin = [name for name in super().list_commands(ctx) if not self.commands[name].hidden]
        limit = formatter.width - 6 - max(map(len, builtin), default=0)
        with formatter.section("Commands"):
            formatter.write_dl([(name, self.commands[name].get_short_help_str(limit)) for name in builtin])
        installed = _installed_stages()
        for name in sorted(set(installed) & set(builtin)):
            click.echo(f"warning: the stage {name!r} installed by {installed[name]} is hidden by the built-in "
                       f"command {name!r}.", err=True)
        extra = [(name, _LazyStageCommand(name).get_short_help_str()) for name in sorted(set(installed) - set(builtin))]
        if extra:
            with formatter.section("Installed stages (entry points 'starlog.stages'; STAGE --help for more)"):
                formatter.write_dl(extra)


def _print_json(data: Any) -> None:
    click.echo(json.dumps(data, indent=2, allow_nan=False))


def _status(quiet: bool, text: str) -> None:
    """A status line (what was written where) on stderr, unless ``--quiet``; results go to stdout."""
    if not quiet:
        click.echo(text, err=True)


# ---------------------------------------------------------------- shared options
def output_option(help_text: str = "Output log (.mcap). Written atomically.") -> Callable[[F], F]:
    return click.option("-o", "--output", required=True, type=click.Path(dir_okay=False, path_type=Path),
                        help=help_text)


def quiet_option(f: F) -> F:
    return click.option("--quiet", "-q", is_flag=True, help=QUIET_HELP)(f)


def write_options(f: F) -> F:
    """--force, --compression, --workers, --quiet."""
    f = quiet_option(f)
    f = click.option("--workers", type=click.IntRange(1, 256), default=os.cpu_count() or 1,
                     show_default="all cores",
                     help="Cores for per-frame work, image decoding and chunk compression; the output "
                          "does not depend on it.")(f)
    f = click.option("--compression", type=click.Choice(["zstd", "lz4", "none"]), default="zstd",
                     show_default=True, help="Chunk compression of the output log.")(f)
    f = click.option("--force", is_flag=True, help="Overwrite the output if it exists.")(f)
    return f


FLATTEN_HELP = ("Write one self-contained log (every file of the input's chain and this stage's channels) instead "
                "of a layer on the input: the file to share or archive.")


def flatten_option(f: F) -> F:
    return click.option("--flatten", is_flag=True, help=FLATTEN_HELP)(f)


def json_option(f: F) -> F:
    return click.option("--json", "as_json", is_flag=True, help="Print the result as JSON.")(f)


input_log = click.argument("log", type=click.Path(exists=True, dir_okay=False, path_type=Path))


RANGE_HELP = ("log time in ns (1234567), seconds on the same clock with an 's' suffix (12.5s), or frame:N "
              "(the N-th message, 0-based, of {what})")


STAGE_RANGE = "The stage reads [start, end) of every channel; its channels hold that range."
COPY_RANGE = "Every channel's messages in [start, end) are kept."


def time_range_options(what: str, effect: str = STAGE_RANGE) -> Callable[[F], F]:
    """--start / --end: the half-open range [start, end) of log_time to process (``effect`` says how)."""

    def add(f: F) -> F:
        f = click.option("--end", metavar="TIME",
                         help=f"Only messages before this time (exclusive): {RANGE_HELP.format(what=what)}. "
                              "Default: after the last message.")(f)
        f = click.option("--start", metavar="TIME",
                         help=f"Only messages from this time on (inclusive): {RANGE_HELP.format(what=what)}. "
                              f"{effect} Default: the first message.")(f)
        return f

    return add


def image_topic_option(f: F) -> F:
    return click.option("--image-topic", metavar="TOPIC",
                        help="Image channel to read [default: /camera/image, else the log's only image channel]. "
                             "Any foxglove.RawImage/CompressedImage or ROS 1/2 sensor_msgs Image/CompressedImage.")(f)


@click.group(cls=_StarlogGroup, context_settings=CONTEXT)
@click.version_option(__version__, prog_name="starlog")
def cli() -> None:
    """starlog: star-tracker centroid extraction, with every step kept in MCAP logs.

    A log starts as image frames (simulate, ingest); each stage writes a layer on it holding
    only the channels it adds, and names the log it extends. Every command reads a layer with
    its chain as one log; open the files together in Foxglove; flatten makes one file of them;
    export tables to Parquet.

    Pixel coordinates: x = column, y = row, (0, 0) at the centre of the top-left pixel.
    Times: integer nanoseconds (log_time).

    Results print on stdout (--json: as JSON); progress bars and status lines ("wrote ...") go
    to stderr, and -q silences them.
    """


# ---------------------------------------------------------------- simulate
def _parse_jitter(values: tuple[str, ...]) -> tuple[Any, ...]:
    from starlog.sim import Jitter

    out = []
    for value in values:
        try:
            freq, amp = (float(v) for v in value.split(":"))
        except ValueError:
            raise click.BadParameter(f"{value!r}: expected FREQ_HZ:AMPLITUDE_PX, e.g. 25:0.05", param_hint="--jitter")
        out.append(Jitter(frequency_hz=freq, amplitude_px=amp))
    return tuple(out)


@cli.command(context_settings=CONTEXT)
@output_option()
@click.option("--preset", type=click.Choice(["paper300", "paper200"]),
              help="The paper's datasets: paper300 = 300 Hz x 3248 frames, paper200 = 200 Hz x 3027 frames. "
                   "Other options override it.")
@click.option("--size", default="256x256", show_default=True, help="Frame size WIDTHxHEIGHT in pixels.")
@click.option("--stars", "n_stars", type=click.IntRange(0), default=12, show_default=True, help="Number of stars.")
@click.option("--flux", default="5000:50000", show_default=True,
              help="Star signal range MIN:MAX in photo-electrons per frame (log-uniform).")
@click.option("--fps", type=float, help="Frame rate in Hz [default: 300, or the preset's].")
@click.option("--frames", "n_frames", type=click.IntRange(1), help="Number of frames [default: 300, or the preset's].")
@click.option("--duration", type=float, help="Duration in seconds (instead of --frames).")
@click.option("--psf-sigma", type=float, default=1.2, show_default=True, help="Gaussian PSF sigma in pixels.")
@click.option("--psf", "psf_model", type=click.Choice(["gaussian", "moffat", "airy"]), default="gaussian",
              show_default=True, help="PSF shape, integrated over pixels.")
@click.option("--psf-fwhm", type=click.FloatRange(min=0), default=0.0,
              help="Moffat / Airy FWHM in pixels [default: 2.3548 x --psf-sigma].")
@click.option("--moffat-beta", type=click.FloatRange(min=1, min_open=True), default=2.5, show_default=True,
              help="Moffat power index beta.")
@click.option("--airy-lambda-d", type=click.FloatRange(min=0), default=0.0,
              help="Airy lambda/D in pixels (instead of --psf-fwhm).")
@click.option("--airy-zero", type=click.FloatRange(min=0), default=0.0,
              help="Airy first-dark-ring radius in pixels, 1.22 lambda/D (instead of --airy-lambda-d).")
@click.option("--sky", type=float, default=20.0, show_default=True, help="Sky background, e-/pixel/frame.")
@click.option("--read-noise", type=float, default=3.0, show_default=True, help="Read noise, e- RMS.")
@click.option("--gain", type=float, default=1.0, show_default=True, help="Gain, e-/DN.")
@click.option("--bias", type=float, default=100.0, show_default=True, help="Bias offset, DN.")
@click.option("--adc-bits", type=click.IntRange(1, 16), default=16, show_default=True,
              help="ADC depth; pixels saturate at 2^bits - 1.")
@click.option("--hot-pixels", type=click.IntRange(0), default=0, show_default=True, help="Number of hot pixels.")
@click.option("--cosmic-rays", type=float, default=0.0, show_default=True, help="Mean cosmic-ray hits per frame.")
@click.option("--jitter", multiple=True, metavar="FREQ:AMP",
              help="Platform vibration: sinusoid of FREQ Hz and AMP px peak on each axis. Repeatable.")
@click.option("--drift", default="0,0", show_default=True, help="Platform drift VX,VY in px/s.")
@click.option("--random-walk", type=float, default=0.0, show_default=True, help="Platform random walk, px/sqrt(s).")
@click.option("--roll", metavar="FREQ:AMP", help="Platform roll about the image centre, FREQ_HZ:AMPLITUDE_RAD "
                                               "(sinusoidal), e.g. 2:0.001. Default: none.")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of every random draw.")
@click.option("--start-ns", type=click.IntRange(0), default=0, show_default=True, help="log_time of frame 0.")
@write_options
def simulate(output: Path, preset: str | None, size: str, n_stars: int, flux: str, fps: float | None,
             n_frames: int | None, duration: float | None, psf_sigma: float, psf_model: str, psf_fwhm: float,
             moffat_beta: float, airy_lambda_d: float, airy_zero: float, sky: float, read_noise: float,
             gain: float, bias: float, adc_bits: int, hot_pixels: int, cosmic_rays: float, jitter: tuple[str, ...],
             drift: str, random_walk: float, roll: str | None, seed: int, start_ns: int, force: bool,
             compression: str, workers: int, quiet: bool) -> None:
    """Write a simulated star-camera log.

    Stars are pixel-integrated Gaussians (or Moffat or Airy PSFs, --psf) on a sky background, with Poisson shot noise, read
    noise, gain, bias, quantisation and saturation; the platform may jitter, drift and random-walk.
    Frames go to /camera/image (foxglove.RawImage mono16), true positions to /sim/truth.
    Same options and seed give identical bytes.

    \b
    Example:
      starlog simulate -o sim.mcap --frames 600 --jitter 25:0.05 --seed 7
      starlog simulate -o paper300.mcap --preset paper300 --size 128x128
    """
    from starlog.sim import PRESETS, CameraModel, SimulationConfig
    from starlog.stages import simulate_log

    try:
        width, height = (int(v) for v in size.lower().split("x"))
        flux_min, flux_max = (float(v) for v in flux.split(":"))
        drift_x, drift_y = (float(v) for v in drift.split(","))
        roll_hz, roll_rad = (float(v) for v in roll.split(":")) if roll else (1.0, 0.0)
    except ValueError as err:
        raise click.BadParameter(f"{err}; see --help for the formats of --size, --flux, --drift and --roll.")
    params: dict[str, Any] = {"fps": 300.0, "n_frames": 300}
    if preset:
        params.update(PRESETS[preset])
    if fps is not None:
        params["fps"] = fps
    if duration is not None and n_frames is not None:
        raise click.UsageError("give --frames or --duration, not both.")
    if duration is not None:
        params["n_frames"] = max(1, int(round(duration * params["fps"])))
    elif n_frames is not None:
        params["n_frames"] = n_frames
    camera = CameraModel(read_noise=read_noise, gain=gain, bias=bias, adc_bits=adc_bits)
    if psf_model != "gaussian":
        from starlog.sim.profiles import AIRY_ZERO_PER_LAMBDA_D

        if airy_zero and airy_lambda_d:
            raise click.UsageError("give --airy-lambda-d or --airy-zero, not both.")
        params.update(psf_model=psf_model, psf_fwhm=psf_fwhm, moffat_beta=moffat_beta,
                      airy_lambda_d=airy_lambda_d or airy_zero / AIRY_ZERO_PER_LAMBDA_D)
    config = SimulationConfig(width=width, height=height, n_stars=n_stars, flux_min=flux_min, flux_max=flux_max,
                              psf_sigma=psf_sigma, sky=sky, camera=camera, hot_pixels=hot_pixels,
                              cosmic_rays_per_frame=cosmic_rays, jitter=_parse_jitter(jitter),
                              drift_px_per_s=(drift_x, drift_y), random_walk_px_per_sqrt_s=random_walk,
                              roll_amplitude_rad=roll_rad, roll_frequency_hz=roll_hz, seed=seed, start_time_ns=start_ns, **params)
    simulate_log(config, output, compression=compression, workers=workers, force=force, show_progress=not quiet)
    _status(quiet, f"wrote {output}: {config.n_frames} frames of {width}x{height} at {config.fps:g} Hz, "
                   f"{n_stars} stars")


# ---------------------------------------------------------------- ingest
@cli.command(context_settings=CONTEXT)
@click.argument("source", type=click.Path(exists=True, path_type=Path))
@output_option()
@click.option("--fps", "--rate", "fps", type=float,
              help="Frame rate in Hz; frame n is at START + n/fps. Without it, a SER or video file's own "
                   "frame times are used.")
@click.option("--start", "start_ns", type=click.IntRange(0), default=0, show_default=True,
              help="log_time of the first frame in ns (with --fps), or offset added to parsed or file times.")
@click.option("--time-pattern", help="Regular expression with a named group 't' that finds the time in each file "
                                     "name, e.g. 'img_(?P<t>\\d+)us'.")
@click.option("--time-unit", type=click.Choice(["s", "ms", "us", "ns"]), default="ns", show_default=True,
              help="Unit of the time parsed with --time-pattern.")
@click.option("--skip-bad", is_flag=True,
              help="Skip unreadable or mismatched files or frames (each named in the summary) instead of stopping.")
@json_option
@write_options
def ingest(source: Path, output: Path, fps: float | None, start_ns: int, time_pattern: str | None, time_unit: str,
           skip_bad: bool, as_json: bool, force: bool, compression: str, workers: int, quiet: bool) -> None:
    """Convert camera output into a log: a folder of star images, a SER file or a video.

    \b
    Folders: 8/16-bit PNG and TIFF, BMP, JPEG, FITS (with `pip install starlog[fits]`), in
      natural file-name order (img2 before img10).
    SER (astronomy-camera video): 8/16-bit mono, RGB/BGR and Bayer (debayered); frame times from
      its timestamp trailer (UTC, ns since 1970) unless --fps is given.
    AVI/MP4/MOV/MKV (via OpenCV, decoded to 8 bits): frame times from the container unless --fps.

    Colour frames are converted to mono, and lossy compression (JPEG, most video codecs), which
    biases sub-pixel centroids, is noted. Every frame must match the first's size and bit depth.

    \b
    Example:
      starlog ingest frames/ -o lab.mcap --fps 300
      starlog ingest frames/ -o lab.mcap --time-pattern 'img_(?P<t>\\d+)' --time-unit us
      starlog ingest capture.ser -o lab.mcap
      starlog ingest capture.avi -o lab.mcap --fps 100 --skip-bad
    """
    import warnings

    from starlog.stages import ingest_folder

    with warnings.catch_warnings():
        warnings.simplefilter("always")
        warnings.showwarning = lambda message, *_, **__: click.echo(f"note: {message}", err=True)
        summary = ingest_folder(source, output, fps=fps, start_ns=start_ns, time_pattern=time_pattern,
                                time_unit=time_unit, skip_bad=skip_bad, compression=compression, workers=workers,
                                force=force, show_progress=not quiet)
    _status(quiet, f"wrote {output}: {summary.frames} frames {summary.width}x{summary.height} {summary.encoding}, "
                   f"timed by {summary.timing}, {len(summary.skipped)} skipped")
    if as_json:
        _print_json(summary.to_dict())
    else:
        for name, reason in summary.skipped:
            click.echo(f"  skipped {name}: {reason}")


# ---------------------------------------------------------------- info
@cli.command(context_settings=CONTEXT)
@input_log
@json_option
@quiet_option
def info(log: Path, as_json: bool, quiet: bool) -> None:
    """Show a log's channels, time range and the provenance of every stage.

    \b
    Example:
      starlog info sim.mcap
      starlog info sim.mcap --json | jq '.channels[].topic'
    """
    from starlog.io.info import describe_log, format_description

    description = describe_log(log)
    if as_json:
        _print_json(description)
        return
    click.echo(format_description(description))
    for note in description["notes"]:  # how the log was read, not what it holds
        _status(quiet, f"note: {note}")


# ---------------------------------------------------------------- export
def scheduler_option(f: F) -> F:
    return click.option("--scheduler", metavar="ADDRESS",
                        help="Dask scheduler (tcp://host:8786) to run several logs on; without it, --workers N > 1 "
                             "starts a local Dask cluster for several logs.")(f)


def _report_batch(outcomes: list[Any], as_json: bool, describe: Callable[[Any], str]) -> None:
    failed = [o for o in outcomes if not o.ok]
    if as_json:
        _print_json([{"log": o.name, "ok": o.ok, "result": o.result, "error": o.error} for o in outcomes])
    else:
        for o in outcomes:
            click.echo(f"{o.name}: {describe(o.result)}" if o.ok else f"{o.name}: FAILED: {o.error}")
        click.echo(f"{len(outcomes) - len(failed)} of {len(outcomes)} logs done, {len(failed)} failed.")
    if failed:
        sys.exit(1)


@cli.command(context_settings=CONTEXT)
@click.argument("logs", nargs=-1, required=True, type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option("-o", "--output", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="Folder for the Parquet files (created if missing); with several logs, one sub-folder each.")
@click.option("--table", "tables", multiple=True, help="Only this table (repeatable); default: every table the log has.")
@click.option("--topic", "export_topics", multiple=True, metavar="TOPIC",
              help="Also export this channel (any JSON, protobuf, ROS 1/2 channel) as a flat table <topic>.parquet: "
                   "log_time first, nested fields as a.b columns, arrays as lists. Repeatable.")
@click.option("--force", is_flag=True, help="Overwrite existing Parquet files.")
@click.option("--workers", type=click.IntRange(1, 256), default=1, show_default=True,
              help="With several logs: local Dask workers.")
@scheduler_option
@quiet_option
@json_option
def export(logs: tuple[Path, ...], output: Path, tables: tuple[str, ...], export_topics: tuple[str, ...], force: bool,
           workers: int, scheduler: str | None, quiet: bool, as_json: bool) -> None:
    """Export a log's channels to Parquet tables (one file per table).

    Tables: frames, truth (simulated logs), detections, centroids, tracks, compensation,
    decisions — each written when the log has its channels. Columns are documented in
    schemas/tables.json and the README. A log from another tool gets a frames table of its
    image channels (topic column); --topic exports any channel as a flat table. With nothing
    to export, the command says so, lists the channels and fails. Several logs go to one
    sub-folder each, in parallel on a Dask cluster with --scheduler or --workers.

    \b
    Example:
      starlog export sim.mcap -o tables/
      starlog export runs/*.mcap -o tables/ --workers 2
      starlog export bag.mcap -o tables/ --topic /imu/data
      python -c "import pyarrow.parquet as pq; print(pq.read_table('tables/truth.parquet'))"
    """
    from starlog.batch import BatchTask, run_batch
    from starlog.export import export_log

    selected = tables or None
    if len(logs) == 1 and not scheduler:
        written = export_log(logs[0], output, tables=selected, force=force, topics=export_topics)
        if as_json:
            _print_json({"output": str(output), "tables": written})
        else:
            for name, rows in written.items():
                click.echo(f"{output / (name + '.parquet')}: {rows} rows")
        return
    tasks = [BatchTask(str(log), export_log, (str(log.absolute()), str((output / log.stem).absolute())),
                       {"tables": selected, "force": force, "topics": export_topics}) for log in logs]
    outcomes = run_batch(tasks, scheduler=scheduler, workers=workers, show_progress=not quiet, description="export")
    _report_batch(outcomes, as_json, lambda r: ", ".join(f"{k} {v} rows" for k, v in r.items()))


# ---------------------------------------------------------------- centroid
def _key_values(values: tuple[str, ...], option: str) -> dict[str, Any]:
    """``KEY=VALUE`` options → dict (values parsed as JSON when they can be, else strings)."""
    out: dict[str, Any] = {}
    for item in values:
        key, sep, raw = item.partition("=")
        if not sep or not key:
            raise click.BadParameter(f"{item!r}: expected KEY=VALUE", param_hint=option)
        try:
            out[key.strip()] = json.loads(raw)
        except json.JSONDecodeError:
            out[key.strip()] = raw
    return out


@cli.command(context_settings=CONTEXT)
@input_log
@output_option()
@click.option("--method", "methods", default="all", show_default=True,
              help="Sub-pixel methods, comma-separated: NONE, MOMENT, MOMENT_SQUARED, BICUBIC, GAUSSFIT, GRADIENT, "
                   "PSFFIT, or all (all but MOMENT_SQUARED and PSFFIT).")
@click.option("--psf", type=click.Choice(["gaussian", "empirical"]),
              help="PSF model of PSFFIT. empirical: an ePSF built once from the log's bright isolated stars, stored "
                   "in the output (metadata starlog.epsf, shown by info). gaussian: the pixel-integrated Gaussian. "
                   "[default: empirical when PSFFIT is among the methods]")
@click.option("--gain", type=float, help="Camera gain e-/DN [default: from the simulator's provenance, else 1].")
@click.option("--read-noise", type=float, help="Read noise e- [default: from the simulator's provenance, else estimated].")
@click.option("--set", "settings", multiple=True, metavar="KEY=VALUE",
              help="Option of starlog.centroid.extract_stars, e.g. --set threshold=5. Repeatable.")
@image_topic_option
@click.option("--skip-bad", is_flag=True, help="Leave out frames that do not decode or do not fit (each named) "
                                              "instead of stopping.")
@click.option("--hot-pixels", "hot_pixels", metavar="auto|FILE",
              help="Hot-pixel map: 'auto' learns it from the log (pixels that are single-pixel spikes in most "
                   "of its first frames), or a FILE: .npy boolean mask of the frame's shape, or text/CSV lines "
                   "'x,y' (column,row). Hot pixels are never stars and are left out of the star windows.")
@click.option("--phase-correction", "phase_correction", metavar="auto|off|FILE", default="off", show_default=True,
              help="Remove each method's pixel-phase bias (S-curve; under-sampled or non-Gaussian PSFs). auto: "
                   "learnt from the log's own stars (its first 16-256 frames, each distinct star once, no catalogue; "
                   "a method with too few is left uncorrected, with a note). FILE: calibrations in JSON (the "
                   "--json output of an earlier auto run, or 'starlog info --json' of its output log). Recorded "
                   "in the provenance and shown by info.")
@time_range_options("the image channel")
@json_option
@flatten_option
@write_options
def centroid(log: Path, output: Path, methods: str, psf: str | None, gain: float | None, read_noise: float | None,
             settings: tuple[str, ...], image_topic: str | None, skip_bad: bool, hot_pixels: str | None,
             phase_correction: str, start: str | None, end: str | None, as_json: bool, flatten: bool, force: bool,
             compression: str, workers: int, quiet: bool) -> None:
    """Detect stars and measure sub-pixel centroids in every frame.

    Writes a layer on the log (the frames stay in the input) holding /stars/detections,
    /stars/centroids/<METHOD> per method and /stars/annotations (circles over the frames in
    Foxglove); reading the layer reads the whole log.

    \b
    Example:
      starlog centroid sim.mcap -o cen.mcap --method GAUSSFIT,MOMENT
      starlog centroid lab.mcap -o cen.mcap --method all --gain 2.1 --workers 2
      starlog centroid sim.mcap -o cen.mcap --start 0.5s --end frame:300
      starlog centroid sim.mcap -o cen.mcap --method PSFFIT,GAUSSFIT --psf empirical
      starlog centroid lab.mcap -o cen.mcap --hot-pixels auto
      starlog centroid sky.mcap -o cen.mcap --method MOMENT,GAUSSFIT --phase-correction auto
    """
    from starlog.stages.centroid import centroid_log

    summary = centroid_log(log, output, methods=methods, gain=gain, read_noise=read_noise, psf=psf,
                           options=_key_values(settings, "--set"), image_topic=image_topic, skip_bad=skip_bad,
                           workers=workers, force=force, compression=compression, show_progress=not quiet,
                           hot_pixels=hot_pixels, phase_correction=phase_correction, start=start, end=end,
                           flatten=flatten)
    d = summary.to_dict()
    for note in d["notes"]:
        click.echo(f"note: {note}", err=True)
    _status(quiet, f"wrote {output}: {d['frames']} of {d['channel_messages']} frames of {d['image_topic']} read, "
                   f"{d['detections_per_frame']:.1f} stars/frame")
    for skipped in d["skipped_frames"]:
        click.echo(f"  skipped frame {skipped['index']} (log_time {skipped['log_time']}): {skipped['reason']}",
                   err=True)
    if as_json:
        _print_json(d)
    else:
        for method, count in d["centroids"].items():
            click.echo(f"  {method:<15} {count:>8} centroids, {d['fit_failed'][method]} not measured (flag "
                       "FIT_FAILED: the detection's position kept)")


# ---------------------------------------------------------------- track
@cli.command(context_settings=CONTEXT)
@input_log
@output_option()
@click.option("--centroids", "method", required=True, help="Centroid method whose channel is tracked, e.g. GAUSSFIT.")
@click.option("--model", "models", default="all", show_default=True,
              help="Motion models, comma-separated: STATIC, RANDOM_WALK, BROWNIAN_MOTION, POLYNOMIAL_TREND, "
                   "CONSTANT_VELOCITY, or all.")
@click.option("--set", "settings", multiple=True, metavar="KEY=VALUE",
              help="Tracker option (gate_probability, association_radius, confirm_hits, max_missed, max_gated, "
                   "sigma_floor). Repeatable.")
@click.option("--motion", "motion", multiple=True, metavar="KEY=VALUE",
              help="Process noise (q_floor, q_position, q_velocity, tau, q_acceleration, q_jerk). Repeatable.")
@time_range_options("the centroid channel")
@json_option
@flatten_option
@write_options
def track(log: Path, output: Path, method: str, models: str, settings: tuple[str, ...], motion: tuple[str, ...],
          start: str | None, end: str | None, as_json: bool, flatten: bool, force: bool, compression: str,
          workers: int, quiet: bool) -> None:
    """Track every star with an Unscented Kalman Filter under each motion model.

    Writes a layer on the log holding /track/<METHOD>/<MODEL> per model: filtered position,
    covariance, innovation, NIS, gating and track id of every star in every frame; the
    brightest star's track is marked.

    \b
    Example:
      starlog track cen.mcap -o trk.mcap --centroids GAUSSFIT --model all
      starlog track cen.mcap -o trk.mcap --centroids NONE --model STATIC --set sigma_floor=0.05
    """
    from starlog.stages.track import track_log

    summary = track_log(log, output, method=method, models=models, tracker=_key_values(settings, "--set"),
                        motion=_key_values(motion, "--motion"), force=force, compression=compression,
                        workers=workers, show_progress=not quiet, start=start, end=end, flatten=flatten)
    d = summary.to_dict()
    _status(quiet, f"wrote {output}: {d['frames']} frames of {d['method']} centroids")
    if as_json:
        _print_json(d)
    else:
        click.echo(f"  {'model':<18} {'tracks':>7} {'confirmed':>9} {'gated':>6} {'mean NIS':>9} {'brightest':>9}")
        for model, m in d["models"].items():
            click.echo(f"  {model:<18} {m['tracks']:>7} {m['confirmed_tracks']:>9} {m['gated_measurements']:>6} "
                       f"{m['mean_nis']:>9.2f} {m['brightest_track']:>9}")


# ---------------------------------------------------------------- motion
def _burn_in_option(value: str) -> object:
    """``--burn-in`` as a :data:`starlog.compensate.BurnInSetting` (a bad value is a usage error)."""
    from starlog.compensate import parse_burn_in
    from starlog.errors import InvalidParameterError

    try:
        return parse_burn_in(value)
    except InvalidParameterError as err:
        raise click.BadParameter(str(err), param_hint="--burn-in") from None


BURN_IN_HELP = ("The tracking filter's start-up skipped before scoring: auto (until its position variance is within "
                "2x of the steady state, capped at 0.5 s), off (score from the first frame), or a number of seconds. "
                "Recorded in every decision record.")


@cli.command(context_settings=CONTEXT)
@input_log
@output_option()
@click.option("--track", "track_topic", help="Track channel, e.g. /track/GAUSSFIT/STATIC, or all [default: the only one].")
@click.option("--model", "fit", type=click.Choice(["translation", "rigid", "similarity"]), default="rigid",
              show_default=True, help="2-D platform motion fitted per frame about the image centre.")
@click.option("--set", "settings", multiple=True, metavar="KEY=VALUE",
              help="Option of starlog.motion.estimate_platform (k_sigma, min_stars, min_star_frames, max_iterations, "
                   "tol, max_rejections). Repeatable.")
@time_range_options("the (first) track channel")
@json_option
@flatten_option
@write_options
def motion(log: Path, output: Path, track_topic: str | None, fit: str, settings: tuple[str, ...], start: str | None,
           end: str | None, as_json: bool, flatten: bool, force: bool, compression: str, workers: int,
           quiet: bool) -> None:
    """Fit the platform motion to all tracked stars; each star's residual is its centroid error alone.

    Per frame, a weighted least-squares fit of the stars' measured positions (meas_x, meas_y of
    the track channel) to their static positions, estimated jointly over the log; stars more
    than k_sigma off the fit are left out and flagged. Writes a layer on the log holding
    /platform/<METHOD>/<MODEL> (dx, dy, roll, 1-sigma, stars used, residual RMS) and
    /stars/residuals/<METHOD>/<MODEL>. Frames with
    fewer than 3 usable stars get no motion. The per-star noise printed is each star's centroid
    noise measured without a simulator.

    \b
    Example:
      starlog motion trk.mcap -o mot.mcap --track /track/GAUSSFIT/STATIC
      starlog motion trk.mcap -o mot.mcap --track all --model translation --set k_sigma=4 --json
    """
    from starlog.stages.motion import motion_log

    summary = motion_log(log, output, track=track_topic, model=fit, options=_key_values(settings, "--set"),
                         force=force, compression=compression, workers=workers, start=start, end=end,
                         flatten=flatten)
    d = summary.to_dict()
    _status(quiet, f"wrote {output}: {fit} platform motion of {len(d['channels'])} track channel(s)")
    if as_json:
        _print_json(d)
        return
    for topic, ch in d["channels"].items():
        click.echo(f"{topic}: {ch['frames_with_motion']}/{ch['frames']} frames with a motion, {ch['stars']} stars, "
                   f"{ch['outliers']} outliers, {ch['short_tracks']} short tracks left out")
        if ch["frames_without_motion"]:
            click.echo(f"  {ch['frames_without_motion']} frames without a motion ({ch['without_motion_reason']})")
        click.echo(f"  RMS dx {ch['rms_dx']:.4f} px, dy {ch['rms_dy']:.4f} px, roll {ch['rms_roll']:.3g} rad; "
                   f"median 1-sigma dx {ch['median_sigma_dx']:.4f} px, dy {ch['median_sigma_dy']:.4f} px; "
                   f"median residual RMS {ch['median_residual_rms']:.4f} px")
        noise = ", ".join(f"{track}: {value:.4f}" for track, value in ch["star_noise"].items())
        click.echo(f"  centroid noise per track (px, 1 sigma per axis): {noise}")


# ---------------------------------------------------------------- compensate
def format_records(records: list[dict[str, Any]]) -> str:
    """Readable table of compensation decision records."""
    motion = any(r.get("motion", "keep") != "keep" for r in records)
    lines = [f"{'method':<9} {'model':<17} {'Hz':>5} {'protocol':<9} " + ("motion   " if motion else "")
             + f"{'reference':<13} {'RMSE before':>11} {'after':>8} {'gain':>6}  passes (x = rolled back)"]
    for r in records:
        for k, fig in enumerate(r["figures"]):
            passes = " > ".join(p["strategy"] + ("" if p["kept"] else " x") for p in r["compensation"]["passes"])
            head = (f"{r['method']:<9} {r['model']:<17} {r['rate_hz']:>5g} {r['protocol']:<9}" if k == 0
                    else " " * 43)
            if motion:
                head += f" {r.get('motion', 'keep'):<8}" if k == 0 else " " * 9
            lines.append(f"{head} {fig['reference']:<13} {fig['rmse_before']:>11.4f} {fig['rmse_after']:>8.4f} "
                         f"{100 * fig['effective']:>5.1f}%  {passes if k == 0 else ''}")
    return "\n".join(lines)


@cli.command(context_settings=CONTEXT)
@input_log
@output_option()
@click.option("--track", "track_topic", help="Track channel, e.g. /track/GAUSSFIT/STATIC [default: the only one].")
@click.option("--rate", "rates", required=True, help="Down-sampling rates in Hz, comma-separated, e.g. 10,50.")
@click.option("--protocol", "protocols", default="all", show_default=True,
              help="paper, truth (simulated logs), leakfree, relative (truth-free: against the motion fitted to the "
                   "other stars), comma-separated, or all (= paper, truth, leakfree).")
@click.option("--motion", "motion", default="keep", show_default=True,
              help="keep: compensate the positions (the paper's method); separate: compensate the star's residual "
                   "from the platform motion fitted to the other stars and add the motion back; or keep,separate.")
@click.option("--set", "settings", multiple=True, metavar="KEY=VALUE",
              help="Option of starlog.compensate.evaluate (accuracy_source, calibration_fraction, top_k, "
                   "rollback_threshold, leakfree_reference). Repeatable.")
@time_range_options("the (first) track channel")
@json_option
@flatten_option
@click.option("--force", is_flag=True, help="Overwrite the output if it exists.")
@click.option("--compression", type=click.Choice(["zstd", "lz4", "none"]), default="zstd", show_default=True,
              help="Chunk compression of the output log.")
@click.option("--workers", type=click.IntRange(1, 256), default=1, show_default=True,
              help="Processes for the (track, rate, protocol) evaluations; pays off for many of them (reading "
                   "the tracks dominates otherwise). The output does not depend on it.")
@quiet_option
@click.option("--burn-in", "burn_in", default="auto", show_default=True, metavar="auto|off|SECONDS", help=BURN_IN_HELP)
def compensate(log: Path, output: Path, track_topic: str | None, rates: str, protocols: str, motion: str,
               settings: tuple[str, ...], start: str | None, end: str | None, as_json: bool, flatten: bool,
               force: bool, compression: str, workers: int, quiet: bool, burn_in: str) -> None:
    """Decompose the brightest star's error, select strategies and compensate (paper 2.2-2.5).

    For each rate: equidistant decimation, error decomposition, eq. 12 scores, the top three
    strategies with rollback below 1 %, under each protocol. Writes a layer on the log holding
    the series before/after and one decision record per (rate, protocol) on
    /compensated/<METHOD>/<MODEL>/decisions.

    \b
    Example:
      starlog compensate trk.mcap -o comp.mcap --track /track/GAUSSFIT/STATIC --rate 10,50
      starlog compensate trk.mcap -o comp.mcap --rate 50 --protocol paper --json
      starlog compensate trk.mcap -o comp.mcap --rate 10,50 --protocol truth,relative --motion keep,separate
    """
    from starlog.stages.compensate import compensate_log

    try:
        rate_values = [float(r) for r in rates.split(",") if r.strip()]
    except ValueError:
        raise click.BadParameter(f"{rates!r}: expected numbers in Hz, e.g. 10,50", param_hint="--rate")
    summary = compensate_log(log, output, rates=rate_values, track=track_topic, protocols=protocols,
                             options=_key_values(settings, "--set"), motion=motion, workers=workers,
                             show_progress=not quiet, force=force, compression=compression, start=start, end=end,
                             burn_in=_burn_in_option(burn_in), flatten=flatten)
    _status(quiet, f"wrote {output}: {len(summary.records)} decision records")
    if as_json:
        _print_json(summary.to_dict())
    else:
        click.echo(format_records(summary.records))


# ---------------------------------------------------------------- run
def _batch_report(output: Path, force: bool) -> str:
    """Write the HTML report beside one output of a batch ``run``; the text saying so."""
    from starlog.report import write_report

    report = output.with_suffix(".html")
    if report.exists() and not force:
        return f"; {report.name} exists (kept; --force replaces it)"
    write_report(output, report)
    return f"; report {report}"


@cli.command(context_settings=CONTEXT)
@click.argument("logs", nargs=-1, type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option("-o", "--output", type=click.Path(path_type=Path),
              help="Output log (.mcap); with several input logs, a folder (one output per log, same name).")
@click.option("--config", "config_path", type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="Pipeline config (TOML) [default: the built-in config, see --print-config].")
@click.option("--print-config", is_flag=True, help="Print the built-in config (a starting point) and exit.")
@click.option("--table", "full_table", is_flag=True,
              help="Print every compensation row (one log), not only the short summary.")
@time_range_options("the first stage's input channel (the image channel for centroid)",
                    "The first stage reads [start, end) of every channel; the others process what it wrote.")
@scheduler_option
@json_option
@click.option("--flatten", is_flag=True, help="Write OUTPUT as one self-contained log (the input and every stage's "
                                               "channels) instead of a chain of layers (the layers are removed).")
@write_options
def run(logs: tuple[Path, ...], output: Path | None, config_path: Path | None, print_config: bool, full_table: bool,
        start: str | None, end: str | None, scheduler: str | None, as_json: bool, flatten: bool, force: bool,
        compression: str, workers: int, quiet: bool) -> None:
    """Replay logs through several stages (centroid, track, compensate) from one config file.

    Each stage's parameters come from its table in the TOML config; your own stages run after
    them from [stages.NAME] tables (uses = "module:function"). Each stage writes a layer on the
    one before it: OUT.1-centroid.mcap, OUT.2-track-NONE.mcap, ... and the last one OUT itself,
    each the file the stage run alone gives; reading OUT reads them all with the input (open
    them together in Foxglove). With --flatten, OUT is then the whole chain as one
    self-contained log (what `starlog flatten` gives), and the other layers are removed. One
    log: --workers sets the cores for per-frame work, and an HTML
    report (figures of every stage, see `starlog report`) is written beside the output with
    the suffix .html; a short summary points to it. Several logs:
    they run in parallel on a Dask cluster (--scheduler, or a local one with --workers), a
    failed log is reported and the others complete.

    \b
    Example:
      starlog run --print-config > pipeline.toml
      starlog run sim.mcap -o result.mcap --config pipeline.toml
      starlog run logs/*.mcap -o results/ --config pipeline.toml --scheduler tcp://10.0.0.5:8786
      starlog run sim.mcap -o first-second.mcap --start 0s --end 1s
    """
    from starlog.pipeline import DEFAULT_CONFIG_TOML, load_config, run_pipeline, run_pipeline_task

    if print_config:
        click.echo(DEFAULT_CONFIG_TOML, nl=False)
        return
    if not logs or output is None:
        raise click.UsageError("give the input LOG(s) and -o/--output (or --print-config).")
    config = load_config(config_path)
    if len(logs) > 1 or scheduler:
        from starlog.batch import BatchTask, run_batch

        output.mkdir(parents=True, exist_ok=True)
        options = {"force": force, "flatten": flatten, "compression": compression, "start": start, "end": end}
        tasks = [BatchTask(str(log), run_pipeline_task, (str(log.absolute()), str((output / log.name).absolute()),
                                                          config), options) for log in logs]
        outcomes = run_batch(tasks, scheduler=scheduler, workers=workers, show_progress=not quiet,
                             description="run")
        reports = {o.result["output"]: _batch_report(Path(o.result["output"]), force) for o in outcomes if o.ok}
        _report_batch(outcomes, as_json, lambda r: f"wrote {r['output']} ({len(r['stages'])} stages){reports[r['output']]}")
        return

    def report(stage: str, result: dict[str, Any]) -> None:
        if quiet:
            return
        if stage == "centroid":
            click.echo(f"centroid: {result['frames']} frames, {result['detections_per_frame']:.1f} stars/frame, "
                       f"methods {', '.join(result['methods'])}", err=True)
        elif stage.startswith("track"):
            models = ", ".join(f"{m} (track {v['brightest_track']}, NIS {v['mean_nis']:.2f})"
                               for m, v in result["models"].items())
            click.echo(f"track {result['method']}: brightest star under {models}", err=True)

    from starlog.errors import OutputExistsError
    from starlog.report import write_report
    from starlog.report.summary import run_summary_lines

    report_path = output.with_suffix(".html") if output.suffix != ".html" else output.with_name(output.name + ".html")
    if report_path.exists() and not force:
        raise OutputExistsError(report_path)
    result = run_pipeline(logs[0], output, config, workers=workers, force=force, flatten=flatten,
                          compression=compression, show_progress=not quiet, on_stage=report, start=start, end=end)
    if result.layers:
        _status(quiet, f"wrote {len(result.layers)} layers on {logs[0]}: "
                       f"{', '.join(str(p) for p in result.layers)}")
    _status(quiet, f"wrote {output}; inspect it with: starlog info {output}; tables: starlog export {output} -o DIR")
    write_report(output, report_path)
    _status(quiet, f"wrote {report_path}")
    if as_json:
        _print_json({**result.to_dict(), "report": str(report_path)})
        return
    if full_table:
        for stage, summary in result.stages:
            if stage == "compensate":
                click.echo(format_records(summary["records"]))
    click.echo("\n".join(run_summary_lines(output, result.stages, report_path)))


# ---------------------------------------------------------------- experiment
@cli.command(context_settings=CONTEXT)
@click.option("-o", "--output", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="Folder for the datasets, logs, tables (Markdown + Parquet), plots and report.")
@click.option("--quick", is_flag=True, help="Small frames and few frames: every table and plot in about a minute.")
@click.option("--sweep", is_flag=True, help="Instead of the paper's tables, the regime map: keep vs separate "
                                            "compensation over jitter 0-10x the centroid noise, 3/6/20 stars, 10 and "
                                            "50 Hz, every UKF model (regime_map.parquet/.md/.png).")
@click.option("--regime", "regimes", type=click.Choice(["paper", "modern"]), multiple=True,
              help="Dataset regime(s) to run (repeatable): 'paper' (conditions derived from the paper's numbers) "
                   "or 'modern'. Default: both.")
@click.option("--top-k", type=click.IntRange(1, 5), default=3, show_default=True,
              help="Most strategies run per compensation (those with an eq. 12 score > 0).")
@click.option("--force-top-k", is_flag=True,
              help="Ablation: run the top-k strategies even when their eq. 12 score is 0.")
@click.option("--workers", type=click.IntRange(1, 256), default=os.cpu_count() or 1, show_default="all cores",
              help="Local Dask workers for the independent runs (1: serial).")
@scheduler_option
@click.option("--force", is_flag=True, help="Overwrite an existing output folder's results.")
@quiet_option
@json_option
@click.option("--burn-in", "burn_in", default="auto", show_default=True, metavar="auto|off|SECONDS", help=BURN_IN_HELP)
def experiment(output: Path, quick: bool, sweep: bool, regimes: tuple[str, ...], top_k: int, force_top_k: bool,
               workers: int, scheduler: str | None, force: bool, quiet: bool, as_json: bool,
               burn_in: str = "auto") -> None:
    """Regenerate the paper's Tables 2-4 and Figure 5 on simulated "laboratory" datasets.

    Simulates the two datasets (300 Hz x 3248 frames, 200 Hz x 3027 frames; static star field,
    small platform perturbations) in each regime ('paper': one faint star, read noise and background,
    conditions derived from the paper's numbers; 'modern': six bright stars), runs centroid ->
    track -> compensate (the filter's start-up skipped; Table 3 with Table 2's best model) and
    writes each table under the paper's protocol with the paper's numbers beside ours, and again
    under the honest protocols (truth, leakfree); Table 2's cells again over 8 more simulated
    realisations of the 'paper' datasets (not with --quick; a single dataset's cell scatters by
    7-12 %); plots (Figure 4/5 analogues, trajectories) and report.md.

    \b
    Example:
      starlog experiment -o results/ --quick
      starlog experiment -o results/ --regime paper --workers 2
      starlog experiment -o ablation/ --force-top-k --workers 2
      starlog experiment -o results/ --scheduler tcp://10.0.0.5:8786
      starlog experiment -o regime/ --sweep --workers 2
    """
    from starlog.experiment import experiment_command

    compensation: dict[str, object] = {"top_k": top_k, "select_positive": not force_top_k}
    summary = experiment_command(output, quick=quick, workers=workers, scheduler=scheduler, force=force,
                                 show_progress=not quiet, sweep=sweep, regimes=regimes or ("paper", "modern"),
                                 compensation=compensation, burn_in=_burn_in_option(burn_in))
    if as_json:
        _print_json(summary.to_dict())
    else:
        click.echo(summary.text())


# ---------------------------------------------------------------- filter, cat
def topic_selection_options(f: F) -> F:
    """--topic / --exclude-topic globs and --frame-topic."""
    f = click.option("--frame-topic", metavar="TOPIC",
                     help="Channel whose messages frame:N counts [default: the only channel selected, else the log's "
                          "image channel].")(f)
    f = click.option("--exclude-topic", "exclude_topics", multiple=True, metavar="GLOB",
                     help="Leave out the channels matching this glob (fnmatch: * matches / too). Repeatable.")(f)
    f = click.option("--topic", "topics", multiple=True, metavar="GLOB",
                     help="Keep the channels matching this glob, e.g. '/camera/*' (fnmatch: * matches / too). "
                          "Repeatable. Default: every channel.")(f)
    return f


@cli.command(name="filter", context_settings=CONTEXT)
@input_log
@output_option()
@topic_selection_options
@time_range_options("--frame-topic", COPY_RANGE)
@click.option("--force", is_flag=True, help="Overwrite the output if it exists.")
@click.option("--compression", type=click.Choice(["zstd", "lz4", "none"]), default="zstd", show_default=True,
              help="Compression of the chunks that must be re-encoded (those only partly kept); chunks kept whole "
                   "are copied as they are.")
@quiet_option
@json_option
def filter_command(log: Path, output: Path, topics: tuple[str, ...], exclude_topics: tuple[str, ...],
                   frame_topic: str | None, start: str | None, end: str | None, force: bool, compression: str,
                   quiet: bool, as_json: bool) -> None:
    """Copy some channels and a time range of any MCAP log into a new log.

    Keeps the schemas, metadata and provenance records (and attachments in the range) and adds
    a provenance record of its own (stage "filter"). A chunk whose every message is kept is
    copied byte for byte, never re-compressed; a chunk only partly kept is re-encoded. The
    range is half-open: [start, end). Works on ROS 2 bags, Foxglove logs and logs without
    indexes as on starlog logs; the output is fully indexed.

    \b
    Example:
      starlog filter sim.mcap -o images.mcap --topic '/camera/*'
      starlog filter trk.mcap -o small.mcap --exclude-topic '/camera/image' --start 1s --end 2.5s
      starlog filter bag.mcap -o first100.mcap --end frame:100
    """
    from starlog.stages.filter import filter_log

    report = filter_log(log, output, topics=topics, exclude_topics=exclude_topics, start=start, end=end,
                        frame_topic=frame_topic, force=force, compression=compression)
    d = report.to_dict()
    _status(quiet, f"wrote {output}: {sum(d['messages'].values())} messages of {len(d['messages'])} channels; "
                   f"{d['chunks_copied']} chunks copied as they are, {d['chunks_reencoded']} re-encoded")
    if as_json:
        _print_json(d)
    else:
        for topic, count in d["messages"].items():
            click.echo(f"  {topic}: {count} messages")


@cli.command(context_settings=CONTEXT)
@input_log
@topic_selection_options
@time_range_options("--frame-topic", COPY_RANGE)
@click.option("--limit", type=click.IntRange(0), help="Stop after this many messages.")
@quiet_option
def cat(log: Path, topics: tuple[str, ...], exclude_topics: tuple[str, ...], frame_topic: str | None,
        start: str | None, end: str | None, limit: int | None, quiet: bool) -> None:
    """Print messages as JSON lines, in log_time order, for jq and scripts.

    Each line is {"topic", "log_time", "publish_time", "sequence", "message"}. starlog's JSON
    messages come out as they are; images as {width, height, encoding, bytes, sha256} instead of
    pixels; other protobuf, ROS 1 and ROS 2 messages decoded to objects (long byte fields as
    {bytes, sha256}); anything else as {schema, encoding, bytes}.

    \b
    Example:
      starlog cat sim.mcap --topic /sim/truth --limit 3
      starlog cat cen.mcap --topic '/stars/centroids/*' --start frame:10 --end frame:20 | jq '.message.stars | length'
      starlog cat bag.mcap --topic /camera/image_raw | head -n 5
    """
    from starlog.stages.filter import cat_messages

    notes: list[str] = []
    lines = cat_messages(log, topics=topics, exclude_topics=exclude_topics, start=start, end=end,
                         frame_topic=frame_topic, limit=limit, notes=notes)
    out = sys.stdout
    try:
        for line in lines:
            out.write(json.dumps(line, separators=(",", ":"), allow_nan=False))
            out.write("\n")
        out.flush()
        for note in notes:  # how the log was read
            _status(quiet, f"note: {note}")
    except BrokenPipeError:  # the reader (head, jq ...) has what it wanted: stop quietly
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, out.fileno())  # the interpreter's final flush must not fail again
        lines.close()


# ---------------------------------------------------------------- report
@cli.command(name="report", context_settings=CONTEXT)
@input_log
@output_option("Output HTML file; one self-contained file (no network needed to view it). Written atomically.")
@click.option("--force", is_flag=True, help="Overwrite the output if it exists.")
@json_option
@quiet_option
def report_command(log: Path, output: Path, force: bool, as_json: bool, quiet: bool) -> None:
    """Write an HTML report of a log: figures and tables of every stage it holds.

    A frame with its centroids, the tracks of every star, the brightest star's error and its
    amplitude spectrum (dominant frequency marked), the error decomposition, RMSE before/after
    compensation per protocol, the strategy decisions and the provenance of every stage. A
    section whose channels the log lacks says so and names the stage that makes them. Long
    logs are sampled, so the file stays small; it needs no network to view.

    \b
    Example:
      starlog report result.mcap -o result.html
      starlog report sim.mcap -o sim.html --force
    """
    from starlog.report import collect_report_data, render_report
    from starlog.report.log_report import write_text_atomic

    data = collect_report_data(log)
    write_text_atomic(output, render_report(data), force=force)
    _status(quiet, f"wrote {output}" + (f" ({len(data.missing)} parts missing: {', '.join(data.missing)})"
                                        if data.missing else ""))
    if as_json:
        _print_json({"output": str(output), "missing": data.missing})


# ---------------------------------------------------------------- recover
@cli.command(context_settings=CONTEXT)
@input_log
@output_option("Output log (.mcap), complete and fully indexed.")
@click.option("--force", is_flag=True, help="Overwrite the output if it exists.")
@json_option
@quiet_option
def recover(log: Path, output: Path, force: bool, as_json: bool, quiet: bool) -> None:
    """Rebuild a readable, indexed log from a truncated, unfinished or damaged one.

    Keeps every complete message (chunks whose bytes are whole and whose CRC checks) and the
    provenance records, and reports what was lost: damaged or cut-off chunks with their time
    range and, where the file still says, the channels and message counts they held. A layer
    stays a layer on its base when the base is there, unchanged; else its own records are
    recovered into a file that opens alone.

    \b
    Example:
      starlog recover crashed.mcap -o recovered.mcap
      starlog recover crashed.mcap -o recovered.mcap --json
    """
    from starlog.io.recover import recover_log

    report = recover_log(log, output, force=force)
    if as_json:
        _print_json(report.to_dict())
        return
    _status(quiet, f"wrote {output}")
    click.echo(f"{sum(report.kept_by_topic.values())} messages kept"
               f"{'' if report.had_footer else f', the last {report.tail_bytes_lost} bytes were unreadable'}")
    if report.base:
        click.echo(f"  a layer on {report.base}, as the input was")
    if report.base_note:
        click.echo(f"  note: {report.base_note}")
    for topic, count in sorted(report.kept_by_topic.items()):
        lo, hi = report.kept_time_range[topic]
        click.echo(f"  kept {topic}: {count} messages, log_time {lo}..{hi}")
    for chunk in report.lost_chunks:
        what = ", ".join(f"{t}: {n}" for t, n in chunk.messages_by_topic.items()) or "channels unknown"
        click.echo(f"  lost chunk at offset {chunk.offset} (log_time {chunk.message_start_time}.."
                   f"{chunk.message_end_time}; {what}): {chunk.reason}")
    for what, n in sorted(report.skipped_records.items()):
        click.echo(f"  skipped {n} x {what}")


# ---------------------------------------------------------------- verify
@cli.command(context_settings=CONTEXT)
@input_log
@click.option("--file-only", is_flag=True, help="Check this one file alone, not the bases of a layer.")
@json_option
@quiet_option
def verify(log: Path, file_only: bool, as_json: bool, quiet: bool) -> None:
    """Check every record of an MCAP log and report every problem found (like `mcap doctor`).

    Checks magic, header, footer, the summary and its CRC, every chunk (CRC, decompression),
    message and chunk indexes against the contents, statistics, schema/channel references,
    JSON messages against their schemas, protobuf/ROS decoding, image decoding and size, and
    log_time order per channel. Valid but unusual layouts (no message indexes, no summary) are
    notes. A layer is checked with every file of its chain: each base must be where the layer
    says, with the size, summary CRC and SHA-256 it recorded, and ids and topics must be unique
    across the chain (--file-only: the one file). Exit status 0 only when no error was found.

    \b
    Example:
      starlog verify sim.mcap
      starlog verify result.mcap --file-only
      starlog verify bag.mcap --json | jq '.files[].problems[] | select(.severity == "error")'
    """
    from tqdm import tqdm

    from starlog.io.verify import verify_log

    def progress(done: int, total: int) -> None:
        bar.total = total
        bar.update(done - bar.n)

    with tqdm(total=log.stat().st_size, desc="verify", unit="B", unit_scale=True, leave=False, dynamic_ncols=True,
              disable=True if quiet else None) as bar:  # None: shown on a terminal only
        report = verify_log(log, chain=not file_only, on_progress=progress)
    if as_json:
        _print_json(report.to_dict())
    else:
        for file in report.files:
            if len(report.files) > 1:
                click.echo(f"{file.path}:")
            _print_problems(file.problems)
            if len(report.files) > 1:
                click.echo(f"  {file.verdict()}")
        _print_problems(report.chain_problems)
        click.echo(report.verdict())
    if not report.ok:
        sys.exit(1)


def _print_problems(problems: list[Any]) -> None:
    """One line per problem, at most 20 of a kind (all of them with --json)."""
    shown: dict[str, int] = {}
    for problem in problems:
        shown[problem.kind] = shown.get(problem.kind, 0) + 1
        if shown[problem.kind] <= 20:
            click.echo(problem.line())
    for kind, count in shown.items():
        if count > 20:
            click.echo(f"... {count - 20} more {kind} problems (all of them with --json)")


# ---------------------------------------------------------------- flatten
@cli.command(context_settings=CONTEXT)
@input_log
@output_option("Output log (.mcap): one self-contained file. Written atomically.")
@click.option("--force", is_flag=True, help="Overwrite the output if it exists.")
@quiet_option
@json_option
def flatten(log: Path, output: Path, force: bool, quiet: bool, as_json: bool) -> None:
    """Write a layer and its chain (the log it extends, and so on) as one self-contained log.

    Every message, schema, metadata and attachment record of the chain's files is kept; chunks are
    copied byte for byte (nothing is decompressed or re-compressed). The records by which layers
    name their bases are left out: the output holds the bases. Use it for the file to share or
    archive, or for tools that read one file; every starlog command reads a chain as it is.

    \b
    Example:
      starlog flatten result.mcap -o result-all.mcap
    """
    from starlog.io.copying import flatten_log

    report = flatten_log(log, output, force=force)
    d = report.to_dict()
    _status(quiet, f"wrote {output}: {sum(d['messages'].values())} messages of {len(d['messages'])} channels, "
                   f"{d['chunks_copied']} chunks copied as they are")
    if as_json:
        _print_json(d)


# ---------------------------------------------------------------- installed stages
@functools.cache
def _installed_stages() -> dict[str, str]:
    """Name → ``"package version"`` of every stage installed packages register (their metadata only, once)."""
    from starlog.plugins import distribution_of, registered_stages

    return {name: distribution_of(point) for name, point in registered_stages().items()}


class _LazyStageCommand(click.Command):
    """An installed stage's command, listed without importing it; imported when it runs or shows its help."""

    def __init__(self, name: str) -> None:
        super().__init__(name, context_settings=CONTEXT)

    def get_short_help_str(self, limit: int = 45) -> str:
        return f"Stage from {_installed_stages().get(self.name or '', '?')} (run STAGE --help)."

    def make_context(self, info_name: str | None, args: list[str], parent: click.Context | None = None,
                     **extra: Any) -> click.Context:
        from starlog.plugins import load_registered

        try:
            declared = load_registered(self.name or "")
        except StarlogError as err:
            raise click.ClickException(str(err)) from err
        return stage_command(declared, self.name or declared.name).make_context(info_name, args, parent, **extra)


def stage_command(declared: Any, name: str) -> click.Command:
    """The ``starlog NAME LOG -o OUT`` command of a declared stage (:mod:`starlog.stage_api`)."""
    options = ", ".join(f"{k}={json.dumps(v)}" for k, v in declared.options.items())
    options += "".join(f", {k} (required)" for k in declared.required_options)
    writes = ", ".join(o.topic for o in declared.outputs)
    templated = " ({name}: the last part of the input topic)" if "{name}" in writes else ""
    help_text = (f"{declared.description or 'A declared stage.'}\n\n"
                 f"Stage {declared.name} {declared.version} ({declared.reference}): reads {declared.reads}, writes "
                 f"{writes}{templated}. Options: {options.strip(', ') or 'none'}."
                 f"\n\n\b\nExample:\n  starlog {name} LOG -o OUT.mcap")

    @click.command(name=name, context_settings=CONTEXT, help=help_text)
    @input_log
    @output_option()
    @click.option("--input-topic", "--input", "input_topic", metavar="TOPIC",
                  help=f"Channel to read, or all: each {declared.reads} channel in turn [default: the log's only "
                       f"{declared.reads} channel]. (--input is the same option.)")
    @click.option("--set", "settings", multiple=True, metavar="KEY=VALUE",
                  help="Option of the stage (values parsed as JSON when they can be). Repeatable.")
    @time_range_options(f"the {declared.reads} channel the stage reads")
    @json_option
    @flatten_option
    @write_options
    def command(log: Path, output: Path, input_topic: str | None, settings: tuple[str, ...], start: str | None,
                end: str | None, as_json: bool, flatten: bool, force: bool, compression: str, workers: int,
                quiet: bool) -> None:
        from starlog.stages.custom import run_stage

        summary = run_stage(declared, log, output, options=_key_values(settings, "--set"), input_topic=input_topic,
                            workers=workers, force=force, compression=compression, show_progress=not quiet,
                            start=start, end=end, flatten=flatten)
        d = summary.to_dict()
        for note in d["notes"]:
            click.echo(f"note: {note}", err=True)
        written = ", ".join(f"{n} records on {t}" for t, n in d["records"].items())
        _status(quiet, f"wrote {output}: {d['messages']} messages of {', '.join(d['inputs'])} read; {written}")
        if as_json:
            _print_json(d)

    return command


class _Terminated(BaseException):
    """SIGTERM arrived: unwind (abort partial outputs, stop worker pools), then die of the signal."""


def _raise_terminated(signum: int, frame: Any) -> None:
    raise _Terminated()


def main() -> None:
    """Console-script entry point."""
    import signal

    signal.signal(signal.SIGTERM, _raise_terminated)
    try:
        cli(prog_name="starlog")
    except _Terminated:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        os.kill(os.getpid(), signal.SIGTERM)  # exit status says "terminated by SIGTERM", as without the handler


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
