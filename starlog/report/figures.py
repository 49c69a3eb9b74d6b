"""How the experiment's figures are written: matplotlib, saved as a PNG file or inlined in an HTML report as SVG.

``starlog experiment`` writes its figures as PNG files that users keep and docs/RESULTS.md shows,
and its HTML report shows Figure 5: matplotlib writes both PNG and SVG from one drawing.
:func:`save_png` writes a file, :func:`inline_svg` gives an ``<svg>`` element for an HTML report
that needs nothing at view time (no script, text drawn with the viewer's own fonts, images as
``data:`` URIs, ids fixed so the same data gives the same bytes). The figures themselves are in
:mod:`starlog.report.experiment_figures`. matplotlib is imported when a figure is drawn, so
importing the report stays light.
"""

from __future__ import annotations

import io
import re
from html import escape
from pathlib import Path
from typing import TYPE_CHECKING

from starlog.errors import StarlogError

if TYPE_CHECKING:
    from matplotlib.figure import Figure

__all__ = ["PlotDependencyError", "inline_svg", "new_figure", "save_png"]

#: Resolution of the PNG files, dots per inch.
PNG_DPI = 64

#: SVG settings: text as text (no glyph outlines), ids from a fixed salt (same figure, same bytes),
#: no metadata block (it names web addresses) and no creation date.
_SVG_RC = {"svg.fonttype": "none", "svg.hashsalt": "starlog"}
_SVG_METADATA = {"Creator": None, "Date": None, "Format": None, "Type": None}
#: Digits of path coordinates past the second decimal (0.01 px): dropped, which halves a long line's size.
_TRAILING_DIGITS = re.compile(r"(\.\d\d)\d+")


class PlotDependencyError(StarlogError, ImportError):
    """matplotlib is missing (a starlog dependency: reinstall starlog)."""


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
    path = Path(path)
    figure.savefig(path, dpi=dpi)
    return path


def inline_svg(figure: Figure, *, label: str) -> str:
    """``figure`` as one ``<svg>`` element to put in an HTML page, sized in CSS pixels (1 pt = 1 px)."""
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
    return svg.strip()
