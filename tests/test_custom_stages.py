"""Your own stages (starlog.stage_api): run from a config, from an installed entry point, and from Python,
with the guarantees of the built-in stages."""

from __future__ import annotations

import filecmp
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path
from typing import Any

import jsonschema
import pytest

from starlog.errors import InvalidInputError, InvalidParameterError, StageFunctionError
from starlog.io import LogReader
from starlog.io.verify import verify_log
from starlog.pipeline import PipelineConfig, run_pipeline
from starlog.replay.plugins import load_reference
from starlog.stage_api import Stage, run_stage, stage
from starlog.stages import simulate_log
from starlog.stages.centroid import centroid_log
from tests.helpers import doc_section, small_config

SECTION = doc_section("## An example: `flux_fwhm`")  # docs/STAGES.md's own-stage example
STARLOG = Path(sys.executable).with_name("starlog")

#: Stages of the tests, written to a module in a temporary folder (workers import stages by name).
MODULE = "starlog_test_stages"
STAGES_SOURCE = '''
import os
from pathlib import Path

import numpy as np

from starlog.centroiding.table import CENTROID_DTYPE
from starlog.stage_api import stage

SCHEMA = {"title": "test.Brightest", "type": "object", "additionalProperties": False,
          "required": ["frame", "method", "flux", "x"],
          "properties": {"frame": {"type": "integer", "minimum": 0}, "method": {"type": "string"},
                         "flux": {"type": "number"}, "x": {"type": "number"}}}


@stage(name="brightest_flux", version="2.1", reads="centroids", writes={"/stars/brightest/{name}": SCHEMA})
def brightest_flux(message, *, min_snr=0.0, pid_dir=""):
    """Flux and column of each frame's brightest centroid."""
    assert message.data.dtype == CENTROID_DTYPE
    if pid_dir:
        Path(pid_dir, str(os.getpid())).touch()
    stars = message.data[message.data["snr"] >= min_snr]
    if not stars.size:
        return None
    best = stars[np.argmax(stars["flux"])]
    return {"frame": message.frame, "method": message.fields["method"], "flux": best["flux"], "x": best["x"]}


@stage(name="kilo_flux", version="1", reads="/stars/brightest/GAUSSFIT",
       writes={"/stars/kilo_flux": {"type": "object", "properties": {"kflux": {"type": "number"}}},
               "/stars/bright_frames": {"type": "object", "properties": {"frame": {"type": "integer"}}}})
def kilo_flux(message, *, threshold=0.0):
    """Reads another custom stage's channel (a JSON dict) and writes two channels."""
    out = {"/stars/kilo_flux": {"kflux": message.data["flux"] / 1000}}
    if message.data["flux"] > threshold:
        out["/stars/bright_frames"] = {"frame": message.data["frame"]}
    return out


@stage(name="bad_record", version="0", reads="centroids", writes={"/stars/bad": SCHEMA})
def bad_record(message):
    return {"frame": message.frame, "method": "x", "flux": "bright", "x": 1.0}


@stage(name="failing", version="0", reads="/stars/centroids/NONE", writes={"/stars/failing": {"type": "object"}})
def failing(message):
    if message.index == 3:
        raise ZeroDivisionError("boom")
    return {}


@stage(name="pixel_sum", version="1", reads="image", writes={"/camera/sum": {"type": "object"}})
def pixel_sum(message, *, scale):
    return {"frame": message.index, "sum": int(message.data.sum()) * scale, "shape": list(message.data.shape)}
'''


@pytest.fixture(scope="module")
def stage_folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("stages")
    (folder / f"{MODULE}.py").write_text(STAGES_SOURCE, encoding="utf-8")
    return folder


def _stage(folder: Path, name: str) -> Stage:
    return load_reference(f"{MODULE}:{name}", search_path=[str(folder)])


@pytest.fixture(scope="module")
def centroid_log_path(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """80 frames (more than two batches) with NONE and GAUSSFIT centroid channels."""
    folder = tmp_path_factory.mktemp("cen")
    simulate_log(small_config(n_frames=80), folder / "sim.mcap")
    centroid_log(folder / "sim.mcap", folder / "cen.mcap", methods=["NONE", "GAUSSFIT"], workers=1)
    return folder / "cen.mcap"


def _payloads(path: Path, topic: str) -> list[dict[str, Any]]:
    with LogReader(path) as log:
        return [m.payload for m in log.messages(topic)]


# ---------------------------------------------------------------- Python API
def test_a_stage_reads_the_centroid_table_and_records_its_provenance(stage_folder: Path, centroid_log_path: Path,
                                                                    tmp_path: Path) -> None:
    brightest = _stage(stage_folder, "brightest_flux")
    out = tmp_path / "out.mcap"
    summary = run_stage(brightest, centroid_log_path, out, options={"min_snr": 5}, workers=1,
                        input_topic="/stars/centroids/GAUSSFIT")
    assert summary.to_dict()["records"] == {"/stars/brightest/GAUSSFIT": 80}
    centroids = _payloads(centroid_log_path, "/stars/centroids/GAUSSFIT")
    records = _payloads(out, "/stars/brightest/GAUSSFIT")
    namespace: dict[str, Any] = {}
    exec(STAGES_SOURCE, namespace)
    for record, frame in zip(records, centroids, strict=True):
        jsonschema.validate(record, namespace["SCHEMA"])  # an independent checker agrees with the writer's
        fluxes = [s["flux"] for s in frame["stars"] if s["snr"] >= 5]
        assert record["flux"] == max(fluxes) and record["frame"] == frame["frame"]
        assert record["method"] == "GAUSSFIT"
    with LogReader(out) as log:
        last = log.provenance()[-1]
    assert last.stage == "brightest_flux" and last.channels == ["/stars/brightest/GAUSSFIT"]
    assert last.parameters == {"stage_version": "2.1", "function": f"{MODULE}:brightest_flux",
                               "input": "/stars/centroids/GAUSSFIT", "options": {"min_snr": 5, "pid_dir": ""}}
    assert verify_log(out).ok


def test_a_stage_runs_on_a_time_slice_and_records_the_range(stage_folder: Path, centroid_log_path: Path,
                                                             tmp_path: Path) -> None:
    brightest = _stage(stage_folder, "brightest_flux")
    out = tmp_path / "slice.mcap"
    summary = run_stage(brightest, centroid_log_path, out, options={"min_snr": 5}, workers=1,
                        input_topic="/stars/centroids/GAUSSFIT", start="frame:10", end="frame:30")
    assert summary.to_dict()["records"] == {"/stars/brightest/GAUSSFIT": 20}
    records = _payloads(out, "/stars/brightest/GAUSSFIT")
    assert [r["frame"] for r in records] == list(range(10, 30))
    with LogReader(out) as log:
        assert log.channel("/stars/centroids/GAUSSFIT").message_count == 80  # the input is whole
        last = log.provenance()[-1]
    assert last.stage == "brightest_flux"
    assert (last.parameters["range"]["start"], last.parameters["range"]["end"]) == ("frame:10", "frame:30")
    with pytest.raises(InvalidParameterError):
        run_stage(brightest, centroid_log_path, tmp_path / "none.mcap", input_topic="/stars/centroids/GAUSSFIT",
                  start="frame:30", end="frame:10")


def test_several_matching_channels_need_the_input_named(stage_folder: Path, centroid_log_path: Path,
                                                        tmp_path: Path) -> None:
    with pytest.raises(InvalidParameterError, match=r"several centroids channels .*GAUSSFIT.*--input"):
        run_stage(_stage(stage_folder, "brightest_flux"), centroid_log_path, tmp_path / "out.mcap")
    with pytest.raises(InvalidParameterError, match="has schema 'foxglove.RawImage'"):
        run_stage(_stage(stage_folder, "brightest_flux"), centroid_log_path, tmp_path / "out.mcap",
                  input_topic="/camera/image")
    with pytest.raises(InvalidParameterError, match=r"output topics \['/stars/bad', '/stars/bad'\] collide"):
        run_stage(_stage(stage_folder, "bad_record"), centroid_log_path, tmp_path / "out.mcap", input_topic="all")
    assert not list(tmp_path.iterdir())


def test_input_all_reads_each_matching_channel_in_turn(stage_folder: Path, centroid_log_path: Path,
                                                       tmp_path: Path) -> None:
    brightest = _stage(stage_folder, "brightest_flux")
    summary = run_stage(brightest, centroid_log_path, tmp_path / "all.mcap", input_topic="all", workers=2)
    assert summary.to_dict()["records"] == {"/stars/brightest/NONE": 80, "/stars/brightest/GAUSSFIT": 80}
    for method in ("NONE", "GAUSSFIT"):
        run_stage(brightest, centroid_log_path, tmp_path / f"{method}.mcap", input_topic=f"/stars/centroids/{method}")
        assert _payloads(tmp_path / "all.mcap", f"/stars/brightest/{method}") == \
            _payloads(tmp_path / f"{method}.mcap", f"/stars/brightest/{method}")
    with LogReader(tmp_path / "all.mcap") as log:
        assert log.provenance()[-1].parameters["input"] == ["/stars/centroids/NONE", "/stars/centroids/GAUSSFIT"]


def test_workers_give_the_same_bytes_from_worker_processes(stage_folder: Path, centroid_log_path: Path,
                                                           tmp_path: Path) -> None:
    brightest = _stage(stage_folder, "brightest_flux")
    pids = tmp_path / "pids"
    pids.mkdir()
    outputs = []
    for workers in (1, 2, 2):
        outputs.append(tmp_path / f"w{workers}-{len(outputs)}.mcap")
        run_stage(brightest, centroid_log_path, outputs[-1], options={"pid_dir": str(pids)}, workers=workers,
                  input_topic="/stars/centroids/NONE")
    assert filecmp.cmp(outputs[0], outputs[1], shallow=False)  # --workers 2 == --workers 1
    assert filecmp.cmp(outputs[1], outputs[2], shallow=False)  # a rerun
    assert {int(p.name) for p in pids.iterdir()} - {os.getpid()}, "no record came from a worker process"


def test_an_image_stage_gets_frames_and_its_required_option(stage_folder: Path, sim_log: Path, tmp_path: Path) -> None:
    pixel_sum = _stage(stage_folder, "pixel_sum")
    with pytest.raises(InvalidParameterError, match=r"needs the option\(s\) \['scale'\]"):
        run_stage(pixel_sum, sim_log, tmp_path / "out.mcap")
    run_stage(pixel_sum, sim_log, tmp_path / "out.mcap", options={"scale": 2})
    with LogReader(sim_log) as log:
        sums = [int(image.sum()) * 2 for _, _, image in log.frames()]
    records = _payloads(tmp_path / "out.mcap", "/camera/sum")
    assert [r["sum"] for r in records] == sums and records[0]["shape"] == [48, 64]
    assert [r["frame"] for r in records] == list(range(len(sums)))


def test_a_record_that_does_not_match_its_schema_is_an_error_naming_the_field(
        stage_folder: Path, centroid_log_path: Path, tmp_path: Path) -> None:
    with pytest.raises(InvalidInputError, match=r"'/stars/bad' .*\$\.flux: expected number, got str"):
        run_stage(_stage(stage_folder, "bad_record"), centroid_log_path, tmp_path / "out.mcap",
                  input_topic="/stars/centroids/NONE")
    assert not list(tmp_path.iterdir())  # no output, no partial file


@pytest.mark.parametrize("workers", [1, 2])
def test_a_failing_function_is_named_with_its_message(stage_folder: Path, centroid_log_path: Path, tmp_path: Path,
                                                      workers: int) -> None:
    with pytest.raises(StageFunctionError, match=r"stage 'failing' on '/stars/centroids/NONE' message 3 "
                                                 r"\(log_time \d+\): ZeroDivisionError: boom"):
        run_stage(_stage(stage_folder, "failing"), centroid_log_path, tmp_path / "out.mcap", workers=workers)
    assert not list(tmp_path.iterdir())


def test_options_are_checked(stage_folder: Path, centroid_log_path: Path, tmp_path: Path) -> None:
    brightest = _stage(stage_folder, "brightest_flux")
    with pytest.raises(InvalidParameterError, match=r"unknown option\(s\) \['min_snrr'\].*\['min_snr', 'pid_dir'\]"):
        run_stage(brightest, centroid_log_path, tmp_path / "o.mcap", options={"min_snrr": 1})
    with pytest.raises(InvalidParameterError, match="JSON values"):
        run_stage(brightest, centroid_log_path, tmp_path / "o.mcap", options={"min_snr": float("nan")})


def test_declarations_are_checked() -> None:
    def function(message: Any, *, k: int = 1) -> None:
        return None

    with pytest.raises(InvalidParameterError, match="pattern"):
        stage(name="s", version="1", reads="image", writes={"/s": {"type": "string", "pattern": "a+"}})(function)
    with pytest.raises(InvalidParameterError, match="lower-case"):
        stage(name="Bad Name", version="1", reads="image", writes={"/s": {}})
    with pytest.raises(InvalidParameterError, match="must start with '/'"):
        stage(name="s", version="1", reads="image", writes={"s": {}})(function)
    with pytest.raises(InvalidParameterError, match="one positional"):
        stage(name="s", version="1", reads="image", writes={"/s": {}})(lambda a, b: None)
    declared = stage(name="s", version="1", reads="image", writes={"/s": {}})(function)
    assert declared.options == {"k": 1} and declared(None) is None and not declared.importable()


# ---------------------------------------------------------------- run configs
def _config(tables: str, folder: Path) -> PipelineConfig:
    path = folder / "p.toml"
    path.write_text(tables, encoding="utf-8")
    from starlog.pipeline import load_config

    return load_config(path)


def test_run_with_custom_stages_equals_the_stages_one_by_one(stage_folder: Path, tmp_path: Path) -> None:
    sim = tmp_path / "sim.mcap"
    simulate_log(small_config(n_frames=40), sim)
    config = _config(f'[centroid]\nmethods = ["NONE", "GAUSSFIT"]\n'
                     f'[stages.bright]\nuses = "{MODULE}:brightest_flux"\ninput_topic = "/stars/centroids/GAUSSFIT"\n'
                     f'min_snr = 5\n'
                     f'[stages.kilo]\nuses = "{MODULE}:kilo_flux"\nthreshold = 20000\n', stage_folder)
    (tmp_path / "run").mkdir()
    (tmp_path / "steps").mkdir()
    result = run_pipeline(sim, tmp_path / "run" / "out.mcap", config, workers=2)
    assert [name for name, _ in result.stages] == ["centroid", "bright", "kilo"]
    a, b, c = (tmp_path / "steps" / p.name for p in result.layers)
    assert c.name == "out.mcap"
    centroid_log(sim, a, methods=["NONE", "GAUSSFIT"], workers=1)
    run_stage(_stage(stage_folder, "brightest_flux"), a, b, options={"min_snr": 5},
              input_topic="/stars/centroids/GAUSSFIT")
    run_stage(_stage(stage_folder, "kilo_flux"), b, c, options={"threshold": 20000})
    for layer in result.layers:
        assert filecmp.cmp(layer, tmp_path / "steps" / layer.name, shallow=False), layer.name
    bright = _payloads(c, "/stars/brightest/GAUSSFIT")
    kilo = _payloads(c, "/stars/kilo_flux")
    assert [k["kflux"] for k in kilo] == [b["flux"] / 1000 for b in bright]
    frames = [f["frame"] for f in _payloads(c, "/stars/bright_frames")]
    assert frames == [b["frame"] for b in bright if b["flux"] > 20000]


def test_a_run_whose_stage_fails_leaves_only_its_input(stage_folder: Path, tmp_path: Path) -> None:
    """A stage that fails: neither its output, its temporary file nor the layers of the stages before it
    are left."""
    sim = tmp_path / "sim.mcap"
    simulate_log(small_config(n_frames=20), sim)
    config = _config(f'[centroid]\nmethods = ["NONE"]\n[stages.f]\nuses = "{MODULE}:failing"\n', stage_folder)
    with pytest.raises(StageFunctionError, match="boom"):
        run_pipeline(sim, tmp_path / "run.mcap", config, workers=1)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sim.mcap"]


@pytest.mark.parametrize(("tables", "message"), [
    ('[stages.x]\nmin_snr = 1\n', r'\[stages.x\] needs uses = "package.module:function"'),
    ('[stages.x]\nuses = "no_such_module_here:f"\n', r"\[stages.x\]: uses = .*cannot import 'no_such_module_here'"),
    (f'[stages.x]\nuses = "{MODULE}:SCHEMA"\n', "is not a declared stage"),
    (f'[stages.x]\nuses = "{MODULE}:brightest_flux"\nmin_snrr = 1\n',
     r"\[stages.x\]: unknown option\(s\) \['min_snrr'\]"),
    (f'[stages.x]\nuses = "{MODULE}:brightest_flux"\ninput = 3\n', "input_topic must be a topic"),
    ('[stages.x]\nuses = "not_installed_stage"\n', "no installed stage named 'not_installed_stage'"),
    ('[stage.x]\nuses = "a:b"\n', r"unknown table\(s\) \['stage'\]"),
])
def test_config_errors_name_the_table(stage_folder: Path, tables: str, message: str) -> None:
    with pytest.raises(InvalidParameterError, match=message):
        _config(tables, stage_folder)


# ---------------------------------------------------------------- the docs' example, as a user runs it
def _block(language: str, containing: str) -> str:
    blocks = [b for b in re.findall(rf"```{language}\n(.*?)```", SECTION, flags=re.S) if containing in b]
    assert len(blocks) == 1, f"the docs' own-stage example has no single {language} block with {containing!r}"
    return blocks[0]


def _starlog(args: str, cwd: Path, *, installed: bool = False) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": str(cwd)} if installed else {k: v for k, v in os.environ.items()
                                                                     if k != "PYTHONPATH"}
    return subprocess.run([str(STARLOG), *shlex.split(args)], cwd=cwd, env=env, capture_output=True, text=True,
                          check=False, timeout=600)


@pytest.mark.slow
def test_the_readme_stage_runs_from_its_config_and_as_an_installed_command(tmp_path: Path) -> None:
    source = _block("python", "@stage(")
    (tmp_path / "flux_fwhm.py").write_text(source, encoding="utf-8")
    (tmp_path / "flux_fwhm.toml").write_text(_block("toml", "[stages.flux_fwhm]"), encoding="utf-8")
    simulate_log(small_config(n_frames=48), tmp_path / "demo.mcap")
    # "installed": a dist-info folder on the path is what importlib.metadata finds for an installed package
    dist = tmp_path / "flux_fwhm_example-1.0.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: flux-fwhm-example\nVersion: 1.0\n")
    (dist / "entry_points.txt").write_text("[starlog.stages]\nflux_fwhm = flux_fwhm:flux_fwhm\n"
                                           "broken = flux_fwhm_missing_module:stage\ncentroid = flux_fwhm:flux_fwhm\n")
    run_command = _block("bash", "starlog run ").strip()
    installed_command = _block("bash", "starlog flux_fwhm ").strip()

    done = _starlog(run_command.removeprefix("starlog "), tmp_path)  # the module is found beside the config
    assert done.returncode == 0, done.stderr
    done = _starlog(installed_command.removeprefix("starlog "), tmp_path, installed=True)
    assert done.returncode == 0, done.stderr
    run_output = Path(tmp_path / shlex.split(run_command)[shlex.split(run_command).index("-o") + 1])

    # outputs validate against the declared schema; the provenance names the stage and its version
    namespace: dict[str, Any] = {"__name__": "flux_fwhm_check"}
    exec(source, namespace)
    records = _payloads(run_output, "/stars/flux_fwhm")
    assert len(records) == 48 and sum(len(r["stars"]) for r in records) > 48
    for record in records:
        jsonschema.validate(record, namespace["SCHEMA"])
        assert all(1.5 < s["fwhm"] < 6 for s in record["stars"])  # the simulator's PSF: sigma 1.2 px, FWHM 2.8
    with LogReader(run_output) as log:
        last = log.provenance()[-1]
    assert (last.stage, last.parameters["stage_version"], last.parameters["options"]) == \
        ("flux_fwhm", "1.0", {"half": 4, "min_snr": 20})

    # a rerun with two workers, and the stages one by one (the installed command), give the same bytes
    layers = sorted(tmp_path.glob(f"{run_output.stem}.*mcap"))
    written = {layer.name: layer.read_bytes() for layer in layers}
    assert len(written) == 2  # the centroid layer, and the stage's layer (the run's output)
    assert _starlog(f"{run_command.removeprefix('starlog ')} --workers 2", tmp_path).returncode == 0
    assert {layer.name: layer.read_bytes() for layer in layers} == written
    centroid_layer = next(name for name in written if name != run_output.name)
    assert _starlog(f"centroid demo.mcap -o {centroid_layer} --method GAUSSFIT --workers 1 --force",
                    tmp_path).returncode == 0
    done = _starlog(f"flux_fwhm {centroid_layer} -o {run_output.name} --set min_snr=20 --workers 2 --force", tmp_path,
                    installed=True)
    assert done.returncode == 0, done.stderr
    assert {layer.name: layer.read_bytes() for layer in layers} == written

    # starlog --help lists installed stages without importing them; a broken one fails alone, clearly
    done = _starlog("--help", tmp_path, installed=True)
    assert done.returncode == 0 and re.search(r"Installed stages.*\n\s+broken .*\n\s+flux_fwhm ", done.stdout)
    assert "the stage 'centroid' installed by flux-fwhm-example 1.0 is hidden by the built-in command" in done.stderr
    done = _starlog("broken demo.mcap -o x.mcap", tmp_path, installed=True)
    assert done.returncode == 1 and "Traceback" not in done.stderr
    assert "the stage 'broken' registered by flux-fwhm-example 1.0 (flux_fwhm_missing_module:stage) cannot be " \
           "loaded: ModuleNotFoundError" in done.stderr
    assert _starlog("flux_fwhm --help", tmp_path, installed=True).stdout.count("min_snr=10.0") == 1
    assert not (tmp_path / "x.mcap").exists()
