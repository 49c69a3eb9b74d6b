"""The sky as the judge: one camera fitted to many frames, each method's catalogue residual on the stars every method
identified with its bootstrap confidence, and the rule naming the method to trust from whichever evidence a log has.

Known answers: a fake catalogue projected through known cameras (exact positions give a zero residual and the
camera back; positions with a known noise give that noise), and methods of known noise."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from starlog.attitude.camera import camera_for_image, fit_cameras_shared
from starlog.attitude.rotation import attitude_from_radec_roll, small_rotation
from starlog.attitude.sky_evidence import IdentifiedFrame, sky_evidence
from starlog.centroiding.evidence import MIN_SKY_STARS, EvidenceAccumulator, FrameEvidence, bootstrap_rms, trust

SHAPE = (600, 800)


def _sky(rng: np.random.Generator, n: int = 4000) -> np.ndarray:
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1)[:, None]


def _cameras(frames: int, *, focal: float = 2000.0, k: float = 0.01):
    base = replace(camera_for_image(SHAPE, focal), k=k)
    return [replace(base, rotation=attitude_from_radec_roll(40.0 * j, 10.0 * j - 20.0, 15.0 * j)) for j in range(frames)]


def _seen(camera, vectors: np.ndarray, margin: float = 10.0):
    """Rows of the catalogue inside the frame, and their exact pixels."""
    x, y, front = camera.project(vectors)
    rows = np.flatnonzero(front & (x > margin) & (x < SHAPE[1] - margin) & (y > margin) & (y < SHAPE[0] - margin))
    return rows, x[rows], y[rows]


def test_one_camera_fitted_to_many_frames_recovers_the_shared_focal_length_and_distortion():
    rng = np.random.default_rng(1)
    vectors = _sky(rng)
    truth = _cameras(5)
    starts, vs, xs, ys = [], [], [], []
    for cam in truth:
        rows, x, y = _seen(cam, vectors)
        vs.append(vectors[rows])
        xs.append(x)
        ys.append(y)
        # each frame solved on its own: attitude off by ~1 px, focal length and distortion off
        starts.append(replace(cam, rotation=small_rotation(rng.normal(0, 5e-4, 3)) @ cam.rotation, focal=2010.0, k=0.0))
    fitted = fit_cameras_shared(starts, vs, xs, ys)
    assert fitted[0].focal == pytest.approx(2000.0, rel=1e-6) and fitted[0].k == pytest.approx(0.01, abs=1e-6)
    assert len({c.focal for c in fitted}) == 1
    for cam, v, x, y in zip(fitted, vs, xs, ys):
        px, py, _ = cam.project(v)
        assert np.max(np.hypot(px - x, py - y)) < 1e-5


def _identified(truth, vectors, rng, noise: dict[str, float], drop: float = 0.0):
    """Per method, the frames' identified stars: exact positions plus that method's Gaussian noise (px per axis);
    ``drop``: the share of stars each method misses, at random."""
    out = {m: [] for m in noise}
    for j, cam in enumerate(truth):
        rows, x, y = _seen(cam, vectors)
        solved = replace(cam, rotation=small_rotation([1e-4, 0, 0]) @ cam.rotation)
        for m, s in noise.items():
            keep = rng.random(rows.size) >= drop
            out[m].append(IdentifiedFrame(j, solved, rows[keep], x[keep] + rng.normal(0, s, keep.sum()),
                                          y[keep] + rng.normal(0, s, keep.sum())))
    return out


def test_each_method_s_catalogue_residual_is_its_noise_on_the_stars_all_identified():
    rng = np.random.default_rng(2)
    vectors = _sky(rng)
    truth = _cameras(6)
    evidence = sky_evidence(_identified(truth, vectors, rng, {"A": 0.05, "B": 0.10}, drop=0.2), vectors,
                            np.zeros(vectors.shape[0]), isolation_px=0.0)
    a, b = evidence["A"], evidence["B"]
    assert a["stars"] == b["stars"] > 100 and a["frames"] == 6
    # the per-frame attitudes and the shared camera absorb a few of the degrees of freedom
    assert a["residual_px"] == pytest.approx(0.05, rel=0.1) and b["residual_px"] == pytest.approx(0.10, rel=0.1)
    assert a["interval_px"][0] < a["residual_px"] < a["interval_px"][1] < b["interval_px"][0]
    assert a["p_best"] == 1.0 and b["p_best"] == 0.0
    assert b["ratio_to_best"] == pytest.approx(2.0, rel=0.1) and b["ratio_interval"][0] > 1.5
    assert a["focal_px"] == pytest.approx(2000.0, rel=1e-3)


def test_the_sky_judges_on_the_brighter_half_of_the_common_stars():
    """Method B is exact on the catalogue's brighter stars and far off on the fainter ones, A a little off on all:
    the faint ones, noise-limited for every method, are not what the sky judges."""
    rng = np.random.default_rng(6)
    vectors = _sky(rng)
    frames = _identified(_cameras(6), vectors, rng, {"A": 0.05, "B": 0.0})
    limit = np.median(np.concatenate([f.catalogue for f in frames["A"]]))  # half the field's stars bright
    magnitudes = np.where(np.arange(vectors.shape[0]) <= limit, 3.0, 7.0)
    for b in frames["B"]:
        faint = magnitudes[b.catalogue] > 5.0
        b.x[faint] += rng.normal(0, 0.3, faint.sum())
    judged = sky_evidence(frames, vectors, magnitudes, isolation_px=0.0)
    every = sky_evidence(frames, vectors, magnitudes, isolation_px=0.0, brighter=1.0)
    assert judged["B"]["residual_px"] < 0.2 * judged["A"]["residual_px"]
    assert every["A"]["residual_px"] < 0.7 * every["B"]["residual_px"]
    assert judged["A"]["matches"] == pytest.approx(every["A"]["matches"] / 2, rel=0.1)


def test_a_catalogue_star_with_a_close_neighbour_is_left_out():
    rng = np.random.default_rng(3)
    vectors = _sky(rng)
    truth = _cameras(2)
    rows, _, _ = _seen(truth[0], vectors)
    # a companion 2 px from one of the field's stars
    twin = vectors[rows[0]] + 2.0 / 2000.0 * np.cross(vectors[rows[0]], [0.0, 0.0, 1.0])
    vectors = np.vstack([vectors, twin / np.linalg.norm(twin)])
    frames = _identified(truth, vectors, rng, {"A": 0.05, "B": 0.05})
    flat = np.zeros(vectors.shape[0])
    with_pair = sky_evidence(frames, vectors, flat, isolation_px=0.0)["A"]["stars"]
    isolated = sky_evidence(frames, vectors, flat, isolation_px=6.0)["A"]["stars"]
    assert isolated == with_pair - 2


def test_no_common_star_gives_no_figure():
    rng = np.random.default_rng(4)
    vectors = _sky(rng)
    frames = _identified(_cameras(1), vectors, rng, {"A": 0.05})
    frames["B"] = []
    evidence = sky_evidence(frames, vectors, np.zeros(vectors.shape[0]))
    assert evidence["A"]["residual_px"] is None and evidence["B"]["stars"] == 0


def test_the_bootstrap_resamples_stars_with_all_their_residuals():
    # star 0 holds a large error in each of its 50 frames: drawing it or not is what moves the figure
    sums = np.array([[50 * 2 * 1.0**2] + [2 * 0.1**2] * 99])
    counts = np.array([50.0] + [1.0] * 99)
    draws = bootstrap_rms(sums, counts, draws=500, seed=3)
    lo, hi = np.percentile(draws[:, 0], [2.5, 97.5])
    assert lo < 0.3 < np.sqrt(sums.sum() / (2 * counts.sum())) < hi
    assert np.array_equal(draws, bootstrap_rms(sums, counts, draws=500, seed=3))


def _noise(pairs: int, values: dict[str, float]):
    return {m: {"pairs": pairs, "noise_px": v, "interval_px": [0.9 * v, 1.1 * v], "p_best": 0.9 if v == min(values.values())
                else 0.1, "median_sigma_px": v, "stars": pairs} for m, v in values.items()}


def _sky_figures(stars: int, values: dict[str, float]):
    return {m: {"stars": stars, "frames": 4, "residual_px": v, "interval_px": [0.9 * v, 1.1 * v], "p_best": 0.5,
                "ratio_to_best": v / min(values.values()), "ratio_interval": [0.95, 1.2]} for m, v in values.items()}


def test_the_sky_names_the_method_when_it_has_enough_stars_and_the_noise_is_shown_beside_it():
    decision = trust(_noise(500, {"A": 0.01, "B": 0.02}), _sky_figures(MIN_SKY_STARS, {"A": 0.08, "B": 0.06}))
    assert decision["method"] == "B" and decision["evidence"] == "sky" and decision["figure_px"] == 0.06
    assert decision["interval_px"] == [pytest.approx(0.054), pytest.approx(0.066)]
    assert "catalogue residual" in decision["reason"] and "frame-to-frame noise names A" in decision["reason"]


def test_without_enough_sky_the_frame_to_frame_noise_names_it_saying_why():
    decision = trust(_noise(500, {"A": 0.01, "B": 0.02}), _sky_figures(MIN_SKY_STARS - 1, {"A": 0.08, "B": 0.06}))
    assert decision["method"] == "A" and decision["evidence"] == "frame-to-frame"
    assert f"the sky needs {MIN_SKY_STARS}" in decision["reason"]
    missing = trust(_noise(500, {"A": 0.01, "B": 0.02}), None, sky_missing="cedar-solve is not installed")
    assert missing["method"] == "A" and "no catalogue evidence: cedar-solve is not installed" in missing["reason"]


def test_with_neither_no_method_is_named_and_both_reasons_are_given():
    decision = trust(_noise(3, {"A": 0.01, "B": 0.02}), None, sky_missing="the frames did not plate-solve")
    assert decision["method"] is None and decision["evidence"] is None
    assert "consecutive frames" in decision["reason"] and "did not plate-solve" in decision["reason"]


def test_the_frame_to_frame_noise_has_a_bootstrap_interval_over_the_stars_followed():
    rng = np.random.default_rng(5)
    xs, ys = rng.uniform(0, 500, 40), rng.uniform(0, 500, 40)
    acc = EvidenceAccumulator(["A", "B"])
    for _ in range(30):
        shift = rng.normal(0, 0.1, 2)  # the platform's motion: every star within the match radius of its last place
        x = np.stack([xs + shift[0] + rng.normal(0, s, 40) for s in (0.02, 0.04)])
        y = np.stack([ys + shift[1] + rng.normal(0, s, 40) for s in (0.02, 0.04)])
        acc.add(FrameEvidence(x, y, np.full((2, 40), 0.03)))
    result = acc.result()
    a, b = result["A"], result["B"]
    assert a["noise_px"] == pytest.approx(0.02, rel=0.1) and b["noise_px"] == pytest.approx(0.04, rel=0.1)
    assert a["interval_px"][0] < 0.02 < a["interval_px"][1] < b["interval_px"][0]
    assert a["p_best"] == 1.0
    assert acc.next_star == 40  # every star followed from the first pair of frames on
