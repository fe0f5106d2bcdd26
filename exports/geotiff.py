"""The pile's surfaces as one GeoTIFF: the ground, each deposit's top, the top surface.

One float32 band per surface, bottom to top: band 1 the ground (S0), band k + 1 the top
of deposit k (S(k)), so the last band is the top surface; each band's description names
it.  Pixels
are the pile's cells (:func:`exports.placement.place`: a rotated affine transform fitted
to the exact conversion), values are mine-grid heights (m), nodata NaN.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from exports.placement import atomic_path, place, raster_rows
from geo.site_crs import SiteCrs
from projector.query import PileState

__all__ = ["write_surfaces"]


def surface_names(pile: PileState) -> list[str]:
    """Each band's description, bottom to top: the ground, then each deposit's top (the
    last one is the top surface)."""
    stack = pile.state.stack
    n = stack.n_deposits
    names = ["ground" if n else "ground (the top surface: nothing stacked)"]
    for k in range(1, n + 1):
        info = stack.info(k)
        top = "top surface: " if k == n else ""
        names.append(f"{top}top of deposit {k} (pass {info.pass_id or '-'}, lot "
                     f"{info.lot_id or '-'})")
    return names


def write_surfaces(path: str | Path, pile: PileState, site: SiteCrs) -> dict:
    """Write the GeoTIFF; returns what was written (bands, shape, CRS, transform, the
    placement's residual in m)."""
    import rasterio

    if pile.geometry is None:
        raise ValueError(f"pile {pile.pile_id!r} is not declared as of this time")
    stack = pile.state.stack
    surfaces = [stack.surface_k(k) for k in range(stack.n_deposits + 1)]
    placement = place(site, pile.geometry, stack.ground())
    bands = np.stack([raster_rows(placement.heights_m(s)) for s in surfaces]).astype(np.float32)
    names = surface_names(pile)
    profile = {"driver": "GTiff", "width": pile.geometry.nx, "height": pile.geometry.ny,
               "count": len(bands), "dtype": "float32", "crs": site.crs.to_wkt(),
               "transform": placement.transform, "nodata": float("nan"),
               "compress": "deflate", "predictor": 3, "tiled": True}
    with atomic_path(path) as tmp:
        with rasterio.open(tmp, "w", **profile) as out:
            out.write(bands)
            for i, name in enumerate(names, start=1):
                out.set_band_description(i, name)
            out.update_tags(pile_id=pile.pile_id, valid_time_ns=str(pile.valid_time_ns),
                            known_time_ns=str(pile.known_time_ns),
                            cell_m=repr(pile.geometry.cell_m),
                            placement_residual_m=f"{placement.residual_m:.6f}",
                            heights="ellipsoidal, m")
    return {"path": str(path), "bands": names, "width": pile.geometry.nx,
            "height": pile.geometry.ny, "epsg": site.epsg,
            "transform": tuple(placement.transform)[:6],
            "placement_residual_m": placement.residual_m}
