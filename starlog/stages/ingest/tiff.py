"""TIFF frames for ingest, as cameras and imaging libraries write them.

tifffile reads the layout (strips or tiles, either byte order, contiguous or planar samples,
predictors) and imagecodecs decodes the compression (LZW, Deflate, ZSTD, PackBits, JPEG, ...).
The first image of the file comes back in native byte order as :func:`read_image` takes an image
of any format: 2-D grey, or (H, W, 3 or 4) RGB(A) for its conversion to luma. Grey + alpha gives
its grey, a palette image its colours (8-bit for an 8-bit index, as OpenCV reads a palette PNG),
a bilevel image 0/255 and a MinIsWhite image is inverted, so that a star is bright. A stack of
images in one file is refused: ingest takes one frame per file.
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from starlog.errors import ImageFolderError
from starlog.stages.ingest.image_warnings import lossy_warning

__all__ = ["read_tiff"]

_ONE_IMAGE_AXES = {"YX", "YXS", "SYX"}
_LOSSY_COMPRESSIONS = {"JPEG", "OJPEG"}
_PHOTOMETRICS = {"MINISBLACK", "MINISWHITE", "RGB", "PALETTE"}


def read_tiff(path: Path) -> npt.NDArray[Any]:
    """The first image of a TIFF file: 2-D grey or (H, W, 3 or 4) RGB(A), native byte order.

    Raises :class:`ImageFolderError` for a stack of images, a colour model other than grey, RGB and
    palette, or pixels that cannot be decoded.
    """
    import tifffile

    with tifffile.TiffFile(path) as tif:
        series = tif.series[0]
        page = series.keyframe
        if not series.axes:
            raise ImageFolderError(path, "has no image tifffile can read (damaged, or not an image).")
        if series.axes not in _ONE_IMAGE_AXES:
            raise ImageFolderError(path, f"holds images of shape {series.shape} (axes {series.axes}); starlog "
                                         "ingests one 2-D frame per file: save the stack as one file per frame.")
        photometric, compression = page.photometric.name, page.compression.name
        _check_photometric(path, photometric, compression)
        image = _decode(path, series, compression)
        if series.axes == "SYX":  # planar samples: RGBRGB... as planes
            image = np.moveaxis(image, 0, -1)
        if compression in _LOSSY_COMPRESSIONS:
            warnings.warn(lossy_warning(f"{path.name} (TIFF with {compression} compression)"), stacklevel=3)
        return _as_grey_or_rgb(image, photometric, page.bitspersample, page.colormap)


def _check_photometric(path: Path, photometric: str, compression: str) -> None:
    if photometric in _PHOTOMETRICS or (photometric == "YCBCR" and compression in _LOSSY_COMPRESSIONS):
        return  # a JPEG decoder gives YCbCr as RGB
    raise ImageFolderError(path, f"is a {photometric} TIFF; starlog reads grey, RGB and palette TIFF "
                                 "(save it as grey or RGB first).")


def _decode(path: Path, series: Any, compression: str) -> npt.NDArray[Any]:
    try:
        return np.asarray(series.asarray())
    except Exception as err:  # codecs raise many unrelated types on damaged data
        raise ImageFolderError(path, f"has TIFF pixels ({compression} compression) that cannot be decoded "
                                     f"({type(err).__name__}: {err}).") from err


def _as_grey_or_rgb(image: npt.NDArray[Any], photometric: str, bits: int,
                    colormap: npt.NDArray[np.uint16] | None) -> npt.NDArray[Any]:
    if photometric == "MINISWHITE":
        image = ~image if image.dtype == bool else _inverted(image, bits)
    if image.dtype == bool:
        return image.astype(np.uint8) * np.uint8(255)
    if photometric == "PALETTE" and colormap is not None:
        colours = np.moveaxis(colormap[:, image], 0, -1)
        return (colours >> 8).astype(np.uint8) if image.dtype == np.uint8 else colours
    if image.ndim == 3 and image.shape[2] == 2:  # grey + alpha
        return image[..., 0]
    return image


def _inverted(image: npt.NDArray[Any], bits: int) -> npt.NDArray[Any]:
    if image.dtype.kind != "u":
        return image  # refused later for its pixel type
    return (np.uint64(2**bits - 1) - image).astype(image.dtype)
