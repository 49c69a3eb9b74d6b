"""The I/O benchmark's ingest target: the best lz4 ingest row, informational, not judged at --quick."""

from __future__ import annotations

import pytest

from tests.tool_modules import tool_module

ROWS = [("numpy tofile (reference)", 900.0, 500.0), ("ingest PNG lz4 workers=1", 160.0, 84.0),
        ("ingest PNG lz4 workers=2", 300.0, 157.0), ("ingest PNG zstd workers=2", 190.0, 100.0)]


@pytest.fixture(scope="module")
def bench():
    with tool_module("bench_io") as module:
        yield module


def test_the_ingest_target_takes_the_best_lz4_row(bench):
    targets = bench.Targets()
    bench.check_ingest(targets, ROWS, quick=False)
    (target,) = targets.items
    assert target.verdict == "PASS" and "157.0 MB/s" in target.text


def test_a_slow_ingest_is_an_informational_miss_and_not_judged_at_quick_size(bench):
    slow = [(name, fps, mbs / 2) for name, fps, mbs in ROWS]
    full, quick = bench.Targets(), bench.Targets()
    bench.check_ingest(full, slow, quick=False)
    bench.check_ingest(quick, slow, quick=True)
    assert full.items[0].verdict == "MISS" and full.report() == 0
    assert quick.items[0].verdict == "n/a"


def test_the_star_table_targets_judge_the_frame_times_and_the_uncompressed_sizes(bench):
    frames = [("centroid: detections + centroids + annotations", 160.0, 31.0), ("track: one message", 100.0, 55.0)]
    sizes = [("centroid (uncompressed)", 1000, 460), ("track (uncompressed)", 1000, 510),
             ("centroid (zstd)", 1000, 800)]
    targets = bench.Targets()
    bench.check_codec(targets, frames, sizes, 50.0)
    assert [t.verdict for t in targets.items] == ["PASS", "FAIL", "PASS", "FAIL", "MISS"]
    assert "centroid stage (50 stars): 31.0 us <= 50" in targets.items[0].text
    assert targets.report() == 1
