"""The solve stage on simulated sky fields: channels, layer, identities against the truth, attitude error,
frames that cannot be solved, the CLI, export and the run config. Skipped without cedar-solve (tetra3)."""

from __future__ import annotations

import json
from pathlib import Path

import jsonschema
import numpy as np
import pyarrow.parquet as pq
import pytest
from click.testing import CliRunner

from starlog.cli import cli
from starlog.parquet import export_log
from starlog.io import file_digest
from starlog.codecs import load_json_schema
from starlog import topics
from starlog.io.chain import base_reference
from starlog.facts import log_facts
from starlog.cli.describe import info_text
from starlog.io.reader import LogReader
from starlog.sim import Jitter, SimulationConfig, Simulator
from starlog.stages import simulate_log
from starlog.stages.centroid import centroid_log

pytest.importorskip("tetra3")

from starlog.stages.solve import probe_sky, solve_log  # noqa: E402

SKY = dict(width=384, height=384, sky_attitude=(120.0, -30.0, 40.0), fov_deg=10.0, magnitude_limit=7.0, n_frames=24,
           jitter=(Jitter(5.0, 0.5),), roll_amplitude_rad=0.002, roll_frequency_hz=2.0, seed=2)


@pytest.fixture(scope="module")
def logs(tmp_path_factory) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("solve")
    simulate_log(SimulationConfig(**SKY), folder / "sky.mcap")
    centroid_log(folder / "sky.mcap", folder / "cen.mcap", methods="GAUSSFIT,MOMENT")
    summary = solve_log(folder / "cen.mcap", folder / "att.mcap", centroids="all")
    return {"folder": folder, "sky": folder / "sky.mcap", "cen": folder / "cen.mcap", "att": folder / "att.mcap",
            "summary": summary}


def test_sky_field_truth_holds_the_attitude_and_catalogue_stars(logs):
    sim = Simulator(SimulationConfig(**SKY))
    assert sim.field.x.size >= 15 and sim.field.catalogue_id is not None
    with LogReader(logs["sky"]) as log:
        truth = [m.payload for m in log.messages(topics.TRUTH)]
    schema = load_json_schema("starlog.SimTruth")
    for record in truth[:3]:
        jsonschema.validate(record, schema)
    first = truth[0]
    assert {"quaternion", "ra_deg", "dec_deg", "roll_deg"} <= set(first["attitude"])
    assert first["stars"][0]["catalogue_id"] == int(sim.field.catalogue_id[0])
    # the platform turns the camera: the truth's attitude changes from frame to frame, the catalogue stars follow it
    assert truth[5]["attitude"]["quaternion"] != first["attitude"]["quaternion"]
    moved = np.hypot(truth[5]["stars"][0]["x"] - first["stars"][0]["x"], truth[5]["stars"][0]["y"] - first["stars"][0]["y"])
    assert 0.01 < moved < 3.0


def test_the_layer_holds_only_the_solve_channels_and_names_its_base(logs):
    with LogReader(logs["att"], chain=False) as layer:
        topics_in_layer = set(layer.topics)
        base = base_reference(layer.files[0])
    assert topics_in_layer == ({f"/attitude/{m}" for m in ("GAUSSFIT", "MOMENT")}
                               | {f"/stars/identified/{m}" for m in ("GAUSSFIT", "MOMENT")}
                               | {f"/stars/identified/{m}/annotations" for m in ("GAUSSFIT", "MOMENT")})
    assert base is not None and base.path == "cen.mcap"
    with LogReader(logs["att"]) as log:
        record = log.provenance()[-1]
    assert record.stage == "solve" and record.input_digest == file_digest(logs["cen"])
    assert record.parameters["centroids"] == ["/stars/centroids/GAUSSFIT", "/stars/centroids/MOMENT"]


def test_every_frame_solved_lost_in_space_once_then_tracked(logs):
    with LogReader(logs["att"]) as log:
        records = [m.payload for m in log.messages("/attitude/GAUSSFIT")]
    schema = load_json_schema("starlog.Attitude")
    for record in records:
        jsonschema.validate(record, schema)
    assert all(r["solved"] for r in records)
    assert [r["mode"] for r in records] == ["lost_in_space"] + ["tracking"] * (len(records) - 1)
    assert records[0]["ra_deg"] == pytest.approx(120.0, abs=0.01) and records[0]["dec_deg"] == pytest.approx(-30.0, abs=0.01)
    assert records[0]["fov_deg"] == pytest.approx(10.0)  # the simulator's camera, from its provenance


def test_identified_stars_are_the_truths_catalogue_stars(logs):
    with LogReader(logs["att"]) as log:
        identified = [m.payload for m in log.messages("/stars/identified/GAUSSFIT")]
        truth = [m.payload for m in log.messages(topics.TRUTH)]
        annotations = next(log.messages("/stars/identified/GAUSSFIT/annotations")).payload
    jsonschema.validate(identified[0], load_json_schema("starlog.IdentifiedStars"))
    for frame, true in zip(identified, truth):
        by_id = {s["catalogue_id"]: s for s in true["stars"]}
        assert len(frame["stars"]) >= 0.8 * len(by_id)
        for star in frame["stars"]:
            t = by_id[star["catalogue_id"]]
            # the catalogue star projected with the solved attitude lands on its true position
            assert np.hypot(star["x_catalogue"] - t["x"], star["y_catalogue"] - t["y"]) < 0.05
            assert np.hypot(star["x"] - t["x"], star["y"] - t["y"]) < 3.0  # blended pairs pull a centroid
            assert star["magnitude"] == pytest.approx(t["magnitude"])
    assert len(annotations.texts) == len(identified[0]["stars"])
    assert annotations.texts[0].text.startswith("HIP ")


def test_attitude_error_is_within_the_covariance_bound(logs):
    for method in ("GAUSSFIT", "MOMENT"):
        error = logs["summary"].methods[method]["attitude_error"]
        assert error["frames"] == SKY["n_frames"]
        assert error["ratio"]["cross_boresight"] <= 1.5 and error["ratio"]["roll"] <= 1.5


def test_export_writes_attitude_and_identified_tables(logs, tmp_path):
    written = export_log(logs["att"], tmp_path, tables=["attitude", "identified"])
    assert written["attitude"] == 2 * SKY["n_frames"]
    table = pq.read_table(tmp_path / "attitude.parquet").to_pydict()
    for column in ("frame", "log_time", "solved", "ra_deg", "dec_deg", "roll_deg", "fov_deg", "n_matched",
                   "residual_px", "residual_arcsec", "error_roll_arcsec"):
        assert column in table
    assert all(table["solved"]) and np.isfinite(table["error_x_arcsec"]).all()
    identified = pq.read_table(tmp_path / "identified.parquet")
    assert identified.num_rows == sum(table["n_matched"])


def test_frames_that_cannot_be_solved_say_why(tmp_path):
    config = SimulationConfig(width=128, height=96, n_stars=5, n_frames=3, seed=1)
    simulate_log(config, tmp_path / "rand.mcap")
    centroid_log(tmp_path / "rand.mcap", tmp_path / "cen.mcap", methods="GAUSSFIT")
    summary = solve_log(tmp_path / "cen.mcap", tmp_path / "att.mcap",
                        options={"timeout_ms": 200, "try_mirrored": False, "min_stars": 6})
    with LogReader(tmp_path / "att.mcap") as log:
        records = [m.payload for m in log.messages("/attitude/GAUSSFIT")]
    assert len(records) == 3 and not any(r["solved"] for r in records)
    reasons = [r["reason"] for r in records]
    assert all(r.startswith(("too few stars (", "lost-in-space: no solution (")) for r in reasons), reasons
    assert any("usable centroids, fewer than 6" in r for r in reasons)
    assert sum(summary.methods["GAUSSFIT"]["unsolved"].values()) == 3


def test_solve_command_prints_the_residual_table_and_the_attitude_error(logs, tmp_path):
    out = tmp_path / "cli.mcap"
    result = CliRunner().invoke(cli, ["solve", str(logs["cen"]), "-o", str(out), "--centroids", "GAUSSFIT", "--end",
                                      "frame:6", "-q"])
    assert result.exit_code == 0, result.output
    assert "GAUSSFIT" in result.output and "focal px" in result.output
    assert "attitude error against the true attitude" in result.output
    bad = CliRunner().invoke(cli, ["solve", str(logs["cen"]), "-o", str(tmp_path / "x.mcap"), "--centroids", "PSFFIT"])
    assert bad.exit_code == 1 and "no centroid channel /stars/centroids/PSFFIT" in bad.output


def test_report_shows_the_attitude_residuals_and_error_per_method(logs, tmp_path):
    from starlog.report import write_report

    html = write_report(logs["att"], tmp_path / "r.html").read_text(encoding="utf-8")
    assert "Attitude and catalogue residuals per centroid method" in html
    assert "attitude from GAUSSFIT centroids" in html
    assert "residual RMS (arcsec)" in html and "cross-boresight error / sigma" in html
    section = html[html.index('<section id="attitude">'):html.index('<section id="provenance">')]
    assert section.count("<td>MOMENT</td>") == 2  # the residual table and the error table


def test_info_states_the_camera_and_residuals_per_method(logs):
    result = CliRunner().invoke(cli, ["info", str(logs["att"])])
    assert result.exit_code == 0, result.output
    assert "solve      per centroid method" in result.output
    text = result.output[result.output.index("solve      per centroid method"):]
    line = next(ln for ln in text.splitlines() if ln.strip().startswith("GAUSSFIT "))
    assert f"{SKY['n_frames']}/{SKY['n_frames']}" in line and "10.0000" in line
    assert "attitude error RMS arcsec" in result.output


def test_run_config_chains_centroid_and_solve(logs, tmp_path):
    from starlog.pipeline import load_config, run_pipeline, stage_line

    config_file = tmp_path / "p.toml"
    config_file.write_text('[centroid]\nmethods = ["GAUSSFIT"]\n[solve]\ncentroids = "all"\n[solve.options]\n'
                           'match_radius = 2.5\n', encoding="utf-8")
    result = run_pipeline(logs["sky"], tmp_path / "out.mcap", load_config(config_file), end="frame:5")
    assert [name for name, _ in result.stages] == ["centroid", "solve"]
    assert [p.name for p in result.layers] == ["out.1-centroid.mcap", "out.mcap"]
    line = stage_line("solve", result.stages[1][1])
    assert line == "solve: GAUSSFIT 5/5 solved, residual " + line.split("residual ")[1]
    with LogReader(tmp_path / "out.mcap") as log:
        assert log.provenance()[-1].parameters["options"] == {"match_radius": 2.5}


def test_the_readme_solve_block_runs_as_written(tmp_path, monkeypatch):
    """The docs' solve block (docs/PROCESSING.md): a simulated sky field, centroided and solved per method."""
    import shlex

    from tests.helpers import doc_blocks

    blocks = [b for _, b in doc_blocks("bash") if "--sky-attitude" in b and "--centroids all" in b]
    assert len(blocks) == 1, "the docs have no single solve block"
    block = blocks[0]
    monkeypatch.chdir(tmp_path)
    output = ""
    for command in block.strip().split(" && "):
        words = shlex.split(command)
        assert words[0] == "starlog"
        result = CliRunner().invoke(cli, words[1:])
        assert result.exit_code == 0, f"{command}: {result.output}"
        output = result.stdout
    assert "GAUSSFIT" in output and "MOMENT" in output and "attitude error against the true attitude" in output


def test_solve_on_json_centroids_writes_what_it_writes_on_protobuf_ones(logs, tmp_path):
    """A log of an earlier version (centroids as JSON) solves to the same attitude and identified stars."""
    from tests.json_logs import write_json_log

    old = write_json_log(logs["cen"], tmp_path / "old-cen.mcap")
    solve_log(old, tmp_path / "att.mcap", centroids="GAUSSFIT")
    topics_ = ["/attitude/GAUSSFIT", "/stars/identified/GAUSSFIT"]
    with LogReader(tmp_path / "att.mcap") as log, LogReader(logs["att"]) as new:
        assert {c.topic: c.message_encoding for c in log.channels() if c.topic in topics_} == dict.fromkeys(
            topics_, "protobuf")
        for topic in topics_:  # solver_ms: the solver's own time, not a result
            assert [{**m.payload, "solver_ms": 0} for m in log.messages(topic)] == [
                {**m.payload, "solver_ms": 0} for m in new.messages(topic)]


@pytest.fixture(scope="module")
def deep(tmp_path_factory) -> dict[str, object]:
    """A field to magnitude 8: enough stars for the sky to judge on the brighter half."""
    folder = tmp_path_factory.mktemp("deep")
    simulate_log(SimulationConfig(**{**SKY, "magnitude_limit": 8.0, "n_frames": 6}), folder / "sky.mcap")
    centroid_log(folder / "sky.mcap", folder / "cen.mcap", methods="GAUSSFIT,MOMENT")
    return {"cen": folder / "cen.mcap", "att": folder / "att.mcap",
            "summary": solve_log(folder / "cen.mcap", folder / "att.mcap", centroids="all")}


def test_the_sky_judges_the_centroid_methods_on_the_stars_both_identified(deep):
    sky = deep["summary"].sky_evidence
    assert set(sky) == {"GAUSSFIT", "MOMENT"}
    g, m = sky["GAUSSFIT"], sky["MOMENT"]
    assert g["stars"] == m["stars"] >= 20 and g["frames"] == m["frames"] == 6
    # a simulated sky: the catalogue is the truth and the camera known, the residual is the centroid error alone
    for e in (g, m):
        assert 0.0 < e["residual_px"] < 0.1 and e["interval_px"][0] <= e["residual_px"] <= e["interval_px"][1]
        assert e["focal_px"] == pytest.approx(384 / 2 / np.tan(np.radians(5.0)), rel=1e-3)
    assert g["p_best"] + m["p_best"] == pytest.approx(1.0)
    info = log_facts(deep["att"])
    assert info["solve"][-1]["sky_evidence"] == json.loads(json.dumps(sky))
    text = info_text(info)
    assert "sky        per centroid method: catalogue residual" in text
    decision = info["trust"]
    assert decision["evidence"] == "sky" and decision["method"] == min(sky, key=lambda k: sky[k]["residual_px"])
    assert text.splitlines()[-2] == f"trust      {decision['method']} (by sky evidence)"


def test_too_few_stars_for_the_sky_leave_the_frame_to_frame_noise_to_name_the_method(logs):
    sky = logs["summary"].sky_evidence
    assert 0 < sky["GAUSSFIT"]["stars"] < 20
    decision = log_facts(logs["att"])["trust"]
    assert decision["evidence"] == "frame-to-frame" and "the sky needs 20" in decision["reason"]


def test_the_sky_is_probed_in_memory_and_not_on_a_field_without_a_sky(deep, tmp_path):
    with LogReader(deep["cen"]) as log:
        sky, why = probe_sky(log, ["/stars/centroids/GAUSSFIT", "/stars/centroids/MOMENT"], frames=3)
    assert why == "" and sky["GAUSSFIT"]["frames"] == 3 and sky["GAUSSFIT"]["stars"] >= 20
    flat = tmp_path / "flat.mcap"
    simulate_log(SimulationConfig(width=128, height=128, n_stars=8, n_frames=3), flat)
    centroid_log(flat, tmp_path / "flat-cen.mcap", methods="GAUSSFIT,MOMENT")
    with LogReader(tmp_path / "flat-cen.mcap") as log:
        sky, why = probe_sky(log, ["/stars/centroids/GAUSSFIT", "/stars/centroids/MOMENT"])
    assert sky is None and why.startswith("a simulated star field without a sky")
