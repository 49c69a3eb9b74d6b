"""Detections that exist only because of an artefact are flagged ARTEFACT and left out of the centroids."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from starlog.centroiding import CentroidFlag, extract_stars
from starlog.centroiding.stamps import gather_stamps
from starlog.centroiding.artefacts import detection_threshold, remaining_snr
from starlog.cli import cli
from starlog.detect import detect_stars
from starlog.detect.detection import matched_filter
from starlog.io import LogReader
from starlog import topics
from starlog.sim.camera import CameraModel
from starlog.sim.psf import render_stars

SKY, BIAS = 20.0, 100.0
CAMERA = CameraModel(read_noise=3.0, gain=1.0, bias=BIAS, adc_bits=16)
ARTEFACT = int(CentroidFlag.ARTEFACT)


GRID_X, GRID_Y = (a.ravel() for a in np.meshgrid(np.array([24.3, 64.3, 104.3]), np.array([23.8, 63.8, 103.8])))


def _field() -> np.ndarray:
    """Expected image (e-) of 128x128 px with a 3x3 grid of stars (the frame's model error is measured on them)."""
    return SKY + render_stars((128, 128), GRID_X, GRID_Y, np.full(GRID_X.size, 3000.0), 1.2)


def _off_grid(det: np.ndarray, centroids: dict, seed: int = 1):
    """The detections away from the grid's stars, and every method's centroids of them."""
    far = np.hypot(det["x"][:, None] - GRID_X, det["y"][:, None] - GRID_Y).min(axis=1) > 3.0
    assert (~far).sum() == GRID_X.size
    return det[far], {m: c[np.isin(c["star"], det["star"][far])] for m, c in centroids.items()}


def _extract(expected: np.ndarray, seed: int):
    det, centroids = extract_stars(CAMERA.expose(expected, np.random.default_rng(seed)),
                                   methods=["GAUSSFIT", "MOMENT"], psf_sigma=1.2)
    assert all(c.size == det.size - np.count_nonzero(det["flags"] & ARTEFACT) for c in centroids.values())
    return _off_grid(det, centroids)


def _assert_only_artefacts(det: np.ndarray, centroids: dict) -> None:
    assert det.size == 1
    assert np.all(det["flags"] & ARTEFACT)
    assert all(c.size == 0 for c in centroids.values())


def test_a_hot_pixel_by_the_frame_edge_alone_is_an_artefact() -> None:
    """Next to the edge the spike test sees a replicated neighbour, so the hot pixel is detected; masked, it
    leaves noise."""
    expected = _field()
    expected[44, 1] += 3000.0
    _assert_only_artefacts(*_extract(expected, 1))


@pytest.mark.parametrize("track", [((44, 45), (44, 45, 46)), ((44, 46), (44, 45))], ids=["block", "pair"])
def test_a_cosmic_ray_hit_alone_is_an_artefact(track) -> None:
    """A soft-edged hit (a 2x3 block; two pixels a knight's move apart), no star: the spike and elongation
    tests let it through."""
    expected = _field()
    rows, cols = track
    if len(rows) == len(cols):
        expected[rows, cols] += 3000.0
    else:
        expected[np.ix_(rows, cols)] += 1500.0
    _assert_only_artefacts(*_extract(expected, 2))


@pytest.mark.parametrize("seed", range(1, 7))
def test_a_faint_star_next_to_a_hot_pixel_is_kept(seed: int) -> None:
    """A star at matched-filter SNR ~20-30 with a hot pixel 3 px away, in its window: the artefact is
    masked, the star stays."""
    x, y = 44.3, 84.6
    expected = _field() + render_stars((128, 128), np.array([x]), np.array([y]), np.array([500.0]), 1.2)
    expected[85, 47] += 300.0
    det, centroids = _extract(expected, seed)
    assert det.size == 1 and not det["flags"][0] & ARTEFACT
    assert np.hypot(det["x"][0] - x, det["y"][0] - y) < 2.5
    for c in centroids.values():
        assert c.size == 1


@pytest.mark.parametrize(("sigma", "flux"), [(0.8, 5e4), (1.2, 3000.0), (2.0, 600.0), (1.2, 400.0)])
def test_clean_frames_flag_nothing_and_drop_no_star(sigma: float, flux: float) -> None:
    rng = np.random.default_rng(4)
    c = 20 + 28 * np.arange(5)
    cx, cy = np.meshgrid(c, c)
    x, y = cx.ravel() + rng.uniform(-0.5, 0.5, cx.size), cy.ravel() + rng.uniform(-0.5, 0.5, cy.size)
    expected = SKY + render_stars((152, 152), x, y, np.full(x.size, flux), sigma)
    for _ in range(3):
        det, centroids = extract_stars(CAMERA.expose(expected, rng), methods=["GAUSSFIT"], psf_sigma=sigma)
        assert not np.any(det["flags"] & ARTEFACT)
        found = np.hypot(det["x"][:, None] - x, det["y"][:, None] - y).min(axis=0) < 1.0
        assert found.all()
        assert np.array_equal(centroids["GAUSSFIT"]["star"], det["star"])


def test_the_remaining_snr_of_a_whole_window_is_the_detector_snr() -> None:
    rng = np.random.default_rng(5)
    image = CAMERA.expose(SKY + render_stars((64, 64), np.array([31.8]), np.array([32.4]), np.array([900.0]), 1.2),
                          rng).astype(np.float32)
    det = detect_stars(image)
    assert det.size == 1
    threshold, filter_sigma = detection_threshold()
    assert (threshold, filter_sigma) == (5.0, 1.5)
    assert detection_threshold({"threshold": 7.0}) == (7.0, 1.5)
    filtered, k1 = matched_filter(image, filter_sigma)
    peak = det["y_peak"][0], det["x_peak"][0]
    want = (filtered[peak] - det["background"][0]) / (det["noise"][0] * np.sum(k1**2))
    st = gather_stamps(image, det["x_peak"].astype(float), det["y_peak"].astype(float), 8, det["background"],
                       det["noise"], 1.0, np.inf)
    got = remaining_snr(st, np.zeros(1), np.zeros(1), det["noise"], filter_sigma, np.zeros(1))
    assert got[0] == pytest.approx(want, rel=1e-4)
    assert got[0] == pytest.approx(det["snr"][0], rel=1e-3)


def test_keeping_artefacts_flags_them_in_the_centroids_too() -> None:
    expected = _field()
    expected[44, 1] += 3000.0
    det, centroids = extract_stars(CAMERA.expose(expected, np.random.default_rng(1)), methods=["GAUSSFIT"],
                                   psf_sigma=1.2, drop_artefacts=False)
    table = centroids["GAUSSFIT"]
    assert det.size == table.size == GRID_X.size + 1
    assert np.array_equal(table["flags"] & ARTEFACT, det["flags"] & ARTEFACT)
    assert np.count_nonzero(table["flags"] & ARTEFACT) == 1


def test_the_centroid_stage_counts_the_artefacts_it_leaves_out(tmp_path: Path) -> None:
    sim, cen = tmp_path / "sim.mcap", tmp_path / "cen.mcap"
    runner = CliRunner()
    made = runner.invoke(cli, ["simulate", "-o", str(sim), "--size", "128x128", "--frames", "20", "--stars", "6",
                               "--hot-pixels", "60", "--cosmic-rays", "20", "--seed", "0", "-q"])
    assert made.exit_code == 0, made.output
    ran = runner.invoke(cli, ["centroid", str(sim), "-o", str(cen), "--method", "GAUSSFIT,NONE", "--json", "-q"])
    assert ran.exit_code == 0, ran.output
    summary = json.loads(ran.output)
    flagged = kept = 0
    with LogReader(cen) as log:
        for det, *cens in zip(log.messages(topics.DETECTIONS), log.messages("/stars/centroids/GAUSSFIT"),
                              log.messages("/stars/centroids/NONE")):
            stars = det.payload["stars"]
            artefacts = {s["star"] for s in stars if s["flags"] & ARTEFACT}
            flagged += len(artefacts)
            for c in cens:
                listed = {s["star"] for s in c.payload["stars"]}
                assert listed == {s["star"] for s in stars} - artefacts
                assert not any(s["flags"] & ARTEFACT for s in c.payload["stars"])
            kept += len(stars) - len(artefacts)
        (record,) = [p for p in log.provenance() if p.stage == "centroid"]
    assert summary["artefacts"] == flagged > 0
    assert record.parameters["results"] == {"artefacts": flagged}
    assert summary["centroids"] == {"GAUSSFIT": kept, "NONE": kept}


def _undersampled_field(psf_sigma: float, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A 256x256 frame of 30 stars of PSF sigma ``psf_sigma`` and 40 hot pixels; its stars' x, y and the hot pixels."""
    rng = np.random.default_rng(seed)
    x, y = rng.uniform(10, 246, 30), rng.uniform(10, 246, 30)
    expected = SKY + render_stars((256, 256), x, y, rng.uniform(2000, 30000, 30), psf_sigma)
    hot = rng.integers(0, 256, (2, 40))
    expected[hot[0], hot[1]] += rng.uniform(500, 5000, 40)
    return CAMERA.expose(expected, rng), x, y, hot


@pytest.mark.parametrize("psf_sigma", [0.3, 0.4])
def test_undersampled_stars_are_found_and_hot_pixels_are_not(psf_sigma: float) -> None:
    """Stars narrower than the default spike test allows (sigma < 0.55 px) look like hot pixels at most
    sub-pixel phases: with the frame's PSF measured undersampled, only candidates sharper than any focused
    star are rejected; the hot pixels are still left out."""
    image, x, y, hot = _undersampled_field(psf_sigma, 7)
    strict = detect_stars(image)
    det, centroids = extract_stars(image, methods=["GAUSSFIT"])
    kept = det[(det["flags"] & ARTEFACT) == 0]
    distance = np.hypot(kept["x"][:, None] - x, kept["y"][:, None] - y)
    near_star = distance.min(axis=1) <= 1.5
    found_strict = np.hypot(strict["x"][:, None] - x, strict["y"][:, None] - y).min(axis=0) <= 1.5
    assert found_strict.mean() < 0.6
    assert (distance.min(axis=0) <= 1.5).mean() >= 0.95
    assert np.count_nonzero(~near_star) <= 1
    on_hot = np.hypot(kept["x"][:, None] - hot[1], kept["y"][:, None] - hot[0]).min(axis=1) <= 0.5
    assert np.count_nonzero(on_hot & ~near_star) <= 1


def test_a_well_sampled_frame_keeps_the_default_spike_test() -> None:
    from starlog.centroiding.psf_width import detect_options_for_psf

    assert detect_options_for_psf(1.2) == {}
    assert detect_options_for_psf(0.4) == {"sharpness_ratio": 0.02}
    assert detect_options_for_psf(0.4, {"sharpness_ratio": 0.2}) == {"sharpness_ratio": 0.2}
    image, x, y, _ = _undersampled_field(1.2, 8)
    det, _ = extract_stars(image, methods=["GAUSSFIT"])
    np.testing.assert_array_equal(det[["x", "y", "flux"]], detect_stars(image)[["x", "y", "flux"]])


def test_the_centroid_stage_records_the_relaxed_spike_test_of_an_undersampled_log(tmp_path: Path) -> None:
    sim, cen = tmp_path / "sim.mcap", tmp_path / "cen.mcap"
    runner = CliRunner()
    made = runner.invoke(cli, ["simulate", "-o", str(sim), "--size", "128x128", "--frames", "10", "--stars", "12",
                               "--psf-sigma", "0.35", "--seed", "1", "-q"])
    assert made.exit_code == 0, made.output
    ran = runner.invoke(cli, ["centroid", str(sim), "-o", str(cen), "--method", "GAUSSFIT", "--json", "-q"])
    assert ran.exit_code == 0, ran.output
    with LogReader(cen) as log:
        (record,) = [p for p in log.provenance() if p.stage == "centroid"]
    assert record.parameters["options"]["detect_options"] == {"sharpness_ratio": 0.02}
    assert json.loads(ran.output)["detections_per_frame"] >= 11
