"""Property-based: hostile bytes into the readers, recover and image ingest.

Only starlog's own errors (StarlogError subclasses) may come out; whatever reads successfully
is exactly what the intact log holds.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from starlog.errors import StarlogError
from starlog.io import LogReader
from starlog.io.recover import recover_log
from starlog.io.layout import MAGIC as MCAP_MAGIC
from starlog.stages import simulate_log
from starlog.stages.ingest import ColourImageWarning, ingest_folder
from tests.helpers import small_config

FUZZ = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


@pytest.fixture(scope="module")
def tiny_log(tmp_path_factory: pytest.TempPathFactory) -> bytes:
    path = tmp_path_factory.mktemp("fuzz") / "tiny.mcap"
    simulate_log(small_config(width=32, height=32, n_frames=4, n_stars=1, margin=6.0), path, compression="lz4")
    return path.read_bytes()


@pytest.fixture(scope="module")
def tiny_content(tiny_log: bytes, tmp_path_factory: pytest.TempPathFactory) -> dict[tuple[str, int], bytes]:
    path = tmp_path_factory.mktemp("fuzzc") / "tiny.mcap"
    path.write_bytes(tiny_log)
    with LogReader(path) as log:
        return {(c.topic, m.log_time): bytes(m.data) for _, c, m in log.raw_messages(log.topics)}


def _exercise(path: Path, out: Path, original: dict[tuple[str, int], bytes]) -> None:
    """Read every channel and recover: StarlogError or exact data, nothing else."""
    try:
        with LogReader(path) as log:
            log.channels()
            log.provenance()
            got = {(c.topic, m.log_time): bytes(m.data) for _, c, m in log.raw_messages(log.topics)}
            for topic in log.topics:
                for _ in log.messages(topic):
                    pass
        assert got == original, "a damaged log was read without an error but gave other data"
    except StarlogError:
        pass
    try:
        recover_log(path, out, force=True)
    except StarlogError:
        return
    with LogReader(out) as log:
        for _, c, m in log.raw_messages(log.topics):
            assert original.get((c.topic, m.log_time)) == bytes(m.data)


@FUZZ
@given(data=st.binary(max_size=400), magic=st.booleans())
def test_random_bytes_as_a_log(tmp_path: Path, data: bytes, magic: bool) -> None:
    path = tmp_path / "random.mcap"
    path.write_bytes((MCAP_MAGIC if magic else b"") + data + (MCAP_MAGIC if magic else b""))
    _exercise(path, tmp_path / "out.mcap", {})


@FUZZ
@given(mutations=st.lists(st.tuples(st.floats(0, 1, exclude_max=True), st.integers(1, 255)), min_size=1,
                          max_size=4),
       cut=st.one_of(st.none(), st.floats(0, 1)))
def test_mutated_log(tmp_path: Path, tiny_log: bytes, tiny_content: dict[tuple[str, int], bytes],
                     mutations: list[tuple[float, int]], cut: float | None) -> None:
    data = bytearray(tiny_log)
    for where, mask in mutations:
        data[int(where * len(data))] ^= mask
    if cut is not None:
        data = data[: int(cut * len(data))]
    path = tmp_path / "mutated.mcap"
    path.write_bytes(bytes(data))
    _exercise(path, tmp_path / "out.mcap", tiny_content)


def _ingest(folder: Path, out: Path) -> None:
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ColourImageWarning)
            ingest_folder(folder, out, fps=10, force=True)
    except StarlogError:
        return
    with LogReader(out) as log:
        for _ in log.frames():
            pass


@FUZZ
@given(data=st.binary(max_size=300), suffix=st.sampled_from([".png", ".tif", ".tiff"]))
def test_random_bytes_as_an_image(tmp_path: Path, data: bytes, suffix: str) -> None:
    folder = tmp_path / "in"
    folder.mkdir(exist_ok=True)
    for old in folder.iterdir():
        old.unlink()
    (folder / f"a{suffix}").write_bytes(data)
    _ingest(folder, tmp_path / "out.mcap")


@FUZZ
@given(image=hnp.arrays(dtype=st.sampled_from([np.uint8, np.uint16, np.int16, np.float32, np.uint32, np.bool_]),
                        shape=hnp.array_shapes(min_dims=1, max_dims=4, min_side=1, max_side=6)),
       suffix=st.sampled_from([".png", ".tif"]), second=st.booleans())
def test_random_arrays_as_images(tmp_path: Path, image: np.ndarray, suffix: str, second: bool) -> None:
    import cv2
    import tifffile

    folder = tmp_path / "in"
    folder.mkdir(exist_ok=True)
    for old in folder.iterdir():
        old.unlink()
    names = ["f1", "f2"] if second else ["f1"]
    for n, name in enumerate(names):
        path = folder / f"{name}{suffix}"
        frame = image if n == 0 else image[..., :1] if image.ndim > 1 else image
        if suffix == ".tif":
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    tifffile.imwrite(path, frame, photometric="minisblack")
            except Exception:  # tifffile cannot write every array: then the file is junk, also worth ingesting
                path.write_bytes(frame.tobytes())
        else:
            encodable = frame.dtype in (np.uint8, np.uint16) and (
                frame.ndim == 2 or (frame.ndim == 3 and frame.shape[2] in (1, 3, 4)))
            if encodable:
                _, buf = cv2.imencode(".png", frame)
                path.write_bytes(buf.tobytes())
            else:  # what PNG cannot hold: junk bytes under a .png name
                path.write_bytes(frame.tobytes())
    _ingest(folder, tmp_path / "out.mcap")
