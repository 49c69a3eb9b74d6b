"""The compiled frame step of StarTracker against its numpy steps (the reference) and against filterpy.

Scenarios are random (hypothesis draws a seed and the scenario's knobs, numpy draws the values): static,
crowded and moving fields, missed detections, outliers, spurious detections, empty frames, irregular
frame intervals, every motion model and the tracker's options. The compiled step must give the same
tracks (ids, association, gating, confirmation, losses, brightest track) and the same numbers to
rounding: positions, velocities and innovations within ``RTOL`` of their scale (the coordinates; the
largest velocity of the run), covariances within ``RTOL_COV`` of ``sqrt(cov_xx cov_yy)`` and the NIS
(``νᵀ S⁻¹ ν``, S from them) within ``RTOL_COV`` of ``1 + nis``. A posterior covariance is the prior's
minus the gain's share: where the measurement is far more precise than the prediction (a new
POLYNOMIAL_TREND track, its acceleration unknown, measured to 1e-3 px) the subtraction cancels up to 8
digits, and each form keeps its own rounding of the prior in what is left (1500 random scenarios:
positions within 1e-11, covariances and NIS within 6e-8).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose, assert_array_equal

from starlog.errors import InvalidInputError
from starlog.tracking import (
    TRACK_DTYPE,
    MotionModel,
    NoTrackError,
    StarTracker,
    TrackerConfig,
    filterpy_step,
    initial_covariance,
    make_filterpy_ukf,
    state_dim,
)
from starlog.tracking.frame_kernel import INT_COLUMNS, Status
from starlog.tracking.state import INT_FIELDS, TrackState

RTOL = 1e-9
RTOL_COV = 1e-6
PERIOD_NS = 3_333_333
FLOATS = [n for n in TRACK_DTYPE.names if TRACK_DTYPE[n].kind == "f"]
EXACT = [n for n in TRACK_DTYPE.names if TRACK_DTYPE[n].kind != "f"]


@dataclass(frozen=True)
class Scenario:
    """A random centroid stream: ``frames`` of (log_time, x, y, sigma, flux)."""

    frames: list[tuple[int, np.ndarray, np.ndarray, np.ndarray, np.ndarray]]


def scenario(seed: int, n_stars: int, n_frames: int, side: float, detect: float, outliers: float,
             spurious: float, speed: float) -> Scenario:
    rng = np.random.default_rng(seed)
    pos = rng.uniform(0, side, (n_stars, 2))
    vel = rng.normal(0, speed, (n_stars, 2))  # px/s
    sigma = rng.uniform(0, 0.3, n_stars) * (rng.random(n_stars) > 0.1)  # some 0: the floor applies
    flux = rng.uniform(1e3, 1e5, n_stars)
    t = 0
    frames = []
    for _ in range(n_frames):
        t += int(rng.integers(1, 16)) * PERIOD_NS // 3  # irregular intervals, 1-18 ms
        shake = rng.normal(0, 0.05, 2)
        p = pos + vel * t * 1e-9 + shake + rng.normal(size=pos.shape) * np.maximum(sigma, 0.01)[:, None]
        p[rng.random(n_stars) < outliers] += rng.uniform(-5, 5, 2)
        keep = rng.random(n_stars) < detect
        extra = rng.poisson(spurious)
        x = np.concatenate([p[keep, 0], rng.uniform(0, side, extra)])
        y = np.concatenate([p[keep, 1], rng.uniform(0, side, extra)])
        s = np.concatenate([sigma[keep], rng.uniform(0, 0.5, extra)])
        f = np.concatenate([flux[keep], rng.uniform(10, 1e3, extra)])
        order = rng.permutation(x.size)
        frames.append((t, x[order], y[order], s[order], f[order]))
    return Scenario(frames)


def run(config: TrackerConfig, sc: Scenario, *, vectorised: bool) -> tuple[list[np.ndarray], StarTracker]:
    tracker = StarTracker(config, vectorised=vectorised)
    return [tracker.update(*frame) for frame in sc.frames], tracker


def scales(rows: np.ndarray, velocity: float) -> dict[str, np.ndarray]:
    """The magnitude each float column of ``rows`` is computed at (see the module docstring)."""
    position = np.maximum(np.maximum(np.abs(rows["x"]), np.abs(rows["y"])), 1.0)
    measured = np.maximum(np.maximum(np.abs(rows["meas_x"]), np.abs(rows["meas_y"])), position)
    cov = np.sqrt(rows["cov_xx"] * rows["cov_yy"])
    return {"x": position, "y": position, "vx": np.full(rows.size, velocity), "vy": np.full(rows.size, velocity),
            "cov_xx": cov, "cov_xy": cov, "cov_yy": cov, "innovation_x": measured,
            "innovation_y": measured, "nis": 1.0 + rows["nis"], "meas_x": measured, "meas_y": measured,
            "meas_sigma": rows["meas_sigma"], "flux": np.abs(rows["flux"])}


def assert_same_tracks(compiled: list[np.ndarray], reference: list[np.ndarray]) -> None:
    assert len(compiled) == len(reference)
    both = [r for r in reference if r.size]
    velocity = max([1.0] + [float(np.abs(r[["vx", "vy"]].tolist()).max()) for r in both])
    for k, (a, b) in enumerate(zip(compiled, reference, strict=True)):
        assert a.dtype == TRACK_DTYPE and a.shape == b.shape, k
        for name in EXACT:
            assert_array_equal(a[name], b[name], err_msg=f"frame {k}: {name}")
        for name, scale in scales(b, velocity).items():
            rtol = RTOL_COV if name.startswith("cov") or name == "nis" else RTOL
            assert np.all(np.abs(a[name] - b[name]) <= rtol * scale), f"frame {k}: {name}"


def assert_same_summary(compiled: StarTracker, reference: StarTracker) -> None:
    a, b = compiled.track_stats(), reference.track_stats()
    for name in ("track", "alive", "confirmed", "hits", "gated", "first_log_time", "last_log_time"):
        assert_array_equal(a[name], b[name])
    for name in ("mean_flux", "mean_x", "mean_y"):
        assert_allclose(a[name], b[name], rtol=RTOL, atol=0)
    assert compiled.n_live == reference.n_live and compiled.frames == reference.frames
    try:
        brightest = reference.brightest_track()
    except NoTrackError:
        with pytest.raises(NoTrackError):
            compiled.brightest_track()
    else:
        assert compiled.brightest_track() == brightest


def test_kernel_reads_the_state_columns_in_their_order() -> None:
    assert INT_COLUMNS == INT_FIELDS


@settings(max_examples=150, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    model=st.sampled_from(list(MotionModel)),
    n_stars=st.integers(0, 12),
    n_frames=st.integers(1, 40),
    side=st.sampled_from([15.0, 60.0, 400.0]),
    detect=st.floats(0.5, 1.0),
    outliers=st.sampled_from([0.0, 0.05, 0.3]),
    spurious=st.sampled_from([0.0, 0.3, 2.0]),
    speed=st.sampled_from([0.0, 30.0]),
    options=st.fixed_dictionaries({
        "gate_probability": st.sampled_from([0.9999, 0.99, 1.0]),
        "confirm_hits": st.integers(1, 4),
        "max_missed": st.integers(0, 3),
        "max_gated": st.integers(1, 5),
        "sigma_floor": st.sampled_from([1e-3, 0.05]),
        "max_distance": st.sampled_from([None, 2.0]),
        "association_radius": st.sampled_from([3.0, 0.5]),
    }),
)
def test_compiled_step_equals_the_numpy_steps(seed: int, model: MotionModel, n_stars: int, n_frames: int,
                                              side: float, detect: float, outliers: float, spurious: float,
                                              speed: float, options: dict) -> None:
    sc = scenario(seed, n_stars, n_frames, side, detect, outliers, spurious, speed)
    config = TrackerConfig(model=model, **options)
    compiled, tracker = run(config, sc, vectorised=False)
    reference, ref_tracker = run(config, sc, vectorised=True)
    assert_same_tracks(compiled, reference)
    assert_same_summary(tracker, ref_tracker)


@pytest.mark.parametrize("model", list(MotionModel))
def test_compiled_step_equals_filterpy(model: MotionModel) -> None:
    """One star, every measurement applied: the compiled filter is filterpy's UKF."""
    rng = np.random.default_rng(5)
    n = 150
    dts = rng.integers(2, 7, n) * 1_000_000  # 2-6 ms
    sig = rng.uniform(0.03, 0.3, n)
    z = np.array([512.3, 100.7]) + rng.normal(size=(n, 2)) * sig[:, None]
    tracker = StarTracker(model=model, gate_probability=1.0, association_radius=1e3)
    tracker.update(0, [512.0], [101.0], [0.2], [1e4])
    x0 = np.zeros(state_dim(model))
    x0[:2] = 512.0, 101.0
    ref = make_filterpy_ukf(model, x=x0, P=initial_covariance(model, [0.2])[0])
    t = 0
    for k in range(n):
        t += int(dts[k])
        rows = tracker.update(t, z[k, :1], z[k, 1:], sig[k : k + 1], [1e4])
        nis, applied = filterpy_step(ref, model, dts[k] * 1e-9, z[k], sig[k], gate_probability=1.0)
        assert applied and rows["measured"][0]
        assert_allclose([rows["x"][0], rows["y"][0]], ref.x[:2], rtol=0, atol=1e-9)
        if ref.x.size >= 4:
            assert_allclose([rows["vx"][0], rows["vy"][0]], ref.x[2:4], rtol=1e-6, atol=1e-6)
        s = np.sqrt(ref.P[0, 0] * ref.P[1, 1])
        assert_allclose([rows["cov_xx"][0], rows["cov_xy"][0], rows["cov_yy"][0]],
                        [ref.P[0, 0], ref.P[0, 1], ref.P[1, 1]], rtol=0, atol=1e-9 * s)
        assert_allclose(rows["nis"][0], nis, rtol=0, atol=1e-9 * max(1.0, nis))


def test_an_assignment_with_a_choice_goes_to_the_solver() -> None:
    """Two stars 1 px apart, each centroid admissible for both tracks: the compiled step hands the
    assignment to scipy, as the numpy steps solve it, and the tracks never swap."""
    rng = np.random.default_rng(6)
    stars = np.array([[100.0, 100.0], [101.0, 100.2]])
    frames = []
    for k in range(50):
        p = stars + rng.normal(0, 0.05, stars.shape)
        order = rng.permutation(2)
        frames.append((k * PERIOD_NS, p[order, 0], p[order, 1], np.full(2, 0.05), np.array([1e4, 2e4])[order]))
    sc = Scenario(frames)
    compiled, _ = run(TrackerConfig(), sc, vectorised=False)
    reference, _ = run(TrackerConfig(), sc, vectorised=True)
    assert_same_tracks(compiled, reference)
    for rows in compiled[1:]:
        assert_array_equal(rows["track"], [0, 1])
        assert rows["measured"].all()
        assert abs(rows["x"][0] - 100.0) < 0.3 and abs(rows["x"][1] - 101.0) < 0.3


def test_a_covariance_to_repair_goes_to_the_numpy_steps() -> None:
    """A track whose covariance rounding made indefinite: the compiled step stops before changing it and
    the numpy steps repair it, as they would have alone."""
    compiled = StarTracker(model="CONSTANT_VELOCITY")
    reference = StarTracker(model="CONSTANT_VELOCITY", vectorised=True)
    for tracker in (compiled, reference):
        tracker.update(0, [10.0, 50.0], [20.0, 60.0], [0.1, 0.1], [1e4, 1e4])
        state: TrackState = tracker._tracks
        P = state.P[0]
        P[:] = [[1.0, 0.0, 1.0, 0.0], [0.0, 1.0, 0.0, 0.0], [1.0, 0.0, 1.0 - 1e-12, 0.0], [0.0, 0.0, 0.0, 1.0]]
    a = compiled.update(PERIOD_NS, [10.0, 50.0], [20.0, 60.0], [0.1, 0.1], [1e4, 1e4])
    b = reference.update(PERIOD_NS, [10.0, 50.0], [20.0, 60.0], [0.1, 0.1], [1e4, 1e4])
    assert_same_tracks([a], [b])
    assert np.isfinite(a["cov_xx"]).all()


def test_an_update_to_repair_goes_to_the_numpy_steps() -> None:
    """A frame the call hands back after its prediction (an updated covariance to repair: rounding makes it
    too rare to provoke) is finished by the numpy steps as they would have alone."""
    sc = scenario(8, 6, 2, 400.0, 1.0, 0.0, 0.0, 0.0)
    compiled = StarTracker(model="CONSTANT_VELOCITY")
    reference = StarTracker(model="CONSTANT_VELOCITY", vectorised=True)
    (t0, *first), (t, *second) = sc.frames
    compiled.update(t0, *first)
    reference.update(t0, *first)
    compiled._predict(t)  # what the call does before it hands the frame back
    out = np.empty(compiled.n_live + second[0].size, dtype=TRACK_DTYPE)
    rows = compiled._step._handed_back(Status.REPAIR_UPDATE, t, np.stack(second, axis=1), out)
    assert_same_tracks([out[:rows]], [reference.update(t, *second)])
    assert_same_summary(compiled, reference)


def test_track_state_views_share_the_tables() -> None:
    state = TrackState.born(ids=np.array([0, 1]), x=np.arange(8.0).reshape(2, 4),
                            P=np.stack([np.eye(4), 2 * np.eye(4)]), log_time=7, sums=np.ones((2, 3)))
    state.reserve(40)
    assert state.floats.shape[0] >= 40 and len(state) == 2
    assert np.shares_memory(state.P, state.floats) and np.shares_memory(state.x, state.floats)
    state.P[1, 2, 3] = 5.0
    state.age += 1
    assert state.floats[1, 4 + 2 * 4 + 3] == 5.0
    assert state.ints[:2, INT_FIELDS.index("age")].tolist() == [1, 1]
    assert_array_equal(state.anchor, [[0.0, 1.0], [4.0, 5.0]])


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), model=st.sampled_from(list(MotionModel)), vectorised=st.booleans(),
       cuts=st.lists(st.integers(0, 30), max_size=4))
def test_update_block_equals_update_frame_by_frame(seed: int, model: MotionModel, vectorised: bool,
                                                    cuts: list[int]) -> None:
    """Blocks of any length (births growing the block's table among them) give each frame's rows in turn."""
    sc = scenario(seed, 8, 30, 60.0, 0.8, 0.05, 2.0, 0.0)
    expected, _ = run(TrackerConfig(model=model), sc, vectorised=vectorised)
    tracker = StarTracker(model=model, vectorised=vectorised)
    got = []
    for a, b in zip([0, *sorted(cuts)], [*sorted(cuts), len(sc.frames)], strict=True):
        frames = sc.frames[a:b]
        table = np.array([[x, y, s, f] for _, *cols in frames for x, y, s, f in zip(*cols, strict=True)]).reshape(-1, 4)
        rows, counts = tracker.update_block([t for t, *_ in frames], [f[1].size for f in frames], table)
        assert counts.tolist() == [r.size for r in expected[len(got):len(got) + len(frames)]]
        got += np.split(rows, np.cumsum(counts)[:-1]) if len(frames) else []
    assert len(got) == len(expected)
    for a, b in zip(got, expected, strict=True):
        assert_array_equal(a, b)


def test_update_block_checks_its_input() -> None:
    tracker = StarTracker()
    with pytest.raises(InvalidInputError, match="table"):
        tracker.update_block([0, 1], [1, 1], np.zeros((3, 4)))
    tracker.update_block([0], [1], [[1.0, 2.0, 0.1, 1e3]])
    with pytest.raises(InvalidInputError, match="must increase"):
        tracker.update_block([5, 5], [0, 0], np.zeros((0, 4)))
    with pytest.raises(InvalidInputError, match="finite"):
        tracker.update_block([9], [1], [[np.nan, 2.0, 0.1, 1e3]])
