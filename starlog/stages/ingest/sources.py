"""Where ingested frames come from: image files, SER files and video files, as one stream of frames.

Each source yields :class:`SourceFrame` items in order: the 2-D uint8/uint16 image or the reason
it cannot be used, the frame's position (for rate timing) and its time from the file, if the file
keeps one (SER timestamp trailer, video container timestamps).

Colour (RGB/BGR) frames become luma ``0.299 R + 0.587 G + 0.114 B``; Bayer frames are debayered
to mono with OpenCV; both with a :class:`ColourImageWarning`. Lossy files (JPEG, JPEG-compressed TIFF,
lossy video codecs) give a :class:`LossyImageWarning`: compression artefacts bias sub-pixel centroids
(both warnings in :mod:`starlog.stages.ingest.image_warnings`).
"""

from __future__ import annotations

import re
import warnings
from collections.abc import Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from starlog.errors import ImageFolderError
from starlog.stages.ingest.ser import HEADER_SIZE, SerReader
from starlog.stages.ingest.image_warnings import ColourImageWarning, LossyImageWarning, lossy_warning
from starlog.replay.pool import ordered_map

__all__ = ["IMAGE_SUFFIXES", "SER_SUFFIXES", "VIDEO_SUFFIXES", "ColourImageWarning", "LossyImageWarning",
           "SourceFrame", "folder_frames", "list_images", "natural_key", "read_image", "ser_frames", "video_frames"]

IMAGE_SUFFIXES = {".png", ".tif", ".tiff", ".fits", ".fit", ".fts", ".jpg", ".jpeg", ".bmp"}
LOSSY_SUFFIXES = {".jpg", ".jpeg"}
SER_SUFFIXES = {".ser"}
VIDEO_SUFFIXES = {".avi", ".mp4", ".mov", ".mkv"}
_LUMA = np.array([0.299, 0.587, 0.114])
# FourCCs of lossless codecs OpenCV/FFmpeg read; anything else is treated as lossy.
_LOSSLESS_FOURCCS = {"FFV1", "HFYU", "FFVH", "MPNG", "PNG ", "RGBA", "Y800", "GREY", "Y16 ", "LAGS", "UTVD", "DIB "}


@dataclass
class SourceFrame:
    """One frame of a source: ``image`` or, if it cannot be used, ``problem`` (a sentence)."""

    name: str
    path: Path
    position: int
    image: npt.NDArray[Any] | None = None
    problem: str | None = None
    file_time_ns: int | None = None
    bit_depth: int = 0
    caught: list[warnings.WarningMessage] = field(default_factory=list)

    def error(self) -> ImageFolderError:
        """The error naming this frame's file (and frame number, for video)."""
        where = self.name[len(self.path.name):].strip()
        return ImageFolderError(self.path, f"{where}: {self.problem}" if where else str(self.problem))


def natural_key(name: str) -> list[Any]:
    """Sort key that orders digit runs by value: ``f2`` < ``f10``."""
    return [int(part) if part.isdigit() else part.lower() for part in re.split(r"(\d+)", name)]


def luma(image: npt.NDArray[Any]) -> npt.NDArray[Any]:
    """Mono (luma) of an (H, W, 3 or 4) RGB(A) image, same dtype."""
    return np.rint(image[..., :3].astype(np.float64) @ _LUMA).astype(image.dtype)


# ---------------------------------------------------------------- image files
def read_image(path: Path) -> npt.NDArray[np.uint8] | npt.NDArray[np.uint16]:
    """Read one image file as a 2-D uint8/uint16 array.

    Colour images are converted to mono (with :class:`ColourImageWarning`).

    Raises
    ------
    ImageFolderError
        The file cannot be decoded, or its pixel type is not 8/16-bit unsigned.
    """
    suffix = path.suffix.lower()
    try:
        if suffix in {".fits", ".fit", ".fts"}:
            image = _read_fits(path)
        elif suffix in {".tif", ".tiff"}:
            from starlog.stages.ingest.tiff import read_tiff

            image = read_tiff(path)
        else:
            import cv2

            image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            if image is not None and image.ndim == 3:
                image = image[..., 2::-1]  # OpenCV gives BGR(A): RGB, without the alpha luma ignores
    except ImageFolderError:
        raise
    except Exception as err:  # decoders raise many unrelated types on damaged files
        raise ImageFolderError(path, f"cannot be read as an image ({type(err).__name__}: {err}).") from err
    if image is None:
        raise ImageFolderError(path, "cannot be read as an image (damaged or not an image file).")
    image = np.asarray(image)
    if image.ndim == 3 and image.shape[2] in (3, 4):
        warnings.warn(f"{path.name}: colour image converted to mono (luma).", ColourImageWarning, stacklevel=2)
        image = luma(image)
    if image.ndim != 2:
        raise ImageFolderError(path, f"has shape {image.shape}; starlog ingests 2-D mono (or RGB) frames.")
    if image.dtype not in (np.uint8, np.uint16):
        raise ImageFolderError(
            path, f"has pixel type {image.dtype}; starlog ingests 8- or 16-bit unsigned frames. Convert it first."
        )
    return image


def _read_fits(path: Path) -> npt.NDArray[Any]:
    try:
        from astropy.io import fits
    except ImportError as err:
        raise ImageFolderError(path, "is FITS; install the extra to read it: pip install 'starlog[fits]'.") from err
    with fits.open(path, memmap=False) as hdul:
        for hdu in hdul:
            if hdu.data is not None and hdu.data.ndim == 2:
                data = np.asarray(hdu.data)
                bzero = hdu.header.get("BZERO", 0)
                if data.dtype.kind == "i" and data.dtype.itemsize == 2 and bzero == 32768:
                    data = (data.astype(np.int32) + 32768).astype(np.uint16)
                if data.dtype.kind == "u" or data.dtype.kind == "i":
                    if data.min() >= 0 and data.max() <= 65535:
                        return data.astype(np.uint16 if data.max() > 255 or data.dtype.itemsize > 1 else np.uint8)
                return data
    raise ImageFolderError(path, "has no 2-D image in any HDU.")


def list_images(folder: Path) -> list[Path]:
    """Image files of ``folder`` (not recursive) in natural name order."""
    if not folder.is_dir():
        raise ImageFolderError(folder, "is not a folder.")
    files = [p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES]
    if not files:
        videos = sorted(p.name for p in folder.iterdir() if p.suffix.lower() in SER_SUFFIXES | VIDEO_SUFFIXES)
        hint = f" It holds video files: ingest each one (starlog ingest {folder / videos[0]} ...)." if videos else ""
        raise ImageFolderError(
            folder, f"contains no image files ({', '.join(sorted(IMAGE_SUFFIXES))}); nothing to ingest.{hint}"
        )
    return sorted(files, key=lambda p: natural_key(p.name))


def folder_frames(files: Sequence[Path], workers: int) -> Iterator[SourceFrame]:
    """Decode image files in order on ``workers`` threads (decoders release the GIL)."""

    def decode(position: int, path: Path) -> SourceFrame:
        frame = SourceFrame(path.name, path, position)
        try:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                frame.image = read_image(path)
            frame.caught = list(caught)
            frame.bit_depth = 16 if frame.image.dtype == np.uint16 else 8
        except ImageFolderError as err:
            frame.problem = err.reason
        return frame

    if workers <= 1:
        for position, path in enumerate(files):
            yield decode(position, path)
        return
    with ThreadPoolExecutor(max_workers=workers) as pool:
        yield from ordered_map(pool, decode, enumerate(files), window=4 * workers)


# ---------------------------------------------------------------- SER
def ser_frames(path: Path) -> tuple[int, bool, Iterator[SourceFrame]]:
    """``(frame count, has timestamps, frames)`` of a SER file (format: :mod:`starlog.stages.ingest.ser`)."""
    with SerReader(path) as reader:
        count, times = reader.header.frame_count, reader.timestamps_ns()
        if count == 0:
            whole = (reader.size - HEADER_SIZE) // reader.header.frame_bytes
            raise ImageFolderError(path, f"has FrameCount 0 in its header (its bytes hold {whole} whole frames: "
                                         "the capture may not have been closed properly).")
    return count, times is not None, _ser_iter(path, times)


def _ser_iter(path: Path, times: list[int] | None) -> Iterator[SourceFrame]:
    with SerReader(path) as reader:
        header = reader.header
        for index in range(header.frame_count):
            frame = SourceFrame(f"{path.name} frame {index}", path, index, bit_depth=header.depth,
                                file_time_ns=None if times is None else times[index])
            if index >= reader.frames_in_file:  # the file was cut off here: one entry for the frames lost
                last = header.frame_count - 1
                frame.name = f"{path.name} frame {index}" + (f"-{last}" if last > index else "")
                frame.problem = f"cut off (the file ends at byte {reader.size}, before the frame's last byte)."
                yield frame
                return
            raw = reader.read_frame(index)
            frame.image = _ser_to_mono(raw, header.colour)
            if index == 0 and header.colour != "mono":
                what = f"Bayer {header.colour} frames debayered" if raw.ndim == 2 else "colour frames converted"
                frame.caught = [_message(ColourImageWarning(f"{path.name}: {what} to mono (luma)."))]
            yield frame


def _ser_to_mono(raw: npt.NDArray[Any], colour: str) -> npt.NDArray[Any]:
    if colour == "mono":
        return raw
    if colour in ("RGB", "BGR"):
        return luma(raw if colour == "RGB" else raw[..., ::-1])
    import cv2

    code = getattr(cv2, f"COLOR_Bayer{colour}2GRAY")  # OpenCV's pattern-named codes (the Bayer{XY} ones are shifted)
    return cv2.cvtColor(np.ascontiguousarray(raw), code)


def _message(warning: Warning) -> warnings.WarningMessage:
    return warnings.WarningMessage(warning, type(warning), __file__, 0)


# ---------------------------------------------------------------- video (OpenCV)
_MAX_FAILED_READS = 50


def video_frames(path: Path) -> tuple[int, bool, Iterator[SourceFrame]]:
    """``(frame count or 0 if unknown, has timestamps, frames)`` of a video file read with OpenCV.

    Frames are decoded to 8 bits; a frame's time is its presentation time in the container.
    """
    import cv2

    capture = _open_video(path)
    try:
        count = max(0, int(capture.get(cv2.CAP_PROP_FRAME_COUNT)))
        fourcc = int(capture.get(cv2.CAP_PROP_FOURCC)).to_bytes(4, "little").decode("latin-1")
    finally:
        capture.release()
    return count, True, _video_iter(path, count, fourcc)


def _open_video(path: Path) -> Any:
    import cv2

    capture = cv2.VideoCapture(str(path))
    if not capture.isOpened():
        capture.release()
        raise ImageFolderError(path, "cannot be opened as a video (damaged, or a codec OpenCV cannot read).")
    return capture


def _video_iter(path: Path, count: int, fourcc: str) -> Iterator[SourceFrame]:
    """Frames in order; a run of frames that cannot be decoded comes as one bad item naming the range."""
    import cv2

    capture = _open_video(path)
    notes = [] if fourcc.upper() in _LOSSLESS_FOURCCS else [_message(lossy_warning(f"{path.name} ({fourcc.strip()})"))]
    colour_noted = False
    bad_from: int | None = None
    index = 0
    try:
        while count == 0 or index < count:
            ok, image = capture.read()
            if not ok or image is None:
                if count == 0:  # length unknown: this is the end
                    break
                bad_from = index if bad_from is None else bad_from
                index += 1
                if index - bad_from > _MAX_FAILED_READS:  # the rest is gone too
                    index = count
                    break
                continue
            if bad_from is not None:
                yield _undecodable(path, bad_from, index - 1)
                bad_from = None
            frame = SourceFrame(f"{path.name} frame {index}", path, index, bit_depth=8, caught=notes)
            notes = []
            frame.file_time_ns = int(round(capture.get(cv2.CAP_PROP_POS_MSEC) * 1e6))
            frame.image, colour = _video_to_mono(image)
            if colour and not colour_noted:
                colour_noted = True
                frame.caught = [*frame.caught,
                                _message(ColourImageWarning(f"{path.name}: colour frames converted to mono (luma)."))]
            yield frame
            index += 1
        if bad_from is not None:
            yield _undecodable(path, bad_from, index - 1)
    finally:
        capture.release()


def _undecodable(path: Path, first: int, last: int) -> SourceFrame:
    span = f"{first}-{last}" if last > first else f"{first}"
    return SourceFrame(f"{path.name} frame {span}", path, first, bit_depth=8,
                       problem="cannot be decoded (damaged, or the video ends early).")


def _video_to_mono(image: npt.NDArray[Any]) -> tuple[npt.NDArray[Any], bool]:
    """Mono frame and whether it had colour (grey video decodes to three equal channels)."""
    if image.ndim == 2:
        return image, False
    if image.shape[2] == 1 or (np.array_equal(image[..., 0], image[..., 1])
                               and np.array_equal(image[..., 1], image[..., 2])):
        return np.ascontiguousarray(image[..., 0]), False
    return luma(image[..., 2::-1]), True
