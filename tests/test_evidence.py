"""Which centroid method to trust, from the log alone: the rule on simulated logs where the answer is known."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from starlog.centroiding import CentroidMethod, extract_stars
from starlog.centroiding.evidence import (
    EvidenceAccumulator,
    FrameEvidence,
    evidence_sums,
    evidence_sums_vectorised,
    frame_evidence,
    recommend,
)
from starlog.facts import log_facts
from starlog.cli.describe import info_text
from starlog.sim.psf import render_stars
from starlog.stages.centroid import centroid_log
from starlog.sim import SimulationConfig
from starlog.stages import simulate_log

METHODS = [CentroidMethod.NONE, CentroidMethod.MOMENT, CentroidMethod.BICUBIC, CentroidMethod.GAUSSFIT]


def _faint_field(frames: int, seed: int) -> EvidenceAccumulator:
    """Faint pixel-integrated Gaussian stars (SNR ~ 15-40) drifting with a common platform motion."""
    rng = np.random.default_rng(seed)
    centres = np.arange(16.0, 240.0, 24.0)
    cx, cy = np.meshgrid(centres, centres)
    x0, y0 = cx.ravel() + rng.uniform(-0.5, 0.5, cx.size), cy.ravel() + rng.uniform(-0.5, 0.5, cy.size)
    flux = rng.uniform(600.0, 1500.0, x0.size)
    acc = EvidenceAccumulator([m.value for m in METHODS])
    for k in range(frames):
        shift = rng.normal(0.0, 0.3, 2)  # the platform moves every star alike
        clean = 100.0 + render_stars((256, 256), x0 + shift[0], y0 + shift[1], flux, 1.3)
        image = rng.poisson(clean).astype(np.float64) + rng.normal(0.0, 3.0, clean.shape)
        _, tables = extract_stars(image, methods=METHODS, psf_sigma=1.3)
        acc.add(frame_evidence([tables[m] for m in METHODS]))
    return acc


def test_on_pixel_integrated_gaussian_stars_the_fit_or_the_weighted_moment_is_trusted() -> None:
    evidence = _faint_field(12, seed=1).result()
    method, reason = recommend(evidence)
    assert method in ("GAUSSFIT", "MOMENT"), evidence
    assert method in reason
    best = evidence[method]["noise_px"]
    assert evidence["NONE"]["noise_px"] > best and evidence["BICUBIC"]["noise_px"] > best


def test_no_method_is_named_without_stars_seen_twice() -> None:
    acc = _faint_field(1, seed=2)
    method, reason = recommend(acc.result())
    assert method is None and "consecutive frames" in reason


def test_the_stage_records_the_evidence_and_info_names_the_method(tmp_path: Path) -> None:
    sim, out = tmp_path / "sim.mcap", tmp_path / "cen.mcap"
    simulate_log(SimulationConfig(width=256, height=256, n_stars=30, n_frames=20, seed=3), sim)
    summary = centroid_log(sim, out, methods="NONE,MOMENT,GAUSSFIT").to_dict()
    assert summary["recommended"]["method"] in ("GAUSSFIT", "MOMENT")
    assert set(summary["evidence"]) == {"NONE", "MOMENT", "GAUSSFIT"}
    info = log_facts(out)
    assert info["centroid_evidence"][0]["recommended"] == summary["recommended"]["method"]
    assert "recommended: " + summary["recommended"]["reason"] in info_text(info)


@settings(max_examples=200, deadline=None, derandomize=True)
@given(seed=st.integers(0, 2**32 - 1), methods=st.integers(1, 5), before=st.integers(0, 40), after=st.integers(0, 40),
       spread=st.sampled_from([3.0, 30.0, 300.0]))
def test_the_compiled_sums_are_numpys(seed: int, methods: int, before: int, after: int, spread: float) -> None:
    """Random frames, stars near each other and near the matching radius included: the compiled sums are
    the numpy form's, bit for bit."""
    rng = np.random.default_rng(seed)

    def frame(n: int, shift: tuple[float, float]) -> FrameEvidence:
        x = rng.uniform(0, spread, n) + shift[0] + rng.normal(0, 0.02, (methods, n))
        y = rng.uniform(0, spread, n) + shift[1] + rng.normal(0, 0.02, (methods, n))
        return FrameEvidence(x, y, np.ones((methods, n)))

    first = frame(before, (0.0, 0.0))
    second = FrameEvidence(first.x[:, : after] + rng.uniform(-1.2, 1.2), first.y[:, : after] + rng.normal(0, 0.5),
                           first.sigma[:, : after]) if after <= before and seed % 2 else frame(after, (0.3, -0.2))
    for previous in (None, first):
        got, want = evidence_sums(previous, second), evidence_sums_vectorised(previous, second)
        for name in ("apart", "steps", "before", "after", "squares"):
            np.testing.assert_array_equal(getattr(got, name), getattr(want, name), err_msg=name)


@settings(max_examples=30, deadline=None, derandomize=True)
@given(seed=st.integers(0, 2**32 - 1), methods=st.integers(1, 4), frames=st.integers(1, 8))
def test_the_accumulator_gives_the_same_evidence_with_the_compiled_sums(seed: int, methods: int, frames: int) -> None:
    """A field drifting with the platform, stars leaving and new ones coming in, each method with its own noise:
    the pooled evidence, its per-star sums and their bootstrap are the numpy form's, bit for bit; the per-star sums
    hold every pair's displacement once."""
    rng = np.random.default_rng(seed)
    names = [f"M{k}" for k in range(methods)]
    fast, reference = EvidenceAccumulator(names), EvidenceAccumulator(names, vectorised=True)
    x0, y0 = rng.uniform(0, 400, 60), rng.uniform(0, 400, 60)
    shift = np.zeros(2)
    for _ in range(frames):
        shift += rng.normal(0, 0.3, 2)
        seen = rng.permutation(np.flatnonzero(rng.random(x0.size) < 0.8))  # in no fixed order
        noise = rng.uniform(0.01, 0.1, (methods, 1))
        x = x0[seen] + shift[0] + rng.normal(0, 1, (methods, seen.size)) * noise
        y = y0[seen] + shift[1] + rng.normal(0, 1, (methods, seen.size)) * noise
        frame = FrameEvidence(x, y, np.broadcast_to(noise, x.shape).copy())
        fast.add(frame)
        reference.add(frame)
    assert fast.result() == reference.result()
    np.testing.assert_array_equal(fast.star_sums, reference.star_sums)
    np.testing.assert_array_equal(fast.star_pairs, reference.star_pairs)
    np.testing.assert_allclose(fast.star_sums.sum(axis=1), fast.steps, rtol=1e-12, atol=0)
    assert fast.star_pairs.sum() == fast.pairs
