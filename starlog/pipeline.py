"""``starlog run``: replay a log through several stages from one TOML config file.

A config has one table per stage, run in the order centroid → track → compensate → solve; a
stage whose table is absent is skipped (``[compensate]``: ``stars = "all"`` also compensates every confirmed
track; ``[solve]``: ``centroids``, methods or ``"all"``, ``compensated`` (``"50/truth"`` or ``"all"``: the attitude
before and after compensation), and
``[solve.options]``, the options of :func:`starlog.stages.solve.solve_log`; it needs the optional
cedar-solve, ``pip install 'starlog[solve]'``). Each stage writes a layer (:mod:`starlog.io.chain`) on the
one before it: ``run LOG -o OUT.mcap`` writes ``OUT.1-centroid.mcap``, ``OUT.2-track-NONE.mcap``,
... and the last stage's layer as ``OUT.mcap`` itself, each file the bytes the stage run alone
with the same options and output name gives; reading ``OUT.mcap`` reads the whole chain. With
``flatten`` the layers go to a hidden folder beside ``OUT.mcap``, removed once their chain is
flattened into ``OUT.mcap``, one self-contained log. The built-in config is :data:`DEFAULT_CONFIG_TOML` (``starlog run
--print-config`` prints it).

Before any stage runs, the ``[compensate]`` rates and protocols are checked against the log's length
(:func:`starlog.stages.compensate.track_shortfalls`, the rule the compensate stage applies): the built-in
config leaves out those the log is too short for (:attr:`PipelineResult.skipped`); a config file that names
one is refused, naming each with the log length it needs.

Your own stages (:mod:`starlog.stage_api`) come after the built-in ones: one table
``[stages.NAME]`` each, with ``uses = "package.module:function"`` (or an installed stage's
name), optionally ``input_topic = "TOPIC"`` (or ``"all"``; ``input`` is its old name), and the stage's
options. They run in the
order of their tables, so each can read what the stages before it wrote.
"""

from __future__ import annotations

import os
import tomllib
from contextlib import suppress
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from starlog.batch import BatchOutcome, BatchTask, run_batch
from starlog.compensation import Shortfall
from starlog.errors import InvalidParameterError, OutputExistsError
from starlog import topics
from starlog.io.reader import LogReader, LogSource
from starlog.io.copying import flatten_log
from starlog.io.timerange import TimeRange
from starlog.io.output_files import output_identity, temporary_folder
from starlog.stages.centroid import centroid_log, parse_methods
from starlog.stages.compensate import compensate_log, parse_protocols, too_short_message, track_shortfalls
from starlog.replay.window import window_of
from starlog.stages.custom import run_stage
from starlog.stages.track import track_log
from starlog.trusted import resolve_trusted, tracks_trusted, with_trusted

if TYPE_CHECKING:
    from starlog.stage_api import Stage

__all__ = ["DEFAULT_CONFIG_TOML", "CustomStageConfig", "PipelineConfig", "PipelineResult", "fit_to_log", "layer_paths",
           "load_config", "possible_layers", "report_path", "run_pipeline", "run_pipeline_batch", "run_pipeline_task",
           "stage_line", "stage_steps"]

#: The built-in config, a starting point for your own (``starlog run --print-config``).
DEFAULT_CONFIG_TOML = """\
[centroid]
methods = "all"         # every method that can win (starlog centroid --method all)
# gain = 1.0            # e-/DN; default: from the simulator's provenance, else 1
# read_noise = 3.0      # e-; default: from the simulator's provenance, else estimated
# image_topic = "/camera/image_raw"  # default: /camera/image, else the log's only image channel
phase_correction = "auto"  # pixel-phase calibration from the log's own stars; "off", or a calibration file
# mode = "auto"         # "tracking": stars measured in windows, full searches every acquire_every frames; "full"
# acquire_every = 100   # tracking: frames between two full searches
[centroid.options]      # keyword options of starlog.centroiding.extract_stars

[track]
methods = ["NONE", "trusted"]   # centroid channels to track, one stage run each; "trusted": the method the log's
                                # evidence names once its centroids are written (GAUSSFIT when it names none)
models = "all"
[track.tracker]         # starlog.tracking.TrackerConfig fields
sigma_floor = 0.05      # px: the platform jitter a STATIC model must absorb
[track.motion]          # starlog.tracking.MotionModelConfig fields

[compensate]
tracks = "all"          # or ["GAUSSFIT/STATIC", ...]
rates = [10, 50]        # built-in config: a rate or protocol the log is too short for is left out;
protocols = "all"       # in a --config file, it is refused before any stage runs
[compensate.options]    # keyword options of starlog.compensation.evaluate
"""

_STAGE_KEYS: dict[str, set[str]] = {
    "centroid": {"methods", "gain", "read_noise", "options", "image_topic", "skip_bad", "psf", "phase_correction",
                 "mode", "acquire_every"},
    "track": {"methods", "models", "tracker", "motion"},
    "compensate": {"tracks", "rates", "protocols", "options", "stars"},
    "solve": {"centroids", "options", "compensated"},
}


@dataclass(frozen=True)
class PipelineConfig:
    """Parsed pipeline config: each stage's table, or None when the stage is skipped. ``builtin``: the built-in
    config (:func:`load_config` without a file), which leaves out the ``[compensate]`` rates and protocols a log is
    too short for; any other config that names one is refused."""

    centroid: dict[str, Any] | None = None
    track: dict[str, Any] | None = None
    compensate: dict[str, Any] | None = None
    solve: dict[str, Any] | None = None
    source: str = "<default>"
    stages: tuple[CustomStageConfig, ...] = ()
    builtin: bool = False

    @classmethod
    def from_dict(cls, data: dict[str, Any], *, source: str = "<dict>", folder: str | None = None) -> PipelineConfig:
        """Validate a config mapping (unknown tables or keys are errors, named with their place).

        ``folder`` (the config file's) is searched, after ``sys.path``, for the modules ``uses`` names.
        """
        unknown = sorted(set(data) - set(_STAGE_KEYS) - {"stages"})
        if unknown:
            raise InvalidParameterError(
                f"{source}: unknown table(s) {unknown}; a pipeline config has [centroid], [track], [compensate], "
                "[solve] and [stages.NAME] tables.")
        stages: dict[str, dict[str, Any] | None] = {}
        for stage, keys in _STAGE_KEYS.items():
            table = data.get(stage)
            if table is None:
                stages[stage] = None
                continue
            if not isinstance(table, dict):
                raise InvalidParameterError(f"{source}: [{stage}] must be a table.")
            bad = sorted(set(table) - keys)
            if bad:
                raise InvalidParameterError(
                    f"{source}: unknown key(s) {bad} in [{stage}]; allowed: {sorted(keys)}.")
            stages[stage] = dict(table)
        if stages["compensate"] is not None and "rates" not in stages["compensate"]:
            raise InvalidParameterError(f"{source}: [compensate] needs rates = [..] (Hz).")
        custom = _custom_stages(data.get("stages"), source=source, folder=folder)
        return cls(**stages, source=source, stages=custom)  # type: ignore[arg-type]


def load_config(path: str | os.PathLike[str] | None) -> PipelineConfig:
    """Read a TOML pipeline config (the default config when ``path`` is None)."""
    if path is None:
        config = PipelineConfig.from_dict(tomllib.loads(DEFAULT_CONFIG_TOML), source="the built-in config")
        return replace(config, builtin=True)
    try:
        text = Path(path).read_text(encoding="utf-8")
    except OSError as err:
        raise InvalidParameterError(f"cannot read config {path}: {err.strerror}.") from err
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise InvalidParameterError(f"{path}: not valid TOML ({err}).") from err
    return PipelineConfig.from_dict(data, source=str(path), folder=str(Path(path).resolve().parent))


def _list(value: Any) -> list[str]:
    return [value] if isinstance(value, str) else list(value)


@dataclass
class PipelineResult:
    """What each stage of :func:`run_pipeline` reported, in order, and the ``[compensate]`` rates and protocols
    the built-in config left out because the log is too short for them."""

    output: Path
    stages: list[tuple[str, dict[str, Any]]] = field(default_factory=list)
    layers: list[Path] = field(default_factory=list)
    skipped: list[Shortfall] = field(default_factory=list)
    trusted: dict[str, Any] | None = None
    """What ``"trusted"`` in ``[track]`` stood for and why (:func:`trusted_method`); None without it."""

    def lines(self) -> list[str]:
        """What ``starlog run`` prints: what ran, the method trusted, the headline compensation figures, what was
        left out, and where the report (beside the output, :func:`report_path`) and the rows are."""
        from starlog.report.summary import run_summary_lines

        return run_summary_lines(self.output, self.stages, report_path(self.output),
                                 [s.to_dict() for s in self.skipped], self.trusted)

    def to_dict(self) -> dict[str, Any]:
        return {"output": str(self.output), "layers": [str(p) for p in self.layers],
                "stages": [{"stage": s, **r} for s, r in self.stages], "skipped": [s.to_dict() for s in self.skipped],
                "trusted": self.trusted}


Step = Callable[[LogSource, Path], dict[str, Any]]


def _steps(config: PipelineConfig, *, workers: int, compression: str, show_progress: bool) -> list[tuple[str, Step]]:
    """Every stage run of ``config``, in order, as ``(name, step(input, layer) -> report)``; a step overwrites its
    layer (the caller refuses existing files first, unless told to overwrite them)."""
    steps: list[tuple[str, Step]] = []
    common: dict[str, Any] = {"compression": compression, "force": True}
    skip_short = config.builtin
    if config.centroid is not None:
        c = config.centroid
        steps.append(("centroid", lambda i, o: centroid_log(
            i, o, methods=c.get("methods", "all"), gain=c.get("gain"), read_noise=c.get("read_noise"),
            options=c.get("options"), image_topic=c.get("image_topic"), skip_bad=bool(c.get("skip_bad", False)),
            workers=workers, show_progress=show_progress, psf=c.get("psf"),
            phase_correction=c.get("phase_correction", "auto"), mode=c.get("mode", "auto"),
            acquire_every=c.get("acquire_every"), **common).to_dict()))
    if config.track is not None:
        t = config.track
        for method in _list(t.get("methods", ["GAUSSFIT"])):
            chosen = t.get("selected_by") if t.get("selected_by", {}).get("method") == method else None
            steps.append((f"track {method}", lambda i, o, m=method, why=chosen: track_log(
                i, o, method=m, models=t.get("models", "all"), tracker=t.get("tracker"), motion=t.get("motion"),
                workers=workers, show_progress=show_progress, selected_by=why, **common).to_dict()
                | ({"selected_by": why} if why else {})))
    if config.compensate is not None:
        k = config.compensate
        steps.append(("compensate", lambda i, o: compensate_log(
            i, o, rates=k["rates"], track=k.get("tracks", "all"), protocols=k.get("protocols", "all"),
            options=k.get("options"), skip_short=skip_short, show_progress=show_progress, stars=k.get("stars", "brightest"),
            **common).to_dict()))
    if config.solve is not None:
        v = config.solve
        steps.append(("solve", lambda i, o: _solve_step(i, o, v, show_progress=show_progress, **common)))
    for custom in config.stages:
        steps.append((custom.label, lambda i, o, c=custom: run_stage(
            c.load(), i, o, options=c.options, input_topic=c.input, workers=workers, show_progress=show_progress,
            **common).to_dict()))
    return steps


def stage_steps(config: PipelineConfig, *, workers: int = 1, compression: str = "zstd",
                show_progress: bool = False) -> list[tuple[str, Step]]:
    """Every stage run of ``config``, in order, as ``(name, step(input, layer) -> report)``, as :func:`run_pipeline`
    runs them (``starlog live`` runs those that need the whole log when its source ends)."""
    return _steps(config, workers=workers, compression=compression, show_progress=show_progress)


def fit_to_log(source: LogSource, config: PipelineConfig) -> tuple[PipelineConfig, list[Shortfall]]:
    """``config`` as :func:`run_pipeline` runs it on ``source``: the ``[compensate]`` rates and protocols the log
    is too short for left out (the built-in config) or refused (any other), and those left out."""
    frame_topic, options = _frame_channel(config)
    return _fit_to_length(source, config, frame_topic, options)


def _solve_step(source: LogSource, layer: Path, table: dict[str, Any], **keywords: Any) -> dict[str, Any]:
    """The ``[solve]`` step (imported when it runs: the stage needs the optional cedar-solve)."""
    from starlog.stages.solve import solve_log

    return solve_log(source, layer, centroids=table.get("centroids", "all"), compensated=table.get("compensated"),
                     options=table.get("options"), **keywords).to_dict()


def _frame_channel(config: PipelineConfig) -> tuple[Any, dict[str, Any]]:
    """The first stage's ``frame_topic(log, options)`` and its options: the channel ``frame:N`` counts."""
    stage: Any
    if config.centroid is not None:
        stage, options = centroid_log, {"image_topic": config.centroid.get("image_topic")}
    elif config.track is not None:
        stage, options = track_log, {"method": _list(config.track.get("methods", ["GAUSSFIT"]))[0]}
    elif config.compensate is None and config.solve is not None:
        from starlog.stages.solve import solve_log

        stage, options = solve_log, {"centroids": config.solve.get("centroids", "all")}
    else:
        stage, options = compensate_log, {"track": (config.compensate or {}).get("tracks", "all")}
    return stage.frame_topic, options


def run_pipeline(
    input_path: str | os.PathLike[str],
    output_path: str | os.PathLike[str],
    config: PipelineConfig,
    *,
    workers: int = 1,
    force: bool = False,
    flatten: bool = False,
    compression: str = "zstd",
    show_progress: bool = False,
    on_stage: Callable[[str, dict[str, Any]], None] | None = None,
    on_skip: Callable[[Shortfall], None] | None = None,
    start: str | int | None = None,
    end: str | int | None = None,
) -> PipelineResult:
    """Run the stages of ``config`` on ``input_path``, each writing a layer on the one before it
    (:func:`layer_paths`); the last one is ``output_path``.

    With ``flatten``, the layers are written in a hidden folder beside ``output_path`` and removed once
    their chain is flattened into ``output_path``, one self-contained file. With ``start`` / ``end`` the
    first stage runs on that window of the input (``frame:N`` counts its input channel) and the others
    on what it wrote: the layers are those of the first stage run with the same range, then the others
    without. If a stage fails, the layers this run wrote are removed.

    Before any stage runs, the ``[compensate]`` rates and protocols are checked against the log's length: the
    built-in config leaves out those it is too short for (``on_skip`` is called with each, before the first
    stage), any other config is refused with :class:`InvalidParameterError`.
    """
    output = Path(output_path)
    keywords = {"workers": workers, "compression": compression, "show_progress": show_progress}
    if not _steps(config, **keywords):
        raise InvalidParameterError(f"{config.source}: the config runs no stage.")
    trusted = None
    if tracks_trusted(config.track) and config.centroid is None:  # the input's own centroids hold the evidence
        track, trusted = resolve_trusted(config.track or {}, input_path)
        config = replace(config, track=track)
    frame_topic, options = _frame_channel(config)
    source = window_of(input_path, TimeRange.parse(start, end), lambda log: frame_topic(log, options))
    config, skipped = _fit_to_length(source, config, frame_topic, options)
    if on_skip:
        for shortfall in skipped:
            on_skip(shortfall)
    result = PipelineResult(output=output, skipped=skipped, trusted=trusted)
    if not flatten:
        _refuse_existing(possible_layers(output, config), force=force)
        result.layers = _run_plan(source, config, output, result, keywords, on_stage=on_stage)
        return result
    _refuse_existing([output], force=force)
    with temporary_folder(output) as folder:
        layers = _run_plan(source, config, folder / output.name, result, keywords, on_stage=on_stage)
        flatten_log(layers[-1], output, force=True)
    return result


def possible_layers(output: Path, config: PipelineConfig) -> list[Path]:
    """Every layer file a run of ``config`` into ``output`` may write: with ``"trusted"`` standing for each centroid
    method in turn (:func:`run_pipeline` and ``starlog live`` refuse them all before writing any)."""
    if config.centroid is None or config.track is None or not tracks_trusted(config.track):
        return layer_paths(output, [name for name, _ in stage_steps(config)])
    paths: list[Path] = []
    for method in parse_methods(config.centroid.get("methods", "all")):
        trial = replace(config, track={**config.track, "methods": with_trusted(config.track, method.value)})
        paths += [p for p in layer_paths(output, [n for n, _ in stage_steps(trial)]) if p not in paths]
    return paths


def _run_plan(source: LogSource, config: PipelineConfig, output: Path, result: PipelineResult,
              keywords: dict[str, Any], *, on_stage: Callable[[str, dict[str, Any]], None] | None) -> list[Path]:
    """Run every stage of ``config`` into the layers of ``output`` (:func:`layer_paths`) and return them. With
    ``"trusted"`` in ``[track]``, the centroid layer is written first and the method decided on it
    (:func:`resolve_trusted`). If a stage fails, the layers this run wrote are removed."""
    written: list[Path] = []
    try:
        if tracks_trusted(config.track) and config.centroid is not None:
            alone = replace(config, track=None, compensate=None, solve=None, stages=())
            first = layer_paths(output, ["centroid", "track"])[0]
            _run_steps(source, _steps(alone, **keywords), [first], result, on_stage=on_stage, written=written)
            track, result.trusted = resolve_trusted(config.track or {}, first)
            config = replace(config, track=track)
            steps = _steps(config, **keywords)
            layers = layer_paths(output, [name for name, _ in steps])
            _run_steps(first, steps[1:], layers[1:], result, on_stage=on_stage, written=written)
            return layers
        steps = _steps(config, **keywords)
        layers = layer_paths(output, [name for name, _ in steps])
        _run_steps(source, steps, layers, result, on_stage=on_stage, written=written)
        return layers
    except BaseException:
        for path in written:
            path.unlink(missing_ok=True)
        raise


def layer_paths(output: Path, stages: list[str]) -> list[Path]:
    """The file of each stage's layer in ``run ... -o OUTPUT``: ``OUTPUT`` for the last, ``STEM.N-STAGE.SUFFIX``
    beside it for the others (numbered in chain order)."""
    return [output.with_name(f"{output.stem}.{i}-{_slug(name)}{output.suffix}") for i, name in
            enumerate(stages[:-1], 1)] + [output]


def _slug(stage: str) -> str:
    return "".join(c if c.isalnum() or c in "-_" else "-" for c in stage.replace(" ", "-"))


def _refuse_existing(paths: list[Path], *, force: bool) -> None:
    for path in paths:
        if path.exists() and not force:
            raise OutputExistsError(path)


def _fit_to_length(source: LogSource, config: PipelineConfig, frame_topic: Any,
                   options: dict[str, Any]) -> tuple[PipelineConfig, list[Shortfall]]:
    """``config`` as it runs on ``source`` and the ``[compensate]`` rates and protocols it leaves out: those
    the log's first-stage channel is too short for (:func:`~starlog.stages.compensate.track_shortfalls`). The
    built-in config leaves them out (and the compensate stage when none is left); any other config is refused
    here, before any stage runs."""
    if config.compensate is None:
        return config, []
    k = config.compensate
    with LogReader(source) as log:
        channel = log.channel(frame_topic(log, options))
        protocols = parse_protocols(k.get("protocols", "all"), has_truth=log.has_topic(topics.TRUTH))
        short = track_shortfalls(log, [channel], k["rates"], protocols, options=k.get("options") or {})
    if not short:
        return config, []
    if not config.builtin:
        length = f"{channel.message_count} frames, {(channel.last_log_time - channel.first_log_time) * 1e-9:.2f} s"
        raise InvalidParameterError(too_short_message(
            f"{config.source}, [compensate]: {channel.topic} ({length})", short,
            "Give a longer log or range, or other rates or protocols in [compensate] (the built-in config, "
            "without --config, leaves out what a log is too short for)."))
    pairs = {(float(r), p) for r in k["rates"] for p in protocols}
    if pairs <= {(s.rate_hz, s.protocol) for s in short}:
        return replace(config, compensate=None), short
    return config, short


def _run_steps(source: LogSource, steps: list[tuple[str, Step]], layers: list[Path], result: PipelineResult, *,
               on_stage: Callable[[str, dict[str, Any]], None] | None, written: list[Path]) -> None:
    """Each step on the layer of the one before (the first on ``source``), each layer added to ``written`` once
    it is; a layer the failing step had already put in place is removed."""
    for (name, step), layer in zip(steps, layers, strict=True):
        before = output_identity(layer)
        try:
            report = step(source, layer)
        except BaseException:
            with suppress(OSError):
                if output_identity(layer) not in (None, before):
                    layer.unlink()
            raise
        written.append(layer)
        source = layer
        result.stages.append((name, report))
        if on_stage:
            on_stage(name, report)


def run_pipeline_task(input_path: str, output_path: str, config: PipelineConfig, *, force: bool = False,
                      flatten: bool = False, compression: str = "zstd", start: str | int | None = None,
                      end: str | int | None = None) -> dict[str, Any]:
    """One log of a batch (a picklable top-level function for Dask): serial per-frame work, JSON-ready result."""
    return run_pipeline(input_path, output_path, config, workers=1, force=force, flatten=flatten,
                        compression=compression, start=start, end=end).to_dict()


def run_pipeline_batch(logs: Sequence[Path], folder: Path, config: PipelineConfig, *, scheduler: str | None = None,
                       workers: int = 1, show_progress: bool = False, force: bool = False, flatten: bool = False,
                       compression: str = "zstd", start: str | int | None = None,
                       end: str | int | None = None) -> list[BatchOutcome]:
    """:func:`run_pipeline_task` on each log, its output of the same name in ``folder`` (created if missing), on a
    Dask cluster (:func:`starlog.batch.run_batch`); a failed log is reported in its outcome, the others complete."""
    folder.mkdir(parents=True, exist_ok=True)
    options = {"force": force, "flatten": flatten, "compression": compression, "start": start, "end": end}
    tasks = [BatchTask(str(log), run_pipeline_task, (str(log.absolute()), str((folder / log.name).absolute()), config),
                       options) for log in logs]
    return run_batch(tasks, scheduler=scheduler, workers=workers, show_progress=show_progress, description="run")


def report_path(output: Path) -> Path:
    """The HTML report ``starlog run`` writes beside its output: the output with the suffix ``.html``."""
    return output.with_suffix(".html") if output.suffix != ".html" else output.with_name(output.name + ".html")


def stage_line(stage: str, result: dict[str, Any]) -> str | None:
    """One line on a finished stage of :func:`run_pipeline` (its ``on_stage`` report): the centroid stage's stars
    per frame, each track stage's brightest star; None for the other stages."""
    if stage == "centroid":
        return (f"centroid: {result['frames']} frames, {result['detections_per_frame']:.1f} stars/frame, "
                f"methods {', '.join(result['methods'])}, {result['mode']} mode")
    if stage.startswith("track"):
        models = ", ".join(f"{m} (track {v['brightest_track']}, NIS {v['mean_nis']:.2f})"
                           for m, v in result["models"].items())
        why = result.get("selected_by")
        chosen = "" if not why else (f" (the trusted method, by {why['evidence']} evidence)" if why["evidence"]
                                     else " (the default: no evidence names a method)")
        return f"track {result['method']}{chosen}: brightest star under {models}"
    if stage == "solve":
        methods = ", ".join(f"{m} {v['solved']}/{v['frames']} solved, residual {v['residual_px']:.4f} px"
                            for m, v in result["methods"].items())
        return f"solve: {methods}"
    return None


# ---------------------------------------------------------------- your own stages
@dataclass(frozen=True)
class CustomStageConfig:
    """A ``[stages.NAME]`` table: the stage it uses, the channel it reads (None: chosen), its options."""

    label: str
    uses: str
    input: str | None = None
    options: dict[str, Any] = field(default_factory=dict)
    search_path: tuple[str, ...] = ()

    def load(self) -> Stage:
        """The declared stage ``uses`` names (imported on first use)."""
        from starlog.replay.plugins import resolve_stage

        return resolve_stage(self.uses, search_path=self.search_path)


def _custom_stages(tables: Any, *, source: str, folder: str | None) -> tuple[CustomStageConfig, ...]:
    """The ``[stages.NAME]`` tables, in config order; each stage is loaded and its options checked now."""
    if tables is None:
        return ()
    if not isinstance(tables, dict):
        raise InvalidParameterError(f"{source}: [stages] holds one table per stage, [stages.NAME].")
    out = []
    for label, table in tables.items():
        where = f"{source}: [stages.{label}]"
        if not isinstance(table, dict):
            raise InvalidParameterError(f"{where} must be a table.")
        if "input" in table and "input_topic" in table:
            raise InvalidParameterError(f"{where}: give input_topic once (input is its old name).")
        uses, topic = table.get("uses"), table.get("input_topic", table.get("input"))
        if not isinstance(uses, str) or not uses:
            raise InvalidParameterError(f'{where} needs uses = "package.module:function" (or an installed '
                                        "stage's name).")
        if topic is not None and not isinstance(topic, str):
            raise InvalidParameterError(f'{where}: input_topic must be a topic, e.g. input_topic = '
                                        '"/stars/centroids/GAUSSFIT".')
        options = {k: v for k, v in table.items() if k not in ("uses", "input", "input_topic")}
        config = CustomStageConfig(str(label), uses, topic, options, (folder,) if folder else ())
        try:
            config.load().resolve_options(options, where=where)
        except InvalidParameterError as err:
            raise InvalidParameterError(str(err) if str(err).startswith(where) else f"{where}: {err}") from err
        out.append(config)
    return tuple(out)
