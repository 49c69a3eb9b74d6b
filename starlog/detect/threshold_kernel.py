"""Compiled (numba): which pixels of a frame lie above a threshold map interpolated from a cell grid.

:meth:`Background.map <starlog.detect.background.Background.map>` makes the map at full
resolution (a resize of the padded grid, then a crop) and a comparison reads it back: at
1024 x 1024 that is 5 MB written and 9 MB read for a one-bit answer per pixel. Here the grid
rows are first interpolated along the columns (a few rows of the frame's width), then each
frame row of the map is made between two of them and compared at once; the map is never stored.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True, error_model="numpy")
def mark_above(image, columns, row_cell, row_weight, out):  # type: ignore[no-untyped-def]
    """``out[y, x]`` = 255 where ``image[y, x]`` exceeds the map there, else 0.

    ``columns`` holds the grid rows interpolated to every column of the frame; row ``y`` of the
    map lies ``row_weight[y]`` of the way from ``columns`` row ``row_cell[y]`` to the next.
    """
    rows, cols = image.shape
    threshold = np.empty(cols, np.float32)
    for y in range(rows):
        i = row_cell[y]
        a = np.float32(row_weight[y])
        b = np.float32(1.0) - a
        low, high = columns[i], columns[i + 1]
        for x in range(cols):
            threshold[x] = b * low[x] + a * high[x]
        row, mark = image[y], out[y]
        for x in range(cols):
            mark[x] = 255 if row[x] > threshold[x] else 0
