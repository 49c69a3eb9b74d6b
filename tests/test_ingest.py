"""Image-folder ingest: round trip with the simulator, ordering, timestamps, bad input."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import tifffile

from starlog.errors import ImageFolderError, InvalidParameterError, OutputExistsError
from starlog.io import LogReader
from starlog import topics
from starlog.stages import ingest_folder
from starlog.stages.ingest import ColourImageWarning, natural_key


def _write_frames(sim_log: Path, folder: Path, suffix: str) -> list[tuple[int, np.ndarray]]:
    folder.mkdir()
    frames = []
    with LogReader(sim_log) as log:
        for index, t, image in log.frames():
            name = folder / f"frame{index}{suffix}"
            if suffix == ".png":
                assert cv2.imwrite(str(name), image)
            else:
                tifffile.imwrite(name, image)
            frames.append((t, image))
    return frames


@pytest.mark.parametrize("suffix", [".png", ".tif"])
def test_folder_round_trip_gives_identical_pixels_and_times(sim_log: Path, tmp_path: Path, suffix: str) -> None:
    frames = _write_frames(sim_log, tmp_path / "frames", suffix)
    summary = ingest_folder(tmp_path / "frames", tmp_path / "lab.mcap", fps=100.0, workers=2)
    assert summary.frames == 20 and summary.encoding == "mono16" and not summary.skipped
    with LogReader(tmp_path / "lab.mcap") as log:
        got = [(t, image) for _, t, image in log.frames()]
        sources = [m.payload["source"] for m in log.messages(topics.FRAME_INFO)]
        assert log.provenance()[0].stage == "ingest"
    assert [t for t, _ in got] == [t for t, _ in frames]  # natural order: frame2 before frame10
    for (_, a), (_, b) in zip(got, frames):
        np.testing.assert_array_equal(a, b)
    assert sources[:3] == [f"frame0{suffix}", f"frame1{suffix}", f"frame2{suffix}"]


def test_natural_key_orders_numbers_by_value() -> None:
    names = ["img10.png", "img2.png", "img1.png", "Img3.png"]
    assert sorted(names, key=natural_key) == ["img1.png", "img2.png", "Img3.png", "img10.png"]


def _folder(tmp_path: Path, images: dict[str, np.ndarray]) -> Path:
    folder = tmp_path / "in"
    folder.mkdir()
    for name, image in images.items():
        cv2.imwrite(str(folder / name), image)
    return folder


def test_time_pattern_parses_file_names(tmp_path: Path) -> None:
    img = np.zeros((8, 8), np.uint8)
    folder = _folder(tmp_path, {"a_1500us.png": img, "a_3500us.png": img, "a_900us.png": img})
    ingest_folder(folder, tmp_path / "o.mcap", time_pattern=r"_(?P<t>\d+)us", time_unit="us", start_ns=7)
    with LogReader(tmp_path / "o.mcap") as log:
        assert [t for _, t, _ in log.frames()] == [900_007, 1_500_007, 3_500_007]


def test_eight_bit_frames_stay_mono8(tmp_path: Path) -> None:
    folder = _folder(tmp_path, {"1.png": np.full((6, 5), 7, np.uint8)})
    summary = ingest_folder(folder, tmp_path / "o.mcap", fps=10)
    assert summary.encoding == "mono8"
    with LogReader(tmp_path / "o.mcap") as log:
        (_, _, image), = log.frames()
    assert image.dtype == np.uint8 and image.shape == (6, 5) and image[0, 0] == 7


def test_colour_image_is_converted_with_a_warning(tmp_path: Path) -> None:
    rgb = np.zeros((4, 4, 3), np.uint8)
    rgb[..., 1] = 100  # green
    folder = _folder(tmp_path, {"c.png": rgb})
    with pytest.warns(ColourImageWarning, match="converted to mono"):
        ingest_folder(folder, tmp_path / "o.mcap", fps=10)
    with LogReader(tmp_path / "o.mcap") as log:
        (_, _, image), = log.frames()
    assert image[0, 0] == round(0.587 * 100)


def test_rgba_png_is_converted_from_its_colours_not_its_alpha(tmp_path: Path) -> None:
    bgra = np.zeros((4, 4, 4), np.uint8)
    bgra[..., 2], bgra[..., 3] = 200, 255  # red, opaque
    folder = _folder(tmp_path, {"c.png": bgra})
    with pytest.warns(ColourImageWarning, match="converted to mono"):
        ingest_folder(folder, tmp_path / "o.mcap", fps=10)
    with LogReader(tmp_path / "o.mcap") as log:
        (_, _, image), = log.frames()
    assert (image == round(0.299 * 200)).all()


def test_empty_folder(tmp_path: Path) -> None:
    (tmp_path / "empty").mkdir()
    with pytest.raises(ImageFolderError, match="no image files"):
        ingest_folder(tmp_path / "empty", tmp_path / "o.mcap", fps=10)
    assert not (tmp_path / "o.mcap").exists()


def test_unreadable_file_is_named_and_nothing_is_written(tmp_path: Path) -> None:
    folder = _folder(tmp_path, {"1.png": np.zeros((8, 8), np.uint16)})
    (folder / "2.png").write_bytes(b"not a png at all")
    with pytest.raises(ImageFolderError, match="2.png"):
        ingest_folder(folder, tmp_path / "o.mcap", fps=10)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in"]


def test_mismatched_size_stops_or_is_skipped(tmp_path: Path) -> None:
    folder = _folder(tmp_path, {"1.png": np.zeros((8, 8), np.uint16), "2.png": np.zeros((9, 8), np.uint16),
                                "3.png": np.zeros((8, 8), np.uint8), "4.png": np.ones((8, 8), np.uint16)})
    with pytest.raises(ImageFolderError, match="2.png.*all frames must match"):
        ingest_folder(folder, tmp_path / "o.mcap", fps=10)
    summary = ingest_folder(folder, tmp_path / "o.mcap", fps=10, skip_bad=True)
    assert summary.frames == 2 and [name for name, _ in summary.skipped] == ["2.png", "3.png"]


def test_existing_output_is_kept_without_force(tmp_path: Path) -> None:
    folder = _folder(tmp_path, {"1.png": np.zeros((8, 8), np.uint16)})
    (tmp_path / "o.mcap").write_bytes(b"old")
    with pytest.raises(OutputExistsError):
        ingest_folder(folder, tmp_path / "o.mcap", fps=10)
    assert (tmp_path / "o.mcap").read_bytes() == b"old"


def test_timing_is_required(tmp_path: Path) -> None:
    folder = _folder(tmp_path, {"1.png": np.zeros((8, 8), np.uint16)})
    with pytest.raises(InvalidParameterError, match="--fps"):
        ingest_folder(folder, tmp_path / "o.mcap")
    with pytest.raises(InvalidParameterError, match="named group 't'"):
        ingest_folder(folder, tmp_path / "o.mcap", time_pattern=r"\d+")


def test_float_images_are_refused_with_advice(tmp_path: Path) -> None:
    folder = tmp_path / "in"
    folder.mkdir()
    tifffile.imwrite(folder / "f.tif", np.zeros((4, 4), np.float32))
    with pytest.raises(ImageFolderError, match="8- or 16-bit unsigned"):
        ingest_folder(folder, tmp_path / "o.mcap", fps=10)


def test_fits_frames_ingest_with_the_extra(tmp_path: Path) -> None:
    fits = pytest.importorskip("astropy.io.fits", reason="FITS needs the extra: pip install 'starlog[fits]'")
    folder = tmp_path / "fits"
    folder.mkdir()
    rng = np.random.default_rng(8)
    frames = [rng.integers(0, 60000, (12, 10), dtype=np.uint16) for _ in range(3)]
    for n, frame in enumerate(frames):
        fits.PrimaryHDU(frame).writeto(folder / f"f{n}.fits")  # stored as int16 + BZERO 32768
    summary = ingest_folder(folder, tmp_path / "o.mcap", fps=50)
    assert summary.frames == 3 and summary.encoding == "mono16"
    with LogReader(tmp_path / "o.mcap") as log:
        for (_, _, image), frame in zip(log.frames(), frames):
            np.testing.assert_array_equal(image, frame)
