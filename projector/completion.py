"""What the scans did not see: flanks hidden behind the crest and layers under the margin.

A cell a stacking pass crossed since it was last seen (or never seen) holds at least the
repose cone of the seen surface (:func:`unseen_floor`): :func:`complete_unseen` raises
the stack to it, the material given to the passes that crossed.  A layer thinner than a
cell's noise margin is taken up where the cells around agree that it rose
(:func:`catch_up_rises`).  Both run when the next pass starts, at the first cut after a
pass and at a query's end, and update the state in place.  Why each threshold is what it
is: see docs/design-notes.md.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from schemas.times import NS_PER_S

from projector import slump
from projector.elevation import fill_holes
from projector.attribution import deposition_ns, rise_to_crossing_passes
from projector.crossings import (last_crossings, row_crests_m, stacker_speed_m_s, stale,
                                 typical_pass_s)
from projector.cuts import journal_rises
from projector.repose import cone, tan_repose
from projector.state import ProjectorState
from projector.surface_fit import plane_fit_of_seen

__all__ = ["filled_elevation", "unseen_floor", "seen_while_pouring", "complete_unseen",
           "accounted_ns", "catch_up_rises"]


def filled_elevation(state: ProjectorState) -> np.ndarray:
    """The height map's elevation (m, (nx, ny)) with gaps of up to ``fill_gap_cells``
    interpolated."""
    if not state.config.fill_gap_cells:
        return state.height.elevation
    return fill_holes(state.height.elevation, method="linear",
                                max_gap_cells=state.config.fill_gap_cells)


def unseen_floor(state: ProjectorState, elevation: np.ndarray, t_ns: int,
                 pouring_ns: np.ndarray | None = None) -> np.ndarray:
    """The repose cone of the (gap-filled) ``elevation`` (m, (nx, ny)) where a pass
    crossed a cell since it was last seen (or it was seen while the pass still poured on
    it, :func:`seen_while_pouring`), NaN elsewhere: a cell seen since is as measured,
    whatever the cone.

    A never-seen cell's cone rises from the seen heights fitted with a plane over
    ``cone_smooth_cells`` x ``cone_smooth_cells`` cells
    (:func:`projector.surface_fit.plane_fit_of_seen`), not from their noisy maximum; so does a cell
    seen while poured on (it lies down a flank seen with few points).  ``pouring_ns``: the
    :func:`seen_while_pouring` of this state, when the caller has it.
    """
    stale_ = stale(state, t_ns)
    fitted = stale_ & ~np.isfinite(state.height.grid["last_update_ns"])
    if state.config.pouring_tail:
        if pouring_ns is None:
            pouring_ns = seen_while_pouring(state, t_ns)
        pouring = np.isfinite(pouring_ns) & ~stale_
        stale_ = stale_ | pouring
        fitted = fitted | pouring
    floor = cone(state, elevation)
    n = int(state.config.cone_smooth_cells)
    if n > 1 and fitted.any():
        floor = np.where(fitted, cone(state, plane_fit_of_seen(elevation, n)), floor)
    return np.where(stale_, floor, np.nan)


def seen_while_pouring(state: ProjectorState, t_ns: int) -> np.ndarray:
    """When the last pass to cross each cell by ``t_ns`` crossed it (UTC ns, float64,
    (nx, ny)) where the cell was last seen after that crossing but while the pass's cone
    could still reach it; NaN elsewhere.  The pass has ended, and the look came less than
    :func:`slump.pour_reach_m` of rail travel after the crossing.

    A pass's flow varies, and each surge of the cone on its line reaches far down the
    flanks, behind the boom as well as ahead of it (by the pass's median layer, offset
    from the crest of each row): a flank the scanner looked at only just after the
    stacker passed was still filling.  Only the last crossing of each row counts.
    """
    geometry = state.pile.geometry
    out = np.full(geometry.shape, np.nan)
    passes, latest, last_crossing = last_crossings(state, t_ns)
    if not passes or state.stack is None:
        return out
    typical = typical_pass_s(passes)
    seen = state.height.grid["last_update_ns"]
    x, crest = row_crests_m(geometry, state.stack.surface())
    for i in np.unique(latest):
        record = passes[int(i)]
        rows = (latest == i) & np.isfinite(last_crossing)
        speed = stacker_speed_m_s(record, typical)
        if record.ended_ns is None or not rows.any() or not speed > 0:
            continue
        thickness = state.stack.thickness(record.deposit_index)
        layer = thickness[thickness > 0]
        if layer.size == 0:
            continue
        offset = x[:, None] - crest[None, rows]
        reach = slump.pour_reach_m(np.full(offset.shape, float(np.median(layer))), offset,
                                   tan_repose(state, estimate=False))
        crossed = np.broadcast_to(last_crossing[rows][None, :], offset.shape)
        look = seen[:, rows]
        with np.errstate(invalid="ignore"):
            poured_on = (look >= crossed) & (look < np.minimum(
                crossed + reach / speed * NS_PER_S, float(t_ns)))
        out[:, rows] = np.where(poured_on, crossed, np.nan)
    return out


def complete_unseen(state: ProjectorState, t_ns: int,
                    filled_m: np.ndarray | None = None) -> np.ndarray | None:
    """Raise the stack (in place) to the repose cone of the seen surface where it is
    below it.

    A flank hidden behind the crest keeps its last seen (older, lower) height in the
    height map; the pile there is at least as high as the cone.  Its material goes to
    the passes that crossed the cell since it was last seen.  Returns the
    :func:`unseen_floor` it used (None when it had none), for
    :func:`projector.follow.follow_height`.  ``filled_m``: the :func:`filled_elevation`,
    when the caller has it.
    """
    if not state.config.complete_unseen or state.stack is None or state.stack.n_deposits == 0:
        return None
    elevation = filled_elevation(state) if filled_m is None else filled_m
    if not np.isfinite(elevation).any():
        return None
    pouring_ns = seen_while_pouring(state, t_ns) if state.config.pouring_tail else None
    floor = unseen_floor(state, elevation, t_ns, pouring_ns)
    top = state.stack.surface()
    # A stale cell's margin is the fixed part only: a never-seen cell has no variance of
    # its own, and a seen one's says how well its old level was known, not whether the
    # pile is still there (a pass crossed it since).
    margin = state.margin_m
    with np.errstate(invalid="ignore"):
        lift = (floor > top + margin) & ~(elevation >= floor - margin)
    if not lift.any():
        return floor
    level = np.where(lift, floor, np.nan)
    before = state.stack.total_volume_m3()
    accounted = accounted_ns(state, state.height.grid["last_update_ns"])
    if pouring_ns is not None:
        # a look while a pass still poured saw part of its layer: that pass crossed since
        # (unless a completion after its crossing already took the layer)
        with np.errstate(invalid="ignore"):
            open_ = np.isfinite(pouring_ns) & ~(accounted > state.height.grid["last_update_ns"])
        accounted = np.where(open_, pouring_ns - 1.0, accounted)
    left = rise_to_crossing_passes(state, level, accounted, t_ns)
    if left.any() and state.stack.n_deposits:
        # no pass crossed since the cell was seen: the top deposit's (it stands above it)
        state.stack, _added = state.stack.raise_to(np.where(left, level, np.nan),
                                                   deposition_ns(state, t_ns, left))
    # a new array each time (never written in place: a snapshot's arrays are read-only)
    state.completed_ns = np.where(lift, float(t_ns), np.nan if state.completed_ns is None
                                  else state.completed_ns)
    journal_rises(state, t_ns, np.flatnonzero(lift), top)
    state.count("cells_completed", int(lift.sum()))
    state.count("completed_mm3", int(round((state.stack.total_volume_m3() - before) * 1e3)))
    return floor


def accounted_ns(state: ProjectorState, seen_ns: np.ndarray) -> np.ndarray:
    """Since when each cell's material is accounted for (UTC ns, (nx, ny), NaN never): the
    later of when it was last seen (``seen_ns``) and when it was last completed to the
    repose cone.

    A rise is given to the passes that crossed a cell since then.  A never-seen cell is
    completed at each pass's start as the cone of the growing pile rises; counted from
    never, each increment would be shared by every pass so far.
    """
    if state.completed_ns is None:
        return seen_ns.copy()
    return np.fmax(seen_ns, state.completed_ns)


def catch_up_rises(state: ProjectorState, t_ns: int) -> None:
    """Raise the stack (in place) to the height map where it is below it by less than the
    margin but the cells around agree that it rose.

    Each cell follows a rise only beyond its own noise margin, so a layer thinner than
    the margin is taken up only partly.  Pooled over ``catch_up_cells`` x
    ``catch_up_cells`` seen cells the mean rise is known far better: where it exceeds
    3 sigma of that mean (and nothing more), the cells that are above the stack rise to
    the height map, their material the top deposit's (the pass before the next).
    """
    n = int(state.config.catch_up_cells)
    if n < 2 or state.stack is None or state.stack.n_deposits == 0:
        return
    elevation = state.height.elevation
    seen = np.isfinite(elevation)
    if not seen.any():
        return
    top = state.stack.surface()
    diff = np.where(seen, elevation - top, 0.0)
    var = np.where(seen, np.nan_to_num(state.height.variance, nan=0.0), 0.0)
    count = ndimage.uniform_filter(seen.astype(float), n, mode="constant")
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = ndimage.uniform_filter(diff, n, mode="constant") / count
        pooled_var = ndimage.uniform_filter(var, n, mode="constant") / count / (count * n * n)
        up = seen & (diff > 0) & (count * n * n >= 0.5 * n * n) & (
            mean > 3.0 * np.sqrt(pooled_var))
    if not up.any():
        return
    before = state.stack.total_volume_m3()
    state.stack, _added = state.stack.raise_to(np.where(up, elevation, np.nan),
                                               deposition_ns(state, t_ns, up))
    journal_rises(state, t_ns, np.flatnonzero(up), top)
    state.count("cells_caught_up", int(up.sum()))
    state.count("caught_up_mm3", int(round((state.stack.total_volume_m3() - before) * 1e3)))
