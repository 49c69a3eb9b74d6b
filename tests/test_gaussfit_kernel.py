"""The compiled GAUSSFIT against the vectorised numpy fit, a noise-free star, and its per-star independence."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose, assert_array_equal

from starlog.centroiding.stamps import gather_stamps, model
from starlog.centroiding.gaussfit import fit_gaussians, fit_gaussians_vectorised
from starlog.errors import InvalidInputError

FIELDS = ("dx", "dy", "flux", "flux_err", "background", "psf_sigma", "sigma", "ok")


def _frame(seed: int, n: int, *, psf: float = 1.3, h: int = 5, holes: int = 30, size: int = 80):
    """Stamps of ``n`` Gaussian stars on a noisy frame with ``holes`` NaN pixels, and the true offsets."""
    rng = np.random.default_rng(seed)
    image = rng.normal(100.0, 3.0, (size, size))
    x, y = rng.uniform(3, size - 3, n), rng.uniform(3, size - 3, n)  # some windows cut by the edge
    yy, xx = np.mgrid[:size, :size]
    for xi, yi, f in zip(x, y, rng.uniform(200, 20000, n)):
        image += f / (2 * np.pi * psf**2) * np.exp(-((xx - xi) ** 2 + (yy - yi) ** 2) / (2 * psf**2))
    image[rng.integers(0, size, holes), rng.integers(0, size, holes)] = np.nan
    stamps = gather_stamps(image, x, y, h, np.full(n, 100.0), np.full(n, 3.0), 2.0, np.inf)
    start_x = x - stamps.xc + rng.normal(0, 0.3, n)  # a coarse position, as detection gives
    start_y = y - stamps.yc + rng.normal(0, 0.3, n)
    return stamps, start_x, start_y, rng.uniform(200, 20000, n)


@settings(max_examples=30, deadline=None, derandomize=True)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 30), psf=st.sampled_from([0.5, 1.3, 2.5]),
       fit_sigma=st.booleans(), fit_background=st.booleans())
def test_compiled_fit_agrees_with_the_vectorised_fit(seed, n, psf, fit_sigma, fit_background):
    stamps, dx, dy, flux = _frame(seed, n, psf=psf, h=max(3, int(np.ceil(3.5 * psf)) + 1))
    compiled = fit_gaussians(stamps, dx, dy, flux, psf, fit_sigma=fit_sigma, fit_background=fit_background)
    reference = fit_gaussians_vectorised(stamps, dx, dy, flux, psf, fit_sigma=fit_sigma,
                                         fit_background=fit_background)
    both = compiled.ok & reference.ok
    # the two stop at different iterations (a star's own convergence against the slowest star's)
    assert np.count_nonzero(compiled.ok != reference.ok) <= max(1, n // 10)
    assert_allclose(compiled.dx[both], reference.dx[both], rtol=0, atol=1e-3)
    assert_allclose(compiled.dy[both], reference.dy[both], rtol=0, atol=1e-3)
    assert_allclose(compiled.psf_sigma[both], reference.psf_sigma[both], rtol=0, atol=1e-3)
    for name in ("flux", "flux_err", "sigma"):
        assert_allclose(getattr(compiled, name)[both], getattr(reference, name)[both], rtol=1e-2, err_msg=name)
    assert_allclose(compiled.background[both], reference.background[both], rtol=0, atol=0.05 * 3.0)


def test_the_fitted_width_stays_within_its_bounds():
    """A star narrower than a pixel drives the fitted width down to its floor, 0.2 px, in both fits."""
    stamps, dx, dy, flux = _frame(11, 8, psf=0.25, holes=0)
    compiled = fit_gaussians(stamps, dx, dy, flux, 1.0, fit_sigma=True)
    reference = fit_gaussians_vectorised(stamps, dx, dy, flux, 1.0, fit_sigma=True)
    assert np.all(compiled.psf_sigma >= 0.2) and np.any(compiled.psf_sigma == 0.2)
    assert_array_equal(compiled.psf_sigma == 0.2, reference.psf_sigma == 0.2)


def test_mismatched_lengths_are_refused():
    stamps, dx, dy, flux = _frame(5, 6)
    with pytest.raises(InvalidInputError, match="dx0"):
        fit_gaussians(stamps, dx[:4], dy, flux, 1.3)
    with pytest.raises(InvalidInputError, match="psf_sigma"):
        fit_gaussians(stamps, dx, dy, flux, np.full(3, 1.3))


def test_a_noise_free_star_is_recovered_exactly():
    stamps, _, _, _ = _frame(1, 6, holes=0, size=60)
    true_x, true_y = np.linspace(-0.45, 0.45, 6), np.linspace(0.3, -0.3, 6)
    flux = np.linspace(500.0, 50000.0, 6)
    exact = flux[:, None, None] * model(stamps, true_x, true_y, 1.3) + 4.0
    stamps.data[:] = exact
    stamps.valid[:] = True
    fit = fit_gaussians(stamps, true_x + 0.4, true_y - 0.4, flux * 0.7, 1.3)
    assert fit.ok.all()
    assert_allclose(fit.dx, true_x, atol=1e-7)
    assert_allclose(fit.dy, true_y, atol=1e-7)
    assert_allclose(fit.flux, flux, rtol=1e-7)
    assert_allclose(fit.background, 4.0, atol=1e-5)
    free = fit_gaussians(stamps, true_x + 0.4, true_y - 0.4, flux * 0.7, 1.0, fit_sigma=True)
    assert_allclose(free.psf_sigma, 1.3, rtol=1e-6)


def test_a_star_result_does_not_depend_on_the_other_stars_of_its_frame():
    stamps, dx, dy, flux = _frame(7, 12)
    together = fit_gaussians(stamps, dx, dy, flux, 1.3)
    for k in (0, 5, 11):
        one = _take(stamps, k)
        alone = fit_gaussians(one, dx[k : k + 1], dy[k : k + 1], flux[k : k + 1], 1.3)
        for name in FIELDS:
            assert_array_equal(getattr(alone, name), getattr(together, name)[k : k + 1], err_msg=name)


@pytest.mark.parametrize("fit_sigma", [False, True])
def test_a_window_without_valid_pixels_is_not_ok_and_does_not_stop_the_others(fit_sigma):
    stamps, dx, dy, flux = _frame(3, 5, holes=0)
    stamps.valid[2] = False
    stamps.data[2] = 0.0
    fit = fit_gaussians(stamps, dx, dy, flux, 1.3, fit_sigma=fit_sigma)
    assert not fit.ok[2]
    assert np.isinf(fit.sigma[2])
    assert fit.ok[[0, 1, 3, 4]].all()


def _take(stamps, k: int):
    from starlog.centroiding.robust import take_stamps

    return take_stamps(stamps, np.array([k]))
