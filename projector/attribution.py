"""Whose material a rise of the height map is, and when it was deposited.

A cell that rose is given to the stacking passes whose stacker crossed it since it was
last seen (:func:`rise_to_crossing_passes`), dated when each crossed it
(:func:`crossing_dates`); material no crossing explains is the top deposit's, dated by
:func:`deposition_ns`.  A lot's grade is looked up by these dates, in assay windows of
tens of seconds, so they place each layer's material where along the pass it was poured:
the poured cone's front reaches a cell before the boom does (:func:`pour_lead_s`,
:func:`projector.slump.pour_front_lead_m`).  Why each date is shifted as it is: see
docs/design-notes.md.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage

from schemas.times import NS_PER_S

from projector import slump
from projector.crossings import (crossing_ns, row_crests_m, row_y_m, stacker_speed_m_s,
                                 typical_pass_s)
from projector.repose import tan_repose
from projector.state import PassRecord, ProjectorState, around

__all__ = ["rise_to_crossing_passes", "crossing_dates", "deposition_ns", "pour_lead_s",
           "seen_nearby_ns"]


def rise_to_crossing_passes(state: ProjectorState, surface: np.ndarray,
                            seen_before_ns: np.ndarray, t_ns: int,
                            observed_ns: np.ndarray | None = None) -> np.ndarray:
    """Give each risen cell's material to the passes whose stacker crossed it since it
    was last seen, in equal shares, deposited when the stacker crossed (earlier near
    and past the end of its run: :func:`crossing_dates`); raises the stack in place and
    returns the cells still risen (bool, (nx, ny): no such pass, or a later deposit
    already holds material there).

    ``surface``: the level each risen cell rose to (m, (nx, ny), NaN where it did not
    rise); ``seen_before_ns``: when each cell was last seen before (UTC ns, NaN never).
    The crossings counted end at ``t_ns``, or earlier where ``observed_ns`` (the height
    map's layer) says the new level was first seen earlier: a rise sighted before a pass
    started and confirmed after is not that pass's material.
    """
    risen = np.isfinite(surface)
    passes = sorted(state.passes.values(), key=lambda p: p.deposit_index)
    if not passes:
        return risen
    cells = np.flatnonzero(risen)            # work on the risen cells only
    if cells.size == 0:
        return risen
    typical = typical_pass_s(passes)
    geometry = state.pile.geometry
    iy = cells % geometry.ny
    y = row_y_m(geometry)[iy]
    seen = _seen_before(state, seen_before_ns, cells)
    prev = np.where(np.isfinite(seen), seen, -np.inf)
    upto = np.full(cells.size, float(t_ns))
    if observed_ns is not None:
        upto = np.fmin(upto, observed_ns.ravel()[cells])
    cands = []
    for record in passes:
        crossing = crossing_ns(record, y, t_ns, typical)
        cands.append((record, crossing, (crossing > prev) & (crossing <= upto)))
    count = sum(c[2].astype(int) for c in cands)
    top = state.stack.surface().ravel()[cells]
    rise = surface.ravel()[cells] - top
    position, updates, crests = np.zeros(cells.size), [], None
    for record, crossing, hit in cands:
        position += hit
        if hit.any():
            share = (rise / np.maximum(count, 1))[hit]
            if crests is None:     # the stack is raised after the loop: one crest per row
                crests = row_crests_m(geometry, state.stack.surface())
            updates.append((record.deposit_index, cells[hit],
                            (top + rise * (position / np.maximum(count, 1)))[hit],
                            crossing_dates(state, record, cells[hit], share, crossing[hit],
                                           typical, crests)))
    state.stack, raised = state.stack.raise_deposits(updates)
    done = sum(int(r.sum()) for r in raised)
    if done:
        state.count("rises_by_crossing", done)
    # what is left: cells not fully raised (a later deposit already held material)
    with np.errstate(invalid="ignore"):
        return risen & (surface > state.stack.surface())


def _seen_before(state: ProjectorState, seen_before_ns: np.ndarray,
                 cells: np.ndarray) -> np.ndarray:
    """When each of ``cells`` (flat indices) was last seen (UTC ns, NaN never).

    A cell never seen itself lies between (or beside) seen ones: it was last seen when
    they were, not never (else every pass so far would share its rise).
    """
    seen = seen_before_ns.ravel()[cells]
    if not np.isfinite(seen).all():
        geometry = state.pile.geometry
        blind = ~np.isfinite(seen)
        bx, by = np.divmod(cells[blind], geometry.ny)
        box = around(bx, by, max(int(state.config.fill_gap_cells), 1), geometry)
        seen = seen.copy()
        seen[blind] = seen_nearby_ns(state, seen_before_ns[box])[bx - box[0].start,
                                                                 by - box[1].start]
    return seen


def seen_nearby_ns(state: ProjectorState, seen_ns: np.ndarray) -> np.ndarray:
    """``seen_ns`` with each never-seen cell given the latest time a cell within
    ``fill_gap_cells`` of it was seen (NaN where none was)."""
    size = 2 * max(int(state.config.fill_gap_cells), 1) + 1
    filled = ndimage.maximum_filter(np.where(np.isfinite(seen_ns), seen_ns, -np.inf),
                                    size=size, mode="constant", cval=-np.inf)
    return np.where(np.isfinite(seen_ns), seen_ns, np.where(np.isfinite(filled), filled, np.nan))


def crossing_dates(state: ProjectorState, record: PassRecord, cells: np.ndarray,
                   thickness_m: np.ndarray, crossed_ns: np.ndarray,
                   typical_s: float | None,
                   crests: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """When a pass laid its material in ``cells`` (flat indices, ``thickness_m`` of it
    each), given when its stacker crossed them (``crossed_ns``, UTC ns, float64, shape of
    ``cells``); ``crests``: :func:`projector.crossings.row_crests_m` of the stack's top,
    when the caller has it.

    Along the run the crossing stands: the cone's front lays a cell's layer before the
    boom comes (:func:`slump.pour_front_lead_m`), but a varying flow lays part of it
    after the boom has passed, for about as far again (:func:`slump.pour_reach_m`), and
    the two offset.  Toward the end of the run fewer releases come after the crossing:
    with less run left than the cone's reach the front's lead counts in proportion, in
    full at the end, and past the end (the pile's end slope, where the crossing is the
    pass's end) the boom stops short of the cell and the lead is the mean travel it still
    had to go (:func:`slump.pour_end_lead_m`).  Never before the pass started.
    """
    speed_m_s = stacker_speed_m_s(record, typical_s)
    if not speed_m_s > 0 or cells.size == 0:
        return crossed_ns
    geometry = state.pile.geometry
    ix, iy = np.divmod(cells, geometry.ny)
    x, crest = crests or row_crests_m(geometry, state.stack.surface())   # the boom's line
    offset = (x[ix] - crest[iy])[None, :]
    thickness = np.asarray(thickness_m, np.float64)[None, :]
    ahead = (record.end_y_m - row_y_m(geometry)[iy]) * np.sign(record.end_y_m
                                                                - record.start_y_m)
    tan = tan_repose(state, estimate=False)
    lead_m = slump.pour_end_lead_m(thickness, offset, np.clip(-ahead, 0.0, None)[None, :],
                                   tan)[0]
    reach = slump.pour_reach_m(thickness, offset, tan)[0]
    with np.errstate(invalid="ignore", divide="ignore"):
        weight = np.where(ahead <= 0, 1.0, np.clip(1.0 - ahead / reach, 0.0, 1.0))
    weight = np.where(reach > 0, weight, 0.0)
    return np.maximum(crossed_ns - weight * lead_m / speed_m_s * NS_PER_S,
                      float(record.started_ns))


def deposition_ns(state: ProjectorState, t_ns: int,
                  rising: np.ndarray | None = None) -> int | np.ndarray:
    """When the top deposit's material seen rising at ``t_ns`` was deposited: one integer
    (UTC ns) for every cell, or a float64 array of shape (nx, ny).  ``rising``: the cells
    (bool, (nx, ny)) about to rise, the only ones whose times are used (default all).

    Material of a pass was stacked as the stacker came over it
    (:func:`projector.crossings.crossing_ns`, a run along the rail), not when the
    scanner, which trails the stacker, saw it.  The poured cone's front reaches a cell
    before the boom does, the more so the thicker the layer and the further down the
    flank: the crossing less :func:`pour_lead_s`, with the layer as the height map (or
    the stack) stands over the deposit below.  It is never after ``t_ns`` nor outside the
    pass.  A pass without rail positions gives the time seen, clipped to the pass;
    material outside any pass, ``t_ns``.

    Only the material this dates (a rise no crossing explains, a catch-up, a completed
    flank) gets the lead; a rise given to the passes that crossed a cell since it was
    last seen keeps their crossings (:func:`rise_to_crossing_passes`).
    """
    info = state.stack.deposits[-1] if state.stack.n_deposits else None
    record = state.passes.get(info.pass_id) if info is not None and info.pass_id else None
    if record is None:
        return t_ns
    end = record.ended_ns if record.ended_ns is not None else t_ns
    seen = int(min(max(t_ns, record.started_ns), end))
    if not (math.isfinite(record.start_y_m) and math.isfinite(record.end_y_m)):
        return seen
    geometry = state.pile.geometry
    y = row_y_m(geometry)
    typical = typical_pass_s(state.passes.values())
    times = np.repeat(crossing_ns(record, y, t_ns, typical)[None, :], geometry.nx, axis=0)
    ix, iy = np.nonzero(np.ones(geometry.shape, bool) if rising is None else rising)
    top = state.stack.surface()
    # the pass's layer as it stands now: the map's level (or the stack's) over the deposit
    # below the pass's
    level = np.fmax(state.height.elevation[ix, iy], top[ix, iy])
    below = state.stack.surface_k(state.stack.n_deposits - 1)[ix, iy]
    times[ix, iy] -= pour_lead_s(state, record, level - below, ix, iy, top, typical) * NS_PER_S
    return np.clip(times, float(record.started_ns), float(seen))


def pour_lead_s(state: ProjectorState, record: PassRecord, thickness_m: np.ndarray,
                ix: np.ndarray, iy: np.ndarray, top_m: np.ndarray,
                typical_s: float | None) -> np.ndarray:
    """How long before its stacker crossed cells ``(ix, iy)`` a pass laid its layer there,
    on average (s, shape of ``ix``; 0 where unknown): :func:`slump.pour_front_lead_m` over
    the stacker's speed along the rail.

    The boom pours on the crest: each row's line is where the stack's top (``top_m``,
    (nx, ny)) is highest.  ``thickness_m``: the pass's layer at each cell (m);
    ``typical_s``: the duration assumed for a pass still running
    (:func:`projector.crossings.typical_pass_s`).
    """
    geometry = state.pile.geometry
    speed_m_s = stacker_speed_m_s(record, typical_s)
    if not speed_m_s > 0 or ix.size == 0:
        return np.zeros(ix.shape)
    x, crest = row_crests_m(geometry, top_m)
    offset = x[ix] - crest[iy]
    lead_m = slump.pour_front_lead_m(thickness_m[None, :], offset[None, :],
                                     tan_repose(state, estimate=False))[0]
    return lead_m / speed_m_s
