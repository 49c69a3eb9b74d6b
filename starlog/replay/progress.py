"""Progress bars for long stages (tqdm on stderr; silent when disabled)."""

from __future__ import annotations

import sys
from collections.abc import Iterable, Iterator
from typing import TypeVar

from tqdm import tqdm

T = TypeVar("T")

__all__ = ["hidden", "progress"]


def progress(items: Iterable[T], *, total: int | None, description: str, enabled: bool,
             unit: str = "frame") -> Iterator[T]:
    """Wrap ``items`` in a progress bar (counting ``unit``) when ``enabled`` and stderr is a terminal or a
    notebook's cell (:func:`hidden`)."""
    if not enabled:
        yield from items
        return
    with tqdm(items, total=total, desc=description, unit=unit, dynamic_ncols=True, leave=False,
              disable=hidden()) as bar:
        yield from bar


def hidden() -> bool | None:
    """tqdm's ``disable`` for a bar asked for: None (shown on a terminal only) from the command line, False (shown)
    in a Jupyter kernel, whose stderr is the cell's output, not a terminal."""
    shell = getattr(sys.modules.get("IPython"), "get_ipython", lambda: None)()
    return False if type(shell).__name__ == "ZMQInteractiveShell" else None
