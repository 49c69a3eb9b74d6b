"""Detection's parts on hand-made arrays: components, peaks and deblending, screening, coarse position."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from starlog.detect import DetectionFlag
from starlog.detect.components import component_peaks, find_components
from starlog.detect.position import coarse_offsets, log_parabola
from starlog.detect.screening import elongation, gather, is_spike, screen


def _mask(text: str) -> np.ndarray:
    return np.array([[ch == "#" for ch in line] for line in text.strip().splitlines()], np.uint8)


def _by_box(comp):
    """{(x_min, y_min, x_max, y_max): area} of every component."""
    return {(int(a), int(b), int(c), int(d)): int(n)
            for a, b, c, d, n in zip(comp.x_min, comp.y_min, comp.x_max, comp.y_max, comp.area)}


def test_components_are_8_connected_with_areas_and_boxes():
    mask = _mask("""
##.......
##.....#.
......#..
.#.......
.........
""")
    comp = find_components(mask)
    assert _by_box(comp) == {(0, 0, 1, 1): 4, (6, 1, 7, 2): 2, (1, 3, 1, 3): 1}
    for c in range(comp.count):  # pixels grouped by component, inside its box, in raster order
        sl = slice(comp.start[c], comp.start[c] + comp.area[c])
        assert_array_equal(comp.label[sl], c)
        assert np.all((comp.x[sl] >= comp.x_min[c]) & (comp.x[sl] <= comp.x_max[c]))
        assert np.all(np.diff(comp.y[sl] * mask.shape[1] + comp.x[sl]) > 0)
    assert _by_box(find_components(mask, min_area=2, max_area=3)) == {(6, 1, 7, 2): 2}


def test_component_reaching_into_another_box_is_kept_apart():
    # the L's box covers the blob on its right: each keeps only its own pixels
    mask = _mask("""
#.....
#..##.
#..##.
#.....
######
""")
    comp = find_components(mask)
    assert _by_box(comp) == {(0, 0, 5, 4): 10, (3, 1, 4, 2): 4}


def test_empty_mask_has_no_component():
    comp = find_components(np.zeros((20, 30), np.uint8))
    assert comp.count == 0 and comp.y.size == 0


def _two_peaks(separation: float, ratio: float = 0.5, shape=(21, 41)):
    yy, xx = np.mgrid[: shape[0], : shape[1]].astype(np.float64)
    x1, x2 = 20 - separation / 2, 20 + separation / 2
    r1, r2 = (xx - x1) ** 2 + (yy - 10) ** 2, (xx - x2) ** 2 + (yy - 10) ** 2
    img = 100 * np.exp(-r1 / 8) + 100 * ratio * np.exp(-r2 / 8)
    return img.astype(np.float32), (x1, x2)


def test_separated_peaks_are_split_and_share_the_flux():
    img, (x1, x2) = _two_peaks(10.0)
    comp = find_components((img > 1.0).astype(np.uint8))
    assert comp.count == 1
    level, noise = np.zeros(1), np.full(1, 0.5)
    peaks = component_peaks(comp, img, img, level, noise)
    assert_array_equal(peaks.x, [round(x1), round(x2)])  # brightest first
    assert_array_equal(peaks.y, [10, 10])
    assert peaks.blended.all()
    assert_allclose(peaks.fval, img[10, [round(x1), round(x2)]])
    total = img[comp.y, comp.x].astype(np.float64).sum()
    assert_allclose(peaks.flux.sum(), total)
    assert_allclose(peaks.flux[1] / peaks.flux[0], peaks.fval[1] / peaks.fval[0])


def test_peaks_without_a_significant_saddle_are_not_split():
    img, (x1, _) = _two_peaks(10.0)
    comp = find_components((img > 1.0).astype(np.uint8))
    level = np.zeros(1)
    # the secondary rises ~50 above the saddle: a 200-sigma requirement keeps one star
    for peaks in (component_peaks(comp, img, img, level, np.full(1, 0.25), nsigma=200.0),
                  component_peaks(comp, img, img, level, np.full(1, 0.5), deblend=False)):
        assert_array_equal(peaks.x, [round(x1)])
        assert not peaks.blended.any()
        assert_allclose(peaks.flux, img[comp.y, comp.x].astype(np.float64).sum())


def test_flux_is_measured_above_the_component_level():
    img, _ = _two_peaks(0.0, ratio=0.0)
    comp = find_components((img > 1.0).astype(np.uint8))
    peaks = component_peaks(comp, img + 7, img + 7, np.full(1, 7.0), np.full(1, 0.5))
    assert_array_equal((peaks.y, peaks.x), ([10], [20]))
    assert_allclose(peaks.fval, [100.0])
    assert_allclose(peaks.flux, img[comp.y, comp.x].astype(np.float64).sum(), rtol=1e-6)


def test_gather_replicates_edge_pixels():
    img = np.arange(20.0).reshape(4, 5)
    w = gather(img, np.array([0]), np.array([4]), 1)
    assert_array_equal(w[0], [[3, 4, 4], [3, 4, 4], [8, 9, 9]])


def _gaussian_box(sigma_x, sigma_y, amp=1000.0, r=2):
    d = np.arange(-r, r + 1, dtype=np.float64)
    return (amp * np.exp(-d[None, :, None] ** 2 / (2 * sigma_y**2) - d[None, None, :] ** 2 / (2 * sigma_x**2)))


def test_spike_test_rejects_hot_pixels_and_keeps_stars():
    hot = np.zeros((1, 5, 5))
    hot[0, 2, 2] = 500.0
    assert is_spike(hot, np.ones(1), 0.2).all()
    assert not is_spike(_gaussian_box(1.2, 1.2), np.ones(1), 0.2).any()
    assert not is_spike(hot, np.full(1, 100.0), 0.2).any()  # not significant over that noise


def test_elongation_is_the_axis_ratio():
    assert_allclose(elongation(_gaussian_box(1.5, 1.5, r=3)), 1.0, atol=1e-9)
    cross = np.zeros((1, 7, 7))
    cross[0, 3, 2:5] = 1.0  # x variance 2 / 3.5, y variance 0.5 / 3.5: axis ratio 2
    cross[0, [2, 4], 3] = 0.25
    assert_allclose(elongation(cross), 2.0, rtol=1e-12)
    assert_allclose(elongation(np.swapaxes(cross, 1, 2)), 2.0, rtol=1e-12)
    assert_allclose(elongation(np.zeros((1, 7, 7))), 1.0)


def test_screen_keeps_saturated_and_flags_elongated():
    raw = np.concatenate([_gaussian_box(1.2, 1.2, amp=900.0), np.zeros((1, 5, 5)), _gaussian_box(1.2, 1.2)])
    raw[1, 2, 2] = 800.0  # a hot pixel
    raw[2, 1:4, 1:4] = 1000.0  # flat-topped, saturated at 1000
    filt = np.stack([_gaussian_box(1.2, 1.2, r=3)[0], _gaussian_box(0.5, 0.5, r=3)[0], _gaussian_box(2.0, 0.9, r=3)[0]])
    keep, flags, elong = screen(raw, filt, np.zeros(3), np.ones(3), np.zeros(3, bool), saturation=1000.0,
                                sharpness_ratio=0.2, max_elongation=1.8, elongation_flag=1.6)
    assert_array_equal(keep, [True, False, True])
    assert flags[2] & DetectionFlag.SATURATED and flags[2] & DetectionFlag.ELONGATED
    assert flags[0] == 0
    assert elong[2] > 1.8  # too long, but saturated stars are exempt


@pytest.mark.parametrize("offset", [-0.45, -0.1, 0.0, 0.3])
def test_log_parabola_is_exact_for_a_gaussian(offset):
    f = np.exp(-((np.array([-1.0, 0.0, 1.0]) - offset) ** 2) / (2 * 1.3**2))
    off, ok = log_parabola(f[:1], f[1:2], f[2:])
    assert ok.all()
    assert_allclose(off, offset, atol=1e-12)


def test_coarse_offsets_fall_back_to_moments():
    d = np.arange(-1, 2, dtype=np.float64)
    filt = np.exp(-((d[None, :, None] + 0.2) ** 2) / 2 - (d[None, None, :] - 0.35) ** 2 / 2)
    box = _gaussian_box(1.0, 1.0)
    dx, dy = coarse_offsets(box, filt)
    assert_allclose((dx, dy), ([0.35], [-0.2]), atol=1e-12)
    flat = filt.copy()
    flat[0, 1, 0] = 0.0  # no log-parabola in x: the 5x5 moment (0 for a centred star)
    dx, dy = coarse_offsets(box, flat)
    assert_allclose((dx, dy), ([0.0], [-0.2]), atol=1e-12)
