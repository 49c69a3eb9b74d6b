"""The fast forms of detection and centroid steps against their plain, direct definitions."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose, assert_array_equal

import starlog.detect.components as components
from starlog.centroiding.gaussfit import fit_gaussians
from starlog.detect import estimate_background
from starlog.detect.background import Background
from starlog.detect.components import find_components_vectorised
from starlog.detect.detection import matched_filter

from starlog.centroiding.stamps import fisher_sigma, gather_stamps, model, profile_1d
# private _Problem, _Profiles: GAUSSFIT's normal equations, checked against the dense Jacobian they stand for
from starlog.centroiding.gaussfit import _Problem, _Profiles
# private _centre_of_weights: MOMENT's centre, checked against the weighted mean it computes
from starlog.centroiding.moment import _centre_of_weights
# private _edge_padded, _fit_planes(_vectorised): the background's padding and its compiled and numpy cell fits
from starlog.detect.background import _edge_padded, _fit_planes, _fit_planes_vectorised
# private _edge_noise_factor: detection's cached edge-noise table, checked against its definition
from starlog.detect.detection import _edge_noise_factor


def _random_mask(seed: int, shape: tuple[int, int], fill: float) -> np.ndarray:
    rng = np.random.default_rng(seed)
    mask = (rng.random(shape) < fill).astype(np.uint8)
    mask[rng.random(shape) < 0.02] = 255  # any non-zero value is foreground
    return mask


def _components_tuple(comp: components.Components) -> tuple[np.ndarray, ...]:
    return (comp.y, comp.x, comp.label, comp.start, comp.area, comp.x_min, comp.x_max, comp.y_min, comp.y_max)


# private _CROPS_UP_TO: which labelling a mask gets is a module constant; -1 sends every box through the graph
@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), fill=st.floats(0.05, 0.6), rows=st.integers(1, 40), cols=st.integers(1, 40))
def test_overlapping_boxes_as_crops_match_the_pixel_graph(seed, fill, rows, cols):
    mask = _random_mask(seed, (rows, cols), fill)
    by_crops = find_components_vectorised(mask)
    saved = components._CROPS_UP_TO
    components._CROPS_UP_TO = -1  # every overlapping box through the one sparse graph
    try:
        by_graph = find_components_vectorised(mask)
    finally:
        components._CROPS_UP_TO = saved
    for a, b in zip(_components_tuple(by_crops), _components_tuple(by_graph)):
        assert_array_equal(a, b)


def _bilinear_reference(grid: np.ndarray, mesh: int, x: float, y: float, extrapolate: bool) -> float:
    """Bilinear value between cell centres, written out point by point."""
    def axis(c: float, n: int) -> tuple[int, float]:
        if n == 1:
            return 0, 0.0
        f = (c + 0.5) / mesh - 0.5
        if not extrapolate:
            f = min(max(f, 0.0), n - 1.0)
        i0 = int(min(max(np.floor(f), 0), n - 2))
        return i0, f - i0

    (iy, ty), (ix, tx) = axis(y, grid.shape[0]), axis(x, grid.shape[1])
    g = grid.astype(np.float64)
    at = lambda i, j: g[min(i, grid.shape[0] - 1), min(j, grid.shape[1] - 1)]  # noqa: E731
    return ((1 - ty) * (1 - tx) * at(iy, ix) + (1 - ty) * tx * at(iy, ix + 1)
            + ty * (1 - tx) * at(iy + 1, ix) + ty * tx * at(iy + 1, ix + 1))


@pytest.mark.parametrize("shape", [(256, 192), (64, 300), (40, 40)])
def test_background_values_at_points_are_the_bilinear_maps(shape):
    rng = np.random.default_rng(7)
    yy, xx = np.mgrid[: shape[0], : shape[1]]
    image = (200 + 0.3 * xx - 0.2 * yy + 50 * np.sin(xx / 40.0) + rng.normal(0, 5, shape)).astype(np.float32)
    bg = estimate_background(image, mesh=32)
    x = np.concatenate([rng.uniform(-3, shape[1] + 3, 200), [0.0, shape[1] - 1.0]])
    y = np.concatenate([rng.uniform(-3, shape[0] + 3, 200), [shape[0] - 1.0, 0.0]])
    for grid, got, extrapolate in ((bg.mesh_level, bg.level_at(x, y), True), (bg.mesh_noise, bg.noise_at(x, y), False)):
        want = [_bilinear_reference(grid, bg.mesh, a, b, extrapolate) for a, b in zip(x, y)]
        assert_allclose(got, want, rtol=1e-6)  # the weights are float32, as the maps'
    # on the pixel grid they are the full-resolution maps
    iy, ix = rng.integers(0, shape[0], 50), rng.integers(0, shape[1], 50)
    assert_allclose(bg.level_at(ix, iy), bg.level[iy, ix], rtol=1e-5)
    assert_allclose(bg.noise_at(ix, iy), bg.noise[iy, ix], rtol=1e-5)
    assert bg.level_at(np.float64(10.0), np.float64(12.0)).shape == ()


def _edge_noise_direct(k1: np.ndarray, dist: int) -> float:
    """Filtered-noise factor at ``dist`` px from a reflected edge, by filtering white noise's covariance."""
    r = k1.size // 2
    w = np.zeros(dist + r + 1)
    for j in range(-r, r + 1):
        i = dist + j
        w[i if i >= 0 else -i - 1] += k1[j + r]
    return float(np.sqrt(np.sum(w**2) / np.sum(k1**2))) if dist <= r else 1.0


@pytest.mark.parametrize("sigma", [0.8, 1.5, 2.6])
def test_edge_noise_factor_from_the_cached_table(sigma):
    _, k1 = matched_filter(np.zeros((16, 16), np.float32), sigma)
    dist = np.arange(0, 12)
    got = _edge_noise_factor(k1, dist)
    assert_allclose(got, [_edge_noise_direct(k1, int(d)) for d in dist], rtol=1e-12)
    assert got[0] > got[1] > 1.0 and got[-1] == 1.0


def _stamps(seed: int, n: int = 12, h: int = 5):
    rng = np.random.default_rng(seed)
    image = rng.normal(100.0, 3.0, (80, 80))
    x, y = rng.uniform(8, 72, n), rng.uniform(8, 72, n)
    yy, xx = np.mgrid[:80, :80]
    for xi, yi, f in zip(x, y, rng.uniform(200, 5000, n)):
        image += f / (2 * np.pi * 1.3**2) * np.exp(-((xx - xi) ** 2 + (yy - yi) ** 2) / (2 * 1.3**2))
    image[rng.integers(0, 80, 30), rng.integers(0, 80, 30)] = np.nan  # invalid pixels in some windows
    st_ = gather_stamps(image, x, y, h, np.full(n, 100.0), np.full(n, 3.0), 2.0, np.inf)
    return st_, x - st_.xc, y - st_.yc, rng


def test_model_is_the_product_of_the_axis_profiles():
    st_, dx, dy, _ = _stamps(1)
    for s in (1.3, np.linspace(0.8, 2.0, dx.size)):
        ex, _, _ = profile_1d(st_.u, dx, s)
        ey, _, _ = profile_1d(st_.u, dy, s)
        assert_array_equal(model(st_, dx, dy, s), ey[:, :, None] * ex[:, None, :])


@pytest.mark.parametrize("seed", [2, 3])
def test_fisher_sigma_matches_the_dense_information_matrix(seed):
    st_, dx, dy, rng = _stamps(seed)
    flux, s = rng.uniform(100, 3000, dx.size), 1.3
    ex, dex, _ = profile_1d(st_.u, dx, s, deriv=True)
    ey, dey, _ = profile_1d(st_.u, dy, s, deriv=True)
    f = flux[:, None, None]
    w = st_.valid / (st_.noise[:, None, None] ** 2 + f * ey[:, :, None] * ex[:, None, :] / st_.gain)
    jx, jy = f * ey[:, :, None] * dex[:, None, :], f * dey[:, :, None] * ex[:, None, :]
    ixx, iyy, ixy = ((w * a * b).sum(axis=(1, 2)) for a, b in ((jx, jx), (jy, jy), (jx, jy)))
    want = np.sqrt(0.5 * (ixx + iyy) / (ixx * iyy - ixy**2))
    assert_allclose(fisher_sigma(st_, dx, dy, flux, s), want, rtol=1e-10)


@pytest.mark.parametrize("fit_background", [True, False])
def test_separable_normal_equations_match_the_jacobian_planes(fit_background):
    st_, dx, dy, rng = _stamps(4)
    n = dx.size
    f, s = rng.uniform(100, 3000, n), np.full(n, 1.3)
    prob = _Problem(st_, fit_background, False)
    prof = _Profiles.at(prob.edges, dx, dy, s)
    w = prob.weights(f[:, None, None] * prob.model(prof))
    r = rng.normal(0, 3, st_.data.shape)
    a_mat, g = prob.normal(prof, f, s, w, w * r)
    ex, dex, _ = profile_1d(st_.u, dx, s, deriv=True)
    ey, dey, _ = profile_1d(st_.u, dy, s, deriv=True)
    planes = [f[:, None, None] * ey[:, :, None] * dex[:, None, :], f[:, None, None] * dey[:, :, None] * ex[:, None, :],
              ey[:, :, None] * ex[:, None, :]]
    if fit_background:
        planes.append(np.ones_like(planes[0]))
    j = np.stack(planes, axis=1)
    assert_allclose(a_mat, np.einsum("npij,nqij,nij->npq", j, j, w), rtol=1e-10, atol=1e-12)
    assert_allclose(g, np.einsum("npij,nij->np", j, w * r), rtol=1e-10, atol=1e-10)


def test_gaussfit_with_and_without_the_psf_width_agree_on_a_known_width():
    st_, dx, dy, rng = _stamps(5)
    flux0 = np.full(dx.size, 1000.0)
    fixed = fit_gaussians(st_, dx, dy, flux0, 1.3)
    free = fit_gaussians(st_, dx, dy, flux0, 1.3, fit_sigma=True)
    good = fixed.ok & free.ok
    assert good.sum() >= dx.size - 2
    # the image's Gaussian is sampled at pixel centres: the pixel-integrated width is a little less
    assert abs(np.median(free.psf_sigma[good]) - np.sqrt(1.3**2 - 1 / 12)) < 0.05
    assert np.median(np.abs(free.dx[good] - fixed.dx[good])) < 0.02
    assert np.median(np.abs(free.dy[good] - fixed.dy[good])) < 0.02


def test_centre_of_weights_is_the_weighted_mean_offset():
    rng = np.random.default_rng(6)
    w = rng.random((7, 9, 9))
    w[3] = 0.0
    u = np.arange(-4, 5, dtype=np.float64)
    cx, cy, ok = _centre_of_weights(w, u)
    assert_array_equal(ok, np.arange(7) != 3)
    assert_allclose(cx[ok], (w[ok] * u[None, None, :]).sum(axis=(1, 2)) / w[ok].sum(axis=(1, 2)), rtol=1e-12)
    assert_allclose(cy[ok], (w[ok] * u[None, :, None]).sum(axis=(1, 2)) / w[ok].sum(axis=(1, 2)), rtol=1e-12)


@pytest.mark.parametrize("shape", [(1, 1), (1, 5), (4, 1), (3, 4), (16, 16)])
def test_edge_padding_copies_the_outer_cells(shape):
    grid = np.random.default_rng(8).normal(size=shape).astype(np.float32)
    assert_array_equal(_edge_padded(grid), np.pad(grid, 1, mode="edge"))


def _keys_surface(sm: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """The Keys (a = -0.5) bicubic surface of one window at many points, straight from the kernel."""
    from starlog.centroiding.bicubic import keys_kernel

    w = sm.shape[0]
    cols = np.arange(w)
    kx = keys_kernel(x[:, None] - cols[None, :])[0]
    ky = keys_kernel(y[:, None] - cols[None, :])[0]
    return np.einsum("pi,ij,pj->p", ky, sm, kx)


def _grid_line_maximum(sm: np.ndarray, other: float, axis: int, lo: float, hi: float) -> tuple[float, np.ndarray]:
    """Best point of a 1e-4 px grid over [lo, hi] along ``axis`` (0: x at row ``other``; 1: y at column ``other``)."""
    grid = np.arange(lo, hi + 1e-9, 1e-4)
    fixed = np.full_like(grid, other)
    values = _keys_surface(sm, grid, fixed) if axis == 0 else _keys_surface(sm, fixed, grid)
    return float(grid[np.argmax(values)]), values


# private _line_maximum, _values_along: one axis step of BICUBIC's peak search, checked alone against a grid
@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), sigma=st.floats(0.5, 2.0), snr=st.floats(5.0, 200.0),
       start=st.floats(1.0, 9.0), other=st.floats(1.0, 9.0), axis=st.integers(0, 1))
def test_bicubic_line_maxima_in_closed_form_match_a_fine_grid_search(seed, sigma, snr, start, other, axis):
    """Each axis step of the peak search: the closed-form maximum of the surface along the line
    equals the best point of a 1e-4 px grid over the same bracket (to the grid's resolution), for
    either axis, any line and any start inside the window (the bracket clamped at its edges)."""
    from starlog.centroiding.bicubic import _line_maximum, _values_along

    rng = np.random.default_rng(seed)
    w = 11
    u = np.arange(w) - w // 2
    dx, dy = rng.uniform(-2.0, 2.0, 2)
    sm = snr * np.exp(-((u[None, :] - dx) ** 2 + (u[:, None] - dy) ** 2) / (2 * sigma**2))
    sm += rng.standard_normal(sm.shape)
    lo, hi = max(start - 1.0, 1.0), min(start + 1.0, w - 2.0)
    found = _line_maximum(_values_along(sm[None], np.array([other]), axis), np.array([start]), np.array([lo]),
                          np.array([hi]))[0]
    best, values = _grid_line_maximum(sm, other, axis, lo, hi)
    if 1e-3 < best - lo and 1e-3 < hi - best:  # an interior maximum: the search must find it
        assert abs(found - best) <= 2e-4
        point = (np.array([found]), np.array([other])) if axis == 0 else (np.array([other]), np.array([found]))
        assert _keys_surface(sm, *point)[0] >= values.max() - 1e-9 * max(1.0, abs(values.max()))


# private _line_maximum: a rounding edge case of one search step, which a whole centroid would not show
def test_bicubic_finds_a_maximum_that_sits_on_a_pixel_centre():
    """A symmetric peak centred on a pixel: the slope's zero is at an interval's end, where rounding
    can put it a hair outside both intervals that share it."""
    from starlog.centroiding.bicubic import _line_maximum

    from starlog.centroiding.bicubic import keys_kernel

    rng = np.random.default_rng(2)
    misses = checked = 0
    for _ in range(3000):
        values = rng.standard_normal(9)
        # neighbours equal to within one rounding step: the slope's zero is on pixel 4, give or take 1e-16 px
        values[5] = values[3] * (1.0 + rng.choice([-1e-16, 0.0, 1e-16]))
        values[4] = max(values[3], values[5]) + abs(rng.standard_normal()) + 1e-3
        lo, hi = np.array([3.3]), np.array([5.3])
        grid = np.linspace(lo[0], hi[0], 2001)
        surface = keys_kernel(grid[:, None] - np.arange(9)[None, :])[0] @ values
        if not 3.31 < grid[np.argmax(surface)] < 5.29:
            continue  # the surface is highest at the bracket's end: not an interior maximum
        checked += 1
        found = _line_maximum(values[None], np.array([4.3]), lo, hi)[0]
        value = keys_kernel(np.array([found])[:, None] - np.arange(9)[None, :])[0] @ values
        misses += bool(value[0] < surface.max() - 1e-9 * max(1.0, abs(surface.max())))
    assert checked > 1000 and misses == 0


@settings(max_examples=60, deadline=None, derandomize=True)
@given(seed=st.integers(0, 2**31 - 1), ny=st.integers(1, 6), nx=st.integers(1, 6), mesh=st.sampled_from([8, 16, 64]),
       trim_rows=st.integers(0, 7), trim_cols=st.integers(0, 7), k=st.floats(0.5, 10.0))
def test_pixels_above_the_threshold_as_with_the_full_map(seed, ny, nx, mesh, trim_rows, trim_cols, k):
    """The compiled comparison decides as a comparison with the resized map, but within float32
    rounding of the threshold; grids of one row or column and frames not a multiple of the cell
    size included."""
    rng = np.random.default_rng(seed)
    shape = (max(1, ny * mesh - trim_rows), max(1, nx * mesh - trim_cols))
    level = rng.uniform(90, 110, (ny, nx)).astype(np.float32)
    noise = rng.uniform(1, 5, (ny, nx)).astype(np.float32)
    bg = Background(level, noise, mesh, shape, float(np.median(level)), float(np.median(noise)))
    threshold = bg.map(level, plus=np.float32(k) * noise)
    image = (threshold + rng.normal(0, 2, shape)).astype(np.float32)
    image.flat[::50] = threshold.flat[::50]  # exactly at it
    expected = cv2.compare(image, threshold, cv2.CMP_GT)
    got = bg.above(image, k)
    differ = got != expected
    assert np.all(np.abs(image[differ] - threshold[differ]) <= 1e-5 * np.abs(threshold[differ]))
    assert image.size < 100 or 0 < np.count_nonzero(expected) < image.size


@settings(max_examples=40, deadline=None, derandomize=True)
@given(seed=st.integers(0, 2**31 - 1), cells=st.integers(1, 30), m=st.sampled_from([4, 8, 9, 16]),
       holes=st.floats(0.0, 0.9), clip=st.floats(2.0, 4.0), iterations=st.integers(1, 3))
def test_compiled_cell_planes_match_the_vectorised_fit(seed, cells, m, holes, clip, iterations):
    """The planes agree to float32 rounding (a sample at the clipping limit could go either way in a
    later iteration; none does here); cells with too few samples keep their start values."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:m, :m] - (m - 1) / 2
    level = rng.uniform(50, 500, cells)
    vals = (level[:, None, None] + rng.uniform(-2, 2, (cells, 1, 1)) * xx + rng.uniform(-2, 2, (cells, 1, 1)) * yy
            + rng.normal(0, 3, (cells, m, m))).reshape(cells, m * m).astype(np.float32)
    vals[rng.random(vals.shape) < holes] = np.nan
    vals[:, 0] += np.float32(200)  # a star's pixel in every cell
    start_level, start_noise = level + rng.normal(0, 1, cells), rng.uniform(2, 4, cells)
    got = _fit_planes(vals, start_level, start_noise, iterations, clip)
    want = _fit_planes_vectorised(vals, start_level, start_noise, iterations, clip)
    for a, b in zip(got, want):
        assert_allclose(a, b, rtol=1e-5, atol=1e-4)


def test_compiled_and_vectorised_cell_planes_agree_on_digitised_values():
    """Whole-number samples of a noise below one step (start noise: one step): both fits measure the
    digitised values' spread, and a cell whose samples are all one value gets noise 0 in both."""
    rng = np.random.default_rng(4)
    cells, m = 12, 16
    level = rng.uniform(10, 14, cells)
    vals = np.rint(level[:, None] + rng.normal(0, 0.3, (cells, m * m))).astype(np.float32)
    vals[0] = np.float32(12)
    start_level, start_noise = np.median(vals, axis=1).astype(np.float64), np.ones(cells)
    got = _fit_planes(vals, start_level, start_noise, 1, 3.0)
    want = _fit_planes_vectorised(vals, start_level, start_noise, 1, 3.0)
    for a, b in zip(got, want):
        assert_allclose(a, b, rtol=1e-5, atol=1e-6)
    assert got[3][0] == 0.0 and np.all(got[3][1:] > 0.1)


def test_a_pixel_exactly_at_the_threshold_is_not_above_it():
    """On a one-cell grid the threshold is level + k x noise exactly, with no interpolation: equal is not above."""
    level, noise = np.full((1, 1), 100.0, np.float32), np.full((1, 1), 2.0, np.float32)
    bg = Background(level, noise, 16, (16, 16), 100.0, 2.0)
    threshold = np.float32(100.0) + np.float32(5.0) * np.float32(2.0)
    assert not bg.above(np.full((16, 16), threshold, np.float32), 5.0).any()
    assert bg.above(np.full((16, 16), np.nextafter(threshold, np.float32(np.inf)), np.float32), 5.0).all()
