"""Your own stages: peak memory in log length, 1 vs 2 workers, and the cost of listing installed stages.

Runs docs/STAGES.md's example stage (``flux_fwhm``: flux and FWHM of every star in every frame,
from the image) as a user would, through ``starlog run --config``, and prints:

1. peak resident memory on a log and on one 10x longer (target: flat within 10 %);
2. seconds with ``--workers 1`` and ``--workers 2``, and whether the outputs are identical;
3. ``starlog --help`` with no installed stage and with one registered (an entry point on the path).

Usage::

    python tools/bench_custom_stage.py            # 300 / 3000 frames
    python tools/bench_custom_stage.py --quick    # 100 / 1000 frames

Run time of --quick on a 2-core machine: about 40 s. Exit status 1 when
a target is missed (peak memory flat within 10 %; the outputs of 1 and 2 workers identical), 0 when
both are met; the seconds of 1 and 2 workers and of ``--help`` are figures, not targets.
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_targets import Targets  # noqa: E402
from starlog.sim import Jitter, SimulationConfig  # noqa: E402
from starlog.stages import simulate_log  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
STARLOG = str(Path(sys.executable).with_name("starlog"))


def _docs_block(language: str, containing: str) -> str:
    text = (ROOT / "docs" / "STAGES.md").read_text(encoding="utf-8")
    return next(b for b in re.findall(rf"```{language}\n(.*?)```", text, flags=re.S) if containing in b)


def _timed(argv: list[str], *, env: dict[str, str] | None = None) -> tuple[float, float]:
    """Wall seconds and peak RSS (MiB, GNU time) of a command."""
    start = time.perf_counter()
    result = subprocess.run(["/usr/bin/time", "-f", "MAXRSS_KB %M", *argv], stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True, env=env)
    elapsed = time.perf_counter() - start
    if result.returncode != 0:
        raise RuntimeError(f"{' '.join(argv)} failed:\n{result.stderr}")
    line = [x for x in result.stderr.splitlines() if x.startswith("MAXRSS_KB")][-1]
    return elapsed, int(line.split()[1]) / 1024


def _example(folder: Path) -> Path:
    """docs/STAGES.md's stage module and config in ``folder``, and a dist-info registering the stage."""
    (folder / "flux_fwhm.py").write_text(_docs_block("python", "@stage("), encoding="utf-8")
    config = folder / "flux_fwhm.toml"
    config.write_text("[stages.flux_fwhm]\nuses = \"flux_fwhm:flux_fwhm\"\nmin_snr = 20\n", encoding="utf-8")
    dist = folder / "flux_fwhm_example-1.0.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: flux-fwhm-example\nVersion: 1.0\n")
    (dist / "entry_points.txt").write_text("[starlog.stages]\nflux_fwhm = flux_fwhm:flux_fwhm\n")
    return config


def _log(path: Path, frames: int) -> None:
    simulate_log(SimulationConfig(width=256, height=256, n_stars=12, n_frames=frames, seed=1,
                                  jitter=(Jitter(frequency_hz=25.0, amplitude_px=0.05),)), path, workers=2)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="100 / 1000 frames (about 40 s)")
    args = parser.parse_args()
    frames = 100 if args.quick else 300
    print(f"# starlog bench_custom_stage (cores: {os.cpu_count()}, load: {os.getloadavg()[0]:.2f})")
    targets = Targets()
    with tempfile.TemporaryDirectory(dir=os.environ.get("BENCH_TMP")) as d:
        tmp = Path(d)
        config = _example(tmp)
        peaks, seconds = {}, {}
        for scale in (1, 10):
            _log(tmp / f"sim{scale}.mcap", frames * scale)
            _, peaks[scale] = _timed([STARLOG, "run", str(tmp / f"sim{scale}.mcap"), "-o", str(tmp / f"out{scale}.mcap"),
                                      "--config", str(config), "--workers", "1", "-q"])
        print(f"\n## peak memory, {frames} vs {10 * frames} frames (256x256, 12 stars)\n")
        growth = peaks[10] / peaks[1] - 1
        print(f"peak MiB 1x {peaks[1]:.1f}, 10x {peaks[10]:.1f}, growth {100 * growth:+.1f} %"
              "  (target: flat within 10 %)")
        targets.check(f"peak memory, {frames} -> {10 * frames} frames: {100 * growth:+.1f} % <= 10 %", growth <= 0.10)
        log = tmp / "sim10.mcap"
        for workers in (1, 2):
            seconds[workers], _ = _timed([STARLOG, "run", str(log), "-o", str(tmp / f"w{workers}.mcap"), "--config",
                                          str(config), "--workers", str(workers), "-q"])
        same = (tmp / "w1.mcap").read_bytes() == (tmp / "w2.mcap").read_bytes()
        print(f"\n## {10 * frames} frames, workers 1 vs 2\n")
        print(f"{'workers':>8} {'seconds':>9} {'frames/s':>9}")
        for workers, s in seconds.items():
            print(f"{workers:>8} {s:>9.2f} {10 * frames / s:>9.1f}")
        print(f"speed-up {seconds[1] / seconds[2]:.2f}x; outputs identical: {same}")
        targets.check(f"outputs of --workers 1 and 2 identical ({same})", same)
        print("\n## starlog --help (best of 5)\n")
        for label, env in (("no installed stage", None), ("one installed stage", {**os.environ, "PYTHONPATH": d})):
            best = min(_timed([STARLOG, "--help"], env=env)[0] for _ in range(5))
            print(f"{label:<22} {best:.3f} s")
    return targets.report()


if __name__ == "__main__":
    sys.exit(main())
