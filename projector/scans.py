"""Scans into the height map: the fold's batches of scans (:func:`process_scans`).

A scan waits for the scanner pose after it; then, in batches, scans are georeferenced
(:mod:`projector.georef`), their profiles cleaned (:mod:`projector.profile`), their
heights referenced to the declared ground they see (:func:`reference_ground`),
rasterised and fused into the height map (:mod:`projector.heightmap`), after the cells a
stacking pass reached since they were last seen are refreshed (:func:`refresh_crossed`:
their old height no longer holds).  The stack then follows the rises the batch shows
(:func:`projector.follow.follow_height`).  Everything updates the state in place.
"""

from __future__ import annotations

import math

import numpy as np

from schemas.times import NS_PER_S

from projector import georef, ground, heightmap, profile
from projector.completion import accounted_ns
from projector.crossings import crossing_ns, row_y_m, typical_pass_s
from projector.follow import follow_height
from projector.repose import flank_reach_m
from projector.state import PendingScan, ProjectorState, around

__all__ = ["note_pending", "note_pose", "process_scans", "reference_ground", "refresh_crossed",
           "scan_is_ready"]


def process_scans(state: ProjectorState, *, until_ns: int | None = None,
                  final: bool = False) -> None:
    """Fuse the waiting scans that have a pose of their own scanner after them (all up to
    ``until_ns``, UTC ns); ``final``: drop those that have none (at a query's end)."""
    ready = _ready_scans(state, until_ns, final)
    if not ready:
        return
    by_beams: dict[tuple[str, int, float, float], list[PendingScan]] = {}
    for frame, scan in ready:
        by_beams.setdefault((frame, scan.ranges_m.size, scan.start_angle_rad,
                             scan.end_angle_rad), []).append(scan)
    for (frame, beams, start, end), scans in by_beams.items():
        if beams < 2:
            state.count("scans_unusable", len(scans))
            continue
        track = state.poses[frame]
        t = np.asarray([s.t_ns for s in scans], np.int64)
        xyz, q = georef.interpolate_poses(t, np.asarray(track.t_ns, np.int64),
                                          np.asarray(track.xyz, np.float64),
                                          np.asarray(track.q, np.float64),
                                          max_gap_ns=state.config.max_pose_gap_ns)
        ranges = np.stack([s.ranges_m for s in scans])
        ranges = profile.clean_profile(ranges, fit_beams=state.config.profile_fit_beams,
                                       grazing_frac=state.config.grazing_mixed_frac)
        increment = (end - start) / (beams - 1)
        points = georef.georeference(ranges, start, increment, xyz, q)
        if state.config.ground_reference:
            points[..., 2] -= reference_ground(state, t, points)[:, None]
        points = points.reshape(-1, 3)
        points = points[np.isfinite(points).all(axis=1)]
        state.count("scans_fused", len(scans))
        state.count("points_fused", len(points))
        if len(points) == 0:
            continue
        obs = heightmap.rasterize(state.pile.geometry, points)
        if obs.ix.size == 0:     # a scanner that saw only another pile, or the ground
            continue
        _fuse_batch(state, obs, int(t.max()))


def track_frame(state: ProjectorState, frame_id: str) -> str | None:
    """The pose track that places a scan of ``frame_id``: its own, or with one scanner in
    the yard the only track there is (a scan and its poses that name the frame
    differently); None: no pose of it yet."""
    if frame_id in state.poses:
        return frame_id
    if len(state.poses) == 1:
        return next(iter(state.poses))
    return None


def _ready_scans(state: ProjectorState, until_ns: int | None,
                 final: bool) -> list[tuple[str, PendingScan]]:
    """Take the waiting scans that have a pose of their own scanner after them out of
    ``state.pending``, each with its track's frame; those that never will (up to
    ``until_ns``, all when ``final``, or waiting longer than ``max_scan_wait_ns``) are
    dropped (counted ``scans_without_pose``)."""
    if not state.pending or state.pile is None:
        return []
    ready, waiting = [], []
    floors: dict[str, int] = {}
    for scan in state.pending:
        frame = track_frame(state, scan.frame_id)
        last_pose = state.poses[frame].t_ns[-1] if frame is not None else None
        if last_pose is not None and scan.t_ns <= last_pose:
            ready.append((frame, scan))
        elif final or (until_ns is not None and scan.t_ns <= until_ns
                       and (last_pose is None or scan.t_ns < last_pose)) \
                or (last_pose is not None
                    and last_pose - scan.t_ns > state.config.max_scan_wait_ns):
            state.count("scans_without_pose")
        else:
            waiting.append(scan)
            if scan.t_ns < floors.get(scan.frame_id, scan.t_ns + 1):
                floors[scan.frame_id] = scan.t_ns
    state.pending, state.pending_floor_ns = waiting, floors
    state.pending_settled = True
    return ready


def note_pending(state: ProjectorState, scan: PendingScan) -> None:
    """Add ``scan`` to the waiting scans; unsettle them if its pose is already here."""
    state.pending.append(scan)
    floors = state.pending_floor_ns
    if scan.t_ns < floors.get(scan.frame_id, scan.t_ns + 1):
        floors[scan.frame_id] = scan.t_ns
    if scan_is_ready(state, scan):
        state.pending_settled = False


def note_pose(state: ProjectorState, frame: str, t_ns: int, new_track: bool) -> None:
    """A pose at ``t_ns`` was added to track ``frame``: unsettle the waiting scans if it
    makes one ready (a new track may place scans of other frames: always)."""
    if new_track or any(floor <= t_ns and track_frame(state, f) == frame
                        for f, floor in state.pending_floor_ns.items()):
        state.pending_settled = False


def scan_is_ready(state: ProjectorState, scan: PendingScan) -> bool:
    """Whether ``scan`` has a pose of its own scanner at or after its time."""
    frame = track_frame(state, scan.frame_id)
    return frame is not None and scan.t_ns <= state.poses[frame].t_ns[-1]


def _fuse_batch(state: ProjectorState, obs, t_ns: int) -> None:
    """Fuse one batch's rasterised observations (:class:`heightmap.CellObservations`) taken
    up to ``t_ns`` into the height map, then let the stack follow the rises.

    A cell seen by several points of this batch that agree is strong evidence of a change
    on its own (a stacked layer rises between two patrols, so waiting for agreeing patrols
    would never accept it); a cell seen by a point or two needs repeated agreeing
    observations.
    """
    seen_before_ns = state.height.grid["last_update_ns"].copy()
    if state.config.refresh_crossed:
        refresh_crossed(state, obs, t_ns, seen_before_ns)
    strong = obs.count >= state.config.strong_points
    for subset, change_count in ((strong, 1), (~strong, state.config.change_count)):
        if subset.any():
            state.height, _stats = heightmap.fuse(
                state.height, _subset(obs, subset), t_ns, state.point_sd_m,
                gate_sigma=state.config.gate_sigma, change_count=change_count,
                process_sd_m=state.process_sd_m, inplace=True)
    follow_height(state, t_ns, drops=False,
                  seen_before_ns=accounted_ns(state, seen_before_ns),
                  sighted_before_ns=seen_before_ns,
                  region=around(obs.ix, obs.iy, state.config.fill_gap_cells + 1,
                                state.pile.geometry))


def reference_ground(state: ProjectorState, t_ns: np.ndarray, points: np.ndarray) -> np.ndarray:
    """The height offset (m) to subtract from each scan's points, shape (S,), for scans
    taken at ``t_ns`` (UTC ns, (S,)) with georeferenced ``points`` (m, (S, beams, 3)).

    Candidate ground points lie over cells the layer stack holds as bare (no more than
    ``margin_m`` of material); :func:`projector.ground.height_corrections` finds
    each scan's ground level among them and pools the scans within ``ground_window_s``.
    A pooled offset within ``ground_deadband_sigma`` standard errors or
    ``ground_deadband_m`` of 0 is not applied; a scan whose window saw no ground holds the
    last offset applied up to ``ground_hold_s`` before it (else 0).  Counters: scans
    referenced / held / unreferenced, and the applied offsets' sum and largest
    ``|offset|`` (mm).
    """
    pile = state.pile
    bare = (state.stack.surface() - state.stack.ground()) <= state.margin_m
    applied, seen = ground.height_corrections(t_ns, points, pile.geometry, bare,
                                              pile.ground_z_m,
                                              **state.config.ground_kwargs(state.point_sd_m))
    _hold_ground_offsets(state, t_ns, seen, applied)
    state.count("scans_ground_referenced", int(seen.sum()))
    if applied.size:
        mm = np.abs(applied) * 1e3
        state.count("ground_offset_abs_sum_mm", int(round(float(mm.sum()))))
        peak = int(round(float(mm.max())))
        if peak > state.counters.get("ground_offset_max_mm", 0):
            state.counters["ground_offset_max_mm"] = peak
    return applied


def _hold_ground_offsets(state: ProjectorState, t_ns: np.ndarray, seen: np.ndarray,
                         applied: np.ndarray) -> None:
    """Give the scans whose window saw no ground (``~seen``) the last offset applied up to
    ``ground_hold_s`` before them, in ``applied`` (in place); remember the last one."""
    last_t, last_offset = state.ground_offset
    hold_ns = state.config.ground_hold_s * NS_PER_S
    for i in np.argsort(t_ns, kind="stable").tolist():
        if seen[i]:
            last_t, last_offset = int(t_ns[i]), float(applied[i])
        elif abs(int(t_ns[i]) - last_t) <= hold_ns:
            applied[i] = last_offset
            state.count("scans_ground_held")
        else:
            state.count("scans_ground_unreferenced")
    state.ground_offset = (last_t, last_offset)


def refresh_crossed(state: ProjectorState, obs, t_ns: int,
                    seen_before_ns: np.ndarray) -> None:
    """Cells a stacking pass reached since they were last seen may have risen by a layer:
    their fused heights' variance grows (in place) to at least
    ``(refresh_sd_factor * point_sd)^2`` before this batch (``obs``, taken up to ``t_ns``)
    is fused, so the observations after the pass weigh as fresh ones.

    Without it, a layer's rise smaller than the fusion's gate (a thin layer, a flank the
    material ran down) is a Kalman step of gain ``P / (P + R)`` from the level before the
    pass: a cell seen many times (small ``P``) keeps most of its old height, and where
    points are few (flanks seen at grazing angles) the deficit is never made up.  A pass
    reaches a cell when its stacker comes within ``refresh_reach`` of it along the rail:
    the pile's height / tan(repose), how far poured material runs down the flanks.
    """
    if not state.passes:
        return
    g = state.pile.geometry
    prev = seen_before_ns[obs.ix, obs.iy]
    seen = np.isfinite(prev)
    if not seen.any():
        return
    y = row_y_m(g)[obs.iy]
    earliest = float(np.min(prev[seen]))
    passes = list(state.passes.values())
    typical = typical_pass_s(passes)
    # material poured at the crest runs down the flanks: the stacker "crossed" a cell when
    # it came that close along the rail
    reach_m = flank_reach_m(state) if state.config.refresh_reach else 0.0
    crossed = np.zeros(obs.ix.size, bool)
    for record in passes:
        if record.ended_ns is not None and record.ended_ns <= earliest:
            continue
        a = crossing_ns(record, y - reach_m, t_ns, typical)
        b = crossing_ns(record, y + reach_m, t_ns, typical)
        with np.errstate(invalid="ignore"):
            hit = (np.maximum(a, b) > prev) & (np.minimum(a, b) <= t_ns)
        lo_y, hi_y = sorted((record.start_y_m, record.end_y_m))
        if math.isfinite(lo_y) and math.isfinite(hi_y):   # the path comes within reach
            hit &= (y + reach_m >= lo_y) & (y - reach_m <= hi_y)
        crossed |= hit
    if not crossed.any():
        return
    variance = state.height.grid["variance"]
    ix, iy = obs.ix[crossed], obs.iy[crossed]
    floor_m2 = (state.config.refresh_sd_factor * state.point_sd_m) ** 2
    variance[ix, iy] = np.maximum(variance[ix, iy], floor_m2)
    state.count("cells_refreshed", int(crossed.sum()))


def _subset(obs, mask: np.ndarray):
    """The observations of ``obs`` (:class:`heightmap.CellObservations`) that ``mask``
    (bool, one per observed cell) keeps."""
    pick = (lambda a: None if a is None else a[mask])
    return heightmap.CellObservations(obs.ix[mask], obs.iy[mask], obs.z_mean_m[mask],
                                      obs.z_var_m2[mask], obs.count[mask],
                                      pick(obs.x_offset_m), pick(obs.y_offset_m))
