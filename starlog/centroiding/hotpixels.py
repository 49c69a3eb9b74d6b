"""Hot-pixel maps: learnt from the frames themselves, or read from a file.

A hot pixel is a single pixel, the highest of its 3x3 neighbourhood, far above its local
background (a 5x5 median) whose neighbours are not: the
same spike test the detector screens candidates with (:func:`starlog.detect.screening.is_spike`:
more than 8 noise sigma above the mean of its two horizontal, or its two vertical, neighbours,
which stay below 0.2 of it), applied to every pixel of a frame. A star, even a static one,
lights its neighbours and is never a spike; a cosmic ray is a spike in one frame only. A pixel
that is a spike in most frames of a sample (:func:`learn_hot_pixels`) is hot.

Map files (:func:`load_hot_pixels`): a ``.npy`` boolean array of the frame's shape (True =
hot), or a text file (``.txt``, ``.csv``) with one ``x,y`` pair per line (column, row, 0-based;
blank lines and lines starting with ``#`` ignored; a header line ``x,y`` allowed).
:func:`without_hot_pixels` turns hot pixels into missing (NaN) pixels, which detection fills
and never detects, and which every star window leaves out.
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from starlog.errors import InvalidInputError

__all__ = ["describe_hot_pixels", "hot_pixel_spikes", "learn_hot_pixels", "load_hot_pixels", "without_hot_pixels"]

Mask = npt.NDArray[np.bool_]

SPIKE_SIGMA = 8.0
"""Excess over the neighbours, in background sigma (as the detector's spike test)."""
SPIKE_RATIO = 0.2
"""The neighbours' excess must stay below this fraction of the pixel's (as the detector's)."""


def hot_pixel_spikes(image: npt.ArrayLike) -> Mask:
    """Pixels of one frame that are single-pixel spikes above their local background."""
    img = np.asarray(image, np.float32)
    img = np.where(np.isfinite(img), img, np.nanmedian(img)).astype(np.float32)
    level = cv2.medianBlur(img, 5)
    excess = img - level
    noise = 1.4826 * float(np.median(np.abs(excess - np.median(excess))))
    noise = max(noise, 1e-6)
    pair_h = cv2.filter2D(excess, -1, np.array([[0.5, 0.0, 0.5]], np.float32), borderType=cv2.BORDER_REFLECT)
    pair_v = cv2.filter2D(excess, -1, np.array([[0.5], [0.0], [0.5]], np.float32), borderType=cv2.BORDER_REFLECT)
    lowest = np.minimum(pair_h, pair_v)
    peak = img >= cv2.dilate(img, np.ones((3, 3), np.uint8))  # on a star's flank a pixel is no peak
    return peak & (excess - lowest > SPIKE_SIGMA * noise) & (lowest < SPIKE_RATIO * excess)


def learn_hot_pixels(frames: Iterable[npt.ArrayLike], *, min_fraction: float = 0.5, min_frames: int = 3) -> Mask:
    """Pixels that are spikes (:func:`hot_pixel_spikes`) in more than ``min_fraction`` of ``frames``.

    With fewer than ``min_frames`` frames no pixel can be told from a cosmic ray: the map is empty.
    """
    count: npt.NDArray[np.int32] | None = None
    n = 0
    for image in frames:
        spikes = hot_pixel_spikes(image)
        count = spikes.astype(np.int32) if count is None else count + spikes
        n += 1
    if count is None:
        raise InvalidInputError("no frame to learn a hot-pixel map from.")
    if n < min_frames:
        return np.zeros(count.shape, bool)
    return count > min_fraction * n


def load_hot_pixels(path: str | Path, shape: tuple[int, int]) -> Mask:
    """A hot-pixel map file (``.npy`` boolean mask, or ``x,y`` text lines; see the module docstring)."""
    path = Path(path)
    if path.suffix.lower() == ".npy":
        mask = np.load(path, allow_pickle=False)
        if mask.shape != tuple(shape):
            raise InvalidInputError(f"{path}: the hot-pixel mask is {mask.shape}, the frames are {tuple(shape)}.")
        return mask.astype(bool)
    rows = []
    for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
        text = line.strip()
        if not text or text.startswith("#") or text.replace(" ", "").lower() == "x,y":
            continue
        try:
            x, y = (int(v) for v in text.replace(";", ",").split(","))
        except ValueError:
            raise InvalidInputError(f"{path}:{number}: expected 'x,y' (integer column, row), got {text!r}.") from None
        if not (0 <= x < shape[1] and 0 <= y < shape[0]):
            raise InvalidInputError(f"{path}:{number}: pixel ({x}, {y}) is outside the {shape[1]}x{shape[0]} frame.")
        rows.append((y, x))
    mask = np.zeros(shape, bool)
    if rows:
        yy, xx = np.array(rows).T
        mask[yy, xx] = True
    return mask


def describe_hot_pixels(mask: Mask, source: str, max_listed: int = 4096) -> dict[str, Any]:
    """Provenance record of a map: count, SHA-256 of its packed bits (row-major), source, and the pixels."""
    yy, xx = np.nonzero(mask)
    out: dict[str, Any] = {
        "source": source,
        "count": int(yy.size),
        "shape": [int(s) for s in mask.shape],
        "sha256": hashlib.sha256(np.packbits(mask.astype(bool), axis=None).tobytes()).hexdigest(),
    }
    if yy.size <= max_listed:
        out["pixels"] = [[int(x), int(y)] for x, y in zip(xx, yy)]
    return out


def without_hot_pixels(image: npt.ArrayLike, mask: Mask | None) -> npt.NDArray[Any]:
    """``image`` with its hot pixels missing (float32 NaN); unchanged when the map is empty or ``None``."""
    arr = np.asarray(image)
    if mask is None or not mask.any():
        return arr
    if mask.shape != arr.shape:
        raise InvalidInputError(f"the hot-pixel map is {mask.shape}, the frame is {arr.shape}.")
    dtype = np.float64 if arr.dtype == np.float64 else np.float32
    out = arr.astype(dtype)
    out[mask] = np.nan
    return out
