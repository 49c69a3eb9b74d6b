"""Messages checked against their schema where they are encoded (worker processes), not again by the writer."""

from __future__ import annotations

import pickle
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from starlog.errors import InvalidInputError
from starlog.io import LogReader, LogWriter
from starlog.codecs import encode_json, json_message_type
from starlog.codecs.checked_json import CheckedJson, encode_checked_json, schema_checker, schema_digest
from starlog.codecs.json_messages import decode_json

DETECTIONS = json_message_type("starlog.Detections")
FRAME_INFO = json_message_type("starlog.FrameInfo")


@given(st.integers(min_value=-3, max_value=10**6), st.sampled_from([[], "x", None, [1], [{"star": 0}]]))
def test_checked_exactly_when_the_writer_would_accept(frame: int, stars: object) -> None:
    value = {"frame": frame, "stars": stars}
    valid = schema_checker(DETECTIONS.schema_data)(decode_json(encode_json(value))) is None
    if valid:
        message = encode_checked_json(value, DETECTIONS)
        assert message == encode_json(value)
        assert message.schema_digest == schema_digest(DETECTIONS.schema_data)
    else:
        with pytest.raises(InvalidInputError, match="does not match its schema"):
            encode_checked_json(value, DETECTIONS)


def test_checked_message_survives_pickling() -> None:
    message = encode_checked_json({"frame": 3, "stars": []}, DETECTIONS)
    copy = pickle.loads(pickle.dumps(message))
    assert type(copy) is CheckedJson and copy == message and copy.schema_digest == message.schema_digest


def test_writer_checks_a_message_checked_against_another_schema(tmp_path: Path) -> None:
    with LogWriter(tmp_path / "a.mcap") as log:
        channel = log.add_channel("/stars/detections", DETECTIONS)
        forged = CheckedJson(b'{"frame": "not a number"}', schema_digest(FRAME_INFO.schema_data))
        with pytest.raises(InvalidInputError, match="does not match"):
            log.write(channel, log_time=1, data=forged)


def test_writer_writes_checked_messages_as_they_are(tmp_path: Path) -> None:
    path = tmp_path / "b.mcap"
    messages = [encode_checked_json({"frame": k, "stars": []}, DETECTIONS) for k in range(3)]
    with LogWriter(path) as log:
        channel = log.add_channel("/stars/detections", DETECTIONS)
        for k, message in enumerate(messages):
            log.write(channel, log_time=k + 1, data=message)
    with LogReader(path, validate_messages="all") as log:
        assert [m.payload["frame"] for m in log.messages("/stars/detections")] == [0, 1, 2]
        assert [bytes(m.data) for _, _, m in log.raw_messages(["/stars/detections"])] == [bytes(m) for m in messages]
