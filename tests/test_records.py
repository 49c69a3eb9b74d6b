"""Record messages encoded from structured arrays: the same bytes, and the same refusals, as the dict path."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from starlog.centroiding import CentroidMethod, extract_stars
from starlog.errors import InvalidInputError
from starlog.codecs import encode_json, json_message_type
from starlog.codecs.checked_json import encode_checked_json
from starlog.codecs.json_rows import RecordEncoder, record_encoder, structured_to_dicts
from starlog.codecs.schemas import MessageType
from starlog.sim import SimulationConfig, Simulator

CENTROIDS = json_message_type("starlog.Centroids")
DETECTIONS = json_message_type("starlog.Detections")
TRACKS = json_message_type("starlog.Tracks")


def _reference(header: dict, key: str, table: np.ndarray, message_type: MessageType) -> bytes:
    return encode_checked_json({**header, key: structured_to_dicts(table)}, message_type)


def _outcome(call):  # type: ignore[no-untyped-def]
    try:
        return bytes(call())
    except InvalidInputError as err:
        return InvalidInputError, str(err).split(" (")[0]


_DTYPES = [np.int32, np.int64, np.uint16, np.float32, np.float64, np.bool_]
_VALUES = st.one_of(st.integers(-5, 5), st.floats(allow_nan=True, allow_infinity=True, width=64),
                    st.sampled_from([0.5, -0.0, 1e300, 2.0**40, 3.0]))


@st.composite
def record_tables(draw, message_type: MessageType, key: str):  # type: ignore[no-untyped-def]
    """Structured arrays with some of the schema's fields (in any order), an unknown one now and then,
    random dtypes and values (NaN, infinities, negatives, fractions in integer fields)."""
    props = list(json.loads(message_type.schema_data)["properties"][key]["items"]["properties"])
    names = props if draw(st.booleans()) else draw(
        st.lists(st.sampled_from(props), unique=True, min_size=max(1, len(props) - 2), max_size=len(props)))
    if draw(st.booleans()) and draw(st.booleans()):
        names.append("unknown")
    if draw(st.booleans()):
        names = draw(st.permutations(names))
    dtype = np.dtype([(n, draw(st.sampled_from(_DTYPES))) for n in names])
    n = draw(st.integers(0, 4))
    table = np.zeros(n, dtype)
    for name in names:
        values = draw(st.lists(st.one_of(st.integers(0, 100), _VALUES), min_size=n, max_size=n))
        for i, value in enumerate(values):
            with np.errstate(all="ignore"):
                try:
                    table[name][i] = value
                except (OverflowError, ValueError):
                    table[name][i] = 0
    return table


@pytest.mark.parametrize(("message_type", "key", "header"), [
    (CENTROIDS, "stars", {"frame": 3, "method": "GAUSSFIT"}),
    (DETECTIONS, "stars", {"frame": 0}),
    (TRACKS, "tracks", {"frame": 7, "method": "NONE", "model": "STATIC"}),
])
@settings(max_examples=150, derandomize=True, deadline=None)
@given(data=st.data())
def test_same_bytes_or_same_refusal_as_the_dict_path(message_type: MessageType, key: str, header: dict,
                                                     data: st.DataObject) -> None:
    table = data.draw(record_tables(message_type, key))
    encoder = RecordEncoder(message_type, key)
    new = _outcome(lambda: encoder.encode(header, table))
    old = _outcome(lambda: _reference(header, key, table, message_type))
    assert new == old


def test_real_detections_and_centroids_encode_to_the_dict_path_bytes() -> None:
    sim = Simulator(SimulationConfig(width=128, height=128, n_stars=12, n_frames=3, margin=8.0, seed=5))
    for k, frame in enumerate(sim.frames()):
        detections, centroids = extract_stars(frame.image, methods=(CentroidMethod.GAUSSFIT,), gain=1.0)
        assert detections.size > 5
        got = record_encoder("starlog.Detections", "stars").encode({"frame": k}, detections)
        assert got == _reference({"frame": k}, "stars", detections, DETECTIONS)
        table = centroids[CentroidMethod.GAUSSFIT]
        header = {"frame": k, "method": "GAUSSFIT"}
        assert record_encoder("starlog.Centroids", "stars").encode(header, table) == _reference(
            header, "stars", table, CENTROIDS)


def test_a_nan_is_refused_with_the_dict_paths_message() -> None:
    table = np.zeros(2, [("star", np.int32), ("x", np.float64)])
    table["x"][1] = np.nan
    encoder = RecordEncoder(DETECTIONS, "stars")
    with pytest.raises(InvalidInputError, match="NaN or infinite"):
        encoder.encode({"frame": 1}, table)


def test_a_bad_value_is_named_with_its_place() -> None:
    table = np.zeros(3, [(n, np.int64) for n in ("star", "x", "y", "flux", "snr", "sigma", "peak", "background",
                                                 "psf_sigma", "flags", "n_masked")])
    table["n_masked"][2] = -1
    with pytest.raises(InvalidInputError, match=r"\$\.stars\[2\]\.n_masked"):
        RecordEncoder(CENTROIDS, "stars").encode({"frame": 1, "method": "MOMENT"}, table)


def test_extra_columns_follow_the_table_and_must_have_its_length() -> None:
    rows = np.zeros(2, [("track", np.int32)])
    schema = {"type": "object", "properties": {"frame": {"type": "integer"}, "rows": {
        "type": "array", "items": {"type": "object", "properties": {
            "track": {"type": "integer"}, "name": {"type": "string"}, "ok": {"type": "boolean"}}}}}}
    kind = MessageType("t.Rows", "jsonschema", json.dumps(schema).encode(), "json")
    encoder = RecordEncoder(kind, "rows")
    names = np.array(["a,b", 'say "hi"'])
    got = encoder.message({"frame": 1}, encoder.rows(rows, {"name": names, "ok": np.array([True, False])}))
    assert got == encode_json({"frame": 1, "rows": [{"track": 0, "name": "a,b", "ok": True},
                                                    {"track": 0, "name": 'say "hi"', "ok": False}]})
    with pytest.raises(InvalidInputError, match="needs 2 values"):
        encoder.rows(rows, {"ok": np.array([True])})


def test_header_must_match_and_come_first() -> None:
    encoder = RecordEncoder(DETECTIONS, "stars")
    with pytest.raises(InvalidInputError, match="does not match its schema"):
        encoder.message({"frame": -1}, [])
    with pytest.raises(InvalidInputError, match="must come last"):
        encoder.message({}, [])
    assert encoder.message({"frame": 2}, []) == encode_json({"frame": 2, "stars": []})


def test_only_arrays_of_flat_records_are_accepted() -> None:
    with pytest.raises(InvalidInputError, match="not an array of flat records"):
        RecordEncoder(DETECTIONS, "frame")



def _kind(items: dict, top: dict | None = None) -> MessageType:
    schema = {"type": "object", "properties": {"frame": {"type": "integer"}, "stars": {"type": "array", "items": items}},
              **(top or {})}
    return MessageType("t.Stars", "jsonschema", json.dumps(schema).encode(), "json")


def _same_as_the_dict_path(kind: MessageType, header: dict, table: np.ndarray) -> None:
    assert _outcome(lambda: RecordEncoder(kind, "stars").encode(header, table)) == _outcome(
        lambda: _reference(header, "stars", table, kind))


@pytest.mark.parametrize("name", ["a%b", "a%%b", "100%", "rate_%s"])
def test_field_names_with_percent_signs(name: str) -> None:
    table = np.zeros(2, [("x", np.float64), (name, np.float64)])
    table["x"] = [1.5, 2.5]
    _same_as_the_dict_path(_kind({"type": "object", "properties": {"x": {"type": "number"}}}), {"frame": 1}, table)
    closed = {"type": "object", "properties": {name: {"type": "number"}}, "additionalProperties": False}
    _same_as_the_dict_path(_kind(closed), {"frame": 1}, np.zeros(1, [(name, np.float64)]))


@pytest.mark.parametrize(("dtype", "value", "bound"), [
    (np.float32, 0.1, {"maximum": 0.1}),  # float32(0.1) is 0.10000000149...: above
    (np.float16, 0.1, {"minimum": 0.1}),  # float16(0.1) is 0.0999755...: below
    (np.int64, 2**53 + 1, {"maximum": float(2**53)}),
    (np.int64, 5, {"maximum": 10**400}),
])
def test_bounds_are_compared_exactly(dtype: type, value: float, bound: dict) -> None:
    items = {"type": "object", "properties": {"x": {"type": "number", **bound}}}
    _same_as_the_dict_path(_kind(items), {"frame": 1}, np.array([(value,)], [("x", dtype)]))


def test_unknown_columns_against_an_additional_properties_schema() -> None:
    items = {"type": "object", "properties": {"x": {"type": "number"}}, "additionalProperties": {"type": "integer"}}
    table = np.zeros(1, [("x", np.float64), ("y", np.float64)])
    table["y"] = 0.5
    _same_as_the_dict_path(_kind(items), {"frame": 1}, table)
    table["y"] = 2.0
    _same_as_the_dict_path(_kind(items), {"frame": 1}, table)


@pytest.mark.parametrize("dtype", [np.longdouble, object, "S3"])
def test_columns_orjson_cannot_encode_take_the_dict_path(dtype: object) -> None:
    table = np.zeros(2, [("x", dtype)])
    table["x"] = [1, 2] if dtype != "S3" else [b"ab", b"c"]
    if dtype is object:
        table["x"] = [np.int64(1), 2.5]
    _same_as_the_dict_path(_kind({"type": "object", "properties": {"x": {}}}), {"frame": 1}, table)


def test_header_values_are_encoded_as_a_dict_message_encodes_them() -> None:
    kind = _kind({"type": "object", "properties": {"x": {"type": "number"}}})
    _same_as_the_dict_path(kind, {"frame": np.int64(3)}, np.zeros(1, [("x", np.float64)]))
    _same_as_the_dict_path(kind, {"frame": 1, "gain": float("nan")}, np.zeros(1, [("x", np.float64)]))


def test_records_come_as_a_one_dimensional_array() -> None:
    with pytest.raises(InvalidInputError, match="1-D"):
        RecordEncoder(DETECTIONS, "stars").rows(np.zeros((), [("star", np.int32)]))
