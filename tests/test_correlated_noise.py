"""The detector measures the filtered frame's noise where pixels' noise is correlated (JPEG, blur) and keeps
the white-noise prediction on frames of independent pixel noise."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from starlog.detect import detect_stars, estimate_background
from starlog.detect.correlated_noise import WHITE_NOISE_LIMIT, filtered_noise_factor
from starlog.detect.detection import matched_filter, matched_filter_kernel
from starlog.sim.camera import CameraModel
from starlog.sim.psf import render_stars

FILTER_SIGMA = 1.5


def _factor(image: np.ndarray) -> float:
    work = image.astype(np.float32)
    filtered, k1 = matched_filter(work, FILTER_SIGMA)
    return filtered_noise_factor(filtered, estimate_background(work), k1)


@settings(max_examples=15, deadline=None)
@given(rows=st.integers(48, 400), cols=st.integers(48, 400), sigma=st.floats(0.5, 50.0), seed=st.integers(0, 2**32 - 1))
def test_white_noise_keeps_the_white_prediction(rows: int, cols: int, sigma: float, seed: int) -> None:
    image = 1000.0 + np.random.default_rng(seed).normal(0.0, sigma, (rows, cols))
    assert _factor(image) == 1.0


def test_blurred_noise_matches_the_filtered_noise_computed_from_the_kernels() -> None:
    """Noise blurred by a Gaussian of 1 px: per-pixel sigma s * |k_b|, filtered sigma s * |k_b * k_f| (2-D
    kernels' L2 norms), so the factor is |k_b * k_f| / (|k_b| |k_f|)."""
    rng = np.random.default_rng(3)
    blur = 1.0
    image = cv2.GaussianBlur(rng.normal(0.0, 10.0, (1024, 1024)), (0, 0), blur) + 500.0
    kb = cv2.getGaussianKernel(2 * int(np.ceil(4 * blur)) + 1, blur, cv2.CV_64F).ravel()
    kf = matched_filter_kernel(FILTER_SIGMA)
    both = np.convolve(kb, kf)
    expected = np.sum(both**2) / (np.sum(kb**2) * np.sum(kf**2))  # separable: the 2-D norms are the 1-D ones squared
    assert expected > WHITE_NOISE_LIMIT
    assert _factor(image) == pytest.approx(expected, rel=0.08)


def _star_field(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    x, y = rng.uniform(20, 492, 30), rng.uniform(20, 492, 30)
    expected = 40.0 + render_stars((512, 512), x, y, rng.uniform(3000, 30000, 30), 1.2)
    image = CameraModel(read_noise=3.0, gain=4.0, bias=10.0, adc_bits=8).expose(expected, rng)
    return image, x, y


def _false_detections(det: np.ndarray, x: np.ndarray, y: np.ndarray) -> int:
    near = np.hypot(det["x"][:, None] - x, det["y"][:, None] - y).min(axis=1) <= 2.0
    return int(np.count_nonzero(~near))


def test_a_jpeg_frame_gives_its_stars_not_its_compression_noise() -> None:
    rng = np.random.default_rng(5)
    image, x, y = _star_field(rng)
    ok, encoded = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 70])
    jpeg = cv2.imdecode(encoded, cv2.IMREAD_UNCHANGED)
    assert ok and _factor(jpeg) > 2.0
    det = detect_stars(jpeg)
    assert _false_detections(det, x, y) <= 2
    found = np.hypot(det["x"][:, None] - x, det["y"][:, None] - y).min(axis=0) <= 2.0
    assert found.mean() >= 0.9


def test_a_frame_of_independent_noise_is_detected_as_before() -> None:
    """The factor is 1 on the sensor's own frame: detection uses the white-noise threshold unchanged."""
    image, x, y = _star_field(np.random.default_rng(6))
    assert _factor(image) == 1.0
    assert _false_detections(detect_stars(image), x, y) == 0
