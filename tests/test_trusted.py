"""``starlog run`` tracks the method the log's evidence names ("trusted"), decided once the centroids are written:
the choice and why in the track stage's provenance and the summary, the default kept (saying so) where the log
holds no evidence, the same bytes on every run; ``--method all`` holds every method that can win."""

from __future__ import annotations

from pathlib import Path

import pytest

from starlog.centroiding import CentroidMethod
from starlog.io.reader import LogReader
from starlog.pipeline import PipelineConfig, load_config, run_pipeline
from starlog.report.summary import run_summary_lines
from starlog.sim import Jitter, SimulationConfig
from starlog.stages import simulate_log
from starlog.stages.centroid import centroid_log, parse_methods
from starlog.trusted import DEFAULT_TRACKED, resolve_trusted, trusted_method

TRACK_ONLY = {"centroid": {"methods": ["NONE", "MOMENT", "GAUSSFIT", "WINPOS"]},
              "track": {"methods": ["NONE", "trusted"], "models": ["STATIC"], "tracker": {"sigma_floor": 0.05}}}


@pytest.fixture(scope="module")
def sim_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("trusted") / "sim.mcap"
    simulate_log(SimulationConfig(width=160, height=160, n_stars=10, n_frames=40, seed=4,
                                  jitter=(Jitter(frequency_hz=9.0, amplitude_px=0.05),)), path)
    return path


def test_all_holds_every_method_that_can_win():
    assert {CentroidMethod.WINPOS, CentroidMethod.PSFFIT, CentroidMethod.MOMENT, CentroidMethod.GAUSSFIT,
            CentroidMethod.NONE, CentroidMethod.BICUBIC} <= set(parse_methods("all"))
    assert load_config(None).track["methods"] == ["NONE", "trusted"]


def test_run_tracks_the_method_the_frame_to_frame_noise_names(sim_log: Path, tmp_path: Path):
    result = run_pipeline(sim_log, tmp_path / "out.mcap", PipelineConfig.from_dict(TRACK_ONLY))
    decision = result.trusted
    assert decision is not None and decision["evidence"] == "frame-to-frame"
    assert decision["method"] in ("MOMENT", "GAUSSFIT") and "simulated star field without a sky" in decision["reason"]
    assert [p.name for p in result.layers] == ["out.1-centroid.mcap", "out.2-track-NONE.mcap", "out.mcap"]
    with LogReader(result.layers[-1]) as log:
        record = log.provenance()[-1]
        assert log.has_topic(f"/track/{decision['method']}/STATIC")
    assert record.stage == "track" and record.parameters["method"] == decision["method"]
    assert record.parameters["selected_by"] == decision
    with LogReader(result.layers[0]) as log:  # the same decision from the centroid layer alone
        assert trusted_method(log) == decision
    lines = run_summary_lines(result.output, result.stages, None, (), decision)
    assert f"trust {decision['method']} (least frame-to-frame noise" in lines[1]


def test_run_gives_the_same_bytes_twice(sim_log: Path, tmp_path: Path):
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    first = run_pipeline(sim_log, tmp_path / "a" / "out.mcap", PipelineConfig.from_dict(TRACK_ONLY))
    second = run_pipeline(sim_log, tmp_path / "b" / "out.mcap", PipelineConfig.from_dict(TRACK_ONLY))
    for a, b in zip(first.layers, second.layers, strict=True):
        assert a.read_bytes() == b.read_bytes(), a.name


def test_a_log_too_short_for_evidence_keeps_the_default_and_says_so(tmp_path: Path):
    short = tmp_path / "short.mcap"
    simulate_log(SimulationConfig(width=96, height=96, n_stars=3, n_frames=2, seed=5), short)
    centroid_log(short, tmp_path / "cen.mcap", methods="NONE,MOMENT,GAUSSFIT")
    track, decision = resolve_trusted({"methods": ["NONE", "trusted"]}, tmp_path / "cen.mcap")
    assert decision["method"] == DEFAULT_TRACKED and decision["evidence"] is None
    assert decision["reason"].startswith(f"kept the default {DEFAULT_TRACKED}: no method named")
    assert track["methods"] == ["NONE", DEFAULT_TRACKED] and track["selected_by"] == decision
    lines = run_summary_lines(tmp_path / "x.mcap", [("centroid", {"frames": 2, "detections_per_frame": 3.0})], None,
                              (), decision)
    assert "trust: no method named" in lines[1] and f"kept the default {DEFAULT_TRACKED}" in lines[2]


def test_trusted_standing_for_a_method_already_tracked_is_tracked_once(tmp_path: Path, sim_log: Path):
    centroid_log(sim_log, tmp_path / "cen.mcap", methods="NONE,GAUSSFIT")
    with LogReader(tmp_path / "cen.mcap") as log:
        method = trusted_method(log)["method"]
    track, _ = resolve_trusted({"methods": [method, "trusted"]}, tmp_path / "cen.mcap")
    assert track["methods"] == [method]


def test_all_on_a_log_without_a_star_to_learn_a_psf_from_fits_the_gaussian_and_says_so(tmp_path: Path):
    faint = tmp_path / "faint.mcap"
    simulate_log(SimulationConfig(width=64, height=64, n_stars=0, n_frames=3, seed=6), faint)  # an empty sky
    summary = centroid_log(faint, tmp_path / "cen.mcap", methods="all")
    assert "PSFFIT" in summary.methods and summary.epsf is None
    assert any(n.startswith("PSFFIT fits the Gaussian of the log's PSF width") for n in summary.notes)
