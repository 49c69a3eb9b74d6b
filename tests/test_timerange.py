"""--start / --end: the parser of time bounds and the half-open range it resolves to (property tests)."""

from __future__ import annotations

from decimal import Decimal

import pytest
from hypothesis import given
from hypothesis import strategies as st

from starlog.errors import InvalidParameterError
from starlog.io.timerange import END_OF_TIME, TimeRange, parse_time_bound

NS = st.integers(min_value=0, max_value=END_OF_TIME - 1)


@given(NS)
def test_integer_nanoseconds_parse_to_themselves(ns: int) -> None:
    for written in (str(ns), ns, f"  {ns} "):
        bound = parse_time_bound(written)
        assert (bound.kind, bound.value) == ("ns", ns)


@given(st.integers(min_value=0, max_value=10**10), st.integers(min_value=0, max_value=9))
def test_seconds_with_up_to_nine_decimals_are_exact(units: int, decimals: int) -> None:
    seconds = Decimal(units).scaleb(-decimals)
    bound = parse_time_bound(f"{seconds:f}s")
    assert bound.kind == "ns"
    assert bound.value == int(seconds * 10**9)


def test_seconds_examples() -> None:
    assert parse_time_bound("12.5s").value == 12_500_000_000
    assert parse_time_bound(".5s").value == 500_000_000
    assert parse_time_bound("3.s").value == 3 * 10**9
    with pytest.raises(InvalidParameterError, match="finer than a nanosecond"):
        parse_time_bound("1.0000000001s")


@given(st.integers(min_value=0, max_value=10**9))
def test_frame_bounds_keep_their_index(n: int) -> None:
    bound = parse_time_bound(f"frame:{n}")
    assert (bound.kind, bound.value, bound.text) == ("frame", n, f"frame:{n}")


@given(st.text(alphabet=st.characters(blacklist_categories=("Nd",)), max_size=12))
def test_text_without_digits_is_refused_with_the_accepted_forms(text: str) -> None:
    with pytest.raises(InvalidParameterError, match="expected log time in ns"):
        parse_time_bound(text, option="--end")


@pytest.mark.parametrize("text", ["-5", "-1s", "1e9", "frame:-1", "frame:", "5 s", "1,5s", "frame:1.5", str(2**64)])
def test_malformed_bounds_are_refused(text: str) -> None:
    with pytest.raises(InvalidParameterError):
        parse_time_bound(text)


@given(NS, NS, st.lists(NS, max_size=30))
def test_resolved_range_is_half_open(a: int, b: int, times: list[int]) -> None:
    time_range = TimeRange.parse(a, b)
    assert time_range is not None
    if b <= a:
        with pytest.raises(InvalidParameterError, match="empty|reversed"):
            time_range.resolve()
        return
    resolved = time_range.resolve()
    assert resolved.contains(a) and not resolved.contains(b)
    assert [t for t in times if resolved.contains(t)] == [t for t in times if a <= t < b]
    assert resolved.to_dict()["start_ns"] == a and resolved.to_dict()["end_ns"] == b


@given(st.lists(st.integers(min_value=0, max_value=10**6), min_size=1, max_size=40, unique=True),
       st.data())
def test_frame_ranges_select_frames_start_to_end_minus_one(offsets: list[int], data: st.DataObject) -> None:
    times = sorted(offsets)
    first = data.draw(st.integers(min_value=0, max_value=len(times) - 1))
    last = data.draw(st.integers(min_value=first + 1, max_value=len(times)))
    resolved = TimeRange.parse(f"frame:{first}", f"frame:{last}").resolve(
        lambda n: times[n] if 0 <= n < len(times) else None, frame_topic="/t")
    assert [t for t in times if resolved.contains(t)] == times[first:last]
    assert resolved.frame_topic == "/t"


def test_frames_past_the_channel_are_outside_the_log() -> None:
    times = [10, 20, 30]

    def lookup(n: int) -> int | None:
        return times[n] if 0 <= n < len(times) else None

    assert TimeRange.parse(None, "frame:3").resolve(lookup).end_ns == 31  # one past the last: up to its end
    with pytest.raises(InvalidParameterError, match="outside the log"):
        TimeRange.parse("frame:3", None).resolve(lookup)
    with pytest.raises(InvalidParameterError, match="outside the log"):
        TimeRange.parse(None, "frame:4").resolve(lookup)
    with pytest.raises(InvalidParameterError, match="frame channel"):
        TimeRange.parse("frame:1", None).resolve(None)


def test_open_bounds() -> None:
    assert TimeRange.parse(None, None) is None
    resolved = TimeRange.parse("5s", None).resolve()
    assert resolved.contains(END_OF_TIME - 1) and not resolved.contains(5 * 10**9 - 1)
    assert resolved.to_dict() == {"start": "5s", "end": None, "start_ns": 5 * 10**9, "end_ns": None}
