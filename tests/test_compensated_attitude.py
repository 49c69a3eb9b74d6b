"""The attitude before and after compensation: simulate a catalogue field with jitter, centroid, track,
``compensate --stars all``, then ``solve --compensated``: the all-star channels, the attitude channels before and
after with their error against the simulator's truth, and ``--stars brightest`` writing the same bytes as a run without the option.
Skipped without cedar-solve (tetra3)."""

from __future__ import annotations

import jsonschema
import pytest
from click.testing import CliRunner

from starlog.cli import cli
from starlog.codecs import load_json_schema
from starlog import topics
from starlog.io.reader import LogReader
from starlog.sim import Jitter, SimulationConfig
from starlog.stages import simulate_log
from starlog.stages.centroid import centroid_log
from starlog.stages.compensate import compensate_log
from starlog.stages.track import track_log

pytest.importorskip("tetra3")

from starlog.stages.solve import solve_log  # noqa: E402

SKY = dict(width=256, height=256, sky_attitude=(120.0, -30.0, 40.0), fov_deg=10.0, magnitude_limit=7.0, n_frames=240,
           jitter=(Jitter(5.0, 0.5),), seed=2)
STARS = "/compensated/MOMENT/RANDOM_WALK/stars/50Hz/truth"


@pytest.fixture(scope="module")
def logs(tmp_path_factory) -> dict[str, object]:
    folder = tmp_path_factory.mktemp("compatt")
    simulate_log(SimulationConfig(**SKY), folder / "sky.mcap")
    centroid_log(folder / "sky.mcap", folder / "cen.mcap", methods="MOMENT")
    track_log(folder / "cen.mcap", folder / "trk.mcap", method="MOMENT", models=["RANDOM_WALK"])
    compensated = compensate_log(folder / "trk.mcap", folder / "all.mcap", rates=[50], protocols="paper,truth",
                                 motion="keep,separate", stars="all")
    solved = solve_log(folder / "all.mcap", folder / "att.mcap", compensated="50/truth,50/truth/separate")
    return {"folder": folder, "compensated": compensated, "solved": solved}


def test_every_confirmed_track_is_compensated_per_frame(logs):
    summary = logs["compensated"]
    groups = {g["topic"]: g for g in summary.stars}
    assert set(groups) == {STARS, STARS + "/separate", STARS.replace("truth", "paper"),
                           STARS.replace("truth", "paper") + "/separate"}
    group = groups[STARS]
    assert group["tracks"] >= 15 and group["compensated"] + sum(group["left_out"].values()) == group["tracks"]
    assert group["compensated"] >= 15 and group["frames"] >= 16
    schema = load_json_schema("starlog.CompensatedStars")
    with LogReader(logs["folder"] / "all.mcap") as log:
        frames = [m.payload for m in log.messages(STARS)]
        decisions = [m.payload for m in log.messages("/compensated/MOMENT/RANDOM_WALK/stars/decisions")]
        brightest = list(log.messages("/compensated/MOMENT/RANDOM_WALK/50Hz/truth"))
        record = log.provenance()[-1]
    jsonschema.validate(frames[0], schema)
    assert len(frames) == group["frames"] and max(len(f["stars"]) for f in frames) == group["compensated"]
    assert [f["sample"] for f in frames] == list(range(len(frames)))
    # one decision record per compensated star, rate, protocol and motion mode, each with its own strategies
    assert len(decisions) == sum(g["compensated"] for g in summary.stars)
    assert {d["series_topic"] for d in decisions} == set(groups)
    assert brightest and record.parameters["stars"] == "all"  # the brightest star's channels are kept


def test_the_all_star_output_does_not_depend_on_workers(logs):
    folder = logs["folder"]
    compensate_log(folder / "trk.mcap", folder / "all-2.mcap", rates=[50], protocols="paper,truth",
                   motion="keep,separate", stars="all", workers=2)
    assert (folder / "all-2.mcap").read_bytes() == (folder / "all.mcap").read_bytes()


def test_attitude_before_and_after_compensation_against_the_truth(logs):
    solved = logs["solved"].methods
    names = [f"compensated/MOMENT/RANDOM_WALK/50Hz/truth{s}/{w}" for s in ("", "/separate") for w in ("before", "after")]
    assert list(solved) == names
    with LogReader(logs["folder"] / "att.mcap") as log:
        for name in names:
            records = [m.payload for m in log.messages(topics.attitude_topic(name))]
            assert len(records) == logs["compensated"].stars[0]["frames"]
            assert all(r["solved"] for r in records) and "error_x_arcsec" in records[0]
            assert log.has_topic(topics.identified_topic(name))
        identified = next(log.messages(topics.identified_topic(names[1]))).payload
    assert len(identified["stars"]) >= 10  # identities of the compensated tracks (star = track id)
    for name in names:
        error = solved[name]["attitude_error"]
        assert error["frames"] == solved[name]["frames"] and error["rms_arcsec"]["x"] < 60
    lines = logs["solved"].lines()
    assert any(line.startswith("compensated/MOMENT/RANDOM_WALK/50Hz/truth/separate: attitude error") for line in lines)
    # compensating the residual from the platform motion keeps the motion: the attitude error does not grow
    before = solved[names[2]]["attitude_error"]["rms_arcsec"]
    after = solved[names[3]]["attitude_error"]["rms_arcsec"]
    assert after["x"] <= before["x"] and after["y"] <= before["y"]


def test_brightest_is_the_default_and_writes_the_same_bytes(logs, tmp_path):
    folder = logs["folder"]
    args = ["compensate", str(folder / "trk.mcap"), "--rate", "50", "--protocol", "paper", "-q"]
    plain = CliRunner().invoke(cli, [*args, "-o", str(tmp_path / "plain.mcap")])
    brightest = CliRunner().invoke(cli, [*args, "-o", str(tmp_path / "brightest.mcap"), "--stars", "brightest"])
    assert plain.exit_code == 0 and brightest.exit_code == 0, plain.output + brightest.output
    assert (tmp_path / "plain.mcap").read_bytes() == (tmp_path / "brightest.mcap").read_bytes()
    with LogReader(tmp_path / "plain.mcap", chain=False) as layer:
        assert not [t for t in layer.topics if "/stars/" in t]


def test_the_commands_print_the_stars_and_the_error_before_and_after(logs, tmp_path):
    folder = logs["folder"]
    out = CliRunner().invoke(cli, ["compensate", str(folder / "trk.mcap"), "-o", str(tmp_path / "c.mcap"), "--rate",
                                   "50", "--protocol", "paper", "--stars", "all", "-q"])
    assert out.exit_code == 0, out.output
    assert "/compensated/MOMENT/RANDOM_WALK/stars/50Hz/paper: " in out.output and "confirmed tracks" in out.output
    solved = CliRunner().invoke(cli, ["solve", str(tmp_path / "c.mcap"), "-o", str(tmp_path / "a.mcap"),
                                      "--compensated", "50/paper", "-q"])
    assert solved.exit_code == 0, solved.output
    assert "compensated/MOMENT/RANDOM_WALK/50Hz/paper: attitude error RMS arcsec before -> after" in solved.output
    bad = CliRunner().invoke(cli, ["solve", str(tmp_path / "c.mcap"), "-o", str(tmp_path / "b.mcap"),
                                   "--compensated", "10/paper"])
    assert bad.exit_code == 1 and "no all-star compensated channel '10/paper'" in bad.output


def test_a_run_config_compensates_every_star_and_solves_before_and_after(logs, tmp_path):
    from starlog.pipeline import load_config, run_pipeline

    config = tmp_path / "pipeline.toml"
    config.write_text('[compensate]\nrates = [50]\nprotocols = "paper"\nstars = "all"\n\n'
                      '[solve]\ncentroids = "all"\ncompensated = "all"\n', encoding="utf-8")
    run_pipeline(logs["folder"] / "trk.mcap", tmp_path / "out.mcap", load_config(config))
    with LogReader(tmp_path / "out.mcap") as log:
        assert log.has_topic("/compensated/MOMENT/RANDOM_WALK/stars/50Hz/paper")
        assert log.has_topic("/attitude/MOMENT")
        for which in ("before", "after"):
            assert log.has_topic(f"/attitude/compensated/MOMENT/RANDOM_WALK/50Hz/paper/{which}")


def test_export_keeps_the_brightest_decisions_and_every_attitude(logs, tmp_path):
    from starlog.parquet import export_log

    written = export_log(logs["folder"] / "att.mcap", tmp_path, tables=["decisions", "attitude"])
    frames = logs["compensated"].stars[0]["frames"]
    assert written["attitude"] == 4 * frames
    with LogReader(logs["folder"] / "att.mcap") as log:
        brightest = [m.payload for m in log.messages("/compensated/MOMENT/RANDOM_WALK/decisions")]
    assert written["decisions"] == sum(len(r["compensation"]["passes"]) for r in brightest)
