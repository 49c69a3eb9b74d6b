"""The compiled MOMENT centroid against the vectorised numpy one, a symmetric star, and its per-star independence."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose, assert_array_equal

from starlog.centroiding.stamps import gather_stamps, model
from starlog.centroiding.moment import weighted_centroid, weighted_centroid_vectorised
from starlog.centroiding.robust import take_stamps
from starlog.errors import InvalidInputError


def _frame(seed: int, n: int, *, psf: float = 1.3, h: int = 5, holes: int = 30, size: int = 80):
    """Stamps of ``n`` Gaussian stars on a noisy frame with ``holes`` NaN pixels, a coarse start and the fluxes."""
    rng = np.random.default_rng(seed)
    image = rng.normal(100.0, 3.0, (size, size))
    x, y = rng.uniform(3, size - 3, n), rng.uniform(3, size - 3, n)
    flux = rng.uniform(200, 20000, n)
    yy, xx = np.mgrid[:size, :size]
    for xi, yi, f in zip(x, y, flux):
        image += f / (2 * np.pi * psf**2) * np.exp(-((xx - xi) ** 2 + (yy - yi) ** 2) / (2 * psf**2))
    image[rng.integers(0, size, holes), rng.integers(0, size, holes)] = np.nan
    stamps = gather_stamps(image, x, y, h, np.full(n, 100.0), np.full(n, 3.0), 2.0, np.inf)
    return stamps, x - stamps.xc + rng.normal(0, 0.3, n), y - stamps.yc + rng.normal(0, 0.3, n), flux


@settings(max_examples=25, deadline=None, derandomize=True)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 30), weighting=st.sampled_from(["optimal", "gaussian", "none"]))
def test_compiled_moment_agrees_with_the_vectorised_one(seed, n, weighting):
    stamps, dx, dy, flux = _frame(seed, n)
    options = {"dx0": dx, "dy0": dy, "flux": flux, "psf_sigma": np.full(n, 1.3), "weighting": weighting}
    cx, cy, ok = weighted_centroid(stamps.data, stamps, **options)
    rx, ry, rok = weighted_centroid_vectorised(stamps.data, stamps, **options)
    # each star stops at its own convergence (1e-5 px), the vectorised one when the slowest has
    assert np.count_nonzero(ok != rok) <= max(1, n // 10)
    both = ok & rok
    assert_allclose(cx[both], rx[both], rtol=0, atol=1e-4)
    assert_allclose(cy[both], ry[both], rtol=0, atol=1e-4)


def test_a_noise_free_star_is_found_at_its_centre():
    stamps, _, _, _ = _frame(2, 5, holes=0, size=60)
    true_x, true_y = np.linspace(-0.4, 0.4, 5), np.linspace(0.35, -0.35, 5)
    flux = np.full(5, 5000.0)
    stamps.data[:] = flux[:, None, None] * model(stamps, true_x, true_y, 1.3)
    stamps.valid[:] = True
    cx, cy, ok = weighted_centroid(stamps.data, stamps, dx0=true_x + 0.3, dy0=true_y - 0.3, flux=flux,
                                   psf_sigma=np.full(5, 1.3))
    assert ok.all()
    # the optimal weight is symmetric about the star's centre on a window that holds the whole star
    assert_allclose(cx, true_x, atol=2e-3)
    assert_allclose(cy, true_y, atol=2e-3)


def test_a_star_result_does_not_depend_on_the_other_stars_of_its_frame():
    stamps, dx, dy, flux = _frame(9, 12)
    psf = np.full(12, 1.3)
    together = weighted_centroid(stamps.data, stamps, dx0=dx, dy0=dy, flux=flux, psf_sigma=psf)
    for k in (0, 4, 11):
        one = take_stamps(stamps, np.array([k]))
        alone = weighted_centroid(one.data, one, dx0=dx[k : k + 1], dy0=dy[k : k + 1], flux=flux[k : k + 1],
                                  psf_sigma=psf[k : k + 1])
        for a, b in zip(alone, together):
            assert_array_equal(a, b[k : k + 1])


@pytest.mark.parametrize("weighting", ["optimal", "none"])
def test_an_empty_window_is_not_ok(weighting):
    stamps, dx, dy, flux = _frame(4, 4, holes=0)
    stamps.valid[1] = False
    stamps.data[1] = 0.0
    _, _, ok = weighted_centroid(stamps.data, stamps, dx0=dx, dy0=dy, flux=flux, psf_sigma=np.full(4, 1.3),
                                 weighting=weighting)
    assert not ok[1]


def test_mismatched_lengths_are_refused():
    stamps, dx, dy, flux = _frame(6, 5)
    with pytest.raises(InvalidInputError, match="dx0"):
        weighted_centroid(stamps.data, stamps, dx0=dx[:3], dy0=dy, flux=flux, psf_sigma=np.full(5, 1.3))
    with pytest.raises(InvalidInputError, match="shape"):
        weighted_centroid(stamps.data[:2], stamps, dx0=dx, dy0=dy, flux=flux, psf_sigma=np.full(5, 1.3))
