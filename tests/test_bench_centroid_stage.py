"""The centroid stage benchmark's comparison of tracking with full mode: matching to the truth, the paired RMSE,
how long a star goes unmeasured and how late an entering star is found."""

from __future__ import annotations

import math

import pytest

from tests.tool_modules import tool_module


@pytest.fixture(scope="module")
def bench():
    with tool_module("bench_centroid_stage") as module:
        yield module


def _truth(*xy):
    return {"stars": [{"star": k, "x": x, "y": y} for k, (x, y) in enumerate(xy)]}


def _centroids(*xy):
    return {"stars": [{"x": x, "y": y} for x, y in xy]}


def test_centroids_match_their_nearest_true_star_within_a_pixel(bench):
    truth = _truth((10.0, 10.0), (20.0, 20.0))
    got = bench.frame_matches(_centroids((10.1, 10.0), (25.0, 20.0), (10.05, 10.0)), truth)
    assert got == {0: pytest.approx((0.05, 0.0))}  # the nearer of the two centroids on star 0; none within 1 px of 1
    assert bench.frame_matches(_centroids(), truth) == {}


def test_the_paired_rmse_uses_the_pairs_both_modes_measured(bench):
    full = [{0: (0.1, 0.0), 1: (0.0, 0.1)}, {0: (0.1, 0.0)}]
    tracked = [{0: (0.2, 0.0)}, {0: (0.1, 0.0), 1: (5.0, 5.0)}]
    a, b, pairs = bench.paired_rmse(full, tracked)
    assert pairs == 2 and a == pytest.approx(0.1) and b == pytest.approx(math.sqrt((0.04 + 0.01) / 2))
    assert math.isnan(bench.paired_rmse([{}], [{}])[0])


def test_the_longest_gap_and_the_entry_delay(bench):
    seen = {0: (0.0, 0.0)}
    both = {0: (0.0, 0.0), 1: (0.0, 0.0)}
    full = [seen, both, both, both, both, seen]
    tracked = [seen, seen, seen, both, seen, seen]
    assert bench.longest_gap(full, tracked) == 2  # star 1 unmeasured in frames 1-2, and again in frame 4
    assert bench.entry_delay(full, tracked) == 2  # star 1 entered at frame 1, tracked from frame 3
    assert bench.entry_delay([seen], [seen]) == 0
    assert bench.entry_delay([seen, both], [seen, seen]) == 1  # never found: counted to the log's end
