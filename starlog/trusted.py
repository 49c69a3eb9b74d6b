"""What ``"trusted"`` stands for in a pipeline config's ``[track] methods``: the centroid method the log's evidence
names, decided once the centroids are written.

The evidence (:func:`starlog.centroiding.evidence.trust`) is the sky's when the frames plate-solve (a ``solve``
record's catalogue residuals, else a few frames solved in memory, :func:`starlog.stages.solve.probe_sky`, when
cedar-solve is installed), else the centroid stage's frame-to-frame noise. A log too short or too sparse for
either keeps :data:`DEFAULT_TRACKED`, saying so. The decision and its reason go into the track stage's
provenance (``selected_by``) and ``starlog run``'s summary.
"""

from __future__ import annotations

from typing import Any

from starlog.io.reader import LogReader, LogSource

__all__ = ["DEFAULT_TRACKED", "TRUSTED", "default_tracked", "resolve_trusted", "tracks_trusted", "trusted_method",
           "with_trusted"]

#: The word ``[track] methods`` uses for the method the log's evidence names (:func:`trusted_method`).
TRUSTED = "trusted"
#: The method tracked as ``"trusted"`` when the evidence names none (the built-in config's before it followed it).
DEFAULT_TRACKED = "GAUSSFIT"


def _list(value: Any) -> list[str]:
    return [value] if isinstance(value, str) else list(value)


def tracks_trusted(track: dict[str, Any] | None) -> bool:
    """Whether a ``[track]`` table names the method ``"trusted"`` (:data:`TRUSTED`)."""
    return track is not None and TRUSTED in [m.lower() for m in _list(track.get("methods", []))]


def trusted_method(log: LogReader) -> dict[str, Any]:
    """The centroid method ``"trusted"`` stands for in a log (:func:`starlog.centroiding.evidence.trust`): from its
    solve record's catalogue residuals, else from the sky probed on a few frames in memory
    (:func:`starlog.stages.solve.probe_sky`), else from the centroid stage's frame-to-frame noise; with none of
    them, :data:`DEFAULT_TRACKED` (the built-in config's method before the evidence), saying so. Returns
    ``method``, ``evidence`` (``"sky"``, ``"frame-to-frame"`` or None), ``figure_px``, ``interval_px``, ``p_best``
    and ``reason``."""
    from starlog.centroiding.evidence import trust
    from starlog.facts import evidence_summaries, trust_summary
    from starlog.stages.solve import probe_sky

    decision = trust_summary(log).get("trust")
    if decision is None or decision["evidence"] != "sky":
        channels = [c.topic for c in log.channels() if c.schema_name == "starlog.Centroids"]
        records = [r for r in evidence_summaries(log).get("centroid_evidence", []) if "error" not in r]
        sky, why = probe_sky(log, channels)
        decision = trust(records[-1]["methods"] if records else None, sky, sky_missing=why)
    if decision["method"] is not None:
        return decision
    fallback = default_tracked([c.topic.rsplit("/", 1)[-1] for c in log.channels()
                                if c.schema_name == "starlog.Centroids"])
    return decision | {"method": fallback, "reason": f"kept the default {fallback}: {decision['reason']}"}


def default_tracked(methods: list[str]) -> str:
    """The method ``"trusted"`` stands for when the evidence names none, of the centroid ``methods`` measured:
    :data:`DEFAULT_TRACKED` when it is one of them (or there are none), else the first other than NONE."""
    if DEFAULT_TRACKED in methods or not methods:
        return DEFAULT_TRACKED
    return next((m for m in methods if m != "NONE"), methods[0])


def resolve_trusted(track: dict[str, Any], log_path: LogSource) -> tuple[dict[str, Any], dict[str, Any]]:
    """The ``[track]`` table with ``"trusted"`` replaced by :func:`trusted_method` of the log at ``log_path``
    (repeats dropped) and that decision under ``selected_by`` (the track stage records it), and the decision."""
    with LogReader(log_path) as log:
        decision = trusted_method(log)
    return {**track, "methods": with_trusted(track, decision["method"]), "selected_by": decision}, decision


def with_trusted(track: dict[str, Any], method: str) -> list[str]:
    """A ``[track]`` table's methods with ``"trusted"`` standing for ``method`` (repeats dropped)."""
    return list(dict.fromkeys(method if m.lower() == TRUSTED else m.upper() for m in _list(track["methods"])))
