"""Ingest of what cameras write besides PNG/TIFF: SER files, AVI video, JPEG and BMP.

SER files are written here from the public SER v3 header layout (see :mod:`starlog.stages.ingest.ser`), so
the reader is checked against the format, not against itself.
"""

from __future__ import annotations

import json
import struct
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from starlog.cli import cli
from starlog.errors import ImageFolderError, InvalidParameterError, StarlogError
from starlog.io import LogReader
from starlog import topics
from starlog.stages.ingest.ser import unix_ns_to_ticks
from starlog.sim import SimulationConfig, Simulator
from starlog.stages import ingest_source
from starlog.stages.ingest import ColourImageWarning, LossyImageWarning

EPOCH_NS = 1_700_000_000_000_000_000  # 2023-11-14, a plausible capture date (SER times are UTC)
COLOR_IDS = {"mono": 0, "RGGB": 8, "GRBG": 9, "GBRG": 10, "BGGR": 11, "RGB": 100, "BGR": 101}


def write_ser(path: Path, frames: list[np.ndarray], *, colour: str = "mono", depth: int | None = None,
              times_ns: list[int] | None = None, byte_order: str = "<", flag: int | None = None,
              frame_count: int | None = None) -> None:
    """A SER v3 file: 178-byte header, frames, optional trailer of UTC ticks (100 ns since 0001-01-01)."""
    first = frames[0]
    depth = depth or (16 if first.dtype == np.uint16 else 8)
    flag = (1 if byte_order == "<" else 0) if flag is None else flag  # the specification's meaning
    header = struct.pack("<14s7i40s40s40sqq", b"LUCAM-RECORDER", 0, COLOR_IDS[colour], flag, first.shape[1],
                         first.shape[0], depth, len(frames) if frame_count is None else frame_count,
                         b"observer", b"test camera", b"test scope", 0, 0)
    assert len(header) == 178
    dtype = np.dtype(byte_order + ("u2" if depth > 8 else "u1"))
    with open(path, "wb") as f:
        f.write(header)
        for frame in frames:
            f.write(np.ascontiguousarray(frame, dtype=dtype).tobytes())
        if times_ns is not None:
            f.write(np.array([unix_ns_to_ticks(t) for t in times_ns], "<i8").tobytes())


@pytest.fixture(scope="module")
def sim_frames() -> list[tuple[int, np.ndarray, np.ndarray]]:
    """(log_time, 16-bit image, true x/y) of 12 simulated frames."""
    sim = Simulator(SimulationConfig(width=48, height=40, n_stars=4, n_frames=12, fps=100.0, seed=4, margin=8.0))
    return [(f.log_time, f.image, np.column_stack([f.x, f.y])) for f in (sim.render(n) for n in range(12))]


def _read_log(path: Path) -> tuple[list[int], list[np.ndarray], list[dict]]:
    with LogReader(path) as log:
        frames = list(log.frames())
        infos = [m.payload for m in log.messages(topics.FRAME_INFO)]
    return [t for _, t, _ in frames], [image for _, _, image in frames], infos


# ---------------------------------------------------------------- SER
@pytest.mark.parametrize("bits", [8, 16])
def test_ser_mono_round_trip_gives_the_same_pixels_and_times(sim_frames, tmp_path: Path, bits: int) -> None:
    images = [image if bits == 16 else (image >> 8).astype(np.uint8) for _, image, _ in sim_frames]
    times = [EPOCH_NS + t for t, _, _ in sim_frames]  # multiples of 100 ns: exact in SER ticks
    write_ser(tmp_path / "capture.ser", images, times_ns=times)
    summary = ingest_source(tmp_path / "capture.ser", tmp_path / "o.mcap")
    assert summary.frames == 12 and summary.timing == "SER timestamps" and not summary.skipped
    assert summary.encoding == ("mono16" if bits == 16 else "mono8")
    got_times, got_images, infos = _read_log(tmp_path / "o.mcap")
    assert got_times == times
    for got, want in zip(got_images, images):
        np.testing.assert_array_equal(got, want)
    assert infos[3]["source"] == "capture.ser frame 3" and infos[0]["bit_depth"] == bits


@pytest.mark.parametrize("pattern", ["RGGB", "GRBG", "GBRG", "BGGR"])
@pytest.mark.parametrize("bits", [8, 16])
def test_ser_bayer_frames_are_debayered_to_mono(tmp_path: Path, pattern: str, bits: int) -> None:
    """A red-only scene must come out as red's luma weight (0.299): the pattern is read the right way round."""
    dtype, level = (np.uint16, 40000) if bits == 16 else (np.uint8, 200)
    mosaic = np.zeros((16, 20), dtype)
    red_row, red_col = {"RGGB": (0, 0), "GRBG": (0, 1), "GBRG": (1, 0), "BGGR": (1, 1)}[pattern]
    mosaic[red_row::2, red_col::2] = level
    frames = [mosaic, mosaic.copy()]
    times = [EPOCH_NS, EPOCH_NS + 5_000_000]
    write_ser(tmp_path / "bayer.ser", frames, colour=pattern, times_ns=times)
    with pytest.warns(ColourImageWarning, match=f"Bayer {pattern} frames debayered"):
        summary = ingest_source(tmp_path / "bayer.ser", tmp_path / "o.mcap")
    got_times, got_images, _ = _read_log(tmp_path / "o.mcap")
    assert got_times == times and summary.frames == 2
    centre = got_images[0][4:-4, 4:-4].astype(float)
    np.testing.assert_allclose(centre, 0.299 * level, rtol=0.01)
    np.testing.assert_array_equal(got_images[1], cv2.cvtColor(mosaic, getattr(cv2, f"COLOR_Bayer{pattern}2GRAY")))


@pytest.mark.parametrize("byte_order, flag", [(">", 0), ("<", 0), (">", 1)])
def test_ser_16_bit_byte_order_is_found_whatever_the_flag_says(sim_frames, tmp_path: Path, byte_order: str,
                                                               flag: int) -> None:
    images = [image for _, image, _ in sim_frames[:3]]
    write_ser(tmp_path / "c.ser", images, byte_order=byte_order, flag=flag, depth=12 if flag else 16)
    ingest_source(tmp_path / "c.ser", tmp_path / "o.mcap", fps=50)
    _, got, _ = _read_log(tmp_path / "o.mcap")
    for a, b in zip(got, images):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("colour", ["RGB", "BGR"])
def test_ser_colour_frames_become_luma(tmp_path: Path, colour: str) -> None:
    rgb = np.zeros((6, 8, 3), np.uint16)
    rgb[..., 0], rgb[..., 1], rgb[..., 2] = 1000, 2000, 3000
    stored = rgb if colour == "RGB" else rgb[..., ::-1]
    write_ser(tmp_path / "c.ser", [stored], colour=colour)
    with pytest.warns(ColourImageWarning, match="colour frames converted"):
        ingest_source(tmp_path / "c.ser", tmp_path / "o.mcap", fps=10)
    _, (image,), _ = _read_log(tmp_path / "o.mcap")
    assert image.dtype == np.uint16 and image[0, 0] == round(0.299 * 1000 + 0.587 * 2000 + 0.114 * 3000)


def test_ser_without_trailer_needs_a_rate(sim_frames, tmp_path: Path) -> None:
    write_ser(tmp_path / "c.ser", [image for _, image, _ in sim_frames[:4]])
    with pytest.raises(InvalidParameterError, match="no frame timestamps.*--fps"):
        ingest_source(tmp_path / "c.ser", tmp_path / "o.mcap")
    summary = ingest_source(tmp_path / "c.ser", tmp_path / "o.mcap", fps=200, start_ns=7)
    assert summary.timing == "200 fps"
    assert _read_log(tmp_path / "o.mcap")[0] == [7, 5_000_007, 10_000_007, 15_000_007]


def test_cut_off_ser_names_the_frame_or_is_skipped(sim_frames, tmp_path: Path) -> None:
    images = [image for _, image, _ in sim_frames[:6]]
    write_ser(tmp_path / "c.ser", images)
    data = (tmp_path / "c.ser").read_bytes()
    (tmp_path / "c.ser").write_bytes(data[: 178 + 4 * images[0].nbytes + 100])  # frame 4 cut, frame 5 gone
    with pytest.raises(ImageFolderError, match=r"c\.ser: frame 4-5: cut off"):
        ingest_source(tmp_path / "c.ser", tmp_path / "o.mcap", fps=10)
    assert not (tmp_path / "o.mcap").exists()
    summary = ingest_source(tmp_path / "c.ser", tmp_path / "o.mcap", fps=10, skip_bad=True)
    assert summary.frames == 4 and [name for name, _ in summary.skipped] == ["c.ser frame 4-5"]


def test_ser_times_must_increase(sim_frames, tmp_path: Path) -> None:
    images = [image for _, image, _ in sim_frames[:3]]
    write_ser(tmp_path / "c.ser", images, times_ns=[EPOCH_NS, EPOCH_NS + 100, EPOCH_NS + 100])
    with pytest.raises(ImageFolderError, match=r"c\.ser: frame 2: its timestamp .* --fps"):
        ingest_source(tmp_path / "c.ser", tmp_path / "o.mcap")


@pytest.mark.parametrize("damage, match", [
    (lambda d: d[:100], "too short for a SER file"),
    (lambda d: b"NOT-A-SER-FILE" + d[14:], "not a SER file"),
    (lambda d: d[:18] + struct.pack("<i", 16) + d[22:], "CYYM colour filter"),
    (lambda d: d[:34] + struct.pack("<i", 0) + d[38:], "invalid SER header"),
    (lambda d: d[:38] + struct.pack("<i", 0) + d[42:], "FrameCount 0 .* 1 whole frames"),
])
def test_unusable_ser_header_is_a_clear_error(tmp_path: Path, damage, match: str) -> None:
    write_ser(tmp_path / "c.ser", [np.zeros((4, 4), np.uint8)], times_ns=[EPOCH_NS])
    (tmp_path / "c.ser").write_bytes(damage((tmp_path / "c.ser").read_bytes()))
    with pytest.raises(ImageFolderError, match=match):
        ingest_source(tmp_path / "c.ser", tmp_path / "o.mcap", fps=10)


def test_random_bytes_after_a_ser_header_never_crash(tmp_path: Path) -> None:
    rng = np.random.default_rng(11)
    for trial in range(40):
        depth = int(rng.integers(1, 17))
        colour = list(COLOR_IDS)[int(rng.integers(len(COLOR_IDS)))]
        count = int(rng.integers(0, 4))
        header = struct.pack("<14s7i40s40s40sqq", b"LUCAM-RECORDER", 0, COLOR_IDS[colour], int(rng.integers(2)),
                             int(rng.integers(1, 6)), int(rng.integers(1, 6)), depth, count, b"", b"", b"", 0, 0)
        path = tmp_path / f"r{trial}.ser"
        path.write_bytes(header + rng.bytes(int(rng.integers(0, 400))))
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", ColourImageWarning)
                ingest_source(path, tmp_path / "o.mcap", fps=10, force=True, skip_bad=bool(trial % 2))
        except StarlogError:
            continue
        _read_log(tmp_path / "o.mcap")


# ---------------------------------------------------------------- video (OpenCV)
def _write_video(path: Path, images: list[np.ndarray], fourcc: str, fps: float = 25.0) -> None:
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), fps, images[0].shape[::-1], isColor=False)
    assert writer.isOpened(), f"OpenCV cannot write {fourcc} here"
    for image in images:
        writer.write(image)
    writer.release()


def _eight_bit(sim_frames) -> list[np.ndarray]:
    return [np.clip(image.astype(np.int64) // 16 - 4, 0, 255).astype(np.uint8) for _, image, _ in sim_frames]


def test_lossless_avi_round_trip(sim_frames, tmp_path: Path) -> None:
    images = _eight_bit(sim_frames)
    _write_video(tmp_path / "capture.avi", images, "FFV1", fps=25.0)
    summary = ingest_source(tmp_path / "capture.avi", tmp_path / "o.mcap", start_ns=1000)
    assert summary.frames == len(images) and summary.encoding == "mono8" and summary.timing == "video timestamps"
    got_times, got_images, infos = _read_log(tmp_path / "o.mcap")
    assert got_times == [1000 + n * 40_000_000 for n in range(len(images))]  # container times at 25 fps
    for got, want in zip(got_images, images):
        assert np.abs(got.astype(int) - want).max() <= 1
    assert infos[2]["source"] == "capture.avi frame 2"


def test_lossy_video_is_noted_and_close(sim_frames, tmp_path: Path) -> None:
    images = _eight_bit(sim_frames)
    _write_video(tmp_path / "capture.avi", images, "MJPG")
    with pytest.warns(LossyImageWarning, match=r"capture\.avi \(MJPG\) is lossy"):
        summary = ingest_source(tmp_path / "capture.avi", tmp_path / "o.mcap", fps=100)
    assert summary.frames == len(images) and summary.timing == "100 fps"
    _, got_images, _ = _read_log(tmp_path / "o.mcap")
    assert np.mean([np.abs(g.astype(int) - w).mean() for g, w in zip(got_images, images)]) < 3


def test_damaged_video_names_the_frames_or_skips_them(sim_frames, tmp_path: Path) -> None:
    images = _eight_bit(sim_frames) * 3
    _write_video(tmp_path / "v.avi", images, "MJPG")
    data = (tmp_path / "v.avi").read_bytes()
    (tmp_path / "v.avi").write_bytes(data[: len(data) // 2])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", LossyImageWarning)
        with pytest.raises(ImageFolderError, match=r"v\.avi: frame \d+-\d+: cannot be decoded"):
            ingest_source(tmp_path / "v.avi", tmp_path / "o.mcap", fps=100)
        summary = ingest_source(tmp_path / "v.avi", tmp_path / "o.mcap", fps=100, skip_bad=True)
    assert 0 < summary.frames < len(images) and summary.skipped
    assert summary.frames + sum(_count(name) for name, _ in summary.skipped) == len(images)


def _count(name: str) -> int:
    first, _, last = name.rsplit(" ", 1)[1].partition("-")
    return int(last or first) - int(first) + 1


def test_not_a_video(tmp_path: Path) -> None:
    (tmp_path / "v.mp4").write_bytes(b"\0" * 1000)
    with pytest.raises(ImageFolderError, match=r"v\.mp4: cannot be opened as a video"):
        ingest_source(tmp_path / "v.mp4", tmp_path / "o.mcap", fps=10)


# ---------------------------------------------------------------- JPEG, BMP
def test_jpeg_is_warned_about_and_centroids_stay_close(sim_frames, tmp_path: Path) -> None:
    from starlog.centroiding import extract_stars

    folder = tmp_path / "jpg"
    folder.mkdir()
    _, image16, truth = sim_frames[0]
    image = np.clip(image16.astype(np.int64) // 16 - 4, 0, 255).astype(np.uint8)
    assert cv2.imwrite(str(folder / "f0.jpg"), image, [cv2.IMWRITE_JPEG_QUALITY, 95])
    with pytest.warns(LossyImageWarning, match="f0.jpg is lossy.*biases sub-pixel centroids"):
        summary = ingest_source(folder, tmp_path / "o.mcap", fps=10)
    assert any("lossy" in note for note in summary.notes)
    _, (decoded,), _ = _read_log(tmp_path / "o.mcap")
    assert decoded.dtype == np.uint8 and np.abs(decoded.astype(int) - image).max() > 0  # it is lossy
    exact = extract_stars(image, methods=["MOMENT"], psf_sigma=1.2)[1]["MOMENT"]
    lossy = extract_stars(decoded, methods=["MOMENT"], psf_sigma=1.2)[1]["MOMENT"]
    assert len(exact) == len(lossy) == len(truth)
    shifts = [np.hypot(exact["x"] - r["x"], exact["y"] - r["y"]).min() for r in lossy]
    print(f"JPEG q95 centroid shifts: {np.round(shifts, 4)} px")
    assert max(shifts) < 0.05


def test_bmp_and_a_single_image_file(tmp_path: Path) -> None:
    folder = tmp_path / "bmp"
    folder.mkdir()
    for n in range(3):
        assert cv2.imwrite(str(folder / f"f{n}.bmp"), np.full((5, 7), 10 * n, np.uint8))
    summary = ingest_source(folder, tmp_path / "o.mcap", fps=10)
    assert summary.frames == 3 and [int(i[0, 0]) for i in _read_log(tmp_path / "o.mcap")[1]] == [0, 10, 20]
    summary = ingest_source(folder / "f2.bmp", tmp_path / "one.mcap", fps=10)
    assert summary.frames == 1


def test_folder_of_videos_points_to_the_files(tmp_path: Path) -> None:
    (tmp_path / "in").mkdir()
    write_ser(tmp_path / "in" / "a.ser", [np.zeros((4, 4), np.uint8)])
    with pytest.raises(ImageFolderError, match="no image files.*a.ser"):
        ingest_source(tmp_path / "in", tmp_path / "o.mcap", fps=10)


def test_time_pattern_is_for_folders(tmp_path: Path) -> None:
    write_ser(tmp_path / "c.ser", [np.zeros((4, 4), np.uint8)])
    with pytest.raises(InvalidParameterError, match="--time-pattern"):
        ingest_source(tmp_path / "c.ser", tmp_path / "o.mcap", time_pattern=r"(?P<t>\d+)")


# ---------------------------------------------------------------- command line
def test_cli_ingests_a_ser_file_with_one_line_notes(tmp_path: Path) -> None:
    mosaic = np.zeros((8, 8), np.uint8)
    mosaic[::2, ::2] = 100
    write_ser(tmp_path / "c.ser", [mosaic] * 3, colour="RGGB", times_ns=[EPOCH_NS + n * 1000 for n in range(3)])
    result = CliRunner().invoke(cli, ["ingest", str(tmp_path / "c.ser"), "-o", str(tmp_path / "o.mcap"), "--json",
                                      "-q"])
    assert result.exit_code == 0, result.output
    data = json.loads(result.stdout)
    assert data["frames"] == 3 and data["timing"] == "SER timestamps" and data["first_log_time"] == EPOCH_NS
    assert result.stderr.strip() == "note: c.ser: Bayer RGGB frames debayered to mono (luma)."
    result = CliRunner().invoke(cli, ["ingest", str(tmp_path / "c.ser"), "-o", str(tmp_path / "o.mcap"),
                                      "--rate", "30", "--force"])
    assert result.exit_code == 0 and "timed by 30 fps" in result.stderr
