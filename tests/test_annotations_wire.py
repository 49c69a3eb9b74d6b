"""foxglove.ImageAnnotations written on the wire: the same bytes as protobuf's deterministic serialization."""

from __future__ import annotations

import math

from hypothesis import given
from hypothesis import strategies as st

from starlog.codecs import encode_image_annotations


def _by_protobuf(x: list[float], y: list[float], *, log_time: int, diameter: float, thickness: float,
                 rgba: tuple[float, float, float, float]) -> bytes:
    from foxglove_schemas_protobuf.ImageAnnotations_pb2 import ImageAnnotations

    msg = ImageAnnotations()
    seconds, nanos = divmod(log_time, 1_000_000_000)
    for xi, yi in zip(x, y):
        if not (math.isfinite(xi) and math.isfinite(yi)):
            continue
        circle = msg.circles.add()
        circle.timestamp.seconds = seconds
        circle.timestamp.nanos = nanos
        circle.position.x = float(xi) + 0.5
        circle.position.y = float(yi) + 0.5
        circle.diameter = diameter
        circle.thickness = thickness
        circle.outline_color.r, circle.outline_color.g, circle.outline_color.b, circle.outline_color.a = rgba
    return msg.SerializeToString(deterministic=True)


coordinates = st.lists(st.one_of(st.floats(allow_nan=True, allow_infinity=True, width=64),
                                 st.sampled_from([-0.5, 0.0, -0.0, 1e300, -1e-300])), max_size=8)
numbers = st.one_of(st.floats(allow_nan=False, allow_infinity=False), st.sampled_from([0.0, -0.0, 1.0]))


@given(coordinates, coordinates, st.one_of(st.integers(min_value=0, max_value=2**63 - 1),
                                           st.sampled_from([0, 5, 1_000_000_000, -1, -1_500_000_000])),
       numbers, numbers, st.tuples(numbers, numbers, numbers, numbers))
def test_wire_encoding_equals_protobufs(x: list[float], y: list[float], log_time: int, diameter: float,
                                        thickness: float, rgba: tuple[float, float, float, float]) -> None:
    expected = _by_protobuf(x, y, log_time=log_time, diameter=diameter, thickness=thickness, rgba=rgba)
    assert encode_image_annotations(x, y, log_time=log_time, diameter=diameter, thickness=thickness,
                                    rgba=rgba) == expected


def test_default_look() -> None:
    x, y = [10.25, float("nan"), 3.0], [4.0, 1.0, -0.5]
    assert encode_image_annotations(x, y, log_time=1_234_567_890_123) == _by_protobuf(
        x, y, log_time=1_234_567_890_123, diameter=8.0, thickness=1.0, rgba=(0.1, 1.0, 0.2, 1.0))
