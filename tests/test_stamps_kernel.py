"""The compiled window cutter against its numpy reference: the same arrays, bit for bit."""

from __future__ import annotations

from dataclasses import fields

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from starlog.centroiding.stamps import gather_stamps, gather_stamps_vectorised
from starlog.errors import InvalidInputError


def _assert_same(image: np.ndarray, x: np.ndarray, y: np.ndarray, h: int, saturation: float) -> None:
    rng = np.random.default_rng(int(x.size))
    background = rng.uniform(0, 50, x.size)
    noise = rng.uniform(1, 5, x.size)
    got = gather_stamps(image, x, y, h, background, noise, 2.0, saturation)
    want = gather_stamps_vectorised(image, x, y, h, background, noise, 2.0, saturation)
    for f in fields(want):
        a, b = getattr(got, f.name), getattr(want, f.name)
        if isinstance(b, np.ndarray):
            assert a.dtype == b.dtype and a.shape == b.shape, f.name
        np.testing.assert_array_equal(a, b, err_msg=f.name)


@settings(max_examples=200, derandomize=True, deadline=None)
@given(dtype=st.sampled_from(["u1", "<u2", ">u2", "<f2", "<f4", "<f8", "i4"]), rows=st.integers(1, 24),
       cols=st.integers(1, 24), n=st.integers(0, 6), h=st.integers(0, 6), seed=st.integers(0, 2**16),
       holes=st.booleans(), saturation=st.sampled_from([np.inf, 200.0, 65535.0]))
def test_windows_equal_the_numpy_reference(dtype: str, rows: int, cols: int, n: int, h: int, seed: int,
                                           holes: bool, saturation: float) -> None:
    rng = np.random.default_rng(seed)
    image = rng.uniform(0, 255, (rows, cols)).astype(dtype)
    if holes and image.dtype.kind == "f":
        image[rng.random(image.shape) < 0.1] = np.nan
        image[rng.random(image.shape) < 0.05] = np.inf
    # centres inside, on and beyond the edges, and on pixel halves (rounded to even)
    x = rng.uniform(-h - 2, cols + h + 2, n).round(1)
    y = np.concatenate([rng.integers(-2, rows + 2, n // 2) + 0.5, rng.uniform(-3, rows + 3, n - n // 2)])
    _assert_same(image, x, y, h, saturation)


def test_windows_of_a_non_contiguous_frame() -> None:
    image = np.arange(40 * 30, dtype=np.uint16).reshape(40, 30)[::2, ::-1]
    _assert_same(image, np.array([0.0, 7.4, 14.6]), np.array([19.5, 3.0, 0.2]), 3, 1000.0)


def test_positions_must_pair_up() -> None:
    with pytest.raises(InvalidInputError, match="one value per star"):
        gather_stamps(np.zeros((8, 8)), np.zeros(3), np.zeros(2), 2, np.zeros(3), np.ones(3), 1.0, np.inf)
    with pytest.raises(InvalidInputError, match="one value per star"):
        gather_stamps(np.zeros((8, 8)), np.zeros(3), np.zeros(3), 2, np.zeros(2), np.ones(3), 1.0, np.inf)


@pytest.mark.parametrize("shape", [(0, 5), (5, 0), (0, 0)])
def test_an_empty_frame_is_refused(shape: tuple[int, int]) -> None:
    with pytest.raises(InvalidInputError, match="non-empty 2-D"):
        gather_stamps(np.zeros(shape), np.zeros(1), np.zeros(1), 1, np.zeros(1), np.ones(1), 1.0, np.inf)
