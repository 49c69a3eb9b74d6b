"""Progress bars for long stages (tqdm on stderr; silent when disabled)."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from typing import TypeVar

from tqdm import tqdm

T = TypeVar("T")

__all__ = ["progress"]


def progress(items: Iterable[T], *, total: int | None, description: str, enabled: bool,
             unit: str = "frame", weight: Callable[[T], int] | None = None) -> Iterator[T]:
    """Wrap ``items`` in a progress bar (counting ``unit``) when ``enabled`` and stderr is a terminal.

    With ``weight``, each item counts ``weight(item)`` units (e.g. a block of frames) when it is done.
    """
    if not enabled:
        yield from items
        return
    if weight is None:
        with tqdm(items, total=total, desc=description, unit=unit, dynamic_ncols=True, leave=False,
                  disable=None) as bar:
            yield from bar
        return
    with tqdm(total=total, desc=description, unit=unit, dynamic_ncols=True, leave=False, disable=None) as bar:
        for item in items:
            yield item
            bar.update(weight(item))
