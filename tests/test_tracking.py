"""Tracking mode (:mod:`starlog.centroiding.tracking`, :class:`starlog.stages.centroid.frames.TrackedFrames`) on
hand-checkable sequences of small frames: where each star is is known, and so is when the whole frame must be
searched again."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.special import erf

from starlog.centroiding import CentroidFlag, CentroidMethod
from starlog.centroiding.psf_width import window_half_size
from starlog.centroiding.tracking import TrackingSettings, is_image_sequence
from starlog.errors import InvalidParameterError
from starlog.io import LogReader
from starlog.pipeline import PipelineConfig, run_pipeline
from starlog.stages import ingest_folder, simulate_log
# private module: the per-frame work of the centroid stage, tested without a log
from starlog.stages.centroid.frames import FrameExtractor
from starlog.stages.centroid import centroid_log
from tests.helpers import small_config

PSF = 1.2
SIZE = 64
METHODS = (CentroidMethod.GAUSSFIT, CentroidMethod.MOMENT)


def render(stars: list[tuple[float, float, float]], *, seed: int, size: int = SIZE) -> np.ndarray:
    """A frame of pixel-integrated Gaussian stars ``(x, y, flux)`` on a sky of 100 DN with 3 DN of noise."""
    edges = np.arange(size + 1) - 0.5
    image = np.full((size, size), 100.0)
    for x, y, flux in stars:
        gx = np.diff(0.5 * erf((edges - x) / (np.sqrt(2) * PSF)))
        gy = np.diff(0.5 * erf((edges - y) / (np.sqrt(2) * PSF)))
        image += flux * np.outer(gy, gx)
    image += np.random.default_rng(seed).normal(0.0, 3.0, image.shape)
    return np.clip(np.rint(image), 0, 65535).astype(np.uint16)


def extractor(acquire_every: int = 10) -> FrameExtractor:
    return FrameExtractor(methods=METHODS, gain=1.0, read_noise=None, options={"psf_sigma": PSF},
                          tracking=TrackingSettings(acquire_every=acquire_every))


def run(frames: list[np.ndarray], acquire_every: int = 10) -> list[tuple[np.ndarray, bool]]:
    """Each frame's GAUSSFIT centroids in tracking mode, and whether the frame was searched in full."""
    block = extractor(acquire_every).block()
    out = []
    for image in frames:
        _, centroids, acquired = block.measure(image)
        out.append((centroids[CentroidMethod.GAUSSFIT], acquired))
    return out


def off_truth(rows: np.ndarray, truth: list[tuple[float, float, float]]) -> float:
    """The largest distance from a centroid to the nearest true star, px (0 without centroids)."""
    if rows.size == 0:
        return 0.0
    xy = np.array([(x, y) for x, y, _ in truth])
    return float(max(np.min(np.hypot(xy[:, 0] - r["x"], xy[:, 1] - r["y"])) for r in rows))


STATIC = [(15.3, 20.7, 6000.0), (40.6, 44.2, 9000.0), (48.1, 12.9, 4000.0)]


def test_static_field_tracking_agrees_with_full_mode() -> None:
    """Acquisitions are full mode itself (the same bytes); tracked frames measure every star with the full
    mode's own code, from a coarse position found in the window: the same centroids to well under the noise."""
    frames = [render(STATIC, seed=k) for k in range(12)]
    full = extractor(1)
    tracked = run(frames)
    assert [acquired for _, acquired in tracked] == [True] + [False] * 9 + [True, False]
    for image, (rows, acquired) in zip(frames, tracked):
        _, reference = full.centroids(image)
        ref = reference[CentroidMethod.GAUSSFIT]
        assert rows.size == ref.size == 3
        order = [int(np.argmin(np.hypot(ref["x"] - r["x"], ref["y"] - r["y"]))) for r in rows]
        if acquired:
            assert rows.tobytes() == ref.tobytes()
        else:
            assert np.all(rows["flags"] & CentroidFlag.TRACKED)
            np.testing.assert_allclose(rows["x"], ref["x"][order], atol=2e-3)
            np.testing.assert_allclose(rows["y"], ref["y"][order], atol=2e-3)


def test_the_same_detection_gives_the_same_numbers_in_both_modes() -> None:
    """Given the same detection rows, the tracked measurement is the full mode's to the last bit."""
    image = render(STATIC, seed=1)
    ex = extractor()
    detections, full = ex.centroids(image)
    measured = ex.measure(*ex.prepared(image), detections)
    for method in METHODS:
        assert measured[method].tobytes() == full[method].tobytes()


def test_windows_follow_a_star_drifting_across_them() -> None:
    """A star drifting 3 px a frame leaves any fixed window within two frames; the predicted window follows it
    without a new search."""
    truth = [[(10.0 + 3.0 * k, 30.0 + 0.5 * k, 8000.0), (32.0, 10.0, 5000.0)] for k in range(14)]
    tracked = run([render(t, seed=k) for k, t in enumerate(truth)], acquire_every=100)
    assert [acquired for _, acquired in tracked] == [True] + [False] * 13
    for (rows, _), stars in zip(tracked, truth):
        assert rows.size == 2
        assert off_truth(rows, stars) < 0.1


def test_a_brighter_neighbour_in_the_search_window_is_not_taken_for_the_star() -> None:
    """A faint star 7 px from a bright one (inside its search window): each window keeps its own star."""
    pair = [(30.0, 30.0, 20000.0), (35.2, 34.9, 4000.0)]
    tracked = run([render(pair, seed=k) for k in range(8)], acquire_every=100)
    assert [acquired for _, acquired in tracked] == [True] + [False] * 7
    assert all(rows.size == 2 and off_truth(rows, pair) < 0.1 for rows, _ in tracked)


def test_a_sudden_jump_is_searched_again() -> None:
    truth = [[(x + (20.0 if k >= 5 else 0.0), y, f) for x, y, f in STATIC[:2]] for k in range(8)]
    tracked = run([render(t, seed=k) for k, t in enumerate(truth)], acquire_every=100)
    assert [acquired for _, acquired in tracked] == [True, False, False, False, False, True, False, False]
    for (rows, _), stars in zip(tracked, truth):
        assert rows.size == 2
        assert off_truth(rows, stars) < 0.1


def test_a_star_entering_and_leaving_the_field() -> None:
    """A bright star entering is found one frame after full mode finds it (light outside the windows in two
    frames in a row: not a cosmic ray); leaving, it is dropped when the search at the edge does not find it; the
    static star is measured in every frame."""
    truth = [[(-6.0 + 4.0 * k, 30.0, 8000.0), (20.0, 50.0, 5000.0)] for k in range(20)]
    frames = [render(t, seed=k) for k, t in enumerate(truth)]
    tracked = run(frames, acquire_every=8)
    full = extractor(1)
    counts = [full.centroids(image)[1][CentroidMethod.GAUSSFIT].size for image in frames]
    for k, (rows, _) in enumerate(tracked):
        assert off_truth(rows, truth[k]) < 0.15
        assert np.any(np.hypot(rows["x"] - 20.0, rows["y"] - 50.0) < 0.2)
        assert rows.size in (counts[k], counts[k - 1]), f"frame {k}: tracking {rows.size} stars, full {counts[k]}"
    entered = counts.index(2)
    assert tracked[entered][0].size == 1 and tracked[entered + 1][0].size == 2


def test_a_cosmic_ray_calls_for_no_search() -> None:
    """A cosmic-ray hit outside the windows lights a cell for one frame: no search; the same light in the next
    frame (a star) calls for one."""
    frames = [render(STATIC, seed=k) for k in range(6)]
    frames[2][52:54, 3] = 3000  # the cells of rows 48-63, columns 0-15 are far from every star
    frames[4][58, 8:10] = 3000
    frames[5][58, 8:10] = 3000
    assert [acquired for _, acquired in run(frames, acquire_every=100)] == [True, False, False, False, False, True]


def test_two_stars_crossing() -> None:
    """Two stars crossing: while their windows would overlap the frame is searched in full (one blended star,
    as full mode sees it); once the blend comes apart (its flux halves) it is searched again, and both stars are
    tracked on. Every frame gives full mode's stars."""
    truth = [[(8.0 + 2.5 * k, 30.0, 7000.0), (56.0 - 2.5 * k, 31.5, 7000.0)] for k in range(20)]
    frames = [render(t, seed=k) for k, t in enumerate(truth)]
    tracked = run(frames, acquire_every=100)
    full = extractor(1)
    for k, ((rows, _), image) in enumerate(zip(tracked, frames)):
        reference = full.centroids(image)[1][CentroidMethod.GAUSSFIT]
        assert rows.size == reference.size, f"frame {k}"
        assert all(np.min(np.hypot(reference["x"] - r["x"], reference["y"] - r["y"])) < 0.05 for r in rows)
    acquired = [k for k, (_, a) in enumerate(tracked) if a]
    assert acquired[0] == 0 and 2 <= len(acquired) <= 4 and not tracked[-1][1]


@pytest.mark.parametrize("odd", ["blank", "saturated"])
def test_a_blank_or_saturated_frame(odd: str) -> None:
    """The odd frame loses every star (searched in full, nothing found); the next frame finds them again."""
    frames = [render(STATIC, seed=k) for k in range(8)]
    frames[4] = render([], seed=4) if odd == "blank" else np.full((SIZE, SIZE), 65535, np.uint16)
    tracked = run(frames, acquire_every=100)
    assert tracked[4][1] and tracked[4][0].size == 0
    assert tracked[5][1] and tracked[5][0].size == 3
    assert [acquired for _, acquired in tracked[6:]] == [False, False]
    assert all(off_truth(rows, STATIC) < 0.1 for rows, _ in tracked)


def test_auto_mode_tells_a_sequence_from_unrelated_images() -> None:
    rng = np.random.default_rng(0)
    field = rng.uniform(0, 500, (30, 2))
    sequence = [(field[:, 0] + 0.7 * k, field[:, 1] - 0.3 * k) for k in range(6)]
    stills = [tuple(rng.uniform(0, 500, (2, 30))) for _ in range(6)]
    assert is_image_sequence(sequence, 5)[0]
    assert not is_image_sequence(stills, 5)[0]
    assert not is_image_sequence(sequence[:2], 5)[0]  # one pair cannot tell


@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(vx=st.floats(-4, 4), vy=st.floats(-4, 4), ax=st.floats(-0.3, 0.3), seed=st.integers(0, 1000))
def test_every_star_is_measured_in_every_frame_under_platform_motion(vx: float, vy: float, ax: float,
                                                                      seed: int) -> None:
    """Platform motion of up to 4 px a frame, slowly accelerating: every star away from the frame's edge is
    measured in every frame, within 0.1 px of the truth (one whose window the edge cuts is flagged BORDER, as in
    full mode, and its position there is not the test's)."""
    base = [(22.0, 22.0, 8000.0), (42.0, 40.0, 6000.0)]
    truth = [[(x + vx * k + ax * k * k / 2, y + vy * k, f) for x, y, f in base] for k in range(6)]
    tracked = run([render(t, seed=seed + k) for k, t in enumerate(truth)], acquire_every=100)
    for (rows, _), stars in zip(tracked, truth):
        reach = window_half_size(PSF) + 1  # nearer the edge a star's window is cut: flagged BORDER in both modes
        inside = [s for s in stars if reach <= min(s[0], s[1]) and max(s[0], s[1]) <= SIZE - 1 - reach]
        clear = rows[(rows["flags"] & CentroidFlag.BORDER) == 0]
        assert clear.size >= len(inside)
        assert off_truth(clear, stars) < 0.1


def test_tracking_stage_gives_the_same_bytes_for_any_workers(tmp_path: Path) -> None:
    sim = tmp_path / "sim.mcap"
    simulate_log(small_config(width=80, height=64, n_stars=4, n_frames=90, margin=10.0), sim)
    for workers in (1, 2):
        summary = centroid_log(sim, tmp_path / f"w{workers}.mcap", methods="GAUSSFIT", mode="tracking",
                               acquire_every=20, workers=workers)
        assert summary.mode == "tracking" and 5 <= summary.acquisitions < 90
    assert (tmp_path / "w1.mcap").read_bytes() == (tmp_path / "w2.mcap").read_bytes()
    with LogReader(tmp_path / "w1.mcap") as log:
        (record,) = [p for p in log.provenance() if p.stage == "centroid"]
        assert record.parameters["mode"] == "tracking"
        assert record.parameters["acquisitions"] == summary.acquisitions
    centroid_log(sim, tmp_path / "full.mcap", methods="GAUSSFIT", mode="full")
    with LogReader(tmp_path / "full.mcap") as log:
        (record,) = [p for p in log.provenance() if p.stage == "centroid"]
        assert record.parameters["mode"] == "full" and record.parameters["acquisitions"] == 90


def test_the_run_config_takes_the_mode(tmp_path: Path) -> None:
    sim = tmp_path / "sim.mcap"
    simulate_log(small_config(n_frames=12), sim)
    config = PipelineConfig.from_dict({"centroid": {"methods": ["GAUSSFIT"], "mode": "tracking", "acquire_every": 5}})
    run_pipeline(sim, tmp_path / "out.mcap", config)
    with LogReader(tmp_path / "out.mcap") as log:
        (record,) = [p for p in log.provenance() if p.stage == "centroid"]
    assert record.parameters["mode"] == "tracking" and record.parameters["tracking"]["acquire_every"] == 5
    assert record.parameters["acquisitions"] == 3  # frames 0, 5 and 10
    with pytest.raises(InvalidParameterError, match="mode must be one of"):
        run_pipeline(sim, tmp_path / "bad.mcap", PipelineConfig.from_dict({"centroid": {"mode": "fast"}}))


def test_auto_mode_searches_every_frame_of_a_folder_of_unrelated_stills(tmp_path: Path) -> None:
    import cv2

    folder = tmp_path / "stills"
    folder.mkdir()
    rng = np.random.default_rng(5)
    for k in range(6):
        stars = [(float(x), float(y), 6000.0) for x, y in rng.uniform(8, SIZE - 8, (4, 2))]
        cv2.imwrite(str(folder / f"still{k}.png"), render(stars, seed=k))
    ingest_folder(folder, tmp_path / "stills.mcap", fps=10.0)
    summary = centroid_log(tmp_path / "stills.mcap", tmp_path / "cen.mcap", methods="GAUSSFIT")
    assert summary.mode == "full" and summary.acquisitions == 6
    with LogReader(tmp_path / "cen.mcap") as log:
        (record,) = [p for p in log.provenance() if p.stage == "centroid"]
    assert record.parameters["mode_reason"].startswith("auto: 0 of 5 pairs")


def test_an_acquisition_tracks_the_stars_not_the_detections_only_an_artefact_made() -> None:
    """A soft-edged cosmic-ray hit in the acquired frame is detected, flagged ARTEFACT and has no centroid:
    the tracked stars are the measured ones, each at its own centroid."""
    stars = [(20.3, 18.7, 20000.0), (44.6, 40.2, 15000.0)]
    first = render(stars, seed=1)
    first[50:52, 10:13] += np.uint16(1500)
    block = extractor().block()
    detections, centroids, acquired = block.measure(first)
    assert acquired and np.count_nonzero(detections["flags"] & CentroidFlag.ARTEFACT) == 1
    rows = centroids[CentroidMethod.GAUSSFIT]
    assert rows.size == 2
    np.testing.assert_array_equal(block.state.x, rows["x"])
    np.testing.assert_array_equal(block.state.reference["star"], rows["star"])
    tracked, _ = run([first, render(stars, seed=2)])[1]
    assert tracked.size == 2 and off_truth(tracked, stars) < 0.1
