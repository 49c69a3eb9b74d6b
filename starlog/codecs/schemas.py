"""Message types: the schema and encoding of every channel starlog writes.

starlog's star tables (detections, centroids, tracks, platform motion, residuals, attitude,
identified stars) are protobuf: their ``.proto`` sources are in the repository's ``schemas/starlog/``
folder and compiled into ``schemas/starlog.desc`` (``tools/build_descriptors.py``); each channel's
schema is the ``FileDescriptorSet`` of the file defining its message. starlog's other messages are
JSON, described by JSON Schemas in ``schemas/`` (so are the star tables of earlier logs). The folder
is installed as ``starlog/_schemas``; every log embeds the schemas of its channels. Images and
overlays use the Foxglove well-known protobuf schemas, embedded as a ``FileDescriptorSet``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any

from google.protobuf.descriptor import FileDescriptor
from google.protobuf.descriptor_pb2 import FileDescriptorProto, FileDescriptorSet

from starlog.errors import InvalidParameterError

__all__ = ["MessageType", "schema_dir", "load_json_schema", "json_message_type", "protobuf_message_type",
           "starlog_descriptor_set", "STARLOG_DESCRIPTORS"]

#: The compiled ``.proto`` sources of starlog's protobuf messages, in :func:`schema_dir`.
STARLOG_DESCRIPTORS = "starlog.desc"


@dataclass(frozen=True)
class MessageType:
    """How the messages of one channel are encoded.

    Attributes
    ----------
    schema_name : str
        e.g. ``"foxglove.RawImage"`` or ``"starlog.Centroids"``.
    schema_encoding : str
        ``"protobuf"`` or ``"jsonschema"`` (MCAP well-known schema encodings).
    schema_data : bytes
        The serialized FileDescriptorSet, or the JSON Schema text.
    message_encoding : str
        ``"protobuf"`` or ``"json"``.
    """

    schema_name: str
    schema_encoding: str
    schema_data: bytes
    message_encoding: str


def schema_dir() -> Path:
    """The folder holding starlog's JSON Schemas (installed copy first, then the source tree)."""
    here = Path(__file__).resolve().parent.parent
    for candidate in (here / "_schemas", here.parent / "schemas"):
        if candidate.is_dir():
            return candidate
    raise FileNotFoundError(f"starlog's schemas/ folder is missing (looked in {here / '_schemas'}).")


@cache
def load_json_schema(name: str) -> dict[str, Any]:
    """Load the JSON Schema of the starlog message type ``name`` (e.g. ``"starlog.Centroids"``)."""
    path = schema_dir() / f"{name}.json"
    if not path.is_file():
        known = sorted(p.stem for p in schema_dir().glob("*.json"))
        raise InvalidParameterError(f"no JSON Schema named {name!r}; known: {', '.join(known)}.")
    return json.loads(path.read_text(encoding="utf-8"))


@cache
def json_message_type(name: str) -> MessageType:
    """The :class:`MessageType` of a starlog JSON message, its schema read from ``schemas/``."""
    schema = load_json_schema(name)
    data = json.dumps(schema, sort_keys=True, separators=(",", ":")).encode()
    return MessageType(name, "jsonschema", data, "json")


def _file_descriptor_set(descriptor: Any) -> bytes:
    fds = FileDescriptorSet()
    seen: set[str] = set()

    def add(fd: FileDescriptor) -> None:
        for dep in fd.dependencies:
            if dep.name not in seen:
                add(dep)
        if fd.name not in seen:
            seen.add(fd.name)
            fd.CopyToProto(fds.file.add())

    add(descriptor.file)
    return fds.SerializeToString(deterministic=True)


@cache
def starlog_descriptor_set() -> FileDescriptorSet:
    """The FileDescriptorSet of starlog's protobuf messages (``schemas/starlog.desc``)."""
    return FileDescriptorSet.FromString((schema_dir() / STARLOG_DESCRIPTORS).read_bytes())


def _starlog_file_set(full_name: str) -> bytes | None:
    """The FileDescriptorSet of the starlog ``.proto`` file defining ``full_name`` (its imports first), or None."""
    files = {f.name: f for f in starlog_descriptor_set().file}
    defining = [f for f in files.values() if any(f"{f.package}.{m.name}" == full_name for m in f.message_type)]
    if not defining:
        return None
    fds = FileDescriptorSet()
    seen: set[str] = set()

    def add(fd: FileDescriptorProto) -> None:
        for dep in fd.dependency:
            if dep not in seen and dep in files:
                add(files[dep])
        seen.add(fd.name)
        fds.file.add().CopyFrom(fd)

    add(defining[0])
    return fds.SerializeToString(deterministic=True)


@cache
def protobuf_message_type(full_name: str) -> MessageType:
    """The :class:`MessageType` of a protobuf message: a Foxglove well-known one (``"foxglove.RawImage"``,
    ``"foxglove.ImageAnnotations"``) or one of starlog's (``"starlog.Centroids"``, ...: ``schemas/starlog/``)."""
    from foxglove_schemas_protobuf.ImageAnnotations_pb2 import ImageAnnotations
    from foxglove_schemas_protobuf.RawImage_pb2 import RawImage

    classes = {"foxglove.RawImage": RawImage, "foxglove.ImageAnnotations": ImageAnnotations}
    if full_name in classes:
        return MessageType(full_name, "protobuf", _file_descriptor_set(classes[full_name].DESCRIPTOR), "protobuf")
    own = _starlog_file_set(full_name)
    if own is None:
        known = sorted(classes) + sorted(f"{f.package}.{m.name}" for f in starlog_descriptor_set().file
                                         for m in f.message_type)
        raise InvalidParameterError(f"unsupported protobuf message {full_name!r}; known: {known}.")
    return MessageType(full_name, "protobuf", own, "protobuf")
