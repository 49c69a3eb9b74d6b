"""Sub-pixel centroid methods: accuracy, pixel-phase bias, uncertainty calibration, edge cases."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose

from starlog.centroiding import (
    CENTROID_DTYPE,
    CentroidFlag,
    CentroidMethod,
    extract_stars,
    measure_centroids,
)
from starlog.detect import DetectionWarning, detect_stars
from starlog.errors import InvalidInputError, InvalidParameterError
from starlog.sim.camera import CameraModel
from starlog.sim.psf import render_stars

PEDESTAL = 120.0  # bias 100 DN + sky 20 e- at gain 1

# worst error over a 6x6 grid of pixel phases on noise-free stars (the S-curve bound), px
NOISE_FREE_TOL = {
    CentroidMethod.NONE: 1e-3,
    CentroidMethod.MOMENT: 1e-4,
    CentroidMethod.MOMENT_SQUARED: 1e-3,
    CentroidMethod.BICUBIC: 2e-3,
    CentroidMethod.GAUSSFIT: 1e-4,
    CentroidMethod.GRADIENT: 1e-3,
    CentroidMethod.PSFFIT: 1e-4,
    CentroidMethod.WINPOS: 1e-4,
}


def _phase_grid(sigma):
    ph = np.linspace(-0.5, 0.5, 6)
    px, py = np.meshgrid(ph, ph)
    cx, cy = np.meshgrid(30 + 40 * np.arange(6), 30 + 40 * np.arange(6))
    x, y = (cx + px).ravel(), (cy + py).ravel()
    img = PEDESTAL + render_stars((260, 260), x, y, np.full(x.size, 2e4), sigma)
    return img, x, y


def _errors(c, x, y):
    d = np.hypot(c["x"][:, None] - x[None, :], c["y"][:, None] - y[None, :])
    k = d.argmin(axis=1)
    return c["x"] - x[k], c["y"] - y[k]


@pytest.mark.parametrize("sigma", [0.7, 1.2, 2.0])
@pytest.mark.parametrize("method", list(CentroidMethod))
def test_noise_free_stars_across_pixel_phases(method, sigma):
    img, x, y = _phase_grid(sigma)
    det = detect_stars(img)
    assert det.size == x.size
    c = measure_centroids(img, det, method=method, psf_sigma=sigma)
    ex, ey = _errors(c, x, y)
    assert_allclose(np.concatenate([ex, ey]), 0.0, rtol=0, atol=NOISE_FREE_TOL[method])
    assert not np.any(c["flags"] & CentroidFlag.FIT_FAILED)


def test_debias_removes_the_bicubic_s_curve():
    img, x, y = _phase_grid(0.7)
    det = detect_stars(img)
    raw = measure_centroids(img, det, method="BICUBIC", psf_sigma=0.7, debias=False)
    ex, _ = _errors(raw, x, y)
    assert np.abs(ex).max() > 0.01  # the raw interpolated peak has a visible S-curve
    fixed = measure_centroids(img, det, method="BICUBIC", psf_sigma=0.7)
    ex, _ = _errors(fixed, x, y)
    assert np.abs(ex).max() < 2e-3


def test_gaussfit_recovers_flux_background_and_estimated_psf():
    img, x, y = _phase_grid(1.2)
    det = detect_stars(img)
    c = measure_centroids(img, det, method="GAUSSFIT")  # PSF sigma estimated from the frame
    assert_allclose(c["psf_sigma"], 1.2, rtol=0, atol=1e-3)
    assert_allclose(c["flux"], 2e4, rtol=1e-3, atol=0)
    assert_allclose(c["background"], PEDESTAL, rtol=0, atol=1e-3)


def _calibration_samples(sigma, flux_range, reps, seed):
    rng = np.random.default_rng(seed)
    g = 20 + 30 * np.arange(4)
    cx, cy = np.meshgrid(g, g)
    x = cx.ravel() + rng.uniform(-0.5, 0.5, cx.size)
    y = cy.ravel() + rng.uniform(-0.5, 0.5, cy.size)
    flux = rng.uniform(*flux_range, x.size)
    expected = 20.0 + render_stars((130, 130), x, y, flux, sigma)
    cam = CameraModel()
    z = {m: [] for m in CentroidMethod}
    for _ in range(reps):
        img = cam.expose(expected, rng)
        det, cents = extract_stars(img, methods=list(CentroidMethod), psf_sigma=sigma)
        for m, c in cents.items():
            ex, ey = _errors(c, x, y)
            ok = np.hypot(ex, ey) < 3
            z[m].append(np.concatenate([ex[ok] / c["sigma"][ok], ey[ok] / c["sigma"][ok]]))
    return {m: np.concatenate(v) for m, v in z.items()}


@pytest.mark.parametrize(
    ("sigma", "flux_range"),
    [(0.7, (2e4, 1e5)), (1.2, (2e3, 8e3)), (2.0, (500.0, 1000.0))],
    ids=["bright", "medium", "faint"],
)
def test_sigma_is_calibrated(sigma, flux_range):
    z = _calibration_samples(sigma, flux_range, reps=25, seed=11)
    for m in CentroidMethod:
        assert z[m].size > 600
        spread = float(np.sqrt(np.mean(z[m] ** 2)))
        assert 0.8 <= spread <= 1.25, (m, spread)


@pytest.mark.parametrize("method", list(CentroidMethod))
def test_saturated_star_is_measured_and_flagged(method):
    rng = np.random.default_rng(3)
    cam = CameraModel(adc_bits=12)
    img = cam.expose(20.0 + render_stars((64, 64), [31.3], [30.8], [3e5], 1.5), rng)
    det = detect_stars(img, saturation=4095)
    c = measure_centroids(img, det, method=method, saturation=4095, psf_sigma=1.5)
    assert c.size == 1 and c["flags"][0] & CentroidFlag.SATURATED
    tol = 0.05 if method is CentroidMethod.GAUSSFIT else 0.5
    assert_allclose([c["x"][0], c["y"][0]], [31.3, 30.8], rtol=0, atol=tol)
    assert np.all(np.isfinite([c["sigma"][0], c["flux"][0], c["snr"][0]]))


@pytest.mark.parametrize("method", list(CentroidMethod))
def test_star_at_the_border_and_masked_pixels(method):
    rng = np.random.default_rng(4)
    img = CameraModel().expose(20.0 + render_stars((48, 48), [1.4, 30.2], [24.3, 30.6], [6e3, 6e3], 1.2), rng)
    img = img.astype(np.float64)
    img[31, 29] = np.nan
    before = img.copy()
    det = detect_stars(img)
    det_before = det.copy()
    c = measure_centroids(img, det, method=method, psf_sigma=1.2)
    np.testing.assert_array_equal(img, before)
    np.testing.assert_array_equal(det, det_before)
    assert c.size == 2
    for name in CENTROID_DTYPE.names:
        assert np.all(np.isfinite(c[name]))
    edge = c[np.argmin(c["x"])]
    assert edge["flags"] & CentroidFlag.BORDER
    assert_allclose([edge["x"], edge["y"]], [1.4, 24.3], rtol=0, atol=0.3)
    other = c[np.argmax(c["x"])]
    assert other["flags"] & CentroidFlag.MASKED
    assert_allclose([other["x"], other["y"]], [30.2, 30.6], rtol=0, atol=0.2)
    assert np.all(c["sigma"] > 0)


def test_empty_constant_and_nan_frames():
    empty = detect_stars(np.full((32, 32), 7.0))
    out = measure_centroids(np.full((32, 32), 7.0), empty, method="GAUSSFIT")
    assert out.shape == (0,) and out.dtype == CENTROID_DTYPE
    det, cents = extract_stars(np.full((32, 32), 100, np.uint16), methods=["MOMENT", "NONE"])
    assert det.shape == (0,) and set(cents) == {CentroidMethod.MOMENT, CentroidMethod.NONE}
    assert all(c.shape == (0,) and c.dtype == CENTROID_DTYPE for c in cents.values())
    with pytest.warns(DetectionWarning, match="no finite pixel"):
        det, cents = extract_stars(np.full((32, 32), np.nan), methods=["GRADIENT"])
    assert det.shape == (0,) and cents[CentroidMethod.GRADIENT].shape == (0,)


def test_invalid_arguments_raise():
    img = PEDESTAL + render_stars((32, 32), [16.0], [16.0], [1e4], 1.2)
    det = detect_stars(img)
    with pytest.raises(InvalidParameterError, match="unknown centroid method"):
        measure_centroids(img, det, method="CENTER")
    with pytest.raises(InvalidParameterError, match="gain must"):
        measure_centroids(img, det, method="MOMENT", gain=0)
    with pytest.raises(InvalidInputError, match="detections must"):
        measure_centroids(img, np.zeros(3), method="MOMENT")
    with pytest.raises(InvalidInputError, match="2-D"):
        measure_centroids(img[0], det, method="MOMENT")


@settings(max_examples=30, deadline=None)
@given(
    method=st.sampled_from(list(CentroidMethod)),
    fx=st.floats(-0.5, 0.5),
    fy=st.floats(-0.5, 0.5),
    sx=st.integers(-8, 8),
    sy=st.integers(-8, 8),
    sigma=st.sampled_from([0.8, 1.5]),
)
def test_centroid_is_shift_equivariant(method, fx, fy, sx, sy, sigma):
    x0, y0 = 24.0 + fx, 26.0 + fy
    a = PEDESTAL + render_stars((52, 52), [x0], [y0], [5e3], sigma)
    b = PEDESTAL + render_stars((52, 52), [x0 + sx], [y0 + sy], [5e3], sigma)
    ca = measure_centroids(a, detect_stars(a), method=method, psf_sigma=sigma)
    cb = measure_centroids(b, detect_stars(b), method=method, psf_sigma=sigma)
    assert ca.size == cb.size == 1
    assert_allclose([cb["x"][0] - ca["x"][0], cb["y"][0] - ca["y"][0]], [sx, sy], rtol=0, atol=1e-6)
