"""Layered logs: a stage writes a layer naming its base, and a chain reads as one log everywhere.

Oracles: the ``mcap`` library's own reader, each file read alone (a layer is a valid MCAP file on its
own; a chain is the union of its files), and the flattened file (one self-contained log).
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow.parquet as pq
import pytest
from click.testing import CliRunner
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader

from starlog.cli import cli
from starlog.errors import BaseMismatchError, CorruptLogError, InvalidInputError
from starlog.parquet import export_log
from starlog.io import LogReader, LogWriter, file_digest
from starlog.codecs import encode_raw_image, json_message_type, protobuf_message_type
from starlog.io.chain import BASE_METADATA_NAME, LayerBase, base_reference
from starlog.io.recover import recover_log
from starlog.io.copying import flatten_log
from starlog.io.verify import verify_log
from starlog.stages import simulate_log
from starlog.stages.centroid import centroid_log
from starlog.stages.motion import motion_log
from starlog.stages.track import track_log
from tests.helpers import small_config


@pytest.fixture(scope="module")
def chain(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """sim.mcap <- cen.mcap <- trk.mcap <- mot.mcap, in one folder (read-only for the tests)."""
    d = tmp_path_factory.mktemp("chain")
    sim = d / "sim.mcap"
    simulate_log(small_config(n_frames=30, n_stars=4), sim)
    centroid_log(sim, d / "cen.mcap", methods="MOMENT,GAUSSFIT", options={"psf_sigma": 1.2})
    track_log(d / "cen.mcap", d / "trk.mcap", method="GAUSSFIT", models=["STATIC"])
    motion_log(d / "trk.mcap", d / "mot.mcap")
    return {"sim": sim, "cen": d / "cen.mcap", "trk": d / "trk.mcap", "mot": d / "mot.mcap"}


def _messages(path: Path) -> list[tuple[str, int, bytes]]:
    with LogReader(path) as log:
        return [(c.topic, m.log_time, m.data) for _, c, m in log.raw_messages(log.topics)]


def _oracle_messages(*files: Path) -> list[tuple[str, int, bytes]]:
    """Every message of the files, each read alone by the mcap library."""
    out = []
    for path in files:
        with open(path, "rb") as f:
            out += [(c.topic, m.log_time, bytes(m.data)) for _, c, m in make_reader(f).iter_messages()]
    return sorted(out)


def _oracle_metadata(*files: Path) -> list[tuple[str, dict[str, str]]]:
    out = []
    for path in files:
        with open(path, "rb") as f:
            out += [(r.name, dict(r.metadata)) for r in make_reader(f).iter_metadata() if r.name != BASE_METADATA_NAME]
    return out


def _metadata(path: Path) -> list[tuple[str, dict[str, str]]]:
    with LogReader(path) as log:
        return log.metadata()


# ---------------------------------------------------------------- one log
@pytest.mark.parametrize("depth", [1, 2, 3])
def test_a_chain_reads_as_its_files_together_and_as_its_flattened_file(chain: dict[str, Path], tmp_path: Path,
                                                                       depth: int) -> None:
    files = [chain[k] for k in ("sim", "cen", "trk", "mot")][:depth + 1]
    flat = flatten_log(files[-1], tmp_path / "flat.mcap").output
    assert sorted(_messages(files[-1])) == sorted(_messages(flat)) == _oracle_messages(*files) == \
        _oracle_messages(flat)
    assert _messages(files[-1]) == _messages(flat)  # same order too, ties included
    assert _metadata(files[-1]) == _metadata(flat) == _oracle_metadata(*files) == _oracle_metadata(flat)
    with LogReader(files[-1]) as log, LogReader(flat) as whole:
        assert [f.path for f in log.files] == files
        assert [c.to_dict() for c in log.channels()] == [c.to_dict() for c in whole.channels()]


def test_export_of_a_chain_and_of_its_flattened_file_are_the_same_tables(chain: dict[str, Path],
                                                                         tmp_path: Path) -> None:
    flat = flatten_log(chain["mot"], tmp_path / "flat.mcap").output
    a = export_log(chain["mot"], tmp_path / "a")
    assert export_log(flat, tmp_path / "b") == a and len(a) >= 6
    for table in a:
        assert pq.read_table(tmp_path / "a" / f"{table}.parquet").equals(pq.read_table(tmp_path / "b" /
                                                                                       f"{table}.parquet")), table


def test_ids_and_topics_are_unique_across_a_chain(chain: dict[str, Path]) -> None:
    seen: dict[str, set[Any]] = {"schema": set(), "channel": set(), "topic": set()}
    with LogReader(chain["mot"]) as log:
        for file in log.files:
            for kind, values in (("schema", file.summary.schemas), ("channel", file.summary.channels),
                                 ("topic", [c.topic for c in file.summary.channels.values()])):
                assert seen[kind].isdisjoint(values)
                seen[kind].update(values)


def test_a_layer_holds_only_what_its_stage_adds_and_names_its_base(chain: dict[str, Path]) -> None:
    with LogReader(chain["trk"], chain=False) as layer:
        assert layer.topics == ["/track/GAUSSFIT/STATIC"]
        base = base_reference(layer.files[0])
    assert base is not None and base.path == "cen.mcap" and base.size == chain["cen"].stat().st_size
    assert base.sha256 == file_digest(chain["cen"])
    assert base.chain == (file_digest(chain["sim"]),)
    with LogReader(chain["trk"]) as log:
        assert log.provenance()[-1].input_digest == file_digest(chain["cen"])


def test_a_window_reads_only_its_range_and_the_stage_records_it(chain: dict[str, Path], tmp_path: Path) -> None:
    out = tmp_path / "trk.mcap"
    track_log(chain["cen"], out, method="MOMENT", models=["STATIC"], start="frame:10", end="frame:20")
    with LogReader(out) as log:
        assert log.channel("/track/MOMENT/STATIC").message_count == 10
        assert log.channel("/camera/image").message_count == 30  # the base is whole
        assert log.provenance()[-1].parameters["range"]["start"] == "frame:10"
    assert out.parent != chain["cen"].parent  # a layer in another folder than its base


# ---------------------------------------------------------------- where the base is
def _copy_chain(chain: dict[str, Path], to: Path, names: tuple[str, ...] = ("sim", "cen", "trk")) -> dict[str, Path]:
    to.mkdir(parents=True, exist_ok=True)
    return {k: Path(shutil.copy2(chain[k], to / chain[k].name)) for k in names}


def test_a_chain_moved_together_reads_from_anywhere(chain: dict[str, Path], tmp_path: Path,
                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    moved = _copy_chain(chain, tmp_path / "somewhere" / "else")
    monkeypatch.chdir(tmp_path)
    expected = _messages(chain["trk"])
    assert _messages(Path("somewhere/else/trk.mcap")) == expected
    monkeypatch.chdir(moved["sim"].parent)
    assert _messages(Path("trk.mcap")) == expected


@pytest.mark.parametrize("change", ["deleted", "moved", "replaced", "truncated"])
def test_a_wrong_or_missing_base_is_never_read(chain: dict[str, Path], tmp_path: Path, change: str) -> None:
    copy = _copy_chain(chain, tmp_path / "c")
    if change == "deleted":
        copy["cen"].unlink()
    elif change == "moved":
        copy["cen"].rename(tmp_path / "cen.mcap")
    elif change == "replaced":  # `simulate --force` into the base's name
        simulate_log(small_config(n_frames=30, n_stars=4, seed=99), copy["cen"], force=True)
    else:
        with open(copy["cen"], "r+b") as f:
            f.truncate(copy["cen"].stat().st_size - 100)
    with pytest.raises(BaseMismatchError) as err:
        LogReader(copy["trk"])
    message = str(err.value)
    assert str(copy["cen"]) in message and file_digest(chain["cen"]) in message
    assert "Put that file back" in message
    with LogReader(copy["trk"], chain=False) as alone:  # the layer itself still opens
        assert alone.topics == ["/track/GAUSSFIT/STATIC"]


def test_a_base_changed_inside_its_chunks_is_caught_by_verify_and_never_read_silently(tmp_path: Path) -> None:
    sim, out = tmp_path / "sim.mcap", tmp_path / "cen.mcap"
    simulate_log(small_config(n_frames=10), sim, compression="none")
    centroid_log(sim, out, methods="MOMENT", options={"psf_sigma": 1.2})
    with LogReader(sim) as log:
        ci = log.files[0].summary.chunk_indexes[0]
    data = bytearray(sim.read_bytes())
    data[ci.chunk_start_offset + ci.chunk_length - 20] ^= 0xFF  # same size, same summary: only the digest tells
    sim.write_bytes(bytes(data))
    report = verify_log(out)
    assert not report.ok and {"base_digest", "chunk_crc"} <= {p.kind for p in report.errors}
    alone = verify_log(out, chain=False)
    assert alone.ok and "its base was not checked" in alone.verdict()  # the layer alone is intact
    assert "has changed (its SHA-256" in recover_log(out, tmp_path / "rec.mcap").base_note
    with LogReader(out) as log, pytest.raises(CorruptLogError):
        list(log.frames())


def _frames_log(path: Path, seed: int) -> Path:
    """Five uncompressed 16x16 frames of random pixels: logs of two seeds differ in their pixels only."""
    pixels = np.random.default_rng(seed).integers(0, 4096, (5, 16, 16), dtype=np.uint16)
    with LogWriter(path, compression="none", force=True) as writer:
        channel = writer.add_channel("/camera/image", protobuf_message_type("foxglove.RawImage"))
        for n, image in enumerate(pixels):
            writer.write(channel, log_time=n * 10_000_000, data=encode_raw_image(image, log_time=n * 10_000_000))
    return path


def test_a_base_replaced_by_another_of_the_same_size_and_summary_is_refused(tmp_path: Path) -> None:
    """Two uncompressed logs of one layout: the same size and summary, other pixels; the data section's CRC
    tells them apart."""
    base, layer = _frames_log(tmp_path / "frames.mcap", 1), tmp_path / "layer.mcap"
    _layer_on(base, layer)
    with open(base, "rb") as f:
        summary = f.read()[-200:]
    _frames_log(base, 2)
    assert base.read_bytes()[-200:] == summary  # the same summary section, footer and CRC
    with pytest.raises(BaseMismatchError, match="its data section is not the one the layer recorded"):
        LogReader(layer)
    report = recover_log(layer, tmp_path / "rec.mcap")
    assert not report.base and "data section" in report.base_note


def _layer_on(base: Path, layer: Path) -> None:
    with LogReader(base) as log:
        layer_base = log.layer_base()
    with LogWriter(layer, layer=layer_base) as writer:
        channel = writer.add_channel("/extra", json_message_type("starlog.FrameInfo"))
        writer.write(channel, log_time=0, data=b'{"frame":0,"width":16,"height":16,"encoding":"mono16",'
                                               b'"bit_depth":16,"source":""}')


def test_an_output_is_never_a_file_of_its_own_chain(chain: dict[str, Path], tmp_path: Path) -> None:
    copy = _copy_chain(chain, tmp_path / "c")
    before = {k: p.read_bytes() for k, p in copy.items()}
    runner = CliRunner()
    for args in (["track", str(copy["cen"]), "-o", str(copy["sim"]), "--centroids", "MOMENT", "--force"],
                 ["centroid", str(copy["sim"]), "-o", str(copy["sim"]), "--flatten", "--force"],
                 ["flatten", str(copy["trk"]), "-o", str(copy["cen"]), "--force"],
                 ["filter", str(copy["trk"]), "-o", str(copy["sim"]), "--force"]):
        result = runner.invoke(cli, args)
        assert result.exit_code == 1 and "is one of the files it is written from" in result.output, result.output
    assert {k: p.read_bytes() for k, p in copy.items()} == before


def test_a_chain_reads_through_symbolic_links(chain: dict[str, Path], tmp_path: Path) -> None:
    data = _copy_chain(chain, tmp_path / "data" / "sub")
    (tmp_path / "home").mkdir()
    (tmp_path / "home" / "link").symlink_to(data["sim"].parent, target_is_directory=True)
    (tmp_path / "home" / "trk.mcap").symlink_to(data["trk"])
    expected = _messages(chain["trk"])
    assert _messages(tmp_path / "home" / "link" / "trk.mcap") == expected
    assert _messages(tmp_path / "home" / "trk.mcap") == expected
    (tmp_path / "out").mkdir()
    (tmp_path / "results").symlink_to(tmp_path / "out", target_is_directory=True)
    motion_log(tmp_path / "home" / "link" / "trk.mcap", tmp_path / "results" / "mot.mcap")
    assert _messages(tmp_path / "results" / "mot.mcap") == _messages(tmp_path / "out" / "mot.mcap")


def test_verify_reports_a_missing_base_and_ids_that_collide(chain: dict[str, Path], tmp_path: Path) -> None:
    copy = _copy_chain(chain, tmp_path / "c")
    copy["sim"].unlink()
    report = verify_log(copy["trk"])
    assert [p.kind for p in report.errors] == ["base_missing"] and len(report.files) == 2
    bad = tmp_path / "c" / "bad.mcap"
    layer = LayerBase(chain["trk"], chain["trk"].stat().st_size, 0, 0, (), (), 1, 1, frozenset())
    with LogWriter(bad, layer=layer) as w:
        w.add_channel("/other", json_message_type("starlog.FrameInfo"))  # channel id 1: the base's camera
    assert "chain_collision" in {p.kind for p in verify_log(bad).errors}


def test_recover_keeps_a_layer_on_its_base_or_makes_it_stand_alone(chain: dict[str, Path], tmp_path: Path) -> None:
    copy = _copy_chain(chain, tmp_path / "c")
    report = recover_log(copy["trk"], tmp_path / "on-base.mcap")
    assert report.base == str(copy["cen"]) and not report.base_note
    with LogReader(tmp_path / "on-base.mcap") as log:
        assert log.channel("/camera/image").message_count == 30 and log.has_topic("/track/GAUSSFIT/STATIC")
    copy["cen"].unlink()
    report = recover_log(copy["trk"], tmp_path / "alone.mcap")
    assert not report.base and f"base {copy['cen']} is missing" in report.base_note
    with LogReader(tmp_path / "alone.mcap") as log:
        assert log.topics == ["/track/GAUSSFIT/STATIC"] and len(log.files) == 1


def _read_in_another_folder(layer: str, folder: str) -> int:
    """What a Dask worker runs: chdir elsewhere, then read the chain by the layer's absolute path."""
    os.chdir(folder)
    with LogReader(layer) as log:
        return sum(1 for _ in log.raw_messages(log.topics))


def test_a_dask_worker_resolves_a_chain_relative_to_the_layer(chain: dict[str, Path], tmp_path: Path) -> None:
    from starlog.batch import dask_client

    with dask_client(scheduler=None, workers=1) as client:
        count = client.submit(_read_in_another_folder, str(chain["trk"]), str(tmp_path), pure=False).result()
    assert count == len(_messages(chain["trk"]))


# ---------------------------------------------------------------- the commands
def test_info_shows_the_chain_file_by_file(chain: dict[str, Path]) -> None:
    result = CliRunner().invoke(cli, ["info", str(chain["mot"])])
    assert result.exit_code == 0, result.output
    assert "chain      4 files" in result.output
    for i, key in enumerate(("sim", "cen", "trk", "mot"), 1):
        assert f"  {i}. {chain[key]}" in result.output


def test_flatten_and_stage_flatten_write_the_same_self_contained_log(chain: dict[str, Path], tmp_path: Path) -> None:
    runner = CliRunner()
    assert runner.invoke(cli, ["flatten", str(chain["trk"]), "-o", str(tmp_path / "a.mcap"), "-q"]).exit_code == 0
    result = runner.invoke(cli, ["track", str(chain["cen"]), "-o", str(tmp_path / "b.mcap"), "--centroids",
                                 "GAUSSFIT", "--model", "STATIC", "--flatten", "-q"])
    assert result.exit_code == 0, result.output
    assert _messages(tmp_path / "a.mcap") == _messages(tmp_path / "b.mcap") == _messages(chain["trk"])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.mcap", "b.mcap"]  # no hidden layer left
    with LogReader(tmp_path / "b.mcap") as log:
        assert len(log.files) == 1 and BASE_METADATA_NAME not in [n for n, _ in log.files[0].metadata()]


def test_run_flatten_is_run_then_flatten_and_leaves_one_file(chain: dict[str, Path], tmp_path: Path) -> None:
    """The same messages and records (the stages' inputs are other files, so their digests differ), the same
    bytes on a rerun, and nothing left but the output."""
    from starlog.pipeline import PipelineConfig, run_pipeline

    config = PipelineConfig.from_dict({"centroid": {"methods": ["MOMENT"], "options": {"psf_sigma": 1.2}},
                                       "track": {"methods": ["MOMENT"], "models": ["STATIC"]}})
    for folder in ("a", "b"):
        (tmp_path / folder).mkdir()
    layers = run_pipeline(chain["sim"], tmp_path / "a" / "out.mcap", config).layers
    flatten_log(layers[-1], tmp_path / "a" / "flat.mcap")
    run_pipeline(chain["sim"], tmp_path / "b" / "out.mcap", config, flatten=True)
    assert _messages(tmp_path / "b" / "out.mcap") == _messages(tmp_path / "a" / "flat.mcap")
    assert _without_digests(tmp_path / "b" / "out.mcap") == _without_digests(tmp_path / "a" / "flat.mcap")
    once = (tmp_path / "b" / "out.mcap").read_bytes()
    run_pipeline(chain["sim"], tmp_path / "b" / "out.mcap", config, flatten=True, force=True)
    assert (tmp_path / "b" / "out.mcap").read_bytes() == once
    assert [p.name for p in (tmp_path / "b").iterdir()] == ["out.mcap"]


def _without_digests(path: Path) -> list[tuple[str, dict[str, str]]]:
    return [(name, {k: v for k, v in data.items() if k != "input_digest"}) for name, data in _metadata(path)]


def test_a_stage_refuses_a_topic_already_in_the_chain(chain: dict[str, Path], tmp_path: Path) -> None:
    with pytest.raises(InvalidInputError, match="already has a channel '/stars/detections'"):
        centroid_log(chain["trk"], tmp_path / "again.mcap", methods="MOMENT", options={"psf_sigma": 1.2})
    assert not list(tmp_path.iterdir())


# ---------------------------------------------------------------- any sequence of stages
STAGES = {
    "centroid": lambda i, o, r: centroid_log(i, o, methods="MOMENT", options={"psf_sigma": 1.2}, **r),
    "track": lambda i, o, r: track_log(i, o, method="MOMENT", models=["STATIC"], **r),
    "motion": lambda i, o, r: motion_log(i, o, track="/track/MOMENT/STATIC", model="translation", **r),
}


@settings(max_examples=6, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(windows=st.lists(st.sampled_from([None, ("0.05s", None), (None, "0.25s"), ("0.03s", "0.2s")]),
                        min_size=3, max_size=3),
       flatten_at=st.integers(0, 3))
def test_any_sequence_of_stages_flattens_to_the_self_contained_log(chain: dict[str, Path], tmp_path_factory: Any,
                                                                   windows: list[Any], flatten_at: int) -> None:
    """Each stage on the one before, a window or not, one of them perhaps written flattened (then the next
    layers stand on a self-contained file): the chain, the union of its files and its flattened file hold
    the same messages and metadata."""
    d = tmp_path_factory.mktemp("seq")
    source = chain["sim"]
    files = [source]
    for k, (name, window) in enumerate(zip(STAGES, windows, strict=True)):
        out = d / f"{k}-{name}.mcap"
        limits = {} if window is None else {"start": window[0], "end": window[1]}
        STAGES[name](source, out, {**limits, "flatten": k == flatten_at})
        files = [out] if k == flatten_at else [*files, out]
        source = out
    flat = flatten_log(source, d / "flat.mcap").output
    assert _messages(source) == _messages(flat)
    assert sorted(_messages(source)) == _oracle_messages(*files)
    assert _metadata(source) == _metadata(flat) == _oracle_metadata(*files)
