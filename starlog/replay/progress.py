"""Progress bars for long stages (tqdm on stderr; silent when disabled)."""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from typing import TypeVar

from tqdm import tqdm

T = TypeVar("T")

__all__ = ["progress"]


def progress(items: Iterable[T], *, total: int | None, description: str, enabled: bool,
             unit: str = "frame") -> Iterator[T]:
    """Wrap ``items`` in a progress bar (counting ``unit``) when ``enabled`` and stderr is a terminal."""
    if not enabled:
        yield from items
        return
    with tqdm(items, total=total, desc=description, unit=unit, dynamic_ncols=True, leave=False,
              disable=None) as bar:
        yield from bar
