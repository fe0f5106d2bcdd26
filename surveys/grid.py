"""A survey's points binned into a pile's grid, and the ``Survey`` message that holds them.

:class:`CellAccumulator` takes site-frame points chunk by chunk and keeps, per cell of the
pile's grid, the sum of heights and the count of the points that fell in it (float64 and
int64 arrays of the grid's shape: memory is the grid's, whatever the file's size).
:func:`survey_message` crops to the cells with points and encodes the mean heights
(float32, NaN where none fell) and the counts (uint16, capped) into a ``Survey``;
:func:`projector.surveys.survey_heights` decodes them back onto the pile's grid.
"""

from __future__ import annotations

import numpy as np

from projector.grid import GridGeometry, cell_index
from schemas import pb
from schemas.events import set_timestamp_ns

__all__ = ["CellAccumulator", "survey_message"]

#: the largest count a cell stores (uint16)
MAX_COUNT = 65_535


class CellAccumulator:
    """Sums and counts of point heights per cell of ``geometry``.

    Parameters
    ----------
    geometry : GridGeometry
        The pile's grid (site frame).
    """

    def __init__(self, geometry: GridGeometry) -> None:
        self.geometry = geometry
        self.sum_m = np.zeros(geometry.shape)
        self.count = np.zeros(geometry.shape, np.int64)
        self.points = 0
        self.points_in_grid = 0

    def add(self, x_m: np.ndarray, y_m: np.ndarray, z_m: np.ndarray) -> None:
        """Bin one chunk of site-frame points (three 1-D arrays of one length, m)."""
        x, y, z = (np.asarray(a, np.float64) for a in (x_m, y_m, z_m))
        if not (x.ndim == y.ndim == z.ndim == 1 and x.size == y.size == z.size):
            raise ValueError(f"x, y, z must be 1-D of one length, got {x.shape}, {y.shape}, "
                             f"{z.shape}")
        self.points += x.size
        ix, iy = cell_index(self.geometry, x, y)
        ok = ((ix >= 0) & (ix < self.geometry.nx) & (iy >= 0) & (iy < self.geometry.ny)
              & np.isfinite(z))
        flat = np.ravel_multi_index((ix[ok], iy[ok]), self.geometry.shape)
        n = self.sum_m.size
        self.sum_m += np.bincount(flat, weights=z[ok], minlength=n).reshape(self.geometry.shape)
        self.count += np.bincount(flat, minlength=n).reshape(self.geometry.shape)
        self.points_in_grid += int(ok.sum())

    def mean_m(self) -> np.ndarray:
        """Mean height per cell (nx, ny), m; NaN where no point fell."""
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(self.count > 0, self.sum_m / self.count, np.nan)


def survey_message(acc: CellAccumulator, *, time_ns: int, survey_id: str, pile_id: str,
                   provider: str, accuracy_m: float, source_sha256: bytes,
                   crs_epsg: int) -> pb.Survey:
    """The ``Survey`` of an accumulator: the bounding box of the cells with points."""
    if acc.points_in_grid == 0:
        raise ValueError("no point of the survey falls in the pile's grid (is the CRS right?)")
    ix, iy = np.nonzero(acc.count)
    x0, x1, y0, y1 = int(ix.min()), int(ix.max()) + 1, int(iy.min()), int(iy.max()) + 1
    g = acc.geometry
    msg = pb.Survey(survey_id=survey_id, pile_id=pile_id, provider=provider,
                    accuracy_m=float(accuracy_m), source_sha256=bytes(source_sha256),
                    crs_epsg=int(crs_epsg), origin_x_m=g.origin_x_m, origin_y_m=g.origin_y_m,
                    cell_m=g.cell_m, ix0=x0, iy0=y0, nx=x1 - x0, ny=y1 - y0,
                    heights_m=acc.mean_m()[x0:x1, y0:y1].astype("<f4").tobytes(),
                    counts=np.minimum(acc.count[x0:x1, y0:y1], MAX_COUNT)
                    .astype("<u2").tobytes(),
                    points=acc.points, points_in_grid=acc.points_in_grid)
    set_timestamp_ns(msg.time, int(time_ns))
    return msg
