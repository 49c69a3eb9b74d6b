"""Declaring a stage: :func:`stage`, the :class:`Stage` it makes, its :class:`Message` and :class:`Output`.

What :mod:`starlog.replay.plugins` loads and :mod:`starlog.stages.custom` runs; users import it through
:mod:`starlog.stage_api`. It imports neither of them.
"""

from __future__ import annotations

import inspect
import json
import re
import sys
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from starlog.errors import InvalidParameterError
from starlog.codecs.json_schema import compile_json_schema
from starlog.codecs.schemas import MessageType

__all__ = ["KINDS", "Message", "Output", "Stage", "stage"]


#: What ``reads`` may name besides a topic ("/...") or a schema name: the channel kinds of a starlog log.
KINDS: dict[str, str | None] = {
    "image": None,  # any image channel starlog decodes (foxglove.RawImage, CompressedImage, ROS Image, ...)
    "centroids": "starlog.Centroids",
    "detections": "starlog.Detections",
    "tracks": "starlog.Tracks",
}

_NAME = re.compile(r"[a-z][a-z0-9_-]*\Z")
_RESERVED_OPTIONS = {"uses", "input"}


@dataclass(frozen=True)
class Message:
    """One message as a stage's function sees it.

    Attributes
    ----------
    topic : str
        The channel read.
    log_time : int
        The message's time (ns); the records returned for it are written at this time.
    index : int
        Position of the message in its channel, from 0 (the frame number, for an image channel).
    data : Any
        An image channel: the frame as a 2-D array (read-only; copy it to write into it).
        ``starlog.Centroids`` / ``Detections`` / ``Tracks``: the per-star table as the structured
        array the built-in stages use (``CENTROID_DTYPE``, ``DETECTION_DTYPE``, ``TRACK_DTYPE``
        plus ``brightest``), protobuf or (logs of earlier versions) JSON alike. starlog's other
        star tables: the dict of their JSON form. Any other JSON channel: the decoded dict; other
        protobuf and ROS channels: the decoded object.
    fields : dict
        A per-star table's other fields (e.g. ``{"frame": 12, "method": "GAUSSFIT"}``); for
        any other JSON channel the whole decoded dict, as in ``data``.
    """

    topic: str
    log_time: int
    index: int
    data: Any
    fields: dict[str, Any] = field(default_factory=dict)

    @property
    def frame(self) -> int:
        """The frame the message belongs to: its ``frame`` field when it has one, else its index."""
        value = self.fields.get("frame")
        return value if isinstance(value, int) and not isinstance(value, bool) else self.index


@dataclass(frozen=True)
class Output:
    """A channel a stage writes: its topic (``{name}`` stands for the last part of the input topic) and type."""

    topic: str
    message_type: MessageType

    @property
    def is_json(self) -> bool:
        return self.message_type.message_encoding == "json"

    def topic_for(self, input_topic: str) -> str:
        return self.topic.replace("{name}", input_topic.rstrip("/").rsplit("/", 1)[-1])


class Stage:
    """A declared stage (made by :func:`stage`); calling it calls its function."""

    def __init__(self, function: Callable[..., Any], *, name: str, version: str, reads: str,
                 outputs: tuple[Output, ...], description: str) -> None:
        self.function = function
        self.name = name
        self.version = version
        self.reads = reads
        self.outputs = outputs
        self.description = description
        self.options, self.required_options = _options_of(function, name)
        self.__doc__ = function.__doc__
        self.__wrapped__ = function

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        return self.function(*args, **kwargs)

    def __repr__(self) -> str:
        return f"<starlog stage {self.name} {self.version} ({self.reference})>"

    @property
    def reference(self) -> str:
        """``module:qualname`` of the function, as ``uses =`` names it."""
        return f"{self.function.__module__}:{self.function.__qualname__}"

    def importable(self) -> bool:
        """Whether :attr:`reference` leads back to this stage (worker processes load it by that name)."""
        module = sys.modules.get(self.function.__module__)
        if module is None or self.function.__module__ == "__main__" or "<locals>" in self.function.__qualname__:
            return False
        target: Any = module
        for part in self.function.__qualname__.split("."):
            target = getattr(target, part, None)
        return target is self

    def resolve_options(self, given: Mapping[str, Any] | None, *, where: str = "") -> dict[str, Any]:
        """The options of a run: the defaults updated with ``given`` (unknown or missing ones are errors)."""
        given = dict(given or {})
        place = where or f"stage {self.name!r}"
        unknown = sorted(set(given) - set(self.options) - set(self.required_options))
        if unknown:
            allowed = sorted([*self.options, *self.required_options]) or "none"
            raise InvalidParameterError(f"{place}: unknown option(s) {unknown}; the stage's options: {allowed}.")
        missing = sorted(set(self.required_options) - set(given))
        if missing:
            raise InvalidParameterError(f"{place}: the stage needs the option(s) {missing}.")
        options = {**self.options, **given}
        try:
            json.dumps(options, allow_nan=False)
        except (TypeError, ValueError) as err:
            raise InvalidParameterError(f"{place}: options must be JSON values (they go to the provenance): "
                                        f"{err}.") from err
        return options


def stage(*, name: str, version: str, reads: str, writes: Mapping[str, Any],
          description: str | None = None) -> Callable[[Callable[..., Any]], Stage]:
    """Declare a stage: decorate ``function(message, *, option=default, ...) -> record | None``.

    Parameters
    ----------
    name, version : str
        Recorded in the provenance; ``name`` is also the command an installed stage adds to
        ``starlog`` (lower case, digits, ``_`` and ``-``).
    reads : str
        The channel read: a topic (``"/stars/centroids/GAUSSFIT"``), a kind (``"image"``,
        ``"centroids"``, ``"detections"``, ``"tracks"``) or a schema name
        (``"starlog.Centroids"``). A kind or schema matching several channels needs the run's
        ``input`` (``--input TOPIC``, or ``--input all`` to read each in turn).
    writes : mapping
        Topic → JSON Schema of its records: a dict, or a ``.json`` file (a path relative to the
        function's module). A :class:`~starlog.codecs.schemas.MessageType` declares any other
        encoding (the function then returns the message's bytes or a protobuf object).
        With one channel the function returns its record (or None: nothing for this message);
        with several, a dict topic → record.
    description : str, optional
        One line for ``starlog --help`` (default: the first line of the function's docstring).
    """
    if not isinstance(name, str) or not _NAME.match(name):
        raise InvalidParameterError(f"stage name {name!r}: use lower-case letters, digits, '_' and '-'.")
    if not isinstance(reads, str) or not reads:
        raise InvalidParameterError(f"stage {name!r}: reads must be a topic, a kind {sorted(KINDS)} or a schema name.")
    if not writes:
        raise InvalidParameterError(f"stage {name!r}: writes must name at least one channel.")

    def declare(function: Callable[..., Any]) -> Stage:
        base = _module_folder(function)
        outputs = tuple(_output(name, topic, schema, base, len(writes)) for topic, schema in writes.items())
        summary = description or next(iter((function.__doc__ or "").strip().splitlines()), "")
        return Stage(function, name=name, version=str(version), reads=reads, outputs=outputs,
                     description=summary.strip())

    return declare


# ---------------------------------------------------------------- declaration helpers
def _options_of(function: Callable[..., Any], name: str) -> tuple[dict[str, Any], tuple[str, ...]]:
    """The keyword-only parameters of ``function``: defaults, and those without one."""
    try:
        parameters = list(inspect.signature(function).parameters.values())
    except (TypeError, ValueError) as err:
        raise InvalidParameterError(f"stage {name!r}: its function has no readable signature ({err}).") from err
    positional = [p for p in parameters if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD)]
    if len(positional) != 1:
        raise InvalidParameterError(f"stage {name!r}: the function takes the message as its one positional "
                                    "parameter, and its options as keyword-only ones (after '*').")
    keyword = [p for p in parameters if p.kind is p.KEYWORD_ONLY]
    clash = sorted(p.name for p in keyword if p.name in _RESERVED_OPTIONS)
    if clash:
        raise InvalidParameterError(f"stage {name!r}: option name(s) {clash} are reserved by the run config.")
    defaults = {p.name: p.default for p in keyword if p.default is not p.empty}
    return defaults, tuple(p.name for p in keyword if p.default is p.empty)


def _module_folder(function: Callable[..., Any]) -> Path:
    module = sys.modules.get(getattr(function, "__module__", ""), None)
    file = getattr(module, "__file__", None)
    return Path(file).resolve().parent if file else Path.cwd()


def _output(stage_name: str, topic: str, schema: Any, base: Path, count: int) -> Output:
    """One declared channel, its JSON Schema read and compiled (so a bad schema fails at declaration)."""
    if not isinstance(topic, str) or not topic.startswith("/"):
        raise InvalidParameterError(f"stage {stage_name!r}: output topic {topic!r} must start with '/'.")
    if isinstance(schema, MessageType):
        return Output(topic, schema)
    if isinstance(schema, (str, Path)):
        path = Path(schema) if Path(schema).is_absolute() else base / schema
        try:
            schema = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, ValueError) as err:
            raise InvalidParameterError(f"stage {stage_name!r}: cannot read the JSON Schema of {topic} from "
                                        f"{path} ({err}).") from err
    if not isinstance(schema, dict):
        raise InvalidParameterError(f"stage {stage_name!r}: the schema of {topic} must be a JSON Schema (dict or "
                                    f"file) or a MessageType, got {type(schema).__name__}.")
    try:
        compile_json_schema(schema)
    except (InvalidParameterError, ValueError, TypeError, KeyError) as err:
        raise InvalidParameterError(f"stage {stage_name!r}: the JSON Schema of {topic} cannot be checked "
                                    f"({err}).") from err
    title = schema.get("title") or (f"{stage_name}.Record" if count == 1 else f"{stage_name}{topic}")
    data = json.dumps(schema, sort_keys=True, separators=(",", ":")).encode()
    return Output(topic, MessageType(str(title), "jsonschema", data, "json"))
