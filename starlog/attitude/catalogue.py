"""The star catalogue: cedar-solve's Hipparcos star table (stars to magnitude ~8), read from its package data.

cedar-solve (``pip install 'starlog[solve]'``; import name ``tetra3``) ships its pattern database,
``tetra3/data/default_database.npz``, with the package: the catalogue is read from that file
(only its star table and catalogue numbers), so nothing is downloaded at run time.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cache
from importlib.util import find_spec
from pathlib import Path

import numpy as np
import numpy.typing as npt

from starlog.errors import InvalidParameterError

__all__ = ["Catalogue", "MISSING_SOLVER", "load_catalogue", "solver_data_file"]

MISSING_SOLVER = ("plate solving needs cedar-solve (import name tetra3), the optional extra 'solve': "
                  "pip install 'starlog[solve]' (with NumPy 2: pip install --no-deps cedar-solve).")


@dataclass(frozen=True)
class Catalogue:
    """Catalogue stars: sky unit vectors (n, 3), magnitudes and catalogue numbers (Hipparcos)."""

    vectors: npt.NDArray[np.float64]
    magnitude: npt.NDArray[np.float64]
    ids: npt.NDArray[np.int64]
    name: str = "hip_main"

    def cone(self, boresight: npt.NDArray[np.float64], radius_deg: float) -> npt.NDArray[np.int64]:
        """Indices of the stars within ``radius_deg`` of the unit vector ``boresight``."""
        return np.flatnonzero(self.vectors @ boresight >= math.cos(math.radians(radius_deg)))

    def brighter_than(self, magnitude: float) -> Catalogue:
        """The stars of magnitude <= ``magnitude``."""
        keep = self.magnitude <= magnitude
        return Catalogue(self.vectors[keep], self.magnitude[keep], self.ids[keep], self.name)


def solver_data_file() -> Path:
    """cedar-solve's shipped database file; :class:`InvalidParameterError` naming the extra when it is missing."""
    spec = find_spec("tetra3")
    if spec is None or spec.origin is None:
        raise InvalidParameterError(MISSING_SOLVER)
    path = Path(spec.origin).parent / "data" / "default_database.npz"
    if not path.is_file():
        raise InvalidParameterError(f"cedar-solve is installed but its database {path} is missing; reinstall it. "
                                    + MISSING_SOLVER)
    return path


@cache
def load_catalogue() -> Catalogue:
    """cedar-solve's star table as a :class:`Catalogue` (read once per process)."""
    with np.load(solver_data_file()) as data:
        table = np.asarray(data["star_table"], np.float64)
        ids = np.asarray(data["star_catalog_IDs"], np.int64).reshape(-1)
    vectors = table[:, 2:5] / np.linalg.norm(table[:, 2:5], axis=1)[:, None]
    return Catalogue(vectors, table[:, 5], ids)
