"""Each reclaim cut's footprint and what it delivered, as GeoJSON in the mine grid.

A cut's footprint is the cells its removals took material from (the envelope's cut and
what slid into it after), drawn exactly: the outline of those cells, traced along cell
edges (:func:`footprint_rings`), outer rings counter-clockwise and holes clockwise, as
RFC 7946 wants.  The coordinates are the mine grid's, not WGS-84 as RFC 7946 expects, so
the file names its CRS in the ``crs`` member that GDAL and QGIS read.
"""

from __future__ import annotations

import json
from collections import defaultdict
from pathlib import Path

import numpy as np

from exports.placement import atomic_path
from geo.site_crs import SiteCrs
from projector.query import PileState
from schemas.jsonl import json_safe
from schemas.times import format_time_ns

__all__ = ["footprint_rings", "write_cuts"]

#: each cell's four edges, counter-clockwise, as (corner offset from, corner offset to,
#: the neighbour across the edge)
_EDGES = (((0, 0), (1, 0), (0, -1)), ((1, 0), (1, 1), (1, 0)),
          ((1, 1), (0, 1), (0, 1)), ((0, 1), (0, 0), (-1, 0)))


def footprint_rings(mask: np.ndarray) -> list[tuple[list[tuple[int, int]], list]]:
    """The outline of the True cells of ``mask`` (nx, ny) as polygons of lattice corners.

    Returns ``[(outer, [hole, ...]), ...]``; each ring a closed list of corner indices
    ``(i, j)`` (corner (i, j) is cell (i, j)'s lower-left), outer rings counter-clockwise,
    holes clockwise, straight runs merged.  Cells that touch only at a corner are
    separate polygons.
    """
    mask = np.asarray(mask, bool)
    if mask.ndim != 2:
        raise ValueError(f"mask must be 2-D (nx, ny), got shape {mask.shape}")
    padded = np.pad(mask, 1)
    out_edges: dict[tuple[int, int], list[tuple[int, int]]] = defaultdict(list)
    for i, j in zip(*np.nonzero(mask)):
        for (a, b), (c, d), (di, dj) in _EDGES:
            if not padded[i + di + 1, j + dj + 1]:
                out_edges[(i + a, j + b)].append((i + c, j + d))
    rings = []
    while out_edges:
        start = next(iter(out_edges))
        ring, prev, here = [start], None, start
        while True:
            nxt = _take(out_edges, here, prev)
            if nxt == start:
                break
            ring.append(nxt)
            prev, here = here, nxt
        rings.append(_merge_straight(ring))
    outers = [r for r in rings if _area2(r) > 0]
    holes = [r for r in rings if _area2(r) < 0]
    polygons: list[tuple[list, list]] = [(r, []) for r in outers]
    for hole in holes:
        probe = ((hole[0][0] + hole[1][0]) / 2, (hole[0][1] + hole[1][1]) / 2)
        owner = next((p for p in polygons if _inside(probe, p[0])), None)
        if owner is None:
            raise ValueError("a hole outside every outer ring (bad footprint)")
        owner[1].append(hole)
    return polygons


def _take(edges: dict, here: tuple[int, int], prev: tuple[int, int] | None) -> tuple[int, int]:
    """Remove and return the edge out of ``here``: at a corner with two, the one turning
    left (it keeps corner-touching cells apart)."""
    choices = edges[here]
    if len(choices) > 1 and prev is not None:
        din = (here[0] - prev[0], here[1] - prev[1])
        choices.sort(key=lambda c: -(din[0] * (c[1] - here[1]) - din[1] * (c[0] - here[0])))
    nxt = choices.pop(0)
    if not choices:
        del edges[here]
    return nxt


def _merge_straight(ring: list[tuple[int, int]]) -> list[tuple[int, int]]:
    n = len(ring)
    keep = []
    for k in range(n):
        a, b, c = ring[k - 1], ring[k], ring[(k + 1) % n]
        if (b[0] - a[0]) * (c[1] - b[1]) - (b[1] - a[1]) * (c[0] - b[0]) != 0:
            keep.append(b)
    return keep


def _area2(ring) -> float:
    """Twice the signed area (> 0: counter-clockwise)."""
    return float(sum(ring[k - 1][0] * ring[k][1] - ring[k][0] * ring[k - 1][1]
                     for k in range(len(ring))))


def _inside(point, ring) -> bool:
    x, y = point
    inside = False
    for k in range(len(ring)):
        (x1, y1), (x2, y2) = ring[k - 1], ring[k]
        if (y1 > y) != (y2 > y) and x < x1 + (y - y1) * (x2 - x1) / (y2 - y1):
            inside = not inside
    return inside


def write_cuts(path: str | Path, pile: PileState, site: SiteCrs) -> dict:
    """Write the GeoJSON FeatureCollection (one feature per cut); returns a summary."""
    if pile.geometry is None:
        raise ValueError(f"pile {pile.pile_id!r} is not declared as of this time")
    g = pile.geometry
    z_m = float(np.nanmean(pile.state.stack.ground()))
    features = []
    for record, summary in zip(pile.state.cuts, pile.cuts):
        mask = np.zeros(g.shape, bool)
        for removal in record.removals:
            mask.ravel()[removal.flat_cells(g.shape)] = True
        polygons = []
        for outer, holes in footprint_rings(mask):
            polygons.append([_ring_coords(r, g, site, z_m) for r in (outer, *holes)])
        geometry = ({"type": "MultiPolygon", "coordinates": polygons} if polygons else None)
        features.append({"type": "Feature", "id": summary.cut_id, "geometry": geometry,
                         "properties": json_safe({
                             "cut_id": summary.cut_id, "bench_id": summary.bench_id,
                             "start_time": format_time_ns(summary.start_time_ns),
                             "end_time": format_time_ns(summary.end_time_ns),
                             "tonnes": summary.tonnes, "tonnes_sd": summary.tonnes_sd,
                             "belt_tonnes": summary.tonnes_scale,
                             "volume_m3": summary.volume_m3,
                             "footprint_cells": int(mask.sum()),
                             "footprint_m2": float(mask.sum() * g.cell_area_m2),
                             **{f"{a}_pct": v for a, v in summary.grade.items()},
                             **{f"{a}_sd_pp": v for a, v in summary.grade_sd.items()},
                             "assayed_fraction": summary.assayed_fraction})})
    doc = {"type": "FeatureCollection", "name": f"{pile.pile_id} cuts",
           "crs": {"type": "name", "properties": {"name": f"urn:ogc:def:crs:EPSG::{site.epsg}"}},
           "features": features}
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(doc, indent=1, allow_nan=False) + "\n")
    return {"path": str(path), "cuts": len(features), "epsg": site.epsg}


def _ring_coords(ring, g, site: SiteCrs, z_m: float) -> list[list[float]]:
    i = np.array([c[0] for c in ring] + [ring[0][0]], np.float64)
    j = np.array([c[1] for c in ring] + [ring[0][1]], np.float64)
    e, n, _ = site.to_grid(g.origin_x_m + i * g.cell_m, g.origin_y_m + j * g.cell_m, z_m)
    return [[round(float(a), 4), round(float(b), 4)] for a, b in zip(e, n)]
