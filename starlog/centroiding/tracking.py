"""Tracking mode: known stars measured in windows around their predicted positions, the full frame searched
only at intervals.

A star tracker acquires its stars by searching the whole frame (detection, :func:`starlog.detect.detect_stars`),
then tracks them: each star's next position is predicted from its last ones (constant velocity), its peak is
found in a small window of the matched-filtered frame around the prediction, and its coarse position, with
the background and noise its acquisition measured, makes the detection row that the ordinary measurement
(:func:`starlog.centroiding.measure.measure_methods`) takes. So a tracked star is measured as full mode measures
it, on the same window whenever the coarse position rounds to the same pixel.

The functions here are the numpy form of a tracked frame (:func:`track_frame_vectorised`, completed by
:func:`finish_tracked` once measured); :mod:`starlog.centroiding.tracked_frame` does the same in compiled code,
the same numbers given the same state, and the tests compare the two.

The functions here decide when a tracked frame must be searched in full instead:

* :func:`locate_stars` — a star is *not found* when its filtered peak falls below the detection threshold, lies
  on the edge of its search window (it moved farther than predicted) or outside the frame;
* :func:`lost_stars` — a measured star is *lost* when its fit failed, its flux changed much and significantly
  from its acquisition's (a newcomer blended in, a blend came apart, the star faded), or another star comes
  within its window;
* :func:`new_light` and :func:`lasting_light` — light appeared outside every star's window in two frames in a
  row: cell means of the frame against those of the acquisition, a cell rising by more than
  ``new_light_sigma`` of its noise (a bright star entered; a cosmic ray lasts one frame);
* :func:`is_image_sequence` — whether the first frames of a log are a sequence of one field (tracking pays)
  or unrelated images (a folder of stills, a log whose frames jump).

Coordinates: x = column, y = row, 0-based, (0, 0) at the centre of the top-left pixel.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from starlog.detect import DETECTION_DTYPE
from starlog.detect.flags import StarFlag
from starlog.detect.detection import matched_filter_kernel
from starlog.detect.position import coarse_offsets
from starlog.errors import InvalidParameterError

__all__ = ["DEFAULT_ACQUIRE_EVERY", "TrackedFrame", "TrackingSettings", "TrackState", "advance", "cell_means",
           "finish_tracked", "is_image_sequence", "lasting_light", "locate_stars", "lost_stars", "new_light",
           "start_tracking", "track_frame_vectorised"]

F64 = npt.NDArray[np.float64]
Mask = npt.NDArray[np.bool_]

DEFAULT_ACQUIRE_EVERY = 100
"""Frames between two full-frame searches. ``tools/bench_centroid_stage.py`` measures the choice: at 1024² a
search costs about five compiled tracked frames, so one every 100 frames adds about 4 % to a tracked frame's cost
(every 200 frames is no cheaper within the machine's noise), and a star entering too faint for :func:`new_light`
waits at most a third of a second at 300 Hz."""

_KEPT_FLAGS = int(StarFlag.BLENDED | StarFlag.ELONGATED)
"""Detection flags a tracked star keeps from its acquisition (the others are measured again in every frame)."""


@dataclass(frozen=True)
class TrackingSettings:
    """How tracking finds, keeps and gives up stars.

    Attributes
    ----------
    acquire_every : int
        Frames between two full-frame searches (the first frame of every block is one).
    search : int
        Half-size of the search window, px: how far a star's peak may lie from its predicted pixel.
    threshold, filter_sigma, border : float, float, int
        The detection's threshold (matched-filter SNR), matched-filter sigma and border margin.
    flux_change, flux_sigma : float
        A star whose flux changed from its acquisition's by more than ``flux_change`` of it and ``flux_sigma``
        times its error is lost.
    cell : int
        Side of the cells whose means :func:`new_light` compares, px.
    new_light_sigma : float
        Rise of a cell's mean, in its noise, that calls for a full search.
    """

    acquire_every: int = DEFAULT_ACQUIRE_EVERY
    search: int = 5
    threshold: float = 5.0
    filter_sigma: float = 1.5
    border: int = 3
    flux_change: float = 0.33
    flux_sigma: float = 5.0
    cell: int = 16
    new_light_sigma: float = 8.0

    def __post_init__(self) -> None:
        if not (self.acquire_every >= 1 and self.search >= 1 and self.cell >= 4 and self.flux_change > 0):
            raise InvalidParameterError(
                f"tracking needs acquire_every >= 1, search >= 1 px, cell >= 4 px and flux_change > 0; got "
                f"{self.acquire_every!r}, {self.search!r}, {self.cell!r}, {self.flux_change!r}.")

    def to_dict(self) -> dict[str, Any]:
        return {"acquire_every": self.acquire_every, "search_px": self.search, "flux_change": self.flux_change,
                "flux_sigma": self.flux_sigma, "new_light_cell_px": self.cell, "new_light_sigma": self.new_light_sigma}


@dataclass(frozen=True)
class TrackState:
    """The stars being tracked: their acquisition rows, last positions and velocities, the acquisition's cell means."""

    reference: npt.NDArray[np.void]
    """DETECTION_DTYPE rows of the tracked stars from their acquisition (background, noise, flags, star index)."""
    flux: F64
    """Each star's flux at its acquisition (the first method's), DN."""
    x: F64
    y: F64
    vx: F64
    vy: F64
    cells: F64 | None
    """Cell means of the acquisition frame (:func:`cell_means`)."""
    acquired_x: F64
    acquired_y: F64
    """Where every detection of the acquisition was (the cells around them never count as new light)."""
    quiet: Mask | None = None
    """Stars lost in the frame right after their acquisition: still looked for, measured when found, but their
    loss calls for no full search (a star at the detection's threshold would call for one every frame)."""
    since_acquisition: int = 0
    excess: F64 | None = None
    """Half of how far each cell of the acquisition stands above its median cell (:func:`new_light`'s margin for
    light already there), made once with the state."""

    @property
    def quiet_stars(self) -> Mask:
        return self.quiet if self.quiet is not None else np.zeros(self.x.size, np.bool_)


def cell_means(image: npt.NDArray[Any], cell: int) -> F64:
    """Mean of every whole ``cell`` x ``cell`` block of the frame (a ragged last row or column left out; missing
    pixels count as the frame's median). Integer frames are summed exactly, in integers."""
    rows, cols = image.shape[0] // cell, image.shape[1] // cell
    if rows == 0 or cols == 0:
        return np.zeros((0, 0))
    block = image[: rows * cell, : cols * cell]
    if block.dtype.kind in "ui" and block.dtype.itemsize <= 2 and cell <= 256:
        accumulator: type = np.uint32
    else:
        accumulator = np.float64
        if block.dtype.kind == "f" and not np.isfinite(block).all():
            finite = np.isfinite(block)
            block = np.where(finite, block, np.median(block[finite]) if finite.any() else 0.0)
    sums = block.reshape(rows, cell, cols * cell).sum(axis=1, dtype=accumulator)
    return np.asarray(sums.reshape(rows, cols, cell).sum(axis=2, dtype=accumulator), np.float64) / (cell * cell)


def _carried_velocities(x: F64, y: F64, previous: TrackState, radius: float) -> tuple[F64, F64]:
    """Velocity of each star of a new acquisition: its step from the star of ``previous`` whose prediction is
    nearest, within ``radius`` px; the others take the median step of the matched ones (the platform's
    motion), or of ``previous``'s velocities when none matched."""
    vx, vy = np.full(x.size, np.median(previous.vx)), np.full(x.size, np.median(previous.vy))
    if x.size == 0:
        return vx, vy
    d2 = (x[:, None] - (previous.x + previous.vx)) ** 2 + (y[:, None] - (previous.y + previous.vy)) ** 2
    nearest = np.argmin(d2, axis=1)
    matched = d2[np.arange(x.size), nearest] <= radius * radius
    if not matched.any():
        return vx, vy
    step_x, step_y = x - previous.x[nearest], y - previous.y[nearest]
    return (np.where(matched, step_x, np.median(step_x[matched])),
            np.where(matched, step_y, np.median(step_y[matched])))


def start_tracking(image: npt.NDArray[Any], detections: npt.NDArray[np.void], centroids: npt.NDArray[np.void],
                   settings: TrackingSettings, previous: TrackState | None = None) -> TrackState:
    """The state after a full-frame search: every detection tracked from its centroid (``centroids``: the first
    method's rows, in the detections' order), its velocity carried from ``previous`` (the frame before, when it
    was tracked; matched within twice the search window plus that state's largest speed), the frame's cell
    means as the reference."""
    good = (centroids["flags"] & int(StarFlag.FIT_FAILED)) == 0
    x, y = np.array(centroids["x"], np.float64), np.array(centroids["y"], np.float64)
    if previous is not None and previous.x.size:
        speed = float(np.max(np.hypot(previous.vx, previous.vy)))
        vx, vy = _carried_velocities(x, y, previous, 2.0 * settings.search + speed)
    else:
        vx, vy = np.zeros(x.size), np.zeros(x.size)
    cells = cell_means(image, settings.cell)
    return TrackState(reference=detections[good].copy(), flux=np.asarray(centroids["flux"][good], np.float64),
                      x=x[good], y=y[good], vx=vx[good], vy=vy[good], cells=cells, acquired_x=x, acquired_y=y,
                      quiet=np.zeros(int(good.sum()), np.bool_), excess=0.5 * _lit(cells))


def _reflect(index: npt.NDArray[np.intp], n: int) -> npt.NDArray[np.intp]:
    """Indices beyond ``[0, n)`` reflected as OpenCV's ``BORDER_REFLECT`` (``fedcba|abcdef``), the detection's."""
    index = np.where(index < 0, -index - 1, index)
    return np.clip(np.where(index >= n, 2 * n - index - 1, index), 0, n - 1)


def _search_windows(image: npt.NDArray[Any], xc: npt.NDArray[np.intp], yc: npt.NDArray[np.intp], half: int,
                    fill: F64) -> F64:
    """(n, 2 half + 1, 2 half + 1) windows of the frame centred on ``(xc, yc)``, reflected at its edges, their
    missing (non-finite) pixels filled by ``fill`` (each star's background)."""
    d = np.arange(-half, half + 1)
    rows = _reflect(yc[:, None] + d, image.shape[0])
    cols = _reflect(xc[:, None] + d, image.shape[1])
    win = np.asarray(image[rows[:, :, None], cols[:, None, :]], np.float64)
    if win.dtype.kind == "f" and not np.isfinite(win).all():
        win = np.where(np.isfinite(win), win, fill[:, None, None])
    return win


def _filtered(windows: F64, k1: F64) -> F64:
    """The windows smoothed by the separable kernel ``k1``, 'valid' part only (each side shorter by its radius):
    rows, then columns, in float64, each tap added in turn (the compiled search's order, so the same bits)."""
    taps = k1.size
    inner = windows.shape[2] - taps + 1
    rows = k1[0] * windows[:, :, :inner]
    for t in range(1, taps):
        rows = rows + k1[t] * windows[:, :, t: t + inner]
    out = k1[0] * rows[:, :inner, :]
    for t in range(1, taps):
        out = out + k1[t] * rows[:, t: t + inner, :]
    return out


def _nearest_peak(filtered: F64, outside: Mask, level: F64, dx: F64, dy: F64) -> npt.NDArray[np.intp]:
    """Per window, the flat index (in the central search area, 2 px inside ``filtered``) of the local maximum above
    ``level`` nearest the predicted offset ``(dx, dy)`` from the centre; the highest pixel when none is (a
    neighbour brighter than the star, inside its search window, is not taken for it)."""
    n, side = filtered.shape[0], filtered.shape[1] - 4
    core = filtered[:, 2: side + 2, 2: side + 2]
    peak = (core >= level[:, None, None]) & ~outside
    for oy in (-1, 0, 1):
        for ox in (-1, 0, 1):
            if oy or ox:
                peak &= core >= filtered[:, 2 + oy: side + 2 + oy, 2 + ox: side + 2 + ox]
    d = np.arange(side) - side // 2
    distance = (d[None, :, None] - dy[:, None, None]) ** 2 + (d[None, None, :] - dx[:, None, None]) ** 2
    nearest = np.argmin(np.where(peak, distance, np.inf).reshape(n, -1), axis=1)
    highest = np.argmax(np.where(outside, -np.inf, core).reshape(n, -1), axis=1)
    return np.where(peak.reshape(n, -1).any(axis=1), nearest, highest)


def locate_stars(image: npt.NDArray[Any], state: TrackState, settings: TrackingSettings
                 ) -> tuple[npt.NDArray[np.void], Mask]:
    """Detection rows of the tracked stars in this frame, and which were found.

    Each star's peak is the local maximum of the matched-filtered frame above the detection's threshold nearest
    its predicted position, within ``search`` px of its predicted pixel; its coarse position is the detection's
    (:func:`starlog.detect.position.coarse_offsets`) around that peak, with the background and noise of its
    acquisition; flagged ``BORDER`` within ``border`` px of the frame's edge, as the detection flags it. Not found: the peak's SNR is below the threshold, the peak is on
    the search window's edge (the star moved farther than predicted) or outside the frame.
    """
    n = state.x.size
    out = np.zeros(n, DETECTION_DTYPE)
    if n == 0:
        return out, np.zeros(0, np.bool_)
    k1 = matched_filter_kernel(settings.filter_sigma)
    r, s = k1.size // 2, settings.search
    h, w = image.shape
    px = np.clip(np.rint(state.x + state.vx), 0, w - 1).astype(np.intp)
    py = np.clip(np.rint(state.y + state.vy), 0, h - 1).astype(np.intp)
    bg, noise = np.asarray(state.reference["background"], np.float64), np.asarray(state.reference["noise"], np.float64)
    raw = _search_windows(image, px, py, s + 2 + r, bg) - bg[:, None, None]
    filtered = _filtered(raw, k1)  # centred on the prediction, half-size s + 2
    d = np.arange(-s, s + 1)
    outside = ((py[:, None] + d < 0) | (py[:, None] + d >= h))[:, :, None] | \
        ((px[:, None] + d < 0) | (px[:, None] + d >= w))[:, None, :]  # reflections of the frame's own light
    level = settings.threshold * noise * float(np.sum(k1 * k1))
    best = _nearest_peak(filtered, outside, level, state.x + state.vx - px, state.y + state.vy - py)
    area = np.where(outside, -np.inf, filtered[:, 2: 2 * s + 3, 2: 2 * s + 3]).reshape(n, -1)
    iy, ix = np.divmod(best, 2 * s + 1)
    rows = np.arange(n)
    peak = area[rows, best]
    snr = peak / (noise * float(np.sum(k1 * k1)))
    fy, fx = iy + 2, ix + 2  # the peak in the filtered windows
    d3, d5 = np.arange(-1, 2), np.arange(-2, 3)
    three = filtered[rows[:, None, None], (fy[:, None] + d3)[:, :, None], (fx[:, None] + d3)[:, None, :]]
    box = raw[rows[:, None, None], (fy[:, None] + r + d5)[:, :, None], (fx[:, None] + r + d5)[:, None, :]]
    ox, oy = coarse_offsets(box, three)
    x_peak, y_peak = px - s + ix, py - s + iy
    inside = (x_peak >= 0) & (x_peak < w) & (y_peak >= 0) & (y_peak < h)
    border = (x_peak < settings.border) | (x_peak >= w - settings.border) | \
             (y_peak < settings.border) | (y_peak >= h - settings.border)
    on_edge = (iy == 0) | (iy == 2 * s) | (ix == 0) | (ix == 2 * s)
    found = (snr >= settings.threshold) & ~on_edge & inside & np.isfinite(snr)
    for name in ("star", "background", "noise", "area", "elongation"):
        out[name] = state.reference[name]
    out["x"], out["y"] = x_peak + ox, y_peak + oy
    out["x_peak"], out["y_peak"] = x_peak, y_peak
    out["flux"], out["peak"], out["snr"] = state.reference["flux"], box[:, 2, 2], snr
    out["x_min"], out["x_max"], out["y_min"], out["y_max"] = x_peak - 2, x_peak + 2, y_peak - 2, y_peak + 2
    out["flags"] = (state.reference["flags"] & _KEPT_FLAGS) | int(StarFlag.TRACKED)
    out["flags"][border] |= np.uint16(StarFlag.BORDER)
    return out, found


def lost_stars(centroids: npt.NDArray[np.void], state: TrackState, settings: TrackingSettings,
               reach: float) -> Mask:
    """Measured stars that cannot be trusted from their window alone: the fit failed; the flux changed from
    the acquisition's by more than ``flux_change`` of it and ``flux_sigma`` of its error (a newcomer blended
    in, a blend coming apart, a star fading); or another tracked star, predicted or measured, is within
    ``reach`` px (its window's half-size), where the two blend (a quiet star near any other is lost, a star
    near only quiet ones is not)."""
    failed = (centroids["flags"] & int(StarFlag.FIT_FAILED)) != 0
    flux = np.asarray(centroids["flux"], np.float64)
    with np.errstate(all="ignore"):
        error = np.abs(flux) / np.asarray(centroids["snr"], np.float64)
    change = np.abs(flux - state.flux)
    changed = ~np.isfinite(flux) | ((change > settings.flux_change * np.abs(state.flux)) &
                                    ~(change <= settings.flux_sigma * error))
    crowded = np.zeros(state.x.size, np.bool_)
    quiet = state.quiet_stars
    if state.x.size > 1:
        for x, y in ((state.x + state.vx, state.y + state.vy), (centroids["x"], centroids["y"])):
            near = (x[:, None] - x[None, :]) ** 2 + (y[:, None] - y[None, :]) ** 2 < reach * reach
            np.fill_diagonal(near, False)
            crowded |= (near & ~quiet[None, :]).any(axis=1) | (quiet & near.any(axis=1))
    return failed | changed | crowded


def new_light(image: npt.NDArray[Any], state: TrackState, settings: TrackingSettings, reach: float
              ) -> Mask | None:
    """The cells where light appeared outside the windows (None when the frame cannot be compared with the
    acquisition's: another size): a cell whose mean rose above the acquisition's by more than
    ``new_light_sigma`` times its noise (the spread of the cells' changes, at least the stars' median pixel
    noise scaled to the difference of two cell means), once the frame's common change (the median over
    cells) is removed. Cells within ``reach`` px of a tracked star, or of any star of the acquisition, do
    not count; a cell already lit in the acquisition frame (a star the search left out, a hot pixel) must
    rise by half its excess more, as such light also moves with the platform and fluctuates with its own
    shot noise. :func:`lasting_light` tells a star from a cosmic ray."""
    if state.cells is None:
        return np.zeros((0, 0), np.bool_)
    cells = cell_means(image, settings.cell)
    if cells.shape != state.cells.shape:
        return None
    if cells.size == 0:
        return np.zeros(cells.shape, np.bool_)
    change = cells - state.cells
    c, (rows, cols) = settings.cell, change.shape
    steps = np.clip(np.arange(-reach, reach + c, c), -reach, reach)  # no cell between two steps is missed
    x = np.concatenate([state.x + state.vx, state.acquired_x])
    y = np.concatenate([state.y + state.vy, state.acquired_y])
    near_col = np.clip((x[:, None] + steps) // c, 0, cols - 1).astype(np.intp)
    near_row = np.clip((y[:, None] + steps) // c, 0, rows - 1).astype(np.intp)
    free = np.ones(change.shape, np.bool_)
    free[near_row[:, :, None], near_col[:, None, :]] = False
    common = float(np.median(change))
    spread = 1.4826 * float(np.median(np.abs(change - common)))
    floor = float(np.median(state.reference["noise"])) * np.sqrt(2.0) / c if state.reference.size else 0.0
    excess = state.excess if state.excess is not None else 0.5 * _lit(state.cells)
    limit = settings.new_light_sigma * max(spread, floor, 1e-6) + excess
    return free & (change - common > limit)


def lasting_light(risen: Mask, before: Mask | None, tracked: int) -> bool:
    """Whether the light that appeared in this frame (:func:`new_light`'s cells) calls for a search: it was there
    in the frame before too, in the same cell or one next to it (a star entering stays, a cosmic ray lasts one
    frame), or it lit more than two cells at once, or no star is tracked (nothing to lose by searching)."""
    if not risen.any():
        return False
    if tracked == 0 or np.count_nonzero(risen) > 2:
        return True
    if before is None or before.shape != risen.shape or not before.any():
        return False
    grown = cv2.dilate(before.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(np.bool_)
    return bool(np.any(risen & grown))


def _lit(cells: F64) -> F64:
    """How far each cell's mean stands above the frame's median cell (none: a frame smaller than a cell)."""
    return np.maximum(cells - np.median(cells), 0.0) if cells.size else np.zeros(cells.shape)


def advance(state: TrackState, centroids: npt.NDArray[np.void], measured: Mask, quiet: Mask,
            shape: tuple[int, ...], margin: float) -> TrackState:
    """The state after a tracked frame: each ``measured`` star at its position in ``centroids`` (the first method's
    rows), its velocity the step it made; the others carried on at their velocity, and left out once their
    next prediction is more than ``margin`` px outside the frame."""
    x = np.where(measured, centroids["x"], state.x + state.vx)
    y = np.where(measured, centroids["y"], state.y + state.vy)
    vx, vy = np.where(measured, x - state.x, state.vx), np.where(measured, y - state.y, state.vy)
    keep = measured | ((x + vx > -margin) & (x + vx < shape[1] - 1 + margin) &
                       (y + vy > -margin) & (y + vy < shape[0] - 1 + margin))
    return replace(state, reference=state.reference[keep], flux=state.flux[keep], x=x[keep], y=y[keep],
                   vx=vx[keep], vy=vy[keep], quiet=quiet[keep], since_acquisition=state.since_acquisition + 1)


@dataclass(frozen=True)
class TrackedFrame:
    """What a tracked frame came to (:func:`track_frame_vectorised`, and its compiled form
    :func:`starlog.centroiding.tracked_frame.track_frame`)."""

    search: bool
    """The frame must be searched in full (the other fields but ``risen`` are then empty)."""
    risen: Mask | None
    """:func:`new_light`'s cells (None: the frame's size differs from the acquisition's)."""
    detections: npt.NDArray[np.void] = field(default_factory=lambda: np.zeros(0, DETECTION_DTYPE))
    """:func:`locate_stars`' rows, one per tracked star."""
    found: Mask = field(default_factory=lambda: np.zeros(0, np.bool_))
    centroids: npt.NDArray[np.void] | None = None
    """The first method's rows, one per tracked star (None: not measured yet)."""
    lost: Mask | None = None
    """Stars not found or lost (:func:`lost_stars`): left out of the frame's tables."""
    state: TrackState | None = None
    """The state after the frame (:func:`advance`)."""
    remeasured: bool = False
    """The compiled frame left the end of the measurement to numpy: a window needed the robust re-measurement."""


def finish_tracked(frame: TrackedFrame, centroids: npt.NDArray[np.void], state: TrackState,
                   settings: TrackingSettings, half_size: int, shape: tuple[int, ...]) -> TrackedFrame:
    """A located ``frame`` completed with its first method's ``centroids`` (every tracked star): the stars lost
    (:func:`lost_stars` within ``half_size``, the windows' half-size), a search when one that is not quiet is (but
    right after an acquisition), else the state :func:`advance` gives."""
    lost = ~frame.found | lost_stars(centroids, state, settings, float(half_size))
    quiet = state.quiet_stars
    if (lost & ~quiet).any() and state.since_acquisition:
        return replace(frame, search=True)
    after = advance(state, centroids, ~lost, quiet | lost, shape, float(settings.search))
    return replace(frame, centroids=centroids, lost=lost, state=after)


def track_frame_vectorised(image: npt.NDArray[Any], state: TrackState, settings: TrackingSettings,
                           before: Mask | None, half_size: int,
                           measure: Callable[[npt.NDArray[np.void]], npt.NDArray[np.void]] | None = None
                           ) -> TrackedFrame:
    """One tracked frame in numpy, the reference of the compiled :func:`~starlog.centroiding.tracked_frame.track_frame`:
    the light check (:func:`new_light` around windows of ``half_size``, :func:`lasting_light` against ``before``,
    the frame before's cells), the window search (:func:`locate_stars`), then with ``measure`` (the first method's
    rows of given detection rows) :func:`finish_tracked`."""
    risen = new_light(image, state, settings, half_size + settings.search + 1)
    if risen is None or lasting_light(risen, before, state.x.size):
        return TrackedFrame(search=True, risen=risen)
    detections, found = locate_stars(image, state, settings)
    if (~found & ~state.quiet_stars).any() and state.since_acquisition:
        return TrackedFrame(search=True, risen=risen)
    frame = TrackedFrame(search=False, risen=risen, detections=detections, found=found)
    if measure is None:
        return frame
    return finish_tracked(frame, measure(detections), state, settings, half_size, image.shape)


def is_image_sequence(positions: Sequence[tuple[F64, F64]], search: float, *, min_matched: float = 0.5
                      ) -> tuple[bool, str]:
    """Whether consecutive frames show one field moving a little (tracking pays) or unrelated images.

    ``positions``: the detections ``(x, y)`` of the log's first frames. For each consecutive pair, the
    field's shift is the median displacement of each star to its nearest neighbour within ``3 search`` px;
    the pair is *continuous* when at least ``min_matched`` of the stars lie within 1.5 px of their shifted
    position. A sequence: at least two pairs, three quarters of them continuous. Returns the verdict and a
    sentence on it.
    """
    pairs = continuous = 0
    for (x0, y0), (x1, y1) in zip(positions, positions[1:]):
        if x0.size == 0 or x1.size == 0:
            continue
        pairs += 1
        dx, dy = x0[:, None] - x1[None, :], y0[:, None] - y1[None, :]
        near = np.argmin(dx * dx + dy * dy, axis=1)
        rows = np.arange(x0.size)
        step_x, step_y = -dx[rows, near], -dy[rows, near]
        close = np.hypot(step_x, step_y) <= 3.0 * search
        if not close.any():
            continue
        sx, sy = np.median(step_x[close]), np.median(step_y[close])
        ex, ey = x0[:, None] + sx - x1[None, :], y0[:, None] + sy - y1[None, :]
        matched = np.sqrt(np.min(ex * ex + ey * ey, axis=1)) <= 1.5
        continuous += int(np.mean(matched) >= min_matched)
    verdict = pairs >= 2 and continuous >= 0.75 * pairs
    reason = f"{continuous} of {pairs} pairs of first frames: one field, shifted < {3 * search:g} px"
    return verdict, reason
