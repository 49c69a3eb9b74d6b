"""The chunk checksum: the same CRC-32 as zlib's, whichever implementation computes it."""

from __future__ import annotations

import zlib

from hypothesis import given
from hypothesis import strategies as st

from starlog.io.checksum import crc32


@given(st.binary(max_size=4096), st.integers(min_value=0, max_value=2**32 - 1))
def test_crc32_equals_zlib(data: bytes, start: int) -> None:
    assert crc32(data) == zlib.crc32(data)
    assert crc32(data, start) == zlib.crc32(data, start)


@given(st.binary(min_size=1, max_size=4096), st.data())
def test_crc32_of_a_read_only_slice(data: bytes, draw: st.DataObject) -> None:
    lo = draw.draw(st.integers(min_value=0, max_value=len(data)))
    hi = draw.draw(st.integers(min_value=lo, max_value=len(data)))
    view = memoryview(data).toreadonly()[lo:hi]
    assert crc32(view) == zlib.crc32(data[lo:hi])


def test_crc32_continues_over_pieces() -> None:
    data = bytes(range(256)) * 4099  # over 1 MB: the long-input path of the fast implementations
    assert crc32(data[1000:], crc32(data[:1000])) == zlib.crc32(data)


def test_the_summary_crc_is_the_one_the_mcap_library_writes_in_its_footer(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """An independent oracle: the footer of a log written by the ``mcap`` library."""
    from starlog.io.layout import read_footer, summary_crc
    from tests.foreign_logs import write_numbers

    path = write_numbers(tmp_path / "plain.mcap", 5)
    with open(path, "rb") as f:
        footer = read_footer(f)
        assert footer.summary_crc != 0
        assert summary_crc(f, footer) == footer.summary_crc
