"""The site's mine-grid CRS from the ledger, and a pile's grid placed in the mine grid.

A pile's grid is square cells on the site frame's axes (east, north).  In the mine grid
those axes turn by the grid convergence and scale by the projection's scale factor, both
nearly constant over a pile; :func:`place` converts every cell centre exactly
(:class:`geo.site_crs.SiteCrs`) and fits one affine transform to them, for a raster whose
pixels are the pile's cells.  The fit's largest miss is reported (``residual_m``).

Raster convention (GDAL's): row 0 is the grid's last ``iy`` (the north edge), column c is
``ix = c``; :func:`raster_rows` turns an ``(nx, ny)`` layer into those ``(ny, nx)`` rows.
"""

from __future__ import annotations

import os
import tempfile
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np

from geo.site_crs import SiteCrs
from projector.grid import GridGeometry, cell_centres
from schemas.events import decode_payload

__all__ = ["GridPlacement", "atomic_path", "place", "raster_rows", "site_crs_from_ledger"]


def site_crs_from_ledger(store, valid_time_ns: int, known_time_ns: int,
                         epsg: int | None = None) -> SiteCrs:
    """The site's datum and CRS as declared by V as known at K (the last declaration).

    ``epsg`` stands in for, or overrides, the declared CRS.  ValueError when the ledger
    declares no site, or neither it nor ``epsg`` gives a CRS.
    """
    declared = None
    for record in store.as_of(valid_time_ns, known_time_ns, types=["site_declared"]):
        declared = decode_payload(record.type, record.payload)
    if declared is None:
        raise ValueError("the ledger declares no site (site_declared) as of that time")
    code = int(epsg) if epsg else int(declared.crs_epsg)
    if not code:
        raise ValueError(f"site {declared.site_id!r} declares no mine-grid CRS: give one "
                         "with --crs EPSG")
    return SiteCrs(declared.datum_lat_deg, declared.datum_lon_deg, declared.datum_alt_m, code)


@dataclass(frozen=True)
class GridPlacement:
    """A pile's cells in the mine grid.

    Attributes
    ----------
    site : SiteCrs
    geometry : GridGeometry
    easting_m, northing_m : ndarray, shape (nx, ny)
        Each cell centre's exact mine-grid position (at the heights ``place`` was given).
    transform : affine.Affine
        Pixel (column, row) -> (E, N) of a raster of :func:`raster_rows`, fitted.
    residual_m : float
        The fit's largest horizontal miss over the cell centres (m).
    """

    site: SiteCrs
    geometry: GridGeometry
    easting_m: np.ndarray
    northing_m: np.ndarray
    transform: object
    residual_m: float

    def heights_m(self, z_m: np.ndarray) -> np.ndarray:
        """Site heights (nx, ny) at the cell centres -> mine-grid heights (m); NaN stays NaN."""
        z = np.asarray(z_m, np.float64)
        if z.shape != self.geometry.shape:
            raise ValueError(f"heights must have shape {self.geometry.shape}, got {z.shape}")
        x, y = cell_centres(self.geometry)
        ok = np.isfinite(z)
        out = np.full(z.shape, np.nan)
        if ok.any():
            out[ok] = self.site.to_grid(x[ok], y[ok], z[ok])[2]
        return out


def place(site: SiteCrs, geometry: GridGeometry, z_m: np.ndarray) -> GridPlacement:
    """Convert every cell centre (at heights ``z_m`` (nx, ny), m; NaN taken as 0) to the
    mine grid and fit the raster transform to them."""
    from affine import Affine

    z = np.nan_to_num(np.asarray(z_m, np.float64))
    if z.shape != geometry.shape:
        raise ValueError(f"heights must have shape {geometry.shape}, got {z.shape}")
    x, y = cell_centres(geometry)
    e, n, _h = site.to_grid(x, y, z)
    ix, iy = np.meshgrid(np.arange(geometry.nx), np.arange(geometry.ny), indexing="ij")
    col, row = ix + 0.5, (geometry.ny - 1 - iy) + 0.5
    a = np.column_stack([col.ravel(), row.ravel(), np.ones(col.size)])
    ce, *_ = np.linalg.lstsq(a, e.ravel(), rcond=None)
    cn, *_ = np.linalg.lstsq(a, n.ravel(), rcond=None)
    miss = np.hypot(a @ ce - e.ravel(), a @ cn - n.ravel())
    transform = Affine(ce[0], ce[1], ce[2], cn[0], cn[1], cn[2])
    return GridPlacement(site, geometry, e, n, transform, float(miss.max()))


def raster_rows(layer: np.ndarray) -> np.ndarray:
    """An ``(nx, ny)`` layer as raster rows ``(ny, nx)``, north row first."""
    layer = np.asarray(layer)
    if layer.ndim != 2:
        raise ValueError(f"a layer is 2-D (nx, ny), got shape {layer.shape}")
    return layer.T[::-1, :]


@contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """A temporary path beside ``path``, renamed to it when the block ends without error
    (and removed when it fails), so a reader never sees half a file."""
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=target.suffix,
                               dir=target.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        os.replace(tmp, target)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
