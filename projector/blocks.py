"""The voxel block model of a projected pile: one row per voxel with material.

:func:`block_model` integrates every deposit band of the pile's layer stack exactly over
its voxel grid (:func:`projector.voxels.integrate`) with four kinds of weight per deposit
and grade class: bulk density (t/m3), density where the class is an assay's, density where
the class has a grade, and density x grade per analyte.  So each block's tonnes, assayed
tonnes, graded tonnes and analyte tonnes are sums over the same pieces the pile's own
figures are (:func:`projector.query.summarise`): the blocks' tonnes add up to the pile's,
and their analyte tonnes over their graded tonnes give the pile's grade.

Coordinates are the site frame (m); :mod:`geo.site_crs` takes them to the mine grid.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from projector.query import PileState
from projector.voxels import ClassWeights, VoxelGrid, integrate

__all__ = ["BlockModel", "block_model"]

#: the weight columns before the analytes: density, assayed density, graded density
_N_FIXED = 3


@dataclass(frozen=True, eq=False)
class BlockModel:
    """Blocks (voxels with material) of one pile as of (V, K), site frame.

    Every array has shape (n,) (``grade_pct``: (n, A)), one entry per block, blocks in
    voxel order (ix, iy, iz).

    Attributes
    ----------
    pile_id : str
    analytes : tuple of str
        The grade columns' analytes, in order.
    x_m, y_m, z_m : ndarray
        Centre of each block's box (site frame, m).  A voxel in the grid's last column or
        row may hold fewer cells than the others: its box is the cells it holds.
    dx_m, dy_m, dz_m : ndarray
        The box's edges (m).
    volume_m3, tonnes : ndarray
        Material in the block (m3, t); ``volume_m3 <= dx * dy * dz``.
    graded_tonnes, assayed_tonnes : ndarray
        Of those tonnes, the ones with a grade, and the ones graded by an assay (t).
    grade_pct : ndarray, shape (n, A)
        Mass % of each analyte over the graded tonnes (NaN where none is graded).
    dominant_lot : ndarray of str
        The lot with the most tonnes in the block.
    """

    pile_id: str
    analytes: tuple[str, ...]
    x_m: np.ndarray
    y_m: np.ndarray
    z_m: np.ndarray
    dx_m: np.ndarray
    dy_m: np.ndarray
    dz_m: np.ndarray
    volume_m3: np.ndarray
    tonnes: np.ndarray
    graded_tonnes: np.ndarray
    assayed_tonnes: np.ndarray
    grade_pct: np.ndarray
    dominant_lot: np.ndarray

    def __len__(self) -> int:
        return int(self.tonnes.size)

    @property
    def density_t_m3(self) -> np.ndarray:
        """Bulk density of the block's material, tonnes / volume (t/m3)."""
        return self.tonnes / self.volume_m3

    @property
    def assayed_fraction(self) -> np.ndarray:
        """Assayed tonnes / tonnes, in [0, 1]."""
        return self.assayed_tonnes / self.tonnes

    @property
    def graded_fraction(self) -> np.ndarray:
        """Graded tonnes / tonnes, in [0, 1]."""
        return self.graded_tonnes / self.tonnes


def block_model(pile: PileState) -> BlockModel:
    """The pile's blocks as of its (V, K) (:func:`projector.query.project`'s answer).

    Raises
    ------
    ValueError
        If the pile was never declared (no geometry).
    """
    state = pile.state
    if state.pile is None or pile.join is None:
        raise ValueError(f"pile {pile.pile_id!r} is not declared as of this time")
    stack, join = state.stack, pile.join
    n_a = len(pile.analytes)
    weights = []
    for k in range(1, stack.n_deposits + 1):
        cells, _thick, times = stack.deposit_cells(k)
        if not cells.size:
            weights.append(ClassWeights(np.zeros(stack.geometry.shape, np.uint8),
                                        np.zeros((1, _N_FIXED + n_a))))
            continue
        c = join.classes(stack.info(k).lot_id, times)
        graded = np.isfinite(c.grade).all(axis=1)
        density = c.density_t_m3
        table = np.column_stack([density, density * c.assayed, density * graded,
                                 density[:, None] * np.where(graded[:, None], c.grade, 0.0)])
        index = np.zeros(stack.geometry.shape, np.min_scalar_type(table.shape[0] - 1))
        index.ravel()[cells] = c.index
        weights.append(ClassWeights(index, table))
    grid = integrate(stack, state.pile.voxel_m, weights if weights else None)
    lots = [stack.info(k).lot_id for k in range(1, stack.n_deposits + 1)]
    return _blocks(pile.pile_id, pile.analytes, grid, stack.geometry, lots)


def _blocks(pile_id: str, analytes, grid: VoxelGrid, geometry, lots: list[str]) -> BlockModel:
    flat = np.flatnonzero(grid.volume_m3.ravel() > 0)
    ix, iy, iz = np.unravel_index(flat, grid.shape)
    m, cell = grid.cells_per_voxel, geometry.cell_m
    # a voxel's cells: m x m, fewer in the last column and row
    x_lo = grid.origin_x_m + ix * m * cell
    y_lo = grid.origin_y_m + iy * m * cell
    dx = np.minimum(m, geometry.nx - ix * m) * cell
    dy = np.minimum(m, geometry.ny - iy * m) * cell
    dz = np.full(flat.size, grid.voxel_m)
    n_a = len(analytes)
    if grid.weighted.shape[-1] == 0:     # no deposits: no material, no blocks
        w = np.zeros((flat.size, _N_FIXED + n_a))
    else:
        w = grid.weighted.reshape(-1, grid.weighted.shape[-1])[flat]
    tonnes, assayed, graded = w[:, 0], w[:, 1], w[:, 2]
    with np.errstate(invalid="ignore", divide="ignore"):
        grade = np.where(graded[:, None] > 0, w[:, _N_FIXED:] / graded[:, None], np.nan)
    return BlockModel(pile_id, tuple(analytes), x_lo + dx / 2, y_lo + dy / 2,
                      grid.z0_m + (iz + 0.5) * grid.voxel_m, dx, dy, dz,
                      grid.volume_m3.ravel()[flat], tonnes, graded, assayed, grade,
                      _dominant_lots(grid, flat, lots))


def _dominant_lots(grid: VoxelGrid, flat: np.ndarray, lots: list[str]) -> np.ndarray:
    """Per block (``flat`` voxels, ascending), the lot with the most tonnes (ties: the
    first lot name in sorted order)."""
    out = np.full(flat.size, "", dtype=object)
    qvo = grid.qvo
    if not len(qvo) or not lots:
        return out
    names, lot_of_deposit = np.unique(np.asarray(lots, dtype=object), return_inverse=True)
    lot = lot_of_deposit[qvo.deposit - 1]
    tonnes = qvo.weighted[:, 0] if qvo.weighted.shape[1] else qvo.volume_m3
    key = qvo.flat * len(names) + lot
    keys, inverse = np.unique(key, return_inverse=True)
    sums = np.bincount(inverse, weights=tonnes)
    voxel, lot_index = keys // len(names), keys % len(names)
    # per voxel, the largest sum: sort by (voxel, -sum, lot) and take each voxel's first
    order = np.lexsort((lot_index, -sums, voxel))
    first = order[np.r_[True, voxel[order][1:] != voxel[order][:-1]]]
    best = dict(zip(voxel[first].tolist(), names[lot_index[first]].tolist()))
    out[:] = [best.get(int(f), "") for f in flat]
    return out
