"""Read SER files, the uncompressed video format of astronomy cameras (SER v3, G. Hahn 2014).

Layout implemented (all integers little-endian)::

    offset  size  field
         0    14  FileID              "LUCAM-RECORDER"
        14     4  LuID                int32, unused
        18     4  ColorID             int32: 0 MONO; 8 BAYER_RGGB, 9 BAYER_GRBG, 10 BAYER_GBRG,
                                      11 BAYER_BGGR (16..19: CYYM/YCMY/YMCY/MYYC, not read);
                                      100 RGB, 101 BGR
        22     4  LittleEndian        int32, byte order of 16-bit samples (see below)
        26     4  ImageWidth          int32, pixels
        30     4  ImageHeight         int32, pixels
        34     4  PixelDepthPerPlane  int32, 1..8: one byte per sample, 9..16: two bytes
        38     4  FrameCount          int32
        42    40  Observer            text
        82    40  Instrument          text
       122    40  Telescope           text
       162     8  DateTime            int64, local time (ticks, see below)
       170     8  DateTime_UTC        int64, UTC (ticks)
       178        frames              FrameCount x Width x Height x planes x bytes-per-sample,
                                      row-major from the top-left pixel; RGB/BGR (3 planes)
                                      interleaved per pixel in the order the name says
                  trailer (optional)  FrameCount x int64: each frame's UTC time in ticks

A tick is 100 ns since 0001-01-01 00:00 (the .NET ``DateTime`` epoch); :meth:`SerReader.timestamps_ns`
gives them as Unix-epoch nanoseconds. The trailer counts as present when the file holds all
``8 x FrameCount`` bytes after the frames and not every tick is zero.

Byte order: the specification says LittleEndian = 1 means little-endian samples, but many
capture programs write the flag inverted, so the flag is unreliable in practice. The reader
decides from the first frame: the order that keeps every sample within PixelDepthPerPlane bits,
else the order whose neighbouring pixels differ clearly less relative to the frame's range (a
byte-swapped star image is noise); the flag, read as the specification says, decides when the
frame cannot (e.g. a frame of one value, or of two).
"""

from __future__ import annotations

import os
import struct
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any, BinaryIO

import numpy as np
import numpy.typing as npt

from starlog.errors import ImageFolderError

__all__ = ["HEADER_SIZE", "SerHeader", "SerReader", "ticks_to_unix_ns", "unix_ns_to_ticks"]

HEADER_SIZE = 178
FILE_ID = b"LUCAM-RECORDER"
_HEADER = struct.Struct("<14s7i40s40s40sqq")
TICKS_AT_UNIX_EPOCH = 621_355_968_000_000_000  # 100-ns ticks from 0001-01-01 to 1970-01-01
MONO, RGB, BGR = 0, 100, 101
BAYER_PATTERNS = {8: "RGGB", 9: "GRBG", 10: "GBRG", 11: "BGGR"}
_UNSUPPORTED_PATTERNS = {16: "CYYM", 17: "YCMY", 18: "YMCY", 19: "MYYC"}


def ticks_to_unix_ns(ticks: int) -> int:
    """SER/.NET ticks (100 ns since 0001-01-01) to nanoseconds since 1970-01-01."""
    return (ticks - TICKS_AT_UNIX_EPOCH) * 100


def unix_ns_to_ticks(ns: int) -> int:
    """Nanoseconds since 1970-01-01 to SER/.NET ticks (rounded down to 100 ns)."""
    return ns // 100 + TICKS_AT_UNIX_EPOCH


@dataclass(frozen=True)
class SerHeader:
    """The fields of a SER header that describe the frames."""

    color_id: int
    little_endian_flag: int
    width: int
    height: int
    depth: int
    frame_count: int
    observer: str = ""
    instrument: str = ""
    telescope: str = ""

    @property
    def planes(self) -> int:
        return 3 if self.color_id in (RGB, BGR) else 1

    @property
    def sample_bytes(self) -> int:
        return 1 if self.depth <= 8 else 2

    @property
    def frame_bytes(self) -> int:
        return self.width * self.height * self.planes * self.sample_bytes

    @property
    def colour(self) -> str:
        """``mono``, ``RGB``, ``BGR`` or the Bayer pattern (``RGGB``...)."""
        if self.color_id == MONO:
            return "mono"
        if self.color_id in (RGB, BGR):
            return "RGB" if self.color_id == RGB else "BGR"
        return BAYER_PATTERNS[self.color_id]


def parse_header(path: Path, data: bytes) -> SerHeader:
    """Decode and check the 178-byte header (:class:`ImageFolderError` naming ``path`` if unusable)."""
    if len(data) < HEADER_SIZE:
        raise ImageFolderError(path, f"is too short for a SER file ({len(data)} bytes; the header alone is 178).")
    (file_id, _lu_id, color_id, flag, width, height, depth, count,
     observer, instrument, telescope, _local, _utc) = _HEADER.unpack(data[:HEADER_SIZE])
    if file_id != FILE_ID:
        raise ImageFolderError(path, "is not a SER file (it does not start with 'LUCAM-RECORDER').")
    if color_id in _UNSUPPORTED_PATTERNS:
        raise ImageFolderError(path, f"has a {_UNSUPPORTED_PATTERNS[color_id]} colour filter; starlog reads mono, "
                                     "RGB/BGR and RGGB/GRBG/GBRG/BGGR Bayer SER files.")
    if color_id not in (MONO, RGB, BGR, *BAYER_PATTERNS):
        raise ImageFolderError(path, f"has an unknown SER ColorID {color_id}.")
    if width <= 0 or height <= 0 or not 1 <= depth <= 16 or count < 0:
        raise ImageFolderError(path, f"has an invalid SER header (width {width}, height {height}, "
                                     f"bit depth {depth}, frame count {count}).")

    def text(raw: bytes) -> str:
        return raw.split(b"\0", 1)[0].decode("latin-1").strip()

    return SerHeader(color_id, flag, width, height, depth, count, text(observer), text(instrument), text(telescope))


class SerReader:
    """Frames of a SER file, read one at a time (constant memory).

    >>> with SerReader("capture.ser") as ser:                  # doctest: +SKIP
    ...     frame = ser.read_frame(0)                          # (H, W) or (H, W, 3) as stored
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        try:
            self._file: BinaryIO = open(self.path, "rb")
        except OSError as err:
            raise ImageFolderError(self.path, f"cannot be opened ({err.strerror}).") from err
        try:
            self.size = os.fstat(self._file.fileno()).st_size
            self.header = parse_header(self.path, self._file.read(HEADER_SIZE))
        except BaseException:
            self._file.close()
            raise
        self._byte_order: str | None = None

    def __enter__(self) -> SerReader:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    def close(self) -> None:
        self._file.close()

    @property
    def frames_in_file(self) -> int:
        """Frames whose bytes are all in the file (fewer than FrameCount if the file was cut off)."""
        whole = (self.size - HEADER_SIZE) // self.header.frame_bytes
        return max(0, min(self.header.frame_count, whole))

    def read_frame(self, index: int) -> npt.NDArray[Any]:
        """Frame ``index`` as stored: uint8/uint16 (native order), (H, W) or (H, W, 3).

        Raises :class:`ImageFolderError` naming the frame if its bytes are not all in the file.
        """
        h = self.header
        if not 0 <= index < h.frame_count:
            raise ImageFolderError(self.path, f"has no frame {index} (FrameCount {h.frame_count}).")
        self._file.seek(HEADER_SIZE + index * h.frame_bytes)
        data = self._file.read(h.frame_bytes)
        if len(data) < h.frame_bytes:
            raise ImageFolderError(self.path, f"frame {index}: cut off (the file ends {len(data)} bytes into the "
                                              f"frame's {h.frame_bytes}).")
        shape = (h.height, h.width, 3) if h.planes == 3 else (h.height, h.width)
        if h.sample_bytes == 1:
            return np.frombuffer(data, np.uint8).reshape(shape)
        if self._byte_order is None:
            self._byte_order = _guess_byte_order(np.frombuffer(data, "<u2"), h.depth, h.little_endian_flag)
        return np.frombuffer(data, self._byte_order + "u2").astype(np.uint16).reshape(shape)

    def timestamps_ns(self) -> list[int] | None:
        """Each frame's UTC time (Unix-epoch ns) from the trailer, or None if the file has none."""
        count = self.header.frame_count
        start = HEADER_SIZE + count * self.header.frame_bytes
        if count == 0 or self.size < start + 8 * count:
            return None
        self._file.seek(start)
        ticks = np.frombuffer(self._file.read(8 * count), "<i8")
        if not ticks.any():
            return None
        return [ticks_to_unix_ns(int(t)) for t in ticks]


def _guess_byte_order(samples: npt.NDArray[np.uint16], depth: int, flag: int) -> str:
    """``'<'`` or ``'>'``: the byte order of a frame's 16-bit samples (see the module docstring)."""
    little, big = samples, samples.byteswap()
    limit = 1 << depth
    fits_little, fits_big = bool(little.max() < limit), bool(big.max() < limit)
    if fits_little != fits_big:
        return "<" if fits_little else ">"
    rough_little, rough_big = _roughness(little), _roughness(big)
    if min(rough_little, rough_big) < 0.5 * max(rough_little, rough_big):
        return "<" if rough_little < rough_big else ">"
    return "<" if flag == 1 else ">"


def _roughness(samples: npt.NDArray[np.uint16]) -> float:
    """Mean step between neighbouring samples relative to their range: byte-swapped noise is rough."""
    values = samples.astype(np.int64)
    spread = int(values.max() - values.min()) if values.size else 0
    return float(np.abs(np.diff(values)).mean()) / spread if spread else 0.0
