"""starlog from Python: one function per command, with the command's name and options.

Each function does what its command does — the command line calls these very functions — and
returns the summary the command prints (``.to_dict()`` is its ``--json``, ``.lines()`` its text).
Options are the command's, as Python keywords (``--read-noise`` → ``read_noise``; ``--set K=V``
→ ``options={"K": V}``); a progress bar only with ``progress=True``; ``workers=None`` uses every
core, as the command does. Errors are :class:`~starlog.errors.StarlogError` subclasses carrying
the command's one-line message. Time bounds (``start`` / ``end``) are written as on the command
line: log time in ns, ``"12.5s"`` or ``"frame:N"``. Where a command takes a comma-separated list
(``--method``, ``--rate``, ``--table``), the function takes that string or a list.

From a script (not a notebook), put the calls under ``if __name__ == "__main__":``: with more than
one worker, starlog's worker processes import the script again, as Python's ``multiprocessing``
does (``workers=1`` needs no guard).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from starlog.errors import InvalidParameterError, LogNotFoundError
from starlog.log import Log, TimeBound

if TYPE_CHECKING:
    from starlog.compensation import Shortfall
    from starlog.io.copying import CopyReport
    from starlog.io.verify import ChainReport
    from starlog.pipeline import PipelineConfig, PipelineResult
    from starlog.stages.centroid import CentroidSummary
    from starlog.stages.compensate import CompensateSummary
    from starlog.stages.ingest import IngestSummary
    from starlog.stages.motion import MotionSummary
    from starlog.stages.simulate import SimulationSummary
    from starlog.stages.solve import SolveSummary
    from starlog.stages.track import TrackSummary

__docformat__ = "restructuredtext"

__all__ = ["centroid", "compensate", "export", "flatten", "ingest", "motion", "open", "run", "simulate", "solve",
           "track", "verify"]

PathLike = str | os.PathLike[str]


def _cores(workers: int | None) -> int:
    return workers if workers is not None else (os.cpu_count() or 1)


def _names(value: str | Sequence[str] | None) -> list[str] | None:
    """A command's comma-separated list, given as that string or as a list."""
    if value is None:
        return None
    items = value.split(",") if isinstance(value, str) else [str(v) for v in value]
    return [item.strip() for item in items if item.strip()]


def _rates(rate: float | str | Sequence[float]) -> list[float]:
    """``rate`` (Hz) as ``compensate --rate`` takes it: a number, ``"10,50"`` or a list of numbers."""
    items = _names(rate) if isinstance(rate, str) else [rate] if not isinstance(rate, Sequence) else list(rate)
    try:
        return [float(r) for r in items or []]
    except (TypeError, ValueError):
        raise InvalidParameterError(f"rate={rate!r}: expected rates in Hz, e.g. 50, [10, 50] or '10,50'.") from None


def open(path: PathLike) -> Log:  # noqa: A001 - starlog.open, as io.open and tarfile.open
    """Open a log (one file, or a chain of layers read as one) for analysis.

    Example::

        import starlog
        with starlog.open("result.mcap") as log:
            print(log.table_names())
            tracks = log.table("tracks").to_pandas()
    """
    return Log(path)


def simulate(output: PathLike, *, preset: str | None = None, size: tuple[int, int] = (256, 256), stars: int = 12,
             flux: tuple[float, float] = (5000.0, 50000.0), fps: float | None = None, frames: int | None = None,
             duration: float | None = None, psf_sigma: float = 1.2, psf: str = "gaussian", psf_fwhm: float = 0.0,
             moffat_beta: float = 2.5, airy_lambda_d: float = 0.0, airy_zero: float = 0.0, sky: float = 20.0,
             read_noise: float = 3.0, gain: float = 1.0, bias: float = 100.0, adc_bits: int = 16,
             hot_pixels: int = 0, cosmic_rays: float = 0.0, jitter: Sequence[tuple[float, float]] = (),
             drift: tuple[float, float] = (0.0, 0.0), random_walk: float = 0.0,
             roll: tuple[float, float] | None = None, sky_attitude: tuple[float, float, float] | None = None,
             fov: float = 12.0, mag_limit: float = 6.5, flux_mag6: float = 20000.0, seed: int = 0,
             start_ns: int = 0, realtime: bool = False, force: bool = False, compression: str = "lz4",
             workers: int | None = None, progress: bool = False,
             on_rendered: Callable[[SimulationSummary], object] | None = None) -> SimulationSummary:
    """Simulate a star-tracker log (``starlog simulate``): frames on /camera/image, truth on /sim/truth.

    ``size`` is (width, height) in pixels, ``flux`` (min, max) photo-electrons, ``jitter`` a list of
    (frequency Hz, amplitude px), ``drift`` (vx, vy) px/s, ``roll`` (frequency Hz, amplitude rad),
    ``sky_attitude`` (RA, Dec, roll) in degrees (a real sky field of ``fov`` degrees); ``preset`` is
    ``"paper300"`` or ``"paper200"``. ``realtime`` writes the frames at the camera's rate
    (``on_rendered(summary)`` is called once they are rendered). Same options and seed give identical bytes.

    Example::

        starlog.simulate("sim.mcap", frames=600, jitter=[(25, 0.05)], seed=7)
    """
    from starlog.sim.options import simulation_config
    from starlog.stages.simulate import simulate_log, simulation_summary

    config = simulation_config(
        preset=preset, size=size, stars=stars, flux=flux, fps=fps, frames=frames, duration=duration,
        psf_sigma=psf_sigma, psf=psf, psf_fwhm=psf_fwhm, moffat_beta=moffat_beta, airy_lambda_d=airy_lambda_d,
        airy_zero=airy_zero, sky=sky, read_noise=read_noise, gain=gain, bias=bias, adc_bits=adc_bits,
        hot_pixels=hot_pixels, cosmic_rays=cosmic_rays, jitter=jitter, drift=drift, random_walk=random_walk,
        roll=roll, sky_attitude=sky_attitude, fov=fov, mag_limit=mag_limit, flux_mag6=flux_mag6, seed=seed,
        start_ns=start_ns)
    summary = simulation_summary(config, output)
    if realtime:
        from starlog.live import simulate_realtime

        simulate_realtime(config, output, compression=compression, workers=_cores(workers), force=force,
                          show_progress=progress, on_rendered=None if on_rendered is None else
                          lambda: on_rendered(summary))
    else:
        simulate_log(config, output, compression=compression, workers=_cores(workers), force=force,
                     show_progress=progress)
    return summary


def ingest(source: PathLike, output: PathLike, *, fps: float | None = None, start: int = 0,
           time_pattern: str | None = None, time_unit: str = "ns", skip_bad: bool = False, force: bool = False,
           compression: str = "lz4", workers: int | None = None, progress: bool = False) -> IngestSummary:
    """Record camera output into a log (``starlog ingest``): a folder of images, a SER file or a video.

    ``fps``: frame n at ``start`` + n/fps (ns); without it, a SER or video file's own times. ``start``: the log
    time of the first frame in ns (with ``fps``), or the offset added to the times parsed with ``time_pattern``
    (a regular expression whose group ``t`` finds the time in each file name, in ``time_unit``) or read from
    the file. ``skip_bad`` leaves out unreadable frames instead of stopping. Notes (lossy compression, colour
    frames) are Python warnings.

    Example::

        starlog.ingest("frames/", "lab.mcap", fps=300)
    """
    from starlog.stages.ingest import ingest_folder

    return ingest_folder(source, output, fps=fps, start_ns=start, time_pattern=time_pattern,
                         time_unit=time_unit, skip_bad=skip_bad, compression=compression, workers=_cores(workers),
                         force=force, show_progress=progress)


def centroid(log: PathLike, output: PathLike, *, method: str | Sequence[str] = "all", psf: str | None = None,
             gain: float | None = None, read_noise: float | None = None, options: Mapping[str, Any] | None = None,
             image_topic: str | None = None, skip_bad: bool = False, hot_pixels: PathLike | None = None,
             phase_correction: PathLike = "auto", mode: str = "auto", acquire_every: int | None = None,
             start: TimeBound = None, end: TimeBound = None, flatten: bool = False, force: bool = False,
             compression: str = "zstd", workers: int | None = None, progress: bool = False) -> CentroidSummary:
    """Detect stars and measure sub-pixel centroids in every frame (``starlog centroid``).

    Writes a layer on ``log`` with ``/stars/detections``, ``/stars/centroids/<METHOD>`` per method and
    ``/stars/annotations``. ``method``: NONE, MOMENT, MOMENT_SQUARED, BICUBIC, GAUSSFIT, GRADIENT, PSFFIT,
    WINPOS, or ``"all"``. ``options``: keywords of :func:`starlog.detect.detect_stars` and
    :func:`starlog.centroiding.measure_centroids` (the command's ``--set``). ``psf``: PSFFIT's model,
    ``"empirical"`` (an ePSF built from the log's stars) or ``"gaussian"``. ``gain`` (e-/DN) and
    ``read_noise`` (e-): by default from the simulator's provenance, else 1 and estimated. ``hot_pixels``:
    ``"auto"`` (learnt from the log) or a file (.npy mask, or ``x,y`` lines). ``phase_correction``:
    ``"auto"`` (each method's pixel-phase bias learnt from the log's stars), ``"off"`` or a calibration file.
    ``mode``: ``"full"`` (search every frame), ``"tracking"`` (windows around predicted positions, a full
    search every ``acquire_every`` frames, 100 by default) or ``"auto"``. ``skip_bad`` leaves out frames that
    do not decode instead of stopping.

    Example::

        summary = starlog.centroid("sim.mcap", "cen.mcap", method="GAUSSFIT,MOMENT")
        print(summary.to_dict()["detections_per_frame"])
    """
    from starlog.stages.centroid import centroid_log

    return centroid_log(log, output, methods=method, gain=gain, read_noise=read_noise, psf=psf,
                        options=dict(options or {}), image_topic=image_topic, skip_bad=skip_bad,
                        workers=_cores(workers), force=force, compression=compression, show_progress=progress,
                        hot_pixels=hot_pixels, phase_correction=phase_correction, start=start, end=end,
                        flatten=flatten, mode=mode, acquire_every=acquire_every)


def track(log: PathLike, output: PathLike, *, centroids: str, model: str | Sequence[str] = "all",
          options: Mapping[str, Any] | None = None, motion: Mapping[str, Any] | None = None,
          start: TimeBound = None, end: TimeBound = None, flatten: bool = False, force: bool = False,
          compression: str = "zstd", workers: int | None = None, progress: bool = False) -> TrackSummary:
    """Track every star with a UKF under each motion model (``starlog track``).

    ``centroids`` is the centroid method whose channel is tracked; ``model``: STATIC, RANDOM_WALK,
    BROWNIAN_MOTION, POLYNOMIAL_TREND, CONSTANT_VELOCITY, or ``"all"``; ``options``: the tracker's
    (:class:`starlog.tracking.TrackerConfig` fields, the command's ``--set``); ``motion``: the process noise
    (:class:`starlog.tracking.MotionModelConfig` fields, ``--motion``).

    Example::

        starlog.track("cen.mcap", "trk.mcap", centroids="GAUSSFIT", model="STATIC,CONSTANT_VELOCITY")
    """
    from starlog.stages.track import track_log

    return track_log(log, output, method=centroids, models=model, tracker=dict(options or {}),
                     motion=dict(motion or {}), force=force, compression=compression, workers=_cores(workers),
                     show_progress=progress, start=start, end=end, flatten=flatten)


def motion(log: PathLike, output: PathLike, *, track: str | Sequence[str] | None = None, model: str = "rigid",
           options: Mapping[str, Any] | None = None, start: TimeBound = None, end: TimeBound = None,
           flatten: bool = False, force: bool = False, compression: str = "zstd",
           workers: int | None = None) -> MotionSummary:
    """Fit the platform motion to all tracked stars; each star's residual is its error alone (``starlog motion``).

    ``track``: the track channel (``/track/GAUSSFIT/STATIC``), or ``"all"``; default the only one.
    ``model``: ``"translation"``, ``"rigid"`` or ``"similarity"``. ``options``: keywords of
    :func:`starlog.platform_motion.estimate_platform`.

    Example::

        starlog.motion("trk.mcap", "mot.mcap", track="/track/GAUSSFIT/STATIC")
    """
    from starlog.stages.motion import motion_log

    return motion_log(log, output, track=track, model=model, options=dict(options or {}), force=force,
                      compression=compression, workers=_cores(workers), start=start, end=end, flatten=flatten)


def compensate(log: PathLike, output: PathLike, *, rate: float | str | Sequence[float], track: str | None = None,
               protocol: str | Sequence[str] = "all", motion: str | Sequence[str] = "keep",
               options: Mapping[str, Any] | None = None, burn_in: str | float = "auto", skip_short: bool = False,
               stars: str = "brightest", start: TimeBound = None, end: TimeBound = None, flatten: bool = False,
               force: bool = False, compression: str = "zstd", workers: int | None = 1,
               progress: bool = False) -> CompensateSummary:
    """Decompose the brightest star's error, select strategies and compensate (``starlog compensate``).

    ``rate`` in Hz: a number, a list or ``"10,50"``. ``protocol``: ``paper``, ``truth`` (simulated logs),
    ``leakfree``, ``relative``, or ``"all"`` (paper, truth, leakfree). ``motion``: ``"keep"`` (the paper's
    method) and/or ``"separate"`` (the platform motion fitted to the other stars set aside). ``options``:
    keywords of :func:`starlog.compensation.evaluate`. ``burn_in``: ``"auto"``, ``"off"`` or seconds.
    ``stars``: ``"brightest"``, or ``"all"`` (every confirmed track too). ``skip_short`` leaves out the rates
    and protocols the track is too short for instead of refusing the log. ``workers``: one by default, as
    for the command (None: every core).

    Example::

        summary = starlog.compensate("trk.mcap", "comp.mcap", rate=[10, 50], protocol="paper")
        print("\\n".join(summary.lines()))
    """
    from starlog.compensation import parse_burn_in
    from starlog.stages.compensate import compensate_log

    return compensate_log(log, output, rates=_rates(rate), track=track, protocols=_names(protocol) or "all",
                          options=dict(options or {}), motion=_names(motion) or "keep", workers=_cores(workers),
                          show_progress=progress, force=force, compression=compression, start=start, end=end,
                          burn_in=parse_burn_in(burn_in), skip_short=skip_short, flatten=flatten, stars=stars)


def solve(log: PathLike, output: PathLike, *, centroids: str | Sequence[str] | None = None,
          compensated: str | Sequence[str] | None = None, options: Mapping[str, Any] | None = None,
          start: TimeBound = None, end: TimeBound = None, flatten: bool = False, force: bool = False,
          compression: str = "zstd", progress: bool = False) -> SolveSummary:
    """Identify the stars in a catalogue and solve the attitude of every frame (``starlog solve``).

    ``centroids``: centroid methods (``"GAUSSFIT,MOMENT"``, a list, or ``"all"``; default the only one).
    ``compensated``: all-star compensated channels of ``compensate(stars="all")``, e.g. ``"50/truth"``.
    ``options``: match_radius, min_matches, min_stars, fov_deg, focal_px, distortion, fit_distortion,
    brightest, timeout_ms, try_mirrored, tracking, reject, max_magnitude, camera (the command's ``--set``).
    Needs cedar-solve (``pip install 'starlog[solve]'``).

    Example::

        summary = starlog.solve("cen.mcap", "att.mcap", centroids="GAUSSFIT")
    """
    from starlog.stages.solve import solve_log

    return solve_log(log, output, centroids=centroids, compensated=compensated, options=dict(options or {}),
                     force=force, compression=compression, show_progress=progress, start=start, end=end,
                     flatten=flatten)


def run(log: PathLike, output: PathLike, *, config: PathLike | Mapping[str, Any] | PipelineConfig | None = None, start: TimeBound = None,
        end: TimeBound = None, flatten: bool = False, report: bool = True, force: bool = False,
        compression: str = "zstd", workers: int | None = None, progress: bool = False,
        on_stage: Callable[[str, dict[str, Any]], object] | None = None,
        on_skip: Callable[[Shortfall], object] | None = None) -> PipelineResult:
    """Replay a log through the stages of a pipeline config (``starlog run``), each writing a layer on the one
    before; ``output`` is the last. ``config``: a TOML file (``starlog run --print-config`` prints the built-in
    one), the same tables as a dict, or a :class:`~starlog.pipeline.PipelineConfig`; default the built-in config. With ``report``, the HTML
    report is written beside ``output`` (suffix .html, :func:`starlog.pipeline.report_path`).
    ``on_stage(name, summary)`` is called as each stage ends, ``on_skip(shortfall)`` for each rate or protocol
    left out because the log is too short for it.

    Example::

        result = starlog.run("sim.mcap", "result.mcap", config={
            "centroid": {"methods": "GAUSSFIT"}, "track": {"methods": ["GAUSSFIT"], "models": "STATIC"},
            "compensate": {"rates": [50], "protocols": "paper"}})
        print(result.to_dict()["layers"])
    """
    from starlog.errors import OutputExistsError
    from starlog.pipeline import PipelineConfig, load_config, report_path, run_pipeline
    from starlog.report import write_report

    html = report_path(Path(output))
    if report and html.exists() and not force:
        raise OutputExistsError(html)
    if isinstance(config, PipelineConfig):
        chosen = config
    elif isinstance(config, Mapping):
        chosen = PipelineConfig.from_dict(dict(config), source="the config given")
    else:
        chosen = load_config(config)
    result = run_pipeline(log, output, chosen, workers=_cores(workers), force=force, flatten=flatten,
                          compression=compression, show_progress=progress, on_stage=on_stage, on_skip=on_skip,
                          start=start, end=end)
    if report:
        write_report(output, html)
    return result


def export(log: PathLike, output: PathLike, *, tables: str | Sequence[str] | None = None,
           topics: str | Sequence[str] = (), force: bool = False) -> dict[str, int]:
    """Write the log's tables as Parquet files in the folder ``output`` (``starlog export``); returns
    ``{table: rows}``. ``tables``: only these (a name, a list or ``"a,b"``; default every table the log has);
    ``topics``: other channels written as flat tables. In memory instead: ``starlog.open(log).table(name)``.

    Example::

        starlog.export("result.mcap", "tables/")
    """
    from starlog.parquet import export_log

    return export_log(log, output, tables=_names(tables), force=force, topics=_names(topics) or [])


def flatten(log: PathLike, output: PathLike, *, force: bool = False) -> CopyReport:
    """Write a chain of layers as one self-contained log (``starlog flatten``), chunks copied byte for byte.

    Example::

        starlog.flatten("result.mcap", "result-whole.mcap")
    """
    from starlog.io.copying import flatten_log

    return flatten_log(log, output, force=force)


def verify(log: PathLike, *, file_only: bool = False, progress: bool = False) -> ChainReport:
    """Check every record of a log and of its chain's files (``starlog verify``); a damaged file is reported, not
    raised: the report's ``status`` is ``"valid"``, ``"nonconformant"``, ``"refused"`` or ``"damaged"``,
    ``lines()`` says why and ``exit_status`` is the command's. ``file_only`` checks the file without its chain.

    Example::

        report = starlog.verify("result.mcap")
        assert report.ok, "\\n".join(report.lines())
    """
    from tqdm import tqdm

    from starlog.io.verify import verify_log
    from starlog.replay.progress import hidden

    if not Path(log).is_file():
        raise LogNotFoundError(log)
    with tqdm(desc="verify", unit="B", unit_scale=True, leave=False, dynamic_ncols=True,
              disable=hidden() if progress else True) as bar:

        def advance(done: int, total: int) -> None:
            bar.total = total
            bar.update(done - bar.n)

        return verify_log(log, chain=not file_only, on_progress=advance)
