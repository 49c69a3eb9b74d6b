"""Camera logs other tools write (ROS 2, ROS 1, Foxglove) and valid MCAP files without indexes.

Each foreign log is built from a simulated starlog log with the other tool's own library, so the
simulator's truth says what ``centroid`` must find: the same centroids as from the native log,
frame for frame.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from starlog.cli import cli
from starlog.errors import InvalidInputError, InvalidParameterError
from starlog.io import LogReader
from starlog import topics
from starlog.codecs.images import pixels_to_mono
from starlog.stages import simulate_log
from starlog.stages.centroid import centroid_log
from tests.foreign_logs import native_frames, write_foxglove_compressed, write_plain, write_ros1, write_ros2
from tests.helpers import small_config

METHOD = "GAUSSFIT"


@pytest.fixture(scope="module")
def native(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A simulated log and its centroids (the reference every foreign log must reproduce)."""
    d = tmp_path_factory.mktemp("native")
    sim = d / "sim.mcap"
    simulate_log(small_config(n_frames=24), sim)
    cen = d / "cen.mcap"
    centroid_log(sim, cen, methods=METHOD, options={"psf_sigma": 1.2})
    return {"sim": sim, "cen": cen, "dir": d}


def _centroids(path: Path) -> list[tuple[int, np.ndarray]]:
    with LogReader(path) as log:
        return [(m.log_time, np.array([(s["x"], s["y"]) for s in m.payload["stars"]]).reshape(-1, 2))
                for m in log.messages(topics.centroid_topic(METHOD))]


def _truth_rms(path: Path, sim: Path) -> float:
    with LogReader(sim) as log:
        truth = {m.log_time: np.array([(s["x"], s["y"]) for s in m.payload["stars"]]) for m in log.messages(topics.TRUTH)}
    errors = []
    for t, found in _centroids(path):
        for x, y in found:
            d = np.hypot(*(truth[t] - (x, y)).T).min()
            if d < 1.0:
                errors.append(d)
    return float(np.sqrt(np.mean(np.square(errors))))


def _same_centroids(foreign_cen: Path, native: dict[str, Path], atol: float = 1e-9) -> None:
    got, want = _centroids(foreign_cen), _centroids(native["cen"])
    assert [t for t, _ in got] == [t for t, _ in want]  # same frames, same times
    for (_, a), (_, b) in zip(got, want):
        np.testing.assert_allclose(a, b, rtol=0, atol=atol)
    assert _truth_rms(foreign_cen, native["sim"]) <= _truth_rms(native["cen"], native["sim"]) + atol


def _run(*args: str) -> tuple[int, str]:
    result = CliRunner().invoke(cli, list(args))
    if result.exit_code != 0:
        assert isinstance(result.exception, SystemExit), result.exception
    return result.exit_code, result.output


# ---------------------------------------------------------------- foreign image types, end to end
FOREIGN = {
    "ros2 mono16": lambda src, dst: write_ros2(src, dst),
    "ros2 mono16 big-endian": lambda src, dst: write_ros2(src, dst, big_endian=True),
    "ros2 16UC1 small chunks": lambda src, dst: write_ros2(src, dst, encoding="16UC1", chunk_size=4096),
    "ros2 png CompressedImage": lambda src, dst: write_ros2(src, dst, compressed="png"),
    "ros1 mono16": lambda src, dst: write_ros1(src, dst),
    "ros1 png CompressedImage": lambda src, dst: write_ros1(src, dst, compressed="png"),
    "foxglove png CompressedImage": lambda src, dst: write_foxglove_compressed(src, dst),
    "foxglove tiff CompressedImage": lambda src, dst: write_foxglove_compressed(src, dst, fmt="tiff"),
    "no chunks": lambda src, dst: write_plain(src, dst, use_chunking=False),
    "no message indexes": lambda src, dst: write_plain(src, dst, message_indexes=False, chunk_size=8192),
    "no summary": lambda src, dst: write_plain(src, dst, summary=False, chunk_size=8192),
    "no summary, no chunks": lambda src, dst: write_plain(src, dst, summary=False, use_chunking=False),
    "out of order, overlapping chunks": lambda src, dst: write_plain(src, dst, shuffle=True, chunk_size=4096),
    "out of order, no message indexes": lambda src, dst: write_plain(src, dst, shuffle=True, message_indexes=False),
    "summary without schemas and channels": lambda src, dst: write_plain(
        src, dst, repeat_schemas=False, repeat_channels=False, chunk_size=8192),
    "summary without channels, no message indexes, no statistics": lambda src, dst: write_plain(
        src, dst, repeat_channels=False, message_indexes=False, statistics=False, chunk_size=8192),
    "no chunks, summary without schemas": lambda src, dst: write_plain(
        src, dst, use_chunking=False, repeat_schemas=False),
}


@pytest.mark.parametrize("kind", list(FOREIGN))
def test_centroid_reads_foreign_logs_like_native_ones(kind: str, native: dict[str, Path], tmp_path: Path) -> None:
    foreign = FOREIGN[kind](native["sim"], tmp_path / "foreign.mcap")
    with LogReader(foreign) as log:
        images = [c for c in log.channels() if c.topic.startswith("/camera/image") or "compressed" in c.topic]
        assert images[0].message_count == 24 and images[0].rate_hz == pytest.approx(100.0)
    out = tmp_path / "cen.mcap"
    code, text = _run("centroid", str(foreign), "-o", str(out), "--method", METHOD, "--set", "psf_sigma=1.2",
                      "-q", "--json", "--workers", "2")
    assert code == 0, text
    summary = json.loads(text[text.index("{"):])
    assert summary["frames"] == summary["channel_messages"] == 24 and not summary["skipped_frames"]
    _same_centroids(out, native)
    with LogReader(out) as log:  # the stage's output keeps the input's channels and reads in full
        assert sum(1 for _ in log.frames(summary["image_topic"])) == 24
        record = log.provenance()[-1]
    if summary["image_topic"] != topics.IMAGE:
        assert record.parameters["image_topic"] == summary["image_topic"]
        assert any("only image channel" in n for n in summary["notes"])


def test_unusual_layouts_say_how_they_were_read(native: dict[str, Path], tmp_path: Path) -> None:
    bare = write_plain(native["sim"], tmp_path / "bare.mcap", message_indexes=False, chunk_size=8192)
    with LogReader(bare) as log:
        assert not log.fully_indexed and any("no message indexes" in n for n in log.notes)
    flat = write_plain(native["sim"], tmp_path / "flat.mcap", summary=False)
    code, text = _run("info", str(flat))
    assert code == 0 and "linear scan" in text and "starlog recover" in text and "24" in text
    loose = write_plain(native["sim"], tmp_path / "loose.mcap", use_chunking=False)
    with LogReader(loose) as log:
        assert any("outside chunks" in n for n in log.notes)
        assert [t for _, t, _ in log.frames()] == [t for t, _ in native_frames(native["sim"])]


def test_header_stamps_reach_annotations_and_info(native: dict[str, Path], tmp_path: Path) -> None:
    offset = 50_000_000  # 5 frame periods at 100 Hz
    bag = write_ros2(native["sim"], tmp_path / "late.mcap", stamp_offset_ns=offset)
    code, text = _run("info", str(bag))
    assert code == 0 and "header stamps differ from log_time" in text
    out = tmp_path / "cen.mcap"
    centroid_log(bag, out, methods=METHOD, options={"psf_sigma": 1.2})
    with LogReader(out) as log:
        for m in log.messages(topics.ANNOTATIONS):
            stamps = {c.timestamp.seconds * 10**9 + c.timestamp.nanos for c in m.payload.circles}
            assert stamps <= {m.log_time + offset}  # Foxglove pairs the circles with the image's own stamp


def test_image_topic_is_chosen_or_named(native: dict[str, Path], tmp_path: Path) -> None:
    from mcap_ros2.writer import Writer

    from tests.foreign_logs import ROS2_IMAGE

    two = tmp_path / "two.mcap"
    with open(two, "wb") as f:
        writer = Writer(f)
        schema = writer.register_msgdef("sensor_msgs/msg/Image", ROS2_IMAGE)
        for t, image in native_frames(native["sim"]):
            for topic in ("/left/image_raw", "/right/image_raw"):
                writer.write_message(topic, schema, {
                    "header": {"stamp": {"sec": 0, "nanosec": 0}, "frame_id": "cam"}, "height": image.shape[0],
                    "width": image.shape[1], "encoding": "mono16", "is_bigendian": 0, "step": 2 * image.shape[1],
                    "data": image.astype("<u2").tobytes()}, log_time=t)
        writer.finish()
    code, text = _run("centroid", str(two), "-o", str(tmp_path / "c.mcap"), "-q")
    assert code == 1 and "/left/image_raw" in text and "/right/image_raw" in text and "--image-topic" in text
    code, text = _run("centroid", str(two), "-o", str(tmp_path / "c.mcap"), "--image-topic", "/right/image_raw",
                      "--method", METHOD, "--set", "psf_sigma=1.2")
    assert code == 0 and "24 of 24 frames of /right/image_raw" in text
    _same_centroids(tmp_path / "c.mcap", native)
    with pytest.raises(InvalidParameterError, match="not an image type"):
        centroid_log(native["sim"], tmp_path / "x.mcap", image_topic=topics.TRUTH)
    code, text = _run("centroid", str(native["sim"]), "-o", str(tmp_path / "x.mcap"), "--image-topic", "/nope", "-q")
    assert code == 1 and "no channel '/nope'" in text


def test_bad_frames_stop_the_stage_or_are_named_with_skip_bad(native: dict[str, Path], tmp_path: Path) -> None:
    from mcap_ros2.writer import Writer

    from tests.foreign_logs import ROS2_COMPRESSED

    bag = tmp_path / "bad.mcap"
    times = []
    with open(bag, "wb") as f:
        writer = Writer(f)
        schema = writer.register_msgdef("sensor_msgs/msg/CompressedImage", ROS2_COMPRESSED)
        frames = [(t + k * 10**9, image) for k in range(3) for t, image in native_frames(native["sim"])]
        for i, (t, image) in enumerate(frames):  # 72 frames: enough for the parallel path
            data = b"not a png" if i == 5 else cv2.imencode(".png", image)[1].tobytes()
            writer.write_message("/camera/image", schema, {"header": {"stamp": {"sec": 0, "nanosec": 0},
                                 "frame_id": "c"}, "format": "png", "data": data}, log_time=t)
            times.append(t)
        writer.finish()
    code, text = _run("centroid", str(bag), "-o", str(tmp_path / "c.mcap"), "-q", "--method", METHOD)
    assert code == 1 and f"log_time {times[5]}" in text and "cannot be decoded" in text
    assert not (tmp_path / "c.mcap").exists()
    for workers in ("1", "2"):
        code, text = _run("centroid", str(bag), "-o", str(tmp_path / "c.mcap"), "--method", METHOD,
                          "--skip-bad", "--force", "--workers", workers)
        assert code == 0 and "71 of 72 frames" in text and f"skipped frame 5 (log_time {times[5]})" in text
        with LogReader(tmp_path / "c.mcap") as log:
            assert [m.payload["frame"] for m in log.messages(topics.DETECTIONS)] == [i for i in range(72) if i != 5]


# ---------------------------------------------------------------- pixel encodings
def test_pixel_encodings_decode_to_mono() -> None:
    rng = np.random.default_rng(2)
    grey16 = rng.integers(0, 65535, size=(6, 8), dtype=np.uint16)
    grey8 = (grey16 >> 8).astype(np.uint8)
    for encoding, data, step, big in [("mono8", grey8.tobytes(), 8, False), ("8UC1", grey8.tobytes(), 8, False),
                                      ("mono16", grey16.astype("<u2").tobytes(), 16, False),
                                      ("16UC1", grey16.astype(">u2").tobytes(), 16, True)]:
        image, note = pixels_to_mono(data, 8, 6, step, encoding, big)
        np.testing.assert_array_equal(image, grey8 if "8" in encoding else grey16)
        assert note is None
    padded = np.zeros((6, 10), np.uint8)
    padded[:, :8] = grey8
    np.testing.assert_array_equal(pixels_to_mono(padded.tobytes(), 8, 6, 10, "mono8")[0], grey8)
    rgb = np.stack([grey8, grey8 // 2, grey8 // 3], axis=2)
    image, note = pixels_to_mono(rgb.tobytes(), 8, 6, 24, "rgb8")
    np.testing.assert_array_equal(image, cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY))
    assert note and "rgb8" in note
    bgra = np.concatenate([rgb[:, :, ::-1], np.full((6, 8, 1), 255, np.uint8)], axis=2)
    np.testing.assert_array_equal(pixels_to_mono(bgra.tobytes(), 8, 6, 32, "bgra8")[0], image)
    np.testing.assert_array_equal(pixels_to_mono(rgb[:, :, ::-1].tobytes(), 8, 6, 24, "bgr8")[0], image)
    np.testing.assert_array_equal(pixels_to_mono(bgra[:, :, [2, 1, 0, 3]].tobytes(), 8, 6, 32, "rgba8")[0], image)
    flat = np.full((8, 8), 1000, np.uint16)  # a grey scene seen through any Bayer filter
    for pattern in ("rggb", "bggr", "gbrg", "grbg"):
        image, note = pixels_to_mono(flat.tobytes(), 8, 8, 16, f"bayer_{pattern}16")
        assert image.dtype == np.uint16 and np.all(np.abs(image.astype(int) - 1000) <= 1) and "Bayer" in note
        image, _ = pixels_to_mono((flat // 8).astype(np.uint8).tobytes(), 8, 8, 8, f"bayer_{pattern}8")
        assert image.dtype == np.uint8 and np.all(np.abs(image.astype(int) - 125) <= 1)
    red = np.zeros((8, 8), np.uint8)
    red[0::2, 0::2] = 200  # only the red sites of an RGGB mosaic are lit: a red scene
    assert pixels_to_mono(red.tobytes(), 8, 8, 8, "bayer_rggb8")[0][4, 4] == round(0.299 * 200)
    with pytest.raises(InvalidInputError, match="unsupported image encoding 'yuv422'"):
        pixels_to_mono(bytes(96), 8, 6, 16, "yuv422")


def test_foxglove_json_images_and_jpeg(native: dict[str, Path], tmp_path: Path) -> None:
    """foxglove.RawImage in its JSON encoding (base64 data) and a JPEG CompressedImage."""
    import base64

    from mcap.writer import Writer

    schema = json.dumps({"title": "foxglove.RawImage", "type": "object", "properties": {
        "timestamp": {"type": "object"}, "frame_id": {"type": "string"}, "width": {"type": "integer"},
        "height": {"type": "integer"}, "encoding": {"type": "string"}, "step": {"type": "integer"},
        "data": {"type": "string", "contentEncoding": "base64"}}}).encode()
    path = tmp_path / "json.mcap"
    frames = list(native_frames(native["sim"]))
    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        sid = w.register_schema("foxglove.RawImage", "jsonschema", schema)
        cid = w.register_channel("/camera/json", "json", sid)
        for t, image in frames:
            w.add_message(cid, log_time=t, publish_time=t, data=json.dumps({
                "timestamp": {"sec": t // 10**9, "nsec": t % 10**9}, "frame_id": "cam", "width": image.shape[1],
                "height": image.shape[0], "encoding": "mono16", "step": 2 * image.shape[1],
                "data": base64.b64encode(image.astype("<u2").tobytes()).decode()}).encode())
        status = w.register_schema("lab.Status", "jsonschema", json.dumps({
            "type": "object", "properties": {"when": {"type": "string", "format": "date-time"}}}).encode())
        w.add_message(w.register_channel("/status", "json", status), log_time=0, publish_time=0,
                      data=b'{"when": "2024-01-01T00:00:00Z"}')
        w.finish()
    with LogReader(path) as log:
        got = list(log.frames("/camera/json"))
        assert [m.payload for m in log.messages("/status")] == [{"when": "2024-01-01T00:00:00Z"}]
        assert any("not checked" in n for n in log.notes)  # a keyword starlog's checker does not know
    for (_, t, image), (t0, image0) in zip(got, frames):
        assert t == t0
        np.testing.assert_array_equal(image, image0)
    jpeg = write_foxglove_compressed(native["sim"], tmp_path / "jpeg.mcap", fmt="jpg")
    with LogReader(jpeg) as log:
        for (_, _, image), (_, image0) in zip(log.frames("/camera/compressed"), frames):
            assert image.dtype == np.uint8 and image.shape == image0.shape  # JPEG holds 8 bits: lossy, but read


# ---------------------------------------------------------------- export from any log
def test_export_foreign_frames_and_any_topic(native: dict[str, Path], tmp_path: Path) -> None:
    import pyarrow.parquet as pq
    from foxglove_schemas_protobuf.Vector3_pb2 import Vector3  # a nested protobuf type
    from foxglove_schemas_protobuf.Pose_pb2 import Pose
    from mcap_protobuf.writer import Writer as ProtobufWriter

    bag = write_ros2(native["sim"], tmp_path / "bag.mcap")
    code, text = _run("export", str(bag), "-o", str(tmp_path / "t"), "--topic", "/camera/image_raw", "--json")
    assert code == 0, text
    frames = pq.read_table(tmp_path / "t" / "frames.parquet").to_pylist()
    times = [t for t, _ in native_frames(native["sim"])]
    assert [r["log_time"] for r in frames] == times and {r["topic"] for r in frames} == {"/camera/image_raw"}
    assert frames[0]["width"] == 64 and frames[0]["height"] == 48 and frames[3]["frame"] == 3
    flat = pq.read_table(tmp_path / "t" / "camera.image_raw.parquet")
    assert flat.column_names[0] == "log_time" and "header.stamp.sec" in flat.column_names
    assert "header.frame_id" in flat.column_names and flat.column("encoding").to_pylist()[0] == "mono16"

    poses = tmp_path / "poses.mcap"
    with open(poses, "wb") as f, ProtobufWriter(f) as writer:
        for t in range(5):
            pose = Pose(position=Vector3(x=t, y=2.0 * t, z=0.5))
            pose.orientation.w = 1.0
            writer.write_message("/pose", pose, log_time=t, publish_time=t)
    code, text = _run("export", str(poses), "-o", str(tmp_path / "p"))
    assert code == 1 and "nothing to export" in text and "/pose (foxglove.Pose)" in text and "--topic" in text
    code, text = _run("export", str(poses), "-o", str(tmp_path / "p"), "--topic", "/pose")
    assert code == 0, text
    table = pq.read_table(tmp_path / "p" / "pose.parquet")
    assert table.column_names[:4] == ["log_time", "position.x", "position.y", "position.z"]
    assert table.column("position.y").to_pylist() == [0.0, 2.0, 4.0, 6.0, 8.0]

    with LogReader(native["cen"]) as log:  # lists and nested JSON of a native channel
        n = sum(1 for _ in log.messages(topics.DETECTIONS))
    code, text = _run("export", str(native["cen"]), "-o", str(tmp_path / "d"), "--table", "detections",
                      "--topic", topics.DETECTIONS)
    detections = pq.read_table(tmp_path / "d" / "stars.detections.parquet")
    assert code == 0 and detections.num_rows == n and detections.column_names == ["log_time", "frame", "stars"]
    assert isinstance(detections.column("stars").to_pylist()[0], list)


def test_run_config_chooses_the_image_topic(native: dict[str, Path], tmp_path: Path) -> None:
    bag = write_ros2(native["sim"], tmp_path / "bag.mcap", compressed="png")
    config = tmp_path / "p.toml"
    config.write_text(f'[centroid]\nmethods = ["{METHOD}"]\nimage_topic = "/camera/image_raw"\n'
                      '[centroid.options]\npsf_sigma = 1.2\n')
    code, text = _run("run", str(bag), "-o", str(tmp_path / "out.mcap"), "--config", str(config), "--json", "-q")
    assert code == 0, text
    stage = json.loads(text)["stages"][0]
    assert stage["image_topic"] == "/camera/image_raw" and stage["frames"] == stage["channel_messages"] == 24
    _same_centroids(tmp_path / "out.mcap", native)


def test_foxglove_compressed_image_in_json(native: dict[str, Path], tmp_path: Path) -> None:
    import base64

    from mcap.writer import Writer

    path = tmp_path / "cjson.mcap"
    frames = list(native_frames(native["sim"]))
    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        sid = w.register_schema("foxglove.CompressedImage", "jsonschema", b'{"type": "object"}')
        cid = w.register_channel("/camera/png", "json", sid)
        for t, image in frames:
            w.add_message(cid, log_time=t, publish_time=t, data=json.dumps({
                "timestamp": {"sec": t // 10**9, "nsec": t % 10**9}, "frame_id": "cam", "format": "png",
                "data": base64.b64encode(cv2.imencode(".png", image)[1].tobytes()).decode()}).encode())
        w.finish()
    out = tmp_path / "cen.mcap"
    summary = centroid_log(path, out, methods=METHOD, options={"psf_sigma": 1.2})
    assert summary.image_topic == "/camera/png" and summary.frames == 24
    _same_centroids(out, native)
