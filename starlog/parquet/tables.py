"""Parquet export: one table per channel family, streamed in row groups (memory flat in log length).

Every table is declared here, in :data:`TABLES` (which channels feed it and how a message
becomes rows), and its columns once, in ``schemas/tables.json``, which this module turns into
Arrow schemas (with each column's description and unit as field metadata) and which docs/FORMATS.md
documents. A family is written only when the log has its channels. The per-star tables are read
as tables (:meth:`~starlog.io.reader.LogReader.tables`): each message's rows become columns whole,
with no dict per star.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager, suppress
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import pyarrow as pa

from starlog.errors import InvalidParameterError, OutputExistsError, file_errors
from starlog.parquet.channels import export_image_frames, export_topic, parquet_writer
from starlog.io.reader import ChannelSummary, LogReader, TableMessage
from starlog.io.schemas import schema_dir
from starlog.io.writer import atomic_output
from starlog.io import topics

__all__ = ["TABLES", "TableSpec", "arrow_schema", "export_log", "family_table", "table_columns", "table_of_channel"]

_ARROW_TYPES: dict[str, pa.DataType] = {
    "int64": pa.int64(),
    "int32": pa.int32(),
    "float64": pa.float64(),
    "string": pa.string(),
    "bool": pa.bool_(),
}

Row = dict[str, Any]
RowMaker = Callable[[ChannelSummary, int, Any], Iterable[Row]]
#: A star-table message → its columns (name → one value per row), for tables fed by star tables.
ColumnMaker = Callable[[TableMessage], dict[str, npt.ArrayLike]]


@cache
def table_columns() -> dict[str, Any]:
    """The ``tables`` mapping of ``schemas/tables.json``."""
    return json.loads((schema_dir() / "tables.json").read_text(encoding="utf-8"))["tables"]


def arrow_schema(table: str) -> pa.Schema:
    """Arrow schema of ``table`` with per-column description/unit metadata."""
    spec = table_columns()[table]
    fields = []
    for name, col in spec["columns"].items():
        meta = {"description": col["description"]}
        if "unit" in col:
            meta["unit"] = col["unit"]
        fields.append(pa.field(name, _ARROW_TYPES[col["type"]], nullable=False, metadata=meta))
    return pa.schema(fields, metadata={"description": spec["description"]})


@dataclass(frozen=True)
class TableSpec:
    """A Parquet table: which channels feed it and how a message becomes rows (a dict per row, from the
    message's dict; or ``columns`` from its rows as a structured array, for a per-star table)."""

    name: str
    matches: Callable[[ChannelSummary], bool]
    rows: RowMaker | None = None
    columns: ColumnMaker | None = None


def _frame_rows(ch: ChannelSummary, log_time: int, msg: Any) -> Iterator[Row]:
    yield {"log_time": log_time, **msg}


def _per_star_rows(ch: ChannelSummary, log_time: int, msg: Any) -> Iterator[Row]:
    """Truth: one row per star of the frame."""
    for star in msg["stars"]:
        yield {"log_time": log_time, "frame": msg["frame"], **star}


def _star_columns(*header: str) -> ColumnMaker:
    """A per-star table's columns: ``log_time``, the ``header`` fields repeated on every row, then the rows'
    fields (a row field that an older log lacks reads as its default: ``n_masked`` 0)."""

    def columns(message: TableMessage) -> dict[str, npt.ArrayLike]:
        rows = message.rows if message.rows is not None else np.zeros(0)
        n = rows.size
        out: dict[str, npt.ArrayLike] = {"log_time": np.full(n, message.log_time, dtype=np.int64)}
        out.update({key: [message.header[key]] * n for key in header})
        out.update({name: rows[name] for name in rows.dtype.names or ()})
        return out

    return columns


def _motion_rows(ch: ChannelSummary, log_time: int, msg: Any) -> Iterator[Row]:
    yield {"log_time": log_time, **msg}


def _series_rows(ch: ChannelSummary, log_time: int, msg: Any) -> Iterator[Row]:
    """A compensated sample; method, model, rate, protocol and motion mode come from its topic."""
    _, _, method, model, rate, protocol, *separate = ch.topic.split("/")
    yield {"log_time": log_time, "method": method, "model": model, "rate_hz": float(rate[:-2]),
           "protocol": protocol, "motion": separate[0] if separate else "keep", **msg}


def _decision_rows(ch: ChannelSummary, log_time: int, msg: Any) -> Iterator[Row]:
    """One row per compensation pass of a decision record, with the record's headline figures."""
    comp = msg["compensation"]
    primary = msg["figures"][0]
    base = {"log_time": log_time, "method": msg["method"], "model": msg["model"], "rate_hz": msg["rate_hz"],
            "protocol": msg["protocol"], "motion": msg.get("motion", "keep"), "n_samples": msg["n_samples"],
            "dominant_frequency": comp["decomposition"]["dominant_frequency"],
            "reference": primary["reference"], "protocol_rmse_before": primary["rmse_before"],
            "protocol_rmse_after": primary["rmse_after"]}
    for p in comp["passes"]:
        yield {**base, "rank": p["rank"], "strategy": p["strategy"], "score": p["score"],
               "rmse_before": p["rmse_before"], "rmse_after": p["rmse_after"], "effective": p["effective"],
               "kept": p["kept"]}


def _attitude_rows(ch: ChannelSummary, log_time: int, msg: Any) -> Iterator[Row]:
    """A frame's attitude: the quaternion in four columns, the attitude error NaN without a true attitude."""
    qx, qy, qz, qw = msg["quaternion"]
    nan = float("nan")
    yield {"log_time": log_time, **msg, "qx": qx, "qy": qy, "qz": qz, "qw": qw,
           **{k: msg.get(k, nan) for k in ("error_x_arcsec", "error_y_arcsec", "error_roll_arcsec")}}


def _topic_is(topic: str) -> Callable[[ChannelSummary], bool]:
    return lambda ch: ch.topic == topic


def _schema_is(schema_name: str) -> Callable[[ChannelSummary], bool]:
    return lambda ch: ch.schema_name == schema_name


#: Every table, in export order; the columns of each are in ``schemas/tables.json``.
TABLES: tuple[TableSpec, ...] = (
    TableSpec("frames", _topic_is(topics.FRAME_INFO), _frame_rows),
    TableSpec("truth", _topic_is(topics.TRUTH), _per_star_rows),
    TableSpec("detections", _topic_is(topics.DETECTIONS), columns=_star_columns("frame")),
    TableSpec("centroids", _schema_is("starlog.Centroids"), columns=_star_columns("frame", "method")),
    TableSpec("tracks", _schema_is("starlog.Tracks"), columns=_star_columns("frame", "method", "model")),
    TableSpec("motion", _schema_is("starlog.PlatformMotion"), _motion_rows),
    TableSpec("residuals", _schema_is("starlog.StarResiduals"),
              columns=_star_columns("frame", "method", "model", "fit")),
    TableSpec("compensation", _schema_is("starlog.CompensatedSample"), _series_rows),
    # the brightest track's records; the per-star records of ``compensate --stars all`` stay in the log
    TableSpec("decisions", lambda ch: ch.schema_name == "starlog.CompensationRecord"
              and not ch.topic.endswith("/stars/decisions"), _decision_rows),
    TableSpec("attitude", _schema_is("starlog.Attitude"), _attitude_rows),
    TableSpec("identified", _schema_is("starlog.IdentifiedStars"), columns=_star_columns("frame", "method")),
)


def _write_table(log: LogReader, spec: TableSpec, channels: list[ChannelSummary], path: Path,
                 row_group_rows: int, force: bool) -> int:
    """Write one table, a row group each time ``row_group_rows`` rows are gathered (after a whole message)."""
    written = 0
    with atomic_output(path, force=force) as tmp, parquet_writer(tmp, arrow_schema(spec.name)) as writer:
        for group in _row_groups(log, spec, channels, row_group_rows):
            writer.write_table(group)
            written += group.num_rows
    return written


def _row_groups(log: LogReader, spec: TableSpec, channels: list[ChannelSummary], row_group_rows: int,
                start: int | None = None, end: int | None = None) -> Iterator[pa.Table]:
    """The table's rows in groups of at least ``row_group_rows`` (whole messages; the last group smaller)."""
    schema = arrow_schema(spec.name)
    names = schema.names
    chunks: dict[str, list[Any]] = {n: [] for n in names}
    pending = 0
    for columns in _columns(log, spec, {c.topic: c for c in channels}, names, start, end):
        for n in names:
            chunks[n].append(columns[n])
        pending += len(columns[names[0]])
        if pending >= row_group_rows:
            yield pa.table({n: _joined(chunks[n], schema.field(n).type) for n in names}, schema=schema)
            pending = 0
            for n in names:
                chunks[n].clear()
    if pending:
        yield pa.table({n: _joined(chunks[n], schema.field(n).type) for n in names}, schema=schema)


def family_table(log: LogReader, name: str, *, topics: Iterable[str] | None = None, start: int | None = None,
                 end: int | None = None) -> pa.Table:
    """The table ``name`` of :data:`TABLES` as ``export`` writes it, in memory: every channel feeding it (or the
    ``topics`` among them), messages with ``start <= log_time < end`` only (the rest of the log is not read)."""
    spec = next((t for t in TABLES if t.name == name), None)
    if spec is None:
        raise InvalidParameterError(f"unknown table {name!r}; known tables: {[t.name for t in TABLES]}.")
    chosen = None if topics is None else set(topics)
    channels = [c for c in log.channels() if spec.matches(c) and (chosen is None or c.topic in chosen)]
    groups = list(_row_groups(log, spec, channels, 1 << 62, start, end))
    return groups[0] if groups else arrow_schema(name).empty_table()


def table_of_channel(channel: ChannelSummary) -> str | None:
    """The name of the table of :data:`TABLES` a channel feeds, if any."""
    return next((t.name for t in TABLES if t.matches(channel)), None)


def _joined(pieces: list[Any], kind: pa.DataType) -> pa.Array:
    """One column of a row group from its pieces, one per message: numpy arrays, or lists of Python values."""
    if pieces and isinstance(pieces[0], np.ndarray):
        return pa.array(np.concatenate(pieces), type=kind)
    return pa.array([value for piece in pieces for value in piece], type=kind)


def _columns(log: LogReader, spec: TableSpec, by_topic: dict[str, ChannelSummary], names: list[str],
             start: int | None = None, end: int | None = None) -> Iterator[dict[str, Any]]:
    """Each message's rows as columns (one list or array per column)."""
    if not by_topic:
        return
    if spec.columns is not None:
        for table in log.tables(list(by_topic), start=start, end=end):
            yield spec.columns(table)
        return
    assert spec.rows is not None
    for message in log.messages(list(by_topic), start=start, end=end):
        rows = list(spec.rows(by_topic[message.topic], message.log_time, message.payload))
        yield {n: [row[n] for row in rows] for n in names}


def export_log(
    log_path: str | os.PathLike[str],
    output_dir: str | os.PathLike[str],
    *,
    tables: Iterable[str] | None = None,
    force: bool = False,
    row_group_rows: int = 16_384,
    topics: Iterable[str] = (),
) -> dict[str, int]:
    """Write a Parquet file per table family found in the log; return ``{table: rows}``.

    Parameters
    ----------
    log_path : path-like
        The log to export.
    output_dir : path-like
        Folder for ``<table>.parquet`` (created if missing).
    tables : iterable of str, optional
        Only these tables (default: every table the log has channels for).
    force : bool
        Overwrite existing Parquet files.
    topics : iterable of str
        Channels exported as flat tables too (any JSON, protobuf, ROS 1 or ROS 2 channel),
        one ``<topic>.parquet`` each (see :func:`starlog.parquet.channels.export_topic`).

    A log without starlog's frame channel but with image channels gets a ``frames`` table of
    those (:func:`starlog.parquet.channels.export_image_frames`). Nothing to export raises
    :class:`InvalidParameterError` listing the log's channels.
    """
    known = [t.name for t in TABLES]
    wanted = list(tables) if tables is not None else known
    unknown = [t for t in wanted if t not in known]
    if unknown:
        raise InvalidParameterError(f"unknown table(s) {unknown}; known tables: {known}.")
    out = Path(output_dir)
    result: dict[str, int] = {}
    with _removed_on_error(out, result), LogReader(log_path) as log:
        channels = log.channels()
        for spec in TABLES:
            if spec.name not in wanted:
                continue
            feeding = [c for c in channels if spec.matches(c)]
            if not feeding:
                continue
            path = out / f"{spec.name}.parquet"
            if path.exists() and not force:
                raise OutputExistsError(path)
            result[spec.name] = _write_table(log, spec, feeding, path, row_group_rows, force)
        _export_foreign(log, out, result, wanted, list(topics), force, row_group_rows)
    return result


@contextmanager
def _removed_on_error(out: Path, written: dict[str, int]) -> Iterator[None]:
    """Make the folder ``out`` if missing; if the block fails, remove the tables it wrote (``written``: their
    names) and the folder when it made it: a failed export leaves nothing behind."""
    with file_errors(out):
        made = not out.is_dir()
        out.mkdir(parents=True, exist_ok=True)
    try:
        yield
    except BaseException:
        for name in written:
            with suppress(OSError):
                (out / f"{name}.parquet").unlink()
        if made:
            with suppress(OSError):  # not empty: files of the user's own are kept
                out.rmdir()
        raise


def _export_foreign(log: LogReader, out: Path, result: dict[str, int], wanted: list[str], topics: list[str],
                    force: bool, row_group_rows: int) -> None:
    """Frames of foreign image channels, the ``topics`` asked for, or an error when nothing was exported."""
    if "frames" in wanted and "frames" not in result:
        rows = export_image_frames(log, out, force=force, row_group_rows=row_group_rows)
        if rows is not None:
            result["frames"] = rows
    for topic in topics:
        name, rows = export_topic(log, topic, out, force=force, row_group_rows=row_group_rows)
        result[name] = rows
    if not result:
        listing = ", ".join(f"{c.topic} ({c.schema_name or 'no schema'})" for c in log.channels()) or "none"
        raise InvalidParameterError(
            f"{log.path}: nothing to export: the log has no channel of the tables {wanted} (channels: {listing}). "
            "Export any channel as a flat table with --topic TOPIC.")

