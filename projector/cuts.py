"""The steps of a reclaim cut that the fold takes besides clamping to its envelope floor.

Before the clamp: rises the cut's own digging caused in its footprint are undone
(:func:`undo_digging_rises`, from the journal :func:`journal_rises` keeps), the buried
deposit tops are fitted once the passes that laid them are complete
(:func:`fit_buried_boundaries`) and the top the cut takes is fitted where it stands above
the floor (:func:`fit_top_for_cut`).  After it: the height map takes the predicted top
(:func:`predict_height`; the face's slide is :mod:`projector.material_fit`'s, and
:func:`slump_face` slides a face to the angle of repose at once, for diagnosis).  Later
drops count as the cut's geometry residual only near its footprint (:func:`near_cut`).
Each step updates the state in place.  Why each step is there: see docs/design-notes.md.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage

from schemas.times import NS_PER_S

from projector import heightmap, slump
from projector.repose import tan_repose
from projector.state import CutRecord, ProjectorState

__all__ = ["journal_rises", "undo_digging_rises", "near_cut", "predict_height",
           "fit_buried_boundaries", "fit_top_for_cut", "slide_region", "slump_face"]


def journal_rises(state: ProjectorState, t_ns: int, cells: np.ndarray,
                  top_before_m: np.ndarray, first_sight: np.ndarray | None = None) -> None:
    """Note in ``state.rises_journal`` in which of ``cells`` (flat indices) the stack's
    top rose, from what level (``top_before_m``, (nx, ny)), at ``t_ns``; entries older than ``dig_journal_s``
    before it are dropped.  A rise that was the height map's first sight of its cell since
    a pass crossed it (``first_sight``, (nx, ny) bool; None for a catch-up or a
    completion, which follow no sighting of their own) is not noted: its level before was
    never measured, so no cut undoes it (:func:`undo_digging_rises`)."""
    rose = state.stack.surface().reshape(-1)[cells] > top_before_m.reshape(-1)[cells]
    if first_sight is not None:
        rose &= ~first_sight.reshape(-1)[cells]
    cells = cells[rose]
    if cells.size:
        state.rises_journal.append((int(t_ns), cells.astype(np.int32),
                                    top_before_m.reshape(-1)[cells]))
    oldest = t_ns - int(state.config.dig_journal_s * NS_PER_S)
    while state.rises_journal and state.rises_journal[0][0] < oldest:
        state.rises_journal.pop(0)


def undo_digging_rises(state: ProjectorState, start_ns: int, footprint: np.ndarray) -> float:
    """Lower the stack (in place) in a cut's footprint (bool, (nx, ny)) to where it was
    before the rises seen from its start (UTC ns) on; returns the volume taken off (m3).

    While the wheel digs, scans see the walls it leaves standing (the face slides only
    once it has passed) and, rasterised into the cells around them, read the footprint
    high.  What rose there then is not material the cut found, and it is not added to it.

    A rise in a cell the map had not seen since a pass last crossed it stays (it is not
    journaled, :func:`journal_rises`): its level before was never measured (a pile end's
    toe, hidden from the rail, is first seen from the reclaimer).
    """
    target = np.full(state.pile.geometry.shape, np.inf)
    flat = target.reshape(-1)
    for t_ns, cells, before in state.rises_journal:
        if t_ns >= start_ns:
            np.minimum.at(flat, cells, before)
    target[~footprint] = np.inf
    if not np.isfinite(target).any():
        return 0.0
    state.stack, removal = state.stack.clamp(target)
    state.count("digging_rises_undone_mm3", int(round(removal.volume_m3 * 1e3)))
    return removal.volume_m3


def near_cut(state: ProjectorState, cut: CutRecord) -> np.ndarray:
    """Cells a cut can have taken material from: its footprint (where its envelope
    removed material) grown by one cell (a wall point rasterised beside it), shape
    (nx, ny).

    A drop further out is the face sliding into the hole the cut left (it shows there
    as a rise): the material moved, it did not go onto the belt.
    """
    g = state.pile.geometry
    footprint = np.zeros(g.shape, bool)
    for removal in cut.removals[:1]:       # the envelope's own removal
        for d in removal.deposits:
            footprint[d.ix, d.iy] = True
    if not footprint.any():
        return footprint
    return ndimage.binary_dilation(footprint, structure=np.ones((3, 3), bool))


def predict_height(height, new_top_m: np.ndarray, old_top_m: np.ndarray, sd_m: float):
    """The height map (a :class:`projector.heightmap.HeightMap`; a new one, ``height`` is
    left alone) after a cut: cells whose stack top the cut (or the slide of its face)
    moved from ``old_top_m`` to ``new_top_m`` (m, (nx, ny)) take the new top.

    Their variance becomes one point's (``sd_m`` squared: the prediction is as good as a
    fresh observation) and pending change evidence is dropped, so the scans after the cut
    confirm it by Kalman steps or correct it through the change gate.
    """
    grid = height.copy().grid
    elevation = grid["elevation"]
    with np.errstate(invalid="ignore"):
        moved = (np.abs(new_top_m - old_top_m) > 1e-9) & (
            np.isfinite(elevation) | (new_top_m > old_top_m))
    if not moved.any():
        return height
    elevation[moved] = new_top_m[moved]
    grid["variance"][moved] = sd_m * sd_m
    heightmap.clear_evidence(grid, moved)
    return type(height)(grid)


def fit_buried_boundaries(state: ProjectorState) -> None:
    """Fit (in place) the tops of the deposits below the top one that are not fitted yet
    (``FoldConfig.boundary_fit_cells``): the passes that laid them are complete."""
    window, n = int(state.config.boundary_fit_cells), state.stack.n_deposits
    if window < 3 or n - 1 <= state.boundaries_fitted:
        return
    state.stack = state.stack.fit_boundaries(range(state.boundaries_fitted + 1, n), window)
    state.count("boundaries_fitted", n - 1 - state.boundaries_fitted)
    state.boundaries_fitted = n - 1


def fit_top_for_cut(state: ProjectorState, floor_m: np.ndarray) -> np.ndarray | None:
    """Put the top a cut is about to take (in place) on a local quadratic fit where it
    stands above the cut's floor (``floor_m``, m, (nx, ny), +inf outside its footprint;
    ``FoldConfig.cut_fit_cells``); counter ``cut_top_fit_mm3``: the volume the fit added
    to the stack less what it removed (before the caller restores the part under the
    floor after the cut).

    Returns the heights to clamp the stack to after the cut (shape (nx, ny), +inf
    elsewhere; None: nothing to restore): where the top stood under the floor and its fit
    above, the rise put material under the floor that the cut leaves; the top there goes
    back to where it was.
    """
    window = int(state.config.cut_fit_cells)
    if window < 3:
        return None
    top = state.stack.surface()
    before = state.stack.total_volume_m3()
    state.stack = state.stack.fit_top_above(floor_m, window)
    state.count("cut_top_fit_mm3", int(round((state.stack.total_volume_m3() - before) * 1e9)))
    with np.errstate(invalid="ignore"):
        rose = (state.stack.surface() > top) & (top < floor_m)
    return np.where(rose, top, np.inf) if rose.any() else None


def slide_region(state: ProjectorState, cells: np.ndarray, tan: float
                 ) -> tuple[slice, slice]:
    """The block a slide at slope ``tan`` starting from ``cells`` (bool, (nx, ny), some
    True) may move: their bounding box padded by a flank's run from the stack's top down
    to its ground, and two cells."""
    geometry = state.pile.geometry
    ix, iy = np.nonzero(cells)
    height = float(np.max(state.stack.surface()) - np.min(state.stack.ground()))
    pad = int(math.ceil(height / tan / geometry.cell_m)) + 2
    return (slice(max(0, ix.min() - pad), min(geometry.nx, ix.max() + pad + 1)),
            slice(max(0, iy.min() - pad), min(geometry.ny, iy.max() + pad + 1)))


def slump_face(state: ProjectorState, floor_m: np.ndarray) -> float:
    """Let the face a cut left slide (in place) to the angle of repose
    (:func:`projector.slump.slump`, mass and composition conserved, over
    :func:`slide_region` of the envelope ``floor_m``'s cells); returns the volume moved (m3)."""
    tan = tan_repose(state) * (1.0 + state.config.relax_slack)
    footprint = np.isfinite(floor_m)
    if not footprint.any():
        return 0.0
    region = slide_region(state, footprint, tan)
    state.stack, moved, _raised = slump.slump(state.stack, tan, region)
    state.count("slumps")
    return moved.volume_m3
