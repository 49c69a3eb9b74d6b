"""Connected components of a foreground mask, their peaks, and the splitting of blends.

Everything works on the list of foreground pixels inside the components' bounding boxes (a
few thousand in a star field), so there is no per-star image operation:

- :func:`find_components`: 8-connected components of the mask with their pixel lists, areas
  and bounding boxes (the paper's "connected components" step);
- :func:`component_peaks`: each component's local maxima of the matched-filtered image,
  brightest first, and the deblending test that keeps a secondary peak only when a
  significant saddle separates it from every brighter kept peak (flag ``BLENDED``).

Coordinates: x = column, y = row, 0-based, (0, 0) at the centre of the top-left pixel.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from starlog.errors import InvalidInputError

__all__ = ["Components", "Peaks", "component_peaks", "find_components", "find_components_vectorised"]

I64 = npt.NDArray[np.intp]
F64 = npt.NDArray[np.float64]

# the forward half of the 8-neighbourhood (each pixel pair once)
_FORWARD = [(0, 1), (1, -1), (1, 0), (1, 1)]


@dataclass(frozen=True)
class Components:
    """Foreground pixels grouped by component (in the order of their external contours).

    ``y``, ``x`` and ``label`` have one entry per pixel, sorted by (label, raster order);
    ``start[c]`` is the first pixel of component ``c``. ``x_min .. y_max`` are inclusive.
    """

    y: I64
    x: I64
    label: I64
    start: I64
    area: I64
    x_min: I64
    x_max: I64
    y_min: I64
    y_max: I64

    @property
    def count(self) -> int:
        return int(self.area.size)

    def box_centres(self) -> tuple[F64, F64]:
        """(x, y) centres of the bounding boxes, px."""
        return self.x_min + 0.5 * (self.x_max - self.x_min), self.y_min + 0.5 * (self.y_max - self.y_min)


def _box_pixels(rects: I64) -> tuple[I64, I64, I64]:
    """(box, y, x) of every pixel inside the boxes ``(x, y, w, h)``, box by box in raster order."""
    sizes = rects[:, 2] * rects[:, 3]
    box = np.repeat(np.arange(rects.shape[0]), sizes)
    offset = np.arange(box.size) - np.repeat(np.cumsum(sizes) - sizes, sizes)
    width = rects[box, 2]
    return box, rects[box, 1] + offset // width, rects[box, 0] + offset % width


def _same_component(box: I64, y: I64, x: I64, seed: npt.NDArray[np.bool_]) -> npt.NDArray[np.bool_]:
    """Which pixels are 8-connected, inside their own box, to their box's seed pixel.

    Pixels are graph nodes, linked to the foreground neighbours of the same box (a box is
    searched on its own, as a crop would be). One graph for all boxes: used when many boxes
    overlap (see :func:`_seed_connected`).
    """
    n = box.size
    span = int(max(y.max(), x.max())) + 3
    key = (box * span + y + 1) * span + x + 1  # unique and ordered by (box, row, column)
    heads, tails = [], []
    for dy, dx in _FORWARD:
        target = key + dy * span + dx
        pos = np.minimum(np.searchsorted(key, target), n - 1)
        hit = key[pos] == target  # the padding column and row keep boxes and rows apart
        heads.append(np.nonzero(hit)[0])
        tails.append(pos[hit])
    head, tail = np.concatenate(heads), np.concatenate(tails)
    graph = coo_matrix((np.ones(head.size, np.int8), (head, tail)), shape=(n, n)).tocsr()
    _, label = connected_components(graph, directed=False)
    seed_label = np.full(int(box.max()) + 1, -1, np.intp)
    seed_label[box[seed]] = label[seed]
    return label == seed_label[box]


_CROPS_UP_TO = 64
"""Up to this many overlapping boxes, each is labelled as an image crop (a few microseconds a
box); beyond, one sparse graph of all their pixels is cheaper."""


def _seed_connected(binary: npt.NDArray[np.uint8], rects: I64, seeds: I64, boxes: I64, box: I64, y: I64,
                    x: I64) -> npt.NDArray[np.bool_]:
    """For the pixels (``box``, ``y``, ``x``) of the boxes ``boxes``: whether each is 8-connected,
    inside its own box's crop of ``binary``, to that box's seed pixel (as :func:`_same_component`)."""
    keep_flat, offset = [], np.zeros(int(rects.shape[0]), np.intp)
    total = 0
    for b in boxes.tolist():
        bx, by, bw, bh = rects[b].tolist()
        _, label = cv2.connectedComponents(binary[by : by + bh, bx : bx + bw], connectivity=8, ltype=cv2.CV_32S)
        keep_flat.append((label == label[seeds[b, 1] - by, seeds[b, 0] - bx]).ravel())
        offset[b] = total
        total += bw * bh
    flat = np.concatenate(keep_flat)
    return flat[offset[box] + (y - rects[box, 1]) * rects[box, 2] + (x - rects[box, 0])]


def find_components(binary: npt.NDArray[np.uint8], min_area: int = 1, max_area: int | None = None) -> Components:
    """8-connected components of a uint8 mask (non-zero = foreground) with ``min_area <= area <= max_area``.

    External contours give each component's bounding box and a seed pixel cheaply; a box's
    foreground pixels are the component's, except where boxes overlap: there only the pixels
    connected to the seed inside the box count (a neighbour poking in is left out). The
    pixels are listed in compiled code (:func:`starlog.detect.peak_kernels.member_pixels`);
    :func:`find_components_vectorised` lists them in numpy, the reference it is tested against.
    """
    return _find_components(binary, min_area, max_area, _member_pixels)


def find_components_vectorised(binary: npt.NDArray[np.uint8], min_area: int = 1,
                               max_area: int | None = None) -> Components:
    """:func:`find_components` with the pixels listed in numpy."""
    return _find_components(binary, min_area, max_area, _member_pixels_vectorised)


def _shared_boxes(rects: I64) -> npt.NDArray[np.bool_]:
    """Which boxes ``(x, y, w, h)`` overlap another (all of them, past 2000 boxes)."""
    x0, y0 = rects[:, 0], rects[:, 1]
    x1, y1 = x0 + rects[:, 2], y0 + rects[:, 3]
    if 1 < rects.shape[0] <= 2000:
        overlap = ((x0[:, None] < x1[None, :]) & (x0[None, :] < x1[:, None])
                   & (y0[:, None] < y1[None, :]) & (y0[None, :] < y1[:, None]))
        return overlap.sum(axis=1) > 1
    return np.full(rects.shape[0], rects.shape[0] > 1)


def _member_pixels(binary: npt.NDArray[np.uint8], rects: I64, seeds: I64) -> tuple[I64, I64, I64]:
    """(box, y, x) of each box's pixels (see :func:`find_components`), box after box in raster order."""
    from starlog.detect.peak_kernels import member_pixels  # numba: imported, and compiled, on first use

    img = np.ascontiguousarray(binary, np.uint8)
    if img.ndim != 2 or rects.ndim != 2 or rects.shape[1] != 4 or seeds.shape != (rects.shape[0], 2):
        raise InvalidInputError("find_components: the mask, boxes or seeds have mismatched shapes.")
    rects, seeds = np.ascontiguousarray(rects, np.intp), np.ascontiguousarray(seeds, np.intp)
    total = int(np.sum(rects[:, 2] * rects[:, 3]))
    box, y, x = np.empty(total, np.intp), np.empty(total, np.intp), np.empty(total, np.intp)
    n = member_pixels(img, rects, seeds, _shared_boxes(rects), box, y, x)
    if n < 0:
        raise InvalidInputError(f"find_components: box {-1 - n} is not inside the mask or misses its seed.")
    return box[:n], y[:n], x[:n]


def _member_pixels_vectorised(binary: npt.NDArray[np.uint8], rects: I64, seeds: I64) -> tuple[I64, I64, I64]:
    """:func:`_member_pixels` in numpy."""
    box, y, x = _box_pixels(rects)
    on = binary[y, x] != 0
    box, y, x = box[on], y[on], x[on]
    shared = _shared_boxes(rects)
    if shared.any():
        sub = shared[box]
        member = np.ones(box.size, bool)
        boxes = np.flatnonzero(shared)
        if boxes.size <= _CROPS_UP_TO:
            member[sub] = _seed_connected(binary, rects, seeds, boxes, box[sub], y[sub], x[sub])
        else:
            seed = (y == seeds[box, 1]) & (x == seeds[box, 0])
            member[sub] = _same_component(box[sub], y[sub], x[sub], seed[sub])
        box, y, x = box[member], y[member], x[member]
    return box, y, x


def _find_components(binary: npt.NDArray[np.uint8], min_area: int, max_area: int | None,
                     member_pixels: Callable[[npt.NDArray[np.uint8], I64, I64], tuple[I64, I64, I64]]
                     ) -> Components:
    contours, _ = cv2.findContours(binary, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    rects = np.array([cv2.boundingRect(c) for c in contours], dtype=np.intp).reshape(-1, 4)
    seeds = np.array([c[0, 0] for c in contours], dtype=np.intp).reshape(-1, 2)
    big = rects[:, 2] * rects[:, 3] >= min_area  # a box smaller than min_area holds no keeper
    rects, seeds = rects[big], seeds[big]
    box, y, x = member_pixels(binary, rects, seeds)
    area = np.bincount(box, minlength=rects.shape[0])
    keep = (area >= min_area) & (area <= (max_area if max_area is not None else box.size))
    if not keep.all():
        on = keep[box]
        box, y, x = (np.cumsum(keep) - 1)[box[on]], y[on], x[on]
        rects, area = rects[keep], area[keep]
    return Components(
        y=y, x=x, label=box, start=np.cumsum(area) - area, area=area,
        x_min=rects[:, 0], x_max=rects[:, 0] + rects[:, 2] - 1,
        y_min=rects[:, 1], y_max=rects[:, 1] + rects[:, 3] - 1,
    )


@dataclass(frozen=True)
class Peaks:
    """Kept peaks, grouped by component and brightest first inside each.

    ``fval`` is the filtered value above the component's level; ``flux`` the component's
    isophotal flux shared in proportion to ``fval``; ``blended`` marks components split in two
    or more; ``component`` indexes :class:`Components`.
    """

    y: I64
    x: I64
    fval: F64
    flux: F64
    blended: npt.NDArray[np.bool_]
    component: I64


def _local_maxima(comp: Components, filtered: npt.NDArray[np.float32]) -> npt.NDArray[np.bool_]:
    """Pixels not below any 8-neighbour that lies in the component's bounding box.

    The box (not the whole frame) is the neighbourhood, so a maximum on the box edge stands
    even when a brighter pixel lies just outside it; a component with no such pixel (its top
    sits on a pixel the opening removed) gets its brightest pixel (first in raster order).
    Compiled (:func:`starlog.detect.peak_kernels.local_maxima`); :func:`_local_maxima_vectorised`
    is the numpy form, the reference it is tested against.
    """
    from starlog.detect.peak_kernels import local_maxima  # numba: imported, and compiled, on first use

    img = np.asarray(filtered)
    n, count = comp.y.shape, comp.area.shape
    if img.ndim != 2 or comp.x.shape != n or comp.label.shape != n or len(n) != 1 or any(
            a.shape != count for a in (comp.x_min, comp.x_max, comp.y_min, comp.y_max)):
        raise InvalidInputError("_local_maxima: the components' arrays or the filtered image have mismatched shapes.")
    peak = np.empty(n, np.bool_)
    # compared in the image's own float type, as the numpy form compares them
    values = np.ascontiguousarray(img if img.dtype in (np.float32, np.float64) else img.astype(np.float64))
    bad = local_maxima(values, *(np.ascontiguousarray(a, np.intp) for a in (
        comp.y, comp.x, comp.label, comp.x_min, comp.x_max, comp.y_min, comp.y_max)), peak)
    if bad >= 0:
        raise InvalidInputError(f"_local_maxima: component or pixel {bad} lies outside the frame or its box.")
    return peak


def _local_maxima_vectorised(comp: Components, filtered: npt.NDArray[np.float32]) -> npt.NDArray[np.bool_]:
    """:func:`_local_maxima` vectorised over the pixels in numpy."""
    cols = filtered.shape[1]
    c = comp.label
    flat = filtered.ravel()
    index = comp.y * cols + comp.x
    f = flat[index]
    # which of the rows y-1, y, y+1 and columns x-1, x, x+1 lie in the pixel's box
    rows_in = [comp.y > comp.y_min[c], None, comp.y < comp.y_max[c]]
    cols_in = [comp.x > comp.x_min[c], None, comp.x < comp.x_max[c]]
    top = f.copy()
    # one neighbour at a time over all pixels (long vectors: numpy reduces short rows slowly)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            if dy == dx == 0:
                continue
            inside = rows_in[dy + 1] if dx == 0 else cols_in[dx + 1] if dy == 0 else rows_in[dy + 1] & cols_in[dx + 1]
            value = flat.take(index + (dy * cols + dx), mode="clip")  # off-frame neighbours are outside the box
            np.maximum(top, np.where(inside, value, f), out=top)
    peak = f >= top
    lonely = np.bincount(c[peak], minlength=comp.count) == 0
    if lonely.any():
        pixel = np.arange(c.size)
        by_value = np.lexsort((pixel, -f.astype(np.float64), c))  # per component: brightest, then raster
        first = by_value[comp.start]
        peak[first[lonely]] = True
    return peak


def _significant(fy: I64, fx: I64, fv: F64, ty: I64, tx: I64, origin: tuple[I64, I64],
                 level: npt.NDArray[np.float32], filtered: npt.NDArray[np.float32], floor: F64,
                 contrast: float) -> npt.NDArray[np.bool_]:
    """Peak (fy, fx) of value fv rises above the lowest point of the straight path to (ty, tx)
    by more than ``max(floor, contrast * fv)`` (the saddle test of deblending).

    The path's pixels are rounded in coordinates relative to ``origin`` (the component's box
    corner): rounding halves to even depends on the integer part.
    """
    oy, ox = origin
    fy, fx, ty, tx = fy - oy, fx - ox, ty - oy, tx - ox
    n = np.maximum(np.abs(ty - fy), np.abs(tx - fx)) + 1
    k = np.arange(int(n.max()) + 1)
    t = k[None, :] * (1.0 / n)[:, None]  # np.linspace(0, 1, n + 1), sample by sample
    t = np.where(k[None, :] == n[:, None], 1.0, t)
    inside = k[None, :] <= n[:, None]
    ys = np.rint(fy[:, None] + t * (ty - fy)[:, None]).astype(np.intp)
    xs = np.rint(fx[:, None] + t * (tx - fx)[:, None]).astype(np.intp)
    ys = np.where(inside, ys, fy[:, None]) + oy[:, None]
    xs = np.where(inside, xs, fx[:, None]) + ox[:, None]
    path = filtered[ys, xs] - level[:, None]  # float32, as the filtered image
    low = np.where(inside, path, np.float32(np.inf)).min(axis=1).astype(np.float64)
    return fv - low > np.maximum(floor, contrast * fv)


def component_peaks(
    comp: Components,
    filtered: npt.NDArray[np.float32],
    image: npt.NDArray[np.float32],
    level: F64,
    filtered_noise: F64,
    *,
    deblend: bool = True,
    nsigma: float = 3.0,
    contrast: float = 0.05,
) -> Peaks:
    """The peaks of each component kept after deblending, with their share of the component's flux.

    ``level`` and ``filtered_noise`` are per component (background level and matched-filter noise
    at the box centre). A secondary peak is kept when, towards every brighter kept peak of its
    component, it rises above the path's lowest filtered value by more than
    ``max(nsigma * filtered_noise, contrast * its value)``.
    """
    lev32 = level.astype(np.float32)
    peak = _local_maxima(comp, filtered)
    c = comp.label[peak]
    py, px = comp.y[peak], comp.x[peak]
    f = filtered[py, px]
    fv = f.astype(np.float64) - lev32[c].astype(np.float64)
    single = comp.area[c] == 1  # one-pixel component: the value is taken in float32
    fv[single] = (f[single] - lev32[c][single]).astype(np.float64)
    order = np.lexsort((-fv, c))  # per component brightest first; ties in raster order
    c, py, px, fv = c[order], py[order], px[order], fv[order]
    npeaks = np.bincount(c, minlength=comp.count)
    rank = np.arange(c.size) - (np.cumsum(npeaks) - npeaks)[c]
    kept = rank == 0
    if deblend:
        kept = _deblend(comp, c, rank, py, px, fv, kept, lev32, filtered, nsigma * filtered_noise, contrast)
    c, py, px, fv = c[kept], py[kept], px[kept], fv[kept]
    nkept = np.bincount(c, minlength=comp.count)
    total = np.bincount(c, weights=fv, minlength=comp.count)
    sums = np.bincount(comp.label, weights=image[comp.y, comp.x].astype(np.float64), minlength=comp.count)
    comp_flux = sums - comp.area * level
    share = np.where(total[c] > 0, fv / np.where(total[c] > 0, total[c], 1.0), 1.0 / nkept[c])
    return Peaks(y=py, x=px, fval=fv, flux=comp_flux[c] * share, blended=nkept[c] > 1, component=c)


def _deblend(comp: Components, c: I64, rank: I64, py: I64, px: I64, fv: F64, kept: npt.NDArray[np.bool_],
             lev32: npt.NDArray[np.float32],
             filtered: npt.NDArray[np.float32], floor: F64, contrast: float) -> npt.NDArray[np.bool_]:
    """Keep flags of the peaks, decided rank by rank (a peak is tested against the brighter kept ones)."""
    kept = kept.copy()
    first = np.nonzero(rank == 0)[0]  # index of each component's brightest peak (components with peaks)
    head = np.full(int(c.max()) + 1 if c.size else 0, -1, np.intp)
    head[c[first]] = first
    for r in range(1, int(rank.max()) + 1 if rank.size else 0):
        cand = np.nonzero(rank == r)[0]
        # pairs (candidate, brighter kept peak of the same component)
        lo = head[c[cand]]
        span = np.repeat(cand, r)
        other = np.repeat(lo, r) + np.tile(np.arange(r), cand.size)
        use = kept[other]
        span, other = span[use], other[use]
        cs = c[span]
        ok = _significant(py[span], px[span], fv[span], py[other], px[other], (comp.y_min[cs], comp.x_min[cs]),
                          lev32[cs], filtered, floor[cs], contrast)
        failed = np.bincount(span[~ok], minlength=kept.size)[cand] > 0
        kept[cand] = ~failed
    return kept
