"""StarTracker: association, gating, re-acquisition, determinism, statistics."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose, assert_array_equal

from starlog.errors import InvalidInputError, InvalidParameterError
from starlog.tracking import (
    TRACK_DTYPE,
    TRACK_STATS_DTYPE,
    MotionModel,
    NoTrackError,
    StarTracker,
    TrackerConfig,
    track_centroids,
)
from starlog.tracking.models import MotionModelConfig
from starlog.tracking.state import FrameRows, TrackState

PERIOD_NS = 3_333_333  # 300 Hz
# well separated stars (> 50 px apart), row-major order is the order below
STARS = np.array([[100.2, 50.7], [400.9, 60.1], [250.4, 300.3], [80.6, 420.8]])
FLUX = np.array([2e4, 9e4, 5e4, 1e4])
SIGMA = np.array([0.08, 0.05, 0.06, 0.12])


def frames(rng: np.random.Generator, n_frames: int, jitter: float = 0.03):
    """Per-frame (x, y, sigma, flux) of the static field with common platform jitter."""
    out = []
    for _ in range(n_frames):
        shake = rng.normal(0, jitter, 2)
        pos = STARS + shake + rng.normal(size=STARS.shape) * SIGMA[:, None]
        out.append([pos[:, 0], pos[:, 1], SIGMA.copy(), FLUX * rng.uniform(0.95, 1.05, 4)])
    return out


def run(tracker: StarTracker, data, start: int = 0):
    return [tracker.update((start + k) * PERIOD_NS, *f) for k, f in enumerate(data)]


def star_of(rows: np.ndarray) -> np.ndarray:
    """Index into STARS of each row (nearest star to the filtered position)."""
    d = np.hypot(rows["x"][:, None] - STARS[:, 0], rows["y"][:, None] - STARS[:, 1])
    return d.argmin(axis=1)


def test_birth_ids_in_row_major_order_and_dtype() -> None:
    rng = np.random.default_rng(0)
    x, y, s, f = frames(rng, 1)[0]
    order = rng.permutation(4)
    rows = StarTracker().update(0, x[order], y[order], s[order], f[order])
    assert rows.dtype == TRACK_DTYPE
    assert_array_equal(rows["track"], [0, 1, 2, 3])
    assert_array_equal(star_of(rows), [0, 1, 2, 3])  # ascending y, then x
    assert rows["measured"].all() and not rows["gated"].any()
    assert_array_equal(rows["age"], 0)
    assert_array_equal(rows["hits"], 1)
    assert not rows["confirmed"].any()
    assert_allclose(rows["meas_sigma"], SIGMA, rtol=0, atol=0)


@pytest.mark.parametrize("model", list(MotionModel))
def test_static_field_tracks_keep_ids(model: MotionModel) -> None:
    rng = np.random.default_rng(1)
    outs = run(StarTracker(model=model), frames(rng, 200))
    for rows in outs:
        assert_array_equal(rows["track"], [0, 1, 2, 3])
        assert_array_equal(star_of(rows), [0, 1, 2, 3])
        for name in TRACK_DTYPE.names:
            if rows.dtype[name].kind == "f":
                assert np.isfinite(rows[name]).all()
    last = outs[-1]
    assert last["confirmed"].all() and last["measured"].all()
    assert_array_equal(last["age"], 199)
    assert (last["cov_xx"] > 0).all() and (last["cov_yy"] > 0).all()
    if model in (MotionModel.STATIC, MotionModel.RANDOM_WALK):
        assert_array_equal(last["vx"], 0.0)


def test_deterministic_ids_independent_of_centroid_order() -> None:
    data = frames(np.random.default_rng(2), 60)
    a = run(StarTracker(), data)
    rng = np.random.default_rng(99)
    shuffled = []
    for x, y, s, f in data:
        p = rng.permutation(4)
        shuffled.append([x[p], y[p], s[p], f[p]])
    b = run(StarTracker(), shuffled)
    for ra, rb in zip(a, b, strict=True):
        assert_array_equal(ra, rb)


def test_injected_outliers_are_gated() -> None:
    rng = np.random.default_rng(3)
    data = frames(rng, 80)
    hit = {30: (1, 1.2), 31: (2, -0.9), 55: (1, 2.0)}  # frame: (star, x offset px)
    for k, (star, dx) in hit.items():
        data[k][0] = data[k][0].copy()
        data[k][0][star] += dx
    outs = run(StarTracker(), data)
    for k, rows in enumerate(outs):
        assert_array_equal(rows["track"], [0, 1, 2, 3])  # no spurious track
        expected = np.zeros(4, dtype=bool)
        if k in hit:
            expected[hit[k][0]] = True
        assert_array_equal(rows["gated"], expected)
        assert_array_equal(rows["measured"], ~expected)
    for k, (star, _) in hit.items():
        row = outs[k][star]
        assert row["nis"] > 18.42
        assert row["missed"] == 1
        assert row["meas_x"] == data[k][0][star]
        assert abs(row["x"] - STARS[star, 0]) < 0.1  # not pulled by the outlier
    assert_array_equal(outs[56]["missed"], 0)


def test_star_missing_five_frames_keeps_id() -> None:
    rng = np.random.default_rng(4)
    data = frames(rng, 60)
    gone = range(20, 25)
    for k in gone:
        data[k] = [a[[0, 1, 3]] for a in data[k]]  # star 2 hidden
    outs = run(StarTracker(), data)
    for k in gone:
        row = outs[k][outs[k]["track"] == 2][0]
        assert not row["measured"] and not row["gated"]
        assert row["missed"] == k - 19
        assert row["flux"] == 0.0 and row["meas_x"] == 0.0 and row["nis"] == 0.0
    back = outs[25]
    assert_array_equal(back["track"], [0, 1, 2, 3])
    assert back["measured"].all() and back["missed"].max() == 0
    assert_array_equal(star_of(outs[-1]), [0, 1, 2, 3])


def test_track_lost_after_max_missed() -> None:
    rng = np.random.default_rng(5)
    data = frames(rng, 40)
    for k in range(10, 14):
        data[k] = [a[[0, 1, 3]] for a in data[k]]
    outs = run(StarTracker(max_missed=2), data)
    assert 2 in outs[11]["track"]  # missed 2 <= max_missed
    assert 2 not in outs[12]["track"]  # third miss: lost
    assert_array_equal(outs[14]["track"], [0, 1, 3, 4])  # back with a new id
    assert_array_equal(star_of(outs[14]), [0, 1, 3, 2])


def test_empty_frame_does_not_break_tracks() -> None:
    rng = np.random.default_rng(6)
    data = frames(rng, 20)
    empty = [np.zeros(0)] * 4
    data[10] = empty
    data[11] = [[], [], [], []]
    outs = run(StarTracker(), data)
    assert_array_equal(outs[11]["track"], [0, 1, 2, 3])
    assert not outs[11]["measured"].any()
    assert_array_equal(outs[11]["missed"], 2)
    assert outs[12]["measured"].all()
    assert_array_equal(outs[12]["track"], [0, 1, 2, 3])
    assert StarTracker().update(0, [], [], [], []).shape == (0,)


@pytest.mark.parametrize("model", [MotionModel.CONSTANT_VELOCITY, MotionModel.POLYNOMIAL_TREND])
def test_two_moving_stars_never_swap(model: MotionModel) -> None:
    """Two stars 8 px apart drifting together at 30 px/s with 0.15 px noise."""
    rng = np.random.default_rng(7)
    tracker = StarTracker(model=model)
    for k in range(300):
        t = k / 300
        truth = np.array([[200.0 + 30 * t, 200.0], [200.0 + 30 * t, 208.0]])
        pos = truth + rng.normal(0, 0.15, truth.shape)
        p = rng.permutation(2)
        rows = tracker.update(k * PERIOD_NS, pos[p, 0], pos[p, 1], [0.15, 0.15], [1e4, 1e4])
        assert_array_equal(rows["track"], [0, 1])
        assert abs(rows["y"][0] - 200.0) < 1 and abs(rows["y"][1] - 208.0) < 1


def test_spurious_single_frame_detection_is_dropped() -> None:
    rng = np.random.default_rng(8)
    data = frames(rng, 20)
    data[5] = [np.append(a, v) for a, v in zip(data[5], [700.0, 700.0, 0.05, 1e7], strict=True)]
    tracker = StarTracker()
    outs = run(tracker, data)
    assert_array_equal(outs[5]["track"], [0, 1, 2, 3, 4])
    assert not outs[5]["confirmed"][4]
    assert_array_equal(outs[6]["track"], [0, 1, 2, 3])
    stats = tracker.track_stats()
    assert stats.dtype == TRACK_STATS_DTYPE
    assert_array_equal(stats["track"], [0, 1, 2, 3, 4])
    assert_array_equal(stats["alive"], [True, True, True, True, False])
    assert tracker.brightest_track() == 1  # the 1e7 transient is never confirmed


def test_brightest_track_and_stats() -> None:
    rng = np.random.default_rng(9)
    tracker = StarTracker()
    with pytest.raises(NoTrackError, match="no confirmed track"):
        tracker.brightest_track()
    run(tracker, frames(rng, 50))
    assert tracker.brightest_track() == 1  # FLUX[1] is the largest
    stats = tracker.track_stats()
    assert_array_equal(stats["hits"], 50)
    assert_allclose(stats["mean_flux"], FLUX, rtol=0.01, atol=0)
    assert_allclose(stats["mean_x"], STARS[:, 0], rtol=0, atol=0.05)
    assert_array_equal(stats["first_log_time"], 0)
    assert_array_equal(stats["last_log_time"], 49 * PERIOD_NS)


def test_brightest_prefers_long_tracks() -> None:
    rng = np.random.default_rng(10)
    data = frames(rng, 50)
    for k in range(25):  # the brightest star only appears in the second half
        data[k] = [a[[0, 2, 3]] for a in data[k]]
    tracker = StarTracker()
    run(tracker, data)
    # ids: stars 0, 2, 3 -> 0, 1, 2 at the start; star 1 (the brightest) -> 3 at frame 25
    assert tracker.brightest_track() == 1  # star 2 (5e4): the brightest seen all along
    assert tracker.brightest_track(min_hits_fraction=0.5) == 3


def test_track_centroids_matches_frame_loop() -> None:
    rng = np.random.default_rng(11)
    data = frames(rng, 30)
    data[7] = [np.zeros(0)] * 4
    ref = run(StarTracker(), data)
    t = np.concatenate([np.full(len(f[0]), k * PERIOD_NS) for k, f in enumerate(data)])
    cols = [np.concatenate([f[i] for f in data]) for i in range(4)]
    times, rows, tracker = track_centroids(
        t, *cols, frame_times=np.arange(30) * PERIOD_NS
    )
    assert_array_equal(rows, np.concatenate(ref))
    expected = [np.full(r.size, k * PERIOD_NS) for k, r in enumerate(ref)]
    assert_array_equal(times, np.concatenate(expected))
    assert tracker.frames == 30


@pytest.mark.parametrize(
    ("args", "match"),
    [
        ((0, [1.0], [1.0, 2.0], [0.1], [1.0]), "1-D arrays of one length"),
        ((0, [np.nan], [1.0], [0.1], [1.0]), "finite"),
        ((0, [1.0], [1.0], [-0.1], [1.0]), "sigma"),
        ((1.5, [1.0], [1.0], [0.1], [1.0]), "log_time must be an integer"),
    ],
)
def test_update_rejects_bad_input(args: tuple, match: str) -> None:
    with pytest.raises(InvalidInputError, match=match):
        StarTracker().update(*args)


def test_log_time_must_increase() -> None:
    tracker = StarTracker()
    tracker.update(10, [1.0], [1.0], [0.1], [1.0])
    with pytest.raises(InvalidInputError, match="log_time must increase"):
        tracker.update(10, [1.0], [1.0], [0.1], [1.0])


def test_sigma_floor_applies() -> None:
    rows = StarTracker(sigma_floor=0.02).update(0, [1.0], [2.0], [0.0], [5.0])
    assert rows["meas_sigma"][0] == 0.02
    assert_allclose(rows["cov_xx"], 0.02**2, rtol=0, atol=1e-15)


@pytest.mark.parametrize(
    ("kw", "match"),
    [
        ({"model": "JERK"}, "unknown motion model"),
        ({"association_radius": 0.0}, "association_radius"),
        ({"confirm_hits": 0}, "confirm_hits"),
        ({"max_missed": -1}, "max_missed"),
        ({"gate_probability": 1.5}, "gate probability"),
        ({"sigma_floor": float("inf")}, "sigma_floor"),
        ({"max_distance": 0.0}, "max_distance"),
        ({"max_distance": float("nan")}, "max_distance"),
    ],
)
def test_config_validation(kw: dict, match: str) -> None:
    with pytest.raises(InvalidParameterError, match=match):
        TrackerConfig(**kw)


def _coast_then_jump(**options: float) -> npt.NDArray[np.void]:
    """A confirmed STATIC track with a large per-frame diffusion coasts 5 frames, then a centroid
    appears 2.5 px away (a noise peak): the rows of that frame."""
    motion = MotionModelConfig(q_floor=1.0 * 300.0)  # 1 px per frame at 300 Hz
    tracker = StarTracker(model="STATIC", motion=motion, confirm_hits=2, max_missed=50, **options)
    dt = 1_000_000_000 // 300
    for k in range(3):
        tracker.update(k * dt, [10.0], [10.0], [0.3], [50.0])
    for k in range(3, 8):
        tracker.update(k * dt, [], [], [], [])
    return tracker.update(8 * dt, [12.5], [10.0], [0.3], [50.0])


def test_max_distance_keeps_a_coasting_track_off_noise_peaks() -> None:
    # without the limit the coasting track's widened gate takes the peak and jumps to it
    free = _coast_then_jump()
    assert free["track"].tolist() == [0] and free["measured"].tolist() == [True] and free["x"][0] > 12.0
    # with it the track stays where its star was, and the peak starts a tentative track
    held = _coast_then_jump(max_distance=1.5)
    assert held["track"].tolist() == [0, 1]
    assert not held["measured"][0] and held["x"][0] == pytest.approx(10.0, abs=1e-9)


def test_max_distance_reacquires_a_static_star_after_a_moving_model_coasts() -> None:
    # a POLYNOMIAL_TREND track fed noisy hits has a velocity and an acceleration; over 57
    # coasted frames its prediction drifts pixels away, but the star is still where it was
    # seen: the limit is measured from there, not from the drifting prediction
    dt = 1_000_000_000 // 300
    tracker = StarTracker(model="POLYNOMIAL_TREND", confirm_hits=2, max_missed=100, max_distance=1.5)
    for k in range(5):  # noisy centroids that look like a drift of 0.25 px per frame
        tracker.update(k * dt, [10.0 + 0.25 * k], [10.0], [0.3], [50.0])
    for k in range(5, 62):
        coasted = tracker.update(k * dt, [], [], [], [])
    assert coasted["x"][0] > 14.0  # the prediction has run away
    rows = tracker.update(62 * dt, [10.5], [9.9], [0.3], [50.0])
    assert rows["track"].tolist() == [0] and rows["measured"][0]
    assert np.hypot(rows["x"][0] - 10.5, rows["y"][0] - 9.9) < 0.5
    # a noise peak 2 px from where the star was seen is not taken, however wide the gate
    far = tracker.update(63 * dt, [12.1], [9.9], [0.3], [50.0])
    assert far["track"].tolist() == [0, 1] and not far["measured"][0]


def test_unknown_option() -> None:
    with pytest.raises(InvalidParameterError, match="unknown StarTracker option"):
        StarTracker(radius=3.0)


frame_strategy = st.lists(
    st.tuples(st.floats(0, 60), st.floats(0, 60), st.floats(0, 2), st.floats(-10, 1e5)),
    max_size=8,
)


@settings(max_examples=100, deadline=None)
@given(
    model=st.sampled_from(list(MotionModel)),
    steps=st.lists(st.tuples(st.integers(1, 50_000_000), frame_strategy), min_size=1, max_size=15),
)
def test_random_frames_never_crash(model: MotionModel, steps: list) -> None:
    tracker = StarTracker(model=model, max_missed=2)
    t = 0
    seen_max = -1
    for dt, cents in steps:
        t += dt
        arr = np.array(cents, dtype=np.float64).reshape(-1, 4)
        rows = tracker.update(t, arr[:, 0], arr[:, 1], arr[:, 2], arr[:, 3])
        assert rows.dtype == TRACK_DTYPE
        ids = rows["track"]
        assert np.unique(ids).size == ids.size
        assert (np.diff(ids) > 0).all()
        for name in TRACK_DTYPE.names:
            if rows.dtype[name].kind == "f":
                assert np.isfinite(rows[name]).all()
        assert rows["measured"].sum() <= arr.shape[0]
        assert not (rows["measured"] & rows["gated"]).any()
        if ids.size:
            seen_max = max(seen_max, int(ids.max()))
    assert tracker.track_stats()["track"].tolist() == list(range(seen_max + 1))


def test_persistent_jump_is_applied_after_max_gated() -> None:
    """A real, lasting 1 px jump is gated for max_gated frames only; the id survives."""
    rng = np.random.default_rng(12)
    data = frames(rng, 120)
    for k in range(40, 120):
        data[k][0] = data[k][0].copy()
        data[k][0][0] += 1.0
    outs = run(StarTracker(model="RANDOM_WALK", max_gated=3), data)
    star0 = np.array([o[0] for o in outs])
    assert (np.array([o["track"].tolist() for o in outs]) == [0, 1, 2, 3]).all()
    assert_array_equal(star0["gated"][40:43], True)
    assert star0["measured"][43] and star0["nis"][43] > 18.42  # forced update
    assert star0["measured"][100:].all()  # caught up: gate passes again
    assert abs(star0["x"][-1] - (STARS[0, 0] + 1.0)) < 0.1


def test_underestimated_sigma_does_not_break_tracks() -> None:
    """Jitter 10x the reported sigma: gating is frequent, but ids never change."""
    rng = np.random.default_rng(13)
    tracker = StarTracker(model="POLYNOMIAL_TREND")
    for k in range(600):
        shake = 0.2 * np.sin(2 * np.pi * 20 * k / 300)
        pos = STARS + shake + rng.normal(0, 0.02, STARS.shape)
        rows = tracker.update(k * PERIOD_NS, pos[:, 0], pos[:, 1], np.full(4, 0.02), FLUX)
        assert_array_equal(rows["track"], [0, 1, 2, 3])


def test_track_state_take_and_concat_keep_every_array_in_step() -> None:
    d = 4
    old = TrackState.born(ids=np.array([0, 1, 2]), x=np.arange(12.0).reshape(3, d),
                          P=np.stack([np.eye(d) * k for k in (1.0, 2.0, 3.0)]), log_time=5,
                          sums=np.ones((3, 3)))
    old.hits[:] = [7, 8, 9]
    new = TrackState.born(ids=np.array([3]), x=np.zeros((1, d)), P=np.eye(d)[None], log_time=9,
                          sums=np.zeros((1, 3)))
    both = TrackState.empty(d).concat(old).concat(new)
    kept = both.take(np.array([True, False, True, True]))
    assert len(both) == 4 and len(kept) == 3
    assert kept.ids.tolist() == [0, 2, 3]
    assert kept.hits.tolist() == [7, 9, 1]
    assert kept.first_time.tolist() == [5, 5, 9]
    assert_array_equal(kept.x[1], np.arange(8.0, 12.0))
    assert_array_equal(kept.P[1], np.eye(d) * 3.0)
    sizes = {name: len(getattr(kept, name)) for name in TrackState.ARRAYS}
    assert set(sizes.values()) == {3}, sizes
    new.missed[0] += 1  # a counter of a new track shares memory with no other counter
    assert [new.coast[0], new.gated_streak[0], new.age[0], new.gated[0]] == [0, 0, 0, 0]
    rows = FrameRows.empty(2).concat(FrameRows.born(np.array([[1.0, 2.0, 0.1, 5e3]])))
    assert rows.measured.tolist() == [False, False, True]
    assert rows.take(np.array([2])).meas.tolist() == [[1.0, 2.0, 0.1, 5e3]]
