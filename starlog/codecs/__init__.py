"""The payload codecs: what each message of a log holds and how its bytes are encoded and decoded.

The MCAP container (:mod:`starlog.io`) stores and finds messages; this package makes values of their
bytes and bytes of values. It imports neither :mod:`starlog.io` nor the stages.

* star tables (detections, centroids, tracks, ...: protobuf, or the JSON of earlier logs) as numpy
  structured arrays: :mod:`~starlog.codecs.star_tables`, on the wire codec of
  :mod:`~starlog.codecs.table_wire` (header and table), :mod:`~starlog.codecs.table_rows` (the rows)
  and :mod:`~starlog.codecs.table_fields` (one field on the wire);
* JSON messages: :mod:`~starlog.codecs.json_messages` (encode, decode),
  :mod:`~starlog.codecs.json_rows` (the JSON star rows of earlier versions, from a structured array),
  :mod:`~starlog.codecs.checked_json` (checked where they are encoded, e.g. in a worker process);
* schemas: :mod:`~starlog.codecs.schemas` (the message type of every channel starlog writes),
  :mod:`~starlog.codecs.json_schema` (a compiled checker for the JSON Schemas in ``schemas/``);
* images: :mod:`~starlog.codecs.images` (camera frames of any common image type, to 2-D mono arrays),
  :mod:`~starlog.codecs.rawimage_wire` (``foxglove.RawImage`` read from the wire),
  :mod:`~starlog.codecs.foxglove_messages` (``foxglove.RawImage`` and ``foxglove.ImageAnnotations``
  written);
* other tools' messages: :mod:`~starlog.codecs.foreign_decoders` (protobuf, ROS 1, ROS 2) and
  :mod:`~starlog.codecs.plain_values` (any message as plain Python values, what ``starlog cat`` prints).

The names below are the ones a script or a stage of your own uses.
"""

from __future__ import annotations

from starlog.codecs.foxglove_messages import decode_raw_image, encode_image_annotations, encode_raw_image
from starlog.codecs.json_messages import decode_json, encode_json
from starlog.codecs.schemas import MessageType, json_message_type, load_json_schema, protobuf_message_type

__all__ = [
    "MessageType",
    "decode_json",
    "decode_raw_image",
    "encode_image_annotations",
    "encode_json",
    "encode_raw_image",
    "json_message_type",
    "load_json_schema",
    "protobuf_message_type",
]
