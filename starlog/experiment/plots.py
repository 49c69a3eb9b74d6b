"""PNG plots of the experiment (matplotlib, Agg backend, imported lazily).

* :func:`plot_figure4` — bar chart of RMSE before/after per sub-pixel method and rate (STATIC,
  300 Hz dataset), one panel per protocol's primary reference (the paper's Figure 4 analogue);
* :func:`plot_figure5` — RMSE before/after vs 10–100 Hz for every model, both datasets, one
  column per protocol's primary reference plus ``truth_series`` (Figure 5 analogue);
* :func:`plot_trajectory` — the brightest star's x(t), y(t) before and after compensation, with
  the true jittered position and the global mean;
* :func:`plot_regime_map` — compensation gain against the jitter / noise ratio, ``keep`` and
  ``separate`` for each star count, one panel per reference and rate.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from starlog.errors import StarlogError
from starlog.experiment.runner import FIGURE5_RATES, METHODS, MODELS, TABLE3_RATES

__all__ = ["PlotDependencyError", "plot_figure4", "plot_figure5", "plot_regime_map", "plot_trajectory"]

_PRIMARY = (("paper", "global_mean"), ("truth", "truth_fixed"), ("leakfree", "heldout_mean"))
_DPI = 64
_FIG5_PANELS = (*_PRIMARY, ("truth", "truth_series"))


class PlotDependencyError(StarlogError, ImportError):
    """matplotlib is missing (install the ``plot`` extra)."""


def _pyplot() -> Any:
    try:
        import matplotlib
    except ImportError as err:  # pragma: no cover - depends on the environment
        raise PlotDependencyError(
            "the experiment's plots need matplotlib (a starlog dependency): pip install matplotlib.") from err
    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def _lookup(rows: Sequence[dict[str, Any]]) -> dict[tuple[Any, ...], dict[str, Any]]:
    return {(r["protocol"], r["reference"], r["dataset"], r["method"], r["model"], r["rate_hz"]): r for r in rows}


def plot_figure4(rows: Sequence[dict[str, Any]], path: str | Path, *, dataset: str = "300Hz",
                 model: str = "STATIC", label: str = "") -> Path:
    """Bar chart: RMSE before/after per sub-pixel method × rate (``model``), per protocol. ``rows``: table3 rows."""
    plt = _pyplot()
    idx = _lookup(rows)
    fig, axes = plt.subplots(len(_PRIMARY), 1, figsize=(9, 7.5), sharex=True)
    width = 0.4
    for ax, (protocol, reference) in zip(axes, _PRIMARY):
        labels, before, after = [], [], []
        for method in METHODS:
            for rate in TABLE3_RATES:
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
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=_DPI)
    plt.close(fig)
    return path


def plot_figure5(rows: Sequence[dict[str, Any]], path: str | Path) -> Path:
    """RMSE before (dashed) / after (solid) vs rate, every model; rows = datasets, columns = protocols."""
    plt = _pyplot()
    idx = _lookup(rows)
    datasets = [d for d in ("300Hz", "200Hz") if any(r["dataset"] == d for r in rows)]
    fig, axes = plt.subplots(len(datasets), len(_FIG5_PANELS), figsize=(13, 3.0 * len(datasets)), squeeze=False)
    colors = ["#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e"]
    for i, ds in enumerate(datasets):
        for j, (protocol, reference) in enumerate(_FIG5_PANELS):
            ax = axes[i][j]
            for model, color in zip(MODELS, colors):
                pts = [(rate, idx.get((protocol, reference, ds, "NONE", model, rate))) for rate in FIGURE5_RATES]
                pts = [(rate, r) for rate, r in pts if r is not None]
                if not pts:
                    continue
                xs = [p[0] for p in pts]
                ax.plot(xs, [p[1]["rmse_before"] for p in pts], "--", color=color, lw=1)
                ax.plot(xs, [p[1]["rmse_after"] for p in pts], "-o", color=color, lw=1.3, ms=3, label=model)
            ax.set_title(f"{ds} — {protocol} / {reference}", fontsize=9)
            ax.set_xlabel("down-sample rate (Hz)")
            ax.set_ylabel("RMSE (px)")
            ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=7, title="solid: after, dashed: before", title_fontsize=7)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=_DPI)
    plt.close(fig)
    return path


def plot_trajectory(series: dict[str, Any], path: str | Path, *, title: str) -> Path:
    """x(t), y(t) of one decimated series before/after compensation (paper and leak-free), with the truth."""
    plt = _pyplot()
    t = series["t_s"]
    before = series["before"]
    fig, axes = plt.subplots(2, 1, figsize=(9, 5.5), sharex=True)
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
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=_DPI)
    plt.close(fig)
    return path


def plot_regime_map(rows: Sequence[dict[str, Any]], gains: dict[tuple[Any, ...], float],
                    figures: Sequence[tuple[str, str]], rates: Sequence[float], path: str | Path) -> Path:
    """Median gain over the UKF models vs jitter/noise; rows of panels = references, columns = rates.

    ``gains`` maps (protocol, reference, rate, motion, stars, jitter ratio) to the median gain
    (:func:`starlog.experiment.regime.median_gains`); ``figures`` are the (protocol, reference) rows.
    """
    plt = _pyplot()
    ratios = sorted({r["jitter_ratio"] for r in rows})
    stars = sorted({r["stars"] for r in rows})
    fig, axes = plt.subplots(len(figures), len(rates), figsize=(10, 11), sharex=True, squeeze=False)
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
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=_DPI)
    plt.close(fig)
    return path
