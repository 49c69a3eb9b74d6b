"""starlog.attitude against known answers: rotations, the q-method and its covariance, the camera, matching,
identification (the lost-in-space parts only where cedar-solve, import name tetra3, is installed)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from starlog.attitude.camera import Camera, camera_for_image, camera_from_pairs, fit_camera
from starlog.attitude.catalogue import Catalogue
from starlog.attitude.identify import AttitudeTracker, TrackerSettings, identify_and_refine
from starlog.attitude.matching import match_mutual
from starlog.attitude.qmethod import davenport_q_method, shuster_covariance
from starlog.attitude.rotation import (attitude_error, attitude_from_radec_roll, matrix_from_quaternion,
                                       quaternion_from_matrix, radec_roll, radec_vectors, small_rotation)
from starlog.errors import InvalidParameterError

SHAPE = (600, 800)
angles = st.tuples(st.floats(0, 359.9), st.floats(-85, 85), st.floats(0, 359.9))


def _unit(rng, n):
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1)[:, None]


def _camera(attitude, *, focal=2000.0, k=0.0, parity=1.0) -> Camera:
    return replace(camera_for_image(SHAPE, focal, parity=parity), rotation=attitude, k=k)


def _field(camera: Camera, rng, n=40, margin=20.0):
    """Sky vectors of n stars at random pixels inside the frame of ``camera``."""
    x = rng.uniform(margin, SHAPE[1] - 1 - margin, n)
    y = rng.uniform(margin, SHAPE[0] - 1 - margin, n)
    return camera.pixel_vectors(x, y) @ camera.rotation, x, y


@given(angles)
@settings(max_examples=50, deadline=None)
def test_radec_roll_and_quaternion_round_trips(a):
    attitude = attitude_from_radec_roll(*a)
    np.testing.assert_allclose(attitude @ attitude.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(attitude) == pytest.approx(1.0)
    ra, dec, roll = radec_roll(attitude)
    assert (ra, dec) == (pytest.approx(a[0], abs=1e-9), pytest.approx(a[1], abs=1e-9))
    assert (roll - a[2] + 180) % 360 - 180 == pytest.approx(0.0, abs=1e-9)
    np.testing.assert_allclose(matrix_from_quaternion(quaternion_from_matrix(attitude)), attitude, atol=1e-12)
    np.testing.assert_allclose(attitude[2], radec_vectors(a[0], a[1]), atol=1e-12)


def test_roll_zero_puts_north_up_and_east_left():
    camera = _camera(attitude_from_radec_roll(100.0, 30.0, 0.0))
    x, y, _ = camera.project(radec_vectors([100.0, 100.0, 100.5], [30.0, 30.5, 30.0]))
    cx, cy = (SHAPE[1] - 1) / 2, (SHAPE[0] - 1) / 2
    assert x[0] == pytest.approx(cx) and y[0] == pytest.approx(cy)
    assert y[1] < cy and x[1] == pytest.approx(cx, abs=1e-6)  # north: up
    assert x[2] < cx  # east (larger RA): left


@given(angles, st.integers(2, 40), st.integers(0, 2**32 - 1))
@settings(max_examples=60, deadline=None)
def test_q_method_on_exact_vectors_recovers_the_rotation(a, n, seed):
    rng = np.random.default_rng(seed)
    truth = attitude_from_radec_roll(*a)
    reference = _unit(rng, n)
    fit = davenport_q_method(reference @ truth.T, reference, rng.uniform(1e-5, 1e-3, n))
    np.testing.assert_allclose(fit.attitude, truth, atol=1e-8)
    np.testing.assert_allclose(matrix_from_quaternion(fit.quaternion), truth, atol=1e-8)
    assert fit.loss == pytest.approx(0.0, abs=1e-3)


def test_q_method_covariance_matches_monte_carlo_scatter():
    rng = np.random.default_rng(5)
    truth = attitude_from_radec_roll(40.0, -20.0, 70.0)
    camera = _camera(truth)
    reference, x, y = _field(camera, rng, n=25)
    sigma_px = rng.uniform(0.05, 0.3, x.size)
    errors = []
    for _ in range(3000):
        noisy = camera.pixel_vectors(x + rng.normal(0, sigma_px), y + rng.normal(0, sigma_px))
        fit = davenport_q_method(noisy, reference, sigma_px / camera.focal)
        errors.append(attitude_error(fit.attitude, truth))
    predicted = shuster_covariance(camera.pixel_vectors(x, y), sigma_px / camera.focal)
    scatter = np.cov(np.array(errors).T)
    np.testing.assert_allclose(np.sqrt(np.diag(scatter)), np.sqrt(np.diag(predicted)), rtol=0.06)
    assert np.sqrt(predicted[2, 2]) > 5 * np.sqrt(predicted[0, 0])  # roll is the weak axis of a narrow field


def test_covariance_of_too_few_directions_is_infinite():
    assert np.isinf(shuster_covariance(np.array([[0.0, 0.0, 1.0]]), np.array([1e-4]))).all()


@pytest.mark.parametrize("k, parity", [(0.0, 1.0), (-0.03, 1.0), (0.02, -1.0)])
def test_projection_round_trip(k, parity):
    rng = np.random.default_rng(2)
    camera = _camera(attitude_from_radec_roll(10.0, 60.0, 200.0), k=k, parity=parity)
    vectors, x, y = _field(camera, rng, n=100, margin=0.0)
    px, py, front = camera.project(vectors)
    assert front.all()
    np.testing.assert_allclose(px, x, atol=1e-7)
    np.testing.assert_allclose(py, y, atol=1e-7)


def test_camera_fit_recovers_focal_length_distortion_and_parity():
    rng = np.random.default_rng(3)
    for parity in (1.0, -1.0):
        truth = _camera(attitude_from_radec_roll(300.0, -10.0, 45.0), focal=2100.0, k=-0.02, parity=parity)
        vectors, x, y = _field(truth, rng, n=60)
        fitted = camera_from_pairs(SHAPE, 2050.0, vectors, x, y)
        assert fitted.parity == parity
        assert fitted.focal == pytest.approx(2100.0, rel=1e-7)
        assert fitted.k == pytest.approx(-0.02, abs=1e-7)
        np.testing.assert_allclose(fitted.rotation, truth.rotation, atol=1e-9)
        refit = fit_camera(replace(fitted, rotation=small_rotation([1e-4, 0, 0]) @ fitted.rotation), vectors, x, y)
        np.testing.assert_allclose(refit.rotation, truth.rotation, atol=1e-9)


@given(st.integers(1, 30), st.floats(0.5, 5.0), st.integers(0, 2**32 - 1))
@settings(max_examples=80, deadline=None)
def test_mutual_matching_is_one_to_one_within_the_radius_and_order_free(n, radius, seed):
    rng = np.random.default_rng(seed)
    cat_x, cat_y = rng.uniform(0, 100, n), rng.uniform(0, 100, n)
    keep = rng.random(n) < 0.8
    x = np.concatenate([cat_x[keep] + rng.normal(0, 0.3, keep.sum()), rng.uniform(0, 100, 3)])
    y = np.concatenate([cat_y[keep] + rng.normal(0, 0.3, keep.sum()), rng.uniform(0, 100, 3)])
    cat, det = match_mutual(cat_x, cat_y, x, y, radius)
    assert len(set(cat)) == cat.size and len(set(det)) == det.size
    assert (np.hypot(x[det] - cat_x[cat], y[det] - cat_y[cat]) <= radius).all()
    order = rng.permutation(x.size)
    cat2, det2 = match_mutual(cat_x, cat_y, x[order], y[order], radius)
    assert sorted(zip(cat2, order[det2])) == sorted(zip(cat, det))


def _catalogue(rng, attitude, n=60):
    camera = _camera(attitude)
    vectors, _, _ = _field(camera, rng, n=n, margin=-100.0)
    far = _unit(rng, 500)
    far = far[far @ attitude[2] < 0.9]  # the rest of the sky, out of the field
    all_vectors = np.vstack([vectors, far])
    return Catalogue(all_vectors, rng.uniform(2, 8, len(all_vectors)), np.arange(len(all_vectors)) + 1000)


def test_tracking_identifies_the_stars_and_refines_the_attitude():
    rng = np.random.default_rng(4)
    truth = attitude_from_radec_roll(150.0, 5.0, 80.0)
    catalogue = _catalogue(rng, truth)
    camera = _camera(truth)
    x, y, front = camera.project(catalogue.vectors)
    seen = np.flatnonzero(front & (x > 0) & (x < SHAPE[1] - 1) & (y > 0) & (y < SHAPE[0] - 1))
    sigma = np.full(seen.size, 0.05)
    xs, ys = x[seen] + rng.normal(0, 0.05, seen.size), y[seen] + rng.normal(0, 0.05, seen.size)
    start = replace(camera, rotation=small_rotation([3e-4, -2e-4, 1e-3]) @ truth)  # about 1 px off
    result = identify_and_refine(start, catalogue, np.arange(len(catalogue.ids)), xs, ys, sigma, radius=3.0,
                                 min_matches=6)
    assert result.solved and result.mode == "tracking"
    assert sorted(result.catalogue_rows) == sorted(seen)
    assert (result.catalogue_rows == seen[result.centroid_rows]).all()
    error = attitude_error(result.camera.rotation, truth)
    sd = np.sqrt(np.diag(result.fit.covariance))
    assert (np.abs(error) < 5 * sd).all()
    far = replace(camera, rotation=small_rotation([0.0, 0.02, 0.0]) @ truth)
    lost = identify_and_refine(far, catalogue, np.arange(len(catalogue.ids)), xs, ys, sigma, radius=3.0,
                               min_matches=6)
    assert not lost.solved and "fewer than 6" in lost.reason


def test_too_few_stars_are_not_tried():
    tracker = AttitudeTracker(Catalogue(np.eye(3), np.zeros(3), np.arange(3)), SHAPE, TrackerSettings(min_stars=4),
                              solver=object())
    result = tracker.solve(*(np.zeros(3) for _ in range(4)))
    assert not result.solved and result.reason.startswith("too few stars (3 usable centroids")


def test_a_missing_solver_names_the_extra(monkeypatch):
    import starlog.attitude.catalogue as catalogue

    monkeypatch.setattr(catalogue, "find_spec", lambda name: None)
    with pytest.raises(InvalidParameterError, match=r"starlog\[solve\]"):
        catalogue.solver_data_file()


# ---------------------------------------------------------------- with cedar-solve
@pytest.fixture(scope="module")
def real_catalogue():
    pytest.importorskip("tetra3")
    from starlog.attitude.catalogue import load_catalogue

    return load_catalogue()


def _sky_frame(catalogue, attitude, rng, *, shape=(768, 1024), fov=11.0, noise=0.05):
    from starlog.attitude.camera import focal_from_fov

    camera = replace(camera_for_image(shape, focal_from_fov(fov, shape[1])), rotation=attitude)
    rows = catalogue.cone(attitude[2], fov)
    rows = rows[catalogue.magnitude[rows] < 7.0]
    x, y, front = camera.project(catalogue.vectors[rows])
    inside = front & (x > 5) & (x < shape[1] - 6) & (y > 5) & (y < shape[0] - 6)
    rows, x, y = rows[inside], x[inside], y[inside]
    flux = 10 ** (-0.4 * catalogue.magnitude[rows])
    return rows, x + rng.normal(0, noise, x.size), y + rng.normal(0, noise, x.size), flux, np.full(x.size, noise)


@pytest.mark.parametrize("mirrored", [False, True])
def test_lost_in_space_then_tracking_on_catalogue_fields(real_catalogue, mirrored):
    rng = np.random.default_rng(11)
    shape = (768, 1024)
    tracker = AttitudeTracker(real_catalogue, shape)
    for n, step in enumerate([0.0, 1e-4, 2e-4]):
        truth = small_rotation([step, -step, 2 * step]) @ attitude_from_radec_roll(250.0, 35.0, 15.0)
        rows, x, y, flux, sigma = _sky_frame(real_catalogue, truth, rng, shape=shape)
        if mirrored:
            x = shape[1] - 1.0 - x
        result = tracker.solve(x, y, flux, sigma)
        assert result.solved, result.reason
        assert result.mode == ("lost_in_space" if n == 0 else "tracking")
        assert ("mirrored" in result.reason) == (mirrored and n == 0)
        assert (result.camera.parity < 0) == mirrored
        assert (result.catalogue_rows == rows[result.centroid_rows]).all()
        error = attitude_error(result.camera.rotation, truth)
        assert (np.abs(error) < 5 * np.sqrt(np.diag(result.fit.covariance))).all()


def test_random_points_do_not_solve_and_say_why(real_catalogue):
    rng = np.random.default_rng(1)
    tracker = AttitudeTracker(real_catalogue, SHAPE, TrackerSettings(timeout_ms=300, try_mirrored=False))
    x, y = rng.uniform(0, SHAPE[1] - 1, 12), rng.uniform(0, SHAPE[0] - 1, 12)
    result = tracker.solve(x, y, rng.uniform(1, 2, 12), np.full(12, 0.1))
    assert not result.solved and result.reason.startswith("lost-in-space")
