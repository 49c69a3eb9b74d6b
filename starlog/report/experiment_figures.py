"""The experiment's figures, drawn from the rows ``starlog experiment`` hands them (:mod:`starlog.report.figures`).

* :func:`plot_figure4` — bar chart of RMSE before/after per sub-pixel method and rate (STATIC,
  300 Hz dataset), one panel per protocol's primary reference (the paper's Figure 4 analogue);
* :func:`plot_figure5` — RMSE before/after vs 10–100 Hz for every model, both datasets, one
  column per protocol's primary reference plus ``truth_series`` (Figure 5 analogue);
  :func:`figure5_panel_svg` draws one of its panels for the HTML report;
* :func:`plot_trajectory` — the brightest star's x(t), y(t) before and after compensation, with
  the true jittered position and the global mean;
* :func:`plot_regime_map` — compensation gain against the jitter / noise ratio, ``keep`` and
  ``separate`` for each star count, one panel per reference and rate.

Methods, models, datasets and rates are shown in the order the rows list them (the experiment
sorts its rows in its canonical order), so the figures need nothing of :mod:`starlog.experiment`.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from starlog.report.figures import inline_svg, new_figure, save_png

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

__all__ = ["FIGURE5_PANELS", "figure5_panel_svg", "plot_figure4", "plot_figure5", "plot_regime_map",
           "plot_trajectory"]

_PRIMARY = (("paper", "global_mean"), ("truth", "truth_fixed"), ("leakfree", "heldout_mean"))
#: Figure 5's panels: each protocol's primary reference, and the instantaneous truth.
FIGURE5_PANELS = (*_PRIMARY, ("truth", "truth_series"))
_MODEL_COLORS = ("#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e")


def _lookup(rows: Sequence[dict[str, Any]]) -> dict[tuple[Any, ...], dict[str, Any]]:
    return {(r["protocol"], r["reference"], r["dataset"], r["method"], r["model"], r["rate_hz"]): r for r in rows}


def _in_order(rows: Sequence[dict[str, Any]], key: str) -> list[Any]:
    """The values of ``key`` in the order the rows first list them."""
    return list(dict.fromkeys(r[key] for r in rows))


def plot_figure4(rows: Sequence[dict[str, Any]], path: str | Path, *, dataset: str = "300Hz",
                 model: str = "STATIC", label: str = "") -> Path:
    """Bar chart: RMSE before/after per sub-pixel method × rate (``model``), per protocol. ``rows``: table3 rows."""
    return save_png(_figure4(rows, dataset=dataset, model=model, label=label), path)


def _figure4(rows: Sequence[dict[str, Any]], *, dataset: str, model: str, label: str) -> Figure:
    idx = _lookup(rows)
    methods, rates = _in_order(rows, "method"), sorted(set(_in_order(rows, "rate_hz")))
    figure = new_figure(9, 7.5)
    axes = figure.subplots(len(_PRIMARY), 1, sharex=True)
    width = 0.4
    for ax, (protocol, reference) in zip(axes, _PRIMARY):
        labels, before, after = [], [], []
        for method in methods:
            for rate in rates:
                r = idx.get((protocol, reference, dataset, method, model, rate))
                if r is None:
                    continue
                labels.append(f"{method}\n{rate:g}")
                before.append(r["rmse_before"])
                after.append(r["rmse_after"] if r["rmse_after"] is not None else float("nan"))
        x = list(range(len(labels)))
        ax.bar([i - width / 2 for i in x], before, width, label="before", color="#9aa5b1")
        ax.bar([i + width / 2 for i in x], after, width, label="after", color="#2f6db5")
        ax.set_ylabel("RMSE (px)")
        ax.set_title(f"{label + ', ' if label else ''}{dataset}, {model} UKF — protocol {protocol}, "
                     f"reference {reference}", fontsize=9)
        ax.grid(axis="y", alpha=0.3)
        ax.set_xticks(x)
        ax.set_xticklabels(labels, fontsize=6)
    axes[0].legend(fontsize=8)
    axes[-1].set_xlabel("sub-pixel method / down-sample rate (Hz)")
    figure.tight_layout()
    return figure


def _figure5_panel(ax: Axes, rows: Sequence[dict[str, Any]], models: Sequence[str], dataset: str, protocol: str,
                   reference: str) -> None:
    """One panel of Figure 5: RMSE before (dashed) / after (solid) against the rate, one colour per model."""
    idx = _lookup(rows)
    rates = sorted(set(_in_order(rows, "rate_hz")))
    for model, color in zip(models, _MODEL_COLORS):
        pts = [(rate, idx.get((protocol, reference, dataset, "NONE", model, rate))) for rate in rates]
        pts = [(rate, r) for rate, r in pts if r is not None]
        if not pts:
            continue
        xs = [p[0] for p in pts]
        ax.plot(xs, [p[1]["rmse_before"] for p in pts], "--", color=color, lw=1)
        ax.plot(xs, [p[1]["rmse_after"] for p in pts], "-o", color=color, lw=1.3, ms=3, label=model)
    ax.set_title(f"{dataset} — {protocol} / {reference}", fontsize=9)
    ax.set_xlabel("down-sample rate (Hz)")
    ax.set_ylabel("RMSE (px)")
    ax.grid(alpha=0.3)


def plot_figure5(rows: Sequence[dict[str, Any]], path: str | Path) -> Path:
    """RMSE before (dashed) / after (solid) vs rate, every model; rows of panels = datasets, columns = protocols."""
    datasets, models = _in_order(rows, "dataset"), _in_order(rows, "model")
    figure = new_figure(13, 3.0 * len(datasets))
    axes = figure.subplots(len(datasets), len(FIGURE5_PANELS), squeeze=False)
    for i, ds in enumerate(datasets):
        for j, (protocol, reference) in enumerate(FIGURE5_PANELS):
            _figure5_panel(axes[i][j], rows, models, ds, protocol, reference)
    axes[0][0].legend(fontsize=7, title="solid: after, dashed: before", title_fontsize=7)
    figure.tight_layout()
    return save_png(figure, path)


def figure5_panel_svg(rows: Sequence[dict[str, Any]], *, dataset: str, protocol: str, reference: str,
                      title: str) -> str:
    """One panel of Figure 5 as inline SVG, with its legend (``rows``: one regime's Figure 5 rows)."""
    figure = new_figure(7.5, 3.6)
    figure.subplots_adjust(left=0.1, right=0.98, top=0.9, bottom=0.14)  # fixed: no layout pass per panel
    ax = figure.subplots()
    _figure5_panel(ax, rows, _in_order(rows, "model"), dataset, protocol, reference)
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=7, title="solid: after, dashed: before", title_fontsize=7)
    return inline_svg(figure, label=title)


def plot_trajectory(series: dict[str, Any], path: str | Path, *, title: str) -> Path:
    """x(t), y(t) of one decimated series before/after compensation (paper and leak-free), with the truth."""
    t = series["t_s"]
    before = series["before"]
    figure = new_figure(9, 5.5)
    axes = figure.subplots(2, 1, sharex=True)
    for k, (ax, axis) in enumerate(zip(axes, ("x", "y"))):
        if series.get("truth_series") is not None:
            ax.plot(t, [p[k] for p in series["truth_series"]], color="#444444", lw=1, label="true (jittered)")
        if series.get("truth_fixed") is not None:
            ax.axhline(series["truth_fixed"][k], color="#444444", ls=":", lw=1, label="true (fixed)")
        mean = sum(p[k] for p in before) / len(before)
        ax.axhline(mean, color="#bbbbbb", ls="--", lw=1, label="global mean (paper's truth)")
        ax.plot(t, [p[k] for p in before], ".", color="#9aa5b1", ms=3, label="before (UKF track)")
        for protocol, color in (("paper", "#2f6db5"), ("leakfree", "#d62728")):
            after = series["after"].get(protocol)
            if after is None:
                continue
            start = series["scored_start"].get(protocol, 0)
            ax.plot(t[start:], [p[k] for p in after[start:]], "-", color=color, lw=1,
                    label=f"after ({protocol}{', scored part' if start else ''})")
        ax.set_ylabel(f"{axis} (px)")
        ax.grid(alpha=0.3)
    axes[0].set_title(title, fontsize=9)
    axes[0].legend(fontsize=7, ncol=3)
    axes[-1].set_xlabel("time (s)")
    figure.tight_layout()
    return save_png(figure, path)


def plot_regime_map(rows: Sequence[dict[str, Any]], gains: dict[tuple[Any, ...], float],
                    figures: Sequence[tuple[str, str]], rates: Sequence[float], path: str | Path) -> Path:
    """Median gain over the UKF models vs jitter/noise; rows of panels = references, columns = rates.

    ``gains`` maps (protocol, reference, rate, motion, stars, jitter ratio) to the median gain
    (:func:`starlog.experiment.regime.median_gains`); ``figures`` are the (protocol, reference) rows.
    """
    ratios = sorted({r["jitter_ratio"] for r in rows})
    stars = sorted({r["stars"] for r in rows})
    figure = new_figure(10, 11)
    axes = figure.subplots(len(figures), len(rates), sharex=True, squeeze=False)
    colors = {"keep": "#2f6db5", "separate": "#d62728"}
    styles = ["-", "--", ":", "-."]
    x = [max(v, 0.2) for v in ratios]  # log axis: jitter 0 drawn at 0.2
    for i, (protocol, reference) in enumerate(figures):
        for j, rate in enumerate(rates):
            ax = axes[i][j]
            for motion in ("keep", "separate"):
                for n, style in zip(stars, styles):
                    y = [100 * gains.get((protocol, reference, rate, motion, n, v), float("nan")) for v in ratios]
                    ax.plot(x, y, style, marker="o", ms=3, color=colors[motion], label=f"{motion}, {n} stars")
            ax.axhline(0, color="#444444", lw=0.8)
            ax.set_xscale("log")
            ax.set_ylim(-150, 100)
            ax.set_title(f"{protocol} / {reference}, {rate:g} Hz", fontsize=9)
            ax.set_ylabel("gain (%)")
            ax.grid(alpha=0.3)
    for ax in axes[-1]:
        ax.set_xlabel("platform jitter RMS / centroid noise (0 drawn at 0.2)")
    axes[0][0].legend(fontsize=7, ncol=2)
    figure.tight_layout()
    return save_png(figure, path)
