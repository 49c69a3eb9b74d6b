"""WINPOS, the windowed position: against ``sep.winpos`` (an independent implementation), the simulator's truth
and its own uncertainty."""

from __future__ import annotations

import numpy as np
import pytest

from starlog.centroiding import CentroidMethod, measure_centroids
from starlog.centroiding.winpos import window_sigma, winpos
from starlog.detect import detect_stars
from starlog.sim.psf import render_stars


def _grid(psf_sigma: float, seed: int, flux: float = 5000.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Isolated pixel-integrated Gaussian stars at random sub-pixel phases on a zero background."""
    rng = np.random.default_rng(seed)
    centres = np.arange(20.0, 400.0, 30.0)
    cx, cy = np.meshgrid(centres, centres)
    x = cx.ravel() + rng.uniform(-0.5, 0.5, cx.size)
    y = cy.ravel() + rng.uniform(-0.5, 0.5, cy.size)
    return render_stars((420, 420), x, y, np.full(x.size, flux), psf_sigma), x, y


@pytest.mark.parametrize("psf_sigma", [0.55, 1.0, 1.8, 3.0])
def test_winpos_agrees_with_sep_winpos_on_the_same_window(psf_sigma: float) -> None:
    sep = pytest.importorskip("sep")
    image, x, y = _grid(psf_sigma, seed=1)
    rng = np.random.default_rng(2)
    x0, y0 = x + rng.normal(0, 0.3, x.size), y + rng.normal(0, 0.3, y.size)
    s = float(window_sigma(psf_sigma))
    sx, sy, _ = sep.winpos(np.ascontiguousarray(image), x0, y0, np.full(x.size, s))
    wx, wy, ok = winpos(image, x0, y0, s)
    assert ok.all()
    assert np.abs(wx - sx).max() < 1e-3 and np.abs(wy - sy).max() < 1e-3


@pytest.mark.parametrize("psf_sigma", [1.0, 1.8, 3.0])
def test_winpos_finds_well_sampled_stars_at_their_true_position(psf_sigma: float) -> None:
    image, x, y = _grid(psf_sigma, seed=3)
    wx, wy, ok = winpos(image, x + 0.2, y - 0.2, window_sigma(psf_sigma))
    assert ok.all()
    assert np.abs(wx - x).max() < 1e-3 and np.abs(wy - y).max() < 1e-3


def test_winpos_of_an_undersampled_star_has_an_s_curve_the_stage_removes() -> None:
    image, x, y = _grid(0.55, seed=4)
    wx, _, _ = winpos(image, x, y, window_sigma(0.55))
    assert np.abs(wx - x).max() > 0.02  # plain windowed positions are pulled towards pixel centres
    c = measure_centroids(image + 100.0, detect_stars(image + 100.0), method=CentroidMethod.WINPOS, psf_sigma=0.55)
    k = np.hypot(c["x"][:, None] - x, c["y"][:, None] - y).argmin(axis=1)
    assert np.abs(c["x"] - x[k]).max() < 1e-3 and np.abs(c["y"] - y[k]).max() < 1e-3


def test_winpos_sigma_matches_the_scatter_of_noisy_stars() -> None:
    """Reported sigma against the RMS error over noisy realisations (Poisson star + read noise)."""
    rng = np.random.default_rng(5)
    clean, x, y = _grid(1.2, seed=6, flux=3000.0)
    errors, sigmas = [], []
    for _ in range(6):
        image = rng.poisson(clean + 50.0).astype(np.float64) + rng.normal(0, 3.0, clean.shape)
        c = measure_centroids(image, detect_stars(image), method=CentroidMethod.WINPOS, psf_sigma=1.2, gain=1.0)
        k = np.hypot(c["x"][:, None] - x, c["y"][:, None] - y).argmin(axis=1)
        errors += [c["x"] - x[k], c["y"] - y[k]]
        sigmas.append(c["sigma"])
    rms = float(np.sqrt(np.mean(np.concatenate(errors) ** 2)))
    assert rms / float(np.median(np.concatenate(sigmas))) == pytest.approx(1.0, abs=0.15)
