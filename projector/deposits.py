"""What a layer stack's deposits are, and what a cut removed from them.

- :class:`DepositInfo`: one deposit of a :class:`projector.layers.LayerStack` (one
  stacking pass, or material that rose outside any pass);
- :class:`DepositRemoval`: what one clamp removed from one deposit, per cell (volume and
  deposition time);
- :class:`Removal`: those of one :meth:`projector.layers.LayerStack.clamp` (or slump), in
  deposit order; :func:`removal_of_drops` forms it from how far a clamp lowered each
  surface.
  Units: metres, m^3, UTC nanoseconds; cells ``(ix, iy)`` index the
stack's grid (:mod:`projector.grid`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from projector.grid import GridGeometry

__all__ = ["DepositInfo", "DepositRemoval", "Removal", "removal_of_drops"]


@dataclass(frozen=True)
class DepositInfo:
    """What a deposit is: one stacking pass (or material that rose outside any pass).

    Attributes
    ----------
    index : int
        1-based position in the stack: the band ``(S(index-1), S(index)]``.
    pass_id : str
        The stacking pass (``""`` when none).
    lot_id : str
        The lot stacked (``""`` when unknown).
    opened_ns : int
        When the deposit was opened (UTC ns).
    flagged : bool
        True for material that rose outside any stacking pass.
    """

    index: int
    pass_id: str
    lot_id: str
    opened_ns: int
    flagged: bool = False


@dataclass(frozen=True, eq=False)
class DepositRemoval:
    """What one clamp removed from one deposit.

    Attributes
    ----------
    index : int
        The deposit (1-based).
    info : DepositInfo
    volume_m3 : float
        Total removed volume (m3).
    ix, iy : ndarray, shape (m,), int64
        The cells some of the deposit was removed from.
    cell_volume_m3 : ndarray, shape (m,)
        Removed volume per cell (m3, > 0).
    deposition_time_ns : ndarray, shape (m,), float64
        When the removed material arrived in that cell (UTC ns): the band's
        thickness-weighted mean deposition time.
    """

    index: int
    info: DepositInfo
    volume_m3: float
    ix: np.ndarray
    iy: np.ndarray
    cell_volume_m3: np.ndarray
    deposition_time_ns: np.ndarray

    @property
    def mean_deposition_time_ns(self) -> float:
        """Volume-weighted mean deposition time of the removed material (UTC ns)."""
        if self.volume_m3 <= 0:
            return math.nan
        return float(np.sum(self.cell_volume_m3 * self.deposition_time_ns) / self.volume_m3)


@dataclass(frozen=True, eq=False)
class Removal:
    """What one :meth:`LayerStack.clamp` removed, per deposit (only deposits that lost material).

    Attributes
    ----------
    deposits : tuple of DepositRemoval
        In deposit order (bottom to top).
    """

    deposits: tuple[DepositRemoval, ...] = ()

    @property
    def volume_m3(self) -> float:
        """Total removed volume (m3)."""
        return float(sum(d.volume_m3 for d in self.deposits))

    def flat_cells(self, shape: tuple[int, int]) -> np.ndarray:
        """Flat indices into ``shape`` (ascending, unique, int64) of the cells material was
        removed from."""
        parts = [np.ravel_multi_index((d.ix, d.iy), shape) for d in self.deposits]
        return np.unique(np.concatenate(parts)) if parts else np.zeros(0, np.int64)

    def by_index(self) -> dict[int, DepositRemoval]:
        """The removals keyed by deposit index."""
        return {d.index: d for d in self.deposits}

    def within(self, mask) -> "Removal":
        """The part of this removal in the cells where ``mask`` (bool, (nx, ny)) is True."""
        mask = np.asarray(mask, dtype=bool)
        parts = []
        for d in self.deposits:
            sel = mask[d.ix, d.iy]
            if sel.any():
                vol = d.cell_volume_m3[sel]
                parts.append(DepositRemoval(d.index, d.info, float(np.sum(vol)), d.ix[sel],
                                            d.iy[sel], vol, d.deposition_time_ns[sel]))
        return Removal(tuple(parts))

    def removed_m(self, geometry: GridGeometry) -> np.ndarray:
        """Removed thickness per cell, all deposits, shape (nx, ny) (m)."""
        out = np.zeros(geometry.shape)
        for d in self.deposits:
            np.add.at(out, (d.ix, d.iy), d.cell_volume_m3 / geometry.cell_area_m2)
        return out


def removal_of_drops(cells, drops, geometry: GridGeometry, infos, times_rel,
                     epoch_ns: int | None) -> Removal:
    """What lowering the surfaces of a monotone layer stack over some cells removed.

    Deposit ``k`` lies between surfaces ``S(k-1)`` and ``S(k)``, so it lost the drop of
    ``S(k)`` less the drop of ``S(k-1)`` in each cell.

    Parameters
    ----------
    cells : ndarray of int, shape (c,)
        Flat indices into ``geometry.shape`` of the cells lowered.
    drops : sequence of (int, ndarray of shape (c,))
        ``(k, drop_m)`` per surface lowered, bottom-most first: ``S(k)`` went down by
        ``drop_m`` (m, >= 0, at least the drop of the surface below) at ``cells``; the
        surface below the first one did not move.
    geometry : GridGeometry
        The stack's grid.
    infos : sequence of DepositInfo
        ``infos[k - 1]`` is deposit ``k``.
    times_rel : sequence of ndarray, shape (nx, ny)
        ``times_rel[k - 1]``: deposit ``k``'s per-cell deposition time (ns) less
        ``epoch_ns``.
    epoch_ns : int or None
        The reference time of ``times_rel`` (UTC ns); None = 0.

    Returns
    -------
    Removal
        One :class:`DepositRemoval` per deposit that lost material, bottom to top.
    """
    area = geometry.cell_area_m2
    epoch = float(epoch_ns) if epoch_ns is not None else 0.0
    removals = []
    below = np.zeros(cells.size)
    for k, drop in drops:
        removed = drop - below  # (S(k) - S'(k)) - (S(k-1) - S'(k-1)) >= 0
        below = drop
        sel = removed > 0
        if not sel.any():
            continue
        lost = cells[sel]
        ix, iy = np.unravel_index(lost, geometry.shape)
        vol = removed[sel] * area
        removals.append(DepositRemoval(
            index=k, info=infos[k - 1], volume_m3=float(np.sum(vol)),
            ix=ix.astype(np.int64), iy=iy.astype(np.int64), cell_volume_m3=vol,
            deposition_time_ns=times_rel[k - 1].ravel()[lost] + epoch))
    return Removal(tuple(removals))
