"""The top surface as a DXF polyface mesh, and its contours as 3D polylines (ezdxf).

Layer ``SURFACE``: one polyface mesh over the cell centres in the mine grid (E, N, height),
every ``step``-th cell each way (the last row and column always in), chosen so the mesh
has at most :data:`MAX_POLYFACE_VERTICES` vertices (a polyface's face records index its
vertices with 16-bit integers).  Layer ``CONTOURS``: the top surface's contours at every
multiple of the interval (mine-grid heights, m), each a 3D polyline at its height, traced
on the full-resolution surface (contourpy) and placed by the cells' exact positions.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np

from exports.placement import GridPlacement, atomic_path, place
from geo.site_crs import SiteCrs
from projector.query import PileState

__all__ = ["MAX_POLYFACE_VERTICES", "mesh_step", "write_mesh"]

#: the most vertices a polyface mesh may have (16-bit vertex indices in its faces)
MAX_POLYFACE_VERTICES = 32_767


def mesh_step(nx: int, ny: int, max_vertices: int = MAX_POLYFACE_VERTICES) -> int:
    """The smallest cell stride whose lattice (last row and column included) has at most
    ``max_vertices`` vertices."""
    if nx < 1 or ny < 1 or max_vertices < 4:
        raise ValueError(f"bad mesh size nx={nx} ny={ny} max_vertices={max_vertices}")
    step = 1
    while _ticks(nx, step).size * _ticks(ny, step).size > max_vertices:
        step += 1
    return step


def _ticks(n: int, step: int) -> np.ndarray:
    ticks = np.arange(0, n, step)
    return ticks if ticks[-1] == n - 1 else np.append(ticks, n - 1)


def write_mesh(path: str | Path, pile: PileState, site: SiteCrs, *,
               contour_m: float = 1.0, max_vertices: int = MAX_POLYFACE_VERTICES) -> dict:
    """Write the DXF; returns what was written (vertices, faces, step, contour count, the
    surface's extent in the mine grid)."""
    import ezdxf
    from ezdxf.render import MeshBuilder

    logging.getLogger("ezdxf").setLevel(logging.WARNING)    # not its INFO lines on stderr
    if pile.geometry is None:
        raise ValueError(f"pile {pile.pile_id!r} is not declared as of this time")
    if not (contour_m > 0 and math.isfinite(contour_m)):
        raise ValueError(f"the contour interval must be > 0 m, got {contour_m}")
    top = np.asarray(pile.state.stack.surface(), np.float64)
    placement = place(site, pile.geometry, top)
    height = placement.heights_m(top)
    step = mesh_step(pile.geometry.nx, pile.geometry.ny, max_vertices)
    tx, ty = _ticks(pile.geometry.nx, step), _ticks(pile.geometry.ny, step)
    mesh = MeshBuilder()
    index = np.full((tx.size, ty.size), -1, np.int64)
    for a, ix in enumerate(tx):
        for b, iy in enumerate(ty):
            if np.isfinite(height[ix, iy]):
                index[a, b] = len(mesh.vertices)
                mesh.vertices.append((float(placement.easting_m[ix, iy]),
                                      float(placement.northing_m[ix, iy]), float(height[ix, iy])))
    for a in range(tx.size - 1):
        for b in range(ty.size - 1):
            quad = (index[a, b], index[a + 1, b], index[a + 1, b + 1], index[a, b + 1])
            if min(quad) >= 0:
                mesh.faces.append(tuple(int(i) for i in quad))
    doc = ezdxf.new("R2010", units=6)          # 6: metres
    doc.layers.add("SURFACE")
    doc.layers.add("CONTOURS")
    msp = doc.modelspace()
    mesh.render_polyface(msp, dxfattribs={"layer": "SURFACE"})
    contours = _contours(placement, height, contour_m)
    for level, line in contours:
        msp.add_polyline3d([(float(e), float(n), level) for e, n in line],
                           dxfattribs={"layer": "CONTOURS"})
    with atomic_path(path) as tmp:
        doc.saveas(tmp)
    finite = np.isfinite(height)
    return {"path": str(path), "vertices": len(mesh.vertices), "faces": len(mesh.faces),
            "step": step, "contours": len(contours), "contour_m": contour_m,
            "extent": {"e_min": float(placement.easting_m[finite].min()),
                       "e_max": float(placement.easting_m[finite].max()),
                       "n_min": float(placement.northing_m[finite].min()),
                       "n_max": float(placement.northing_m[finite].max()),
                       "h_min": float(height[finite].min()),
                       "h_max": float(height[finite].max())}}


def _contours(placement: GridPlacement, height: np.ndarray, contour_m: float
              ) -> list[tuple[float, np.ndarray]]:
    """``(level, (k, 2) E/N points)`` of every contour line of ``height`` (nx, ny)."""
    import contourpy
    from scipy.ndimage import map_coordinates

    finite = height[np.isfinite(height)]
    if finite.size == 0:
        return []
    first = math.ceil(finite.min() / contour_m)
    last = math.floor(finite.max() / contour_m)
    gen = contourpy.contour_generator(z=np.ma.masked_invalid(height.T),
                                      line_type=contourpy.LineType.Separate)
    out = []
    for k in range(first, last + 1):
        level = k * contour_m
        for line in gen.lines(level):        # (k, 2) as (ix, iy), fractional
            if len(line) < 2:
                continue
            coords = [line[:, 0], line[:, 1]]
            e = map_coordinates(placement.easting_m, coords, order=1, mode="nearest")
            n = map_coordinates(placement.northing_m, coords, order=1, mode="nearest")
            out.append((float(level), np.column_stack([e, n])))
    return out
