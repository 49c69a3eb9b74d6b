"""Leave-one-camera-out: how ``tools/bench_realsky.py`` chooses and checks a default on cameras it was not chosen on.

A *camera* is a folder of frames of the real sky that ``bench_realsky``'s protocol scores against the catalogue:
the real frames (``--images``), their degraded copies (``--degraded``), the simulator's cameras
(``--simulated``: :mod:`sim_cameras`) and any folder given with ``--camera NAME=DIR``. Each camera's score of a
starlog method is its pooled RMSE on the common stars over the best SEP setting's (the benchmark's ratio).

Two questions, each answered on every camera in turn, never on the camera scored:

* **the default method** (what ``starlog`` uses where no evidence names one): picked on the *other* cameras, the
  (setting, method) of least mean log-ratio over them, then scored on the held-out camera. A *setting* is one
  run of the benchmark: this code with its options, or an earlier run given with ``--loco-with RUN.json``
  (another version of the code, other options), so that a changed default is checked the same way;
* **the trusted method**: the method ``starlog``'s rule names from the camera's own frames
  (:func:`starlog.centroiding.evidence.trust` on :func:`starlog.attitude.sky_evidence.sky_evidence` of the
  benchmark's identified stars, one camera model per log), which needs no other camera. It is checked against
  the benchmark's own figure: it is the best starlog method on the common stars, or the 95 % bootstrap interval
  of its ratio to the best one (over the common stars) reaches 1.

The table prints one row per held-out camera; ``--json`` saves every camera's figures so that later runs can
compare settings (``--loco-with``).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from starlog.attitude.sky_evidence import IdentifiedFrame, sky_evidence
from starlog.centroiding.evidence import trust

__all__ = ["CameraScore", "held_out_rows", "load_scores", "print_loco", "score_camera", "trust_check"]


@dataclass(frozen=True)
class CameraScore:
    """One camera under one setting: each starlog method's pooled RMSE over the best SEP setting's (``ratios``),
    the best SEP setting, the common stars, and the trusted method with its check (:func:`trust_check`)."""

    camera: str
    setting: str
    ratios: dict[str, float]
    best_sep: str
    common: int
    trusted: str | None
    trusted_ok: bool
    trusted_interval: tuple[float, float]
    reason: str

    def to_dict(self) -> dict[str, Any]:
        return {"camera": self.camera, "setting": self.setting, "ratios": self.ratios, "best_sep": self.best_sep,
                "common": self.common, "trusted": self.trusted, "trusted_ok": self.trusted_ok,
                "trusted_interval": list(self.trusted_interval), "reason": self.reason}

    @classmethod
    def from_dict(cls, d: dict[str, Any], setting: str | None = None) -> CameraScore:
        return cls(d["camera"], setting or d["setting"], d["ratios"], d["best_sep"], d["common"], d["trusted"],
                   d["trusted_ok"], tuple(d["trusted_interval"]), d["reason"])  # type: ignore[arg-type]


def identified_frames(results: list[Any], names: list[str]) -> dict[str, list[IdentifiedFrame]]:
    """Each starlog method's identified stars per solved frame of a benchmark run (its catalogue matches of the
    field's isolated stars, under the frame's refined camera)."""
    out: dict[str, list[IdentifiedFrame]] = {n: [] for n in names}
    for k, r in enumerate(results):
        if r.comparison is None or r.camera is None:
            continue
        for n in names:
            rows, x, y = r.comparison.identified[n]
            out[n].append(IdentifiedFrame(k, r.camera, rows, x, y))
    return out


def trust_check(results: list[Any], names: list[str], catalogue: np.ndarray, pooled: dict[str, float],
                draws: int = 2000, seed: int = 1) -> tuple[str | None, bool, tuple[float, float], str]:
    """The method starlog's rule trusts on these frames, whether the benchmark agrees (the best on the common
    stars, or the 95 % bootstrap interval of its ratio to the best reaches 1), that interval, and the rule's
    reason."""
    decision = trust(None, sky_evidence(identified_frames(results, names), catalogue[:, 2:5], catalogue[:, 5]),
                     sky_missing="no frame solved")
    method = decision["method"]
    if method is None:
        return None, False, (math.nan, math.nan), decision["reason"]
    best = min(names, key=lambda n: pooled[n])
    done = [r.comparison for r in results if r.comparison is not None and r.comparison.common.size]
    a = np.concatenate([(c.residuals[method] ** 2).sum(axis=1) for c in done])
    b = np.concatenate([(c.residuals[best] ** 2).sum(axis=1) for c in done])
    pick = np.random.default_rng(seed).integers(0, a.size, (draws, a.size))
    lo, hi = np.percentile(np.sqrt(a[pick].sum(axis=1) / b[pick].sum(axis=1)), [2.5, 97.5])
    return method, bool(method == best or lo <= 1.0), (float(lo), float(hi)), decision["reason"]


def score_camera(camera: str, setting: str, run: Any, catalogue: np.ndarray) -> CameraScore:
    """A benchmark run's (``bench_realsky.BenchRun``) figures as one camera's :class:`CameraScore`; ``catalogue``:
    the solver's star table (columns 2:5 unit vectors, 5 magnitude)."""
    ours = [n for n in run.names if not n.startswith("SEP")]
    sep = run.pooled[run.best_sep]
    common = sum(r.comparison.common.size for r in run.results if r.comparison is not None)
    trusted, ok, interval, reason = trust_check(run.results, ours, catalogue, run.pooled)
    return CameraScore(camera, setting, {n: run.pooled[n] / sep for n in ours}, run.best_sep, int(common), trusted,
                       ok, interval, reason)


def load_scores(paths: list[Path]) -> list[CameraScore]:
    """Camera scores saved by earlier runs (``--json``), each file's setting named after the file."""
    out = []
    for path in paths:
        for d in json.loads(path.read_text())["cameras"]:
            out.append(CameraScore.from_dict(d, setting=path.stem))
    return out


def _mean_log(scores: list[CameraScore], setting: str, method: str) -> float:
    values = [s.ratios.get(method, math.nan) for s in scores if s.setting == setting]
    values = [v for v in values if math.isfinite(v) and v > 0]
    return float(np.mean(np.log(values))) if values else math.inf


def held_out_rows(scores: list[CameraScore], current: str) -> list[dict[str, Any]]:
    """Per camera (of the ``current`` setting): the (setting, method) of least mean log-ratio over the other
    cameras, its ratio on this camera, and the trusted method's ratio and check under ``current``."""
    cameras = [s.camera for s in scores if s.setting == current]
    settings = sorted({s.setting for s in scores})
    rows = []
    for camera in cameras:
        others = [s for s in scores if s.camera != camera and s.camera in cameras]
        here = {s.setting: s for s in scores if s.camera == camera}
        candidates = [(st, m) for st in settings if st in here for m in here[st].ratios]
        setting, method = min(candidates, key=lambda c: (_mean_log(others, *c), c))
        mine = here[current]
        rows.append({"camera": camera, "common": mine.common, "picked": f"{setting}/{method}" if len(settings) > 1
                     else method, "held_out": here[setting].ratios[method],
                     "best": min(mine.ratios, key=mine.ratios.get), "best_ratio": min(mine.ratios.values()),
                     "trusted": mine.trusted, "trusted_ratio": mine.ratios.get(mine.trusted or "", math.nan),
                     "trusted_ok": mine.trusted_ok, "interval": mine.trusted_interval, "best_sep": mine.best_sep})
    return rows


def print_loco(scores: list[CameraScore], current: str) -> list[dict[str, Any]]:
    """The held-out table (:func:`held_out_rows`) and its summary lines."""
    rows = held_out_rows(scores, current)
    settings = sorted({s.setting for s in scores})
    print(f"\nleave-one-camera-out: ratio = starlog's pooled RMSE / the best SEP setting's on each camera's common "
          f"stars; settings: {', '.join(settings)}")
    print(f"{'camera':<26}{'common':>7}  {'picked on the others':<28}{'held out':>9}  {'trusted':<12}{'ratio':>7}"
          f"  {'trusted/best 95 %':<18}{'ok':<4}{'best here':<18}{'best SEP':<16}")
    for r in rows:
        lo, hi = r["interval"]
        print(f"{r['camera']:<26}{r['common']:>7}  {r['picked']:<28}{r['held_out']:>9.3f}  {str(r['trusted']):<12}"
              f"{r['trusted_ratio']:>7.3f}  {lo:.3f}-{hi:.3f}{'':<7}{'yes' if r['trusted_ok'] else 'NO':<4}"
              f"{r['best']} {r['best_ratio']:.3f}{'':<4}{r['best_sep']:<16}")
    held = [r["held_out"] for r in rows]
    trusted = [r["trusted_ratio"] for r in rows if math.isfinite(r["trusted_ratio"])]
    print(f"held-out default: worst {max(held):.3f}, geometric mean {math.exp(np.mean(np.log(held))):.3f}; trusted "
          f"method: worst {max(trusted, default=math.nan):.3f}, geometric mean "
          f"{math.exp(np.mean(np.log(trusted))) if trusted else math.nan:.3f}; the benchmark agrees with the trusted "
          f"method on {sum(r['trusted_ok'] for r in rows)}/{len(rows)} cameras")
    return rows
