"""``starlog run``: replay a log through several stages from one TOML config file.

A config has one table per stage, run in the order centroid → track → compensate; a stage
whose table is absent is skipped. Each stage writes only what it adds (a sidecar beside the
output, removed at the end) and reads its input and the sidecars before it as one log; the
output is written once and has the same bytes as running the stages one by one with the same
options. The built-in config is :data:`DEFAULT_CONFIG_TOML` (``starlog run --print-config``
prints it).
"""

from __future__ import annotations

import os
import tomllib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from starlog.errors import InvalidParameterError, OutputExistsError
from starlog.io.stack import StackedLog
from starlog.stages.centroid import centroid_log
from starlog.stages.compensate import compensate_log
from starlog.stages.track import track_log

__all__ = ["DEFAULT_CONFIG_TOML", "PipelineConfig", "load_config", "run_pipeline", "run_pipeline_task"]

#: The built-in config, a starting point for your own (``starlog run --print-config``).
DEFAULT_CONFIG_TOML = """\
[centroid]
methods = ["NONE", "MOMENT", "BICUBIC", "GAUSSFIT", "GRADIENT"]
# gain = 1.0            # e-/DN; default: from the simulator's provenance, else 1
# read_noise = 3.0      # e-; default: from the simulator's provenance, else estimated
# image_topic = "/camera/image_raw"  # default: /camera/image, else the log's only image channel
[centroid.options]      # keyword options of starlog.centroid.extract_stars

[track]
methods = ["NONE", "GAUSSFIT"]   # centroid channels to track, one stage run each
models = "all"
[track.tracker]         # starlog.track.TrackerConfig fields
sigma_floor = 0.05      # px: the platform jitter a STATIC model must absorb
[track.motion]          # starlog.track.MotionModelConfig fields

[compensate]
tracks = "all"          # or ["GAUSSFIT/STATIC", ...]
rates = [10, 50]
protocols = "all"
[compensate.options]    # keyword options of starlog.compensate.evaluate
"""

_STAGE_KEYS: dict[str, set[str]] = {
    "centroid": {"methods", "gain", "read_noise", "options", "image_topic", "skip_bad", "psf"},
    "track": {"methods", "models", "tracker", "motion"},
    "compensate": {"tracks", "rates", "protocols", "options"},
}


@dataclass(frozen=True)
class PipelineConfig:
    """Parsed pipeline config: each stage's table, or None when the stage is skipped."""

    centroid: dict[str, Any] | None = None
    track: dict[str, Any] | None = None
    compensate: dict[str, Any] | None = None
    source: str = "<default>"

    @classmethod
    def from_dict(cls, data: dict[str, Any], *, source: str = "<dict>") -> PipelineConfig:
        """Validate a config mapping (unknown tables or keys are errors, named with their place)."""
        unknown = sorted(set(data) - set(_STAGE_KEYS))
        if unknown:
            raise InvalidParameterError(
                f"{source}: unknown table(s) {unknown}; a pipeline config has [centroid], [track], [compensate].")
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
        return cls(**stages, source=source)  # type: ignore[arg-type]


def load_config(path: str | os.PathLike[str] | None) -> PipelineConfig:
    """Read a TOML pipeline config (the default config when ``path`` is None)."""
    if path is None:
        return PipelineConfig.from_dict(tomllib.loads(DEFAULT_CONFIG_TOML), source="<default config>")
    try:
        text = Path(path).read_text(encoding="utf-8")
    except OSError as err:
        raise InvalidParameterError(f"cannot read config {path}: {err.strerror}.") from err
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise InvalidParameterError(f"{path}: not valid TOML ({err}).") from err
    return PipelineConfig.from_dict(data, source=str(path))


def _list(value: Any) -> list[str]:
    return [value] if isinstance(value, str) else list(value)


@dataclass
class PipelineResult:
    """What each stage of :func:`run_pipeline` reported, in order."""

    output: Path
    stages: list[tuple[str, dict[str, Any]]] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return {"output": str(self.output), "stages": [{"stage": s, **r} for s, r in self.stages]}


Step = Callable[[StackedLog, Path], dict[str, Any]]


def _steps(config: PipelineConfig, *, workers: int, compression: str, show_progress: bool) -> list[tuple[str, Step]]:
    """Every stage run of ``config``, in order, as ``(name, step(input, sidecar) -> report)``."""
    steps: list[tuple[str, Step]] = []
    common: dict[str, Any] = {"compression": compression}
    if config.centroid is not None:
        c = config.centroid
        steps.append(("centroid", lambda i, o: centroid_log(
            i, o, methods=c.get("methods", "all"), gain=c.get("gain"), read_noise=c.get("read_noise"),
            options=c.get("options"), image_topic=c.get("image_topic"), skip_bad=bool(c.get("skip_bad", False)),
            workers=workers, show_progress=show_progress, psf=c.get("psf"), **common).to_dict()))
    if config.track is not None:
        t = config.track
        for method in _list(t.get("methods", ["GAUSSFIT"])):
            steps.append((f"track {method}", lambda i, o, m=method: track_log(
                i, o, method=m, models=t.get("models", "all"), tracker=t.get("tracker"), motion=t.get("motion"),
                workers=workers, show_progress=show_progress, **common).to_dict()))
    if config.compensate is not None:
        k = config.compensate
        steps.append(("compensate", lambda i, o: compensate_log(
            i, o, rates=k["rates"], track=k.get("tracks", "all"), protocols=k.get("protocols", "all"),
            options=k.get("options"), show_progress=show_progress, **common).to_dict()))
    return steps


def run_pipeline(
    input_path: str | os.PathLike[str],
    output_path: str | os.PathLike[str],
    config: PipelineConfig,
    *,
    workers: int = 1,
    force: bool = False,
    compression: str = "zstd",
    show_progress: bool = False,
    on_stage: Callable[[str, dict[str, Any]], None] | None = None,
) -> PipelineResult:
    """Run the stages of ``config`` on ``input_path``; the final log goes to ``output_path``.

    Each stage reads the input and the sidecars of the stages before it as one log
    (:class:`~starlog.io.stack.StackedLog`) and writes only its own records; the output is
    written once, at the end, and is the file the stages run one by one would have made.
    """
    output = Path(output_path)
    if output.exists() and not force:
        raise OutputExistsError(output)
    steps = _steps(config, workers=workers, compression=compression, show_progress=show_progress)
    if not steps:
        raise InvalidParameterError(f"{config.source}: the config runs no stage.")
    result = PipelineResult(output=output)
    stack = StackedLog.of(input_path)
    sidecars: list[Path] = []
    try:
        for name, step in steps:
            sidecar = output.with_name(f".{output.name}.{len(sidecars)}.sidecar")
            sidecar.unlink(missing_ok=True)
            report = step(stack, sidecar)
            sidecars.append(sidecar)
            stack = stack.extend(sidecar)
            result.stages.append((name, report))
            if on_stage:
                on_stage(name, report)
        stack.write_to(output, force=force)
    finally:
        for path in sidecars:
            path.unlink(missing_ok=True)
    return result


def run_pipeline_task(input_path: str, output_path: str, config: PipelineConfig, *, force: bool = False,
                      compression: str = "zstd") -> dict[str, Any]:
    """One log of a batch (a picklable top-level function for Dask): serial per-frame work, JSON-ready result."""
    return run_pipeline(input_path, output_path, config, workers=1, force=force,
                        compression=compression).to_dict()
