"""The real-sky benchmark's own geometry: projection, camera refit, matching, common stars, grey conversion.

A fake catalogue is projected through a known camera; the benchmark's refit must give a zero
residual for exact positions and the noise level for noisy ones. The plate-solving part runs
only where cedar-solve (``tetra3``) is installed; no test reads the real images.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from tests.tool_modules import tool_module

SHAPE = (768, 1024)


@pytest.fixture(scope="module")
def bench():
    with tool_module("bench_realsky") as module:
        yield module


def _camera(bench, *, parity=1.0, k=-0.02, ra=30.0, dec=40.0, roll=25.0):
    from scipy.spatial.transform import Rotation

    # boresight (camera z) at (ra, dec), rolled about it
    rot = Rotation.from_euler("ZYZ", [ra, 90.0 - dec, roll], degrees=True).as_matrix().T
    cam = bench.camera_for_image(SHAPE, 5000.0, parity=parity)
    return replace(cam, rotation=rot, k=k)


def _field(bench, cam, rng, n=60):
    """Unit vectors of n fake stars inside the frame (10 px margin) of ``cam``."""
    xs = rng.uniform(10, SHAPE[1] - 11, n)
    ys = rng.uniform(10, SHAPE[0] - 11, n)
    # invert the projection numerically: start from the undistorted direction and correct
    vec = np.column_stack([cam.parity * (xs - cam.cx), ys - cam.cy, np.full(n, cam.focal)])
    vec = (vec / np.linalg.norm(vec, axis=1)[:, None]) @ cam.rotation
    for _ in range(20):
        px, py, _ = cam.project(vec)
        cv = vec @ cam.rotation.T
        cv[:, 0] -= cam.parity * (px - xs) / cam.focal * cv[:, 2]
        cv[:, 1] -= (py - ys) / cam.focal * cv[:, 2]
        vec = (cv / np.linalg.norm(cv, axis=1)[:, None]) @ cam.rotation
    return vec


def _perturbed(cam):
    from scipy.spatial.transform import Rotation

    # a solved camera, off by ~0.5 px at most: what compare_centroiders starts from
    small = Rotation.from_rotvec([2e-5, -3e-5, 1e-4]).as_matrix()
    return replace(cam, rotation=small @ cam.rotation, focal=cam.focal * 1.0002, k=cam.k * 0.95)


def test_projection_of_the_boresight_is_the_image_centre(bench):
    cam = _camera(bench, ra=30.0, dec=40.0)
    boresight = bench.radec_vectors(np.array([30.0]), np.array([40.0]))
    x, y, front = cam.project(boresight)
    assert front.all()
    np.testing.assert_allclose([x[0], y[0]], [(SHAPE[1] - 1) / 2, (SHAPE[0] - 1) / 2], atol=1e-9)


@pytest.mark.parametrize("parity", [1.0, -1.0])
def test_camera_from_pairs_recovers_a_known_camera(bench, parity):
    rng = np.random.default_rng(3)
    cam = _camera(bench, parity=parity)
    vec = _field(bench, cam, rng)
    x, y, _ = cam.project(vec)
    fitted = bench.camera_from_pairs(SHAPE, 4900.0, vec, x, y)
    assert fitted.parity == parity
    assert fitted.focal == pytest.approx(cam.focal, rel=1e-6)
    assert fitted.k == pytest.approx(cam.k, abs=1e-6)
    assert bench.residual_rmse(fitted, vec, x, y) < 1e-6


def test_common_stars_and_refit_give_zero_for_exact_and_the_noise_for_noisy_positions(bench):
    rng = np.random.default_rng(7)
    cam = _camera(bench)
    vec = _field(bench, cam, rng, n=200)
    x, y, _ = cam.project(vec)
    flux = rng.uniform(1e3, 1e5, x.size)
    noisy_x, noisy_y = x + rng.normal(0, 0.1, x.size), y + rng.normal(0, 0.1, x.size)
    missing = np.arange(x.size) % 10 != 0  # the third centroider misses every tenth star
    spurious = (rng.uniform(0, SHAPE[1], 30), rng.uniform(0, SHAPE[0], 30))
    positions = {
        "exact": bench.Positions(np.append(x, spurious[0]), np.append(y, spurious[1]), np.append(flux, np.ones(30))),
        "noisy": bench.Positions(noisy_x, noisy_y, flux),
        "partial": bench.Positions(x[missing][::-1], y[missing][::-1], flux[missing][::-1]),
    }
    isolated = bench.isolated(x, y, 4.0)
    comp = bench.compare_centroiders(_perturbed(cam), vec[isolated], positions, radius=2.0)
    expected = np.flatnonzero(missing[isolated])
    np.testing.assert_array_equal(np.sort(comp.common), expected)
    assert comp.rmse["exact"] < 1e-6
    assert comp.rmse["partial"] < 1e-6
    # refitting 5 parameters on ~2 x 160 coordinates leaves ~the noise level
    assert 0.08 < comp.rmse["noisy"] < 0.115
    assert comp.matched["exact"] == isolated.sum()


def test_plate_terms_remove_a_linear_field_pattern(bench):
    rng = np.random.default_rng(11)
    cam = _camera(bench)
    vec = _field(bench, cam, rng, n=80)
    x, y, _ = cam.project(vec)
    # an anisotropic scale (what differential refraction does) that the camera cannot absorb
    warped = bench.Positions(x, cam.cy + (y - cam.cy) * (1 + 4e-4), np.ones(x.size))
    plain = bench.compare_centroiders(cam, vec, {"w": warped}, radius=2.0)
    planar = bench.compare_centroiders(cam, vec, {"w": warped}, radius=2.0, plate_order=1)
    assert plain.rmse["w"] > 0.02
    assert planar.rmse["w"] < 1e-6


def test_match_nearest_is_one_to_one_within_the_radius(bench):
    cat_x, cat_y = np.array([10.0, 11.0, 50.0]), np.array([10.0, 10.0, 50.0])
    idx = bench.match_nearest(cat_x, cat_y, np.array([10.2, 80.0]), np.array([10.0, 80.0]), 2.0)
    np.testing.assert_array_equal(idx, [0, -1, -1])


def test_colour_images_become_the_channel_sum_with_saturated_pixels_marked(bench):
    raw = np.zeros((4, 5, 3), np.uint8)
    raw[1, 2] = (10, 20, 30)
    raw[3, 4] = (255, 0, 0)
    grey, saturation = bench.to_grey(raw)
    assert saturation == 765.0
    assert grey[1, 2] == 60.0
    assert grey[3, 4] == 765.0
    mono = np.arange(20, dtype=np.uint16).reshape(4, 5)
    same, full = bench.to_grey(mono)
    assert same is mono and full == 65535.0


def test_bootstrap_interval_brackets_the_ratio(bench):
    rng = np.random.default_rng(5)
    res_a = rng.normal(0, 0.08, (300, 2))
    res_b = rng.normal(0, 0.10, (300, 2))
    comp = bench.FrameComparison(np.arange(300), np.zeros((300, 2)), {"A": 0.08, "SEP": 0.1},
                                 {"A": res_a, "SEP": res_b}, {"A": 300, "SEP": 300})
    frame = bench.FrameResult("f", {"A": 300, "SEP": 300}, 300, comp, np.zeros(300))
    lo, hi = bench.bootstrap_ratio([frame], "A", "SEP")
    ratio = np.sqrt((res_a**2).sum() / (res_b**2).sum())
    assert lo < ratio < hi
    assert hi - lo < 0.2


def test_plate_solve_of_a_projected_catalogue_gives_zero_residual(bench):
    pytest.importorskip("tetra3")
    solver = bench.load_solver()
    catalogue = solver.star_table
    cam = replace(_camera(bench, ra=83.0, dec=-2.0, roll=40.0), focal=5100.0, k=0.0)  # ~11.4 deg wide
    field = bench.field_stars(cam, catalogue, SHAPE, margin=8.0, isolation=4.0)
    assert field.size > 30
    vec, mag = catalogue[field, 2:5], catalogue[field, 5]
    x, y, _ = cam.project(vec)
    stars = bench.Positions(x, y, 10 ** (-0.4 * mag))
    solved = bench.solve_frame(solver, stars, SHAPE)
    assert solved is not None
    refined, matched = bench.refine_camera(solved, vec, mag, stars)
    assert matched == field.size
    comp = bench.compare_centroiders(refined, vec, {"exact": stars}, radius=2.0)
    assert comp.common.size == field.size
    assert comp.rmse["exact"] < 1e-5


def test_gain_from_the_background_photon_transfer_of_a_vignetted_frame(bench):
    rng = np.random.default_rng(2)
    rows, cols = SHAPE
    yy, xx = np.mgrid[0:rows, 0:cols]
    r2 = ((xx - cols / 2) ** 2 + (yy - rows / 2) ** 2) / (cols / 2) ** 2
    sky_e = 600.0 * (1.0 - 0.45 * r2)  # electrons, vignetted
    gain = 0.25  # e-/DN
    frame = (rng.poisson(sky_e) + rng.normal(0, 3.0, SHAPE)) / gain + 500.0  # read noise 3 e-, pedestal 500 DN
    assert bench.estimate_gain(frame) == pytest.approx(gain, rel=0.05)


def test_gain_is_unknown_on_a_flat_background(bench):
    rng = np.random.default_rng(4)
    frame = rng.poisson(400.0, SHAPE).astype(np.float64)
    assert bench.estimate_gain(frame) is None
    assert bench.frame_gain(frame, "auto") == 1.0
    assert bench.frame_gain(frame, "0.5") == 0.5


def test_phase_equalisation_removes_a_pixel_phase_bias_without_the_truth(bench):
    rng = np.random.default_rng(9)
    frames, truth = [], []
    for _ in range(3):
        tx, ty = rng.uniform(20, 1000, 400), rng.uniform(20, 740, 400)

        def pulled(v):  # biased towards pixel centres, as an undersampled star's centroid is
            p = v - np.rint(v)
            return np.rint(v) + p - 0.06 * np.sin(2 * np.pi * p)

        star = bench.Positions(pulled(tx), pulled(ty), np.ones(400), np.full(400, 100.0))
        frames.append(bench.MeasuredFrame("f", SHAPE, 1.0, {"GAUSSFIT": star}))
        truth.append((tx, ty))
    out = bench.phase_equalised(frames)
    for f, (tx, ty) in zip(out, truth):
        before = f.positions["GAUSSFIT"].x - tx
        after = f.positions["GAUSSFIT+eq"].x - tx
        assert np.sqrt(np.mean(before**2)) > 0.04
        assert np.sqrt(np.mean(after**2)) < 0.01


def test_phase_correction_replaces_starlog_columns_and_adds_corrected_sep_ones(bench):
    rng = np.random.default_rng(10)
    frames, truth = [], []
    for _ in range(3):
        tx, ty = rng.uniform(20, 1000, 400), rng.uniform(20, 740, 400)

        def pulled(v):
            return v - 0.06 * np.sin(2 * np.pi * (v - np.rint(v)))

        ours = bench.Positions(pulled(tx), pulled(ty), np.ones(400), np.full(400, 100.0), np.full(400, 0.01),
                               np.ones(400, bool))
        sep = bench.Positions(pulled(tx), pulled(ty), np.ones(400))
        frames.append(bench.MeasuredFrame("f", SHAPE, 1.0, {"GAUSSFIT": ours, "SEP iso 1.5s": sep}))
        truth.append(tx)
    out, calibrations = bench.phase_corrected(frames, harmonics=1)
    assert set(out[0].positions) == {"GAUSSFIT", "SEP iso 1.5s", "SEP iso 1.5s+pc"}
    assert calibrations["GAUSSFIT"].amplitude_x[0] == pytest.approx(-0.06, abs=0.01)
    for f, tx in zip(out, truth):
        assert np.sqrt(np.mean((f.positions["SEP iso 1.5s"].x - tx) ** 2)) > 0.04
        for name in ("GAUSSFIT", "SEP iso 1.5s+pc"):
            assert np.sqrt(np.mean((f.positions[name].x - tx) ** 2)) < 0.01


@pytest.mark.parametrize("make", ["nothing", "empty folder"])
def test_missing_frames_end_in_one_line_naming_how_to_get_them(bench, tmp_path, capsys, make):
    folder = tmp_path / "real-sky"
    if make == "empty folder":
        folder.mkdir()
    assert bench.main(["--images", str(folder)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "esa/tetra3" in err and "--images DIR" in err


def test_degraded_copies_are_written_in_the_format_each_kind_names(bench, tmp_path):
    import tifffile

    images = tmp_path / "frames"
    images.mkdir()
    rng = np.random.default_rng(0)
    tifffile.imwrite(str(images / "a.tiff"), (rng.integers(0, 4096, (64, 80)) * 16).astype(np.uint16))
    for kind in bench.DEGRADED:
        out = tmp_path / kind
        out.mkdir()
        bench.write_degraded(images, kind, out)
        (written,) = bench.list_images(out)
        image, saturation = bench.load_grey(written)
        expected = (32, 40) if kind.startswith("binned") else (64, 80)
        assert image.shape == expected
        top = 255.0 if kind == "8-bit" or "jpeg" in kind else 65535.0
        assert saturation == (3 * top if kind.startswith(("colour", "bayer")) else top)


def test_the_demosaiced_copy_is_the_frame_through_a_bayer_mosaic(bench):
    """A flat frame through the mosaic: each channel at its response everywhere (OpenCV fills the others)."""
    image = np.full((16, 16), 1000, np.uint16)
    colour = bench.demosaiced(image)
    assert colour.shape == (16, 16, 3)
    np.testing.assert_allclose(colour[4:-4, 4:-4].reshape(-1, 3).mean(axis=0),
                               1000 * np.array(bench.CHANNEL_RESPONSE), atol=1)


def test_leave_one_camera_out_picks_the_default_on_the_other_cameras():
    with tool_module("loco") as loco:
        def score(camera, setting, a, b):
            return loco.CameraScore(camera, setting, {"A": a, "B": b}, "SEP", 100, "A", True, (0.9, 1.1), "")

        scores = [score("one", "now", 0.80, 0.90), score("two", "now", 0.70, 0.95), score("three", "now", 1.00, 0.60),
                  score("one", "before", 0.85, 0.99), score("two", "before", 0.99, 0.99),
                  score("three", "before", 0.99, 0.99)]
        rows = {r["camera"]: r for r in loco.held_out_rows(scores, "now")}
    # camera three's own best (B) is not what the other two pick (A): its held-out score is A's there
    assert rows["three"]["picked"] == "now/A" and rows["three"]["held_out"] == 1.00
    assert rows["three"]["best"] == "B" and rows["three"]["best_ratio"] == 0.60
    # on camera one, the others' mean log-ratio: A (0.70, 1.00) -0.18, B (0.95, 0.60) -0.28; the earlier setting's
    # are worse: B, scored on camera one
    assert rows["one"]["picked"] == "now/B" and rows["one"]["held_out"] == 0.90
    assert all(r["trusted"] == "A" and r["trusted_ok"] for r in rows.values())


def test_a_simulated_camera_is_the_catalogue_sky_rendered_as_eight_frames(bench, tmp_path):
    pytest.importorskip("tetra3")
    with tool_module("sim_cameras") as sim_cameras:
        sim_cameras.write_camera("sim-gauss-1.2-saturated", tmp_path, bench.write_degraded)
    frames = bench.list_images(tmp_path)
    assert len(frames) == len(sim_cameras.POINTINGS) == 8
    image, saturation = bench.load_grey(frames[0])
    assert image.shape == (768, 1024) and image.dtype == np.uint16
    assert image.max() < saturation and image.max() > 100 + 30000 - 1  # cores clipped at the full well (30000 e-)
