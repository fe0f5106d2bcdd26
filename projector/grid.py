"""One grid geometry, named float layers on it, and index <-> position as free functions.

After ANYbotics ``grid_map``: a 2.5D map is a set of named float layers that share one
geometry (corner, cell size, shape, frame); NaN means "no data".  Cells are square.

Conventions
-----------
- x runs across the pile, y along the rail (site ENU, metres; docs/domain.md §2).
- A layer is a ``float64`` array of shape ``(nx, ny)`` indexed ``[ix, iy]``; an elevation
  layer holds heights (m), NaN where a cell was never seen (:func:`check_elevation`).
- Cell ``(ix, iy)`` covers ``[x0 + ix*cell, x0 + (ix+1)*cell) x [y0 + iy*cell, ...)``;
  its centre is at ``x0 + (ix + 0.5)*cell``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

__all__ = ["GridGeometry", "GridMap", "cell_index", "cell_centre", "inside", "cell_centres",
           "check_elevation"]


@dataclass(frozen=True)
class GridGeometry:
    """A rectangle of ``nx`` x ``ny`` square cells of ``cell_m`` with its corner at (x0, y0).

    Attributes
    ----------
    origin_x_m, origin_y_m : float
        The corner with the smallest x and y, site frame, metres.
    cell_m : float
        Cell edge, metres (> 0).
    nx, ny : int
        Cells along x (across the pile) and along y (along the rail), >= 1.
    frame : str
        The frame the coordinates are in.
    """

    origin_x_m: float
    origin_y_m: float
    cell_m: float
    nx: int
    ny: int
    frame: str = "site"

    def __post_init__(self) -> None:
        if not (math.isfinite(self.cell_m) and self.cell_m > 0):
            raise ValueError(f"cell_m must be finite and > 0, got {self.cell_m}")
        if not (math.isfinite(self.origin_x_m) and math.isfinite(self.origin_y_m)):
            raise ValueError("the grid origin must be finite")
        if int(self.nx) < 1 or int(self.ny) < 1:
            raise ValueError(f"the grid needs at least one cell, got {self.nx} x {self.ny}")

    @classmethod
    def covering(cls, origin_x_m: float, origin_y_m: float, width_m: float, length_m: float,
                 cell_m: float, frame: str = "site") -> "GridGeometry":
        """The grid of ``cell_m`` cells covering ``width_m`` (x) by ``length_m`` (y).

        The cell counts are rounded up, so the grid covers at least the rectangle.
        """
        if not (width_m > 0 and length_m > 0):
            raise ValueError(f"width and length must be > 0, got {width_m} x {length_m}")
        nx = max(1, math.ceil(width_m / cell_m - 1e-9))
        ny = max(1, math.ceil(length_m / cell_m - 1e-9))
        return cls(float(origin_x_m), float(origin_y_m), float(cell_m), nx, ny, frame)

    @property
    def shape(self) -> tuple[int, int]:
        """``(nx, ny)``: the shape of every layer."""
        return (self.nx, self.ny)

    @property
    def length_x_m(self) -> float:
        return self.nx * self.cell_m

    @property
    def length_y_m(self) -> float:
        return self.ny * self.cell_m

    @property
    def cell_area_m2(self) -> float:
        return self.cell_m * self.cell_m

    @property
    def centre_m(self) -> tuple[float, float]:
        """The grid's centre (grid_map's "position"), metres."""
        return (self.origin_x_m + self.length_x_m / 2, self.origin_y_m + self.length_y_m / 2)


def cell_index(geometry: GridGeometry, x_m, y_m) -> tuple[np.ndarray, np.ndarray]:
    """Cell indices ``(ix, iy)`` (int64 arrays) of positions; outside cells are not clipped.

    Use :func:`inside` to mask positions outside the grid.
    """
    x = np.asarray(x_m, dtype=np.float64)
    y = np.asarray(y_m, dtype=np.float64)
    ix = np.floor((x - geometry.origin_x_m) / geometry.cell_m).astype(np.int64)
    iy = np.floor((y - geometry.origin_y_m) / geometry.cell_m).astype(np.int64)
    return ix, iy


def inside(geometry: GridGeometry, x_m, y_m) -> np.ndarray:
    """Whether each position lies in the grid (NaN positions are outside)."""
    x = np.asarray(x_m, dtype=np.float64)
    y = np.asarray(y_m, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        return ((x >= geometry.origin_x_m) & (x < geometry.origin_x_m + geometry.length_x_m)
                & (y >= geometry.origin_y_m) & (y < geometry.origin_y_m + geometry.length_y_m))


def cell_centre(geometry: GridGeometry, ix, iy) -> tuple[np.ndarray, np.ndarray]:
    """Centre positions ``(x, y)`` in metres of cells ``(ix, iy)``."""
    ix = np.asarray(ix, dtype=np.float64)
    iy = np.asarray(iy, dtype=np.float64)
    return (geometry.origin_x_m + (ix + 0.5) * geometry.cell_m,
            geometry.origin_y_m + (iy + 0.5) * geometry.cell_m)


def cell_centres(geometry: GridGeometry) -> tuple[np.ndarray, np.ndarray]:
    """``(X, Y)``, each ``(nx, ny)``: the centre of every cell."""
    ix, iy = np.meshgrid(np.arange(geometry.nx), np.arange(geometry.ny), indexing="ij")
    return cell_centre(geometry, ix, iy)


def check_elevation(elevation) -> np.ndarray:
    """``elevation`` as a ``float64 (nx, ny)`` array of heights (m), NaN = never seen.

    Raises
    ------
    ValueError
        When it is not 2-D or holds an infinity.
    """
    e = np.asarray(elevation, dtype=np.float64)
    if e.ndim != 2:
        raise ValueError(f"elevation must have shape (nx, ny), got {e.shape}")
    if np.isinf(e).any():
        raise ValueError("elevation must not contain infinities (NaN = never seen)")
    return e


@dataclass
class GridMap:
    """Named float layers on one geometry (NaN = no data).

    ``layers[name]`` is a ``float64`` array of shape ``geometry.shape``.
    """

    geometry: GridGeometry
    layers: dict[str, np.ndarray] = field(default_factory=dict)

    def add(self, name: str, fill: float = math.nan) -> np.ndarray:
        """Add (or reset) a layer filled with ``fill``; return it."""
        self.layers[name] = np.full(self.geometry.shape, fill, dtype=np.float64)
        return self.layers[name]

    def __getitem__(self, name: str) -> np.ndarray:
        return self.layers[name]

    def __setitem__(self, name: str, values: np.ndarray) -> None:
        values = np.asarray(values, dtype=np.float64)
        if values.shape != self.geometry.shape:
            raise ValueError(f"layer {name!r} has shape {values.shape}, the grid is "
                             f"{self.geometry.shape}")
        self.layers[name] = values

    def __contains__(self, name: str) -> bool:
        return name in self.layers

    def copy(self) -> "GridMap":
        return GridMap(self.geometry, {k: v.copy() for k, v in self.layers.items()})
