"""The voxel block model as CSV or Parquet, in the mine grid (a regular block model).

One row per block with material (:func:`projector.blocks.block_model`).  Columns, in order
(:data:`COLUMNS`, then one per analyte, then the last three):

``X``, ``Y``, ``Z``
    The block's centre in the mine grid (easting, northing, ellipsoidal height; m).
``DX``, ``DY``, ``DZ``
    The block's edges (m on the ground; the blocks' axes are the site frame's, turned from
    grid north by the grid convergence, which the file's metadata states).
``TONNES``, ``VOLUME_M3``, ``DENSITY_T_M3``
    The material in the block (t, m3) and its bulk density (t/m3).
``<analyte>_PCT``
    Mass % over the block's graded tonnes (empty where none is graded).
``GRADED_FRACTION``
    Tonnes with a grade (an assay or the lot's plan) / tonnes, 0 to 1.  The pile's grade
    is the analyte weighted by ``TONNES * GRADED_FRACTION``; weighted by ``TONNES`` alone
    it would count ungraded material (an undeclared lot) as grade 0 or skip its blocks.
``ASSAYED_FRACTION``
    Tonnes graded by an assay / tonnes, 0 to 1.
``DOMINANT_LOT``
    The lot with the most tonnes in the block.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np

from exports.placement import atomic_path
from geo.site_crs import SiteCrs
from projector.blocks import BlockModel

__all__ = ["COLUMNS", "block_table", "write_blocks"]

COLUMNS = ("X", "Y", "Z", "DX", "DY", "DZ", "TONNES", "VOLUME_M3", "DENSITY_T_M3")
FORMATS = ("csv", "parquet")


def block_table(blocks: BlockModel, site: SiteCrs) -> dict[str, np.ndarray]:
    """The block model's columns (name -> array of one entry per block), mine grid."""
    e, n, h = site.to_grid(blocks.x_m, blocks.y_m, blocks.z_m)
    table = {"X": e, "Y": n, "Z": h, "DX": blocks.dx_m, "DY": blocks.dy_m, "DZ": blocks.dz_m,
             "TONNES": blocks.tonnes, "VOLUME_M3": blocks.volume_m3,
             "DENSITY_T_M3": blocks.density_t_m3}
    for a, analyte in enumerate(blocks.analytes):
        table[f"{analyte.upper()}_PCT"] = blocks.grade_pct[:, a]
    table["GRADED_FRACTION"] = blocks.graded_fraction
    table["ASSAYED_FRACTION"] = blocks.assayed_fraction
    table["DOMINANT_LOT"] = blocks.dominant_lot
    return table


def convergence_deg(site: SiteCrs, x_m: float, y_m: float) -> float:
    """The angle (deg, clockwise from grid north) of the site frame's north at (x, y)."""
    e, n, _ = site.to_grid(np.array([x_m, x_m]), np.array([y_m, y_m + 100.0]), 0.0)
    return math.degrees(math.atan2(e[1] - e[0], n[1] - n[0]))


def write_blocks(path: str | Path, blocks: BlockModel, site: SiteCrs, fmt: str,
                 metadata: dict[str, str] | None = None) -> dict:
    """Write the block model as ``fmt`` (``csv`` or ``parquet``); returns a summary
    (rows, columns, tonnes, the convergence in degrees)."""
    if fmt not in FORMATS:
        raise ValueError(f"unknown block model format {fmt!r} (known: {', '.join(FORMATS)})")
    table = block_table(blocks, site)
    turn = convergence_deg(site, float(np.mean(blocks.x_m)) if len(blocks) else 0.0,
                           float(np.mean(blocks.y_m)) if len(blocks) else 0.0)
    meta = {"pile_id": blocks.pile_id, "crs": f"EPSG:{site.epsg}",
            "block_axes_from_grid_north_deg": f"{turn:.9f}",
            "heights": "ellipsoidal, m", **(metadata or {})}
    with atomic_path(path) as tmp:
        if fmt == "csv":
            _write_csv(tmp, table)
        else:
            _write_parquet(tmp, table, meta)
    return {"path": str(path), "format": fmt, "rows": len(blocks), "columns": list(table),
            "tonnes": float(blocks.tonnes.sum()), **meta}


def _write_csv(path: Path, table: dict[str, np.ndarray]) -> None:
    names = list(table)
    columns = [table[k] for k in names]
    with open(path, "w", newline="") as out:
        writer = csv.writer(out)
        writer.writerow(names)
        for row in zip(*columns):
            writer.writerow(["" if isinstance(v, float) and math.isnan(v) else
                             (repr(float(v)) if isinstance(v, (float, np.floating)) else v)
                             for v in row])


def _write_parquet(path: Path, table: dict[str, np.ndarray], meta: dict[str, str]) -> None:
    import pyarrow as pa
    import pyarrow.parquet as pq

    arrays = {k: (pa.array(v.tolist(), pa.string()) if v.dtype == object
                  else pa.array(v, from_pandas=True))          # NaN -> null
              for k, v in table.items()}
    t = pa.table(arrays)
    t = t.replace_schema_metadata({**(t.schema.metadata or {}),
                                   **{k.encode(): str(v).encode() for k, v in meta.items()}})
    pq.write_table(t, path)
