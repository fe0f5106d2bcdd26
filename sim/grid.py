"""The simulator's deposition grid and its stacking patterns.

:class:`Grid` is the regular grid of square columns the true pile lives on (site frame,
metres; arrays over it have shape ``(ny, nx)``, rows along y = the rail); :class:`Pattern`
names the stacking patterns; :data:`ANALYTES`, :data:`DEFAULT_REPOSE_DEG` and
:data:`DEFAULT_DENSITY_T_M3` are the material defaults every part of the world uses.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

import numpy as np

#: Analytes carried by every parcel (mass %), in this order.
ANALYTES: tuple[str, ...] = ("Fe", "SiO2", "Al2O3", "P", "LOI")

#: Default angle of repose of iron-ore fines (deg, docs/domain.md §4).
DEFAULT_REPOSE_DEG = 37.0

#: Default bulk density of crushed iron ore (t/m3, docs/domain.md §4).
DEFAULT_DENSITY_T_M3 = 2.4


@dataclass(frozen=True)
class Grid:
    """A regular grid of square columns in the site frame.

    ``origin_x_m, origin_y_m`` is the *corner* of cell (0, 0); cell (iy, ix) spans
    ``[origin_x + ix*cell, origin_x + (ix+1)*cell) x [origin_y + iy*cell, ...)`` and its
    centre is half a cell further. Arrays over the grid have shape ``(ny, nx)`` (rows
    along y, the rail / the pile's long axis; columns along x, across the pile).
    """

    origin_x_m: float
    origin_y_m: float
    cell_m: float
    nx: int
    ny: int
    ground_z_m: float = 0.0

    def __post_init__(self):
        for name in ("origin_x_m", "origin_y_m", "cell_m", "ground_z_m"):
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ValueError(f"{name} must be a finite number, got {v!r}")
        if self.cell_m <= 0:
            raise ValueError(f"cell_m must be > 0, got {self.cell_m}")
        for name in ("nx", "ny"):
            v = getattr(self, name)
            if not isinstance(v, (int, np.integer)) or v < 3:
                raise ValueError(f"{name} must be an integer >= 3, got {v!r}")

    @classmethod
    def covering(cls, x_min_m: float, x_max_m: float, y_min_m: float, y_max_m: float,
                 cell_m: float, ground_z_m: float = 0.0) -> "Grid":
        """The smallest grid with cell ``cell_m`` whose cells cover the given rectangle."""
        if not (x_max_m > x_min_m and y_max_m > y_min_m):
            raise ValueError("empty rectangle")
        nx = max(3, int(math.ceil((x_max_m - x_min_m) / cell_m - 1e-9)))
        ny = max(3, int(math.ceil((y_max_m - y_min_m) / cell_m - 1e-9)))
        return cls(float(x_min_m), float(y_min_m), float(cell_m), nx, ny, float(ground_z_m))

    @property
    def shape(self) -> tuple[int, int]:
        return (self.ny, self.nx)

    @property
    def cell_area_m2(self) -> float:
        return self.cell_m * self.cell_m

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """(x_min, x_max, y_min, y_max) of the grid's outer edges (m)."""
        return (self.origin_x_m, self.origin_x_m + self.nx * self.cell_m,
                self.origin_y_m, self.origin_y_m + self.ny * self.cell_m)

    @property
    def x_centres(self) -> np.ndarray:
        """Cell-centre x of every column index, shape (nx,)."""
        return self.origin_x_m + (np.arange(self.nx) + 0.5) * self.cell_m

    @property
    def y_centres(self) -> np.ndarray:
        """Cell-centre y of every row index, shape (ny,)."""
        return self.origin_y_m + (np.arange(self.ny) + 0.5) * self.cell_m

    def centres(self) -> tuple[np.ndarray, np.ndarray]:
        """Cell-centre coordinates ``(X, Y)``, each of shape (ny, nx)."""
        return np.meshgrid(self.x_centres, self.y_centres)

    def index_of(self, x_m, y_m) -> tuple[np.ndarray, np.ndarray]:
        """Indices ``(iy, ix)`` of the cells containing the points (may be out of range)."""
        ix = np.floor((np.asarray(x_m, float) - self.origin_x_m) / self.cell_m).astype(np.int64)
        iy = np.floor((np.asarray(y_m, float) - self.origin_y_m) / self.cell_m).astype(np.int64)
        return iy, ix

    def contains(self, x_m, y_m) -> np.ndarray:
        """True where the point lies on the grid."""
        iy, ix = self.index_of(x_m, y_m)
        return (iy >= 0) & (iy < self.ny) & (ix >= 0) & (ix < self.nx)

    def centre_of(self, iy, ix) -> tuple[np.ndarray, np.ndarray]:
        """Cell-centre ``(x, y)`` of cell indices."""
        return (self.origin_x_m + (np.asarray(ix, float) + 0.5) * self.cell_m,
                self.origin_y_m + (np.asarray(iy, float) + 0.5) * self.cell_m)

    def to_dict(self) -> dict:
        return {"origin_x_m": float(self.origin_x_m), "origin_y_m": float(self.origin_y_m),
                "cell_m": float(self.cell_m), "nx": int(self.nx), "ny": int(self.ny),
                "ground_z_m": float(self.ground_z_m)}


class Pattern(str, enum.Enum):
    """Stacking patterns (thesis §2.1, Fig. 2.1)."""

    CHEVRON = "chevron"
    WINDROW = "windrow"
    CONE_SHELL = "cone_shell"
