"""Hot-pixel maps: learnt from the frames (not the stars), read from files, applied and recorded."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from starlog.centroiding import CentroidMethod, extract_stars
from starlog.centroiding.hotpixels import (
    describe_hot_pixels,
    learn_hot_pixels,
    load_hot_pixels,
    without_hot_pixels,
)
from starlog.cli import cli
from starlog.errors import InvalidInputError
from starlog.io import LogReader
from starlog.sim.camera import CameraModel
from starlog.sim.psf import render_stars
from starlog.sim.simulator import SimulationConfig, Simulator


def _truth_hot(sim: Simulator) -> np.ndarray:
    """Where the hot pixels are: where the expected signal differs from that of the same sky without them."""
    cold = Simulator(replace(sim.config, hot_pixels=0))
    return sim.expected_electrons(0)[0] != cold.expected_electrons(0)[0]


def test_learnt_map_finds_the_hot_pixels_and_not_the_static_stars():
    # static, under-sampled stars and cosmic rays: neither is a hot pixel
    config = SimulationConfig(n_frames=12, seed=5, width=256, height=256, n_stars=40, psf_sigma=0.7,
                              hot_pixels=30, cosmic_rays_per_frame=5.0)
    sim = Simulator(config)
    learnt = learn_hot_pixels(frame.image for frame in sim.frames())
    truth = _truth_hot(sim)
    assert np.count_nonzero(learnt & truth) >= 27
    assert np.count_nonzero(learnt & ~truth) == 0
    # a frame without hot pixels gives an empty map
    quiet = Simulator(SimulationConfig(n_frames=6, seed=5, width=256, height=256, n_stars=40, psf_sigma=0.7))
    assert not learn_hot_pixels(frame.image for frame in quiet.frames()).any()


def test_map_files_text_and_npy(tmp_path: Path):
    mask = np.zeros((20, 30), bool)
    mask[3, 7] = mask[19, 29] = True
    text = tmp_path / "hot.csv"
    text.write_text("# hot pixels\nx,y\n7,3\n\n29,19\n", encoding="utf-8")
    np.save(tmp_path / "hot.npy", mask)
    assert np.array_equal(load_hot_pixels(text, mask.shape), mask)
    assert np.array_equal(load_hot_pixels(tmp_path / "hot.npy", mask.shape), mask)
    (tmp_path / "bad.txt").write_text("30,1\n", encoding="utf-8")
    with pytest.raises(InvalidInputError, match="outside"):
        load_hot_pixels(tmp_path / "bad.txt", mask.shape)
    with pytest.raises(InvalidInputError, match="frames are"):
        load_hot_pixels(tmp_path / "hot.npy", (10, 10))
    record = describe_hot_pixels(mask, "file: hot.csv")
    assert record["count"] == 2 and record["pixels"] == [[7, 3], [29, 19]] and len(record["sha256"]) == 64


def test_hot_pixel_in_a_window_is_left_out_and_never_a_star():
    rng = np.random.default_rng(2)
    x, y = np.array([40.3, 90.7]), np.array([50.2, 60.6])
    expected = 20.0 + render_stars((120, 140), x, y, np.full(2, 4000.0), 1.2)
    expected[52, 42] += 3000.0  # hot pixel on the first star's wing
    expected[100, 20] += 3000.0  # and one alone
    img = CameraModel(read_noise=3.0, gain=1.0, bias=100.0).expose(expected, rng)
    hot = np.zeros(img.shape, bool)
    hot[52, 42] = hot[100, 20] = True
    assert without_hot_pixels(img, hot).dtype == np.float32
    det, cen = extract_stars(img, methods=[CentroidMethod.MOMENT], psf_sigma=1.2, hot_pixels=hot,
                             centroid_options={"robust": False})
    c = cen[CentroidMethod.MOMENT]
    assert det.size == 2
    first = np.argmin(np.hypot(c["x"] - x[0], c["y"] - y[0]))
    assert c["n_masked"][first] == 1 and c["n_masked"][1 - first] == 0
    assert np.hypot(c["x"][first] - x[0], c["y"][first] - y[0]) < 0.1


def test_centroid_cli_learns_and_records_the_map(tmp_path: Path):
    runner = CliRunner()
    sim_log, out = tmp_path / "sim.mcap", tmp_path / "cen.mcap"
    result = runner.invoke(cli, ["simulate", "-o", str(sim_log), "--size", "160x128", "--stars", "6", "--frames", "8",
                                 "--seed", "3", "--hot-pixels", "15", "-q"])
    assert result.exit_code == 0, result.output
    result = runner.invoke(cli, ["centroid", str(sim_log), "-o", str(out), "--method", "MOMENT",
                                 "--hot-pixels", "auto", "-q"])
    assert result.exit_code == 0, result.output
    with LogReader(out) as log:
        record = [p for p in log.provenance() if p.stage == "centroid"][-1].parameters["hot_pixels"]
    assert record["source"].startswith("auto")
    assert 13 <= record["count"] <= 15
    listed = tmp_path / "hot.txt"
    listed.write_text("\n".join(f"{x},{y}" for x, y in record["pixels"]), encoding="utf-8")
    result = runner.invoke(cli, ["centroid", str(sim_log), "-o", str(tmp_path / "file.mcap"), "--method", "MOMENT",
                                 "--hot-pixels", str(listed), "-q"])
    assert result.exit_code == 0, result.output
    with LogReader(tmp_path / "file.mcap") as log:
        again = [p for p in log.provenance() if p.stage == "centroid"][-1].parameters["hot_pixels"]
    assert again["sha256"] == record["sha256"] and again["source"] == f"file: {listed}"
