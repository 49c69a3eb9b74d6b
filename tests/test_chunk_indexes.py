"""The summary's chunk indexes held by column (``starlog.io.chunk_indexes``), against ``mcap``'s own objects."""

from __future__ import annotations

import io
import struct
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from mcap.data_stream import RecordBuilder
from mcap.reader import make_reader
from mcap.records import ChunkIndex
from mcap.writer import CompressionType, Writer

from starlog.io import LogReader
from starlog.io.copying import flatten_log
from starlog.io.chunk_indexes import ChunkIndexTable
from starlog.io.summary_section import read_file_summary

U64 = st.integers(0, 2**64 - 1)

chunk_indexes = st.builds(
    ChunkIndex,
    chunk_length=U64, chunk_start_offset=U64, compression=st.sampled_from(["", "zstd", "lz4"]),
    compressed_size=U64, message_end_time=U64, message_index_length=U64,
    message_index_offsets=st.dictionaries(st.integers(0, 2**16 - 1), U64, max_size=5),
    message_start_time=U64, uncompressed_size=U64,
)


def _records(indexes: list[ChunkIndex]) -> bytes:
    out = RecordBuilder()
    for ci in indexes:
        ci.write(out)
    return out.end()


@settings(max_examples=200, deadline=None)
@given(st.lists(chunk_indexes, max_size=12))
def test_the_table_gives_back_every_field_and_the_same_records(indexes: list[ChunkIndex]) -> None:
    table = ChunkIndexTable(indexes)
    assert len(table) == len(indexes) and bool(table) == bool(indexes)
    assert list(table) == indexes
    assert [list(ci.message_index_offsets) for ci in table] == [list(ci.message_index_offsets) for ci in indexes]
    if indexes:
        assert table[-1] == indexes[-1] and table[1:] == indexes[1:]
    out = RecordBuilder()
    table.write_records(out.write)
    assert out.end() == _records(indexes)
    assert table.compressions() == {ci.compression for ci in indexes}
    assert table.entry_counts().tolist() == [len(ci.message_index_offsets) for ci in indexes]


@settings(max_examples=200, deadline=None)
@given(st.lists(chunk_indexes, max_size=12), st.sets(st.integers(0, 2**16 - 1), max_size=3), U64,
       st.integers(0, 2**64))
def test_selection_by_channel_and_time_is_the_filter_it_replaces(indexes: list[ChunkIndex], ids: set[int],
                                                                  lo: int, hi: int) -> None:
    table = ChunkIndexTable(indexes)
    expected = sorted(
        (ci for ci in indexes
         if (not ci.message_index_offsets or not ids.isdisjoint(ci.message_index_offsets))
         and ci.message_end_time >= lo and ci.message_start_time < hi),
        key=lambda ci: (ci.message_start_time, ci.chunk_start_offset))
    chosen = list(table.indexes_at(table.rows_for_channels(ids, lo, hi)))
    assert [(ci.message_start_time, ci.chunk_start_offset) for ci in chosen] == \
        [(ci.message_start_time, ci.chunk_start_offset) for ci in expected]


same_layouts = st.builds(  # few layouts, so that runs of records of one length and layout occur
    ChunkIndex,
    chunk_length=U64, chunk_start_offset=U64, compression=st.sampled_from(["", "zstd", "lz4\x00"]),
    compressed_size=U64, message_end_time=U64, message_index_length=U64,
    message_index_offsets=st.dictionaries(st.integers(0, 3), U64, max_size=2),
    message_start_time=U64, uncompressed_size=U64,
)


@settings(max_examples=300, deadline=None)
@given(st.lists(same_layouts, max_size=40), st.sampled_from([9, 64, 1 << 20]))
def test_a_summary_of_chunk_indexes_reads_back_run_by_run_as_record_by_record(
        indexes: list[ChunkIndex], block: int) -> None:
    """Runs of records of one length are parsed as columns; the table is the same as mcap's objects."""
    from mcap.records import Footer

    from starlog.io.summary_section import read_summary

    out = RecordBuilder()
    for ci in indexes:
        ci.write(out)
    Footer(summary_start=0, summary_offset_start=0, summary_crc=0).write(out)
    table = read_summary(io.BytesIO(out.end()), 0, block=block).chunk_indexes
    assert list(table) == indexes
    assert [list(ci.message_index_offsets) for ci in table] == [list(ci.message_index_offsets) for ci in indexes]
    assert table.entry_counts().tolist() == [len(ci.message_index_offsets) for ci in indexes]


def test_time_ranges_per_channel() -> None:
    def ci(start: int, end: int, channels: dict[int, int]) -> ChunkIndex:
        return ChunkIndex(chunk_length=10, chunk_start_offset=8, compression="", compressed_size=1,
                          message_end_time=end, message_index_length=0, message_index_offsets=channels,
                          message_start_time=start, uncompressed_size=1)

    table = ChunkIndexTable([ci(5, 9, {1: 100, 2: 120}), ci(2, 4, {2: 200}), ci(10, 30, {}), ci(7, 12, {1: 300})])
    assert table.channel_time_ranges() == {1: (5, 12), 2: (2, 9)}


def test_the_table_grows_after_a_query_and_its_arrays_are_read_only() -> None:
    first = ChunkIndex(chunk_length=10, chunk_start_offset=8, compression="zstd", compressed_size=1,
                       message_end_time=3, message_index_length=0, message_index_offsets={1: 30},
                       message_start_time=2, uncompressed_size=1)
    table = ChunkIndexTable([first])
    offsets = table.column("chunk_start_offset")
    with pytest.raises(ValueError, match="read-only"):
        offsets[0] = 99
    table.append(first)  # a view of the column is still alive
    assert offsets.tolist() == [8] and table.column("chunk_start_offset").tolist() == [8, 8]
    assert list(table) == [first, first]


def _foreign_log(path: Path, messages: int, chunk_size: int) -> Path:
    """A log written by the ``mcap`` library alone: two channels, many small chunks."""
    with open(path, "wb") as f:
        writer = Writer(f, chunk_size=chunk_size, compression=CompressionType.NONE)
        writer.start()
        schema = writer.register_schema(name="starlog.FrameInfo", encoding="jsonschema", data=b'{"type":"object"}')
        channels = [writer.register_channel(topic=t, message_encoding="json", schema_id=schema)
                    for t in ("/camera/frame", "/other")]
        for i in range(messages):
            writer.add_message(channels[0 if i % 3 == 0 else 1], log_time=1000 * i, publish_time=1000 * i,
                               data=b'{"frame":%d}' % i, sequence=i)
        writer.add_metadata("note", {"written by": "mcap"})
        writer.finish()
    return path


@pytest.mark.parametrize("chunk_size", [1, 64, 1 << 20])
def test_a_foreign_summary_reads_as_mcap_reads_it(tmp_path: Path, chunk_size: int) -> None:
    path = _foreign_log(tmp_path / "f.mcap", 3000, chunk_size)
    with open(path, "rb") as f:
        ours = read_file_summary(f)
        f.seek(0)
        theirs = make_reader(f).get_summary()
    assert ours is not None and theirs is not None
    assert list(ours.chunk_indexes) == theirs.chunk_indexes
    assert (ours.schemas, ours.channels, ours.statistics) == (theirs.schemas, theirs.channels, theirs.statistics)
    assert ours.metadata_indexes == theirs.metadata_indexes
    assert ours.attachment_indexes == theirs.attachment_indexes


def test_a_log_of_many_chunks_reads_in_time_order(tmp_path: Path) -> None:
    path = _foreign_log(tmp_path / "f.mcap", 3000, 1)
    with LogReader(path) as log:
        assert len(log.files[0].summary.chunk_indexes) == 3000
        frames = [m.payload["frame"] for m in log.messages("/camera/frame")]
        counts = {c.topic: (c.message_count, c.first_log_time, c.last_log_time) for c in log.channels()}
    assert frames == [i for i in range(3000) if i % 3 == 0]
    assert counts == {"/camera/frame": (1000, 0, 2_997_000), "/other": (2000, 1000, 2_999_000)}


# private _SummarySink._FLUSH_AT: the write size has no public setting; made small for small logs
def test_summaries_read_and_written_in_pieces_are_the_same_bytes(tmp_path: Path,
                                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    """Reading in blocks smaller than a record, and a summary written out every few records, change nothing."""
    from starlog.io import summary_section
    from starlog.io.layout import read_footer

    path = _foreign_log(tmp_path / "f.mcap", 2000, 1)
    with open(path, "rb") as f:
        whole = read_file_summary(f)
        footer = read_footer(f)
        pieces = summary_section.read_summary(f, footer.summary_start, footer.offset, block=37)
    assert pieces is not None and whole is not None
    assert pieces.chunk_indexes == whole.chunk_indexes and pieces.channels == whole.channels
    outputs = []
    for flush_at in (4 << 20, 100):
        monkeypatch.setattr(summary_section._SummarySink, "_FLUSH_AT", flush_at)
        out = tmp_path / f"out_{flush_at}.mcap"
        flatten_log(path, out)  # its summary repeats the input's chunk indexes
        outputs.append(out.read_bytes())
    assert outputs[0] == outputs[1]
    with LogReader(tmp_path / "out_100.mcap") as log:
        assert len(log.files[0].summary.chunk_indexes) == 2000
        assert log.channel("/camera/frame").message_count + log.channel("/other").message_count == 2000


# private scan._covered: the merged ranges are seen publicly only as the loose runs found between them; tested directly
def test_gaps_between_indexed_records_are_those_of_the_objects(tmp_path: Path) -> None:
    """The merged ranges the indexes cover leave the same gaps as the ranges taken one by one."""
    from starlog.io.scan import _covered

    path = _foreign_log(tmp_path / "f.mcap", 500, 64)
    with open(path, "rb") as f:
        summary = read_file_summary(f)
    assert summary is not None
    spans = []
    for ci in summary.chunk_indexes:
        spans.append((ci.chunk_start_offset, ci.chunk_start_offset + ci.chunk_length))
        first = min(ci.message_index_offsets.values())
        spans.append((first, first + ci.message_index_length))
    spans += [(m.offset, m.offset + m.length) for m in summary.metadata_indexes]

    def gaps(ranges: list[tuple[int, int]]) -> list[tuple[int, int]]:
        out, pos = [], 0
        for lo, hi in sorted(ranges):
            if lo > pos:
                out.append((pos, lo))
            pos = max(pos, hi)
        return out

    merged = _covered(summary)
    assert gaps(merged) == gaps(spans) and len(merged) <= 2  # the data section, then the metadata record


def test_a_damaged_chunk_index_is_refused_without_building_anything_large(tmp_path: Path) -> None:
    data = _foreign_log(tmp_path / "f.mcap", 30, 1).read_bytes()
    (summary_start,) = struct.unpack_from("<Q", data, len(data) - 8 - 29 + 9)
    first_index = data.index(bytes([0x08]), summary_start)  # the first Chunk Index record (opcode 0x08)
    damaged = bytearray(data)
    damaged[first_index + 9 + 32:first_index + 9 + 36] = (10 * 400_000_000).to_bytes(4, "little")
    with pytest.raises(ValueError, match="do not fit"):
        read_file_summary(io.BytesIO(bytes(damaged)))


def test_a_failed_append_leaves_the_table_as_it_was() -> None:
    table = ChunkIndexTable()
    with pytest.raises(ValueError):
        table.append_fields(1, 2, 8, 10, 0, 1, 1, "", [1, 2], [30])
    with pytest.raises(OverflowError):
        table.append_fields(1, 2, 8, -10, 0, 1, 1, "", [], [])
    assert len(table) == 0 and list(table) == [] and table.entry_counts().tolist() == []


def test_a_summary_cut_short_is_refused(tmp_path: Path) -> None:
    data = _foreign_log(tmp_path / "f.mcap", 300, 1).read_bytes()
    (summary_start,) = struct.unpack_from("<Q", data, len(data) - 8 - 29 + 9)  # the footer's first field
    damaged = bytearray(data)
    damaged[summary_start + 1:summary_start + 9] = (10**9).to_bytes(8, "little")  # a record longer than the file
    with pytest.raises(ValueError, match="runs past the end of its section"):
        read_file_summary(io.BytesIO(bytes(damaged)))


SMALL = st.integers(0, 200)

#: Chunk indexes of small offsets and lengths, whose ranges overlap and touch across block edges.
nearby_chunk_indexes = st.builds(
    ChunkIndex,
    chunk_length=SMALL, chunk_start_offset=SMALL, compression=st.sampled_from(["", "zstd"]),
    compressed_size=SMALL, message_end_time=SMALL, message_index_length=SMALL,
    message_index_offsets=st.dictionaries(st.integers(0, 3), SMALL, max_size=3),
    message_start_time=SMALL, uncompressed_size=SMALL,
)


# private _covered: its blocks need 65,536+ chunks in a real log; tested directly on tables (with chunk_index_problems)
@settings(max_examples=300, deadline=None)
@given(st.lists(st.one_of(chunk_indexes, nearby_chunk_indexes), max_size=9), st.integers(1, 4),
       st.one_of(st.integers(0, 2**64 - 1), SMALL))
def test_checks_and_gaps_made_block_by_block_are_those_of_the_whole_table(
        indexes: list[ChunkIndex], block: int, data_end: int) -> None:
    """A union of unions is the union, and the first three problems of each kind come in file order,
    so blocks of any size give what one block of the whole table gives."""
    from mcap.summary import Summary

    import starlog.io.chunk_indexes as chunk_module
    from starlog.io.scan import _covered
    from starlog.io.summary_checks import chunk_index_problems

    def both() -> tuple[list[str], list[tuple[int, int]]]:
        summary = Summary()
        summary.chunk_indexes = ChunkIndexTable(indexes)  # type: ignore[assignment]
        return (chunk_index_problems(summary.chunk_indexes, data_end),  # type: ignore[arg-type]
                _covered(summary))

    whole = both()
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(chunk_module, "ROW_BLOCK", block)
        assert len(list(ChunkIndexTable(indexes).row_blocks())) == -(-len(indexes) // block)
        assert both() == whole


@settings(max_examples=200, deadline=None)
@given(st.lists(st.one_of(chunk_indexes, nearby_chunk_indexes), max_size=9), st.sets(st.integers(0, 5), max_size=4))
def test_the_channels_listed_and_the_first_chunk_listing_each_are_those_of_the_chunk_indexes(
        indexes: list[ChunkIndex], asked: set[int]) -> None:
    table = ChunkIndexTable(indexes)
    listed = {cid for ci in indexes for cid in ci.message_index_offsets}
    assert table.channel_ids() == listed
    firsts = table.first_rows(asked)
    assert set(firsts) == asked & listed
    for cid, row in firsts.items():  # the lowest offset listing it; of two at one offset, the first in the table
        naming = [k for k, ci in enumerate(indexes) if cid in ci.message_index_offsets]
        assert row == min(naming, key=lambda k: indexes[k].chunk_start_offset)


def test_blocks_and_row_ranges_out_of_bounds_are_refused() -> None:
    table = ChunkIndexTable([ChunkIndex(chunk_length=1, chunk_start_offset=8 + k, compression="", compressed_size=1,
                                        message_end_time=k, message_index_length=0, message_index_offsets={0: 9 + k},
                                        message_start_time=k, uncompressed_size=1) for k in range(5)])
    assert [b[:2] for b in table.row_blocks(2)] == [(0, 2), (2, 4), (4, 5)]
    assert table.entry_counts(1, 3).tolist() == [1, 1]
    for size in (0, -1):
        with pytest.raises(ValueError):
            list(table.row_blocks(size))
    for start, stop in ((2, 1), (-1, 3), (0, 6)):
        with pytest.raises(IndexError):
            table.entry_counts(start, stop)
