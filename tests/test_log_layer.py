"""The log layer's fast paths: compiled schema checks, checks on write, per-channel chunks."""

from __future__ import annotations

import copy
import json
from pathlib import Path
from typing import Any

import jsonschema
import numpy as np
import pytest
from mcap.writer import Writer as McapWriter

from starlog.errors import InvalidInputError, InvalidMessageError
from starlog.io import LogReader, LogWriter
from starlog.codecs import encode_json, json_message_type
from starlog import topics
from starlog.codecs.json_schema import compile_json_schema
from starlog.codecs.json_messages import decode_json
from starlog.codecs.schemas import load_json_schema, schema_dir
from starlog.io.writer import VALIDATED_METADATA_KEY
from tests.json_logs import write_json_log

SCHEMAS = sorted(p.stem for p in schema_dir().glob("starlog.*.json"))


def _frame_info(frame: Any = 0) -> dict[str, Any]:
    return {"frame": frame, "width": 32, "height": 32, "encoding": "mono16", "bit_depth": 16, "source": ""}


def _mutations(value: Any) -> list[Any]:
    """Copies of ``value`` with one leaf or key changed (wrong type, dropped, extra, out of range)."""
    out: list[Any] = []

    def visit(node: Any, path: list[Any]) -> None:
        if isinstance(node, dict):
            for key in list(node):
                for replace in ("text", None, -1, 1.5, True, [], {}):
                    out.append(_replaced(value, [*path, key], replace))
                dropped = copy.deepcopy(value)
                _at(dropped, path).pop(key)
                out.append(dropped)
                visit(node[key], [*path, key])
            extra = copy.deepcopy(value)
            _at(extra, path)["unexpected"] = 1
            out.append(extra)
        elif isinstance(node, list) and node:
            visit(node[0], [*path, 0])
            out.append(_replaced(value, path, []))

    visit(value, [])
    return out


def _at(node: Any, path: list[Any]) -> Any:
    for key in path:
        node = node[key]
    return node


def _replaced(value: Any, path: list[Any], new: Any) -> Any:
    out = copy.deepcopy(value)
    if not path:
        return new
    _at(out, path[:-1])[path[-1]] = new
    return out


@pytest.fixture(scope="module")
def pipeline_log(tmp_path_factory: pytest.TempPathFactory, sim_log: Path) -> Path:
    from starlog.stages.centroid import centroid_log
    from starlog.stages.track import track_log

    folder = tmp_path_factory.mktemp("layer")
    centroid_log(sim_log, folder / "cen.mcap", methods="GAUSSFIT", workers=1)
    track_log(folder / "cen.mcap", folder / "trk.mcap", method="GAUSSFIT", models="STATIC",
              tracker={"sigma_floor": 0.05})
    return write_json_log(folder / "trk.mcap", folder / "old.mcap")  # the star tables as JSON, as logs of old


def test_compiled_checker_agrees_with_jsonschema(pipeline_log: Path) -> None:
    """Every real message, and hundreds of one-field mutations of one per schema: same verdict."""
    checked = invalid = 0
    with LogReader(pipeline_log) as log:
        for channel in log.channels():
            if channel.schema_encoding != "jsonschema":
                continue
            schema = load_json_schema(channel.schema_name)
            check = compile_json_schema(schema)
            reference = jsonschema.Draft202012Validator(schema)
            first = next(iter(log.messages(channel.topic))).payload
            for value in [first, *_mutations(first)]:
                problem = check(value)
                assert (problem is None) == reference.is_valid(value), (channel.topic, value, problem)
                checked += 1
                invalid += problem is not None
    assert checked > 300 and 100 < invalid < checked


@pytest.mark.parametrize("name", SCHEMAS)
def test_every_schema_compiles(name: str) -> None:
    assert compile_json_schema(load_json_schema(name))({}) is not None  # an empty object misses required fields


def test_writer_refuses_a_message_that_does_not_match_its_schema(tmp_path: Path) -> None:
    with LogWriter(tmp_path / "a.mcap") as w:
        ch = w.add_channel(topics.FRAME_INFO, json_message_type("starlog.FrameInfo"))
        w.write(ch, log_time=0, data=encode_json(_frame_info()))
        with pytest.raises(InvalidInputError, match=r"log_time 1 .*schema 'starlog.FrameInfo'.*\$.frame"):
            w.write(ch, log_time=1, data=encode_json(_frame_info("zero")))
        with pytest.raises(InvalidInputError, match="JSON"):
            w.write(ch, log_time=2, data=b"{not json")
    with LogReader(tmp_path / "a.mcap") as log:
        assert log.files[-1].summary.channels[1].metadata[VALIDATED_METADATA_KEY] == "jsonschema"
        assert [m.payload for m in log.messages(topics.FRAME_INFO)] == [_frame_info()]


def test_unchecked_writer_does_not_mark_its_channels(tmp_path: Path) -> None:
    with LogWriter(tmp_path / "a.mcap", validate=False) as w:
        w.add_channel(topics.FRAME_INFO, json_message_type("starlog.FrameInfo"),
                      metadata={VALIDATED_METADATA_KEY: "jsonschema", "kept": "yes"})
    with LogReader(tmp_path / "a.mcap") as log:
        assert log.files[-1].summary.channels[1].metadata == {"kept": "yes"}


def _forged_log(path: Path, *, marked: bool) -> Path:
    """A log from another writer whose FrameInfo channel claims starlog checked it, holding a bad message."""
    mtype = json_message_type("starlog.FrameInfo")
    with open(path, "wb") as f:
        w = McapWriter(f)
        w.start()
        sid = w.register_schema(mtype.schema_name, mtype.schema_encoding, mtype.schema_data)
        cid = w.register_channel(topics.FRAME_INFO, "json", sid,
                                 {VALIDATED_METADATA_KEY: "jsonschema"} if marked else {})
        w.add_message(cid, log_time=0, data=json.dumps(_frame_info("zero")).encode(), publish_time=0)
        w.finish()
    return path


def test_reader_checks_what_starlog_did_not_check_on_write(tmp_path: Path) -> None:
    unmarked = _forged_log(tmp_path / "unmarked.mcap", marked=False)
    with LogReader(unmarked) as log, pytest.raises(InvalidMessageError, match="schema"):
        list(log.messages(topics.FRAME_INFO))
    marked = _forged_log(tmp_path / "marked.mcap", marked=True)
    with LogReader(marked) as log:  # the mark is trusted: no check on read
        assert [m.payload["frame"] for m in log.messages(topics.FRAME_INFO)] == ["zero"]
    for options in ({"validate_messages": "all"}, {"validate_crcs": False}):
        with LogReader(marked, **options) as log, pytest.raises(InvalidMessageError, match="schema"):
            list(log.messages(topics.FRAME_INFO))


def test_encode_json_matches_the_standard_library_values() -> None:
    value = {"a": np.float32(0.1), "b": np.int64(3), "c": [1e-5, 1e16, -0.0], "d": np.arange(3), 4: "x",
             "e": np.bool_(True), "s": "é"}
    assert decode_json(encode_json(value)) == json.loads(json.dumps(value, default=lambda v: v.item()
                                                                    if hasattr(v, "item") and v.ndim == 0
                                                                    else v.tolist()))
    for bad in (float("nan"), float("inf"), [1.0, -float("inf")], np.array([np.nan])):
        with pytest.raises(InvalidInputError, match="NaN or infinite"):
            encode_json({"v": bad})
    assert encode_json({"v": None}) == b'{"v":null}'


def test_each_channel_has_its_own_chunks_and_images_are_not_read_for_truth(sim_log: Path,
                                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    with LogReader(sim_log) as log:
        (file,) = log.files
        assert all(len(ci.message_index_offsets) == 1 for ci in file.summary.chunk_indexes)
        image_id = next(c.id for c in file.summary.channels.values() if c.topic == topics.IMAGE)
        read: list[Any] = []
        original = file.read_chunk
        monkeypatch.setattr(file, "read_chunk", lambda ci: read.append(ci) or original(ci))
        assert sum(1 for _ in log.messages(topics.TRUTH)) == 20
        assert read and not any(image_id in ci.message_index_offsets for ci in read)


