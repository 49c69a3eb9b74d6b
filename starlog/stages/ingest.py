"""The ``ingest`` stage: turn a folder of star images into a log.

Reads 8- and 16-bit PNG and TIFF (FITS with the ``fits`` extra: ``pip install starlog[fits]``)
in natural file-name order (``img2.png`` before ``img10.png``). Timestamps come from a frame
rate (``fps``, ``start_ns``) or from the file names (``time_pattern``, a regular expression
with a named group ``t``, in ``time_unit``).
"""

from __future__ import annotations

import os
import re
import warnings
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from starlog import __version__
from starlog.errors import ImageFolderError, InvalidParameterError
from starlog.io import LogWriter, Provenance, encode_json, encode_raw_image, json_message_type, protobuf_message_type
from starlog.io import topics
from starlog.io.provenance import PROVENANCE_METADATA_NAME
from starlog.stages._parallel import ordered_map
from starlog.stages._progress import progress

__all__ = ["IMAGE_SUFFIXES", "ColourImageWarning", "IngestSummary", "ingest_folder", "natural_key", "read_image"]

IMAGE_SUFFIXES = {".png", ".tif", ".tiff", ".fits", ".fit", ".fts"}
_TIME_UNITS = {"s": 1e9, "ms": 1e6, "us": 1e3, "ns": 1.0}


class ColourImageWarning(UserWarning):
    """A colour image was converted to mono (luma) on ingest."""


def natural_key(name: str) -> list[Any]:
    """Sort key that orders digit runs by value: ``f2`` < ``f10``."""
    return [int(part) if part.isdigit() else part.lower() for part in re.split(r"(\d+)", name)]


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
            import tifffile

            image = tifffile.imread(path)
        else:
            import cv2

            image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            if image is not None and image.ndim == 3:
                image = image[..., ::-1]  # OpenCV gives BGR(A)
    except ImageFolderError:
        raise
    except Exception as err:  # decoders raise many unrelated types on damaged files
        raise ImageFolderError(path, f"cannot be read as an image ({type(err).__name__}: {err}).") from err
    if image is None:
        raise ImageFolderError(path, "cannot be read as an image (damaged or not an image file).")
    image = np.asarray(image)
    if image.ndim == 3 and image.shape[2] in (3, 4):
        warnings.warn(f"{path.name}: colour image converted to mono (luma).", ColourImageWarning, stacklevel=2)
        rgb = image[..., :3].astype(np.float64)
        luma = rgb @ np.array([0.299, 0.587, 0.114])
        image = np.rint(luma).astype(image.dtype)
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


@dataclass
class IngestSummary:
    """What :func:`ingest_folder` did."""

    output: Path
    frames: int = 0
    width: int = 0
    height: int = 0
    encoding: str = ""
    first_log_time: int = 0
    last_log_time: int = 0
    skipped: list[tuple[str, str]] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form."""
        return {
            "output": str(self.output),
            "frames": self.frames,
            "width": self.width,
            "height": self.height,
            "encoding": self.encoding,
            "first_log_time": self.first_log_time,
            "last_log_time": self.last_log_time,
            "skipped": [{"file": f, "reason": r} for f, r in self.skipped],
        }


def list_images(folder: Path) -> list[Path]:
    """Image files of ``folder`` (not recursive) in natural name order."""
    if not folder.is_dir():
        raise ImageFolderError(folder, "is not a folder.")
    files = [p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES]
    if not files:
        raise ImageFolderError(
            folder, f"contains no image files ({', '.join(sorted(IMAGE_SUFFIXES))}); nothing to ingest."
        )
    return sorted(files, key=lambda p: natural_key(p.name))


def _timestamps(
    files: Sequence[Path], *, fps: float | None, start_ns: int, time_pattern: str | None, time_unit: str
) -> Callable[[int, Path], int]:
    if time_pattern is not None:
        if time_unit not in _TIME_UNITS:
            raise InvalidParameterError(f"time unit must be one of {sorted(_TIME_UNITS)}, got {time_unit!r}.")
        try:
            regex = re.compile(time_pattern)
        except re.error as err:
            raise InvalidParameterError(f"invalid --time-pattern {time_pattern!r}: {err}.") from err
        if "t" not in regex.groupindex:
            raise InvalidParameterError("--time-pattern needs a named group 't', e.g. 'frame_(?P<t>\\d+)us'.")
        scale = _TIME_UNITS[time_unit]

        def from_name(_: int, path: Path) -> int:
            match = regex.search(path.name)
            if match is None:
                raise ImageFolderError(path, f"its name does not match --time-pattern {time_pattern!r}.")
            return start_ns + int(round(float(match.group("t")) * scale))

        return from_name
    if fps is None or not fps > 0:
        raise InvalidParameterError("give the frame rate (--fps, > 0) or a --time-pattern to time the frames.")

    def from_rate(index: int, _: Path) -> int:
        return start_ns + int(round(index * 1e9 / fps))

    return from_rate


def _decode_all(files: Sequence[Path], workers: int) -> Iterator[tuple[Path, Any]]:
    """Decode files in order on ``workers`` threads (decoders release the GIL); errors are yielded."""

    def safe(path: Path) -> Any:
        try:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                return read_image(path), caught
        except ImageFolderError as err:
            return err, []

    if workers <= 1:
        for path in files:
            yield path, safe(path)
        return
    with ThreadPoolExecutor(max_workers=workers) as pool:
        yield from zip(files, ordered_map(pool, safe, ((p,) for p in files), window=4 * workers))


def ingest_folder(
    folder: str | os.PathLike[str],
    output: str | os.PathLike[str],
    *,
    fps: float | None = None,
    start_ns: int = 0,
    time_pattern: str | None = None,
    time_unit: str = "ns",
    skip_bad: bool = False,
    compression: str = "zstd",
    workers: int = 1,
    force: bool = False,
    show_progress: bool = False,
) -> IngestSummary:
    """Ingest a folder of images into a new log at ``output``.

    Every frame must have the size and pixel type of the first; a file that cannot be read or
    does not match stops the ingest with an error naming it, or with ``skip_bad=True`` is
    skipped and listed in the summary. Timestamps must increase strictly.

    Returns
    -------
    IngestSummary
    """
    folder = Path(folder)
    files = list_images(folder)
    stamp = _timestamps(files, fps=fps, start_ns=start_ns, time_pattern=time_pattern, time_unit=time_unit)
    summary = IngestSummary(output=Path(output))
    parameters = {"folder": folder.name, "fps": fps, "start_ns": start_ns, "time_pattern": time_pattern,
                  "time_unit": time_unit, "skip_bad": skip_bad, "files": len(files)}
    reference: tuple[tuple[int, ...], np.dtype[Any]] | None = None
    last_time = -1
    with LogWriter(output, compression=compression, workers=workers, force=force) as log:
        image_ch = log.add_channel(topics.IMAGE, protobuf_message_type("foxglove.RawImage"), monotonic=True)
        info_ch = log.add_channel(topics.FRAME_INFO, json_message_type("starlog.FrameInfo"), monotonic=True)
        decoded = _decode_all(files, workers)
        for position, (path, (result, caught)) in enumerate(
            progress(decoded, total=len(files), description="ingest", enabled=show_progress)
        ):
            for w in caught:
                warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
            problem: str | None = None
            if isinstance(result, ImageFolderError):
                problem = result.reason
                error: ImageFolderError = result
            else:
                image = result
                if reference is None:
                    reference = (image.shape, image.dtype)
                elif (image.shape, image.dtype) != reference:
                    problem = (f"is {image.shape[1]}x{image.shape[0]} {image.dtype}, but the first frame is "
                               f"{reference[0][1]}x{reference[0][0]} {reference[1]}; all frames must match.")
                    error = ImageFolderError(path, problem)
            if problem is not None:
                if skip_bad:
                    summary.skipped.append((path.name, problem))
                    continue
                raise error
            t = stamp(position, path)
            if t <= last_time:
                raise ImageFolderError(path, f"its timestamp {t} ns is not after the previous frame's ({last_time} ns).")
            last_time = t
            log.write(image_ch, log_time=t, data=encode_raw_image(image, log_time=t))
            encoding = "mono16" if image.dtype == np.uint16 else "mono8"
            info = {"frame": summary.frames, "width": int(image.shape[1]), "height": int(image.shape[0]),
                    "encoding": encoding, "bit_depth": 16 if encoding == "mono16" else 8, "source": path.name}
            log.write(info_ch, log_time=t, data=encode_json(info))
            if summary.frames == 0:
                summary.first_log_time = t
                summary.width, summary.height, summary.encoding = info["width"], info["height"], encoding
            summary.last_log_time = t
            summary.frames += 1
        if summary.frames == 0:
            raise ImageFolderError(folder, "no frame could be ingested (every file was skipped as bad).")
        provenance = Provenance(stage="ingest", version=__version__, parameters=parameters,
                                channels=[topics.IMAGE, topics.FRAME_INFO])
        log.add_metadata(PROVENANCE_METADATA_NAME, provenance.to_metadata())
    return summary
