"""The log layer: encoding round trips, both mcap readers with CRCs, schemas, append, atomic writes."""

from __future__ import annotations

import json
from pathlib import Path

import jsonschema
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from mcap.reader import NonSeekingReader, SeekingReader

from starlog.errors import (
    ChannelNotFoundError,
    InvalidInputError,
    InvalidParameterError,
    LogNotFoundError,
    OutputExistsError,
    TruncatedLogError,
)
from starlog.io import LogReader, LogWriter, Provenance, file_digest
from starlog.codecs import (
    decode_raw_image,
    encode_json,
    encode_raw_image,
    json_message_type,
    load_json_schema,
    protobuf_message_type,
)
from starlog import topics


@settings(max_examples=40, deadline=None)
@given(
    image=hnp.arrays(
        dtype=st.sampled_from([np.uint8, np.uint16]),
        shape=hnp.array_shapes(min_dims=2, max_dims=2, min_side=1, max_side=40),
    ),
    log_time=st.integers(0, 2**63 - 1),
)
def test_raw_image_round_trip(image: np.ndarray, log_time: int) -> None:
    decoded = decode_raw_image(encode_raw_image(image, log_time=log_time))
    assert decoded.dtype == image.dtype
    np.testing.assert_array_equal(decoded, image)


def test_mono16_is_little_endian_on_the_wire() -> None:
    from foxglove_schemas_protobuf.RawImage_pb2 import RawImage

    msg = RawImage()
    msg.ParseFromString(encode_raw_image(np.array([[0x0102]], dtype=np.uint16), log_time=0))
    assert msg.encoding == "mono16" and msg.data == b"\x02\x01" and msg.step == 2


def test_raw_image_with_wrong_data_length_is_rejected() -> None:
    from foxglove_schemas_protobuf.RawImage_pb2 import RawImage

    msg = RawImage(width=4, height=4, step=8, encoding="mono16", data=b"\x00" * 30)
    with pytest.raises(InvalidInputError, match="expected step"):
        decode_raw_image(msg.SerializeToString())


def test_unsupported_encoding_is_rejected() -> None:
    from foxglove_schemas_protobuf.RawImage_pb2 import RawImage

    msg = RawImage(width=1, height=1, step=3, encoding="rgb8", data=b"\x00" * 3)
    with pytest.raises(InvalidInputError, match="unsupported image encoding"):
        decode_raw_image(msg.SerializeToString())


def test_json_refuses_nan() -> None:
    with pytest.raises(InvalidInputError, match="NaN"):
        encode_json({"x": float("nan")})


@pytest.mark.parametrize("reader_class", [SeekingReader, NonSeekingReader])
def test_log_reads_with_both_mcap_readers_and_crcs(sim_log: Path, reader_class: type) -> None:
    counts: dict[str, int] = {}
    with open(sim_log, "rb") as f:
        reader = reader_class(f, validate_crcs=True)
        for _, channel, _ in reader.iter_messages():
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
    assert counts == {topics.IMAGE: 20, topics.FRAME_INFO: 20, topics.TRUTH: 20}


def test_json_messages_validate_against_their_schemas(sim_log: Path) -> None:
    with LogReader(sim_log) as log:
        for topic, name in [(topics.TRUTH, "starlog.SimTruth"), (topics.FRAME_INFO, "starlog.FrameInfo")]:
            validator = jsonschema.Draft202012Validator(load_json_schema(name))
            for message in log.messages(topic):
                validator.validate(message.payload)


def test_embedded_schema_is_the_repository_schema(sim_log: Path) -> None:
    with LogReader(sim_log) as log:
        schemas = {s.name: s for s in log.files[-1].summary.schemas.values()}
    assert json.loads(schemas["starlog.SimTruth"].data) == load_json_schema("starlog.SimTruth")
    assert schemas["foxglove.RawImage"].encoding == "protobuf"


def test_every_schema_file_is_a_valid_json_schema() -> None:
    from starlog.codecs.schemas import schema_dir

    for path in sorted(schema_dir().glob("starlog.*.json")):
        jsonschema.Draft202012Validator.check_schema(json.loads(path.read_text()))


def test_reader_lists_channels_and_provenance(sim_log: Path) -> None:
    with LogReader(sim_log) as log:
        channels = {c.topic: c for c in log.channels()}
        assert channels[topics.IMAGE].schema_name == "foxglove.RawImage"
        assert channels[topics.IMAGE].message_count == 20
        assert channels[topics.IMAGE].rate_hz == pytest.approx(100.0)
        (prov,) = log.provenance()
        assert prov.stage == "simulate" and prov.parameters["n_frames"] == 20
        with pytest.raises(ChannelNotFoundError, match="no channel '/nope'"):
            list(log.messages("/nope"))


def test_frames_stream_in_time_order(sim_log: Path) -> None:
    with LogReader(sim_log) as log:
        times = [t for _, t, image in log.frames()]
    assert times == sorted(times) and len(times) == 20


@pytest.mark.parametrize("stride", [1, 2, 3, 7, 50])
def test_stride_decodes_every_nth_message(sim_log: Path, stride: int) -> None:
    with LogReader(sim_log) as log:
        every = [(m.topic, m.log_time) for m in log.messages(topics.FRAME_INFO)]
        assert [(m.topic, m.log_time) for m in log.messages(topics.FRAME_INFO, stride=stride)] == every[::stride]
        with pytest.raises(InvalidParameterError, match="stride"):
            next(log.messages(topics.FRAME_INFO, stride=0))


def _layer_demo(base: Path, out: Path, **kwargs: object) -> None:
    with LogReader(base) as log:
        layer = log.layer_base()
    with LogWriter(out, layer=layer, **kwargs) as w:  # type: ignore[arg-type]
        ch = w.add_channel("/demo", json_message_type("starlog.FrameInfo"))
        for n in range(5):
            w.write(ch, log_time=n * 10_000_000,
                    data=encode_json({"frame": n, "width": 1, "height": 1, "encoding": "mono8", "bit_depth": 8,
                                      "source": ""}))
        w.add_metadata("starlog.provenance", Provenance(stage="demo", version="0", channels=["/demo"]).to_metadata())


def test_a_layer_holds_what_it_adds_and_reads_with_its_unchanged_base(sim_log: Path, tmp_path: Path) -> None:
    before = file_digest(sim_log)
    out = tmp_path / "out.mcap"
    _layer_demo(sim_log, out)
    assert file_digest(sim_log) == before
    assert out.stat().st_size < sim_log.stat().st_size / 20  # no frame in it
    with LogReader(out) as log:
        assert [p.stage for p in log.provenance()] == ["simulate", "demo"]
        assert log.channel("/demo").message_count == 5
        assert log.channel(topics.IMAGE).message_count == 20
        images = [m.payload for m in log.messages(topics.IMAGE)]
    with LogReader(sim_log) as log:
        np.testing.assert_array_equal(images[3], [m.payload for m in log.messages(topics.IMAGE)][3])
    for reader_class in (SeekingReader, NonSeekingReader):  # the layer alone is a valid MCAP file
        with open(out, "rb") as f:
            assert sum(1 for _ in reader_class(f, validate_crcs=True).iter_messages()) == 5


def test_a_layer_refuses_a_topic_of_its_chain(sim_log: Path, tmp_path: Path) -> None:
    with LogReader(sim_log) as log:
        layer = log.layer_base()
    with pytest.raises(InvalidInputError, match="already has a channel '/sim/truth'"):
        with LogWriter(tmp_path / "o.mcap", layer=layer) as w:
            w.add_channel(topics.TRUTH, json_message_type("starlog.SimTruth"))
    assert not list(tmp_path.iterdir())


def test_parallel_compression_gives_the_same_bytes(sim_log: Path, tmp_path: Path) -> None:
    for workers in (1, 2):
        with LogReader(sim_log) as log, LogWriter(tmp_path / f"w{workers}.mcap", workers=workers,
                                                  chunk_size=4096, compression="lz4") as w:
            ch = w.add_channel(topics.IMAGE, protobuf_message_type("foxglove.RawImage"))
            for _, t, image in log.frames():
                w.write(ch, log_time=t, data=encode_raw_image(image, log_time=t))
    assert (tmp_path / "w1.mcap").read_bytes() == (tmp_path / "w2.mcap").read_bytes()


def test_writer_error_leaves_nothing(tmp_path: Path) -> None:
    out = tmp_path / "x.mcap"
    with pytest.raises(RuntimeError):
        with LogWriter(out) as w:
            w.add_channel("/a", json_message_type("starlog.FrameInfo"))
            raise RuntimeError("stage failed")
    assert list(tmp_path.iterdir()) == []


def test_existing_output_needs_force(sim_log: Path, tmp_path: Path) -> None:
    out = tmp_path / "x.mcap"
    out.write_bytes(b"keep me")
    with pytest.raises(OutputExistsError, match="--force"):
        LogWriter(out)
    assert out.read_bytes() == b"keep me"
    _layer_demo(sim_log, out, force=True)
    with LogReader(out) as log:
        assert log.channel("/demo").message_count == 5


@pytest.mark.parametrize("cut", [0.3, 0.7, 0.99])
def test_truncated_log_points_to_recover(sim_log: Path, tmp_path: Path, cut: float) -> None:
    data = sim_log.read_bytes()
    broken = tmp_path / "cut.mcap"
    broken.write_bytes(data[: int(len(data) * cut)])
    with pytest.raises(TruncatedLogError, match="starlog recover"):
        LogReader(broken)


def test_missing_log() -> None:
    with pytest.raises(LogNotFoundError, match="no such file"):
        LogReader("/nonexistent/x.mcap")


def test_monotonic_channels_refuse_time_going_backwards(tmp_path: Path) -> None:
    msg = encode_json({"frame": 0, "width": 1, "height": 1, "encoding": "mono8", "bit_depth": 8, "source": ""})
    with pytest.raises(InvalidInputError, match="is not after the previous"):
        with LogWriter(tmp_path / "m.mcap") as w:
            ch = w.add_channel("/frames", json_message_type("starlog.FrameInfo"), monotonic=True)
            w.write(ch, log_time=10, data=msg)
            w.write(ch, log_time=10, data=msg)
    assert not (tmp_path / "m.mcap").exists()


def test_written_logs_are_not_private(tmp_path: Path) -> None:
    with LogWriter(tmp_path / "p.mcap") as w:
        w.add_channel("/a", json_message_type("starlog.FrameInfo"))
    assert (tmp_path / "p.mcap").stat().st_mode & 0o044  # readable by group/others as the umask allows
