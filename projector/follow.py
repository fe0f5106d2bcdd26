"""The layer stack follows the height map (:func:`follow_height`).

Where the fused height map and the stack's top differ beyond a cell's noise margin, the
stack moves to the map, in place.  A rise is given to the passes whose stacker crossed
the cell since it was last seen (:func:`projector.attribution.rise_to_crossing_passes`),
else to the top deposit: the open pass's, the pass that ended last while its layer
settles, or a flagged deposit outside any pass.  A drop is clamped off the stack and
charged to the latest cut as its geometry residual where it lies near that cut's
footprint (before any cut: an unexplained loss); away from it, a face that failed
later slides to repose (:func:`projector.material_fit.slide_seen_failure`), else the
stack keeps its own slid face unless ``FoldConfig.follow_far_drops``.  The latest cut's
face, while open, is not followed (:func:`projector.material_fit.face_cells`).
"""

from __future__ import annotations

import numpy as np

from projector.elevation import fill_holes
from projector.attribution import deposition_ns, rise_to_crossing_passes
from projector.completion import filled_elevation, unseen_floor
from projector.crossings import stale
from projector.cuts import journal_rises, near_cut
from projector.layers import DepositInfo
from projector.material_fit import face_cells, note_sightings, slide_seen_failure
from projector.state import ProjectorState, last_event_ns, settling_last_pass

__all__ = ["follow_height"]


def follow_height(state: ProjectorState, t_ns: int, *, drops: bool = True,
                  seen_before_ns: np.ndarray | None = None,
                  sighted_before_ns: np.ndarray | None = None, region=None,
                  unseen_floor_m: np.ndarray | None = None,
                  filled_m: np.ndarray | None = None) -> None:
    """Move the layer stack's top (in place) to the height map where they differ beyond
    the margin, at ``t_ns`` (UTC ns).

    Rises follow at once.  Drops follow only when ``drops`` (at a cut, or at the end of
    a query): a cut is known only when its event arrives at its end time, after the
    scans that watched it dig, so a drop seen by those scans must wait for that cut
    rather than be charged to the one before.  ``region``: the (slice, slice) block a
    batch of scans saw (rises only), default the whole grid.  ``seen_before_ns``: when
    each cell's material was last accounted for (UTC ns, (nx, ny)), to give a rise to the
    passes that crossed it since; ``sighted_before_ns``: when each cell was last seen
    before this batch, so that a first sight is not journaled.  ``unseen_floor_m``: the
    :func:`projector.completion.unseen_floor` of the current height map, when the caller
    has it; ``filled_m`` its :func:`projector.completion.filled_elevation` (with no
    ``region``).
    """
    note_sightings(state)   # after every batch of scans: the open face's first looks
    region, elevation = _elevation_to_follow(state, t_ns, drops, region, unseen_floor_m,
                                             filled_m)
    top_r = state.stack.surface()[region]
    with np.errstate(invalid="ignore"):
        margin = state.config.margin_sigma * np.sqrt(
            np.nan_to_num(state.height.variance[region], nan=0.0)) + state.margin_m
        up_r = np.isfinite(elevation) & (elevation > top_r + margin)
        down_r = np.isfinite(elevation) & (elevation < top_r - margin)
    if not (up_r.any() or (drops and down_r.any())):
        return
    shape = state.pile.geometry.shape
    up, down = np.zeros(shape, bool), np.zeros(shape, bool)
    up[region], down[region] = up_r, down_r
    face = face_cells(state, elevation if elevation.shape == shape else None)
    if face is not None:
        # an open face follows the scans once they are fitted (material_fit.close_face)
        up &= ~face[0]
        down &= ~face[1]
        if not (up.any() or (drops and down.any())):
            return
    if elevation.shape != shape:
        block, elevation = elevation, np.full(shape, np.nan)
        elevation[region] = block
    top = state.stack.surface()
    rising = np.flatnonzero(up)
    if up.any() and seen_before_ns is not None:
        up = rise_to_crossing_passes(state, np.where(up, elevation, np.nan), seen_before_ns,
                                     t_ns, observed_ns=state.height.grid["observed_ns"]) & up
    if up.any():
        _raise_to_map(state, t_ns, up, elevation)
    if rising.size:
        first_sight = None
        if sighted_before_ns is not None:
            first_sight = stale(state, t_ns, seen_ns=sighted_before_ns)
        journal_rises(state, t_ns, rising, top, first_sight=first_sight)
    if drops and down.any():
        _follow_drops(state, t_ns, down, elevation, top)


def _elevation_to_follow(state: ProjectorState, t_ns: int, drops: bool, region,
                         unseen_floor_m: np.ndarray | None, filled_m: np.ndarray | None):
    """``(region, elevation)``: the block the stack follows the map over (whole grid when
    ``region`` is None) and the map's elevation there (m), gaps filled; with ``drops``
    (and ``complete_unseen``) raised to the cone of cells unseen since a pass crossed
    them: such a cell is no lower than the cone (and was raised to it), not a drop."""
    if region is not None:
        if drops:
            raise ValueError("a region is for rises only (drops=False)")
        # only the block a batch of scans saw can have risen (rises only: drops wait)
        elevation = state.height.elevation[region]
        if state.config.fill_gap_cells:
            # an unseen strip between seen cells (between two scan lines, behind a
            # crest) is interpolated rather than left at the ground
            elevation = fill_holes(elevation, method="linear",
                                             max_gap_cells=state.config.fill_gap_cells)
    else:
        region = (slice(None), slice(None))
        elevation = filled_elevation(state) if filled_m is None else filled_m
    if drops and state.config.complete_unseen:
        if unseen_floor_m is None:
            unseen_floor_m = unseen_floor(state, elevation, t_ns)
        elevation = np.fmax(elevation, unseen_floor_m)
    return region, elevation


def _raise_to_map(state: ProjectorState, t_ns: int, up: np.ndarray,
                  elevation: np.ndarray) -> None:
    """Raise the top deposit to ``elevation`` (m, (nx, ny)) in the cells ``up`` (bool).

    Outside a pass (and not while the last pass's layer settles) the top deposit is a
    flagged one: after the cuts began, one flagged deposit (the top one) takes every
    slide's material (a deposit per cut would grow the state by a layer each); before
    them, a flagged deposit opened before the latest pass boundary is not reused.  What
    rises outside a pass after a cut slumped into its hole from its face: the cut did not
    take it (its ``returned_m3``).
    """
    outside = state.active_pass is None and not settling_last_pass(state)
    if outside:
        info = state.stack.deposits[-1] if state.stack.n_deposits else None
        if info is None or not info.flagged or (not state.cuts
                                               and info.opened_ns < last_event_ns(state)):
            state.stack = state.stack.open_deposit(
                DepositInfo(state.stack.n_deposits + 1, "", "", t_ns, flagged=True))
    state.stack, added = state.stack.raise_to(np.where(up, elevation, np.nan),
                                              deposition_ns(state, t_ns, up))
    state.count("rises")
    if state.active_pass is None and state.cuts and not settling_last_pass(state):
        state.cuts[-1].returned_m3 += added


def _follow_drops(state: ProjectorState, t_ns: int, down: np.ndarray,
                  elevation: np.ndarray, top: np.ndarray) -> None:
    """Clamp the stack to ``elevation`` (m) in the cells ``down`` (bool, (nx, ny)) and
    charge what that removes: near the latest cut (:func:`projector.cuts.near_cut`), to
    it as its geometry residual (before any cut: an unexplained loss); away from it, a
    face that failed later slides to repose when a failure explains the drop
    (:func:`projector.material_fit.slide_seen_failure`, at ``t_ns``); beyond that, unless
    ``follow_far_drops``, the stack keeps its own face (``top``, m, the stack's top before
    this follow, or after that slide) and counter ``far_drops_mm3`` says how far the
    measurement lies below it, followed, an unexplained loss (counter
    ``unexplained_loss_mm3``)."""
    near = down
    if state.cuts:
        near = down & near_cut(state, state.cuts[-1])
    far = down & ~near
    if state.cuts and far.any() and slide_seen_failure(state, far, elevation, t_ns) > 0:
        top = state.stack.surface()
        with np.errstate(invalid="ignore"):
            far &= elevation < top
    if state.cuts and not state.config.follow_far_drops:
        # the stack keeps its own slid face away from the cut; the gap is reported
        with np.errstate(invalid="ignore"):   # no deeper than the ground
            below = float(np.sum(np.where(
                far, top - np.maximum(elevation, state.stack.ground()), 0.0)))
        state.counters["far_drops_mm3"] = int(round(
            below * state.pile.geometry.cell_area_m2 * 1e3))
        down, far = near, np.zeros_like(far)
        if not down.any():
            return
    # one clamp for all the drops (each lowered surface is copied once), split after
    state.stack, removal = state.stack.clamp(np.where(down, elevation, np.inf))
    if near.any():
        inside = removal.within(near)
        if state.cuts:
            cut = state.cuts[-1]
            cut.removals.append(inside)
            cut.residual_m3 += inside.volume_m3
        else:
            state.flagged_loss_m3 += inside.volume_m3
    if far.any():
        # the measurement wins, but a drop far from the cut is not what it delivered
        outside = removal.within(far)
        state.flagged_loss_m3 += outside.volume_m3
        state.count("unexplained_loss_mm3", int(round(outside.volume_m3 * 1e3)))
