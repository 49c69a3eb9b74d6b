"""Detection: background, thresholding, screening (hot pixels, cosmic rays, saturation, border)."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.testing import assert_allclose

from starlog.detect import (
    DETECTION_DTYPE,
    DetectionFlag,
    DetectionWarning,
    detect_stars,
    estimate_background,
)
from starlog.errors import InvalidInputError, InvalidParameterError
from starlog.sim.camera import CameraModel
from starlog.sim.psf import render_stars

SKY = 20.0


def _frame(rng, shape, x, y, flux, sigma, *, extra=None, camera=None):
    expected = SKY + render_stars(shape, x, y, flux, sigma)
    if extra is not None:
        expected = expected + extra
    return (camera or CameraModel()).expose(expected, rng)


def _grid(n_side, spacing, offset, rng):
    g = offset + spacing * np.arange(n_side)
    x, y = np.meshgrid(g, g)
    return x.ravel() + rng.uniform(-0.5, 0.5, x.size), y.ravel() + rng.uniform(-0.5, 0.5, x.size)


def _match(det, x, y, radius=1.5):
    d = np.hypot(det["x"][:, None] - x[None, :], det["y"][:, None] - y[None, :])
    return d.min(axis=0) <= radius if det.size else np.zeros(x.size, bool)


@pytest.mark.parametrize("sigma", [0.7, 1.2, 2.0])
def test_finds_every_star_near_truth(sigma):
    rng = np.random.default_rng(1)
    x, y = _grid(5, 40, 30, rng)
    img = _frame(rng, (220, 220), x, y, rng.uniform(3e3, 8e3, x.size), sigma)
    det = detect_stars(img)
    assert det.dtype == DETECTION_DTYPE
    assert _match(det, x, y, radius=0.5).all()
    assert det.size == x.size
    assert_allclose(det["star"], np.arange(det.size))
    assert np.all(np.diff(det["flux"]) <= 0)
    assert_allclose(np.median(det["background"]), 100 + SKY, rtol=0, atol=0.5)
    assert_allclose(np.median(det["noise"]), np.sqrt(SKY + 9.0 + 1 / 12), rtol=0.1, atol=0)


def test_empty_and_constant_frames_give_empty_result():
    rng = np.random.default_rng(2)
    noise = CameraModel().expose(np.full((128, 128), SKY), rng)
    assert detect_stars(noise).shape == (0,)
    const = np.full((64, 64), 500, np.uint16)
    out = detect_stars(const)
    assert out.shape == (0,) and out.dtype == DETECTION_DTYPE
    assert detect_stars(np.zeros((32, 32))).shape == (0,)


def test_all_nan_frame_warns_and_is_empty():
    with pytest.warns(DetectionWarning, match="no finite pixel"):
        out = detect_stars(np.full((40, 40), np.nan))
    assert out.shape == (0,) and out.dtype == DETECTION_DTYPE


def test_nan_pixels_are_masked_and_caller_array_untouched():
    rng = np.random.default_rng(3)
    img = _frame(rng, (96, 96), np.array([40.3]), np.array([50.6]), np.array([5e3]), 1.2).astype(np.float64)
    img[51, 42] = np.nan
    img[5:8, 80:90] = np.nan
    before = img.copy()
    det = detect_stars(img)
    np.testing.assert_array_equal(img, before)
    assert det.size == 1
    assert det["flags"][0] & DetectionFlag.MASKED
    assert_allclose([det["x"][0], det["y"][0]], [40.3, 50.6], rtol=0, atol=0.3)


def test_hot_pixels_and_cosmic_rays_are_rejected():
    rng = np.random.default_rng(4)
    x, y = _grid(3, 50, 40, rng)
    extra = np.zeros((160, 160))
    hy, hx = rng.integers(5, 155, 30), rng.integers(5, 155, 30)
    extra[hy, hx] += rng.uniform(300, 5000, 30)
    extra[20, 60:64] += 3000.0  # horizontal track
    extra[np.arange(130, 136), np.arange(10, 16)] += 2500.0  # diagonal track
    extra[100:102, 150] += 4000.0  # two-pixel vertical hit
    img = _frame(rng, (160, 160), x, y, rng.uniform(2e3, 6e3, x.size), 1.2, extra=extra)
    det = detect_stars(img)
    assert _match(det, x, y).all()
    assert det.size == x.size


def test_saturated_star_is_kept_and_flagged():
    rng = np.random.default_rng(5)
    cam = CameraModel(adc_bits=12)
    img = _frame(rng, (80, 80), np.array([40.2, 20.0]), np.array([39.7, 60.0]), np.array([4e5, 3e3]), 1.2, camera=cam)
    assert img.max() == 4095
    det = detect_stars(img, saturation=4095)  # a 12-bit frame in uint16: say where it saturates
    assert det.size == 2
    sat = det[(det["flags"] & DetectionFlag.SATURATED) > 0]
    assert sat.size == 1
    assert_allclose([sat["x"][0], sat["y"][0]], [40.2, 39.7], rtol=0, atol=0.5)


def test_star_at_the_border_is_flagged():
    rng = np.random.default_rng(6)
    img = _frame(rng, (64, 64), np.array([1.2, 32.0]), np.array([30.0, 32.0]), np.array([8e3, 8e3]), 1.2)
    det = detect_stars(img, border=3)
    assert det.size == 2
    edge = det[np.argmin(det["x"])]
    assert edge["flags"] & DetectionFlag.BORDER
    assert not det[np.argmax(det["x"])]["flags"] & DetectionFlag.BORDER


def test_close_pair_is_split_and_flagged_blended():
    rng = np.random.default_rng(7)
    img = _frame(rng, (64, 64), np.array([30.0, 35.5]), np.array([32.0, 32.5]), np.array([2e4, 1.2e4]), 1.2)
    det = detect_stars(img)
    assert det.size == 2
    assert np.all(det["flags"] & DetectionFlag.BLENDED)
    assert _match(det, np.array([30.0, 35.5]), np.array([32.0, 32.5]), radius=0.5).all()


def test_background_follows_gradient_and_vignetting():
    rng = np.random.default_rng(8)
    yy, xx = np.mgrid[0:256, 0:256]
    r2 = ((xx - 128) ** 2 + (yy - 128) ** 2) / 128**2
    sky = 200.0 * (1 - 0.4 * r2) + 0.3 * xx
    x, y = _grid(4, 60, 35, rng)
    img = CameraModel().expose(sky + render_stars((256, 256), x, y, np.full(x.size, 1e5), 1.5), rng)
    bg = estimate_background(img, mesh=32, subsample=2)
    noise = float(np.median(bg.noise))
    assert_allclose(noise, np.sqrt(np.median(sky) + 9.0 + 1 / 12), rtol=0.1, atol=0)
    # the level follows the strong vignetting to a fraction of the noise (worst at the corners,
    # where the curved profile is extrapolated over half a cell)
    assert_allclose(bg.level[32:-32, 32:-32], (sky + 100)[32:-32, 32:-32], rtol=0, atol=0.4 * noise)
    assert_allclose(bg.level, sky + 100, rtol=0, atol=1.0 * noise)
    assert_allclose(bg.level_at(np.array([100.0]), np.array([50.0])), bg.level[50, 100], rtol=0, atol=0.05)
    det = detect_stars(img, background=bg)
    assert _match(det, x, y).all() and det.size == x.size


def test_uint8_and_float_frames():
    rng = np.random.default_rng(9)
    img = _frame(rng, (64, 64), np.array([31.4]), np.array([30.2]), np.array([3e3]), 1.2, camera=CameraModel(adc_bits=8, bias=10, gain=4.0))
    assert img.max() < 256
    for frame in (img.astype(np.uint8), img.astype(np.float32)):
        det = detect_stars(frame)
        assert det.size == 1
        assert_allclose([det["x"][0], det["y"][0]], [31.4, 30.2], rtol=0, atol=0.3)


@pytest.mark.parametrize("gain", [20.0, 40.0, 80.0])
def test_quantised_frame_with_noise_below_one_step_finds_the_stars_not_the_noise(gain):
    """An 8-bit camera of high gain: noise of 0.52, 0.26 and 0.13 DN (sky 100 e-, read noise 3 e-), a
    level half-way between two values at gain 40, most pixels one or two values. The background's noise
    is the digitised values' spread, never below the quantisation error 1/sqrt(12) DN, so the detections
    are the 36 simulated stars (all found, none made of noise); the same as float with NaN holes."""
    rng = np.random.default_rng(3)
    x, y = _grid(6, 45, 30, rng)
    camera = CameraModel(read_noise=3.0, gain=gain, bias=10.0, adc_bits=8)
    img = camera.expose(100.0 + render_stars((300, 300), x, y, gain * rng.uniform(40, 200, x.size), 1.2), rng)
    blank = camera.expose(np.full((300, 300), 100.0), rng)
    noise = estimate_background(img).global_noise
    assert np.float32(1 / np.sqrt(12)) <= noise <= 1.15 * max(float(np.std(blank)), 1 / np.sqrt(12))
    holed = img.astype(np.float64)
    holed[7, 11] = holed[200, 5] = np.nan
    for frame in (img, holed):
        det = detect_stars(frame)
        assert _match(det, x, y).all() and det.size == x.size


@pytest.mark.parametrize(
    ("image", "kwargs", "error"),
    [
        (np.zeros(10), {}, InvalidInputError),
        (np.zeros((4, 4), dtype=bool), {}, InvalidInputError),
        (np.zeros((8, 8)), {"threshold": 0}, InvalidParameterError),
        (np.zeros((8, 8)), {"min_area": 5, "max_area": 2}, InvalidParameterError),
        (np.zeros((8, 8)), {"sharpness_ratio": 1.5}, InvalidParameterError),
    ],
)
def test_invalid_input_raises(image, kwargs, error):
    with pytest.raises(error, match="must"):
        detect_stars(image, **kwargs)


def test_without_the_opening_a_faint_undersampled_star_of_one_pixel_is_found() -> None:
    # PSF sigma 0.4 px, F / sigma_bg = 7: the matched-filtered peak is ~4 sigma and only the
    # central pixel or two pass the threshold, which the 3x3 cross opening erases
    rng = np.random.default_rng(5)
    x, y = np.array([20.0, 44.0]), np.array([20.0, 40.0])
    found = {True: 0, False: 0}
    for _ in range(40):
        img = _frame(rng, (64, 64), x, y, np.full(2, 7.0 * np.sqrt(SKY + 9.0)), 0.4)
        for opening in (True, False):
            det = detect_stars(img, filter_sigma=0.49, threshold=4.0, sharpness_ratio=0.0, min_area=1,
                               opening=opening)
            found[opening] += int(np.sum(_match(det, x, y)))
    assert found[False] > 2 * found[True]
    assert found[False] >= 0.25 * 80
