"""How every report figure is drawn: matplotlib, saved as a PNG file or inlined in an HTML report as SVG.

``starlog experiment`` writes its figures as PNG files that users keep and docs/RESULTS.md shows;
a hand-written SVG cannot give those, while matplotlib writes both PNG and SVG from one drawing.
So matplotlib draws every figure: :func:`save_png` writes a file, :func:`inline_svg` gives an
``<svg>`` element for an HTML report that needs nothing at view time (no script, text drawn with
the viewer's own fonts, images as ``data:`` URIs, ids fixed so the same data gives the same bytes).

:func:`line_chart`, :func:`bar_chart` and :func:`frame_figure` are the log report's figures; long
series are reduced to a bounded number of points (:func:`envelope`) so a figure's size does not grow
with the log's length. The experiment's figures are in :mod:`starlog.report.experiment_figures`.
matplotlib is imported when a figure is drawn, so importing the report stays light.
"""

from __future__ import annotations

import io
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from html import escape
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from starlog.errors import StarlogError

if TYPE_CHECKING:
    from matplotlib.figure import Figure

__all__ = ["PALETTE", "Bars", "PlotDependencyError", "Series", "bar_chart", "envelope", "frame_figure",
           "inline_svg", "line_chart", "new_figure", "save_png"]

#: Colour-blind-safe line colours (Okabe-Ito), repeated for more series.
PALETTE = ("#0072B2", "#D55E00", "#009E73", "#CC79A7", "#E69F00", "#56B4E9", "#000000", "#F0E442")
#: Resolution of the PNG files, dots per inch.
PNG_DPI = 64

_W, _H = 720, 280
_LEFT, _RIGHT, _TOP, _BOTTOM = 64, 16, 46, 40  # the plot's margins, px: the title and the legend above it
_MAX_POINTS = 1200
#: SVG settings: text as text (no glyph outlines), ids from a fixed salt (same figure, same bytes),
#: no metadata block (it names web addresses) and no creation date.
_SVG_RC = {"svg.fonttype": "none", "svg.hashsalt": "starlog"}
_SVG_METADATA = {"Creator": None, "Date": None, "Format": None, "Type": None}
#: Digits of path coordinates past the second decimal (0.01 px): dropped, which halves a long line's size.
_TRAILING_DIGITS = re.compile(r"(\.\d\d)\d+")


class PlotDependencyError(StarlogError, ImportError):
    """matplotlib is missing (a starlog dependency: reinstall starlog)."""


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


# ---------------------------------------------------------------- figures and their outputs
def new_figure(width_in: float, height_in: float) -> Figure:
    """An empty matplotlib figure of that size (inches), outside pyplot: no global state, no window."""
    try:
        from matplotlib.figure import Figure
    except ImportError as err:  # pragma: no cover - depends on the environment
        raise PlotDependencyError("the report's figures need matplotlib (a starlog dependency): "
                                  "pip install matplotlib.") from err
    return Figure(figsize=(width_in, height_in))


def save_png(figure: Figure, path: str | Path, *, dpi: int = PNG_DPI) -> Path:
    """Write ``figure`` as a PNG file; returns its path."""
    from starlog.io.output_files import atomic_output

    path = Path(path)
    with atomic_output(path) as tmp:
        figure.savefig(tmp, dpi=dpi, format="png")
    return path


def inline_svg(figure: Figure, *, label: str, titles: Mapping[str, str] | None = None) -> str:
    """``figure`` as one ``<svg>`` element to put in an HTML page, sized in CSS pixels (1 pt = 1 px).

    ``titles`` maps an artist's ``gid`` to the tooltip shown over it (a ``<title>`` element).
    """
    import matplotlib

    buffer = io.StringIO()
    with matplotlib.rc_context(_SVG_RC):
        figure.savefig(buffer, format="svg", metadata=_SVG_METADATA)
    svg = buffer.getvalue()
    svg = svg[svg.index("<svg"):].replace(' xmlns:xlink="http://www.w3.org/1999/xlink"', "")
    svg = svg.replace("xlink:href=", "href=")
    svg = re.sub(r'(<svg [^>]*?)width="([\d.]+)pt" height="([\d.]+)pt"',
                 lambda m: f'{m[1]}width="{m[2]}" height="{m[3]}" role="img" aria-label="{escape(label)}"', svg, count=1)
    svg = re.sub(r' d="([^"]*)"', lambda m: ' d="' + _TRAILING_DIGITS.sub(r"\1", m.group(1)) + '"', svg)
    for gid, text in (titles or {}).items():
        svg = svg.replace(f'<g id="{gid}">', f'<g id="{gid}"><title>{escape(text)}</title>', 1)
    return svg.strip()


# ---------------------------------------------------------------- the log report's figures
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


def _chart(width: int, height: int, title: str, x_label: str, y_label: str) -> tuple[Figure, Any]:
    """A figure of ``width`` × ``height`` px with one plot in fixed margins: title, axis labels, light grid."""
    figure = new_figure(width / 72, height / 72)
    figure.subplots_adjust(left=_LEFT / width, right=1 - _RIGHT / width, top=1 - _TOP / height,
                           bottom=_BOTTOM / height)
    axes = figure.subplots()
    figure.text(_LEFT / width, 1 - 6 / height, title, ha="left", va="top", fontsize=10, fontweight="bold")
    axes.set_xlabel(x_label, fontsize=9)
    axes.set_ylabel(y_label, fontsize=9)
    axes.tick_params(labelsize=8)
    axes.grid(color="#e4e4e4", linewidth=0.8)
    axes.set_axisbelow(True)
    return figure, axes


def _legend_above(axes: Any, entries: int) -> None:
    """One row of keys between the title and the plot: it never hides a line."""
    axes.legend(fontsize=8, ncol=entries, loc="lower left", bbox_to_anchor=(0.0, 1.0), frameon=False,
                borderaxespad=0.1, borderpad=0.1, handlelength=1.5, columnspacing=1.2)


def _robust_limits(values: npt.NDArray[np.float64]) -> tuple[float, float] | None:
    """The 1st-99th percentile of ``values``, widened by 15 % on each side (None when there are none)."""
    finite = values[np.isfinite(values)]
    if not finite.size:
        return None
    lo, hi = np.percentile(finite, [1.0, 99.0])
    pad = 0.15 * (hi - lo) or abs(lo) * 0.1 or 1.0
    return float(lo - pad), float(hi + pad)


def line_chart(series: Sequence[Series], *, title: str, x_label: str, y_label: str,
               markers: Sequence[tuple[float, str]] = (), legend: bool = True, robust: bool = False,
               width: int = _W, height: int = _H) -> str:
    """Lines on shared axes, as inline SVG; ``markers`` are labelled vertical lines at given x (e.g. a frequency).

    ``robust``: the y range spans the 1st-99th percentile of the points (a start-up transient does
    not flatten the rest); lines are clipped to the plot.
    """
    figure, axes = _chart(width, height, title, x_label, y_label)
    shown = []
    for k, s in enumerate(series):
        x, y = envelope(s.x, s.y)
        ok = np.isfinite(x) & np.isfinite(y)
        shown.append(y[ok])
        axes.plot(x[ok], y[ok], color=s.color or PALETTE[k % len(PALETTE)], linewidth=s.width, label=s.label,
                  marker="o" if ok.sum() == 1 else None, markersize=3)
    axes.margins(x=0)
    limits = _robust_limits(np.concatenate(shown)) if robust and shown else None
    if limits is not None:
        axes.set_ylim(*limits)
    for value, label in markers:
        axes.axvline(value, color="#cc0000", linestyle=(0, (4, 3)), linewidth=1.5)
        right = axes.get_xlim()[0] + 0.7 * (axes.get_xlim()[1] - axes.get_xlim()[0]) < value
        axes.text(value, 0.97, f" {label} ", transform=axes.get_xaxis_transform(), color="#cc0000", fontsize=8,
                  ha="right" if right else "left", va="top")
    if legend and len(series) > 1:
        _legend_above(axes, len(series))
    return inline_svg(figure, label=title)


def bar_chart(groups: Sequence[str], bars: Sequence[Bars], *, title: str, y_label: str,
              width: int = _W, height: int = _H) -> str:
    """Grouped vertical bars, as inline SVG: one group per label of ``groups``, one bar per :class:`Bars`.

    Each bar's value is its tooltip.
    """
    figure, axes = _chart(width, height, title, "", y_label)
    bar_width = 0.8 / max(len(bars), 1)
    titles = {}
    for b, series in enumerate(bars):
        values = np.asarray([float(v) for v in series.values], float)
        x = np.arange(len(groups)) - 0.4 + (b + 0.5) * bar_width
        drawn = axes.bar(x, np.where(np.isfinite(values), values, 0.0), bar_width * 0.92, label=series.label,
                         color=series.color or PALETTE[b % len(PALETTE)])
        for g, (patch, value) in enumerate(zip(drawn.patches, values, strict=True)):
            patch.set_gid(f"bar-{b}-{g}")
            titles[f"bar-{b}-{g}"] = f"{groups[g]} {series.label}: {value:.4g}"
    axes.set_xticks(range(len(groups)), list(groups), fontsize=8)
    axes.grid(axis="x", visible=False)
    if len(bars) > 1:
        _legend_above(axes, len(bars))
    return inline_svg(figure, label=title, titles=titles)


def _stretch(image: npt.NDArray[np.generic], max_side: int) -> npt.NDArray[np.uint8]:
    """8-bit view of a frame: percentile contrast stretch (1 %-99.7 %), square root, downscaled to ``max_side``."""
    import cv2

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
    """A frame (contrast-stretched) with a circle at each ``(x, y, label)``, as inline SVG.

    Coordinates are pixels with (0, 0) at the centre of the top-left pixel; the circles are drawn
    in the frame's own pixels, so they stay exact when the picture is downscaled. Each circle's
    label is its tooltip (its ``gid``: ``centroid-K``).
    """
    from matplotlib.patches import Circle

    h, w = image.shape[:2]
    scale = display / max(w, h)
    figure = new_figure(w * scale / 72, h * scale / 72)
    axes = figure.add_axes((0.0, 0.0, 1.0, 1.0))
    axes.set_axis_off()
    axes.imshow(_stretch(image, max_side), cmap="gray", vmin=0, vmax=255, extent=(-0.5, w - 0.5, h - 0.5, -0.5),
                interpolation="none")
    radius = max(w, h) / 40
    titles = {}
    for k, (x, y, label) in enumerate(points):
        circle = Circle((x, y), radius, fill=False, edgecolor="#ff3b30", linewidth=radius / 8 * scale)
        circle.set_gid(f"centroid-{k}")
        axes.add_patch(circle)
        titles[f"centroid-{k}"] = label
    return inline_svg(figure, label=title, titles=titles)
