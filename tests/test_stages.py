"""Integration: the stages on a small simulated log, through the CLI and the library."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import jsonschema
import numpy as np
import pyarrow.parquet as pq
import pytest
from click.testing import CliRunner

from starlog.centroiding import CENTROID_DTYPE
from starlog.cli import cli
from starlog.detect import DETECTION_DTYPE
from starlog.errors import InvalidInputError, InvalidParameterError
from starlog.parquet import TABLES, arrow_schema, export_log, table_columns
from starlog.io import LogReader, file_digest
from starlog.codecs import json_message_type, load_json_schema
from starlog import topics
from starlog.codecs.star_tables import STAR_TABLES, star_codec
from starlog.pipeline import PipelineConfig, load_config, run_pipeline
from starlog.sim import Jitter
from starlog.stages import simulate_log
# private module _stage: the layer the built-in stages write through; its channel-order rule is tested without one
from starlog.replay.layer import extend_log
from starlog.stages.centroid import centroid_log
from starlog.stages.compensate import compensate_log
from starlog.stages.track import track_log
from starlog.tracking import TRACK_DTYPE
from tests.helpers import small_config


def _invoke(*args: str) -> str:
    result = CliRunner().invoke(cli, list(args))
    assert result.exit_code == 0, result.output
    return result.output


@pytest.fixture(scope="module")
def pipeline_logs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """simulate → centroid (all) → track (GAUSSFIT, all models) → compensate (all tracks), via the CLI."""
    d = tmp_path_factory.mktemp("pipeline")
    logs = {name: d / f"{name}.mcap" for name in ("sim", "cen", "trk", "comp")}
    simulate_log(small_config(width=96, height=80, n_stars=4, n_frames=160, margin=12.0,
                              jitter=(Jitter(frequency_hz=9.0, amplitude_px=0.05),)), logs["sim"])
    _invoke("centroid", str(logs["sim"]), "-o", str(logs["cen"]), "--method", "all", "-q")
    _invoke("track", str(logs["cen"]), "-o", str(logs["trk"]), "--centroids", "GAUSSFIT", "--set",
            "sigma_floor=0.05", "-q")
    _invoke("compensate", str(logs["trk"]), "-o", str(logs["comp"]), "--track", "all", "--rate", "25,50", "-q")
    return logs


def test_each_stage_adds_its_channels_and_provenance(pipeline_logs: dict[str, Path]) -> None:
    with LogReader(pipeline_logs["comp"]) as log:
        topics_ = set(log.topics)
        provenance = log.provenance()
    assert {topics.DETECTIONS, topics.ANNOTATIONS, "/stars/centroids/GAUSSFIT", "/stars/centroids/NONE",
            "/track/GAUSSFIT/STATIC", "/track/GAUSSFIT/CONSTANT_VELOCITY",
            "/compensated/GAUSSFIT/STATIC/50Hz/paper", "/compensated/GAUSSFIT/STATIC/25Hz/truth",
            "/compensated/GAUSSFIT/STATIC/decisions"} <= topics_
    assert [p.stage for p in provenance] == ["simulate", "centroid", "track", "compensate"]
    for record, source in zip(provenance[1:], ("sim", "cen", "trk")):
        assert record.input_digest == file_digest(pipeline_logs[source])  # the chain of inputs


def test_every_json_message_validates_against_its_embedded_schema(pipeline_logs: dict[str, Path]) -> None:
    """JSON messages against the schema in the log; protobuf star tables, as the dicts readers get, against the
    JSON Schema of the same table (what earlier versions wrote)."""
    with LogReader(pipeline_logs["comp"]) as log:
        schemas = {s.id: s for f in log.files for s in f.summary.schemas.values()}
        validators, table_validators = {}, {}
        for schema, channel, message in log.raw_messages(log.topics):
            assert schema is not None
            if channel.message_encoding == "protobuf" and schema.name in STAR_TABLES:
                if schema.name not in table_validators:  # the schema checked once, not once a message
                    table_schema = load_json_schema(schema.name)
                    checker = jsonschema.validators.validator_for(table_schema)
                    checker.check_schema(table_schema)
                    table_validators[schema.name] = checker(table_schema)
                table_validators[schema.name].validate(star_codec(schema.name).to_dict(message.data))
            if channel.message_encoding != "json":
                continue
            if schema.id not in validators:
                embedded = json.loads(schemas[schema.id].data)
                assert embedded == load_json_schema(schema.name)
                validators[schema.id] = jsonschema.Draft202012Validator(embedded)
            validators[schema.id].validate(json.loads(message.data))
    assert len(validators) == 4 and set(table_validators) == {"starlog.Detections", "starlog.Centroids",
                                                              "starlog.Tracks"}


@pytest.mark.parametrize(
    ("schema", "dtype", "extra"),
    [("starlog.Centroids", CENTROID_DTYPE, set()), ("starlog.Detections", DETECTION_DTYPE, set())],
)
def test_row_schemas_match_the_algorithm_dtypes(schema: str, dtype: np.dtype, extra: set[str]) -> None:
    properties = load_json_schema(schema)["properties"]["stars"]["items"]["properties"]
    assert set(properties) == set(dtype.names) | extra


def test_track_schema_matches_the_tracker_dtype() -> None:
    properties = load_json_schema("starlog.Tracks")["properties"]["tracks"]["items"]["properties"]
    assert set(properties) == set(TRACK_DTYPE.names) | {"brightest"}


@pytest.mark.parametrize("table", sorted(table_columns()))
def test_parquet_tables_document_every_column(table: str) -> None:
    schema = arrow_schema(table)
    for field in schema:
        assert field.metadata[b"description"]


def test_export_declares_every_table_in_one_place_without_importing_stages(pipeline_logs: dict[str, Path],
                                                                           tmp_path: Path) -> None:
    assert [t.name for t in TABLES] == list(table_columns())
    code = ("import sys; from starlog.parquet import export_log; "
            f"written = export_log({str(pipeline_logs['comp'])!r}, {str(tmp_path)!r}); "
            "loaded = [m for m in sys.modules if m.startswith('starlog.stages')]; "
            "print(len(written), loaded); sys.exit(1 if loaded else 0)")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=False)
    assert done.returncode == 0 and done.stdout.startswith("7 "), done.stdout + done.stderr


def test_annotations_sit_half_a_pixel_off_the_centroids(pipeline_logs: dict[str, Path]) -> None:
    with LogReader(pipeline_logs["cen"]) as log:
        annotation = next(log.messages(topics.ANNOTATIONS))
        centroids = next(log.messages("/stars/centroids/NONE"))
    assert annotation.log_time == centroids.log_time
    got = sorted((c.position.x, c.position.y) for c in annotation.payload.circles)
    want = sorted((s["x"] + 0.5, s["y"] + 0.5) for s in centroids.payload["stars"])
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)


def test_centroids_agree_with_the_truth(pipeline_logs: dict[str, Path]) -> None:
    with LogReader(pipeline_logs["cen"]) as log:
        truth = {m.log_time: m.payload["stars"] for m in log.messages(topics.TRUTH)}
        errors, unmatched, frames = [], 0, 0
        for m in log.messages("/stars/centroids/GAUSSFIT"):
            frames += 1
            true = np.array([(s["x"], s["y"]) for s in truth[m.log_time]])
            for star in m.payload["stars"]:
                assert -0.5 <= star["x"] < 95.5 and -0.5 <= star["y"] < 79.5  # inside the frame
                d = np.hypot(*(true - (star["x"], star["y"])).T).min()
                if d < 1.0:
                    errors.append(d)
                else:
                    unmatched += 1
    assert len(errors) == 4 * frames  # every star found in every frame
    assert np.sqrt(np.mean(np.square(errors))) < 0.03  # bright stars: hundredths of a pixel
    assert unmatched <= 0.05 * frames  # false detections are rare


def test_export_round_trips_the_channels_exactly(pipeline_logs: dict[str, Path], tmp_path: Path) -> None:
    written = export_log(pipeline_logs["comp"], tmp_path)
    assert set(written) == {"frames", "truth", "detections", "centroids", "tracks", "compensation", "decisions"}
    for name in written:
        table = pq.read_table(tmp_path / f"{name}.parquet")
        assert table.schema.names == list(table_columns()[name]["columns"])
        assert table.num_rows == written[name] > 0
    centroids = pq.read_table(tmp_path / "centroids.parquet").to_pylist()
    with LogReader(pipeline_logs["comp"]) as log:
        expected = [{"log_time": m.log_time, "frame": m.payload["frame"], "method": m.payload["method"], **s}
                    for m in log.messages([t for t in log.topics if t.startswith("/stars/centroids/")])
                    for s in m.payload["stars"]]
    key = lambda r: (r["method"], r["log_time"], r["star"])  # noqa: E731
    assert sorted(centroids, key=key) == sorted(expected, key=key)


def test_decision_records_match_the_series(pipeline_logs: dict[str, Path]) -> None:
    with LogReader(pipeline_logs["comp"]) as log:
        records = [m.payload for m in log.messages("/compensated/GAUSSFIT/STATIC/decisions")]
        assert {(r["rate_hz"], r["protocol"]) for r in records} == {
            (r, p) for r in (25.0, 50.0) for p in ("paper", "truth", "leakfree")}
        paper50 = next(r for r in records if r["rate_hz"] == 50.0 and r["protocol"] == "paper")
        samples = [m.payload for m in log.messages(paper50["series_topic"])]
    assert len(samples) == paper50["n_samples"]
    before = np.array([(s["x_before"], s["y_before"]) for s in samples])
    after = np.array([(s["x_after"], s["y_after"]) for s in samples])
    mean = before.mean(axis=0)
    rmse = lambda a: float(np.sqrt(np.mean(np.sum((a - mean) ** 2, axis=1))))  # noqa: E731  (eq. 15)
    figure = paper50["figures"][0]
    assert figure["reference"] == "global_mean"
    assert rmse(before) == pytest.approx(figure["rmse_before"], rel=1e-9)
    assert rmse(after) == pytest.approx(figure["rmse_after"], rel=1e-9)
    kept = [p["strategy"] for p in paper50["compensation"]["passes"] if p["kept"]]
    assert kept == paper50["compensation"]["kept"]
    assert all(p["effective"] >= 0.01 for p in paper50["compensation"]["passes"] if p["kept"])


def test_stage_keeps_its_input_and_refuses_to_overwrite(pipeline_logs: dict[str, Path], tmp_path: Path) -> None:
    before = file_digest(pipeline_logs["cen"])
    out = tmp_path / "t.mcap"
    track_log(pipeline_logs["cen"], out, method="NONE", models="STATIC")
    assert file_digest(pipeline_logs["cen"]) == before
    result = CliRunner().invoke(cli, ["track", str(pipeline_logs["cen"]), "-o", str(out), "--centroids", "NONE"])
    assert result.exit_code == 1 and "--force" in result.output


def test_stage_channels_refuse_time_going_back_unless_unordered(pipeline_logs: dict[str, Path],
                                                                tmp_path: Path) -> None:
    message_type = json_message_type("starlog.FrameInfo")
    info = json.dumps({"frame": 0, "width": 16, "height": 16, "encoding": "mono16", "bit_depth": 16,
                       "source": ""}).encode()
    with pytest.raises(InvalidInputError, match="not after"):
        with extend_log(pipeline_logs["sim"], tmp_path / "a.mcap", stage="test", parameters={}) as (_, out):
            ch = out.add_channel("/test/ordered", message_type)
            out.writer.write(ch, log_time=2, data=info)
            out.writer.write(ch, log_time=2, data=info)
    assert not (tmp_path / "a.mcap").exists()
    with extend_log(pipeline_logs["sim"], tmp_path / "b.mcap", stage="test", parameters={}) as (_, out):
        ch = out.add_channel("/test/unordered", message_type, unordered=True)
        for t in (2, 2, 1):
            out.writer.write(ch, log_time=t, data=info)
    with LogReader(tmp_path / "b.mcap") as log:
        assert log.channel("/test/unordered").message_count == 3


def test_parallel_centroiding_gives_the_same_bytes(pipeline_logs: dict[str, Path], tmp_path: Path) -> None:
    for workers in (1, 2):
        centroid_log(pipeline_logs["sim"], tmp_path / f"w{workers}.mcap", methods="GAUSSFIT,NONE", workers=workers)
    assert (tmp_path / "w1.mcap").read_bytes() == (tmp_path / "w2.mcap").read_bytes()


@pytest.mark.parametrize("models", ["all", "STATIC"])
def test_parallel_tracking_gives_the_same_bytes(pipeline_logs: dict[str, Path], tmp_path: Path, models: str) -> None:
    """Models tracked in worker processes, or one model with its reading and encoding in worker processes, write
    the log that tracking in this process writes (the CLI's too, for all models)."""
    for name in ("sim", "cen"):  # a layer names its base relative to itself: the same names beside it
        shutil.copy(pipeline_logs[name], tmp_path / pipeline_logs[name].name)
    for workers in (1, 2):
        track_log(tmp_path / "cen.mcap", tmp_path / f"w{workers}.mcap", method="GAUSSFIT", models=models,
                  tracker={"sigma_floor": 0.05}, workers=workers)
    serial = (tmp_path / "w1.mcap").read_bytes()
    assert serial == (tmp_path / "w2.mcap").read_bytes()
    if models == "all":
        assert serial == pipeline_logs["trk"].read_bytes()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cen.mcap", "sim.mcap", "w1.mcap", "w2.mcap"]


def test_run_equals_the_stages_one_by_one(pipeline_logs: dict[str, Path], tmp_path: Path) -> None:
    config = PipelineConfig.from_dict({
        "centroid": {"methods": ["GAUSSFIT"]},
        "track": {"methods": ["GAUSSFIT"], "models": ["STATIC"], "tracker": {"sigma_floor": 0.05}},
        "compensate": {"tracks": "all", "rates": [50], "protocols": "paper"},
    })
    sim = tmp_path / "sim.mcap"
    shutil.copy(pipeline_logs["sim"], sim)
    (tmp_path / "run").mkdir()
    (tmp_path / "one-by-one").mkdir()
    result = run_pipeline(sim, tmp_path / "run" / "out.mcap", config)
    names = [p.name for p in result.layers]
    assert names == ["out.1-centroid.mcap", "out.2-track-GAUSSFIT.mcap", "out.mcap"]
    layers = [tmp_path / "one-by-one" / name for name in names]
    centroid_log(sim, layers[0], methods=["GAUSSFIT"])
    track_log(layers[0], layers[1], method="GAUSSFIT", models=["STATIC"], tracker={"sigma_floor": 0.05})
    compensate_log(layers[1], layers[2], rates=[50], track="all", protocols="paper")
    for name in names:
        assert (tmp_path / "run" / name).read_bytes() == (tmp_path / "one-by-one" / name).read_bytes(), name
    assert sorted(p.name for p in (tmp_path / "run").iterdir()) == sorted(names)


def test_run_cli_with_a_config_file(pipeline_logs: dict[str, Path], tmp_path: Path) -> None:
    config = tmp_path / "p.toml"
    config.write_text('[centroid]\nmethods = ["NONE"]\n[track]\nmethods = ["NONE"]\nmodels = "STATIC"\n'
                      '[track.tracker]\nsigma_floor = 0.05\n[compensate]\nrates = [50]\nprotocols = "paper,truth"\n')
    output = _invoke("run", str(pipeline_logs["sim"]), "-o", str(tmp_path / "r.mcap"), "--config", str(config), "-q",
                     "--table")
    assert "NONE      STATIC" in output and "truth_series" in output
    assert f"report: {tmp_path / 'r.html'}" in output and (tmp_path / "r.html").is_file()
    assert "[centroid]" in _invoke("run", "--print-config")


@pytest.mark.parametrize(
    ("text", "match"),
    [("[centroids]\n", "unknown table"), ("[track]\nmodel = 'STATIC'\n", "unknown key"),
     ("[compensate]\n", "needs rates"), ("[track\n", "not valid TOML")],
)
def test_bad_configs_are_named(tmp_path: Path, text: str, match: str) -> None:
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(InvalidParameterError, match=match):
        load_config(path)


def test_compensate_input_errors(pipeline_logs: dict[str, Path], tmp_path: Path) -> None:
    with pytest.raises(InvalidParameterError, match="at most the frame rate"):
        compensate_log(pipeline_logs["trk"], tmp_path / "x.mcap", rates=[500], track="GAUSSFIT/STATIC")
    with pytest.raises(InvalidInputError, match="no track channel"):
        compensate_log(pipeline_logs["cen"], tmp_path / "x.mcap", rates=[50])
    with pytest.raises(InvalidParameterError, match="several track channels"):
        compensate_log(pipeline_logs["trk"], tmp_path / "x.mcap", rates=[50])
    assert not (tmp_path / "x.mcap").exists()


def test_unknown_method_and_model_are_named(pipeline_logs: dict[str, Path], tmp_path: Path) -> None:
    with pytest.raises(InvalidParameterError, match="unknown centroid method 'FOO'"):
        centroid_log(pipeline_logs["sim"], tmp_path / "x.mcap", methods="FOO")
    with pytest.raises(InvalidParameterError, match="unknown motion model"):
        track_log(pipeline_logs["cen"], tmp_path / "x.mcap", method="NONE", models="FAST")


def test_parallel_simulation_gives_the_same_bytes(tmp_path: Path) -> None:
    config = small_config(width=32, height=32, n_stars=2, n_frames=70, margin=6.0)
    for workers in (1, 2):
        simulate_log(config, tmp_path / f"w{workers}.mcap", workers=workers)
    assert (tmp_path / "w1.mcap").read_bytes() == (tmp_path / "w2.mcap").read_bytes()


def test_parallel_compensation_gives_the_same_bytes(pipeline_logs: dict[str, Path], tmp_path: Path) -> None:
    summaries = [compensate_log(pipeline_logs["trk"], tmp_path / f"w{workers}.mcap", rates=[25, 50], track="all",
                                workers=workers) for workers in (1, 2)]
    assert len(summaries[0].records) == 5 * 2 * 3  # every track channel x rate x protocol
    assert summaries[0].records == summaries[1].records
    assert (tmp_path / "w1.mcap").read_bytes() == (tmp_path / "w2.mcap").read_bytes()


def test_paper_claim_holds_under_its_protocol_and_honest_figures_are_reported(pipeline_logs: dict[str, Path]) -> None:
    with LogReader(pipeline_logs["comp"]) as log:
        records = [m.payload for m in log.messages("/compensated/GAUSSFIT/STATIC/decisions")]
    for record in records:
        figures = {f["reference"]: f for f in record["figures"]}
        if record["protocol"] == "paper":
            assert figures["global_mean"]["rmse_after"] < figures["global_mean"]["rmse_before"]
        elif record["protocol"] == "truth":
            assert set(figures) == {"truth_fixed", "truth_series"}
        else:
            assert set(figures) == {"heldout_mean", "truth_fixed", "truth_series"}
        assert all(np.isfinite([f["rmse_before"], f["rmse_after"]]).all() for f in figures.values())


@pytest.mark.parametrize("stage", ["track", "compensate", "motion"])
def test_stage_refuses_to_read_fewer_messages_than_the_channel_holds(
        pipeline_logs: dict[str, Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch, stage: str) -> None:
    """When the statistics promise more messages than the reader delivers, the stage says so and fails."""
    import dataclasses

    real_channel = LogReader.channel
    source = {"track": "/stars/centroids/GAUSSFIT", "compensate": "/track/GAUSSFIT/STATIC",
              "motion": "/track/GAUSSFIT/STATIC"}[stage]

    def inflated(self: LogReader, topic: str) -> Any:
        found = real_channel(self, topic)
        return dataclasses.replace(found, message_count=found.message_count + 1) if topic == source else found

    monkeypatch.setattr(LogReader, "channel", inflated)
    args = {"track": ["--centroids", "GAUSSFIT", "--model", "STATIC"],
            "compensate": ["--track", "GAUSSFIT/STATIC", "--rate", "50", "--protocol", "paper"],
            "motion": ["--track", "GAUSSFIT/STATIC"]}[stage]
    log = pipeline_logs["cen" if stage == "track" else "trk"]
    result = CliRunner().invoke(cli, [stage, str(log), "-o", str(tmp_path / "o.mcap"), *args])
    assert result.exit_code == 1 and "were read but the channel holds" in result.output, result.output
    assert not (tmp_path / "o.mcap").exists()


# private blocks._WORKER_LOG (worker_log's cache) and McapFile._file: a worker's open logs have no public view
def test_a_worker_opens_each_log_once(tmp_path: Path) -> None:
    from starlog.replay import blocks

    log, other = tmp_path / "a.mcap", tmp_path / "b.mcap"
    for path in (log, other):
        simulate_log(small_config(width=32, height=32, n_stars=2, n_frames=3), path)
    first = blocks.worker_log(str(log))
    assert blocks.worker_log(str(log)) is first  # every block of the same log: no second read of its summary
    second = blocks.worker_log(str(other))
    assert second is not first and first.files[0]._file.closed  # the previous log is closed on moving on
    blocks._WORKER_LOG.clear()
    second.close()


def _count_opens(monkeypatch: pytest.MonkeyPatch, path: Path) -> list[Path]:
    """Every LogReader opened on ``path`` from now on (by this process) is listed."""
    opened: list[Path] = []
    original = LogReader.__init__

    def counting(self: LogReader, source: Any, **kwargs: Any) -> None:
        original(self, source, **kwargs)
        if Path(self.path).resolve() == path.resolve():
            opened.append(Path(self.path))

    monkeypatch.setattr(LogReader, "__init__", counting)
    return opened


def test_the_centroid_stage_opens_its_input_once(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    sim = tmp_path / "sim.mcap"
    simulate_log(small_config(width=64, height=64, n_stars=4, n_frames=24, margin=10.0), sim)
    opened = _count_opens(monkeypatch, sim)
    # every step that reads the first frames: the PSF sigma, hot pixels, the mode, the ePSF, the phase calibration
    summary = centroid_log(sim, tmp_path / "cen.mcap", methods="GAUSSFIT,PSFFIT", psf="empirical", hot_pixels="auto",
                           phase_correction="auto", mode="auto")
    assert summary.frames == 24 and summary.epsf is not None and summary.phase_correction is not None
    assert len(opened) == 1, opened


def test_the_compensate_stage_opens_its_input_once(pipeline_logs: dict[str, Path], tmp_path: Path,
                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    opened = _count_opens(monkeypatch, pipeline_logs["trk"])
    summary = compensate_log(pipeline_logs["trk"], tmp_path / "comp.mcap", rates=[50.0], track="all", stars="all",
                             motion="keep,separate")
    assert summary.records and summary.stars
    assert len(opened) == 1, opened


def test_the_open_count_sees_a_second_open(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    sim = tmp_path / "sim.mcap"
    simulate_log(small_config(width=32, height=32, n_stars=2, n_frames=3), sim)
    opened = _count_opens(monkeypatch, sim)
    with LogReader(sim), LogReader(str(sim)), LogReader(tmp_path / "." / "sim.mcap"):
        pass
    assert len(opened) == 3
