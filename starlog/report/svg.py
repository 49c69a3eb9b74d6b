"""Inline SVG figures drawn with numpy only: line charts, grouped bar charts, a frame with markers.

Each function returns one ``<svg>`` element (a string) that needs nothing at view time: no
script, no font download, images as ``data:`` URIs. Long series are reduced to a bounded number
of points (:func:`envelope`) so a figure's size does not grow with the log's length.
"""

from __future__ import annotations

import base64
import math
import zlib
from collections.abc import Sequence
from dataclasses import dataclass, field
from html import escape

import cv2
import numpy as np
import numpy.typing as npt

__all__ = ["PALETTE", "Series", "Bars", "bar_chart", "envelope", "frame_figure", "line_chart", "nice_ticks"]

#: Colour-blind-safe line colours (Okabe-Ito), repeated for more series.
PALETTE = ("#0072B2", "#D55E00", "#009E73", "#CC79A7", "#E69F00", "#56B4E9", "#000000", "#F0E442")

_W, _H = 720, 280
_LEFT, _RIGHT, _TOP, _BOTTOM = 64, 16, 44, 44
_MAX_POINTS = 1200


@dataclass
class Series:
    """One line of a :func:`line_chart`."""

    label: str
    x: npt.NDArray[np.float64]
    y: npt.NDArray[np.float64]
    color: str = ""
    width: float = 1.2


@dataclass
class Bars:
    """One bar series of a :func:`bar_chart`: one value per group."""

    label: str
    values: Sequence[float]
    color: str = ""


@dataclass
class _Axes:
    x0: float
    x1: float
    y0: float
    y1: float
    width: int = _W
    height: int = _H
    x_ticks: list[float] = field(default_factory=list)
    y_ticks: list[float] = field(default_factory=list)

    def px(self, x: npt.ArrayLike) -> npt.NDArray[np.float64]:
        span = self.x1 - self.x0 or 1.0
        return _LEFT + (np.asarray(x, float) - self.x0) / span * (self.width - _LEFT - _RIGHT)

    def py(self, y: npt.ArrayLike) -> npt.NDArray[np.float64]:
        span = self.y1 - self.y0 or 1.0
        return self.height - _BOTTOM - (np.asarray(y, float) - self.y0) / span * (self.height - _TOP - _BOTTOM)


def nice_ticks(lo: float, hi: float, count: int = 6) -> list[float]:
    """Round tick values (1, 2, 5 × 10^k steps) covering ``[lo, hi]``."""
    if not (math.isfinite(lo) and math.isfinite(hi)):
        return [0.0]
    if hi <= lo:
        hi = lo + (abs(lo) or 1.0)
    raw = (hi - lo) / max(count - 1, 1)
    power = 10 ** math.floor(math.log10(raw))
    step = next(m * power for m in (1, 2, 2.5, 5, 10) if m * power >= raw)
    start = math.floor(lo / step) * step
    ticks = [round(start, 12)]
    while ticks[-1] < hi - step * 1e-9 or len(ticks) < 2:
        ticks.append(round(start + len(ticks) * step, 12))
    return ticks


def _fmt(v: float) -> str:
    if v == 0:
        return "0"
    if abs(v) >= 1e4 or abs(v) < 1e-3:
        return f"{v:.2g}"
    return f"{v:.4g}"


def envelope(x: npt.ArrayLike, y: npt.ArrayLike, max_points: int = _MAX_POINTS
             ) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """At most ``max_points`` points that keep each bucket's minimum and maximum (peaks stay visible)."""
    xs, ys = np.asarray(x, float), np.asarray(y, float)
    if xs.size <= max_points:
        return xs, ys
    buckets = max_points // 2
    edges = np.linspace(0, xs.size, buckets + 1).astype(int)
    keep = []
    for a, b in zip(edges[:-1], edges[1:], strict=True):
        if b <= a:
            continue
        chunk = ys[a:b]
        if not np.isfinite(chunk).any():
            keep.append(a)
            continue
        keep.extend(sorted({a + int(np.nanargmin(chunk)), a + int(np.nanargmax(chunk))}))
    idx = np.asarray(keep, int)
    return xs[idx], ys[idx]


def _frame(ax: _Axes, title: str, x_label: str, y_label: str) -> list[str]:
    """Axes box, grid, tick labels, axis labels and title."""
    w, h = ax.width, ax.height
    out = [f'<rect x="{_LEFT}" y="{_TOP}" width="{w - _LEFT - _RIGHT}" height="{h - _TOP - _BOTTOM}" '
           'fill="#fff" stroke="#888"/>']
    for t in ax.y_ticks:
        y = float(ax.py(t))
        out.append(f'<line x1="{_LEFT}" x2="{w - _RIGHT}" y1="{y:.1f}" y2="{y:.1f}" stroke="#e4e4e4"/>'
                   f'<text x="{_LEFT - 6}" y="{y + 4:.1f}" text-anchor="end">{_fmt(t)}</text>')
    for t in ax.x_ticks:
        x = float(ax.px(t))
        out.append(f'<line x1="{x:.1f}" x2="{x:.1f}" y1="{_TOP}" y2="{h - _BOTTOM}" stroke="#e4e4e4"/>'
                   f'<text x="{x:.1f}" y="{h - _BOTTOM + 16}" text-anchor="middle">{_fmt(t)}</text>')
    out.append(f'<text x="{(w + _LEFT) / 2:.0f}" y="{h - 8}" text-anchor="middle">{escape(x_label)}</text>')
    out.append(f'<text transform="translate(14 {(h - _BOTTOM + _TOP) / 2:.0f}) rotate(-90)" '
               f'text-anchor="middle">{escape(y_label)}</text>')
    out.append(f'<text x="{_LEFT}" y="16" class="title">{escape(title)}</text>')
    return out


def _svg(width: int, height: int, body: list[str], label: str) -> str:
    return (f'<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 {width} {height}" width="{width}" '
            f'height="{height}" role="img" aria-label="{escape(label)}" font-family="sans-serif" font-size="11">'
            "<style>.title{font-weight:bold;font-size:12px}</style>" + "".join(body) + "</svg>")


def _legend(labels: Sequence[tuple[str, str]], width: int) -> list[str]:
    """One row of coloured keys between the title and the plot."""
    out, x = [], float(_LEFT)
    for label, color in labels:
        out.append(f'<rect x="{x:.0f}" y="{_TOP - 17}" width="10" height="10" fill="{color}"/>'
                   f'<text x="{x + 13:.0f}" y="{_TOP - 8}">{escape(label)}</text>')
        x += 22 + 6.2 * len(label)
    return out


def line_chart(series: Sequence[Series], *, title: str, x_label: str, y_label: str,
               markers: Sequence[tuple[float, str]] = (), legend: bool = True, robust: bool = False,
               width: int = _W, height: int = _H) -> str:
    """Lines on shared axes; ``markers`` are labelled vertical lines at given x (e.g. a frequency).

    ``robust``: the y range spans the 1st-99th percentile of the points (a start-up transient does
    not flatten the rest); lines are clipped to the plot.
    """
    reduced = [(s, *envelope(s.x, s.y)) for s in series]
    xs = np.concatenate([r[1] for r in reduced] + [np.array([m for m, _ in markers], float)])
    ys = np.concatenate([r[2] for r in reduced])
    xs, ys = xs[np.isfinite(xs)], ys[np.isfinite(ys)]
    x_ticks = nice_ticks(float(xs.min()), float(xs.max())) if xs.size else [0.0, 1.0]
    y_lo, y_hi = (np.percentile(ys, [1.0, 99.0]) if robust else (ys.min(), ys.max())) if ys.size else (0.0, 1.0)
    if robust:
        y_lo, y_hi = y_lo - 0.15 * (y_hi - y_lo), y_hi + 0.15 * (y_hi - y_lo)
    y_ticks = nice_ticks(float(y_lo), float(y_hi), 5)
    ax = _Axes(float(xs.min()) if xs.size else 0.0, float(xs.max()) if xs.size else 1.0,
               y_ticks[0], y_ticks[-1], width, height, [t for t in x_ticks if xs.size and xs.min() <= t <= xs.max()],
               y_ticks)
    body = _frame(ax, title, x_label, y_label)
    clip = f"clip{zlib.crc32(f'{title} {x_label} {y_label}'.encode()):08x}"
    body.append(f'<clipPath id="{clip}"><rect x="{_LEFT}" y="{_TOP}" width="{width - _LEFT - _RIGHT}" '
                f'height="{height - _TOP - _BOTTOM}"/></clipPath><g clip-path="url(#{clip})">')
    colors = []
    for k, (s, x, y) in enumerate(reduced):
        color = s.color or PALETTE[k % len(PALETTE)]
        colors.append((s.label, color))
        ok = np.isfinite(x) & np.isfinite(y)
        if ok.sum() == 0:
            continue
        pts = " ".join(f"{a:.1f},{b:.1f}" for a, b in zip(ax.px(x[ok]), ax.py(y[ok]), strict=True))
        if ok.sum() == 1:
            body.append(f'<circle cx="{pts.split(",")[0]}" cy="{pts.split(",")[1]}" r="2" fill="{color}"/>')
        body.append(f'<polyline points="{pts}" fill="none" stroke="{color}" stroke-width="{s.width}"/>')
    body.append("</g>")
    for value, label in markers:
        x = float(ax.px(value))
        right = x > 0.7 * width  # label on the side with room
        body.append(f'<line x1="{x:.1f}" x2="{x:.1f}" y1="{_TOP}" y2="{height - _BOTTOM}" stroke="#c00" '
                    f'stroke-dasharray="4 3" stroke-width="1.5"/>'
                    f'<text x="{x - 4 if right else x + 4:.1f}" y="{_TOP + 14}" fill="#c00" '
                    f'text-anchor="{"end" if right else "start"}">{escape(label)}</text>')
    if legend and len(series) > 1:
        body += _legend(colors, width)
    return _svg(width, height, body, title)


def bar_chart(groups: Sequence[str], bars: Sequence[Bars], *, title: str, y_label: str,
              width: int = _W, height: int = _H) -> str:
    """Grouped vertical bars: one group per label of ``groups``, one bar per :class:`Bars`."""
    values = np.array([[float(v) for v in b.values] for b in bars], float).reshape(len(bars), len(groups))
    top = float(np.nanmax(values)) if np.isfinite(values).any() else 1.0
    y_ticks = nice_ticks(0.0, top if top > 0 else 1.0, 5)
    ax = _Axes(0.0, float(len(groups)), 0.0, y_ticks[-1], width, height, [], y_ticks)
    body = _frame(ax, title, "", y_label)
    slot = (width - _LEFT - _RIGHT) / max(len(groups), 1)
    bar_w = slot * 0.8 / max(len(bars), 1)
    colors = []
    for b, series in enumerate(bars):
        color = series.color or PALETTE[b % len(PALETTE)]
        colors.append((series.label, color))
        for g in range(len(groups)):
            v = values[b, g]
            if not np.isfinite(v):
                continue
            x = _LEFT + g * slot + slot * 0.1 + b * bar_w
            y0, y1 = float(ax.py(0.0)), float(ax.py(max(v, 0.0)))
            body.append(f'<rect x="{x:.1f}" y="{y1:.1f}" width="{bar_w * 0.92:.1f}" height="{max(y0 - y1, 0.5):.1f}" '
                        f'fill="{color}"><title>{escape(groups[g])} {escape(series.label)}: {v:.4g}</title></rect>')
    for g, label in enumerate(groups):
        x = _LEFT + (g + 0.5) * slot
        body.append(f'<text x="{x:.1f}" y="{height - _BOTTOM + 16}" text-anchor="middle">{escape(label)}</text>')
    if len(bars) > 1:
        body += _legend(colors, width)
    return _svg(width, height, body, title)


def _stretch(image: npt.NDArray[np.generic], max_side: int) -> npt.NDArray[np.uint8]:
    """8-bit view of a frame: percentile contrast stretch (1 %-99.7 %), square root, downscaled to ``max_side``."""
    data = np.asarray(image, np.float32)
    lo, hi = np.percentile(data, [1.0, 99.7])
    if hi <= lo:
        hi = lo + 1.0
    scaled = np.sqrt(np.clip((data - lo) / (hi - lo), 0.0, 1.0))
    side = max(data.shape)
    if side > max_side:
        f = max_side / side
        scaled = cv2.resize(scaled, (max(1, round(data.shape[1] * f)), max(1, round(data.shape[0] * f))),
                            interpolation=cv2.INTER_AREA)
    return (scaled * 255.0 + 0.5).astype(np.uint8)


def frame_figure(image: npt.NDArray[np.generic], points: Sequence[tuple[float, float, str]], *, title: str,
                 max_side: int = 512, display: int = 480) -> str:
    """A frame (contrast-stretched, as a PNG ``data:`` URI) with a circle at each ``(x, y, label)``.

    Coordinates are pixels with (0, 0) at the centre of the top-left pixel; the SVG's viewBox is in
    the frame's own pixels, so markers stay exact when the picture is downscaled.
    """
    h, w = image.shape[:2]
    ok, png = cv2.imencode(".png", _stretch(image, max_side))
    if not ok:  # pragma: no cover - OpenCV always encodes an 8-bit grey image
        raise RuntimeError("PNG encoding failed")
    uri = "data:image/png;base64," + base64.b64encode(png.tobytes()).decode("ascii")
    scale = display / max(w, h)
    r = max(w, h) / 40
    body = [f'<image href="{uri}" x="-0.5" y="-0.5" width="{w}" height="{h}" preserveAspectRatio="none" '
            'style="image-rendering:pixelated"/>']
    for x, y, label in points:
        body.append(f'<circle cx="{x:.2f}" cy="{y:.2f}" r="{r:.2f}" fill="none" stroke="#ff3b30" '
                    f'stroke-width="{r / 8:.2f}"><title>{escape(label)}</title></circle>')
    return (f'<svg xmlns="http://www.w3.org/2000/svg" viewBox="-0.5 -0.5 {w} {h}" width="{w * scale:.0f}" '
            f'height="{h * scale:.0f}" role="img" aria-label="{escape(title)}">' + "".join(body) + "</svg>")
