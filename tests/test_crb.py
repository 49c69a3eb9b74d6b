"""Cramer-Rao bound of a pixel-integrated Gaussian centroid."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.testing import assert_allclose

from starlog.centroiding import centroid_crb
from starlog.errors import InvalidParameterError


@pytest.mark.parametrize("sigma", [3.0, 5.0, 8.0])
def test_photon_limited_bound_tends_to_sigma_over_sqrt_n(sigma):
    n = 1e6
    crb = centroid_crb(flux=n, psf_sigma=sigma, sky=0.0, read_noise=0.0)
    # the pixel adds 1/12 px^2 to the PSF variance: sigma_eff / sigma -> 1 as sigma grows
    assert_allclose(crb * np.sqrt(n) / sigma, 1.0, rtol=0, atol=0.01)
    assert crb * np.sqrt(n) >= sigma


def test_undersampled_psf_is_worse_than_the_continuous_limit():
    crb = centroid_crb(flux=1e6, psf_sigma=0.5, sky=0.0, read_noise=0.0, x_phase=0.0)
    assert crb > 0.5 / np.sqrt(1e6) * 1.05


@pytest.mark.parametrize("sigma", [3.0, 4.0])
def test_background_limited_bound_matches_closed_form(sigma):
    b, flux = 1e4, 2e3  # variance per pixel, signal: the star is negligible in the noise
    crb = centroid_crb(flux=flux, psf_sigma=sigma, sky=b - 9.0, read_noise=3.0)
    s2 = sigma**2 + 1.0 / 12.0
    assert_allclose(crb, np.sqrt(8 * np.pi * b) * s2 / flux, rtol=0.03, atol=0)


def test_scaling_with_flux():
    photon = centroid_crb(flux=np.array([1e6, 4e6]), psf_sigma=2.0, sky=0.0, read_noise=0.0)
    assert_allclose(photon[1] / photon[0], 0.5, rtol=0, atol=1e-3)
    bkg = centroid_crb(flux=np.array([10.0, 20.0]), psf_sigma=2.0, sky=1e5, read_noise=0.0)
    assert_allclose(bkg[1] / bkg[0], 0.5, rtol=0, atol=1e-3)


def test_monotonic_in_noise_and_nuisance():
    base = centroid_crb(flux=1e3, psf_sigma=1.2, sky=20.0, read_noise=3.0)
    assert centroid_crb(flux=1e3, psf_sigma=1.2, sky=40.0, read_noise=3.0) > base
    assert centroid_crb(flux=1e3, psf_sigma=1.2, sky=20.0, read_noise=6.0) > base
    assert centroid_crb(flux=1e3, psf_sigma=1.2, sky=20.0, read_noise=3.0, quantization=True) > base
    full = centroid_crb(flux=1e3, psf_sigma=1.2, sky=20.0, read_noise=3.0, nuisance=("flux", "sky", "psf_sigma"))
    assert full >= base * (1 - 1e-12)
    assert_allclose(full, base, rtol=0.05, atol=0)  # position is nearly orthogonal to the rest


def test_broadcasting_and_types():
    assert isinstance(centroid_crb(flux=1e3, psf_sigma=1.0, sky=10.0, read_noise=2.0), float)
    out = centroid_crb(flux=[1e3, 2e3, 4e3], psf_sigma=1.0, sky=10.0, read_noise=2.0, x_phase=[0.0, 0.25, 0.5])
    assert isinstance(out, np.ndarray) and out.shape == (3,)
    assert np.all(np.diff(out) < 0)


@pytest.mark.parametrize(
    "kwargs",
    [
        {"flux": 0.0, "psf_sigma": 1.0, "sky": 1.0, "read_noise": 1.0},
        {"flux": 1.0, "psf_sigma": -1.0, "sky": 1.0, "read_noise": 1.0},
        {"flux": 1.0, "psf_sigma": 1.0, "sky": -1.0, "read_noise": 1.0},
        {"flux": 1.0, "psf_sigma": 1.0, "sky": 1.0, "read_noise": -1.0},
        {"flux": 1.0, "psf_sigma": 1.0, "sky": 1.0, "read_noise": 1.0, "nuisance": ("gain",)},
    ],
)
def test_invalid_parameters_raise(kwargs):
    with pytest.raises(InvalidParameterError, match="must"):
        centroid_crb(**kwargs)
