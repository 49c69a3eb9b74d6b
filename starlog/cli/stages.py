"""The replay stages' commands: ``centroid``, ``track``, ``motion``, ``compensate``, and one per declared stage
(:func:`stage_command`, for the stages installed packages register)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import click

from starlog.cli.options import (
    BURN_IN_HELP,
    CONTEXT,
    burn_in_setting,
    echo_status,
    print_result,
    flatten_option,
    image_topic_option,
    input_log,
    json_option,
    key_values,
    output_option,
    print_json,
    quiet_option,
    time_range_options,
    overwrite_options,
    write_options,
)

__all__ = ["centroid", "compensate", "motion", "solve", "stage_command", "track"]


@click.command(context_settings=CONTEXT)
@input_log
@output_option()
@click.option("--method", "methods", default="all", show_default=True,
              help="Sub-pixel methods, comma-separated: NONE, MOMENT, MOMENT_SQUARED, BICUBIC, GAUSSFIT, GRADIENT, "
                   "PSFFIT, WINPOS, or all (every method but MOMENT_SQUARED, the most accurate on no camera of the "
                   "benchmarks).")
@click.option("--psf", type=click.Choice(["gaussian", "empirical"]),
              help="PSF model of PSFFIT. empirical: an ePSF built once from the log's bright isolated stars, stored "
                   "in the output (metadata starlog.epsf, shown by info). gaussian: the pixel-integrated Gaussian. "
                   "[default: empirical when PSFFIT is among the methods]")
@click.option("--gain", type=float, help="Camera gain e-/DN [default: from the simulator's provenance, else 1].")
@click.option("--read-noise", type=float, help="Read noise e- [default: from the simulator's provenance, else estimated].")
@click.option("--set", "settings", multiple=True, metavar="KEY=VALUE",
              help="Detection or centroiding option: a keyword of starlog.detect.detect_stars (e.g. --set threshold=5) "
                   "or of starlog.centroiding.measure_centroids (e.g. --set robust=false). Repeatable.")
@image_topic_option
@click.option("--skip-bad", is_flag=True, help="Leave out frames that do not decode or do not fit (each named) "
                                              "instead of stopping.")
@click.option("--hot-pixels", "hot_pixels", metavar="auto|FILE",
              help="Hot-pixel map: 'auto' learns it from the log (pixels that are single-pixel spikes in most "
                   "of its first frames), or a FILE: .npy boolean mask of the frame's shape, or text/CSV lines "
                   "'x,y' (column,row). Hot pixels are never stars and are left out of the star windows.")
@click.option("--phase-correction", "phase_correction", metavar="auto|off|FILE", default="auto", show_default=True,
              help="Remove each method's pixel-phase bias (S-curve; under-sampled or non-Gaussian PSFs). auto: "
                   "learnt from the log's own stars (its first 16-256 frames, each distinct star once, no catalogue; "
                   "a method with too few is left uncorrected, with a note). FILE: calibrations in JSON (the "
                   "--json output of an earlier auto run, or 'starlog info --json' of its output log). Recorded "
                   "in the provenance and shown by info.")
@click.option("--mode", type=click.Choice(["auto", "tracking", "full"]), default="auto", show_default=True,
              help="full: search every frame for stars. tracking: search the first frame, then measure each known "
                   "star in a window around its predicted position, searching the whole frame again every "
                   "--acquire-every frames, when a star is lost and when light appears outside the windows "
                   "(centroid flag TRACKED). auto: tracking when the log's first frames show one field moving "
                   "little, else full (a folder of unrelated stills). Recorded in the provenance with the number "
                   "of full searches.")
@click.option("--acquire-every", "acquire_every", type=click.IntRange(min=1), metavar="N",
              help="Tracking: frames between two full searches. [default: 100]")
@time_range_options("the image channel")
@json_option
@flatten_option
@write_options
def centroid(log: Path, output: Path, methods: str, psf: str | None, gain: float | None, read_noise: float | None,
             settings: tuple[str, ...], image_topic: str | None, skip_bad: bool, hot_pixels: str | None,
             phase_correction: str, mode: str, acquire_every: int | None, start: str | None, end: str | None,
             as_json: bool, flatten: bool, force: bool, compression: str, workers: int, quiet: bool) -> None:
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
      starlog centroid sim.mcap -o cen.mcap --method GAUSSFIT --mode tracking --acquire-every 50
    """
    from starlog import api

    summary = api.centroid(log, output, method=methods, gain=gain, read_noise=read_noise, psf=psf,
                           options=key_values(settings, "--set"), image_topic=image_topic, skip_bad=skip_bad,
                           workers=workers, force=force, compression=compression, progress=not quiet,
                           hot_pixels=hot_pixels, phase_correction=phase_correction, start=start, end=end,
                           flatten=flatten, mode=mode, acquire_every=acquire_every)
    d = summary.to_dict()
    for note in d["notes"]:
        click.echo(f"note: {note}", err=True)
    echo_status(quiet, f"wrote {output}: {d['frames']} of {d['channel_messages']} frames of {d['image_topic']} read, "
                       f"{d['detections_per_frame']:.1f} stars/frame, {d['mode']} mode ({d['acquisitions']} frames "
                       "searched in full)")
    for skipped in d["skipped_frames"]:
        click.echo(f"  skipped frame {skipped['index']} (log_time {skipped['log_time']}): {skipped['reason']}",
                   err=True)
    print_result(summary, as_json, d)


@click.command(context_settings=CONTEXT)
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
    from starlog import api

    summary = api.track(log, output, centroids=method, model=models, options=key_values(settings, "--set"),
                        motion=key_values(motion, "--motion"), force=force, compression=compression,
                        workers=workers, progress=not quiet, start=start, end=end, flatten=flatten)
    echo_status(quiet, f"wrote {output}: {summary.frames} frames of {summary.method} centroids")
    print_result(summary, as_json)


@click.command(context_settings=CONTEXT)
@input_log
@output_option()
@click.option("--track", "track_topic", help="Track channel, e.g. /track/GAUSSFIT/STATIC, or all [default: the only one].")
@click.option("--model", "fit", type=click.Choice(["translation", "rigid", "similarity"]), default="rigid",
              show_default=True, help="2-D platform motion fitted per frame about the image centre.")
@click.option("--set", "settings", multiple=True, metavar="KEY=VALUE",
              help="Option of starlog.platform_motion.estimate_platform (k_sigma, min_stars, min_star_frames, max_iterations, "
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
    from starlog import api

    summary = api.motion(log, output, track=track_topic, model=fit, options=key_values(settings, "--set"),
                         force=force, compression=compression, workers=workers, start=start, end=end,
                         flatten=flatten)
    echo_status(quiet, f"wrote {output}: {fit} platform motion of {len(summary.channels)} track channel(s)")
    print_result(summary, as_json)


@click.command(context_settings=CONTEXT)
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
              help="Option of starlog.compensation.evaluate (accuracy_source, calibration_fraction, top_k, "
                   "rollback_threshold, leakfree_reference). Repeatable.")
@time_range_options("the (first) track channel")
@json_option
@flatten_option
@overwrite_options
@click.option("--workers", type=click.IntRange(1, 256), default=1, show_default=True,
              help="Processes for the (track, rate, protocol) evaluations; pays off for many of them (reading "
                   "the tracks dominates otherwise). The output does not depend on it.")
@quiet_option
@click.option("--burn-in", "burn_in", default="auto", show_default=True, metavar="auto|off|SECONDS", help=BURN_IN_HELP)
@click.option("--skip-short", is_flag=True,
              help="Leave out the rates and protocols the track is too short for (one line each on stderr) instead "
                   "of refusing the log.")
@click.option("--stars", type=click.Choice(["brightest", "all"]), default="brightest", show_default=True,
              help="all: also compensate every confirmed track (each its own strategy selection; tracks too short "
                   "are left out and counted) and write them per frame on /compensated/<METHOD>/<MODEL>/stars/"
                   "<RATE>Hz/<PROTOCOL>, which solve --compensated reads: the attitude before and after.")
def compensate(log: Path, output: Path, track_topic: str | None, rates: str, protocols: str, motion: str,
               settings: tuple[str, ...], start: str | None, end: str | None, as_json: bool, flatten: bool,
               force: bool, compression: str, workers: int, quiet: bool, burn_in: str, skip_short: bool,
               stars: str) -> None:
    """Decompose the brightest star's error, select strategies and compensate (paper 2.2-2.5).

    For each rate: equidistant decimation, error decomposition, eq. 12 scores, the top three
    strategies with rollback below 1 %, under each protocol. Writes a layer on the log holding
    the series before/after and one decision record per (rate, protocol) on
    /compensated/<METHOD>/<MODEL>/decisions. A track too short for a rate and protocol (too
    few samples after the filter's start-up; leakfree needs about twice as many) is refused
    before anything is written, naming the log length it needs; --skip-short leaves those out.

    \b
    Example:
      starlog compensate trk.mcap -o comp.mcap --track /track/GAUSSFIT/STATIC --rate 10,50
      starlog compensate trk.mcap -o comp.mcap --rate 50 --protocol paper --json
      starlog compensate trk.mcap -o comp.mcap --rate 10,50 --protocol truth,relative --motion keep,separate
      starlog compensate trk.mcap -o comp.mcap --rate 50 --protocol paper --stars all
    """
    from starlog import api

    try:
        rate_values = [float(r) for r in rates.split(",") if r.strip()]
    except ValueError:
        raise click.BadParameter(f"{rates!r}: expected numbers in Hz, e.g. 10,50", param_hint="--rate")
    summary = api.compensate(log, output, rate=rate_values, track=track_topic, protocol=protocols,
                             options=key_values(settings, "--set"), motion=motion, workers=workers,
                             progress=not quiet, force=force, compression=compression, start=start, end=end,
                             burn_in=burn_in_setting(burn_in), skip_short=skip_short, flatten=flatten, stars=stars)
    for skipped in summary.skipped:
        echo_status(quiet, f"skipped (track too short): {skipped.describe()}")
    echo_status(quiet, f"wrote {output}: {len(summary.records)} decision records")
    if as_json:
        print_json(summary.to_dict())
    else:
        for line in summary.lines():
            click.echo(line)


@click.command(context_settings=CONTEXT)
@input_log
@output_option()
@click.option("--centroids", "methods", help="Centroid methods to solve, comma-separated (e.g. GAUSSFIT,MOMENT), "
                                            "or all [default: the only centroid channel; none with --compensated].")
@click.option("--compensated", "compensated", metavar="RATE/PROTOCOL|all",
              help="Also (alone: only) solve all-star compensated channels of compensate --stars all, e.g. 50/truth "
                   "or 50/paper/separate, comma-separated, or all: each from the positions before and after "
                   "compensation, on /attitude/compensated/<METHOD>/<MODEL>/<RATE>Hz/<PROTOCOL>/before|after.")
@click.option("--set", "settings", multiple=True, metavar="KEY=VALUE",
              help="Solve option: match_radius (px, 3), min_matches (6), min_stars (4), fov_deg (the solver's "
                   "field-of-view hint; default: searched), focal_px and distortion (a known camera), fit_distortion, "
                   "brightest (50), timeout_ms (5000), try_mirrored (false), tracking (true), reject (4), "
                   "max_magnitude, camera (auto|fit). Repeatable.")
@time_range_options("the (first) centroid channel")
@json_option
@flatten_option
@overwrite_options
@quiet_option
def solve(log: Path, output: Path, methods: str | None, compensated: str | None, settings: tuple[str, ...],
          start: str | None, end: str | None, as_json: bool, flatten: bool, force: bool, compression: str,
          quiet: bool) -> None:
    """Identify the stars in a catalogue and solve the camera's attitude in every frame.

    Per centroid method: a lost-in-space plate solve (cedar-solve, pip install 'starlog[solve]'; its
    Hipparcos database ships with it), then tracking: each next frame identified from the previous
    attitude and refined by Davenport's q-method weighted by each centroid's sigma, back to lost in
    space when too few stars match. Writes a layer holding /attitude/<METHOD> (quaternion, RA/Dec/roll,
    field of view, residuals, covariance; solved or why not), /stars/identified/<METHOD> and its
    annotations. Prints per method the catalogue residuals and the fitted camera (focal length,
    distortion), and on a simulated sky field the attitude error against the truth.

    \b
    Example:
      starlog solve cen.mcap -o att.mcap --centroids GAUSSFIT
      starlog solve cen.mcap -o att.mcap --centroids all --set match_radius=2 --json
      starlog solve comp.mcap -o att.mcap --compensated 50/truth
    """
    from starlog import api

    summary = api.solve(log, output, centroids=methods, compensated=compensated,
                        options=key_values(settings, "--set"), force=force,
                        compression=compression, progress=not quiet, start=start, end=end, flatten=flatten)
    solved = sum(m["solved"] for m in summary.methods.values())
    frames = sum(m["frames"] for m in summary.methods.values())
    per_frame = 1000 * sum(summary.seconds.values()) / max(frames, 1)
    echo_status(quiet, f"wrote {output}: {solved} of {frames} frames solved over {len(summary.methods)} method(s), "
                       f"{per_frame:.2f} ms a frame")
    print_result(summary, as_json)


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

        summary = run_stage(declared, log, output, options=key_values(settings, "--set"), input_topic=input_topic,
                            workers=workers, force=force, compression=compression, show_progress=not quiet,
                            start=start, end=end, flatten=flatten)
        d = summary.to_dict()
        for note in d["notes"]:
            click.echo(f"note: {note}", err=True)
        written = ", ".join(f"{n} records on {t}" for t, n in d["records"].items())
        echo_status(quiet, f"wrote {output}: {d['messages']} messages of {', '.join(d['inputs'])} read; {written}")
        if as_json:
            print_json(d)

    return command
