"""The simulator: truth consistent with the pixels, noise statistics, determinism, validation."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.testing import assert_allclose

from starlog.errors import InvalidParameterError
from starlog.sim import CameraModel, Jitter, SimulationConfig, Simulator, integrated_gaussian_1d, render_stars


def _centre_of_gravity(image: np.ndarray) -> tuple[float, float]:
    rows, cols = np.indices(image.shape)
    total = image.sum()
    return float((image * cols).sum() / total), float((image * rows).sum() / total)


@pytest.mark.parametrize("sigma", [0.7, 1.2, 2.0])
@pytest.mark.parametrize("phase", [(0.0, 0.0), (0.25, -0.4), (0.5, 0.5), (-0.37, 0.13)])
def test_noise_free_rendering_centroid_equals_truth(sigma: float, phase: tuple[float, float]) -> None:
    x, y = 20.0 + phase[0], 17.0 + phase[1]
    image = render_stars((36, 40), [x], [y], [1e4], sigma)
    cx, cy = _centre_of_gravity(image)
    assert_allclose([cx, cy], [x, y], rtol=0, atol=0.005)


def test_integrated_gaussian_sums_to_one_and_is_symmetric() -> None:
    p = integrated_gaussian_1d(np.arange(-20, 21), 0.0, 1.3)
    assert_allclose(p.sum(), 1.0, rtol=0, atol=1e-12)
    assert_allclose(p, p[::-1], rtol=0, atol=1e-15)


@pytest.mark.parametrize("sigma", [0.7, 2.0])
def test_simulator_truth_matches_expected_image(sigma: float) -> None:
    config = SimulationConfig(width=80, height=60, n_stars=1, n_frames=5, psf_sigma=sigma, margin=15,
                              jitter=(Jitter(frequency_hz=30.0, amplitude_px=0.3),), drift_px_per_s=(1.0, -2.0),
                              seed=11)
    sim = Simulator(config)
    for n in range(config.n_frames):
        expected, _, _ = sim.expected_electrons(n)
        frame = sim.render(n)
        cx, cy = _centre_of_gravity(expected - config.sky)
        assert_allclose([cx, cy], [frame.x[0], frame.y[0]], rtol=0, atol=0.005)


@pytest.mark.parametrize(("sky", "read_noise", "gain"), [(20.0, 3.0, 1.0), (200.0, 8.0, 2.5), (0.0, 5.0, 1.0)])
def test_pixel_statistics_match_noise_model(sky: float, read_noise: float, gain: float) -> None:
    camera = CameraModel(read_noise=read_noise, gain=gain, bias=500.0)
    config = SimulationConfig(width=256, height=256, n_stars=0, n_frames=1, sky=sky, camera=camera, seed=5)
    image = Simulator(config).render(0).image.astype(np.float64)
    n = image.size
    mean_expected = 500.0 + sky / gain
    var_expected = (sky + read_noise**2) / gain**2 + 1.0 / 12.0  # + uniform quantisation
    assert abs(image.mean() - mean_expected) < 5 * np.sqrt(var_expected / n)
    # the sample variance has standard error ~ var * sqrt(2 / n) for near-Gaussian pixels
    assert abs(image.var() - var_expected) < 5 * var_expected * np.sqrt(2.0 / n)


def test_saturation_clips_at_adc_range() -> None:
    config = SimulationConfig(width=40, height=40, n_stars=1, flux_min=5e6, flux_max=5e6, n_frames=1,
                              camera=CameraModel(adc_bits=12), margin=12, seed=1)
    image = Simulator(config).render(0).image
    assert image.max() == 4095


def test_hot_pixels_are_fixed_and_cosmic_rays_vary() -> None:
    config = SimulationConfig(width=64, height=64, n_stars=0, n_frames=3, hot_pixels=5, hot_pixel_charge=5000,
                              cosmic_rays_per_frame=3.0, seed=2)
    sim = Simulator(config)
    frames = [sim.render(n).image.astype(int) for n in range(3)]
    hot = [set(zip(*np.nonzero(f > 2000))) for f in frames]
    common = hot[0] & hot[1] & hot[2]
    assert len(common) >= 4  # hot pixels (two may coincide)
    assert any(h - common for h in hot)  # cosmic-ray hits appear in some frame


def test_frames_are_independent_of_render_order() -> None:
    sim = Simulator(SimulationConfig(n_frames=4, seed=9, random_walk_px_per_sqrt_s=0.5))
    forward = [sim.render(n).image for n in range(4)]
    backward = [Simulator(SimulationConfig(n_frames=4, seed=9, random_walk_px_per_sqrt_s=0.5)).render(n).image
                for n in reversed(range(4))]
    for a, b in zip(forward, reversed(backward)):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize(
    ("overrides", "match"),
    [
        ({"width": 4}, "frame size"),
        ({"flux_min": 10.0, "flux_max": 1.0}, "flux_min"),
        ({"fps": 0.0}, "fps"),
        ({"psf_sigma": 0.0}, "psf_sigma"),
        ({"margin": 200.0}, "margin"),
    ],
)
def test_config_validation(overrides: dict[str, float], match: str) -> None:
    with pytest.raises(InvalidParameterError, match=match):
        SimulationConfig(**overrides)  # type: ignore[arg-type]


def test_camera_validation() -> None:
    with pytest.raises(InvalidParameterError, match="gain"):
        CameraModel(gain=0.0)
    with pytest.raises(InvalidParameterError, match="adc_bits"):
        CameraModel(adc_bits=20)


def test_config_round_trips_through_dict() -> None:
    config = SimulationConfig(jitter=(Jitter(frequency_hz=5.0, amplitude_px=0.2),), drift_px_per_s=(0.1, 0.2))
    assert SimulationConfig.from_dict(config.to_dict()) == config


def test_render_stars_validates_input() -> None:
    from starlog.errors import InvalidInputError

    with pytest.raises(InvalidInputError, match="one value per star"):
        render_stars((10, 10), [1.0, 2.0], [1.0], [1.0], 1.0)
    with pytest.raises(InvalidInputError, match="sigma"):
        render_stars((10, 10), [1.0], [1.0], [1.0], -1.0)
