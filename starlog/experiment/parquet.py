"""The experiment's row lists as Parquet files: one typed column per field, its description as metadata."""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.parquet as pq

from starlog.io.output_files import atomic_output

__all__ = ["write_rows"]


def write_rows(rows: Sequence[Mapping[str, Any]], fields: Mapping[str, tuple[pa.DataType, str]],
               path: str | os.PathLike[str], *, metadata: Mapping[str, str] | None = None) -> Path:
    """Write ``rows`` as zstd Parquet with one column per ``fields`` entry (name -> (Arrow type,
    description)), in that order; ``metadata`` goes to the schema."""
    schema = pa.schema([pa.field(name, dtype, metadata={"description": text}) for name, (dtype, text) in fields.items()],
                       metadata=dict(metadata) if metadata else None)
    table = pa.table({name: [r[name] for r in rows] for name in fields}, schema=schema)
    path = Path(path)
    with atomic_output(path) as tmp:
        pq.write_table(table, tmp, compression="zstd")
    return path
