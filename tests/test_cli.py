"""The command line: help everywhere, every option used, -q, determinism, info/export output, errors, -OO."""

from __future__ import annotations

import ast
import importlib.util
import inspect
import json
import pkgutil
import subprocess
import sys
import textwrap
from collections.abc import Callable
from pathlib import Path
from typing import Any

import click
import cv2
import pyarrow.parquet as pq
import pytest
from click.testing import CliRunner
from tqdm import tqdm

import starlog
from starlog.cli import cli
from starlog.io import LogReader
from starlog.pipeline import DEFAULT_CONFIG_TOML

SMALL = ["--size", "48x40", "--stars", "2", "--frames", "8", "--seed", "4", "-q"]


def test_every_command_has_help_with_an_example() -> None:
    runner = CliRunner()
    for name, command in cli.commands.items():
        result = runner.invoke(cli, [name, "--help"])
        assert result.exit_code == 0, name
        assert "Example" in result.output, f"{name} --help has no example"
        assert command.help


def test_version() -> None:
    result = CliRunner().invoke(cli, ["--version"])
    assert result.exit_code == 0 and "starlog" in result.output


def test_simulate_is_deterministic(tmp_path: Path) -> None:
    runner = CliRunner()
    for name in ("a.mcap", "b.mcap"):
        result = runner.invoke(cli, ["simulate", "-o", str(tmp_path / name), *SMALL, "--jitter", "10:0.1"])
        assert result.exit_code == 0, result.output
    assert (tmp_path / "a.mcap").read_bytes() == (tmp_path / "b.mcap").read_bytes()


def test_info_json_and_export(tmp_path: Path) -> None:
    runner = CliRunner()
    log = tmp_path / "s.mcap"
    assert runner.invoke(cli, ["simulate", "-o", str(log), *SMALL, "--preset", "paper200"]).exit_code == 0
    result = runner.invoke(cli, ["info", str(log), "--json"])
    info = json.loads(result.output)
    image = next(c for c in info["channels"] if c["topic"] == "/camera/image")
    assert image["message_count"] == 8 and image["rate_hz"] == pytest.approx(200.0)
    assert info["provenance"][0]["parameters"]["fps"] == 200.0
    text = runner.invoke(cli, ["info", str(log)]).output
    assert "/sim/truth" in text and "simulate" in text
    result = runner.invoke(cli, ["export", str(log), "-o", str(tmp_path / "t"), "--json"])
    assert json.loads(result.output)["tables"] == {"frames": 8, "truth": 16}
    truth = pq.read_table(tmp_path / "t" / "truth.parquet")
    assert truth.schema.field("x").metadata[b"unit"] == b"px"
    assert truth.column("log_time").type == "int64"


def test_errors_are_one_sentence_with_exit_status_1(tmp_path: Path) -> None:
    runner = CliRunner()
    log = tmp_path / "s.mcap"
    runner.invoke(cli, ["simulate", "-o", str(log), *SMALL])
    result = runner.invoke(cli, ["simulate", "-o", str(log), *SMALL])
    assert result.exit_code == 1 and "exists already; pass --force" in result.output
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(log.read_bytes()[:500])
    result = runner.invoke(cli, ["info", str(bad)])
    assert result.exit_code == 1 and "starlog recover" in result.output
    result = runner.invoke(cli, ["simulate", "-o", str(tmp_path / "x.mcap"), "--size", "4x4"])
    assert result.exit_code == 1 and "frame size" in result.output


def test_bad_option_formats(tmp_path: Path) -> None:
    result = CliRunner().invoke(cli, ["simulate", "-o", str(tmp_path / "x.mcap"), "--jitter", "abc"])
    assert result.exit_code == 2 and "FREQ_HZ:AMPLITUDE_PX" in result.output



def test_centroid_set_routes_flat_options_to_detection_and_centroiding(tmp_path: Path) -> None:
    runner = CliRunner()
    log = tmp_path / "s.mcap"
    assert runner.invoke(cli, ["simulate", "-o", str(log), *SMALL]).exit_code == 0
    args = ["centroid", str(log), "--method", "MOMENT", "-q", "--set", "threshold=6", "--set", "robust=false"]
    result = runner.invoke(cli, [*args, "-o", str(tmp_path / "c.mcap")])
    assert result.exit_code == 0, result.output
    with LogReader(tmp_path / "c.mcap") as reader:
        options = next(p for p in reader.provenance() if p.stage == "centroid").parameters["options"]
    assert options["detect_options"] == {"threshold": 6} and options["centroid_options"] == {"robust": False}
    result = runner.invoke(cli, ["centroid", str(log), "-o", str(tmp_path / "d.mcap"), "--set", "thresh=6"])
    assert result.exit_code == 1 and "unknown centroid option 'thresh'" in result.output
    assert "threshold" in result.output and not (tmp_path / "d.mcap").exists()


# ---------------------------------------------------------------- every option does something
def _names_used(function: Callable[..., Any]) -> set[str]:
    """Names the function's body reads (nested functions included), not its signature."""
    tree = ast.parse(textwrap.dedent(inspect.getsource(function)))
    definition = tree.body[0]
    assert isinstance(definition, ast.FunctionDef)
    return {node.id for statement in definition.body for node in ast.walk(statement)
            if isinstance(node, ast.Name) and isinstance(node.ctx, ast.Load)}


OPTIONS = [pytest.param(name, param.name, id=f"{name} {param.opts[-1]}")
           for name, command in sorted(cli.commands.items()) for param in command.params]


@pytest.mark.parametrize(("name", "param"), OPTIONS)
def test_every_option_in_help_is_used_by_its_command(name: str, param: str) -> None:
    command = cli.commands[name]
    option = next(p for p in command.params if p.name == param)
    assert option.name in inspect.signature(command.callback).parameters  # type: ignore[arg-type]
    if isinstance(option, click.Option):  # listed in --help
        assert not option.hidden and any(o in command.get_help(click.Context(command)) for o in option.opts)
    assert param in _names_used(command.callback), f"{name}: {option.opts} is accepted but never used"  # type: ignore[arg-type]


@pytest.fixture(scope="module")
def quiet_logs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """simulate → centroid → track → compensate, and the frames as PNG files, in one folder."""
    d = tmp_path_factory.mktemp("quiet")
    runner = CliRunner()
    steps = [["simulate", "-o", "sim.mcap", "--size", "80x64", "--stars", "3", "--fps", "100", "--frames", "120",
              "--jitter", "7:0.05", "--seed", "2"],
             ["centroid", "sim.mcap", "-o", "cen.mcap", "--method", "NONE"],
             ["track", "cen.mcap", "-o", "trk.mcap", "--centroids", "NONE", "--model", "STATIC",
              "--set", "sigma_floor=0.05"],
             ["compensate", "trk.mcap", "-o", "cmp.mcap", "--rate", "50", "--protocol", "paper"]]
    for step in steps:
        args = [str(d / a) if a.endswith(".mcap") else a for a in step]
        result = runner.invoke(cli, [*args, "--workers", "1", "-q"])
        assert result.exit_code == 0, result.output
    (d / "frames").mkdir()
    with LogReader(d / "sim.mcap") as log:
        for index, _, image in log.frames():
            assert cv2.imwrite(str(d / "frames" / f"f{index}.png"), image)
    (d / "p.toml").write_text('[centroid]\nmethods = ["NONE"]\n[track]\nmethods = ["NONE"]\nmodels = "STATIC"\n'
                              '[track.tracker]\nsigma_floor = 0.05\n[compensate]\nrates = [50]\nprotocols = "paper"\n')
    return d


#: Each command that takes -q, on the logs of ``quiet_logs``; OUT is its output; True if it writes a log.
QUIET_COMMANDS = {  # name: (arguments, writes a log, shows progress or status without -q)
    "simulate": (["simulate", "-o", "OUT.mcap", "--size", "48x40", "--frames", "20", "--workers", "1"], True, True),
    "ingest": (["ingest", "frames", "-o", "OUT.mcap", "--fps", "100", "--workers", "1"], True, True),
    "centroid": (["centroid", "sim.mcap", "-o", "OUT.mcap", "--method", "NONE,MOMENT", "--workers", "1"], True, True),
    "track": (["track", "cen.mcap", "-o", "OUT.mcap", "--centroids", "NONE", "--model", "STATIC",
               "--set", "sigma_floor=0.05", "--workers", "1"], True, True),
    "compensate": (["compensate", "trk.mcap", "-o", "OUT.mcap", "--rate", "50", "--protocol", "paper",
                    "--workers", "1"], True, True),
    "motion": (["motion", "trk.mcap", "-o", "OUT.mcap", "--workers", "1"], True, True),
    "run": (["run", "sim.mcap", "-o", "OUT.mcap", "--config", "p.toml", "--workers", "1"], True, True),
    "live": (["live", "frames", "-o", "OUT.mcap", "--config", "p.toml", "--no-server", "--fps", "100",
              "--idle-timeout", "0.5", "--workers", "0"], True, True),
    "export": (["export", "sim.mcap", "cen.mcap", "-o", "OUT", "--workers", "1"], False, True),
    "filter": (["filter", "sim.mcap", "-o", "OUT.mcap", "--topic", "/camera/*", "--end", "frame:10"], True, True),
    "verify": (["verify", "sim.mcap"], False, True),
    "flatten": (["flatten", "trk.mcap", "-o", "OUT.mcap"], True, True),
    "recover": (["recover", "trk.mcap", "-o", "OUT.mcap"], True, True),
    "report": (["report", "trk.mcap", "-o", "OUT.html"], False, True),
    "info": (["info", "trk.mcap"], False, False),
    "cat": (["cat", "sim.mcap", "--topic", "/sim/truth", "--limit", "2"], False, False),
}
HAS_SOLVER = importlib.util.find_spec("tetra3") is not None  # solve needs the optional cedar-solve
if HAS_SOLVER:
    QUIET_COMMANDS["solve"] = (["solve", "cen.mcap", "-o", "OUT.mcap", "--centroids", "NONE", "--end", "frame:2",
                                "--set", "timeout_ms=50", "--set", "try_mirrored=false"], True, True)


@pytest.fixture
def progress_bars_shown(monkeypatch: pytest.MonkeyPatch) -> None:
    """Show progress bars although the test's stderr is not a terminal."""
    show = tqdm.__init__

    def init(self: tqdm, *args: Any, **kwargs: Any) -> None:
        if kwargs.get("disable", False) is None:
            kwargs["disable"] = False
        show(self, *args, **kwargs)

    monkeypatch.setattr(tqdm, "__init__", init)


def test_every_command_with_quiet_is_covered() -> None:
    with_quiet = {name for name, command in cli.commands.items() if any(p.name == "quiet" for p in command.params)}
    assert with_quiet == set(QUIET_COMMANDS) | {"experiment"} | (set() if HAS_SOLVER else {"solve"})


@pytest.mark.parametrize("name", sorted(QUIET_COMMANDS))
def test_quiet_silences_progress_and_status_and_keeps_the_results(
        name: str, quiet_logs: Path, progress_bars_shown: None) -> None:
    template, writes_log, shows_status = QUIET_COMMANDS[name]
    args = [str(quiet_logs / a.replace("OUT", name)) if a.startswith(("OUT", "frames")) or a.endswith((".mcap", ".toml"))
            else a for a in template]
    force = ["--force"] if any(p.name == "force" for p in cli.commands[name].params) else []  # verify writes nothing
    runner = CliRunner()
    loud = runner.invoke(cli, [*args, *force])
    quiet = runner.invoke(cli, [*args, *force, "-q"])
    assert loud.exit_code == 0 and quiet.exit_code == 0, loud.output + quiet.output
    assert quiet.stderr == "", f"{name} -q still prints on stderr: {quiet.stderr!r}"
    assert (loud.stderr != "") == shows_status, f"{name} without -q: {loud.stderr!r}"
    if writes_log:
        assert f"wrote {quiet_logs / name}.mcap" in loud.stderr
    assert loud.stdout == quiet.stdout  # the results do not depend on -q


def test_experiment_quiet_turns_off_its_progress_bar(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    calls: list[bool] = []

    class Summary:
        def text(self) -> str:
            return "the summary"

    def experiment_command(output: Path, **options: Any) -> Summary:
        calls.append(options["show_progress"])
        return Summary()

    monkeypatch.setattr("starlog.experiment.experiment_command", experiment_command)
    for flags in ([], ["-q"]):
        result = CliRunner().invoke(cli, ["experiment", "-o", str(tmp_path), "--quick", *flags])
        assert result.exit_code == 0 and result.stdout == "the summary\n", result.output
    assert calls == [True, False]


# ---------------------------------------------------------------- python -OO
def test_help_and_every_module_work_without_docstrings() -> None:
    modules = sorted(m.name for m in pkgutil.walk_packages(starlog.__path__, "starlog.") if m.name != "starlog.__main__")
    assert "starlog.pipeline" in modules
    code = f"import importlib; [importlib.import_module(m) for m in {modules!r}]"
    for args in (["-c", code], ["-m", "starlog", "--help"], ["-m", "starlog", "run", "--print-config"]):
        done = subprocess.run([sys.executable, "-OO", *args], capture_output=True, text=True, check=False)
        assert done.returncode == 0, done.stderr
    assert done.stdout == DEFAULT_CONFIG_TOML


@pytest.mark.parametrize(("flag", "setting", "first_frame"), [("off", "off", 0), ("0.1", "0.1 s", 10)])
def test_compensate_burn_in_switch_is_applied_and_recorded(quiet_logs: Path, flag: str, setting: str,
                                                           first_frame: int) -> None:
    out = quiet_logs / f"burn-{flag}.mcap"
    result = CliRunner().invoke(cli, ["compensate", str(quiet_logs / "trk.mcap"), "-o", str(out), "--rate", "50",
                                      "--protocol", "paper", "--burn-in", flag, "--json", "-q", "--force"])
    assert result.exit_code == 0, result.output
    record = json.loads(result.stdout)["records"][0]
    assert record["burn_in"]["setting"] == setting
    assert record["burn_in"]["samples"] == first_frame  # 100 fps log
    with LogReader(out) as log:
        first = next(log.messages(record["series_topic"]))
    assert first.payload["frame"] == first_frame


def test_burn_in_switch_rejects_a_bad_value(quiet_logs: Path) -> None:
    result = CliRunner().invoke(cli, ["compensate", str(quiet_logs / "trk.mcap"), "-o", str(quiet_logs / "x.mcap"),
                                      "--rate", "50", "--burn-in", "later", "-q"])
    assert result.exit_code == 2 and "--burn-in" in result.output


def test_info_loads_neither_the_fitting_code_nor_scipy(quiet_logs: Path, tmp_path: Path) -> None:
    """info prints the centroid evidence's verdict (which method to trust) without loading what measures it:
    the command starts in a fraction of a second and keeps a small footprint on logs of millions of chunks."""
    two = tmp_path / "two.mcap"
    result = CliRunner().invoke(cli, ["centroid", str(quiet_logs / "sim.mcap"), "-o", str(two), "--method",
                                      "NONE,MOMENT", "--workers", "1", "-q"])
    assert result.exit_code == 0, result.output
    code = (f"import sys; from starlog.cli import cli; cli(['info', {str(two)!r}], standalone_mode=False); "
            "print('LOADED', sorted(m for m in ('scipy', 'numba', 'starlog.centroiding.extract') if m in sys.modules))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=False, timeout=60)
    assert done.returncode == 0, done.stderr
    assert "trust" in done.stdout and done.stdout.rstrip().endswith("LOADED []"), done.stdout
