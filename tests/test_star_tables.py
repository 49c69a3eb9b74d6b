"""The star tables' protobuf form: the ``.proto`` sources against their descriptor set and their JSON Schemas,
and the wire codec (:mod:`starlog.codecs.table_wire`) against the protobuf runtime, both ways."""

from __future__ import annotations

import math
import re
import struct
from pathlib import Path
from typing import Any
from unittest import mock

import numpy as np
import numpy.lib.recfunctions as rfn
import pytest
from google.protobuf import message_factory
from google.protobuf.descriptor import FieldDescriptor as FD
from google.protobuf.descriptor_pb2 import FileDescriptorSet
from google.protobuf.descriptor_pool import DescriptorPool
from hypothesis import given, settings
from hypothesis import strategies as st

from starlog.centroiding.table import CENTROID_DTYPE
from starlog.errors import InvalidInputError
from starlog.codecs import encode_json, load_json_schema, protobuf_message_type
from starlog.codecs.star_tables import STAR_TABLES, json_table, star_codec
from starlog.codecs.table_wire import TableCodec
from tests.tool_modules import tool_module

SCHEMAS = Path(__file__).resolve().parent.parent / "schemas"
NAMES = sorted(STAR_TABLES)


def _runtime_classes() -> dict[str, Any]:
    """Message classes built by the protobuf runtime from the committed descriptor set: the reference."""
    pool = DescriptorPool()
    for file in FileDescriptorSet.FromString((SCHEMAS / "starlog.desc").read_bytes()).file:
        pool.Add(file)
    return {name: message_factory.GetMessageClass(pool.FindMessageTypeByName(name)) for name in NAMES}


CLASSES = _runtime_classes()


# ---------------------------------------------------------------- the sources
def test_the_descriptor_set_is_what_the_sources_compile_to() -> None:
    with tool_module("build_descriptors") as tool:
        compiled = FileDescriptorSet.FromString(tool.compile_descriptors())
    committed = FileDescriptorSet.FromString((SCHEMAS / "starlog.desc").read_bytes())
    assert compiled == committed, "schemas/starlog.desc is stale: run python tools/build_descriptors.py"


@pytest.mark.parametrize("name", NAMES)
def test_each_message_has_the_fields_names_and_descriptions_of_its_json_schema(name: str) -> None:
    schema = load_json_schema(name)
    codec = star_codec(name)
    key = STAR_TABLES[name]
    assert codec.table_key == key
    # the same fields; numbered in the order the stages write them (the JSON's key order, which cat prints)
    assert sorted([f.name for f in codec.fields] + ([key] if key else [])) == sorted(schema["properties"])
    source = " ".join(re.sub(r"\s*//\s*", " ", line) for line in
                      (SCHEMAS / "starlog" / f"{name.split('.')[1]}.proto").read_text().splitlines())
    described = dict(schema["properties"])
    if key is not None:
        items = described.pop(key)["items"]["properties"]
        assert list(codec.row_dtype.names) == list(items)
        described.update(items)
    for field, spec in described.items():
        assert " ".join(spec["description"].split()) in " ".join(source.split()), field


@pytest.mark.parametrize("name", NAMES)
def test_a_channel_schema_is_the_descriptor_set_of_its_file(name: str) -> None:
    message_type = protobuf_message_type(name)
    fds = FileDescriptorSet.FromString(message_type.schema_data)
    assert (message_type.schema_encoding, message_type.message_encoding) == ("protobuf", "protobuf")
    assert [f.name for f in fds.file] == [f"starlog/{name.split('.')[1]}.proto"]


# ---------------------------------------------------------------- random messages
_FLOATS = st.floats(allow_nan=True, allow_infinity=True, width=64)
_RANGES = {"i": lambda size: (-(1 << (8 * size - 1)), (1 << (8 * size - 1)) - 1),
           "u": lambda size: (0, (1 << (8 * size)) - 1)}


def _value(codec: TableCodec, name: str, dtype: np.dtype[Any]) -> st.SearchStrategy[Any]:
    if dtype.kind == "U":  # an enum: the names the runtime's descriptor gives
        table = CLASSES[codec.name].DESCRIPTOR.fields_by_name[codec.table_key].message_type
        return st.sampled_from(sorted(v.name for v in table.fields_by_name[name].enum_type.values))
    if dtype.kind == "b":
        return st.booleans()
    if dtype.kind == "f":
        return _FLOATS
    low, high = _RANGES[dtype.kind](dtype.itemsize)
    return st.one_of(st.integers(low, high), st.sampled_from([0, low, high]))


@st.composite
def rows(draw: st.DrawFn, codec: TableCodec) -> np.ndarray:
    dtype = codec.row_dtype
    values = draw(st.lists(st.tuples(*(_value(codec, n, dtype[n]) for n in dtype.names)), max_size=6))
    return np.array(values, dtype=dtype) if values else np.zeros(0, dtype=dtype)


_HEADER = {"uint64": st.integers(0, 2**64 - 1), "uint32": st.integers(0, 2**32 - 1), "string": st.text(max_size=12),
           "bool": st.booleans(), "double": _FLOATS}


@st.composite
def headers(draw: st.DrawFn, codec: TableCodec) -> dict[str, Any]:
    out = {}
    for f in codec.fields:
        kind = {FD.TYPE_UINT64: "uint64", FD.TYPE_UINT32: "uint32", FD.TYPE_STRING: "string", FD.TYPE_BOOL: "bool",
                FD.TYPE_DOUBLE: "double"}[f.type]
        if f.repeated:
            out[f.name] = draw(st.lists(_FLOATS, max_size=9))
        elif not f.presence or draw(st.booleans()):
            out[f.name] = draw(_HEADER[kind])
    return out


def _same(a: Any, b: Any) -> bool:
    """Equal values, floats bit for bit (NaN payloads and the sign of zero included)."""
    if isinstance(a, float) or isinstance(b, float):
        return isinstance(a, float) and isinstance(b, float) and struct.pack("<d", a) == struct.pack("<d", b)
    if isinstance(a, list):
        return isinstance(b, list) and len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    return type(a) is type(b) and a == b


def _same_rows(a: np.ndarray | None, b: np.ndarray | None) -> bool:
    if a is None or b is None:
        return a is None and b is None
    return a.dtype == b.dtype and all(_same(x, y) for n in a.dtype.names for x, y in zip(a[n].tolist(), b[n].tolist()))


def _runtime_message(name: str, header: dict[str, Any], table: np.ndarray | None) -> Any:
    """The message built with the protobuf runtime (the reference) from a header and rows."""
    message = CLASSES[name]()
    for key, value in header.items():
        if isinstance(value, list):
            getattr(message, key).extend(value)
        else:
            setattr(message, key, value)
    key = STAR_TABLES[name]
    if key is not None and table is not None:
        row_type = getattr(message, key)
        for values in table.tolist():
            row = row_type.add()
            for field, value in zip(table.dtype.names, values):
                setattr(row, field, value)
    return message


def _runtime_fields(name: str, message: Any) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """What the runtime reads from a message: its header (present fields) and rows, enums by name."""
    codec = star_codec(name)
    header = {}
    for f in codec.fields:
        if f.presence and not message.HasField(f.name):
            continue
        value = getattr(message, f.name)
        header[f.name] = list(value) if f.repeated else value
    key = STAR_TABLES[name]
    table = []
    if key is not None:
        for row in getattr(message, key):
            table.append({fd.name: (fd.enum_type.values_by_number[getattr(row, fd.name)].name
                                    if fd.enum_type is not None else getattr(row, fd.name))
                          for fd in row.DESCRIPTOR.fields})
    return header, table


def _messages(name: str) -> st.SearchStrategy[tuple[dict[str, Any], np.ndarray | None]]:
    codec = star_codec(name)
    return st.tuples(headers(codec), rows(codec) if codec.table_key else st.none())


@pytest.mark.parametrize("name", NAMES)
@settings(max_examples=60, deadline=None)
@given(data=st.data())
def test_our_bytes_decode_on_the_fast_path_and_the_runtime_reads_the_same(name: str, data: st.DataObject) -> None:
    codec = star_codec(name)
    header, table = data.draw(_messages(name))
    encoded = codec.encode(header, table)
    with mock.patch.object(TableCodec, "_decode_reference", side_effect=AssertionError("not the fast path")):
        decoded = codec.decode(encoded)
    assert decoded.header.keys() == header.keys() and all(_same(decoded.header[k], v) for k, v in header.items())
    assert _same_rows(decoded.rows, table)
    runtime_header, runtime_rows = _runtime_fields(name, CLASSES[name].FromString(encoded))
    assert all(_same(runtime_header[k], v) for k, v in header.items()) and runtime_header.keys() == header.keys()
    assert all(_same(r[k], v) for r, t in zip(runtime_rows, table.tolist() if table is not None else [])
               for k, v in zip(table.dtype.names, t))


@pytest.mark.parametrize("name", NAMES)
@settings(max_examples=60, deadline=None)
@given(data=st.data())
def test_the_runtimes_own_encodings_decode_the_same(name: str, data: st.DataObject) -> None:
    """Any valid encoding decodes to what the runtime reads from it: the runtime's own (default values left
    out), fields in another order, unknown fields, a header given twice (its repeated fields then merge)."""
    codec = star_codec(name)
    header, table = data.draw(_messages(name))
    message = _runtime_message(name, header, table)
    ours = codec.encode(header, table)
    head = codec.encode_header(header)
    unknown = b"\xf8\x06\x07"  # field 111, varint 7
    for encoding in (message.SerializeToString(), message.SerializeToString(deterministic=True),
                     ours[len(head):] + head, ours + unknown, unknown + ours, head + ours):
        decoded = codec.decode(encoding)
        runtime_header, runtime_rows = _runtime_fields(name, CLASSES[name].FromString(encoding))
        assert decoded.header.keys() == runtime_header.keys()
        assert all(_same(decoded.header[k], v) for k, v in runtime_header.items())
        as_rows = [dict(zip(decoded.rows.dtype.names, v)) for v in decoded.rows.tolist()] if decoded.rows is not None \
            else []
        assert len(as_rows) == len(runtime_rows)
        assert all(_same(a[k], b[k]) for a, b in zip(as_rows, runtime_rows) for k in b)


@pytest.mark.parametrize("name", ["starlog.Centroids", "starlog.Tracks", "starlog.StarResiduals"])
def test_to_dict_is_the_json_form(name: str) -> None:
    """The dict of a decoded message is the JSON the stages wrote: same keys in the same order, ints as ints."""
    codec = star_codec(name)
    table = np.zeros(2, dtype=codec.row_dtype)
    for field in table.dtype.names:
        if table.dtype[field].kind == "f":
            table[field] = [1.0, 2.5]
        elif table.dtype[field].kind in "iu":
            table[field] = [3, 4]
    if name == "starlog.StarResiduals":
        table["flag"] = ["used", "short_track"]
    header = {f.name: ("GAUSSFIT" if f.type == FD.TYPE_STRING else 7) for f in codec.fields}
    message = {**header, STAR_TABLES[name]: [dict(zip(table.dtype.names, v)) for v in table.tolist()]}
    assert encode_json(codec.to_dict(codec.encode(header, table))) == encode_json(message)
    assert codec.encode_dict(message) == codec.encode(header, table)


def test_attitude_keeps_its_optional_errors_only_when_given() -> None:
    codec = star_codec("starlog.Attitude")
    header = {f.name: ([] if f.repeated else 0.5 if f.type == FD.TYPE_DOUBLE else "" if f.type == FD.TYPE_STRING
                       else False if f.type == FD.TYPE_BOOL else 1) for f in codec.fields if not f.presence}
    without = codec.to_dict(codec.encode(header))
    assert "error_x_arcsec" not in without and without["solver_ms"] == 0.5
    with_errors = codec.to_dict(codec.encode({**header, "error_x_arcsec": 0.0, "error_y_arcsec": -1.0,
                                              "error_roll_arcsec": 2.0}))
    assert list(with_errors)[-3:] == ["error_x_arcsec", "error_y_arcsec", "error_roll_arcsec"]
    assert with_errors["error_x_arcsec"] == 0.0


# ---------------------------------------------------------------- what is refused
FULL = np.zeros(3, dtype=CENTROID_DTYPE)
NO_MASKED = rfn.drop_fields(FULL, "n_masked", usemask=False)


@pytest.mark.parametrize(("header", "table", "extra", "match"), [
    ({"frame": 1}, FULL, {}, "needs its field 'method'"),
    ({"frame": 1, "method": "NONE", "model": "x"}, FULL, {}, "no field 'model'"),
    ({"frame": -1, "method": "NONE"}, FULL, {}, "out of its range"),
    ({"frame": 1.5, "method": "NONE"}, FULL, {}, "takes an integer"),
    ({"frame": 1, "method": 3}, FULL, {}, "takes a string"),
    ({"frame": 1, "method": "NONE", "stars": []}, FULL, {}, "no field 'stars'"),
    ({"frame": 1, "method": "NONE"}, FULL, {"fwhm": np.zeros(3)}, "no field 'fwhm'"),
    ({"frame": 1, "method": "NONE"}, FULL, {"x": np.zeros(3)}, "repeated field 'x'"),
    ({"frame": 1, "method": "NONE"}, NO_MASKED, {"n_masked": np.zeros(2)}, "needs 3 values"),
    ({"frame": 1, "method": "NONE"}, NO_MASKED, {}, "need the field 'n_masked'"),
    ({"frame": 1, "method": "NONE"}, NO_MASKED, {"n_masked": np.full(3, 2**40)}, "outside"),
    ({"frame": 1, "method": "NONE"}, NO_MASKED, {"n_masked": np.full(3, 0.5)}, "fractions"),
    ({"frame": 1, "method": "NONE"}, NO_MASKED, {"n_masked": np.full(3, True)}, "takes integers"),
    ({"frame": 1, "method": "NONE"}, NO_MASKED, {"n_masked": np.array(["a", "b", "c"])}, "takes integers"),
    ({"frame": 1, "method": "NONE"}, NO_MASKED.reshape(3, 1), {}, "1-D structured array"),
])
def test_a_message_outside_its_schema_is_refused(header: dict[str, Any], table: np.ndarray,
                                                 extra: dict[str, Any], match: str) -> None:
    with pytest.raises(InvalidInputError, match=match):
        star_codec("starlog.Centroids").encode(header, table, extra)


def test_integers_of_wider_types_are_written_when_they_fit() -> None:
    codec = star_codec("starlog.Centroids")
    wide = codec.encode({"frame": 0, "method": "NONE"}, NO_MASKED[:2], {"n_masked": np.array([5.0, 2**31 - 1])})
    assert codec.decode(wide).rows["n_masked"].tolist() == [5, 2**31 - 1]


def test_an_unknown_enum_name_is_refused_and_a_broken_message_does_not_decode() -> None:
    codec = star_codec("starlog.StarResiduals")
    row = {"track": 1, "x": 0.0, "y": 0.0, "x_static": 0.0, "y_static": 0.0, "residual_x": 0.0, "residual_y": 0.0,
           "sigma": 0.0, "flag": "lost"}
    with pytest.raises(InvalidInputError, match="takes one of"):
        codec.encode_dict({"frame": 0, "method": "NONE", "model": "STATIC", "fit": "rigid", "stars": [row]})
    good = codec.encode_dict({"frame": 0, "method": "NONE", "model": "STATIC", "fit": "rigid",
                              "stars": [{**row, "flag": "outlier"}]})
    for broken in (good[:-1], good[:5] + b"\xff" + good[6:], b"\x0a\x05ab"):
        with pytest.raises(InvalidInputError, match="not a valid starlog.StarResiduals"):
            codec.decode(broken)


def test_an_enum_value_without_a_name_reads_as_its_number() -> None:
    codec = star_codec("starlog.StarResiduals")
    message = CLASSES["starlog.StarResiduals"](frame=1)
    message.stars.add(track=2, flag=9)
    assert codec.to_dict(message.SerializeToString())["stars"][0]["flag"] == "9"


# ---------------------------------------------------------------- JSON of older logs
def test_a_json_row_may_lack_n_masked_but_not_a_required_field() -> None:
    row = {"star": 0, "x": 1.0, "y": 2.0, "flux": 3.0, "snr": 4.0, "sigma": 0.1, "peak": 5.0, "background": 6.0,
           "psf_sigma": 1.2, "flags": 4}
    header, rows = json_table("starlog.Centroids", {"frame": 2, "method": "GAUSSFIT", "stars": [row]})
    assert header == {"frame": 2, "method": "GAUSSFIT"} and rows["n_masked"].tolist() == [0]
    assert rows["flags"].tolist() == [4] and rows["x"].tolist() == [1.0]
    with pytest.raises(InvalidInputError, match="need the field 'sigma'"):
        json_table("starlog.Centroids", {"frame": 2, "method": "GAUSSFIT",
                                         "stars": [{k: v for k, v in row.items() if k != "sigma"}]})


def test_nan_survives_where_json_could_not_hold_it() -> None:
    codec = star_codec("starlog.Centroids")
    table = np.zeros(1, dtype=CENTROID_DTYPE)
    table["x"], table["y"] = math.nan, -math.inf
    rows = codec.decode(codec.encode({"frame": 0, "method": "NONE"}, table)).rows
    assert math.isnan(rows["x"][0]) and rows["y"][0] == -math.inf


def test_a_log_written_with_another_version_of_a_schema_reads_by_its_own_schema(tmp_path: Path) -> None:
    """A Centroids schema with one more row field (as a later version might write): messages() and tables()
    read it by the schema in the log, the new field included."""
    from google.protobuf.descriptor_pb2 import FieldDescriptorProto

    from starlog.io import LogReader, LogWriter
    from starlog.codecs import MessageType

    fds = FileDescriptorSet.FromString(protobuf_message_type("starlog.Centroids").schema_data)
    row = next(m for m in fds.file[0].message_type if m.name == "Centroid")
    row.field.add(name="fwhm", number=12, type=FieldDescriptorProto.TYPE_DOUBLE,
                  label=FieldDescriptorProto.LABEL_OPTIONAL, json_name="fwhm")
    pool = DescriptorPool()
    pool.Add(fds.file[0])
    later = TableCodec(pool.FindMessageTypeByName("starlog.Centroids"))
    table = rfn.append_fields(np.zeros(2, dtype=later.row_dtype[[n for n in later.row_dtype.names if n != "fwhm"]]),
                              "fwhm", np.array([2.5, 3.0]), usemask=False)
    with LogWriter(tmp_path / "later.mcap") as writer:
        channel = writer.add_channel("/stars/centroids/NONE", MessageType("starlog.Centroids", "protobuf",
                                                                         fds.SerializeToString(), "protobuf"))
        writer.write(channel, log_time=5, data=later.encode({"frame": 0, "method": "NONE"}, table))
    with LogReader(tmp_path / "later.mcap") as log:
        payload = next(log.messages("/stars/centroids/NONE")).payload
        rows = next(log.tables("/stars/centroids/NONE")).rows
    assert [star["fwhm"] for star in payload["stars"]] == [2.5, 3.0] and list(payload["stars"][0])[-1] == "fwhm"
    assert rows["fwhm"].tolist() == [2.5, 3.0] and rows["n_masked"].tolist() == [0, 0]
