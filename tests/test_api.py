"""starlog from Python: every function against its command on the same log (same bytes, same summary), the
tables of ``starlog.open`` against ``export``'s Parquet, the errors, the help, the notebook and the reference."""

from __future__ import annotations

import hashlib
import json
import os
import pydoc
import re
import subprocess
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pyarrow.parquet as pq
import pytest
from click.testing import CliRunner

import starlog
from starlog import api
from starlog.cli import cli
from starlog.errors import LogNotFoundError, StarlogError

ROOT = Path(__file__).resolve().parent.parent
SKY = ["--size", "256x256", "--frames", "80", "--fps", "50", "--sky-attitude", "80,20,30", "--fov", "10",
       "--jitter", "2:0.3", "--seed", "4"]
SKY_KEYWORDS: dict[str, Any] = {"size": (256, 256), "frames": 80, "fps": 50, "sky_attitude": (80, 20, 30),
                                "fov": 10, "jitter": [(2, 0.3)], "seed": 4}
#: Summary fields that measure the machine rather than the log.
TIMINGS = {"seconds", "solver_ms", "ms_per_frame", "elapsed_s"}


def _digests(folder: Path) -> dict[str, str]:
    return {p.relative_to(folder).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def _assert_same_but_timings(one: Path, other: Path) -> None:
    """Files that differ in bytes only where the solver's time per frame is recorded (``solve`` writes it)."""
    if one.suffix == ".parquet":
        tables = [pq.read_table(one), pq.read_table(other)]
    else:
        with starlog.open(one) as a, starlog.open(other) as b:
            assert a.table_names() == b.table_names()
            for name in a.table_names():
                _assert_same_but_timings_in(a.table(name), b.table(name), f"{one.name}: {name}")
            return
    _assert_same_but_timings_in(*tables, one.name)


def _assert_same_but_timings_in(one: Any, other: Any, what: str) -> None:
    timed = [c for c in one.column_names if c in TIMINGS]
    assert timed or one.equals(other), what
    assert one.drop_columns(timed).equals(other.drop_columns(timed)), what


def _without_timings(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _without_timings(v) for k, v in value.items() if k not in TIMINGS}
    if isinstance(value, list):
        return [_without_timings(v) for v in value]
    return value


@pytest.fixture(scope="module")
def folders(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Path, Path]]:
    """Two folders, one for the command line and one for Python, each with the same sky log."""
    root = tmp_path_factory.mktemp("api")
    by_cli, by_api = root / "cli", root / "api"
    by_cli.mkdir()
    by_api.mkdir()
    yield by_cli, by_api


def _cli(folder: Path, args: list[str]) -> Any:
    """Run a command in ``folder`` (relative paths: the bytes do not depend on the folder); its --json result."""
    here = os.getcwd()
    os.chdir(folder)
    try:
        result = CliRunner().invoke(cli, args)
    finally:
        os.chdir(here)
    assert result.exit_code == 0, result.output
    return json.loads(result.stdout) if "--json" in args else None


def _api(folder: Path, call: Callable[[], Any]) -> Any:
    here = os.getcwd()
    os.chdir(folder)
    try:
        return call()
    finally:
        os.chdir(here)


def _same(folders: tuple[Path, Path], args: list[str], call: Callable[[], Any],
          summary: Callable[[Any], Any] = lambda s: s.to_dict()) -> None:
    """The command and the function write the same bytes and give the same summary."""
    by_cli, by_api = folders
    printed = _cli(by_cli, args)
    returned = _api(by_api, call)
    written, made = _digests(by_cli), _digests(by_api)
    assert written.keys() == made.keys()
    for name in (n for n in written if written[n] != made[n]):
        _assert_same_but_timings(by_cli / name, by_api / name)
    if not isinstance(returned, dict):  # the command's text too
        assert all(isinstance(line, str) for line in returned.lines())
    if printed is not None:  # the folder named in absolute paths (a layer's bases) aside
        here = json.loads(json.dumps(printed).replace(str(by_cli), "FOLDER"))
        there = json.loads(json.dumps(summary(returned)).replace(str(by_api), "FOLDER"))
        assert _without_timings(here) == _without_timings(there)


def test_each_function_writes_what_its_command_writes_and_returns_what_it_prints(folders: tuple[Path, Path]
                                                                                 ) -> None:
    _same(folders, ["simulate", "-o", "sky.mcap", *SKY, "-q"], lambda: starlog.simulate("sky.mcap", **SKY_KEYWORDS))
    _same(folders, ["centroid", "sky.mcap", "-o", "cen.mcap", "--method", "GAUSSFIT,MOMENT", "--json", "-q"],
          lambda: starlog.centroid("sky.mcap", "cen.mcap", method="GAUSSFIT,MOMENT"))
    _same(folders, ["track", "cen.mcap", "-o", "trk.mcap", "--centroids", "GAUSSFIT", "--model", "STATIC",
                    "--set", "sigma_floor=0.05", "--json", "-q"],
          lambda: starlog.track("cen.mcap", "trk.mcap", centroids="GAUSSFIT", model="STATIC",
                                options={"sigma_floor": 0.05}))
    _same(folders, ["motion", "trk.mcap", "-o", "mot.mcap", "--json", "-q"],
          lambda: starlog.motion("trk.mcap", "mot.mcap"))
    _same(folders, ["compensate", "trk.mcap", "-o", "cmp.mcap", "--rate", "25", "--protocol", "paper,truth",
                    "--burn-in", "off", "--json", "-q"],
          lambda: starlog.compensate("trk.mcap", "cmp.mcap", rate=25, protocol="paper,truth", burn_in="off"))
    _same(folders, ["solve", "cen.mcap", "-o", "att.mcap", "--centroids", "GAUSSFIT", "--start", "frame:2",
                    "--json", "-q"],
          lambda: starlog.solve("cen.mcap", "att.mcap", centroids="GAUSSFIT", start="frame:2"))
    _same(folders, ["flatten", "cmp.mcap", "-o", "whole.mcap", "--json", "-q"],
          lambda: starlog.flatten("cmp.mcap", "whole.mcap"))
    _same(folders, ["export", "att.mcap", "-o", "tables", "--json"],
          lambda: starlog.export("att.mcap", "tables"), lambda written: {"output": "tables", "tables": written})
    _same(folders, ["verify", "cmp.mcap", "--json", "-q"], lambda: starlog.verify("cmp.mcap"))


def test_run_writes_what_the_command_writes(folders: tuple[Path, Path], tmp_path: Path) -> None:
    config = {"centroid": {"methods": "MOMENT"}, "track": {"methods": ["MOMENT"], "models": "STATIC"},
              "compensate": {"rates": [25], "protocols": "paper"}}
    toml = tmp_path / "small.toml"
    toml.write_text('[centroid]\nmethods = "MOMENT"\n[track]\nmethods = ["MOMENT"]\nmodels = "STATIC"\n'
                    '[compensate]\nrates = [25]\nprotocols = "paper"\n', encoding="utf-8")
    _same(folders, ["run", "sky.mcap", "-o", "result.mcap", "--config", str(toml), "--json", "-q"],
          lambda: starlog.run("sky.mcap", "result.mcap", config=config),
          lambda result: {**result.to_dict(), "report": "result.html"})


def test_ingest_writes_what_the_command_writes(tmp_path: Path) -> None:
    frames = tmp_path / "frames"
    frames.mkdir()
    rng = np.random.default_rng(2)
    for n in range(5):
        cv2.imwrite(str(frames / f"img{n}.png"), rng.integers(0, 4000, (32, 48), dtype=np.uint16))
    pair = (tmp_path / "cli", tmp_path / "api")
    for folder in pair:
        folder.mkdir()
    _same(pair, ["ingest", str(frames), "-o", "lab.mcap", "--fps", "30", "--json", "-q"],
          lambda: starlog.ingest(frames, "lab.mcap", fps=30))


@pytest.fixture(scope="module")
def every_table(folders: tuple[Path, Path]) -> Path:
    """A log with a channel of every table export writes (and a foreign JSON channel, /camera/frame)."""
    by_api = folders[1]
    if not (by_api / "att.mcap").exists():
        test_each_function_writes_what_its_command_writes_and_returns_what_it_prints(folders)
    _api(by_api, lambda: starlog.motion("cmp.mcap", "mot2.mcap", force=True))
    _api(by_api, lambda: starlog.solve("mot2.mcap", "all.mcap", centroids="GAUSSFIT", force=True))
    return by_api / "all.mcap"


def test_each_table_is_the_table_export_writes(every_table: Path, tmp_path: Path) -> None:
    written = starlog.export(every_table, tmp_path / "tables", topics=["/stars/annotations"])
    with starlog.open(every_table) as log:
        assert sorted(log.table_names()) == sorted(set(written) - {"stars.annotations"})
        assert {"centroids", "tracks", "motion", "residuals", "compensation", "decisions", "attitude",
                "identified", "truth", "frames", "detections"} <= set(log.table_names())
        for name in log.table_names():
            exported = pq.read_table(tmp_path / "tables" / f"{name}.parquet")
            assert log.table(name).equals(exported), name
        assert log.table("/stars/annotations").equals(pq.read_table(tmp_path / "tables" / "stars.annotations.parquet"))


def test_a_channel_or_a_range_of_a_table_is_those_rows_of_the_whole(every_table: Path) -> None:
    with starlog.open(every_table) as log:
        whole = log.table("centroids").to_pandas()
        one = log.table("/stars/centroids/MOMENT").to_pandas()
        assert one.reset_index(drop=True).equals(whole[whole.method == "MOMENT"].reset_index(drop=True))
        frame_times = sorted(set(whole.log_time))
        part = log.table("centroids", start="frame:5", end="frame:9").to_pandas()
        assert part.reset_index(drop=True).equals(
            whole[(whole.log_time >= frame_times[5]) & (whole.log_time < frame_times[9])].reset_index(drop=True))
        seconds = log.table("frames", start=f"{frame_times[3] * 1e-9:.9f}s", end=frame_times[6])
        assert seconds["log_time"].to_pylist() == frame_times[3:6]


def test_a_range_reads_only_the_chunks_that_hold_it(every_table: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from starlog.io import mcap_file

    opened: list[int] = []
    original = mcap_file.McapFile.read_chunk

    def counting(self: Any, *args: Any, **kwargs: Any) -> Any:
        opened.append(1)
        return original(self, *args, **kwargs)

    monkeypatch.setattr(mcap_file.McapFile, "read_chunk", counting)
    with starlog.open(every_table) as log:
        log.table("/camera/frame")
        everything = len(opened)
        opened.clear()
        log.table("/camera/frame", end="frame:2")
        assert 0 < len(opened) < everything


def test_frames_and_messages_stream_the_range(every_table: Path) -> None:
    with starlog.open(every_table) as log:
        frames = list(log.frames(start="frame:3", end="frame:6"))
        times = [m.log_time for m in log.messages("/camera/frame")]
        assert [t for t, _ in frames] == times[3:6]
        assert all(image.shape == (256, 256) and image.dtype == np.uint16 for _, image in frames)
        assert [m.log_time for m in log.messages("/camera/frame", end="frame:2")] == times[:2]
        described = log.describe()
        assert described["message_count"] == sum(c.message_count for c in log.channels)
        assert [p.stage for p in log.provenance][:2] == ["simulate", "centroid"]
        first, last = log.time_range
        assert first == times[0] and last >= times[-1]


def test_errors_are_starlog_errors_with_the_commands_message(tmp_path: Path) -> None:
    with pytest.raises(LogNotFoundError) as raised:
        starlog.centroid(tmp_path / "missing.mcap", tmp_path / "out.mcap")
    printed = CliRunner().invoke(cli, ["track", str(tmp_path / "missing.mcap"), "-o", str(tmp_path / "t.mcap"),
                                       "--centroids", "GAUSSFIT"])
    assert printed.exit_code == 2  # click checks that the file exists before starlog does
    (tmp_path / "not.mcap").write_bytes(b"not a log")
    with pytest.raises(StarlogError) as raised:
        starlog.open(tmp_path / "not.mcap")
    printed = CliRunner().invoke(cli, ["info", str(tmp_path / "not.mcap")])
    assert printed.exit_code == 1
    assert printed.output.strip() == f"Error: {raised.value}"
    with pytest.raises(StarlogError, match="frames or the duration"):
        starlog.simulate(tmp_path / "x.mcap", frames=10, duration=1.0)


def test_help_shows_an_example_for_every_function() -> None:
    for name in api.__all__:
        text = pydoc.render_doc(getattr(starlog, name), renderer=pydoc.plaintext)
        assert "Example::" in text and f"starlog.{name}(" in text, name
    assert set(api.__all__) | {"Log", "StarlogError", "__version__"} == set(starlog.__all__)


def test_import_starlog_loads_none_of_the_library() -> None:
    """The command line starts with ``import starlog``: the public face is loaded on first use."""
    code = "import sys, starlog; print(sorted(m for m in sys.modules if m.startswith('starlog')))"
    loaded = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert json.loads(loaded.replace("'", '"')) == ["starlog", "starlog.version"]


def test_the_notebook_runs_top_to_bottom(tmp_path: Path) -> None:
    """docs/python.ipynb, executed as a reader would run it: every cell without an error, its figures drawn."""
    import nbformat
    from nbclient import NotebookClient

    notebook = nbformat.read(ROOT / "docs" / "python.ipynb", as_version=4)
    NotebookClient(notebook, timeout=600, kernel_name="python3",
                   resources={"metadata": {"path": str(tmp_path)}}).execute()
    outputs = [o for cell in notebook.cells if cell.cell_type == "code" for o in cell.outputs]
    assert not [o for o in outputs if o.output_type == "error"]
    assert sum("image/png" in o.get("data", {}) for o in outputs) == 2
    bars = [o.text for o in outputs if o.output_type == "stream" and o.name == "stderr"]
    assert any("centroid" in text and "%|" in text for text in bars), "progress=True shows no bar in a notebook"
    assert (tmp_path / "starlog-notebook" / "attitude.mcap").exists()


def test_the_api_reference_builds_without_warnings(tmp_path: Path) -> None:
    """The reference (pdoc, from the docstrings) of the public face, in one page, and the modules it names."""
    done = subprocess.run([sys.executable, "-W", "error", "-m", "pdoc", "starlog", "starlog.api", "starlog.log",
                           "-o", str(tmp_path / "reference")], capture_output=True, text=True)
    assert done.returncode == 0 and not done.stderr.strip(), done.stderr
    page = (tmp_path / "reference" / "starlog.html").read_text(encoding="utf-8")
    documented = set(re.findall(r'id="([A-Za-z_.]+)"', page))
    assert set(starlog.__all__) <= documented
    assert {"Log.table", "Log.frames", "Log.messages", "Log.describe"} <= documented


#: The options of a command that are not keywords of its function: what it prints and how, and the batches of
#: several logs (a Dask scheduler; export's workers, one per log).
COMMAND_ONLY = {"as_json", "quiet", "print_config", "full_table", "scheduler"}
BATCH_ONLY = {("export", "workers")}
#: A command's option → its function's keyword, where the names differ (the command's dest names are older).
RENAMED = {"methods": "method", "models": "model", "settings": "options", "track_topic": "track", "fit": "model",
           "rates": "rate", "protocols": "protocol", "n_stars": "stars", "n_frames": "frames", "psf_model": "psf",
           "fov_deg": "fov", "config_path": "config", "export_topics": "topics", "logs": "log"}
RENAMED_IN = {("ingest", "start_ns"): "start", ("track", "method"): "centroids", ("solve", "methods"): "centroids"}
COMMANDS = ["simulate", "ingest", "centroid", "track", "motion", "compensate", "solve", "run", "export", "flatten",
            "verify"]


@pytest.mark.parametrize("name", COMMANDS)
def test_each_function_takes_its_commands_options_with_its_defaults(name: str) -> None:
    import inspect

    command = cli.commands[name]
    keywords = inspect.signature(getattr(starlog, name)).parameters
    for param in command.params:
        if param.name in COMMAND_ONLY or (name, param.name) in BATCH_ONLY:
            continue
        keyword = RENAMED_IN.get((name, param.name), RENAMED.get(param.name, param.name))
        assert keyword in keywords, f"starlog.{name} has no keyword for the command's {param.opts}"
        given, default = keywords[keyword].default, param.default
        if param.name == "workers":
            assert given in (None, default), f"starlog.{name}(workers=) {given} vs {default}"
        elif (not param.required and default not in (None, ()) and "UNSET" not in repr(default)
              and not param.multiple and param.name not in ("size", "flux", "drift", "logs")):
            # size, flux, drift: numbers in Python, text on the command line
            assert given == default, f"starlog.{name}({keyword}=) defaults to {given!r}, the command to {default!r}"


def test_lists_are_taken_as_the_commands_text_or_as_lists(every_table: Path, tmp_path: Path) -> None:
    assert starlog.export(every_table, tmp_path / "a", tables="centroids,tracks") == \
        starlog.export(every_table, tmp_path / "b", tables=["centroids", "tracks"])
    with pytest.raises(StarlogError, match="rates in Hz"):
        starlog.compensate(every_table, tmp_path / "c.mcap", rate="ten")


def test_a_log_of_a_camera_has_the_frames_table_export_writes(every_table: Path, tmp_path: Path) -> None:
    """Image channels without starlog's frame channel: the frames table of the image channels."""
    camera = tmp_path / "camera.mcap"
    assert CliRunner().invoke(cli, ["filter", str(every_table), "-o", str(camera), "--topic", "/camera/image",
                                    "--end", "frame:6", "-q"]).exit_code == 0
    starlog.export(camera, tmp_path / "tables")
    with starlog.open(camera) as log:
        assert log.table_names() == ["frames"]
        assert log.table("frames").equals(pq.read_table(tmp_path / "tables" / "frames.parquet"))
        assert log.table("frames", start="frame:2")["frame"].to_pylist() == [2, 3, 4, 5]


def test_mistakes_are_one_line_starlog_errors(every_table: Path) -> None:
    with starlog.open(every_table) as log:
        first, _ = log.time_range
        mistakes = [lambda: log.table("centroid"), lambda: log.table("centroids", start=1.5),
                    lambda: log.table("centroids", end=first - 1), lambda: log.frames("/stars/detections"),
                    lambda: log.table("centroids", start="frame:100000")]
        for mistake in mistakes:
            with pytest.raises(StarlogError) as raised:
                mistake()
            assert "\n" not in str(raised.value)
        assert log.table("centroids", start=np.int64(first), end="frame:1").num_rows > 0
    with pytest.raises(StarlogError, match="closed"):
        log.table("centroids")
    with starlog.open(every_table) as log, pytest.raises(StarlogError, match="neither a table"):
        log.table("ingest")
    with pytest.raises(LogNotFoundError):
        starlog.verify(every_table.parent / "missing.mcap")


SCRIPT = """
import starlog
{guard}
    summary = starlog.centroid("sim.mcap", "cen.mcap", method="GAUSSFIT,MOMENT", workers=2, force=True)
    print(summary.to_dict()["frames"])
"""


def test_a_script_runs_its_calls_under_the_main_guard_or_is_told_to(tmp_path: Path) -> None:
    """Worker processes import the script that started them again: under ``if __name__ == "__main__":`` the calls
    run once; without it the worker ends and the call raises a StarlogError that names the guard."""
    starlog.simulate(tmp_path / "sim.mcap", frames=300, size=(128, 128), workers=1)
    for guard, expected in (("if __name__ == '__main__':", 0), ("if True:", 1)):
        (tmp_path / "script.py").write_text(SCRIPT.format(guard=guard), encoding="utf-8")
        done = subprocess.run([sys.executable, "script.py"], cwd=tmp_path, capture_output=True, text=True,
                              timeout=300)
        assert done.returncode == expected, done.stderr
        if expected:
            assert "WorkerProcessError" in done.stderr and '__name__ == \\"__main__\\"' not in done.stderr
            assert 'if __name__ == "__main__":' in done.stderr.splitlines()[-1]
        else:
            assert done.stdout.strip() == "300"


def test_the_text_a_command_prints_is_its_summarys_lines(folders: tuple[Path, Path]) -> None:
    by_cli, by_api = folders
    if not (by_api / "trk.mcap").exists():
        test_each_function_writes_what_its_command_writes_and_returns_what_it_prints(folders)
    here = os.getcwd()
    os.chdir(by_cli)
    try:
        printed = CliRunner().invoke(cli, ["compensate", "trk.mcap", "-o", "text.mcap", "--rate", "25",
                                           "--protocol", "paper", "-q"])
    finally:
        os.chdir(here)
    returned = _api(by_api, lambda: starlog.compensate("trk.mcap", "text.mcap", rate=25, protocol="paper"))
    assert printed.exit_code == 0 and printed.stdout == "".join(f"{line}\n" for line in returned.lines())
