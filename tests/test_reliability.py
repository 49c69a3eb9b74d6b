"""A corpus of broken logs. Every command gives a clear StarlogError or a correct recovery.

Never an uncaught non-starlog exception, never silently wrong data: whenever a read succeeds,
what it returns is compared with the intact log.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from click.testing import CliRunner

from starlog.cli import cli
from starlog.errors import (
    CorruptChunkError,
    CorruptLogError,
    InvalidMessageError,
    MessageDecodeError,
    NotMcapError,
    StarlogError,
    TruncatedLogError,
)
from starlog.io import LogReader, LogWriter, Provenance, file_digest
from starlog.codecs import decode_raw_image, encode_json, encode_raw_image, json_message_type, protobuf_message_type
from starlog import topics
from starlog.io.recover import recover_log
from starlog.codecs.schemas import MessageType
from starlog.stages import simulate_log
from tests.helpers import killed_writer_bytes, small_config

Content = dict[tuple[str, int, int], bytes]  # (topic, log_time, n-th message at that time) -> bytes


# ---------------------------------------------------------------- building blocks
def _rewrite(src: Path, dst: Path, *, chunk_size: int = 2048, compression: str = "lz4") -> None:
    """Copy ``src`` into a log with many small chunks (so damage lands in many places)."""
    with LogReader(src) as log, LogWriter(dst, chunk_size=chunk_size, compression=compression) as w:
        ids: dict[str, int] = {}
        for schema, channel, message in log.raw_messages(log.topics):
            if channel.topic not in ids:
                assert schema is not None
                ids[channel.topic] = w.add_channel(channel.topic, MessageType(
                    schema.name, schema.encoding, schema.data, channel.message_encoding))
            w.write(ids[channel.topic], log_time=message.log_time, data=message.data)
        for name, data in log.metadata():
            w.add_metadata(name, data)


@pytest.fixture(scope="module")
def good_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """32x32 px, 12 frames, lz4, ~2 KiB chunks."""
    folder = tmp_path_factory.mktemp("corpus")
    simulate_log(small_config(width=32, height=32, n_frames=12, n_stars=2, margin=6.0), folder / "sim.mcap")
    _rewrite(folder / "sim.mcap", folder / "good.mcap")
    return folder / "good.mcap"


def _keyed(messages: Any) -> Content:
    out: Content = {}
    for _, channel, message in messages:
        n = 0
        while (channel.topic, message.log_time, n) in out:
            n += 1
        out[(channel.topic, message.log_time, n)] = bytes(message.data)
    return out


def content(path: Path) -> Content:
    """Every message's raw bytes: what an intact read must give."""
    with LogReader(path) as log:
        return _keyed(log.raw_messages(log.topics))


@pytest.fixture(scope="module")
def good_content(good_log: Path) -> Content:
    return content(good_log)


def read_everything(path: Path) -> Content:
    """Decode every channel (frames too) the way the stages do; returns the raw content read."""
    out: Content = {}
    with LogReader(path) as log:
        log.channels()
        log.provenance()
        out = _keyed(log.raw_messages(log.topics))
        for topic in log.topics:
            for _ in log.messages(topic):
                pass
        if topics.IMAGE in log.topics:
            for _ in log.frames():
                pass
    return out


def run_cli(*args: str) -> tuple[int, str]:
    """Run a command; anything but success or a StarlogError turned into exit status 1 fails the test."""
    result = CliRunner().invoke(cli, list(args))
    if result.exit_code != 0:
        assert isinstance(result.exception, SystemExit), (
            f"starlog {' '.join(args)} raised {type(result.exception).__name__}: {result.exception}")
        assert result.exit_code == 1 and "Error:" in result.output, result.output
    return result.exit_code, result.output


def check_every_command(broken: Path, original: Content, tmp: Path, *,
                        expect: type[StarlogError] | None, match: str | None = None) -> tuple[Any, Content]:
    """LogReader + every channel, info, export, recover on ``broken``.

    ``expect``: the StarlogError reading must raise (None: reading must succeed and be exact).
    Returns the recovery report and the recovered content (a subset of ``original``, byte-exact).
    """
    before = file_digest(broken)
    if expect is None:
        assert read_everything(broken) == original
    else:
        with pytest.raises(expect, match=match):
            read_everything(broken)
    code, text = run_cli("info", str(broken))
    if isinstance(expect, type) and issubclass(expect, TruncatedLogError):
        assert code == 1 and "truncated" in text and "starlog recover" in text
    code, text = run_cli("export", str(broken), "-o", str(tmp / "tables"), "--force")
    if expect is None:
        assert code == 0
    elif issubclass(expect, CorruptChunkError):  # export reads only the channels of its tables
        assert code == 0 or ("starlog recover" in text and "chunk at offset" in text)
    elif issubclass(expect, NotMcapError):  # another format: nothing to recover, so no hint to
        assert code == 1 and "not an MCAP file" in text and "starlog recover" not in text
    elif not issubclass(expect, (MessageDecodeError, InvalidMessageError)):
        assert code == 1 and "starlog recover" in text
    rec = tmp / "recovered.mcap"
    code, text = run_cli("recover", str(broken), "-o", str(rec), "--force")
    assert file_digest(broken) == before  # no command changes its input
    if code != 0:
        assert "magic" in text  # only a file that is not MCAP at all cannot be recovered
        return None, {}
    report = recover_log(broken, tmp / "recovered2.mcap", force=True)
    assert (tmp / "recovered2.mcap").read_bytes() == rec.read_bytes()  # recover is reproducible
    recovered = content(rec)
    for key, data in recovered.items():
        assert original.get(key) == data, f"recovered {key} differs from the original"
    counts = {t: sum(1 for k in recovered if k[0] == t) for t in {k[0] for k in recovered}}
    assert counts == report.kept_by_topic
    return report, recovered


# ---------------------------------------------------------------- truncated / unfinished
def _cuts(size: int) -> list[int]:
    edges = [0, 4, 8, 9, 20, size - 1, size - 8, size - 9, size - 28, size - 40]
    return sorted(set(edges + [int(x) for x in np.linspace(30, size - 2, 44)]))


def test_truncated_at_many_offsets(good_log: Path, good_content: Content, tmp_path: Path) -> None:
    data = good_log.read_bytes()
    cuts = _cuts(len(data))
    assert len(cuts) >= 50
    kept_before = -1
    for cut in cuts:
        broken = tmp_path / f"cut{cut}.mcap"
        broken.write_bytes(data[:cut])
        report, recovered = check_every_command(broken, good_content, tmp_path, expect=TruncatedLogError,
                                                match="starlog recover")
        if cut >= 8:
            assert report is not None and not report.had_footer
            assert len(recovered) >= kept_before  # a longer prefix never recovers less
            kept_before = len(recovered)
        broken.unlink()
    assert kept_before == len(good_content)  # cut inside the summary: every message comes back


def test_unfinished_log_flushed_never_finished(good_log: Path, good_content: Content, tmp_path: Path) -> None:
    """What a killed writer leaves: header, chunks and indexes flushed, no summary or footer."""
    writer = LogWriter(tmp_path / "never.mcap", chunk_size=2048, compression="lz4")
    with LogReader(good_log) as log:
        ids = {}
        for schema, channel, message in log.raw_messages(log.topics):
            if channel.topic not in ids:
                ids[channel.topic] = writer.add_channel(channel.topic, MessageType(
                    schema.name, schema.encoding, schema.data, channel.message_encoding))  # type: ignore[union-attr]
            writer.write(ids[channel.topic], log_time=message.log_time, data=message.data)
    broken = tmp_path / "unfinished.mcap"
    broken.write_bytes(killed_writer_bytes(writer))
    report, recovered = check_every_command(broken, good_content, tmp_path, expect=TruncatedLogError,
                                            match="unfinished")
    assert recovered == good_content and not report.lost_chunks


# ---------------------------------------------------------------- damaged bytes
def _flip(path: Path, dst: Path, offset: int, mask: int = 0xFF) -> Path:
    data = bytearray(path.read_bytes())
    data[offset] ^= mask
    dst.write_bytes(bytes(data))
    return dst


@pytest.mark.parametrize("where", [10, 30, 40, 60, -1, 0.5])
def test_flipped_byte_in_a_chunk_names_the_chunk(good_log: Path, good_content: Content, tmp_path: Path,
                                                 where: float) -> None:
    with LogReader(good_log) as log:
        chunk = log.files[-1].summary.chunk_indexes[2]
        names = sorted(log.files[-1].summary.channels[c].topic for c in chunk.message_index_offsets)
    rel = int(chunk.chunk_length * where) if isinstance(where, float) else where % chunk.chunk_length
    broken = _flip(good_log, tmp_path / "flip.mcap", chunk.chunk_start_offset + rel)
    with pytest.raises(CorruptChunkError) as info:
        read_everything(broken)
    err = info.value
    assert err.offset == chunk.chunk_start_offset and sorted(err.topics) == names
    assert (err.start, err.end) == (chunk.message_start_time, chunk.message_end_time)
    assert f"offset {chunk.chunk_start_offset}" in str(err) and "starlog recover" in str(err)
    report, recovered = check_every_command(broken, good_content, tmp_path, expect=CorruptChunkError)
    lost = set(good_content) - set(recovered)
    assert all(chunk.message_start_time <= t <= chunk.message_end_time for _, t, _ in lost)
    if lost:  # the data was hit; a flip in a header field (times, sizes) that the CRC vouches for loses nothing
        assert report.lost_chunks[0].offset == chunk.chunk_start_offset


@pytest.mark.parametrize("field", ["opcode", "length", "channel", "array_length", "time", "offset"])
def test_corrupted_message_index(good_log: Path, good_content: Content, tmp_path: Path, field: str) -> None:
    with LogReader(good_log) as log:
        chunk = log.files[-1].summary.chunk_indexes[1]
    start = min(chunk.message_index_offsets.values())
    rel = {"opcode": 0, "length": 1, "channel": 9, "array_length": 11, "time": 15, "offset": 23}[field]
    broken = _flip(good_log, tmp_path / "index.mcap", start + rel, 0x01 if field == "length" else 0xFF)
    with pytest.raises(CorruptChunkError, match="message index"):
        read_everything(broken)
    report, recovered = check_every_command(broken, good_content, tmp_path, expect=CorruptChunkError)
    assert recovered == good_content  # recover rebuilds the indexes from the chunks


@pytest.mark.parametrize("fraction", [0.0, 0.1, 0.3, 0.5, 0.7, 0.9, 0.999])
def test_corrupted_summary(good_log: Path, good_content: Content, tmp_path: Path, fraction: float) -> None:
    data = good_log.read_bytes()
    summary_start = struct.unpack_from("<Q", data, len(data) - 8 - 29 + 9)[0]
    footer = len(data) - 8 - 29
    broken = _flip(good_log, tmp_path / "summary.mcap", summary_start + int((footer - summary_start) * fraction))
    report, recovered = check_every_command(broken, good_content, tmp_path, expect=CorruptLogError,
                                            match="summary|footer")
    assert recovered == good_content


@pytest.mark.parametrize("field", ["summary_start", "summary_offset_start", "crc", "opcode", "magic"])
def test_corrupted_footer(good_log: Path, good_content: Content, tmp_path: Path, field: str) -> None:
    size = good_log.stat().st_size
    footer = size - 8 - 29
    offset = {"summary_start": footer + 9, "summary_offset_start": footer + 17, "crc": footer + 25,
              "opcode": footer, "magic": size - 3}[field]
    broken = _flip(good_log, tmp_path / "footer.mcap", offset, 0x10)
    expect = TruncatedLogError if field in ("opcode", "magic") else CorruptLogError
    _, recovered = check_every_command(broken, good_content, tmp_path, expect=expect, match="starlog recover")
    assert recovered == good_content


def test_not_mcap_at_all(tmp_path: Path) -> None:
    broken = tmp_path / "junk.mcap"
    broken.write_bytes(b"GIF89a" + bytes(200))
    check_every_command(broken, {}, tmp_path, expect=NotMcapError, match="magic")


# ---------------------------------------------------------------- bad values
def _frame_info(n: int) -> bytes:
    return encode_json({"frame": n, "width": 32, "height": 32, "encoding": "mono16", "bit_depth": 16, "source": ""})


def _raw_image(width: int, height: int, encoding: str, data: bytes, step: int | None = None) -> bytes:
    from foxglove_schemas_protobuf.RawImage_pb2 import RawImage

    return RawImage(width=width, height=height, encoding=encoding, step=2 * width if step is None else step,
                    data=data).SerializeToString()


def _write_log(path: Path, images: list[tuple[int, bytes]], infos: list[tuple[int, bytes]] | None = None) -> Path:
    with LogWriter(path, validate=False) as w:  # a foreign writer: it writes what it is given
        image = w.add_channel(topics.IMAGE, protobuf_message_type("foxglove.RawImage"))
        info = w.add_channel(topics.FRAME_INFO, json_message_type("starlog.FrameInfo"))
        for t, data in images:
            w.write(image, log_time=t, data=data)
        for t, data in infos if infos is not None else [(t, _frame_info(i)) for i, (t, _) in enumerate(images)]:
            w.write(info, log_time=t, data=data)
        w.add_metadata("starlog.provenance", Provenance(stage="test", version="0").to_metadata())
    return path


def _frame(rng: np.random.Generator, shape: tuple[int, int] = (32, 32)) -> np.ndarray:
    return rng.integers(90, 4000, size=shape, dtype=np.uint16)


BAD_VALUES: dict[str, tuple[Callable[[np.random.Generator], list[tuple[int, bytes]]], Any, type, str]] = {
    "protobuf garbage": (lambda rng: [(0, b"\xff\xff\xff\x07garbage")], None, MessageDecodeError,
                         "'/camera/image' at log_time 0"),
    "data length != width*height*depth": (
        lambda rng: [(5, _raw_image(32, 32, "mono16", bytes(32 * 32 * 2 - 1)))], None, MessageDecodeError,
        "log_time 5.*expected step"),
    "mono16 with an odd step": (lambda rng: [(5, _raw_image(3, 2, "mono16", bytes(14), step=7))], None,
                                MessageDecodeError, "whole number"),
    "big-endian mono16": (lambda rng: [(7, _raw_image(32, 32, "mono16be", _frame(rng).astype(">u2").tobytes()))],
                          None, MessageDecodeError, "big-endian"),
    "unsupported encoding": (lambda rng: [(7, _raw_image(32, 32, "yuv422", bytes(32 * 32 * 2), step=64))], None,
                             MessageDecodeError, "unsupported image encoding"),
    "frame of another size": (
        lambda rng: [(0, encode_raw_image(_frame(rng), log_time=0)),
                     (10, encode_raw_image(_frame(rng, (32, 31)), log_time=10))], None, InvalidMessageError,
        "log_time 10.*frame 1 is 31x32"),
    "frame of another pixel type": (
        lambda rng: [(0, encode_raw_image(_frame(rng), log_time=0)),
                     (10, encode_raw_image(_frame(rng).astype(np.uint8), log_time=10))], None, InvalidMessageError,
        "uint8"),
    "two frames at one log_time": (
        lambda rng: [(0, encode_raw_image(_frame(rng), log_time=0)), (0, encode_raw_image(_frame(rng), log_time=0))],
        None, InvalidMessageError, "increase strictly"),
    "JSON garbage": (lambda rng: [(0, encode_raw_image(_frame(rng), log_time=0))], [(0, b"\xfe{not json")],
                     MessageDecodeError, "'/camera/frame' at log_time 0.*JSON"),
    "JSON NaN": (lambda rng: [(0, encode_raw_image(_frame(rng), log_time=0))],
                 [(0, b'{"frame":0,"width":NaN,"height":1,"encoding":"mono8","bit_depth":8,"source":""}')],
                 MessageDecodeError, "NaN"),
    "JSON against its schema": (lambda rng: [(0, encode_raw_image(_frame(rng), log_time=0))],
                                [(0, b'{"frame":"zero"}')], InvalidMessageError, "schema"),
}


@pytest.mark.parametrize("case", list(BAD_VALUES))
def test_bad_values_are_named(case: str, tmp_path: Path) -> None:
    make_images, infos, error, match = BAD_VALUES[case]
    images = make_images(np.random.default_rng(8))
    broken = _write_log(tmp_path / "bad.mcap", images, infos)
    original = content(broken)  # the container is intact: only values are bad
    check_every_command(broken, original, tmp_path, expect=error, match=match)
    code, text = run_cli("centroid", str(broken), "-o", str(tmp_path / "c.mcap"), "--method", "MOMENT", "-q")
    if infos is None:  # the frames are bad: the stage that reads them stops and names the message
        assert code == 1 and "/camera/image" in text and "log_time" in text
    assert not (tmp_path / "c.mcap").exists() or code == 0


def test_messages_out_of_order_in_the_file_are_read_in_time_order(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    times = [int(t) for t in rng.permutation(40) * 1_000_000]
    frames = {t: _frame(rng) for t in times}
    path = tmp_path / "shuffled.mcap"
    with LogWriter(path, chunk_size=4096, compression="lz4") as w:
        ch = w.add_channel(topics.IMAGE, protobuf_message_type("foxglove.RawImage"))
        for t in times:
            w.write(ch, log_time=t, data=encode_raw_image(frames[t], log_time=t))
    with LogReader(path) as log:
        assert len(log.files[-1].summary.chunk_indexes) > 3
        got = list(log.frames())
    assert [t for _, t, _ in got] == sorted(times)
    for _, t, image in got:
        np.testing.assert_array_equal(image, frames[t])
    report, recovered = check_every_command(path, content(path), tmp_path, expect=None)
    assert len(recovered) == 40


def test_chunk_whose_messages_lie_outside_its_index_range(good_log: Path, good_content: Content,
                                                          tmp_path: Path) -> None:
    """A lying chunk index would make the merge return messages out of order: detected instead."""
    data = bytearray(good_log.read_bytes())
    with LogReader(good_log) as log:
        chunk = log.files[-1].summary.chunk_indexes[3]
    struct.pack_into("<Q", data, chunk.chunk_start_offset + 9, chunk.message_start_time + 1)  # chunk header start
    broken = tmp_path / "range.mcap"
    broken.write_bytes(bytes(data))
    with pytest.raises(CorruptChunkError, match=f"offset {chunk.chunk_start_offset}"):
        read_everything(broken)


def test_decode_raw_image_rejects_what_it_cannot_represent() -> None:
    from starlog.errors import InvalidInputError

    with pytest.raises(InvalidInputError, match="big-endian"):
        decode_raw_image(_raw_image(2, 2, "16UC1be", bytes(8)))
    np.testing.assert_array_equal(decode_raw_image(_raw_image(2, 1, "16UC1", b"\x01\x00\x00\x01")), [[1, 256]])
