"""``starlog live`` as a user runs it: on a log another process writes at its camera's rate, on a folder being
filled, on a camera stream; watched by a Foxglove WebSocket client; stopped by Ctrl-C and SIGTERM; on a log
cut off mid-chunk.

The oracle is ``starlog run`` on the finished base with the same config: every live layer holds the same
messages as the layer ``run`` writes of the same name. Processes: after the run, none it started is left.
"""

from __future__ import annotations

import json
import multiprocessing
import os
import re
import signal
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

import starlog
from starlog import topics
from starlog.io import LogReader
from starlog.io.mcap_file import McapFile
from starlog.io.recover import recover_log
from starlog.io.verify import verify_log
from starlog.live import LIVE_METADATA, base_path, write_at_camera_rate
from starlog.pipeline import layer_paths, load_config, stage_steps
from starlog.stages import simulate_log
from tests.helpers import small_config
from tests.test_kill import assert_nothing_left, descendants

PY = [sys.executable, "-m", "starlog"]
CONFIG = """\
[centroid]
methods = ["NONE", "GAUSSFIT"]
mode = "tracking"
acquire_every = 25
[track]
methods = ["GAUSSFIT"]
models = ["STATIC", "CONSTANT_VELOCITY"]
[track.tracker]
sigma_floor = 0.05
"""
SIM = ["--size", "64x48", "--stars", "3", "--seed", "2", "--jitter", "7:0.1", "-q"]


@pytest.fixture
def config(tmp_path: Path) -> Path:
    path = tmp_path / "live.toml"
    path.write_text(CONFIG)
    return path


class Process:
    """A starlog command in the background, its stderr collected line by line; every process it starts carries
    a marker in its environment (:func:`tests.test_kill.assert_nothing_left`)."""

    def __init__(self, args: list[str], cwd: Path, marker: str) -> None:
        env = {**os.environ, "STARLOG_TEST_PROCESS_MARKER": marker}
        self.marker = marker
        self.popen = subprocess.Popen(PY + args, cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                      env=env, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
        self.lines: list[str] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.popen.stderr is not None
        for line in self.popen.stderr:
            self.lines.append(line.rstrip("\n"))

    def wait_for(self, text: str, timeout: float = 120) -> str:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            found = next((line for line in self.lines if text in line), None)
            if found is not None:
                return found
            assert self.popen.poll() is None, f"exited before saying {text!r}:\n" + "\n".join(self.lines)
            time.sleep(0.05)
        raise AssertionError(f"never said {text!r}:\n" + "\n".join(self.lines))

    def finish(self, timeout: float = 300, *, stopped_by: int | None = None) -> str:
        """The command's stdout once it has ended (with status 0, unless it was killed; a command ``stopped_by`` a
        signal it handles, e.g. ``simulate --realtime`` at Ctrl-C, finishes its output and then ends of the signal,
        as every starlog command does)."""
        assert self.popen.stdout is not None
        out = self.popen.stdout.read()  # stderr is the reader thread's
        self.popen.wait(timeout=timeout)
        self._reader.join(timeout=5)
        self.popen.stdout.close()
        if self.popen.stderr is not None:
            self.popen.stderr.close()
        ending = {0, -signal.SIGKILL} | ({-stopped_by} if stopped_by is not None else set())
        assert self.popen.returncode in ending, "\n".join(self.lines)
        return out


class FoxgloveClient:
    """A Foxglove WebSocket client (subprotocol ``foxglove.sdk.v1``) on a thread: it subscribes to ``topics`` as
    they are advertised and keeps each message's ``(log_time, payload)``."""

    def __init__(self, url: str, topics: set[str]) -> None:
        self.url, self.topics = url, topics
        self.advertised: dict[str, dict[str, Any]] = {}
        self.received: dict[str, list[tuple[int, bytes]]] = {t: [] for t in topics}
        self._by_subscription: dict[int, str] = {}
        self._stop = threading.Event()
        self.error: BaseException | None = None
        self.control: list[dict[str, Any]] = []
        self._thread = threading.Thread(target=self._guarded, daemon=True)
        self._thread.start()

    def _guarded(self) -> None:
        try:
            self._run()
        except BaseException as err:  # handed to the test by close()
            self.error = err

    def _run(self) -> None:
        from websockets.exceptions import ConnectionClosed
        from websockets.sync.client import connect

        with connect(self.url, subprotocols=["foxglove.sdk.v1"], max_size=None) as ws:
            while not self._stop.is_set():
                try:
                    message = ws.recv(timeout=0.2)
                except TimeoutError:
                    continue
                except ConnectionClosed:  # the server stopped at the end of the run
                    return
                if isinstance(message, str):
                    self._control(ws, json.loads(message))
                elif message[0] == 0x01:  # message data: subscription id, log time, payload
                    subscription, log_time = struct.unpack_from("<IQ", message, 1)
                    self.received[self._by_subscription[subscription]].append((log_time, bytes(message[13:])))

    def _control(self, ws: Any, message: dict[str, Any]) -> None:
        self.control.append(message)
        unknown = re.fullmatch(r"Unknown channel ID: (\d+)", str(message.get("message", "")))
        if message.get("op") == "status" and unknown:  # foxglove-sdk 0.30 may answer so a subscription sent at
            time.sleep(0.05)                            # once on its channel's advertisement: subscribe again
            again = [{"id": s, "channelId": int(unknown[1])} for s, topic in self._by_subscription.items()
                     if self.advertised[topic]["id"] == int(unknown[1])]
            ws.send(json.dumps({"op": "subscribe", "subscriptions": again}))
        if message.get("op") != "advertise":
            return
        wanted = []
        for channel in message["channels"]:
            self.advertised[channel["topic"]] = channel
            if channel["topic"] in self.topics:
                subscription = len(self._by_subscription) + 1
                self._by_subscription[subscription] = channel["topic"]
                wanted.append({"id": subscription, "channelId": channel["id"]})
        if wanted:
            ws.send(json.dumps({"op": "subscribe", "subscriptions": wanted}))

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=10)
        if self.error is not None:
            raise self.error


def _messages(path: Path) -> dict[str, list[tuple[int, Any]]]:
    """Every message of the file, per topic; an attitude without its ``solver_ms`` (the solver's own wall time,
    which differs between any two runs)."""
    with LogReader(path, chain=False) as log:
        out: dict[str, list[tuple[int, Any]]] = {}
        for c in log.channels():
            if c.topic.startswith("/attitude/"):
                out[c.topic] = [(m.log_time, {k: v for k, v in m.payload.items() if k != "solver_ms"})
                                for m in log.messages(c.topic)]
            else:
                out[c.topic] = [(m.log_time, bytes(m.data)) for _, _, m in log.raw_messages([c.topic])]
        return out


def _layers(output: Path, config: Path) -> list[Path]:
    return layer_paths(output, [name for name, _ in stage_steps(load_config(config))])


def assert_live_is_replay(tmp_path: Path, base: Path, live_output: Path, config: Path) -> None:
    """``run`` on the finished base gives the messages of every live layer; the live chain verifies clean."""
    replay = tmp_path / "replay.mcap"
    starlog.run(base, replay, config=config, workers=1, report=False)  # ``starlog run``, in this process
    for live_layer, run_layer in zip(_layers(live_output, config), _layers(replay, config), strict=True):
        assert _messages(live_layer) == _messages(run_layer), live_layer.name
    assert verify_log(live_output).ok


def _frames(path: Path) -> int:
    with LogReader(path) as log:
        return log.channel("/camera/image").message_count


def test_live_follows_a_log_written_at_camera_rate_and_serves_it_to_foxglove(tmp_path: Path, config: Path) -> None:
    source = tmp_path / "camera.mcap"
    writer = Process(["simulate", "-o", str(source), "--frames", "400", "--fps", "100", "--realtime", *SIM],
                     tmp_path, "live-writer")
    live = Process(["live", str(source), "-o", "out.mcap", "--config", str(config), "--port", "0"], tmp_path,
                   "live-follow")
    url = live.wait_for("serving Foxglove at").split()[3]
    watched = {"/camera/image", "/stars/annotations", "/stars/centroids/GAUSSFIT", "/track/GAUSSFIT/STATIC"}
    client = FoxgloveClient(url, watched)
    live.finish()
    writer.finish()
    client.close()
    assert_nothing_left("live-follow", set())
    output = tmp_path / "out.mcap"
    assert {"/stars/detections", "/stars/centroids/NONE", "/track/GAUSSFIT/CONSTANT_VELOCITY", "/live/status",
            "/camera/frame", "/sim/truth"} | watched <= set(client.advertised)
    assert client.advertised["/track/GAUSSFIT/STATIC"]["schemaName"] == "starlog.Tracks"
    layers = _messages(tmp_path / "out.1-centroid.mcap")
    for topic in ("/stars/annotations", "/stars/centroids/GAUSSFIT"):  # the bytes the layer holds, every frame
        assert client.received[topic] == layers[topic] and len(layers[topic]) == 400
    tracks = dict(client.received["/track/GAUSSFIT/STATIC"])  # marked with the brightest track so far
    assert sorted(tracks) == [t for t, _ in _messages(output)["/track/GAUSSFIT/STATIC"]]
    images = [t for t, _ in client.received["/camera/image"]]  # published as read, some before the client came
    with LogReader(source) as log:
        assert images == [t for _, t, _ in log.frames()][-len(images):] and len(images) > 200
    assert_live_is_replay(tmp_path, source, output, config)


def _write_frames(folder: Path, images: list[np.ndarray], fps: float) -> None:
    """Camera software: PNG files at ``fps``, the fifth written in two halves half a second apart, and one file
    that is no image."""
    for n, image in enumerate(images):
        ok, png = cv2.imencode(".png", image)
        assert ok
        path = folder / f"frame_{n}.png"
        if n == 5:
            with open(path, "wb") as f:
                f.write(png.tobytes()[: len(png) // 2])
                f.flush()
                time.sleep(0.5)
                f.write(png.tobytes()[len(png) // 2:])
        else:
            path.write_bytes(png.tobytes())
        if n == 30:
            (folder / "frame_30b.png").write_bytes(b"not an image")
        time.sleep(1 / fps)


def test_live_processes_each_new_file_of_a_folder_once_whole(tmp_path: Path, config: Path) -> None:
    sim = tmp_path / "sim.mcap"
    simulate_log(small_config(n_frames=300, seed=4), sim)
    with LogReader(sim) as log:
        images = [np.array(image) for _, _, image in log.frames()]
    folder = tmp_path / "frames"
    folder.mkdir()
    writer = multiprocessing.get_context("spawn").Process(target=_write_frames, args=(folder, images, 200.0))
    writer.start()
    live = Process(["live", str(folder), "-o", "out.mcap", "--config", str(config), "--no-server", "--fps", "100",
                    "--idle-timeout", "3"], tmp_path, "live-folder")
    live.finish()
    writer.join()
    assert writer.exitcode == 0
    output = tmp_path / "out.mcap"
    base = base_path(output)
    assert _frames(base) == 300
    assert any("frame_30b.png cannot be read" in line for line in live.lines)
    with LogReader(base) as log:
        assert [m.payload["source"] for m in log.messages("/camera/frame")][4:7] == [
            "frame_4.png", "frame_5.png", "frame_6.png"]
        assert np.array_equal(next(image for n, _, image in log.frames() if n == 5), images[5])
    assert_live_is_replay(tmp_path, base, output, config)


def test_live_records_a_camera_stream_and_processes_it(tmp_path: Path, config: Path) -> None:
    sim = tmp_path / "sim.mcap"
    simulate_log(small_config(n_frames=290, seed=5), sim)
    video = tmp_path / "camera.avi"
    out = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 100.0, (64, 48), False)
    with LogReader(sim) as log:
        for _, _, image in log.frames():
            out.write(np.clip(np.asarray(image, np.float64) / 8, 0, 255).astype(np.uint8))
    out.release()
    live = Process(["live", "--camera", str(video), "-o", "out.mcap", "--config", str(config), "--no-server"],
                   tmp_path, "live-camera")
    live.finish()
    output = tmp_path / "out.mcap"
    assert _frames(base_path(output)) == 290
    assert_live_is_replay(tmp_path, base_path(output), output, config)


def _wait_for_flushed_frames(folder: Path, size: int = 20_000, timeout: float = 300) -> None:
    """Wait until the centroid layer being written has flushed ``size`` bytes (frames processed, however slow the
    machine)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if any(p.stat().st_size >= size for p in folder.glob(".out.1-centroid.mcap.*.partial")):
            return
        time.sleep(0.1)
    raise AssertionError("the centroid layer never grew")


@pytest.mark.parametrize("stop", [signal.SIGINT, signal.SIGTERM])
def test_live_stopped_mid_run_closes_valid_layers_and_leaves_nothing_running(tmp_path: Path, config: Path,
                                                                          stop: signal.Signals) -> None:
    source = tmp_path / "camera.mcap"
    writer = Process(["simulate", "-o", str(source), "--frames", "3000", "--fps", "100", "--realtime", *SIM],
                     tmp_path, "live-writer-long")
    live = Process(["live", str(source), "-o", "out.mcap", "--config", str(config), "--port", "0"], tmp_path,
                   f"live-stop-{stop.name}")
    _wait_for_flushed_frames(tmp_path)
    tracked = descendants(live.popen.pid)
    live.popen.send_signal(stop)
    live.finish()
    assert_nothing_left(f"live-stop-{stop.name}", tracked)
    writer.popen.send_signal(signal.SIGINT)
    writer.finish(stopped_by=signal.SIGINT)
    output = tmp_path / "out.mcap"
    base = base_path(output)  # the part of the log read: the log itself was still being written
    assert 256 <= _frames(base) < 3000
    with LogReader(tmp_path / "out.1-centroid.mcap") as log:
        record = dict(log.metadata(LIVE_METADATA)[0][1])
    assert record["end"] == "stopped" and int(record["frames_done"]) == _frames(base), (record, live.lines)
    assert_live_is_replay(tmp_path, base, output, config)


def test_live_killed_leaves_its_layers_as_far_as_flushed_and_nothing_running(tmp_path: Path, config: Path) -> None:
    source = tmp_path / "camera.mcap"
    writer = Process(["simulate", "-o", str(source), "--frames", "3000", "--fps", "100", "--realtime", *SIM],
                     tmp_path, "live-writer-killed")
    live = Process(["live", str(source), "-o", "out.mcap", "--config", str(config), "--no-server"], tmp_path,
                   "live-killed")
    _wait_for_flushed_frames(tmp_path)
    tracked = descendants(live.popen.pid)
    live.popen.kill()
    live.popen.wait(timeout=30)
    live.finish()
    assert_nothing_left("live-killed", tracked)
    writer.popen.send_signal(signal.SIGINT)
    writer.finish(stopped_by=signal.SIGINT)
    partial = next(tmp_path.glob(".out.1-centroid.mcap.*.partial"))  # flushed at least every half second
    report = recover_log(partial, tmp_path / "recovered.mcap")
    assert verify_log(tmp_path / "recovered.mcap").ok and report.kept_by_topic["/stars/centroids/GAUSSFIT"] > 0


@pytest.mark.parametrize("removed", [False, True], ids=["cut", "cut and removed"])
def test_live_on_a_log_cut_off_mid_chunk_ends_with_the_frames_before_the_cut(tmp_path: Path, config: Path,
                                                                             removed: bool) -> None:
    whole = tmp_path / "whole.mcap"
    simulate_log(small_config(n_frames=320, seed=6), whole, chunk_per_frame=True)
    with McapFile(whole) as file:
        chunks = sorted(file.summary.chunk_indexes, key=lambda c: c.chunk_start_offset)
    cut = chunks[3 * 300].chunk_start_offset + chunks[3 * 300].chunk_length // 2  # inside frame 300's image chunk
    source = tmp_path / "cut.mcap"
    source.write_bytes(whole.read_bytes()[:cut])
    live = Process(["live", str(source), "-o", "out.mcap", "--config", str(config), "--no-server",
                    "--idle-timeout", "1"], tmp_path, "live-cut")
    if removed:  # the source vanishes: what live read is still there to close the layers on
        live.wait_for("learning the centroid parameters")
        source.unlink()
    live.finish()
    assert any("stopped growing 1 s ago without its footer" in line and "unfinished record" in line
               and ("its file was removed" in line) == removed for line in live.lines), live.lines
    output = tmp_path / "out.mcap"
    assert _frames(base_path(output)) == 300
    assert_live_is_replay(tmp_path, base_path(output), output, config)


def test_live_solves_the_attitude_of_each_frame_as_run_does(tmp_path: Path) -> None:
    pytest.importorskip("tetra3")
    from starlog.sim import Jitter, SimulationConfig

    whole = tmp_path / "sky.mcap"
    simulate_log(SimulationConfig(width=384, height=384, sky_attitude=(120.0, -30.0, 40.0), fov_deg=10.0,
                                  magnitude_limit=7.0, n_frames=60, fps=50.0, jitter=(Jitter(5.0, 0.5),), seed=2),
                 whole, chunk_per_frame=True)
    config = tmp_path / "solve.toml"
    config.write_text('[centroid]\nmethods = ["GAUSSFIT", "MOMENT"]\nphase_correction = "off"\nmode = "tracking"\n'
                      '[solve]\ncentroids = "all"\n[solve.options]\ntimeout_ms = 200\n')
    source = tmp_path / "camera.mcap"
    writer = threading.Thread(target=write_at_camera_rate, args=(whole, source))
    writer.start()
    live = Process(["live", str(source), "-o", "out.mcap", "--config", str(config), "--no-server"], tmp_path,
                   "live-solve")
    live.finish()
    writer.join()
    output = tmp_path / "out.mcap"
    messages = _messages(output)
    assert len(messages["/attitude/GAUSSFIT"]) == 60
    with LogReader(output) as log:
        solved = [m.payload for m in log.messages("/attitude/GAUSSFIT")]
    assert sum(a["solved"] for a in solved) >= 55 and all("error_x_arcsec" in a for a in solved if a["solved"])
    assert_live_is_replay(tmp_path, source, output, config)
    records = []
    for path in (output, tmp_path / "replay.mcap"):  # the stage's record: each method's figures, the sky's evidence
        with LogReader(path, chain=False) as log:
            records.append({k: json.loads(v) for k, v in log.metadata(topics.SOLVE_METADATA)[0][1].items()})
    assert records[0] == records[1] and set(records[0]["sky_evidence"]) == {"GAUSSFIT", "MOMENT"}


def assert_same_plan(tmp_path: Path, source: Path, options: list[str]) -> tuple[dict[str, Any], list[str]]:
    """``live`` and ``run`` of ``source`` with ``options`` (--config): the same stages, trusted method and layers,
    each holding the same messages and provenance; live's result and its status lines."""
    live = Process(["live", str(source), "-o", "out.mcap", "--no-server", "--json", *options], tmp_path,
                   "live-plan")
    ran = json.loads(subprocess.run(PY + ["run", str(source), "-o", "replay.mcap", "--workers", "1", "-q", "--json",
                                          *options], cwd=tmp_path, check=True, capture_output=True, text=True,
                                    timeout=600).stdout)  # while live runs: neither reads what the other writes
    lived = json.loads(live.finish())
    assert lived["trusted"] == ran["trusted"] and ran["trusted"] is not None
    assert [s["stage"] for s in lived["stages"]] == [s["stage"] for s in ran["stages"]]
    assert f"track {ran['trusted']['method']}" in [s["stage"] for s in lived["stages"]]
    assert [Path(p).name.replace("out", "replay", 1) for p in lived["layers"]] == [Path(p).name for p in ran["layers"]]
    for live_layer, run_layer in zip(lived["layers"], ran["layers"], strict=True):
        assert _messages(tmp_path / live_layer) == _messages(tmp_path / run_layer), live_layer
        with LogReader(tmp_path / live_layer, chain=False) as a, LogReader(tmp_path / run_layer, chain=False) as b:
            assert a.provenance()[-1].parameters == b.provenance()[-1].parameters, live_layer
    assert verify_log(tmp_path / "out.mcap").ok
    return lived, live.lines


def _camera_log(tmp_path: Path, **simulation: Any) -> Path:
    """A finished log as a camera's recorder writes it (its metadata first, a chunk per frame)."""
    whole, source = tmp_path / "sim.mcap", tmp_path / "camera.mcap"
    simulate_log(small_config(**simulation), whole, chunk_per_frame=True)
    write_at_camera_rate(whole, source, speed=1000.0)
    return source


def test_live_runs_the_plan_of_run_with_the_built_in_config(tmp_path: Path) -> None:
    """Without --config: every method measured, NONE and the trusted method tracked (decided on the centroid
    layer when the source ends, as run decides it), compensate as far as the log is long; the same layers."""
    lived, lines = assert_same_plan(tmp_path, _camera_log(tmp_path, n_frames=300, seed=7), [])
    assert lived["trusted"]["method"] == "GAUSSFIT"  # no evidence in 3 stars: the method tracked live meanwhile
    assert not any(line.startswith("running track") for line in lines), lines


def test_live_tracks_the_method_the_evidence_names_when_the_source_ends(tmp_path: Path) -> None:
    """Tracked live as BICUBIC (the first method but NONE), "trusted" is MOMENT by the frame-to-frame evidence:
    MOMENT's track layer is the track stage's on the finished centroid layer, as run writes it."""
    config = tmp_path / "trusted.toml"
    config.write_text('[centroid]\nmethods = ["NONE", "BICUBIC", "MOMENT"]\nphase_correction = "off"\n'
                      '[track]\nmethods = ["trusted"]\nmodels = ["STATIC"]\n[track.tracker]\nsigma_floor = 0.05\n')
    source = _camera_log(tmp_path, width=128, height=96, n_stars=25, n_frames=120, seed=7)
    lived, lines = assert_same_plan(tmp_path, source, ["--config", str(config)])
    assert lived["trusted"]["method"] == "MOMENT" and lived["trusted"]["evidence"] == "frame-to-frame"
    assert "running track MOMENT on the finished log" in lines, lines
