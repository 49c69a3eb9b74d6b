"""Reading frames without copies: the RawImage wire reader against protobuf's parser, zstd chunks
read in one call against the stream reader, frames as read-only views."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest
import zstandard
from mcap.records import Schema
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from starlog.errors import InvalidInputError
from starlog.io import LogReader, LogWriter
from starlog.codecs import decode_raw_image, encode_raw_image, protobuf_message_type
from starlog.io.frames import cached_image_decoder
from starlog.codecs.images import pixels_to_mono
from starlog.codecs.rawimage_wire import parse_raw_image
from starlog.io.chunks import decompress


# ---------------------------------------------------------------- protobuf wire encoding, by hand
def varint(value: int, padding: int = 0) -> bytes:
    """``value`` (below 2**64) as a varint, with ``padding`` redundant continuation bytes (still valid)."""
    out = bytearray()
    while True:
        out.append(value & 0x7F | 0x80)
        value >>= 7
        if not value:
            break
    out += b"\x80" * padding
    out[-1] &= 0x7F
    return bytes(out)


def tag(number: int, wire_type: int, padding: int = 0) -> bytes:
    return varint(number << 3 | wire_type, padding)


def length_field(number: int, payload: bytes) -> bytes:
    return tag(number, 2) + varint(len(payload)) + payload


def fixed32_field(number: int, value: int) -> bytes:
    return tag(number, 5) + struct.pack("<I", value)


def signed_varint_field(number: int, value: int, bits: int) -> bytes:
    return tag(number, 0) + varint(value & (2**64 - 1) if value < 0 else value)


INT64 = st.integers(-(2**63), 2**63 - 1)
INT32 = st.integers(-(2**31), 2**31 - 1)
UINT32 = st.integers(0, 2**32 - 1)


@st.composite
def timestamp_field(draw: st.DrawFn) -> bytes:
    """One occurrence of ``timestamp``: any subset of seconds / nanos, in either order, maybe with unknown fields."""
    parts = []
    if draw(st.booleans()):
        parts.append(signed_varint_field(1, draw(INT64), 64))
    if draw(st.booleans()):
        parts.append(signed_varint_field(2, draw(INT32), 32))
    parts += draw(st.lists(unknown_field(), max_size=2))
    return length_field(1, b"".join(draw(st.permutations(parts))))


@st.composite
def unknown_field(draw: st.DrawFn) -> bytes:
    number = draw(st.one_of(st.integers(8, 40), st.integers(2**28, 2**29 - 1)))
    wire_type = draw(st.sampled_from([0, 1, 2, 5]))
    if wire_type == 0:
        return tag(number, 0) + varint(draw(st.integers(0, 2**64 - 1)))
    if wire_type == 1:
        return tag(number, 1) + draw(st.binary(min_size=8, max_size=8))
    if wire_type == 5:
        return tag(number, 5) + draw(st.binary(min_size=4, max_size=4))
    return length_field(number, draw(st.binary(max_size=20)))


TEXT = st.text(max_size=12)


@st.composite
def raw_image_bytes(draw: st.DrawFn) -> bytes:
    """A RawImage as another writer might serialize it: fields in any order, some repeated, some absent,
    unknown fields between them, tags with redundant varint bytes."""
    fields = [
        *draw(st.lists(timestamp_field(), max_size=2)),
        *(fixed32_field(n, draw(UINT32)) for n in (2, 3, 5) for _ in range(draw(st.integers(0, 2)))),
        *(length_field(4, draw(TEXT).encode()) for _ in range(draw(st.integers(0, 2)))),
        *(length_field(7, draw(TEXT).encode()) for _ in range(draw(st.integers(0, 2)))),
        *(length_field(6, draw(st.binary(max_size=64))) for _ in range(draw(st.integers(0, 2)))),
        *draw(st.lists(unknown_field(), max_size=3)),
    ]
    fields = draw(st.permutations(fields))
    if fields and draw(st.booleans()):  # one tag written with redundant bytes (at most five in all)
        k = draw(st.integers(0, len(fields) - 1))
        head = fields[k][0]
        if head < 0x80 and (head >> 3) < 16:
            fields[k] = tag(head >> 3, head & 7, draw(st.integers(1, 3))) + fields[k][1:]
    return b"".join(fields)


def protobuf_fields(data: bytes) -> tuple:
    msg = RawImage.FromString(data)
    return (msg.timestamp.seconds, msg.timestamp.nanos, msg.width, msg.height, msg.encoding, msg.step,
            bytes(msg.data), msg.frame_id)


def wire_fields(data: bytes) -> tuple | None:
    f = parse_raw_image(data)
    if f is None:
        return None
    return (f.seconds, f.nanos, f.width, f.height, f.encoding, f.step, bytes(f.data), f.frame_id)


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=raw_image_bytes())
def test_wire_reader_equals_protobuf_on_any_well_formed_raw_image(data: bytes) -> None:
    assert wire_fields(data) == protobuf_fields(data)


@settings(max_examples=300, deadline=None)
@given(data=st.one_of(st.binary(max_size=40),
                      raw_image_bytes().flatmap(lambda b: st.integers(0, max(0, len(b) - 1)).map(lambda n: b[:n]))))
def test_wire_reader_leaves_what_it_does_not_read_to_protobuf(data: bytes) -> None:
    """Random and truncated bytes: whenever the wire reader answers, protobuf parses them to the same fields."""
    got = wire_fields(data)
    if got is not None:
        assert got == protobuf_fields(data)


@pytest.mark.parametrize("data", [
    length_field(4, b"\xff\xfe"),                      # encoding not UTF-8: protobuf refuses it
    tag(2, 0) + varint(5),                              # width as a varint instead of fixed32
    tag(9, 3) + tag(9, 4),                              # a group
    tag(0, 0) + varint(1),                              # field number 0
    tag(3, 5) + b"\x01\x02",                            # fixed32 cut off
    tag(6, 2) + varint(10) + b"abc",                    # data longer than the message
    tag(1, 2) + varint(11) + tag(1, 0) + b"\xff" * 9 + b"\x02",  # an 11-bit-too-long varint in timestamp
    tag(2, 5, padding=5) + bytes(4),                    # a tag of six bytes
], ids=["not-utf8", "wrong-wire-type", "group", "field-0", "cut-fixed32", "cut-bytes", "long-varint", "long-tag"])
def test_unusual_bytes_go_to_protobuf(data: bytes) -> None:
    assert parse_raw_image(data) is None


def test_negative_timestamps_and_merge_like_protobuf() -> None:
    data = (length_field(1, signed_varint_field(1, -5, 64) + signed_varint_field(2, -7, 32))
            + length_field(1, signed_varint_field(2, 9, 32)))
    assert wire_fields(data) == protobuf_fields(data)
    assert wire_fields(data)[:2] == (-5, 9)


@settings(max_examples=60, deadline=None)
@given(width=st.integers(1, 9), height=st.integers(1, 6), pad=st.integers(0, 3), depth=st.sampled_from([1, 2]),
       seconds=st.integers(0, 2**40), nanos=st.integers(0, 10**9 - 1), frame_id=TEXT, seed=st.integers(0, 99))
def test_decoded_frame_equals_the_protobuf_path(width: int, height: int, pad: int, depth: int, seconds: int,
                                                nanos: int, frame_id: str, seed: int) -> None:
    """The stage's decoder (wire reader) gives the image, stamp and frame id the protobuf path gives."""
    step = width * depth + pad * depth
    pixels = np.random.default_rng(seed).integers(0, 256, step * height, dtype=np.uint8).tobytes()
    msg = RawImage(width=width, height=height, step=step, encoding="mono16" if depth == 2 else "mono8",
                   data=pixels, frame_id=frame_id)
    msg.timestamp.seconds, msg.timestamp.nanos = seconds, nanos
    data = msg.SerializeToString()
    decode = cached_image_decoder(Schema(id=1, name="foxglove.RawImage", encoding="protobuf", data=b""), "protobuf")
    got = decode(memoryview(data))
    expected, _ = pixels_to_mono(msg.data, width, height, step, msg.encoding)
    np.testing.assert_array_equal(got.image, expected)
    assert got.image.dtype == expected.dtype
    assert got.stamp == (seconds * 10**9 + nanos or None) and got.frame_id == frame_id


def test_decode_raw_image_errors_are_unchanged() -> None:
    with pytest.raises(InvalidInputError, match="not a valid foxglove.RawImage"):
        decode_raw_image(length_field(4, b"\xff\xfe"))
    image = decode_raw_image(encode_raw_image(np.arange(6, dtype=np.uint16).reshape(2, 3), log_time=3))
    np.testing.assert_array_equal(image, [[0, 1, 2], [3, 4, 5]])
    assert not image.flags.writeable


# ---------------------------------------------------------------- chunks
@pytest.mark.parametrize("how", ["one frame", "no content size", "two frames"])
def test_zstd_chunk_reads_the_same_however_it_was_compressed(how: str) -> None:
    payload = np.random.default_rng(0).integers(0, 50, 100_000, dtype=np.uint8).tobytes()
    if how == "one frame":
        data = zstandard.ZstdCompressor().compress(payload)
    elif how == "no content size":
        data = zstandard.ZstdCompressor(write_content_size=False).compress(payload)
    else:
        half = len(payload) // 2
        data = zstandard.ZstdCompressor().compress(payload[:half]) + zstandard.ZstdCompressor().compress(payload[half:])
    expected = zstandard.ZstdDecompressor().stream_reader(data).read(len(payload) + 1)
    assert bytes(decompress("zstd", memoryview(data), len(payload))) == expected
    assert (expected == payload) == (how != "two frames")


def _outcome(read: object, data: bytes, size: int) -> object:
    try:
        return bytes(read(data, size))  # type: ignore[operator]
    except zstandard.ZstdError as err:
        return f"ZstdError: {err}"


def test_damaged_zstd_chunk_reads_or_fails_like_the_stream_reader() -> None:
    payload = np.random.default_rng(1).integers(0, 40, 50_000, dtype=np.uint8).tobytes()
    clean = zstandard.ZstdCompressor().compress(payload)
    failures = changed = 0
    for k in range(0, len(clean), max(1, len(clean) // 60)):
        data = bytearray(clean)
        data[k] ^= 0x5A
        stream = _outcome(lambda d, n: zstandard.ZstdDecompressor().stream_reader(d).read(n + 1), bytes(data),
                          len(payload))
        assert _outcome(lambda d, n: decompress("zstd", d, n), bytes(data), len(payload)) == stream
        failures += isinstance(stream, str)
        changed += stream != payload and not isinstance(stream, str)
    assert failures and changed  # both kinds of damage were met (the chunk's CRC catches the second)


@pytest.mark.parametrize("compression", ["zstd", "lz4", "none"])
def test_frames_are_read_only_views_equal_to_what_was_written(tmp_path: Path, compression: str) -> None:
    rng = np.random.default_rng(3)
    images = [rng.integers(0, 65535, (15, 17), dtype=np.uint16) for _ in range(6)]
    path = tmp_path / "frames.mcap"
    with LogWriter(path, compression=compression, chunk_size=1024) as log:
        channel = log.add_channel("/camera/image", protobuf_message_type("foxglove.RawImage"))
        for k, image in enumerate(images):
            log.write(channel, log_time=k + 1, data=encode_raw_image(image, log_time=k + 1))
    with LogReader(path) as log:
        frames = list(log.frames())
        raw = [message.data for _, _, message in log.raw_messages(["/camera/image"])]
    for (_, _, got), image in zip(frames, images, strict=True):
        np.testing.assert_array_equal(got, image)
        with pytest.raises(ValueError, match="read-only"):
            got[0, 0] = 1
    assert all(type(data) is bytes for data in raw)  # raw_messages still hands out bytes
