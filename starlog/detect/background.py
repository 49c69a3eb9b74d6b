"""Background level and noise maps that survive bright stars, gradients and vignetting.

The frame is cut into ``mesh`` x ``mesh`` pixel cells (as SExtractor / SEP do). In each cell a
sigma-clipped plane (level, slopes) and the residuals' standard deviation (noise) are computed on a
sub-sampled set of pixels: the clipping starts from the median and the width of the star-free
lower half of the distribution (all cells at once), then each cell's plane is fitted in one
compiled pass (:mod:`starlog.detect.background_kernel`). The cell grid may be median-filtered
(``filter_size``), then it is interpolated back to full resolution bilinearly between cell
centres (linear extrapolation in the outer half cells): :meth:`Background.map`, or, for the
detection threshold, :meth:`Background.above` without making the map.

Quantised frames. A digitised value stands for an interval one step wide: on a frame whose
values are whole numbers (integer frames, and float frames holding whole numbers, such as an
integer frame with hot pixels set to NaN) the step is 1 DN in the units the detector sees
(frames reach it in DN as logged: luma and debayering are rounded to integers at ingest, the gain
only weighs the centroids). When the noise is not much larger than the step (an 8-bit frame of
a dark sky), most of a cell's pixels take one or two values, and the median and the 15.9th
percentile often coincide: a spread of 0 only says "less than one step". The clipping then
starts from one step (it keeps the values within three steps of the median, whatever the
spread) and the fitted plane's residuals measure the spread of the digitised values (noise and
quantisation error together, the variance that reaches the matched filter); the noise map is
never below the quantisation error's own, step / sqrt(12), the standard deviation of a uniform
error over one step. Where the noise is several steps neither bound is reached and nothing changes.

Coordinates follow the starlog convention (x = column, y = row, 0-based, pixel-centre origin).
"""

from __future__ import annotations

import functools
import warnings
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt
from scipy.ndimage import median_filter, uniform_filter
from scipy.special import erf

from starlog.errors import InvalidInputError, InvalidParameterError

__all__ = ["Background", "estimate_background"]

F64 = npt.NDArray[np.float64]


def _axis_weights(c: F64, n: int, mesh: int, extrapolate: bool) -> tuple[npt.NDArray[np.intp], npt.NDArray[np.intp], F64, F64]:
    """Linear interpolation from cell centres to coordinates ``c`` along one axis: the two cells
    and their weights (float32 values, as the map's), per coordinate."""
    if n == 1:
        zero = np.zeros(c.size, np.intp)
        return zero, zero, np.ones(c.size), np.zeros(c.size)
    f = (c + 0.5) / mesh - 0.5
    if not extrapolate:
        f = np.minimum(np.maximum(f, 0.0), n - 1.0)
    i0 = np.minimum(np.maximum(np.floor(f).astype(np.intp), 0), n - 2)
    t = f - i0
    return i0, i0 + 1, (1.0 - t).astype(np.float32).astype(np.float64), t.astype(np.float32).astype(np.float64)


def _edge_padded(grid: npt.NDArray[np.float32]) -> npt.NDArray[np.float32]:
    """The grid with a ring of copies of its outer cells (``np.pad(grid, 1, mode="edge")``, without its overhead)."""
    return cv2.copyMakeBorder(np.ascontiguousarray(grid, np.float32), 1, 1, 1, 1, cv2.BORDER_REPLICATE)


def _padded_grid(grid: npt.NDArray[np.float32], extrapolate: bool, plus: npt.NDArray[np.float32] | None
                 ) -> tuple[npt.NDArray[np.float32], int]:
    """The grid :meth:`Background.map` resizes and the width (in cells) of its ring of ghost cells:
    1, the ghosts linearly extrapolated (``extrapolate``) or copies of the outer cells, with
    ``plus`` (a second grid) added with copies; 0 for a grid of one row or column."""
    g = np.asarray(grid, np.float32)
    ny, nx = g.shape
    if ny > 1 and nx > 1:
        if extrapolate:
            g = np.vstack([2 * g[:1] - g[1:2], g, 2 * g[-1:] - g[-2:-1]])
            g = np.hstack([2 * g[:, :1] - g[:, 1:2], g, 2 * g[:, -1:] - g[:, -2:-1]])
        else:
            g = _edge_padded(g)
        return (g if plus is None else g + _edge_padded(np.asarray(plus, np.float32))), 1
    return (g if plus is None else g + np.asarray(plus, np.float32)), 0


@functools.lru_cache(maxsize=16)
def _resize_axis(n: int, cells: int, mesh: int, ring: int) -> tuple[npt.NDArray[np.intp], F64]:
    """Along one axis of the frame (``n`` px): the grid cell below each pixel and its weight towards the
    next, as ``cv2.resize`` (INTER_LINEAR, scale ``mesh``) places it on a grid of ``cells`` cells whose
    first ``ring`` are ghosts (half-pixel centres; clamped to the grid at both ends).

    The same for every frame of a log: made once per shape (read-only arrays)."""
    source = (np.arange(n) + ring * mesh + 0.5) / mesh - 0.5
    cell = np.floor(source)
    weight = source - cell
    low, high = cell < 0, cell >= cells - 1
    cell = np.where(low, 0, np.where(high, cells - 1, cell)).astype(np.intp)
    weight = np.where(low | high, 0.0, weight)
    cell.flags.writeable = weight.flags.writeable = False
    return cell, weight


@dataclass(frozen=True)
class Background:
    """Background model of one frame: cell grids, evaluated at full resolution on demand.

    Attributes
    ----------
    mesh_level, mesh_noise : (ny, nx) ndarray of float32
        Filtered cell grids: background level and 1-sigma per-pixel noise, DN. Cell values
        sit at cell centres; maps are their bilinear interpolation (see :meth:`map`).
    mesh : int
        Cell size, px.
    shape : (rows, cols)
        Frame shape.
    global_level, global_noise : float
        Medians of the cell grids, DN.
    """

    mesh_level: npt.NDArray[np.float32]
    mesh_noise: npt.NDArray[np.float32]
    mesh: int
    shape: tuple[int, int]
    global_level: float
    global_noise: float

    def map(
        self,
        grid: npt.NDArray[np.float32],
        extrapolate: bool = True,
        plus: npt.NDArray[np.float32] | None = None,
    ) -> npt.NDArray[np.float32]:
        """Full-resolution map of a (ny, nx) cell grid (float32, the frame's shape).

        Bilinear between cell centres (``cv2.resize``); in the outer half cells linear
        extrapolation (the grid is padded with a ring of linearly extrapolated ghost cells)
        or the outer cells' value (``extrapolate=False``, used for the noise). ``plus`` is a
        second grid added with the outer-value rule (one resize for level + k * noise).
        """
        g, ring = _padded_grid(grid, extrapolate, plus)
        full = cv2.resize(g, (g.shape[1] * self.mesh, g.shape[0] * self.mesh), interpolation=cv2.INTER_LINEAR)
        pad = ring * self.mesh
        return full[pad : pad + self.shape[0], pad : pad + self.shape[1]]

    def above(self, image: npt.NDArray[np.float32], k: float) -> npt.NDArray[np.uint8]:
        """255 where ``image`` exceeds level + ``k`` x noise, else 0 (uint8): a comparison with
        ``map(mesh_level, plus=k * mesh_noise)`` without making that map (compiled,
        :mod:`starlog.detect.threshold_kernel`); a pixel within float32 rounding of the
        threshold may be decided differently."""
        from starlog.detect.threshold_kernel import mark_above  # numba: imported, and compiled, on first use

        grid, ring = _padded_grid(self.mesh_level, True, np.float32(k) * self.mesh_noise)
        grid = np.pad(grid, ((0, 1), (0, 1)), mode="edge")  # the cell after the last, for a zero weight
        row_cell, row_weight = _resize_axis(self.shape[0], grid.shape[0] - 1, self.mesh, ring)
        col_cell, col_weight = _resize_axis(self.shape[1], grid.shape[1] - 1, self.mesh, ring)
        b = col_weight.astype(np.float32)
        columns = np.ascontiguousarray(grid[:, col_cell] * (np.float32(1) - b) + grid[:, col_cell + 1] * b)
        out = np.empty(self.shape, np.uint8)
        mark_above(np.ascontiguousarray(image, np.float32), columns, row_cell, row_weight, out)
        return out

    @property
    def level(self) -> npt.NDArray[np.float32]:
        """Background level per pixel, DN (computed on each access)."""
        return self.map(self.mesh_level)

    @property
    def noise(self) -> npt.NDArray[np.float32]:
        """Background noise (1 sigma) per pixel, DN (computed on each access)."""
        return self.map(self.mesh_noise, extrapolate=False)

    def _interp(self, grid: npt.NDArray[np.float32], x: npt.ArrayLike, y: npt.ArrayLike,
                extrapolate: bool) -> npt.NDArray[np.float64]:
        """Bilinear value of a cell grid at pixel positions: past the outer cell centres linear
        extrapolation, or the outer value (``extrapolate=False``)."""
        xs = np.asarray(x, np.float64)
        ys = np.asarray(y, np.float64)
        shape = np.broadcast(xs, ys).shape
        xs, ys = np.broadcast_to(xs, shape).ravel(), np.broadcast_to(ys, shape).ravel()
        g = grid.astype(np.float64)
        y0, y1, a0, a1 = _axis_weights(ys, grid.shape[0], self.mesh, extrapolate)
        x0, x1, b0, b1 = _axis_weights(xs, grid.shape[1], self.mesh, extrapolate)
        value = ((a0 * g[y0, x0]) * b0 + (a0 * g[y0, x1]) * b1) + (a1 * g[y1, x0]) * b0 + (a1 * g[y1, x1]) * b1
        return value.reshape(shape)

    def level_noise_grid(self, rows: npt.NDArray[np.intp], cols: npt.NDArray[np.intp]
                         ) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """Level and noise at every pixel of the grid ``rows`` x ``cols`` (``(len(rows), len(cols))``
        arrays, DN): :meth:`level_at` and :meth:`noise_at` there, interpolated one axis at a time."""
        return (self._grid_interp(self.mesh_level, rows, cols, True),
                self._grid_interp(self.mesh_noise, rows, cols, False))

    def _grid_interp(self, grid: npt.NDArray[np.float32], rows: npt.NDArray[np.intp], cols: npt.NDArray[np.intp],
                     extrapolate: bool) -> npt.NDArray[np.float64]:
        g = grid.astype(np.float64)
        y0, y1, a0, a1 = _axis_weights(np.asarray(rows, np.float64), grid.shape[0], self.mesh, extrapolate)
        x0, x1, b0, b1 = _axis_weights(np.asarray(cols, np.float64), grid.shape[1], self.mesh, extrapolate)
        along_rows = a0[:, None] * g[y0] + a1[:, None] * g[y1]
        return along_rows[:, x0] * b0 + along_rows[:, x1] * b1

    def level_at(self, x: npt.ArrayLike, y: npt.ArrayLike) -> npt.NDArray[np.float64]:
        """Background level at pixel positions (x = column, y = row), DN."""
        return self._interp(self.mesh_level, x, y, True)

    def noise_at(self, x: npt.ArrayLike, y: npt.ArrayLike) -> npt.NDArray[np.float64]:
        """Background noise (1 sigma) at pixel positions (x = column, y = row), DN."""
        return self._interp(self.mesh_noise, x, y, False)


def _cells(img: npt.NDArray[np.float32], mesh: int, sub: int) -> tuple[npt.NDArray[np.float32], int, int]:
    """Sub-sampled pixels of each cell as rows of a (ny*nx, n) array (NaN pads partial cells)."""
    rows, cols = img.shape
    ny, nx = -(-rows // mesh), -(-cols // mesh)
    s = img[::sub, ::sub].astype(np.float32)
    m = -(-mesh // sub)
    if mesh % sub:
        raise InvalidParameterError(f"mesh ({mesh}) must be a multiple of subsample ({sub}).")
    py, px = ny * m - s.shape[0], nx * m - s.shape[1]
    if py or px:
        s = np.pad(s, ((0, py), (0, px)), constant_values=np.nan)
    cells = s.reshape(ny, m, nx, m).transpose(0, 2, 1, 3).reshape(ny * nx, m * m)
    return cells, ny, nx


def _quantisation_step(image: npt.NDArray[Any], samples: npt.NDArray[np.float32]) -> float | None:
    """The step between the values the estimate sees: 1 DN for an integer frame or a float frame whose
    sampled finite values are all whole numbers; None (continuous values) otherwise."""
    if np.issubdtype(image.dtype, np.integer):
        return 1.0
    finite = samples[np.isfinite(samples)]
    return 1.0 if finite.size and np.array_equal(finite, np.rint(finite)) else None


def _robust_start(cells: npt.NDArray[np.float32]) -> tuple[F64, F64, npt.NDArray[np.float32]]:
    """Per cell: median, robust sigma (median - 15.9th percentile: the lower half of the
    distribution is free of stars) and the values with non-finite ones as NaN."""
    finite = np.isfinite(cells)
    if finite.all():
        npx = cells.shape[1]
        k16, k50 = int(0.15865 * (npx - 1)), (npx - 1) // 2
        ordered = np.sort(cells, axis=1)  # a vectorised sort beats a per-cell partition many times over
        med, q = ordered[:, k50], ordered[:, k16]
        vals = cells
    else:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            med = np.nanmedian(cells, axis=1)
            q = np.nanpercentile(cells, 15.865, axis=1)
        vals = np.where(finite, cells, np.float32(np.nan))
    return med.astype(np.float64), (med - q).astype(np.float64), vals


def _fit_planes(vals: npt.NDArray[np.float32], med: F64, sig: F64, iterations: int,
                clip_sigma: float) -> tuple[F64, F64, F64, F64]:
    """Sigma-clipped plane (level + x, y slopes) per cell, so that gradients and vignetting do
    not inflate the noise: level, slopes and residual sigma (not yet corrected for clipping).
    Compiled (:mod:`starlog.detect.background_kernel`); :func:`_fit_planes_vectorised` is the same
    fit in numpy, the reference it is tested against."""
    from starlog.detect.background_kernel import fit_planes  # numba: imported, and compiled, on first use

    level, noise = np.array(med, np.float64), np.array(sig, np.float64)
    slope_x, slope_y = np.empty_like(level), np.empty_like(level)
    fit_planes(np.ascontiguousarray(vals, np.float32), level, noise, float(clip_sigma), int(iterations), slope_x,
               slope_y)
    return level, slope_x, slope_y, noise


def _fit_planes_vectorised(vals: npt.NDArray[np.float32], med: F64, sig: F64, iterations: int,
                           clip_sigma: float) -> tuple[F64, F64, F64, F64]:
    """:func:`_fit_planes` vectorised over the cells in numpy."""
    m = int(round(np.sqrt(vals.shape[1])))
    cx = np.tile(np.arange(m, dtype=np.float32) - (m - 1) / 2, m)
    cy = np.repeat(np.arange(m, dtype=np.float32) - (m - 1) / 2, m)
    bx = np.zeros_like(med)
    by = np.zeros_like(med)
    cx2, cy2 = cx * cx, cy * cy
    for iteration in range(iterations):
        if iteration == 0:  # no slope yet: the plane is the level (adding the zero slopes changes no value)
            resid = vals - med.astype(np.float32)[:, None]
        else:
            resid = vals - (med.astype(np.float32)[:, None] + bx.astype(np.float32)[:, None] * cx
                            + by.astype(np.float32)[:, None] * cy)
        lim = (clip_sigma * np.maximum(sig, 1e-12)).astype(np.float32)[:, None]
        kept = np.abs(resid) <= lim  # NaN compares False
        keep = kept.astype(np.float32)
        v0 = np.where(kept, resid, np.float32(0))
        n = keep.sum(axis=1, dtype=np.float64)
        with np.errstate(all="ignore"):
            d0 = v0.sum(axis=1, dtype=np.float64) / n
            sxx = (keep @ cx2).astype(np.float64)
            syy = (keep @ cy2).astype(np.float64)
            dbx = (v0 @ cx).astype(np.float64) / sxx
            dby = (v0 @ cy).astype(np.float64) / syy
            s2 = np.einsum("ij,ij->i", v0, v0, dtype=np.float64)
            # residual variance about the refitted plane (x, y nearly orthogonal in a cell)
            var = np.maximum((s2 - n * d0**2 - dbx**2 * sxx - dby**2 * syy) / np.maximum(n - 3, 1), 0.0)
        good = (n >= 8) & np.isfinite(d0) & np.isfinite(dbx) & np.isfinite(dby) & (var >= 0)
        med = np.where(good, med + d0, med)
        bx = np.where(good, bx + dbx, bx)
        by = np.where(good, by + dby, by)
        sig = np.where(good, np.sqrt(np.where(good, var, 1.0)), sig)
    return med, bx, by, sig


def estimate_background(
    image: npt.ArrayLike,
    *,
    mesh: int = 64,
    filter_size: int = 1,
    clip_sigma: float = 3.0,
    iterations: int = 1,
    subsample: int = 4,
    min_noise: float | None = None,
) -> Background:
    """Estimate the background level and noise of a frame.

    Parameters
    ----------
    image : (rows, cols) array_like
        Frame in DN; non-finite pixels are ignored.
    mesh : int
        Cell size in pixels (>= 8). Larger than a star's footprint, smaller than the scale of
        the gradients/vignetting to follow.
    filter_size : int
        Size of the median filter applied to the cell grid (1 = none, the default: the
        sigma-clipped cell statistics already ignore isolated stars, and a median filter
        biases curved backgrounds such as vignetting at the frame's edges; use 3 for crowded
        fields or large bright objects).
    clip_sigma : float
        Sigma-clipping half-width about the median.
    iterations : int
        Clipping iterations.
    subsample : int
        Use every ``subsample``-th pixel in each direction (speed; 1 = all pixels).
    min_noise : float, optional
        Floor on the noise map, DN. Default: the quantisation error ``step / sqrt(12)`` for
        whole-number values (step 1 DN: integer frames, float frames of whole numbers; see the
        module's notes on quantised frames), ``1e-6 * max(1, |level|)`` for other float frames.

    Returns
    -------
    Background
        Cell grids of level and noise (maps on demand). A frame with no finite pixel gives
        NaN grids (callers check ``np.isfinite(bg.global_level)``).
    """
    arr = np.asarray(image)
    if arr.ndim != 2 or arr.size == 0:
        raise InvalidInputError(f"image must be a non-empty 2-D array; got shape {arr.shape}.")
    if not (mesh >= 8 and subsample >= 1 and iterations >= 1 and clip_sigma > 0 and filter_size >= 1):
        raise InvalidParameterError(
            "mesh must be >= 8, subsample and iterations >= 1, clip_sigma > 0 and filter_size >= 1; "
            f"got mesh={mesh!r}, subsample={subsample!r}, iterations={iterations!r}, "
            f"clip_sigma={clip_sigma!r}, filter_size={filter_size!r}."
        )
    img = arr
    mesh = min(mesh, max(8, subsample * -(-max(img.shape) // subsample)))
    mesh = -(-mesh // subsample) * subsample
    cells, ny, nx = _cells(img, mesh, subsample)
    step = _quantisation_step(arr, cells)
    med, sig, vals = _robust_start(cells)
    if step is not None:  # order statistics of digitised values resolve no spread below one step
        sig = np.maximum(sig, step)
    med, bx, by, sig = _fit_planes(vals, med, sig, iterations, clip_sigma)
    # the sub-sampled pixels are centred (m-1)/2 samples from the cell's corner, not on the
    # cell's centre: move the fitted plane's level to the true cell centre
    m = int(round(np.sqrt(cells.shape[1])))
    delta = ((mesh - 1) / 2.0 - subsample * (m - 1) / 2.0) / subsample
    med = med + (bx + by) * delta
    # clipping at +-k sigma removes the tails of a Gaussian
    k = clip_sigma
    trunc = np.sqrt(1.0 - 2.0 * k * np.exp(-0.5 * k * k) / np.sqrt(2 * np.pi) / erf(k / np.sqrt(2)))
    sig = sig / trunc
    shape = (int(arr.shape[0]), int(arr.shape[1]))
    return _background(med.reshape(ny, nx), sig.reshape(ny, nx), mesh, shape, filter_size,
                       min_noise if min_noise is not None else (None if step is None else step / np.sqrt(12.0)))


def _background(level_grid: F64, noise_grid: F64, mesh: int, shape: tuple[int, int], filter_size: int,
                min_noise: float | None) -> Background:
    """The Background of the cell grids: failed cells filled by the median, optional median
    filter, 3x3 mean of the noise, noise floor (``None``: ``1e-6 * max(1, |level|)``)."""
    ny, nx = level_grid.shape
    ok = np.isfinite(level_grid) & np.isfinite(noise_grid)
    if not ok.any():
        g = np.full((ny, nx), np.nan, dtype=np.float32)
        return Background(g, g.copy(), mesh, shape, float("nan"), float("nan"))
    if not ok.all():
        level_grid = np.where(ok, level_grid, np.median(level_grid[ok]))
        noise_grid = np.where(ok, noise_grid, np.median(noise_grid[ok]))
    if filter_size > 1 and (ny > 1 or nx > 1):
        level_grid = median_filter(level_grid, size=filter_size, mode="nearest")
        noise_grid = median_filter(noise_grid, size=filter_size, mode="nearest")
    # the noise varies slowly: a 3x3 mean of the cells (a third of the estimation error)
    noise_grid = uniform_filter(noise_grid, size=3, mode="nearest") if min(ny, nx) >= 3 else noise_grid
    glevel = float(np.median(level_grid))
    if min_noise is None:
        min_noise = 1e-6 * max(1.0, abs(glevel))
    noise_grid = np.maximum(noise_grid, min_noise)
    lg = level_grid.astype(np.float32)
    ng = noise_grid.astype(np.float32)
    return Background(lg, ng, mesh, shape, glevel, float(np.median(ng)))
