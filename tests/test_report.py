"""`starlog report`: the HTML report of a log (every section, or what is missing and which stage makes it),
the short summary `run` ends with, and the report rendered in headless Chromium."""

from __future__ import annotations

import json
import re
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from starlog.cli import cli
from starlog.io import LogReader
from starlog.report import collect, collect_report_data, render_report
from starlog.report.log_report import amplitude_spectrum
from starlog.report.figures import envelope
from starlog.sim import Jitter
from starlog.stages import simulate_log
from starlog.stages.centroid import centroid_log
from starlog.stages.track import track_log
from tests.chromium import INSTALL_HINT, Browser, figures_drawn, find_chromium
from tests.helpers import small_config

CONFIG = ('[centroid]\nmethods = ["GAUSSFIT"]\n[track]\nmethods = ["GAUSSFIT"]\nmodels = ["STATIC", "RANDOM_WALK"]\n'
          '[track.tracker]\nsigma_floor = 0.05\n[compensate]\nrates = [25, 50]\nprotocols = "all"\n')
FIGURES = ["frame", "tracks_x", "tracks_y", "error_series", "error_spectrum", "decomposition",
           "compensation", "compensated_paper", "compensated_truth", "compensated_leakfree"]


@pytest.fixture(scope="module")
def logs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A simulated log, its centroids, tracks, and the `run` of all three stages (via the CLI)."""
    d = tmp_path_factory.mktemp("report")
    paths = {name: d / f"{name}.mcap" for name in ("sim", "cen", "trk", "run")}
    simulate_log(small_config(width=96, height=80, n_stars=4, n_frames=160, margin=12.0,
                              jitter=(Jitter(frequency_hz=9.0, amplitude_px=0.05),)), paths["sim"])
    centroid_log(paths["sim"], paths["cen"], methods=["GAUSSFIT"])
    track_log(paths["cen"], paths["trk"], method="GAUSSFIT", models=["STATIC"], tracker={"sigma_floor": 0.05})
    (d / "p.toml").write_text(CONFIG)
    result = CliRunner().invoke(cli, ["run", str(paths["sim"]), "-o", str(paths["run"]), "--config", str(d / "p.toml"),
                                      "--workers", "1"])
    assert result.exit_code == 0, result.output
    (d / "run.stdout").write_text(result.stdout)
    return paths


def _figures(html: str) -> list[str]:
    return re.findall(r'<figure class="fig" data-figure="([^"]+)"', html)


def _missing(html: str) -> list[str]:
    return re.findall(r'<div class="missing">([^<]*)</div>', html)


# ---------------------------------------------------------------- run writes it, and says so in a few lines
def test_run_writes_the_report_and_prints_a_short_summary(logs: dict[str, Path]) -> None:
    report = logs["run"].with_suffix(".html")
    assert report.is_file()
    out = (logs["run"].parent / "run.stdout").read_text().splitlines()
    assert 3 <= len(out) <= 6, out
    assert out[-2] == f"report: {report} (open it in a browser)"
    assert "GAUSSFIT/STATIC at 50 Hz" in out[-3] and "paper" in out[-3] and "truth" in out[-3]
    assert not any("RMSE before" in line for line in out)  # the full table only with --table


def test_run_table_and_json_still_give_every_row(logs: dict[str, Path], tmp_path: Path) -> None:
    config = logs["run"].parent / "p.toml"
    args = ["run", str(logs["sim"]), "--config", str(config), "--workers", "1", "-q"]
    table = CliRunner().invoke(cli, [*args, "-o", str(tmp_path / "t.mcap"), "--table"])
    assert table.exit_code == 0, table.output
    assert table.stdout.count("GAUSSFIT  STATIC") == 6 and "RMSE before" in table.stdout  # 2 rates x 3 protocols
    assert table.stdout.rstrip().endswith("every row: --table (text) or --json")
    as_json = CliRunner().invoke(cli, [*args, "-o", str(tmp_path / "j.mcap"), "--json"])
    data = json.loads(as_json.stdout)
    assert data["report"] == str(tmp_path / "j.html") and len(data["stages"][-1]["records"]) == 12


def test_run_does_not_overwrite_a_report_without_force(logs: dict[str, Path], tmp_path: Path) -> None:
    (tmp_path / "r.html").write_text("mine")
    args = ["run", str(logs["sim"]), "-o", str(tmp_path / "r.mcap"), "--config", str(logs["run"].parent / "p.toml")]
    result = CliRunner().invoke(cli, args)
    assert result.exit_code == 1 and "r.html" in result.output and not (tmp_path / "r.mcap").exists()
    assert (tmp_path / "r.html").read_text() == "mine"


def test_a_batch_run_writes_a_report_beside_each_output(logs: dict[str, Path], tmp_path: Path) -> None:
    config = tmp_path / "c.toml"
    config.write_text('[centroid]\nmethods = ["MOMENT"]\n')
    inputs = [tmp_path / "a.mcap", tmp_path / "b.mcap"]
    for path in inputs:
        path.write_bytes(logs["sim"].read_bytes())
    result = CliRunner().invoke(cli, ["run", *map(str, inputs), "-o", str(tmp_path / "out"), "--config", str(config),
                                      "--workers", "1", "-q"])
    assert result.exit_code == 0, result.output
    for name in ("a", "b"):
        report = tmp_path / "out" / f"{name}.html"
        assert f"; report {report}" in result.stdout
        assert _figures(report.read_text(encoding="utf-8")) == ["frame"]


# ---------------------------------------------------------------- the report of a full run
def test_report_of_a_run_has_every_section_and_figure(logs: dict[str, Path]) -> None:
    html = logs["run"].with_suffix(".html").read_text(encoding="utf-8")
    assert _figures(html) == FIGURES and _missing(html) == []
    with LogReader(logs["run"]) as log:
        records = [m.payload for m in log.messages("/compensated/GAUSSFIT/STATIC/decisions")]
        stages = [p.stage for p in log.provenance()]
    shown = max(records, key=lambda r: (r["protocol"] == "paper", r["rate_hz"]))
    f_d = shown["compensation"]["decomposition"]["dominant_frequency"]
    assert f"f_d = <b>{f_d:.4g} Hz</b>" in html and "50 Hz, protocol paper" in html
    for r in records:  # every run's before/after figure is in the table
        assert f'<td class="num">{r["figures"][0]["rmse_before"]:.4g}</td>' in html
        assert r["compensation"]["passes"] == [] or r["compensation"]["passes"][0]["strategy"] in html
    provenance = html[html.index('id="provenance"'):]
    assert [s for s in ("simulate", "centroid", "track", "compensate") if f"<td>{s}</td>" in provenance] == stages


def test_the_report_needs_no_network(logs: dict[str, Path]) -> None:
    html = logs["run"].with_suffix(".html").read_text(encoding="utf-8")
    links = re.findall(r'\b(?:href|src)="([^"]*)"', html)
    assert links and all(link.startswith(("data:image/png;base64,", "#")) for link in links), set(links)
    assert "<script" not in html and "<link" not in html and "@import" not in html
    assert set(re.findall(r"url\(([^)]*)\)", html)) <= {f"#{c}" for c in re.findall(r'clipPath id="([^"]+)"', html)}
    assert set(re.findall(r"https?://[^\"' <]+", html)) == {"http://www.w3.org/2000/svg"}  # the SVG namespace only


# ---------------------------------------------------------------- logs with some stages only
def test_a_simulated_log_shows_its_frame_and_names_the_missing_stages(logs: dict[str, Path]) -> None:
    html = render_report(collect_report_data(logs["sim"]))
    assert _figures(html) == ["frame"]
    missing = " ".join(_missing(html))
    for stage in ("starlog centroid", "starlog track", "starlog compensate"):
        assert stage in missing
    assert html.count('<section id="') == 9  # every section is there, none is a blank box


def test_a_centroid_log_draws_the_centroids_of_its_frame(logs: dict[str, Path]) -> None:
    data = collect_report_data(logs["cen"])
    assert data.frame is not None and data.frame.overlay_topic == "/stars/centroids/GAUSSFIT"
    with LogReader(logs["cen"]) as log:
        stars = next(log.messages("/stars/centroids/GAUSSFIT", start=data.frame.log_time)).payload
    assert data.frame.index == stars["frame"] and len(data.frame.points) == len(stars["stars"]) == 4
    html = render_report(data)
    assert len(re.findall(r'<g id="centroid-\d+"><title>', html)) == 4 and _figures(html) == ["frame"]
    assert "starlog track" in " ".join(_missing(html))


def test_a_track_log_shows_tracks_and_the_spectrum_peak_without_a_decomposition(logs: dict[str, Path]) -> None:
    data = collect_report_data(logs["trk"])
    assert data.error is not None and data.error.dominant_frequency is None and data.error.t.size == 160
    assert data.tracks is not None and len(data.tracks.tracks) == 4 and data.tracks.brightest in data.tracks.tracks
    html = render_report(data)
    assert _figures(html) == FIGURES[:5]
    assert "spectrum&#x27;s highest peak (no decomposition in this log: starlog compensate makes one)" in html
    assert all("starlog compensate" in m for m in _missing(html)) and len(_missing(html)) == 3


def test_a_foreign_log_is_reported_from_its_own_image_channel(logs: dict[str, Path], tmp_path: Path) -> None:
    from tests.foreign_logs import write_ros2

    bag = write_ros2(logs["sim"], tmp_path / "bag.mcap", compressed="png")
    data = collect_report_data(bag)
    assert data.frame is not None and data.frame.topic == "/camera/image_raw" and data.frame.image.shape == (80, 96)
    html = render_report(data)
    assert _figures(html) == ["frame"] and "no provenance record: it was not written by a starlog stage" in html


def test_long_channels_are_sampled(logs: dict[str, Path], monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(collect, "MAX_TRACK_SAMPLES", 40)
    monkeypatch.setattr(collect, "MAX_SERIES_SAMPLES", 100)
    data = collect_report_data(logs["trk"])
    assert data.tracks is not None and data.tracks.stride == 4
    assert all(v[0].size <= 40 for v in data.tracks.tracks.values())
    assert data.error is not None and data.error.t.size == 100 and data.error.truncated


def test_report_command(logs: dict[str, Path], tmp_path: Path) -> None:
    out = tmp_path / "r.html"
    result = CliRunner().invoke(cli, ["report", str(logs["cen"]), "-o", str(out), "--json"])
    assert result.exit_code == 0, result.output
    assert set(json.loads(result.stdout)["missing"]) == {"tracks", "error", "decisions"} and out.is_file()
    again = CliRunner().invoke(cli, ["report", str(logs["cen"]), "-o", str(out)])
    assert again.exit_code == 1 and "exists" in again.output
    done = CliRunner().invoke(cli, ["report", str(logs["run"]), "-o", str(out), "--force"])
    assert (done.stdout, done.stderr) == ("", f"wrote {out}\n")  # a status line, not a result


# ---------------------------------------------------------------- figure helpers
def test_amplitude_spectrum_finds_a_sinusoid() -> None:
    t = np.arange(400) / 100.0
    freq, amp = amplitude_spectrum(0.3 * np.sin(2 * np.pi * 12.5 * t) + 5.0, 100.0)
    assert freq[np.argmax(amp)] == pytest.approx(12.5) and amp.max() == pytest.approx(0.3, rel=1e-6)


def test_envelope_keeps_the_peaks_of_a_long_series() -> None:
    x = np.arange(100_000, dtype=float)
    y = np.zeros_like(x)
    y[31_337], y[77_000] = 5.0, -4.0
    xs, ys = envelope(x, y, max_points=500)
    assert xs.size <= 500 and ys.max() == 5.0 and ys.min() == -4.0 and np.all(np.diff(xs) > 0)


# ---------------------------------------------------------------- in a browser
@pytest.fixture(scope="module")
def browser() -> Iterator[Browser]:
    executable = find_chromium()
    if executable is None:
        pytest.skip(INSTALL_HINT)
    with Browser(executable, timeout=60) as b:
        yield b
    assert not b.alive(), "Chromium outlived the test"


def test_report_renders_in_chromium_and_every_figure_is_drawn(browser: Browser, logs: dict[str, Path],
                                                              tmp_path: Path) -> None:
    browser.drain()
    browser.events.clear()
    drawn = figures_drawn(browser, logs["run"].with_suffix(".html"))
    assert list(drawn) == FIGURES
    assert all(fraction > 0.02 for fraction in drawn.values()), drawn
    partial = tmp_path / "sim.html"
    partial.write_text(render_report(collect_report_data(logs["sim"])), encoding="utf-8")
    assert figures_drawn(browser, partial)["frame"] > 0.02
    assert browser.errors() == []


def test_the_browser_check_sees_blank_figures_and_console_errors(browser: Browser, tmp_path: Path) -> None:
    browser.drain()
    browser.events.clear()
    page = tmp_path / "blank.html"
    page.write_text('<!DOCTYPE html><html><body><figure class="fig" data-figure="empty">'
                    '<svg xmlns="http://www.w3.org/2000/svg" width="300" height="200"></svg></figure>'
                    '<script>console.error("broken figure")</script></body></html>')
    assert figures_drawn(browser, page) == {"empty": 0.0}
    assert any("broken figure" in e for e in browser.errors())
    browser.events.clear()
