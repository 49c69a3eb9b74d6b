"""The input digest of the provenance, taken from the digest a stage saved with the log it wrote."""

from __future__ import annotations

import hashlib
import os
import shutil
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from starlog.io import LogReader, file_digest
from starlog.io.digest_cache import read_digest_cache, write_digest_cache
from starlog.io.provenance import BackgroundDigest
from starlog.io.resumable_sha256 import ResumableSha256, available
from starlog.stages import simulate_log
from starlog.stages.centroid import centroid_log
from starlog.stages.track import track_log

from tests.conftest import small_config

needs_cache = pytest.mark.skipif(not available() or not hasattr(os, "setxattr"),
                                 reason="no resumable SHA-256 or no extended attributes here")


@pytest.mark.skipif(not available(), reason="libcrypto's SHA256 functions are not available")
@given(st.binary(max_size=3000), st.data())
def test_a_saved_state_resumes_to_hashlibs_digest(data: bytes, draw: st.DataObject) -> None:
    cut = draw.draw(st.integers(min_value=0, max_value=len(data)))
    first = ResumableSha256()
    first.update(data[:cut])
    resumed = ResumableSha256(first.state())
    resumed.update(memoryview(bytearray(data[cut:])))
    assert resumed.hexdigest() == hashlib.sha256(data).hexdigest()
    assert first.hexdigest() == hashlib.sha256(data[:cut]).hexdigest()  # and the first can still finish


def _has_attribute_support(folder: Path) -> bool:
    probe = folder / "probe"
    probe.write_bytes(b"x")
    try:
        os.setxattr(probe, "user.starlog.probe", b"1")
    except OSError:
        return False
    return True


@needs_cache
def test_stages_chain_their_digests(tmp_path: Path) -> None:
    if not _has_attribute_support(tmp_path):
        pytest.skip("this file system keeps no user attributes")
    sim, cen, trk = tmp_path / "sim.mcap", tmp_path / "cen.mcap", tmp_path / "trk.mcap"
    simulate_log(small_config(n_frames=30), sim)
    centroid_log(sim, cen, methods="MOMENT")
    track_log(cen, trk, method="MOMENT", models="STATIC", tracker={"sigma_floor": 0.05})
    for source, output in ((sim, cen), (cen, trk)):
        cached = read_digest_cache(source)
        assert cached is not None and cached.digest == file_digest(source)
        with LogReader(output) as log:
            assert log.provenance()[-1].input_digest == file_digest(source)
    cached = read_digest_cache(trk)
    assert cached is not None and cached.digest == file_digest(trk)


@needs_cache
def test_a_changed_file_is_hashed_again(tmp_path: Path, sim_log: Path) -> None:
    if not _has_attribute_support(tmp_path):
        pytest.skip("this file system keeps no user attributes")
    log = tmp_path / "copy.mcap"
    shutil.copyfile(sim_log, log)
    write_digest_cache(log)
    assert read_digest_cache(log) is not None
    stat = os.stat(log)
    os.utime(log, ns=(stat.st_atime_ns, stat.st_mtime_ns + 1_000_000))  # as a rewrite would
    assert read_digest_cache(log) is None
    digest = BackgroundDigest(log)
    assert digest.result() == file_digest(log)
    assert digest.prefix() is not None  # hashed whole, its data section's state kept on the way


@needs_cache
def test_run_takes_the_saved_digest_and_saves_its_own(tmp_path: Path) -> None:
    from starlog.pipeline import PipelineConfig, run_pipeline

    if not _has_attribute_support(tmp_path):
        pytest.skip("this file system keeps no user attributes")
    sim, out = tmp_path / "sim.mcap", tmp_path / "run.mcap"
    simulate_log(small_config(n_frames=30), sim)
    assert read_digest_cache(sim) is not None
    config = PipelineConfig.from_dict({"centroid": {"methods": ["MOMENT"]},
                                       "track": {"methods": ["MOMENT"], "models": "STATIC"}})
    run_pipeline(sim, out, config)
    with LogReader(out) as log:
        assert log.provenance()[1].input_digest == file_digest(sim)  # [0] is simulate's own record
    cached = read_digest_cache(out)
    assert cached is not None and cached.digest == file_digest(out)
