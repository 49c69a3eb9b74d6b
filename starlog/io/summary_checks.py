"""The checks of a summary that a reader makes on opening a file: its indexes point inside the data section and
name the channels and schemas the file defines.

Each check returns what is wrong, in words (at most a few of each kind); :class:`~starlog.io.mcap_file.McapFile`
refuses a file with any.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
from mcap.records import ChunkIndex
from mcap.summary import Summary

from starlog.io.chunk_indexes import ChunkIndexTable
from starlog.io.layout import MAGIC

__all__ = ["chunk_index_problems", "layout_problems", "missing_schemas", "reference_problems"]


def missing_schemas(summary: Summary) -> set[int]:
    """The schema ids the summary's channels name that its schemas do not hold."""
    return {ch.schema_id for ch in summary.channels.values() if ch.schema_id} - summary.schemas.keys()


def layout_problems(summary: Summary, data_end: int) -> list[str]:
    """What points outside the data section (which ends at ``data_end``): chunk, metadata and attachment indexes."""
    problems = chunk_index_problems(summary.chunk_indexes, data_end)  # type: ignore[arg-type]  # a ChunkIndexTable
    for mi in summary.metadata_indexes:
        if not len(MAGIC) <= mi.offset < mi.offset + mi.length <= data_end:
            problems.append(f"metadata index {mi.name!r} points outside the data section")
    for ai in summary.attachment_indexes:
        if not len(MAGIC) <= ai.offset < ai.offset + ai.length <= data_end:
            problems.append(f"attachment index {ai.name!r} points outside the data section")
    return problems


def reference_problems(summary: Summary, loose: Iterable[ChunkIndex], extents: dict[int, list[int]]) -> list[str]:
    """Channels naming an undefined schema, and channel ids the indexes, statistics or messages name that no channel
    defines (in the summary or, where it does not repeat them, the data section). ``loose``: the runs of messages
    outside chunks; ``extents``: the messages per channel of the chunks without message indexes."""
    missing = missing_schemas(summary)
    problems = [f"channel {ch.topic!r} refers to missing schema {ch.schema_id}"
                for ch in summary.channels.values() if ch.schema_id in missing]
    table: ChunkIndexTable = summary.chunk_indexes  # type: ignore[assignment]  # as read_summary makes it
    unknown = sorted(table.channel_ids() - summary.channels.keys())[:3]
    if unknown:
        offsets = table.column("chunk_start_offset")
        problems += [f"chunk index for offset {int(offsets[row])} names unknown channel {cid}"
                     for cid, row in sorted(table.first_rows(unknown).items())]
    counted = summary.statistics.channel_message_counts if summary.statistics else {}
    named = {c: 1 for run in loose for c in run.message_index_offsets}
    for what, ids in (("statistics count messages of", counted),
                      ("chunks without message indexes hold messages of", extents),
                      ("messages outside chunks name", named)):
        unknown = sorted(c for c, n in ids.items() if n and c not in summary.channels)
        if unknown:
            problems.append(f"{what} unknown channels {unknown}")
    return problems


def chunk_index_problems(table: ChunkIndexTable, data_end: int) -> list[str]:
    """What is wrong with the chunk indexes (at most three of each kind): ranges outside the data
    section, reversed time ranges, message indexes outside the data section.

    Checked a block of chunks at a time, so the temporary arrays stay the size of a block.
    """
    kinds: list[list[str]] = [[], [], []]
    for block in table.row_blocks():
        for kind, found in zip(kinds, _block_problems(table, block, data_end), strict=True):
            kind.extend(found[:3 - len(kind)])
        if all(len(kind) == 3 for kind in kinds):
            break
    return [problem for kind in kinds for problem in kind]


def _block_problems(table: ChunkIndexTable, block: tuple[int, int, int, int], data_end: int
                    ) -> tuple[list[str], list[str], list[str]]:
    """:func:`chunk_index_problems` of each kind among the chunks of one of ``table.row_blocks()``."""
    a, b, e0, e1 = block
    start = table.column("chunk_start_offset")[a:b]
    end = start + table.column("chunk_length")[a:b]  # wraps past 2**64 for a damaged length: then end <= start

    def chunks_where(bad: np.ndarray, what: str) -> list[str]:
        return [f"chunk index for offset {int(start[k])} {what}" for k in np.flatnonzero(bad)[:3]]

    rows, _, offset = table.entries()
    rows, offset = rows[e0:e1] - a, offset[e0:e1]
    first = table.first_index_offsets()[a:b]
    index_end = first + table.column("message_index_length")[a:b]
    outside = (table.entry_counts(a, b) > 0) & (
        (first < end) | (first >= data_end) | (index_end < first) | (index_end > data_end))
    outside[rows[(offset < end[rows]) | (offset >= data_end)]] = True
    return (
        chunks_where((start < len(MAGIC)) | (end <= start) | (end > data_end), "points outside the data section"),
        chunks_where(table.column("message_start_time")[a:b] > table.column("message_end_time")[a:b],
                     "has its time range reversed"),
        chunks_where(outside, "has a message index outside the data section"),
    )
