"""The compiled detection glue (starlog.detect.peak_kernels) against its numpy references, bit for bit."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.testing import assert_array_equal

import starlog.detect.components as components
import starlog.detect.detection as detection
from starlog.compiled_numpy import block_sum, pairwise_sum
from starlog.detect import detect_stars
from starlog.detect.components import Components, Peaks, component_peaks, find_components, find_components_vectorised
from starlog.errors import InvalidInputError
from starlog.sim.camera import CameraModel
from starlog.sim.psf import render_stars


def _scene(seed: int, size: int, n: int, psf: float, *, kind: str = "uint16", hot: int = 5, holes: int = 0,
           saturate: bool = False) -> np.ndarray:
    """A star field with blended pairs, stars at the edges and in a corner, hot pixels, a cosmic-ray
    track, optionally saturated stars (12-bit ADC) and NaN pixels (float frames)."""
    rng = np.random.default_rng(seed)
    rows, cols = size, size + int(rng.integers(-size // 4, size // 4 + 1))
    x, y = rng.uniform(2, cols - 3, n), rng.uniform(2, rows - 3, n)
    pair = np.arange(0, n // 3 - 1, 2)  # blends: a star 1.5 to 4 px from the next one
    x[pair] = np.clip(x[pair + 1] + rng.uniform(1.5, 4.0, pair.size), 0, cols - 1)
    y[pair] = np.clip(y[pair + 1] + rng.uniform(-2.0, 2.0, pair.size), 0, rows - 1)
    edge = np.array([[0.2, rows / 2], [cols - 1.3, rows / 3], [cols / 2, 0.4], [cols / 3, rows - 0.8], [0.3, 0.6],
                     [cols - 0.7, rows - 0.2]])
    x, y = np.concatenate([x, edge[:, 0]]), np.concatenate([y, edge[:, 1]])
    flux = rng.uniform(150, 8000, x.size)
    if saturate:
        flux[rng.integers(0, x.size, 3)] = 5e5
    expected = 20.0 + render_stars((rows, cols), x, y, flux, psf)
    hy, hx = rng.integers(0, rows, hot), rng.integers(0, cols, hot)
    expected[hy, hx] += rng.uniform(300, 6000, hot)
    ty, tx = int(rng.integers(0, rows - 6)), int(rng.integers(0, cols - 6))
    expected[ty + np.arange(6), tx + np.arange(6)] += 3000.0
    img = CameraModel(adc_bits=12 if saturate else 16).expose(expected, rng)
    if kind != "uint16":
        img = img.astype(kind)
        ny, nx = rng.integers(0, rows, holes), rng.integers(0, cols, holes)
        img[ny, nx] = np.nan
        near = rng.integers(0, x.size, min(holes, x.size))  # some on stars' peaks and next to them
        img[np.clip(np.rint(y[near]).astype(int) + rng.integers(-1, 2, near.size), 0, rows - 1),
            np.clip(np.rint(x[near]).astype(int) + rng.integers(-1, 2, near.size), 0, cols - 1)] = np.nan
    return img


# private _prepare, _foreground: detect_stars's intermediate frames, the inputs its private steps are compared on
def _stages(img: np.ndarray, *, opening: bool = True, min_area: int = 3, deblend: bool = True):
    """detect_stars up to its candidates: the arguments of _local_maxima and _candidates."""
    arr = np.asarray(img)
    frame = detection._prepare(arr, None, 64)
    assert frame is not None
    work, bg, _ = frame
    filtered, k1 = detection.matched_filter(work, 1.5)
    knorm = float(np.sum(k1**2))
    comp = find_components(detection._foreground(filtered, bg, 5.0 * knorm, opening=opening), min_area, 20000)
    peaks = None
    if comp.count:
        cx, cy = comp.box_centres()
        peaks = component_peaks(comp, filtered, work, bg.level_at(cx, cy), bg.noise_at(cx, cy) * knorm,
                                deblend=deblend)
    return work, filtered, bg, k1, knorm, comp, peaks


def _candidate_options(saturation: float) -> dict:
    return dict(saturation=saturation, sharpness_ratio=0.2, max_elongation=2.5, elongation_flag=1.6, threshold=5.0,
                border=3)


# private _candidates vs its numpy reference _candidates_vectorised: one step of detect_stars, checked alone
def _same_candidates(peaks, comp, work, filtered, bg, k1, knorm, saturation):
    opts = _candidate_options(saturation)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # the numpy form on non-finite windows
        want, want_keep = detection._candidates_vectorised(peaks, comp, work, filtered, bg, k1, knorm, **opts)
    got, got_keep = detection._candidates(peaks, comp, work, filtered, bg, k1, knorm, **opts)
    assert got.dtype == want.dtype
    for name in want.dtype.names:
        assert got[name].tobytes() == want[name].tobytes(), name
    assert got.tobytes() == want.tobytes()
    assert_array_equal(got_keep, want_keep)


scenes = dict(seed=st.integers(0, 2**31 - 1), size=st.integers(24, 160), n=st.integers(0, 40),
              psf=st.sampled_from([0.5, 0.9, 1.5, 2.5]), kind=st.sampled_from(["uint16", "float32", "float64"]),
              holes=st.integers(0, 12), saturate=st.booleans())


def _same_components(mask, min_area=1, max_area=None):
    got, want = find_components(mask, min_area, max_area), find_components_vectorised(mask, min_area, max_area)
    for name in Components.__dataclass_fields__:
        a, b = getattr(got, name), getattr(want, name)
        assert a.dtype == b.dtype, name
        assert_array_equal(a, b, err_msg=name)


@settings(max_examples=80, deadline=None, derandomize=True)
@given(seed=st.integers(0, 2**31 - 1), fill=st.floats(0.02, 0.7), rows=st.integers(1, 90), cols=st.integers(1, 90),
       min_area=st.integers(1, 6), max_area=st.sampled_from([None, 5, 40]))
def test_pixel_listing_kernel_matches_numpy_on_random_masks(seed, fill, rows, cols, min_area, max_area):
    """Many overlapping boxes (cropped one by one below 65 boxes, one pixel graph above), rings
    around other components, components smaller than min_area inside other boxes."""
    rng = np.random.default_rng(seed)
    mask = (rng.random((rows, cols)) < fill).astype(np.uint8)
    mask[rng.random((rows, cols)) < 0.02] = 255
    _same_components(mask, min_area, max_area)


# private _prepare, _foreground: the thresholded frame detect_stars labels, built as it builds it
@settings(max_examples=40, deadline=None, derandomize=True)
@given(**scenes, opening=st.booleans(), min_area=st.sampled_from([1, 3]))
def test_pixel_listing_kernel_matches_numpy_on_star_fields(seed, size, n, psf, kind, holes, saturate, opening,
                                                         min_area):
    img = _scene(seed, size, n, psf, kind=kind, holes=holes, saturate=saturate)
    work, bg, _ = detection._prepare(np.asarray(img), None, 64)
    filtered, k1 = detection.matched_filter(work, 1.5)
    _same_components(detection._foreground(filtered, bg, 5.0 * float(np.sum(k1**2)), opening=opening), min_area)


def test_ring_and_nested_component():
    mask = np.zeros((9, 9), np.uint8)
    mask[1, 1:8] = mask[7, 1:8] = mask[1:8, 1] = mask[1:8, 7] = 1  # a ring: one external contour
    mask[4, 4] = 1  # inside the ring's hole: listed with the ring
    mask[0, 8] = 1  # touches the ring's corner diagonally
    _same_components(mask)
    comp = find_components(mask)
    assert comp.count == 1 and comp.area[0] == mask.sum()


# private _local_maxima vs its numpy reference _local_maxima_vectorised: one step of detect_stars, checked alone
@settings(max_examples=60, deadline=None, derandomize=True)
@given(**scenes, opening=st.booleans(), min_area=st.sampled_from([1, 3]))
def test_local_maxima_kernel_matches_numpy(seed, size, n, psf, kind, holes, saturate, opening, min_area):
    img = _scene(seed, size, n, psf, kind=kind, holes=holes, saturate=saturate)
    _, filtered, _, _, _, comp, _ = _stages(img, opening=opening, min_area=min_area)
    assert_array_equal(components._local_maxima(comp, filtered), components._local_maxima_vectorised(comp, filtered))


# private _local_maxima vs its numpy reference _local_maxima_vectorised: one step of detect_stars, checked alone
@settings(max_examples=40, deadline=None, derandomize=True)
@given(seed=st.integers(0, 2**31 - 1), fill=st.floats(0.05, 0.7), rows=st.integers(1, 40), cols=st.integers(1, 40),
       nan=st.floats(0, 0.3), levels=st.sampled_from([3, 1000]))
def test_local_maxima_kernel_on_ties_and_nan(seed, fill, rows, cols, nan, levels):
    """Few distinct values (ties, lone components whose top lies off the foreground) and NaN."""
    rng = np.random.default_rng(seed)
    mask = (rng.random((rows, cols)) < fill).astype(np.uint8)
    filtered = rng.integers(0, levels, (rows, cols)).astype(np.float32)
    filtered[rng.random((rows, cols)) < nan] = np.nan
    filtered[rng.random((rows, cols)) < 0.05] = -0.0
    comp = find_components(mask)
    assert_array_equal(components._local_maxima(comp, filtered), components._local_maxima_vectorised(comp, filtered))
    # values that float32 would tie: a float64 image is compared in float64, as numpy compares it
    fine = filtered.astype(np.float64) + rng.integers(0, 2, (rows, cols)) * 1e-9
    assert_array_equal(components._local_maxima(comp, fine), components._local_maxima_vectorised(comp, fine))


# private _local_maxima vs its numpy reference _local_maxima_vectorised: one step of detect_stars, checked alone
def test_a_component_without_a_local_maximum_gets_its_brightest_pixel():
    mask = np.zeros((6, 6), np.uint8)
    mask[2, 1:4] = 1
    mask[3, 1] = 1
    filtered = np.zeros((6, 6), np.float32)
    filtered[2, 1:4] = [5, 7, 7]
    filtered[3, 1] = 6
    filtered[3, 2] = filtered[3, 3] = 9  # in the box, off the foreground, brighter than every pixel
    comp = find_components(mask)
    peak = components._local_maxima(comp, filtered)
    assert_array_equal(peak, components._local_maxima_vectorised(comp, filtered))
    assert_array_equal(comp.x[peak], [2])  # the first of the two 7s
    assert_array_equal(comp.y[peak], [2])
    filtered[2, 2] = filtered[2, 3] = np.nan  # NaN counts as the faintest
    peak = components._local_maxima(comp, filtered)
    assert_array_equal(peak, components._local_maxima_vectorised(comp, filtered))
    assert_array_equal(comp.x[peak], [1])
    assert_array_equal(comp.y[peak], [3])


@settings(max_examples=60, deadline=None, derandomize=True)
@given(**scenes, opening=st.booleans(), deblend=st.booleans())
def test_candidates_kernel_matches_numpy(seed, size, n, psf, kind, holes, saturate, opening, deblend):
    img = _scene(seed, size, n, psf, kind=kind, holes=holes, saturate=saturate)
    work, filtered, bg, k1, knorm, comp, peaks = _stages(img, opening=opening, deblend=deblend)
    if peaks is None:
        return
    # detect_stars's default saturation: the integer type's maximum, none for floating-point frames
    default = float(np.iinfo(img.dtype).max) if np.issubdtype(img.dtype, np.integer) else np.inf
    saturation = 4095.0 if saturate else default
    _same_candidates(peaks, comp, work, filtered, bg, k1, knorm, saturation)


@settings(max_examples=30, deadline=None, derandomize=True)
@given(seed=st.integers(0, 2**31 - 1), bad=st.sampled_from([np.nan, np.inf, -np.inf, -0.0, 0.0]),
       count=st.integers(1, 30))
def test_candidates_kernel_on_non_finite_windows(seed, bad, count):
    """Non-finite and signed-zero values in the raw and filtered windows, zero background level."""
    img = _scene(seed, 96, 20, 1.2)
    work, filtered, bg, k1, knorm, comp, peaks = _stages(img)
    rng = np.random.default_rng(seed)
    work, filtered = work.copy(), filtered.copy()
    for image in (work, filtered):
        at = rng.integers(0, peaks.y.size, count)
        image[np.clip(peaks.y[at] + rng.integers(-3, 4, count), 0, image.shape[0] - 1),
              np.clip(peaks.x[at] + rng.integers(-3, 4, count), 0, image.shape[1] - 1)] = bad
    _same_candidates(peaks, comp, work, filtered, bg, k1, knorm, 65535.0)
    flat = type(bg)(np.zeros_like(bg.mesh_level), bg.mesh_noise, bg.mesh, bg.shape, 0.0, bg.global_noise)
    _same_candidates(peaks, comp, work - np.float32(bg.global_level), filtered - np.float32(bg.global_level), flat,
                     k1, knorm, 65535.0)


@pytest.mark.parametrize("shape", [(1, 1), (1, 5), (5, 1), (3, 4)])
def test_candidates_kernel_on_one_cell_grids(shape):
    """Grids of one row or column of cells (weights 1 and 0), and sub-mesh frames."""
    img = _scene(3, 70, 12, 1.0)
    work, filtered, bg, k1, knorm, comp, peaks = _stages(img)
    rng = np.random.default_rng(1)
    grid = lambda g: (g.mean() + rng.normal(0, 2, shape)).astype(np.float32)  # noqa: E731
    other = type(bg)(grid(bg.mesh_level), np.abs(grid(bg.mesh_noise)), 32, bg.shape, bg.global_level,
                     bg.global_noise)
    _same_candidates(peaks, comp, work, filtered, other, k1, knorm, 65535.0)


@settings(max_examples=200, deadline=None, derandomize=True)
@given(seed=st.integers(0, 2**31 - 1), m=st.integers(1, 6), k=st.sampled_from([1, 2, 3, 5, 7, 9, 11]),
       spread=st.integers(0, 12))
def test_window_sum_is_numpys_summation_order(seed, m, k, spread):
    """numpy's sum(axis=(1, 2)) of (m, k, k) windows, for magnitudes where the order shows."""
    rng = np.random.default_rng(seed)
    windows = rng.standard_normal((m, k, k)) * 10.0 ** rng.integers(-spread, spread + 1, (m, k, k))
    windows[rng.random((m, k, k)) < 0.1] = -0.0
    want = windows.sum(axis=(1, 2))
    got = np.array([0.0 + block_sum(w.ravel().copy(), 0, k * k) for w in windows])
    assert got.tobytes() == want.tobytes()


@settings(max_examples=100, deadline=None, derandomize=True)
@given(seed=st.integers(0, 2**31 - 1), k=st.sampled_from([1, 5, 11, 12, 13, 17, 23, 37]), start=st.integers(0, 9),
       spread=st.integers(0, 12))
def test_pairwise_sum_is_numpys_summation_order_past_128_values(seed, k, start, spread):
    """numpy's sum of one k x k window (169 and more values: the halves' sums added) at an offset in a longer run."""
    rng = np.random.default_rng(seed)
    run = rng.standard_normal(start + k * k) * 10.0 ** rng.integers(-spread, spread + 1, start + k * k)
    want = run[start:].reshape(1, k, k).sum(axis=(1, 2))[0]
    assert np.float64(0.0 + pairwise_sum(run, start, k * k)).tobytes() == want.tobytes()


# private names patched: detect_stars run with its numpy references in place of the compiled steps
def _vectorised(stack):
    stack.setattr(detection, "find_components", components.find_components_vectorised)
    stack.setattr(components, "_local_maxima", components._local_maxima_vectorised)
    stack.setattr(detection, "_candidates", detection._candidates_vectorised)


@settings(max_examples=300, deadline=None, derandomize=True)
@given(**scenes, opening=st.booleans(), deblend=st.booleans(), min_area=st.sampled_from([1, 3]),
       max_stars=st.sampled_from([None, 5]))
def test_detect_stars_is_byte_identical_with_the_numpy_references(seed, size, n, psf, kind, holes, saturate,
                                                                  opening, deblend, min_area, max_stars):
    img = _scene(seed, size, n, psf, kind=kind, holes=holes, saturate=saturate)
    opts = dict(opening=opening, deblend=deblend, min_area=min_area, max_stars=max_stars,
                saturation=4095 if saturate else None)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        got = detect_stars(img, **opts)
        with pytest.MonkeyPatch.context() as stack:
            _vectorised(stack)
            want = detect_stars(img, **opts)
    assert got.dtype == want.dtype and got.shape == want.shape
    assert got.tobytes() == want.tobytes()


# private _candidates, _local_maxima, _member_pixels: their own input checks, which detect_stars never trips
def test_mismatched_or_out_of_range_inputs_are_refused():
    img = _scene(8, 80, 10, 1.2)
    work, filtered, bg, k1, knorm, comp, peaks = _stages(img)
    opts = _candidate_options(65535.0)
    short = Peaks(peaks.y[:-1], peaks.x, peaks.fval, peaks.flux, peaks.blended, peaks.component)
    with pytest.raises(InvalidInputError, match="mismatched"):
        detection._candidates(short, comp, work, filtered, bg, k1, knorm, **opts)
    stray = Peaks(peaks.y, peaks.x, peaks.fval, peaks.flux, peaks.blended, peaks.component + comp.count)
    with pytest.raises(InvalidInputError, match="no component"):
        detection._candidates(stray, comp, work, filtered, bg, k1, knorm, **opts)
    with pytest.raises(InvalidInputError, match="mismatched"):
        detection._candidates(peaks, comp, work, filtered[:-1], bg, k1, knorm, **opts)
    fields = {name: getattr(comp, name) for name in Components.__dataclass_fields__}
    with pytest.raises(InvalidInputError, match="mismatched"):
        components._local_maxima(Components(**{**fields, "x": comp.x[:-1]}), filtered)
    with pytest.raises(InvalidInputError, match="outside"):
        components._local_maxima(Components(**{**fields, "y": comp.y + 1}), filtered)
    with pytest.raises(InvalidInputError, match="outside"):
        components._local_maxima(Components(**{**fields, "x_max": comp.x_max + filtered.shape[1]}), filtered)
    with pytest.raises(InvalidInputError, match="outside"):
        components._local_maxima(Components(**{**fields, "label": comp.label - 1}), filtered)
    mask = np.zeros((8, 8), np.uint8)
    mask[2:4, 2:5] = 1
    rects, seeds = np.array([[2, 2, 3, 2]]), np.array([[2, 2]])
    assert components._member_pixels(mask, rects, seeds)[0].size == 6
    with pytest.raises(InvalidInputError, match="box 0"):
        components._member_pixels(mask, rects, np.array([[1, 2]]))
    with pytest.raises(InvalidInputError, match="box 0"):
        components._member_pixels(mask, np.array([[6, 2, 3, 2]]), np.array([[6, 2]]))
    with pytest.raises(InvalidInputError, match="mismatched"):
        components._member_pixels(mask, rects, np.array([[2, 2], [3, 3]]))
