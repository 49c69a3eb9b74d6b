"""The compiled tracked frame (:func:`starlog.centroiding.tracked_frame.track_frame`) against its numpy reference
(:func:`starlog.centroiding.tracking.track_frame_vectorised`) on hand-checkable windows and on random star fields and
motions, and its measurement against full mode's on the same detection rows."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.ndimage import binary_dilation
from scipy.special import erf

from starlog.centroiding import CentroidFlag, CentroidMethod
from starlog.centroiding.measure import measure_methods
from starlog.centroiding.psf_width import window_half_size
from starlog.centroiding.stamps import SHOULDER
from starlog.centroiding.tracked_frame import WindowFit, track_frame
from starlog.centroiding.tracking import TrackedFrame, TrackingSettings, TrackState, cell_means, track_frame_vectorised
# private module: the per-frame work of the centroid stage, tested without a log
from starlog.stages.centroid.frames import FrameExtractor

PSF = 1.2
GAIN, READ_NOISE = 1.0, 3.0
HALF = window_half_size(PSF)
SETTINGS = TrackingSettings(acquire_every=100)


def render(stars: list[tuple[float, float, float]], *, seed: int, shape: tuple[int, int] = (64, 72),
           sky: float = 100.0) -> np.ndarray:
    """A frame of pixel-integrated Gaussian stars ``(x, y, flux)`` on a sky with shot and read noise."""
    rows, cols = shape
    gx = np.diff(0.5 * erf((np.arange(cols + 1)[None, :] - 0.5 - np.array([s[0] for s in stars])[:, None])
                           / (np.sqrt(2) * PSF)), axis=1) if stars else np.zeros((0, cols))
    gy = np.diff(0.5 * erf((np.arange(rows + 1)[None, :] - 0.5 - np.array([s[1] for s in stars])[:, None])
                           / (np.sqrt(2) * PSF)), axis=1) if stars else np.zeros((0, rows))
    flux = np.array([s[2] for s in stars])
    image = sky + np.einsum("k,ki,kj->ij", flux, gy, gx) if stars else np.full(shape, sky)
    rng = np.random.default_rng(seed)
    image = rng.poisson(np.maximum(image, 0)).astype(np.float64) + rng.normal(0.0, READ_NOISE, shape)
    return np.clip(np.rint(image), 0, 65535).astype(np.uint16)


def acquired(image: np.ndarray, **options: object) -> TrackState:
    """The tracking state after a full search of ``image`` (the stage's own acquisition)."""
    extract = FrameExtractor(methods=(CentroidMethod.GAUSSFIT,), gain=GAIN, read_noise=READ_NOISE,
                             options={"psf_sigma": PSF, **options}, tracking=SETTINGS)
    block = extract.block()
    block.measure(image)
    assert block.state is not None
    return block.state


def first_method(image: np.ndarray, detections: np.ndarray, **options: object) -> np.ndarray:
    """Full mode's GAUSSFIT rows of given detection rows (:func:`measure_methods`, as the stage runs it)."""
    return measure_methods(image, detections, [CentroidMethod.GAUSSFIT], gain=GAIN, read_noise=READ_NOISE,
                           psf_sigma=PSF, **options)[CentroidMethod.GAUSSFIT]


FIT = WindowFit(half_size=HALF, psf_sigma=PSF, gain=GAIN, read_noise=READ_NOISE)


def same_frame(image: np.ndarray, state: TrackState, before: np.ndarray | None = None, fit: WindowFit = FIT,
               saturation: float | None = None) -> tuple[TrackedFrame, TrackedFrame]:
    """The compiled frame and the numpy reference's, checked to agree: the light check's cells, the search, the
    detection rows (coarse positions to a rounding error of a logarithm, the rest bit for bit), the measurement
    bit for bit given the detection rows (full mode's :func:`measure_methods`), the stars lost and the state after
    the frame."""
    options = {} if fit.robust else {"robust": False}
    got = track_frame(image, state, SETTINGS, before, HALF, fit, saturation)
    want = track_frame_vectorised(image, state, SETTINGS, before, HALF,
                                  lambda d: first_method(image, d, saturation=saturation, **options))
    if want.risen is None:
        assert got.risen is None
    else:
        np.testing.assert_array_equal(got.risen, want.risen)
    assert got.search == want.search
    if want.search:
        return got, want
    np.testing.assert_array_equal(got.found, want.found)
    for name in got.detections.dtype.names:
        if name in ("x", "y"):
            np.testing.assert_allclose(got.detections[name], want.detections[name], rtol=0, atol=1e-12)
        else:
            np.testing.assert_array_equal(got.detections[name], want.detections[name], err_msg=name)
    assert got.centroids is not None
    assert got.centroids.tobytes() == first_method(image, got.detections, saturation=saturation,
                                                   **options).tobytes()
    assert want.centroids is not None and want.state is not None and got.state is not None
    np.testing.assert_allclose(got.centroids["x"], want.centroids["x"], rtol=0, atol=1e-9)
    np.testing.assert_allclose(got.centroids["y"], want.centroids["y"], rtol=0, atol=1e-9)
    np.testing.assert_array_equal(got.centroids["flags"], want.centroids["flags"])
    np.testing.assert_array_equal(got.lost, want.lost)
    for name in ("x", "y", "vx", "vy"):
        np.testing.assert_allclose(getattr(got.state, name), getattr(want.state, name), rtol=0, atol=1e-9)
    np.testing.assert_array_equal(got.state.reference, want.state.reference)
    np.testing.assert_array_equal(got.state.quiet_stars, want.state.quiet_stars)
    assert got.state.since_acquisition == want.state.since_acquisition
    return got, want


def assert_same_frame(image: np.ndarray, state: TrackState, before: np.ndarray | None = None, fit: WindowFit = FIT,
                      saturation: float | None = None) -> TrackedFrame:
    """:func:`same_frame`'s compiled frame."""
    return same_frame(image, state, before, fit, saturation)[0]


STARS = [(15.3, 20.7, 6000.0), (40.6, 44.2, 9000.0), (52.1, 12.9, 4000.0)]


def test_a_static_field_is_measured_as_full_mode_measures_it() -> None:
    state = acquired(render(STARS, seed=0))
    frame = assert_same_frame(render(STARS, seed=1), state)
    assert frame.centroids is not None and frame.centroids.size == 3 and not frame.lost.any()
    assert np.all(frame.centroids["flags"] & CentroidFlag.TRACKED)


def settled(stars: list[tuple[float, float, float]]) -> TrackState:
    """The state after an acquisition and one tracked frame of a static field (a star not found now calls for a
    search; right after the acquisition it would turn quiet)."""
    state = assert_same_frame(render(stars, seed=1), acquired(render(stars, seed=0))).state
    assert state is not None
    return state


def test_a_star_at_its_search_windows_edge_calls_for_a_search() -> None:
    """A star 5 px from its prediction peaks on the search window's edge: not found, the frame is searched."""
    moved = [(15.3 + 5.0, 20.7, 6000.0), *STARS[1:]]
    frame = assert_same_frame(render(moved, seed=2), settled(STARS))
    assert frame.search


def test_a_star_whose_window_the_frames_edge_cuts() -> None:
    near_edge = [(2.2, 30.4, 8000.0), (40.6, 44.2, 9000.0)]
    state = acquired(render(near_edge, seed=0))
    frame = assert_same_frame(render(near_edge, seed=1), state)
    assert frame.centroids is not None
    edge = frame.centroids[np.argmin(frame.centroids["x"])]
    assert edge["flags"] & CentroidFlag.BORDER and abs(edge["x"] - 2.2) < 0.2


@pytest.mark.parametrize("robust", [True, False])
def test_two_stars_in_one_window(robust: bool) -> None:
    """Two stars 5.6 px apart, each in the other's window, both lost as crowded (turning quiet, right after their
    acquisition). The neighbour's wing is light a star's model cannot explain: with the robust pass, numpy
    finishes the rows, that light left out."""
    pair = [(30.0, 30.0, 15000.0), (35.5, 31.0, 12000.0)]
    options = {} if robust else {"centroid_options": {"robust": False}}
    state = acquired(render(pair, seed=0), **options)
    assert state.x.size == 2
    frame = assert_same_frame(render(pair, seed=1), state, fit=replace(FIT, robust=robust))
    assert not frame.search and frame.found.all() and frame.remeasured == robust
    assert frame.lost is not None and frame.lost.all() and frame.centroids is not None
    assert bool(np.all(frame.centroids["n_masked"] > 0)) == robust


def test_a_saturated_star() -> None:
    bright = [(30.4, 28.6, 1.0e6), (52.1, 12.9, 4000.0)]
    state = acquired(render(bright, seed=0))
    frame = assert_same_frame(render(bright, seed=1), state)
    assert frame.centroids is not None
    assert np.count_nonzero(frame.centroids["flags"] & CentroidFlag.SATURATED) == 1


@pytest.mark.parametrize("seed", [2, 3, 13])
def test_a_saturated_core_s_shoulders_are_clipped_as_full_mode_clips_them(seed: int) -> None:
    """Pixels just under the saturation level beside a saturated core count as saturated in full mode's windows
    (``SHOULDER`` of the level above the background, joined to the core): the compiled windows clip them alike, and
    the star is measured as full mode measures it."""
    rng = np.random.default_rng(seed)
    bright = [(30 + rng.uniform(-0.5, 0.5), 28 + rng.uniform(-0.5, 0.5), rng.uniform(3e5, 2e6)), (52.1, 12.9, 4000.0)]
    state = acquired(render(bright, seed=100 + seed))
    image = render(bright, seed=200 + seed)
    frame = assert_same_frame(image, state)
    assert frame.centroids is not None and frame.detections is not None
    star = frame.detections[np.flatnonzero(frame.centroids["flags"] & CentroidFlag.SATURATED)[0]]
    xc, yc = int(np.rint(star["x"])), int(np.rint(star["y"]))
    window = image[yc - HALF:yc + HALF + 1, xc - HALF:xc + HALF + 1].astype(np.float64)
    core = window >= 65535
    level = star["background"] + SHOULDER * (65535 - star["background"])
    assert np.any(binary_dilation(core, np.ones((3, 3), bool)) & ~core & (window >= level))  # a shoulder to clip


def test_a_blank_window_right_after_the_acquisition() -> None:
    """The star is gone in the frame right after its acquisition: not found, lost, no search (it turns quiet);
    its blank window's fit fails and falls back as full mode's does."""
    state = acquired(render(STARS, seed=0))
    gone = np.hypot(state.x - STARS[0][0], state.y - STARS[0][1]) < 0.5
    frame = assert_same_frame(render(STARS[1:], seed=1), state)
    assert not frame.search and frame.lost is not None and frame.state is not None and frame.centroids is not None
    np.testing.assert_array_equal(frame.lost, gone)
    np.testing.assert_array_equal(frame.state.quiet_stars, gone)
    assert not frame.found[gone].any()


def test_a_blank_window_later_calls_for_a_search() -> None:
    assert assert_same_frame(render(STARS[1:], seed=2), settled(STARS)).search


def test_a_cosmic_ray_in_a_window_is_remeasured() -> None:
    """A hit next to a star is a pixel its model cannot explain: numpy finishes the frame's rows from the compiled
    fit (the robust re-measurement), the hit left out of the star's window."""
    state = acquired(render(STARS, seed=0))
    image = render(STARS, seed=1)
    image[22, 18] += np.uint16(3000)
    frame = assert_same_frame(image, state)
    assert frame.remeasured and frame.centroids is not None and frame.found.all()
    hit = np.argmin(np.hypot(frame.centroids["x"] - 15.3, frame.centroids["y"] - 20.7))
    assert frame.centroids["n_masked"][hit] >= 1 and frame.centroids["flags"][hit] & CentroidFlag.MASKED
    assert abs(frame.centroids["x"][hit] - 15.3) < 0.1 and abs(frame.centroids["y"][hit] - 20.7) < 0.1


def test_new_light_outside_the_windows() -> None:
    """A bright star appearing far from the windows raises cells; seen in the frame before too, a search."""
    shape = (96, 96)
    state = acquired(render(STARS, seed=0, shape=shape))
    entering = [*STARS, (85.0, 85.0, 30000.0)]
    first = assert_same_frame(render(entering, seed=1, shape=shape), state)
    assert first.risen is not None and first.risen.tolist() == [[False] * 6] * 5 + [[False] * 5 + [True]]
    assert not first.search
    assert assert_same_frame(render(entering, seed=2, shape=shape), state, before=first.risen).search


def test_a_frame_of_another_size_is_searched() -> None:
    state = acquired(render(STARS, seed=0))
    frame = assert_same_frame(render(STARS, seed=1, shape=(80, 72)), state)
    assert frame.search and frame.risen is None


def test_hot_pixels_missing_and_no_robust_pass() -> None:
    """A float frame with missing pixels (a hot-pixel map's NaN), measured without the robust pass."""
    state = acquired(render(STARS, seed=0))
    image = render(STARS, seed=1).astype(np.float32)
    image[21, 16] = image[5, 5] = image[44, 40] = np.nan
    frame = assert_same_frame(image, state, fit=replace(FIT, robust=False), saturation=65535.0)
    assert frame.centroids is not None
    assert frame.centroids["n_masked"].tolist() == [1, 1, 0]


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**16), n=st.integers(1, 8), vx=st.floats(-3, 3), vy=st.floats(-3, 3),
       rows=st.integers(24, 70), cols=st.integers(24, 70))
def test_random_fields_and_motions(seed: int, n: int, vx: float, vy: float, rows: int, cols: int) -> None:
    """Random fields drifting up to 3 px a frame, tracked for four frames: each frame's compiled result is the
    numpy reference's, from the same state (the reference's)."""
    rng = np.random.default_rng(seed)
    base = [(float(x), float(y), float(f)) for x, y, f in
            zip(rng.uniform(-2, cols + 2, n), rng.uniform(-2, rows + 2, n), 10 ** rng.uniform(3, 5, n))]
    frames = [render([(x + vx * k, y + vy * k, f) for x, y, f in base], seed=seed + k, shape=(rows, cols))
              for k in range(5)]
    state, before = acquired(frames[0]), None
    for image in frames[1:]:
        got, _ = same_frame(image, state, before)
        state, before = (got.state, got.risen) if got.state is not None else (acquired(image), None)


def test_a_frame_narrower_than_a_cell_is_tracked_without_the_light_check() -> None:
    """No whole cell in the frame: the acquisition keeps no cells, and the tracked frames go on without them."""
    stars, shape = [(7.3, 12.7, 6000.0), (6.6, 30.2, 8000.0)], (44, SETTINGS.cell - 2)
    state = acquired(render(stars, seed=0, shape=shape))
    assert state.cells is not None and state.cells.size == 0 and state.x.size == 2
    frame = assert_same_frame(render(stars, seed=1, shape=shape), state)
    assert not frame.search and frame.centroids is not None and frame.centroids.size == 2


def test_the_cell_means_of_a_float_frame_with_missing_pixels() -> None:
    """The light check's cells of a float frame: missing pixels at the median of the others, as numpy's."""
    state = acquired(render(STARS, seed=0))
    image = render(STARS, seed=1).astype(np.float64) + 0.25
    image[3, 3] = np.inf
    image[40, 17] = np.nan
    frame = track_frame(image, state, SETTINGS, None, HALF, FIT)
    np.testing.assert_array_equal(frame.risen, track_frame_vectorised(image, state, SETTINGS, None, HALF).risen)
    assert cell_means(image, SETTINGS.cell).shape == state.cells.shape


@pytest.mark.parametrize("dtype", ["u1", ">u2", "f4", "f8", "i4"])
def test_frames_of_other_types(dtype: str) -> None:
    stars = [(15.3, 20.7, 1500.0), (40.6, 44.2, 2000.0)]
    image = (render(stars, seed=1) // (8 if dtype == "u1" else 1)).astype(dtype)
    state = acquired((render(stars, seed=0) // (8 if dtype == "u1" else 1)).astype(dtype))
    assert_same_frame(image, state)
