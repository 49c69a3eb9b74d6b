"""Commands that start a log: ``simulate`` (a simulated star camera) and ``ingest`` (camera output)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from starlog.cli.options import CONTEXT, echo_status, frame_write_options, json_option, output_option, print_json

__all__ = ["ingest", "simulate"]


def _parse_jitter(values: tuple[str, ...]) -> list[tuple[float, float]]:
    out = []
    for value in values:
        try:
            freq, amp = (float(v) for v in value.split(":"))
        except ValueError:
            raise click.BadParameter(f"{value!r}: expected FREQ_HZ:AMPLITUDE_PX, e.g. 25:0.05", param_hint="--jitter")
        out.append((freq, amp))
    return out


def _parse_numbers(size: str, flux: str, drift: str, roll: str | None, sky_attitude: str | None) -> dict[str, Any]:
    """The options written as several numbers, as :func:`starlog.simulate` takes them."""
    try:
        width, height = (int(v) for v in size.lower().split("x"))
        flux_min, flux_max = (float(v) for v in flux.split(":"))
        drift_x, drift_y = (float(v) for v in drift.split(","))
        roll_hz, roll_rad = (float(v) for v in roll.split(":")) if roll else (1.0, 0.0)
        ra, dec, sky_roll = (float(v) for v in sky_attitude.split(",")) if sky_attitude else (0.0, 0.0, 0.0)
    except ValueError as err:
        raise click.BadParameter(f"{err}; see --help for the formats of --size, --flux, --drift, --roll and "
                                 "--sky-attitude.")
    return {"size": (width, height), "flux": (flux_min, flux_max), "drift": (drift_x, drift_y),
            "roll": (roll_hz, roll_rad) if roll else None,
            "sky_attitude": (ra, dec, sky_roll) if sky_attitude else None}


@click.command(context_settings=CONTEXT)
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
@click.option("--sky-attitude", metavar="RA,DEC,ROLL",
              help="Render the real sky: the catalogue stars (cedar-solve's Hipparcos table; pip install "
                   "'starlog[solve]') seen at this attitude, degrees (roll: north from the image's up, counter-"
                   "clockwise); --stars and --flux are then unused, platform motion turns the camera and the true "
                   "attitude goes to /sim/truth.")
@click.option("--fov", "fov_deg", type=float, default=12.0, show_default=True,
              help="With --sky-attitude: horizontal field of view, degrees.")
@click.option("--mag-limit", type=float, default=6.5, show_default=True,
              help="With --sky-attitude: faintest catalogue magnitude rendered.")
@click.option("--flux-mag6", type=float, default=20000.0, show_default=True,
              help="With --sky-attitude: signal of a magnitude-6 star, e-/frame.")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of every random draw.")
@click.option("--start-ns", type=click.IntRange(0), default=0, show_default=True, help="log_time of frame 0.")
@click.option("--realtime", is_flag=True,
              help="Write the frames at the camera's rate, each flushed when its time comes, as a camera's recorder "
                   "writes them (for `starlog live`): the frames are rendered first (beside OUTPUT, removed after), "
                   "then OUTPUT is written under its own name, readable while it grows.")
@frame_write_options
def simulate(output: Path, preset: str | None, size: str, n_stars: int, flux: str, fps: float | None,
             n_frames: int | None, duration: float | None, psf_sigma: float, psf_model: str, psf_fwhm: float,
             moffat_beta: float, airy_lambda_d: float, airy_zero: float, sky: float, read_noise: float,
             gain: float, bias: float, adc_bits: int, hot_pixels: int, cosmic_rays: float, jitter: tuple[str, ...],
             drift: str, random_walk: float, roll: str | None, sky_attitude: str | None, fov_deg: float,
             mag_limit: float, flux_mag6: float, seed: int, start_ns: int, realtime: bool, force: bool,
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
      starlog simulate -o sky.mcap --size 512x512 --sky-attitude 80,20,30 --fov 10 --jitter 5:0.5
      starlog simulate -o camera.mcap --size 512x512 --stars 40 --duration 60 --realtime
    """
    from starlog import api

    summary = api.simulate(
        output, preset=preset, **_parse_numbers(size, flux, drift, roll, sky_attitude), stars=n_stars, fps=fps,
        frames=n_frames, duration=duration, psf_sigma=psf_sigma, psf=psf_model, psf_fwhm=psf_fwhm,
        moffat_beta=moffat_beta, airy_lambda_d=airy_lambda_d, airy_zero=airy_zero, sky=sky, read_noise=read_noise,
        gain=gain, bias=bias, adc_bits=adc_bits, hot_pixels=hot_pixels, cosmic_rays=cosmic_rays,
        jitter=_parse_jitter(jitter), random_walk=random_walk, fov=fov_deg, mag_limit=mag_limit,
        flux_mag6=flux_mag6, seed=seed, start_ns=start_ns, realtime=realtime, force=force, compression=compression,
        workers=workers, progress=not quiet, on_rendered=lambda planned: echo_status(
            quiet, f"rendered; writing {output} at {planned.fps:g} Hz ({planned.frames / planned.fps:.1f} s)"))
    for line in summary.lines():
        echo_status(quiet, line)


@click.command(context_settings=CONTEXT)
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
@frame_write_options
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

    from starlog import api

    with warnings.catch_warnings():
        warnings.simplefilter("always")
        warnings.showwarning = lambda message, *_, **__: click.echo(f"note: {message}", err=True)
        summary = api.ingest(source, output, fps=fps, start=start_ns, time_pattern=time_pattern,
                             time_unit=time_unit, skip_bad=skip_bad, compression=compression, workers=workers,
                             force=force, progress=not quiet)
    echo_status(quiet, f"wrote {output}: {summary.frames} frames {summary.width}x{summary.height} "
                       f"{summary.encoding}, timed by {summary.timing}, {len(summary.skipped)} skipped")
    if as_json:
        print_json(summary.to_dict())
    else:
        for line in summary.lines():
            click.echo(line)
