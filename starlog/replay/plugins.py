"""Finding declared stages: ``uses = "package.module:function"`` references and installed entry points.

An installed package registers its stages in the entry-point group ``starlog.stages``
(:data:`ENTRY_POINT_GROUP`), e.g. in its ``pyproject.toml``::

    [project.entry-points."starlog.stages"]
    flux_fwhm = "my_package.stages:flux_fwhm"

Listing them reads the packages' metadata only; a stage's module is imported when the stage
is run (or its ``--help`` shown), so ``starlog --help`` stays fast and a broken package
breaks only its own command.
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Sequence
from functools import lru_cache
from importlib.metadata import EntryPoint, entry_points
from typing import TYPE_CHECKING, Any

from starlog.errors import InvalidParameterError

if TYPE_CHECKING:  # imported when a stage is loaded: listing installed stages stays light (starlog --help)
    from starlog.replay.declaration import Stage

__all__ = ["ENTRY_POINT_GROUP", "load_reference", "load_registered", "registered_stages", "resolve_stage"]

#: The entry-point group under which installed packages register their stages.
ENTRY_POINT_GROUP = "starlog.stages"


def registered_stages() -> dict[str, EntryPoint]:
    """Entry points of the group ``starlog.stages`` by name (the first installed one wins a name)."""
    found: dict[str, EntryPoint] = {}
    for point in entry_points(group=ENTRY_POINT_GROUP):
        found.setdefault(point.name, point)
    return found


def distribution_of(point: EntryPoint) -> str:
    """``"package version"`` of the distribution that registered ``point`` (``"?"`` when unknown)."""
    dist = getattr(point, "dist", None)
    return f"{dist.name} {dist.version}" if dist is not None else "?"


def load_registered(name: str) -> Stage:
    """The stage registered as ``name``; a package that fails to load is named in the error."""
    point = registered_stages().get(name)
    if point is None:
        raise InvalidParameterError(f"no installed stage named {name!r} (entry-point group {ENTRY_POINT_GROUP!r}); "
                                    f"installed: {', '.join(sorted(registered_stages())) or 'none'}.")
    try:
        target = point.load()
    except Exception as err:  # any error of a third-party import: report it, never crash the caller
        raise InvalidParameterError(
            f"the stage {name!r} registered by {distribution_of(point)} ({point.value}) cannot be loaded: "
            f"{type(err).__name__}: {err}") from err
    return _as_stage(target, point.value)


def load_reference(reference: str, *, search_path: Sequence[str] = ()) -> Stage:
    """The stage named ``"package.module:function"``; ``search_path`` folders are tried after ``sys.path``."""
    module_name, sep, attribute = reference.partition(":")
    if not sep or not module_name or not attribute:
        raise InvalidParameterError(f"uses = {reference!r}: expected 'package.module:function'.")
    for folder in search_path:
        if folder not in sys.path:
            sys.path.append(folder)
    try:
        target: Any = importlib.import_module(module_name)
    except Exception as err:  # any error of a third-party import: report it with the reference
        raise InvalidParameterError(f"uses = {reference!r}: cannot import {module_name!r} "
                                    f"({type(err).__name__}: {err}).") from err
    for part in attribute.split("."):
        if not hasattr(target, part):
            raise InvalidParameterError(f"uses = {reference!r}: {module_name!r} has no {attribute!r}.")
        target = getattr(target, part)
    return _as_stage(target, reference)


def resolve_stage(uses: str, *, search_path: Sequence[str] = ()) -> Stage:
    """``uses`` as a config names it: ``"package.module:function"``, or the name of an installed stage."""
    if ":" in uses:
        return load_reference(uses, search_path=search_path)
    return load_registered(uses)


@lru_cache(maxsize=16)
def cached_reference(reference: str, search_path: tuple[str, ...]) -> Stage:
    """:func:`load_reference`, once per process (worker processes load their stage by reference)."""
    return load_reference(reference, search_path=search_path)


def _as_stage(target: Any, reference: str) -> Stage:
    from starlog.replay.declaration import Stage

    if not isinstance(target, Stage):
        raise InvalidParameterError(f"{reference} is not a declared stage: decorate the function with "
                                    "@starlog.stage_api.stage(name=..., version=..., reads=..., writes=...).")
    return target
