"""A second, independent reader: the TypeScript MCAP indexed reader (@mcap/core) Foxglove uses."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path
from typing import Any

import pytest
from google.protobuf.descriptor import FieldDescriptor as FD

from starlog.io import LogReader, LogWriter
from starlog.codecs import encode_json, json_message_type, protobuf_message_type
from starlog.io.copying import flatten_log
from starlog.codecs.star_tables import star_codec
from starlog.io.verify import verify_file
from starlog.stages.centroid import centroid_log
from starlog.stages import simulate_log
from starlog.excerpt import filter_log
from starlog.stages.motion import motion_log
from starlog.stages.track import track_log
from tests.foreign_logs import write_plain
from tests.helpers import doc_pages, small_config
from tests.json_logs import write_json_log

TS_DIR = Path(__file__).resolve().parent.parent / "tools" / "ts_reader"


@pytest.fixture(scope="module")
def node_reader() -> Path:
    node, npm = shutil.which("node"), shutil.which("npm")
    if node is None or npm is None:
        pytest.skip("Node.js is not installed: the TypeScript MCAP reader check needs node and npm.")
    if not (TS_DIR / "node_modules" / "@mcap" / "core").is_dir():
        subprocess.run([npm, "ci", "--no-audit", "--no-fund", "--loglevel=error"], cwd=TS_DIR, check=True,
                       capture_output=True, timeout=300)
    return TS_DIR / "check.mjs"


def _read_with_node(script: Path, *logs: Path) -> dict[str, Any]:
    result = subprocess.run(["node", str(script), *map(str, logs)], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    return json.loads(result.stdout)


def test_typescript_reader_reads_a_simulated_log(node_reader: Path, sim_log: Path) -> None:
    report = _read_with_node(node_reader, sim_log)
    assert report["counts"] == {"/camera/image": 20, "/camera/frame": 20, "/sim/truth": 20}
    assert report["metadata"] == ["starlog.provenance"]
    assert report["statistics"] == 60


@pytest.mark.parametrize("compression", ["lz4", "none"])
def test_typescript_reader_reads_each_file_of_a_chain_and_together_they_are_the_flattened_log(
        node_reader: Path, sim_log: Path, tmp_path: Path, compression: str) -> None:
    """Each layer opens alone, ids never repeat across the chain, and the files read together (as Foxglove
    merges files opened together) hold what the flattened log holds."""
    layers = [tmp_path / "a.mcap", tmp_path / "b.mcap"]
    for base, layer, topic in [(sim_log, layers[0], "/extra"), (layers[0], layers[1], "/more")]:
        with LogReader(base) as log:
            layer_base = log.layer_base()
        with LogWriter(layer, layer=layer_base, compression=compression) as w:
            ch = w.add_channel(topic, json_message_type("starlog.FrameInfo"))
            for n in range(3):
                w.write(ch, log_time=n * 10_000_000, data=encode_json(
                    {"frame": n, "width": 1, "height": 1, "encoding": "mono8", "bit_depth": 8, "source": ""}))
            w.add_metadata("starlog.provenance", {"stage": "extra"})
    flat = flatten_log(layers[1], tmp_path / "flat.mcap").output
    together = _read_with_node(node_reader, sim_log, *layers)
    alone = _read_with_node(node_reader, flat)
    assert [f["counts"] for f in together["files"][1:]] == [{"/extra": 3}, {"/more": 3}]
    assert together["counts"] == alone["counts"] == {"/camera/image": 20, "/camera/frame": 20, "/sim/truth": 20,
                                                     "/extra": 3, "/more": 3}
    assert [m for m in together["metadata"] if m != "starlog.base"] == alone["metadata"] == ["starlog.provenance"] * 3
    for kind in ("schemaIds", "channelIds"):
        ids = [i for f in together["files"] for i in f[kind]]
        assert len(ids) == len(set(ids)) and sorted(ids) == sorted(alone["files"][0][kind])


def test_typescript_reader_refuses_chunks_without_message_indexes_until_filter_rewrites_them(
        node_reader: Path, sim_log: Path, tmp_path: Path) -> None:
    """What verify's note on such a file says: valid MCAP, which Foxglove's reader refuses; filter rewrites it."""
    bare = write_plain(sim_log, tmp_path / "bare.mcap", message_indexes=False, chunk_size=4096)
    refused = subprocess.run(["node", str(node_reader), str(bare)], capture_output=True, text=True, timeout=120)
    assert refused.returncode != 0 and "chunk index without message indexes" in refused.stderr
    report = verify_file(bare)
    assert report.ok and "Foxglove will not open this file" in report.problems[0].detail
    filter_log(bare, tmp_path / "indexed.mcap")
    assert _read_with_node(node_reader, tmp_path / "indexed.mcap")["counts"] == {
        "/camera/image": 20, "/camera/frame": 20, "/sim/truth": 20}


@pytest.fixture(scope="module")
def star_layers(sim_log: Path, tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    """Layers of protobuf star tables on the simulated log: centroids, tracks, platform motion and residuals."""
    folder = tmp_path_factory.mktemp("star_layers")
    layers = [folder / "cen.mcap", folder / "trk.mcap", folder / "mot.mcap"]
    centroid_log(sim_log, layers[0], methods="GAUSSFIT,MOMENT", mode="full")
    track_log(layers[0], layers[1], method="GAUSSFIT", models="STATIC,CONSTANT_VELOCITY", tracker={"sigma_floor": 0.05})
    motion_log(layers[1], layers[2], track="all", model="translation")
    return layers


def _protobuf_topics(layer: Path) -> set[str]:
    with LogReader(layer, chain=False) as log:
        return {c.topic for c in log.channels() if c.message_encoding == "protobuf"}


def test_typescript_reader_decodes_every_protobuf_message_of_each_layer_alone_with_its_schema(
        node_reader: Path, star_layers: list[Path]) -> None:
    """As Foxglove does (protobufjs from each channel's FileDescriptorSet); the first message of each star table
    decodes to what starlog reads."""
    for layer in star_layers:
        report = _read_with_node(node_reader, layer)["files"][0]
        protobuf = _protobuf_topics(layer)
        assert protobuf and report["decoded"] == {t: n for t, n in report["counts"].items() if t in protobuf}
        assert set(report["first"]) == {t for t in protobuf if t != "/stars/annotations"}
        with LogReader(layer) as log:
            for topic, value in report["first"].items():
                assert value == next(log.messages(topic)).payload, topic


def test_typescript_reader_reads_protobuf_layers_on_a_json_base_and_a_json_layer_on_a_protobuf_one(
        node_reader: Path, sim_log: Path, star_layers: list[Path], tmp_path: Path) -> None:
    old_base = write_json_log(star_layers[0], tmp_path / "old-cen.mcap")
    on_old = tmp_path / "trk-on-old.mcap"
    track_log(old_base, on_old, method="GAUSSFIT", models="STATIC", tracker={"sigma_floor": 0.05})
    old_layer = write_json_log(star_layers[1], tmp_path / "old-trk.mcap", base=star_layers[0])
    for chain in ([old_base, on_old], [sim_log, star_layers[0], old_layer]):
        together = _read_with_node(node_reader, *chain)
        with LogReader(chain[-1]) as log:
            assert together["counts"] == {c.topic: c.message_count for c in log.channels()}
        for file in together["files"]:
            assert set(file["decoded"]) == _protobuf_topics(Path(file["path"]))


def test_typescript_reader_keeps_the_attitude_errors_present_only_when_written(node_reader: Path,
                                                                               tmp_path: Path) -> None:
    """proto3 optional fields: absent when not written (no true attitude), present when written, even 0."""
    codec = star_codec("starlog.Attitude")
    header = {f.name: ([0.0, 0.0, 0.0, 1.0] if f.repeated else 0.5 if f.type == FD.TYPE_DOUBLE else "x"
                       if f.type == FD.TYPE_STRING else True if f.type == FD.TYPE_BOOL else 3)
              for f in codec.fields if not f.presence}
    errors = {"error_x_arcsec": 0.0, "error_y_arcsec": -1.5, "error_roll_arcsec": 2.0}
    with LogWriter(tmp_path / "att.mcap") as writer:
        for k, (topic, message) in enumerate([("/attitude/A", header), ("/attitude/B", {**header, **errors})]):
            channel = writer.add_channel(topic, protobuf_message_type("starlog.Attitude"))
            writer.write(channel, log_time=k, data=codec.encode(message))
    first = _read_with_node(node_reader, tmp_path / "att.mcap")["files"][0]["first"]
    assert first == {"/attitude/A": header, "/attitude/B": {**header, **errors}}


def test_the_readmes_foxglove_plot_paths_give_numbers_on_the_protobuf_layers(node_reader: Path,
                                                                            tmp_path: Path) -> None:
    """Every message path the docs give for Foxglove's Plot panel (docs/FOXGLOVE.md, docs/LIVE.md), evaluated on the
    messages protobufjs decodes (Foxglove's subset: fields, [:], {field==value}), yields numbers: the repeated
    sub-messages keep the filters."""
    docs = "\n".join(page.read_text(encoding="utf-8") for page in doc_pages())
    paths = sorted(set(re.findall(r"`(/[A-Za-z0-9_/]+\.[a-z_]+(?:\[:\]\{[a-z_]+==[a-z0-9]+\}\.[a-z_]+)?)`", docs)))
    assert len(paths) >= 5 and any("{track==9}" in p for p in paths) and any(p.startswith("/attitude/") for p in paths)
    sim, cen, trk, mot, trk2 = (tmp_path / f"{n}.mcap" for n in ("sim", "cen", "trk", "mot", "trk2"))
    simulate_log(small_config(width=160, height=120, n_stars=12, n_frames=20, margin=12.0), sim)
    centroid_log(sim, cen, methods="GAUSSFIT,MOMENT", mode="full")
    track_log(cen, trk, method="GAUSSFIT", models="STATIC", tracker={"sigma_floor": 0.05})
    motion_log(trk, mot)
    track_log(mot, trk2, method="MOMENT", models="STATIC", tracker={"sigma_floor": 0.05})  # the demo's trusted method
    codec = star_codec("starlog.Attitude")
    attitude = {f.name: ([0.0, 0.0, 0.0, 1.0] if f.repeated else 12.5 if f.type == FD.TYPE_DOUBLE else "x"
                         if f.type == FD.TYPE_STRING else True if f.type == FD.TYPE_BOOL else 3)
                for f in codec.fields if not f.presence}
    with LogWriter(tmp_path / "att.mcap") as writer:
        channel = writer.add_channel("/attitude/GAUSSFIT", protobuf_message_type("starlog.Attitude"))
        writer.write(channel, log_time=0, data=codec.encode(attitude))
    result = subprocess.run(["node", str(node_reader), str(sim), str(cen), str(trk), str(mot), str(trk2),
                             str(tmp_path / "att.mcap"),
                             "--paths", *paths], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    found = json.loads(result.stdout)["paths"]
    for path in paths:
        assert found[path]["count"] >= 1 and all(isinstance(v, float | int) for v in found[path]["values"]), path


def test_typescript_reader_cannot_read_channels_its_summary_does_not_repeat_until_filter_rewrites_them(
        node_reader: Path, sim_log: Path, tmp_path: Path) -> None:
    """What verify's note on such a file says: Foxglove's reader takes channels from the summary; filter writes them."""
    unrepeated = write_plain(sim_log, tmp_path / "unrepeated.mcap", repeat_schemas=False, repeat_channels=False,
                             chunk_size=4096)
    refused = subprocess.run(["node", str(node_reader), str(unrepeated)], capture_output=True, text=True, timeout=120)
    assert refused.returncode != 0 and "which the reader does not know" in refused.stderr
    note = [p for p in verify_file(unrepeated).problems if p.kind == "definitions_not_in_summary"]
    assert len(note) == 1 and "Foxglove" in note[0].detail and "starlog filter" in note[0].detail
    with LogReader(unrepeated) as log:
        assert {c.topic: c.message_count for c in log.channels()} == {
            "/camera/image": 20, "/camera/frame": 20, "/sim/truth": 20}
    filter_log(unrepeated, tmp_path / "repeated.mcap")
    assert _read_with_node(node_reader, tmp_path / "repeated.mcap")["counts"] == {
        "/camera/image": 20, "/camera/frame": 20, "/sim/truth": 20}


def test_typescript_reader_reads_every_channel_of_a_shared_topic_once_filter_repeats_them(
        node_reader: Path, tmp_path: Path) -> None:
    """Two image channels and a JSON channel share topics in a file whose summary does not repeat them: verify
    calls it nonconformant (starlog reads it, Foxglove's reader does not) and filter's copy, valid, reads in the
    TypeScript reader channel by channel as starlog reads it."""
    from mcap.writer import IndexType

    from tests.test_shared_topics import CAM, NUM, write_log

    options = {"chunk_size": 300, "index_types": IndexType.ALL, "repeat_schemas": False, "repeat_channels": False}
    shared = tmp_path / "shared.mcap"
    write_log(shared, options, ["raw", "raw_json", "numbers", "numbers_again"], [0, 1, 2, 3, 0, 1, 2, 0, 3])
    refused = subprocess.run(["node", str(node_reader), str(shared)], capture_output=True, text=True, timeout=120)
    assert refused.returncode != 0 and "which the reader does not know" in refused.stderr
    assert verify_file(shared).status == "nonconformant"
    filtered = filter_log(shared, tmp_path / "filtered.mcap").output
    assert verify_file(filtered).status == "valid"
    report = _read_with_node(node_reader, filtered)
    assert report["counts"] == {CAM: 5, NUM: 4}
    assert report["files"][0]["channelCounts"] == {"1": 3, "2": 2, "3": 2, "4": 2}
    with LogReader(filtered) as log:
        assert {c.topic: c.message_count for c in log.channels()} == report["counts"]
        assert {str(i): p.message_count for c in log.channels() for i, p in zip(c.channel_ids, c.per_channel,
                                                                                strict=True)} == \
            report["files"][0]["channelCounts"]
