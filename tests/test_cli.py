"""The command line: help everywhere, determinism, info/export output, errors as one sentence."""

from __future__ import annotations

import json
from pathlib import Path

import pyarrow.parquet as pq
import pytest
from click.testing import CliRunner

from starlog.cli import cli

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
