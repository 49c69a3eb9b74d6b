"""Ingest of TIFF as cameras and libraries write it: every compression, tiles and strips, both byte
orders, and each layout the PNG path takes giving the same frames as PNG."""

from __future__ import annotations

import warnings
from pathlib import Path

import cv2
import imagecodecs
import numpy as np
import pytest
import tifffile
from click.testing import CliRunner
from PIL import Image

from starlog.cli import cli
from starlog.errors import ImageFolderError
from starlog.io import LogReader
from starlog.stages import ingest_folder
from starlog.stages.ingest import ColourImageWarning, LossyImageWarning

SHAPE = (20, 36)  # two rows of three 16x16 tiles, the last row and column cut short
RNG = np.random.default_rng(34)


def _pixels(dtype: type, shape: tuple[int, ...] = SHAPE) -> np.ndarray:
    return RNG.integers(0, np.iinfo(dtype).max, shape, dtype=dtype, endpoint=True)


def _ingested(folder: Path, tmp_path: Path) -> list[np.ndarray]:
    ingest_folder(folder, tmp_path / "o.mcap", fps=10)
    with LogReader(tmp_path / "o.mcap") as log:
        return [image for _, _, image in log.frames()]


def _first_page(path: Path) -> tifffile.TiffPage:
    with tifffile.TiffFile(path) as tif:
        return tif.pages.first


def _folder(tmp_path: Path, name: str = "in") -> Path:
    folder = tmp_path / name
    folder.mkdir()
    return folder


# ---------------------------------------------------------------- tifffile: compressions, tiles, byte orders
COMPRESSIONS = [
    {"compression": "lzw"},
    {"compression": "lzw", "predictor": True},
    {"compression": "zlib"},  # Deflate, as libtiff writes it
    {"compression": "adobe_deflate", "predictor": True},
    {"compression": "zstd"},
    {"compression": "packbits"},
    {},
]
LAYOUTS = {"strips": {"rowsperstrip": 3}, "tiles": {"tile": (16, 16)}}


@pytest.mark.parametrize("byteorder", ["<", ">"])
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
@pytest.mark.parametrize("layout", sorted(LAYOUTS))
@pytest.mark.parametrize("compression", COMPRESSIONS, ids=lambda c: "+".join(map(str, c.values())) or "none")
def test_tiff_frames_ingest_as_written(tmp_path: Path, compression: dict, layout: str, dtype: type,
                                       byteorder: str) -> None:
    folder = _folder(tmp_path)
    frames = [_pixels(dtype) for _ in range(2)]
    for n, frame in enumerate(frames):
        tifffile.imwrite(folder / f"f{n}.tif", frame, byteorder=byteorder, **compression, **LAYOUTS[layout])
    assert _first_page(folder / "f0.tif").is_tiled == (layout == "tiles")
    got = _ingested(folder, tmp_path)
    assert len(got) == 2
    for image, frame in zip(got, frames):
        assert image.dtype == dtype
        np.testing.assert_array_equal(image, frame)


# ---------------------------------------------------------------- OpenCV (LZW by default), through the CLI
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_opencv_tiff_folder_ingests_through_the_cli(tmp_path: Path, dtype: type) -> None:
    folder = _folder(tmp_path)
    frames = [_pixels(dtype) for _ in range(3)]
    for n, frame in enumerate(frames):
        assert cv2.imwrite(str(folder / f"img{n}.tif"), frame)
    assert _first_page(folder / "img0.tif").compression.name == "LZW"
    result = CliRunner().invoke(cli, ["ingest", str(folder), "-o", str(tmp_path / "o.mcap"), "--fps", "10"])
    assert result.exit_code == 0, result.output
    with LogReader(tmp_path / "o.mcap") as log:
        got = [image for _, _, image in log.frames()]
    for image, frame in zip(got, frames, strict=True):
        np.testing.assert_array_equal(image, frame)


# ---------------------------------------------------------------- float: refused, as from every format
def _opencv_float(path: Path, image: np.ndarray) -> None:
    assert cv2.imwrite(str(path), image)


FLOAT_WRITERS = {
    "float32 lzw+predictor": lambda p, a: tifffile.imwrite(p, a.astype(np.float32), compression="lzw",
                                                            predictor=True),
    "float32 zstd tiled": lambda p, a: tifffile.imwrite(p, a.astype(np.float32), compression="zstd",
                                                         tile=(16, 16)),
    "float64 big-endian": lambda p, a: tifffile.imwrite(p, a.astype(np.float64), byteorder=">"),
    "float16": lambda p, a: tifffile.imwrite(p, a.astype(np.float16)),
    "float32 OpenCV": lambda p, a: _opencv_float(p, a.astype(np.float32)),
}


@pytest.mark.parametrize("writer", sorted(FLOAT_WRITERS))
def test_float_tiff_is_refused_in_one_line(tmp_path: Path, writer: str) -> None:
    folder = _folder(tmp_path)
    FLOAT_WRITERS[writer](folder / "f.tif", _pixels(np.uint8) / 255.0)
    with pytest.raises(ImageFolderError, match=r"pixel type float\d+; starlog ingests 8- or 16-bit unsigned") as err:
        ingest_folder(folder, tmp_path / "o.mcap", fps=10)
    assert "\n" not in str(err.value)
    assert not (tmp_path / "o.mcap").exists()


# ---------------------------------------------------------------- each layout the PNG path takes: same frames
def _rgb(dtype: type, channels: int) -> np.ndarray:
    return _pixels(dtype, (*SHAPE, channels))


def _bgr(rgb: np.ndarray) -> np.ndarray:
    return rgb[..., [2, 1, 0, 3][: rgb.shape[2]]]


def _write_palette(path: Path, index: np.ndarray, colours: np.ndarray) -> None:
    image = Image.fromarray(index, "P")
    image.putpalette(colours.tolist())
    image.save(path)


def _layouts() -> dict[str, tuple]:
    """Name → (write the PNG, write the TIFF), both of one image."""
    mono8, mono16, rgb8, rgb16, rgba8, rgba16 = (_pixels(np.uint8), _pixels(np.uint16), _rgb(np.uint8, 3),
                                                 _rgb(np.uint16, 3), _rgb(np.uint8, 4), _rgb(np.uint16, 4))
    grey_alpha = _rgb(np.uint8, 2)
    bilevel = _pixels(np.uint8) > 127
    index, colours = _pixels(np.uint8) % 8, _pixels(np.uint8, (8 * 3,))
    return {
        "mono8": (lambda p: cv2.imwrite(str(p), mono8), lambda p: cv2.imwrite(str(p), mono8)),
        "mono16": (lambda p: cv2.imwrite(str(p), mono16), lambda p: tifffile.imwrite(p, mono16, compression="zlib")),
        "rgb8": (lambda p: cv2.imwrite(str(p), _bgr(rgb8)), lambda p: cv2.imwrite(str(p), _bgr(rgb8))),
        "rgb16": (lambda p: cv2.imwrite(str(p), _bgr(rgb16)),
                  lambda p: tifffile.imwrite(p, rgb16, photometric="rgb", compression="lzw", predictor=True)),
        "rgba8": (lambda p: cv2.imwrite(str(p), _bgr(rgba8)), lambda p: cv2.imwrite(str(p), _bgr(rgba8))),
        "rgba16": (lambda p: cv2.imwrite(str(p), _bgr(rgba16)),
                   lambda p: tifffile.imwrite(p, rgba16, photometric="rgb", extrasamples=["unassalpha"])),
        "rgb8 planar": (lambda p: cv2.imwrite(str(p), _bgr(rgb8)),
                        lambda p: tifffile.imwrite(p, np.moveaxis(rgb8, -1, 0), photometric="rgb",
                                                   planarconfig="separate", compression="zstd")),
        "grey+alpha": (lambda p: p.write_bytes(imagecodecs.png_encode(grey_alpha)),
                       lambda p: tifffile.imwrite(p, grey_alpha, photometric="minisblack",
                                                  extrasamples=["unassalpha"])),
        "palette": (lambda p: _write_palette(p, index, colours), lambda p: _write_palette(p, index, colours)),
        "bilevel": (lambda p: Image.fromarray(bilevel).save(p), lambda p: Image.fromarray(bilevel).save(p)),
        "bilevel miniswhite": (lambda p: Image.fromarray(bilevel).save(p),
                               lambda p: tifffile.imwrite(p, ~bilevel, photometric="miniswhite")),
    }


@pytest.mark.parametrize("layout", sorted(_layouts()))
def test_tiff_gives_the_frames_png_gives(tmp_path: Path, layout: str) -> None:
    write_png, write_tiff = _layouts()[layout]
    png, tiff = _folder(tmp_path, "png"), _folder(tmp_path, "tiff")
    write_png(png / "f.png")
    write_tiff(tiff / "f.tif")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ColourImageWarning)
        (from_png,), (from_tiff,) = _ingested(png, tmp_path / "png"), _ingested(tiff, tmp_path / "tiff")
    assert from_tiff.dtype == from_png.dtype
    np.testing.assert_array_equal(from_tiff, from_png)


def test_miniswhite_tiff_is_inverted(tmp_path: Path) -> None:
    folder = _folder(tmp_path)
    frame = _pixels(np.uint16)
    tifffile.imwrite(folder / "f.tif", frame, photometric="miniswhite", compression="lzw")
    (image,) = _ingested(folder, tmp_path)
    np.testing.assert_array_equal(image, 65535 - frame)


# ---------------------------------------------------------------- what is refused or noted
def test_stack_in_one_file_is_refused_in_one_line(tmp_path: Path) -> None:
    folder = _folder(tmp_path)
    tifffile.imwrite(folder / "stack.tif", _pixels(np.uint16, (3, *SHAPE)), photometric="minisblack")
    with pytest.raises(ImageFolderError, match=r"stack.tif: holds images of shape \(3, 20, 36\).*one file per frame"):
        ingest_folder(folder, tmp_path / "o.mcap", fps=10)


def test_cmyk_tiff_is_refused_in_one_line(tmp_path: Path) -> None:
    folder = _folder(tmp_path)
    tifffile.imwrite(folder / "f.tif", _rgb(np.uint8, 4), photometric="separated")
    with pytest.raises(ImageFolderError, match="is a SEPARATED TIFF; starlog reads grey, RGB and palette TIFF"):
        ingest_folder(folder, tmp_path / "o.mcap", fps=10)


def test_jpeg_compressed_tiff_is_noted_as_lossy(tmp_path: Path) -> None:
    folder = _folder(tmp_path)
    tifffile.imwrite(folder / "f.tif", _pixels(np.uint8), compression="jpeg")
    with pytest.warns(LossyImageWarning, match="TIFF with JPEG compression"):
        summary = ingest_folder(folder, tmp_path / "o.mcap", fps=10)
    assert summary.frames == 1 and any("lossy" in note for note in summary.notes)


def test_damaged_compressed_tiff_names_its_compression(tmp_path: Path) -> None:
    folder = _folder(tmp_path)
    tifffile.imwrite(folder / "f.tif", _pixels(np.uint16), compression="zstd")
    data = bytearray((folder / "f.tif").read_bytes())
    start = _first_page(folder / "f.tif").dataoffsets[0]
    data[start:start + 32] = bytes(32)  # the start of the compressed strip
    (folder / "f.tif").write_bytes(bytes(data))
    with pytest.raises(ImageFolderError, match=r"f.tif: has TIFF pixels \(ZSTD compression\) that cannot be decoded"):
        ingest_folder(folder, tmp_path / "o.mcap", fps=10)
