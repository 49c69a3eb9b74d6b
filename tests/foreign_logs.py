"""Logs as other tools write them, built from a starlog log's frames with those tools' own libraries.

ROS 2 bags with ``mcap-ros2-support``, ROS 1 with ``mcap-ros1-support``, Foxglove protobuf with
``mcap-protobuf-support``, and unusual-but-valid layouts with the plain ``mcap`` writer
(no chunks, no message indexes, no summary). Used by the tests and ``tools/bench_foreign.py``.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from starlog.io import LogReader
from starlog import topics

ROS2_TIME = "int32 sec\nuint32 nanosec\n"
ROS2_HEADER = "builtin_interfaces/Time stamp\nstring frame_id\n"
_SEP = "=" * 80 + "\n"
ROS2_IMAGE = ("std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\nuint8 is_bigendian\n"
              "uint32 step\nuint8[] data\n" + _SEP + "MSG: std_msgs/Header\n" + ROS2_HEADER + _SEP
              + "MSG: builtin_interfaces/Time\n" + ROS2_TIME)
ROS2_COMPRESSED = ("std_msgs/Header header\nstring format\nuint8[] data\n" + _SEP + "MSG: std_msgs/Header\n"
                   + ROS2_HEADER + _SEP + "MSG: builtin_interfaces/Time\n" + ROS2_TIME)
ROS1_IMAGE = ("Header header\nuint32 height\nuint32 width\nstring encoding\nuint8 is_bigendian\nuint32 step\n"
              "uint8[] data\n" + _SEP + "MSG: std_msgs/Header\nuint32 seq\ntime stamp\nstring frame_id\n")
ROS1_COMPRESSED = ("Header header\nstring format\nuint8[] data\n" + _SEP
                   + "MSG: std_msgs/Header\nuint32 seq\ntime stamp\nstring frame_id\n")


def native_frames(path: Path, topic: str = topics.IMAGE) -> Iterator[tuple[int, np.ndarray]]:
    """``(log_time, image)`` of every frame of a starlog log."""
    with LogReader(path) as log:
        for _, t, image in log.frames(topic):
            yield t, image


def _ros_pixels(image: np.ndarray, encoding: str, big_endian: bool) -> tuple[bytes, int]:
    if encoding.startswith("bayer_"):  # mosaic a grey frame: every site holds the grey value
        pixels = image
    elif encoding in ("rgb8", "bgr8"):
        pixels = np.repeat(image[:, :, None], 3, axis=2)
    else:
        pixels = image
    data = pixels.astype(">u2" if big_endian else "<u2").tobytes() if pixels.dtype == np.uint16 else pixels.tobytes()
    return data, len(data) // image.shape[0]


def write_ros2(src: Path, dst: Path, *, topic: str = "/camera/image_raw", encoding: str = "mono16",
               big_endian: bool = False, compressed: str | None = None, stamp_offset_ns: int = 0,
               chunk_size: int = 1024 * 1024) -> Path:
    """A ROS 2 bag (``sensor_msgs/msg/Image`` or, with ``compressed="png"``, ``CompressedImage``)."""
    from mcap_ros2.writer import Writer

    with open(dst, "wb") as f:
        writer = Writer(f, chunk_size=chunk_size)
        schema = (writer.register_msgdef("sensor_msgs/msg/CompressedImage", ROS2_COMPRESSED) if compressed
                  else writer.register_msgdef("sensor_msgs/msg/Image", ROS2_IMAGE))
        for seq, (t, image) in enumerate(native_frames(src)):
            stamp = t + stamp_offset_ns
            header = {"stamp": {"sec": stamp // 10**9, "nanosec": stamp % 10**9}, "frame_id": "star_camera"}
            if compressed:
                message: dict[str, Any] = {"header": header, "format": compressed,
                                           "data": cv2.imencode(f".{compressed}", image)[1].tobytes()}
            else:
                data, step = _ros_pixels(image, encoding, big_endian)
                message = {"header": header, "height": image.shape[0], "width": image.shape[1],
                           "encoding": encoding, "is_bigendian": int(big_endian), "step": step, "data": data}
            writer.write_message(topic, schema, message, log_time=t, publish_time=t, sequence=seq)
        writer.finish()
    return dst


def write_ros1(src: Path, dst: Path, *, topic: str = "/camera/image_raw", compressed: str | None = None) -> Path:
    """A ROS 1 log (``sensor_msgs/Image`` mono16, or ``CompressedImage``) written with mcap-ros1-support."""
    # mcap-ros1-support's private _vendor: its ROS 1 message classes are made only by the genpy it vendors
    from mcap_ros1._vendor.genpy import Time, dynamic
    from mcap_ros1.writer import Writer

    name, text = ("sensor_msgs/CompressedImage", ROS1_COMPRESSED) if compressed else ("sensor_msgs/Image", ROS1_IMAGE)
    cls = dynamic.generate_dynamic(name, text)[name]
    with open(dst, "wb") as f:
        writer = Writer(f)
        for seq, (t, image) in enumerate(native_frames(src)):
            message = cls()
            message.header.seq = seq
            message.header.stamp = Time(t // 10**9, t % 10**9)
            message.header.frame_id = "star_camera"
            if compressed:
                message.format = compressed
                message.data = cv2.imencode(f".{compressed}", image)[1].tobytes()
            else:
                message.height, message.width = image.shape
                message.encoding, message.is_bigendian = "mono16", 0
                message.step = 2 * image.shape[1]
                message.data = image.astype("<u2").tobytes()
            writer.write_message(topic, message, log_time=t, publish_time=t, sequence=seq)
        writer.finish()
    return dst


def write_foxglove_compressed(src: Path, dst: Path, *, topic: str = "/camera/compressed", fmt: str = "png") -> Path:
    """``foxglove.CompressedImage`` (PNG by default) written with mcap-protobuf-support."""
    from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
    from mcap_protobuf.writer import Writer

    with open(dst, "wb") as f, Writer(f) as writer:
        for t, image in native_frames(src):
            message = CompressedImage(frame_id="star_camera", format=fmt,
                                      data=cv2.imencode(f".{fmt}", image)[1].tobytes())
            message.timestamp.seconds, message.timestamp.nanos = divmod(t, 10**9)
            writer.write_message(topic, message, log_time=t, publish_time=t)
    return dst


def write_numbers(dst: Path, count: int, *, padding: int = 0, chunk_size: int = 64, **writer_options: Any) -> Path:
    """A small JSON log written by the ``mcap`` library: ``count`` messages ``{"n": t}`` on ``/numbers``
    (each ``padding`` bytes longer), chunks of ``chunk_size`` bytes; ``writer_options`` go to its ``Writer``."""
    from mcap.writer import Writer

    with open(dst, "wb") as f:
        writer = Writer(f, chunk_size=chunk_size, **writer_options)
        writer.start()
        channel = writer.register_channel("/numbers", "json", writer.register_schema("n", "jsonschema", b"{}"))
        for t in range(count):
            data = b'{"n": %d, "padding": "%s"}' % (t, b"x" * padding) if padding else b'{"n": %d}' % t
            writer.add_message(channel, log_time=t, publish_time=t, data=data)
        writer.finish()
    return dst


def write_plain(src: Path, dst: Path, *, use_chunking: bool = True, message_indexes: bool = True,
                summary: bool = True, shuffle: bool = False, chunk_size: int = 1024 * 1024,
                topic: str = topics.IMAGE, repeat_schemas: bool = True, repeat_channels: bool = True,
                statistics: bool = True) -> Path:
    """Every channel of a starlog log rewritten with the plain ``mcap`` writer in an unusual layout.

    ``use_chunking=False``: messages outside chunks; ``message_indexes=False``: chunks without
    message index records; ``summary=False``: no summary section; ``repeat_schemas=False`` /
    ``repeat_channels=False``: a summary without the schema / channel records (they stay in the data
    section); ``statistics=False``: no statistics record; ``shuffle``: messages written out of
    ``log_time`` order (in reversed blocks). The image channel is renamed ``topic``.
    """
    from mcap.writer import IndexType, Writer

    index_types = IndexType.ALL if message_indexes else IndexType.ALL & ~IndexType.MESSAGE
    with LogReader(src) as log, open(dst, "wb") as f:
        writer = Writer(f, chunk_size=chunk_size, use_chunking=use_chunking, index_types=index_types,
                        use_statistics=summary and statistics, use_summary_offsets=summary,
                        repeat_channels=summary and repeat_channels, repeat_schemas=summary and repeat_schemas)
        writer.start(profile="", library="plain-mcap-test")
        ids: dict[str, int] = {}
        schema_ids: dict[int, int] = {}
        messages = list(log.raw_messages(log.topics))
        if shuffle:
            messages = [m for block in range(0, len(messages), 7) for m in reversed(messages[block: block + 7])]
        for schema, channel, message in messages:
            if channel.topic not in ids:
                assert schema is not None
                if schema.id not in schema_ids:
                    schema_ids[schema.id] = writer.register_schema(schema.name, schema.encoding, schema.data)
                ids[channel.topic] = writer.register_channel(
                    topic if channel.topic == topics.IMAGE else channel.topic, channel.message_encoding,
                    schema_ids[schema.id])
            writer.add_message(ids[channel.topic], log_time=message.log_time, data=message.data,
                               publish_time=message.publish_time)
        for name, data in log.metadata():
            writer.add_metadata(name, data)
        writer.finish()
    if not summary:
        _drop_summary(dst)
    return dst


def _drop_summary(path: Path) -> None:
    """Rewrite the footer so the file has no summary section (summary bytes removed, start 0)."""
    import struct

    data = path.read_bytes()
    footer = len(data) - 8 - 29
    summary_start = struct.unpack_from("<Q", data, footer + 9)[0]
    if summary_start == 0:
        return
    out = data[:summary_start] + struct.pack("<BQQQI", 0x02, 20, 0, 0, 0) + data[-8:]
    path.write_bytes(out)
