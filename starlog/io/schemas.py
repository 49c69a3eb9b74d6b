"""Message types: the schema and encoding of every channel starlog writes.

starlog's own messages are JSON, described by JSON Schemas kept in the repository's
``schemas/`` folder (installed as ``starlog/_schemas``) and embedded in every log. Images and
overlays use the Foxglove well-known protobuf schemas, embedded as a ``FileDescriptorSet``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any

from google.protobuf.descriptor import FileDescriptor
from google.protobuf.descriptor_pb2 import FileDescriptorSet

from starlog.errors import InvalidParameterError

__all__ = ["MessageType", "schema_dir", "load_json_schema", "json_message_type", "protobuf_message_type"]


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
def protobuf_message_type(full_name: str) -> MessageType:
    """The :class:`MessageType` of a Foxglove well-known protobuf message.

    ``full_name`` is ``"foxglove.RawImage"`` or ``"foxglove.ImageAnnotations"``.
    """
    from foxglove_schemas_protobuf.ImageAnnotations_pb2 import ImageAnnotations
    from foxglove_schemas_protobuf.RawImage_pb2 import RawImage

    classes = {"foxglove.RawImage": RawImage, "foxglove.ImageAnnotations": ImageAnnotations}
    if full_name not in classes:
        raise InvalidParameterError(f"unsupported protobuf message {full_name!r}; known: {sorted(classes)}.")
    descriptor = classes[full_name].DESCRIPTOR
    return MessageType(full_name, "protobuf", _file_descriptor_set(descriptor), "protobuf")
