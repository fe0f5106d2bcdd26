"""The projection as a fold: ``apply(state, event)``, no I/O inside.

:func:`apply` updates the state in place and returns it (the caller copies it to keep a
snapshot: :meth:`projector.state.ProjectorState.copy`).  Events are folded in (valid time,
global seq) order, the order :meth:`ledger.store.LedgerStore.as_of` returns.  The state
holds the geometry of one pile (the fused height map and the layer stack with its
deposits), the reclaim cuts with what they removed, and what grades are joined from at
query time: lots' planned grades and the assays the fold has seen.  Grades are never
folded into the geometry: :mod:`projector.query` joins them as known at K.

This module is the entry point (``from projector import fold as F``: ``F.apply``,
``F.flush``, ``F.initial_state``, ``F.FoldConfig``, ``F.FOLD_VERSION``, the state's
records) and dispatches each event type to its handler; the steps live in
:mod:`projector.config` (the tuning), :mod:`projector.state` (the state),
:mod:`projector.scans` (scans into the height map), :mod:`projector.follow` (the stack
follows the map), :mod:`projector.attribution` (whose material a rise is, and when it was
deposited), :mod:`projector.completion` (hidden flanks and thin layers),
:mod:`projector.cuts` (a reclaim cut's steps), :mod:`projector.crossings` (when stackers
crossed each row) and :mod:`projector.repose` (the angle of repose).

How each event type acts
------------------------
``pile_declared``     (this pile) the grid, the empty height map and the layer stack
``machine_declared``  a reclaimer's constants (for the cutting envelope)
``lot_declared``      a lot's planned grade
``stack_started``     opens a deposit for the pass; rises until its end belong to it
``stack_ended``       closes the pass (belt tonnes kept for reports)
``frame_transform``   a pose of a ``<machine>/scanner`` frame; releases waiting scans
``scan``              waits for the scanner pose after it, then is georeferenced,
                      cleaned, referenced to the ground it sees (its height
                      corrected), rasterised and fused into the height map in batches
                      (cells a stacking pass reached since they were last seen are
                      refreshed first: their old height no longer holds)
``reclaim_cut``       slides the face the cut before left as the scans since saw it
                      (:mod:`projector.material_fit`), clamps every surface to the
                      cutting-envelope floor (the removed bands are the cut's
                      composition) and opens the face this cut leaves: the stack keeps
                      it as cut, the height map takes the predicted slide
``assay``             kept (with its recorded time) for the grade join
``survey``            under the pile's ``survey_rebase`` policy only: the model follows
                      the survey (:mod:`projector.rebase`); otherwise ignored

After each batch of scans the layer stack follows the height map: a cell that rose
beyond the noise margin adds to the open pass's deposit (outside any pass: to a
flagged deposit); a cell that fell beyond the margin is clamped to the measurement
and the removed material is attributed to the latest cut as its geometry residual
when the cell is in that cut's footprint (before any cut: flagged as unexplained loss;
after one, a drop away from the latest cut slides a face that failed later to repose
when such a failure explains it, and is otherwise by default not followed: the stack
keeps its own slid face there).  The latest cut's face is not followed while it is open.
The scans that watched a cut dig are fused before it is applied;
what rose in its footprint since its start is undone first (those scans see the walls
the wheel leaves standing, not material).
"""

from __future__ import annotations

import numpy as np

from schemas.events import decode_payload, timestamp_ns

from projector import heightmap
from projector.completion import (accounted_ns, catch_up_rises, complete_unseen,
                                  filled_elevation)
from projector.config import FoldConfig
from projector.cuts import (fit_buried_boundaries, fit_top_for_cut, predict_height,
                            undo_digging_rises)
from projector.envelope import cut_floor
from projector.follow import follow_height
from projector.grades import AssayRecord, grade_from_map
from projector.grid import GridGeometry
from projector.kinematics import Reclaimer
from projector.layers import DepositInfo, LayerStack
from projector.material_fit import close_face, open_face
from projector.rebase import rebase_on_survey
from projector.scans import note_pending, note_pose, process_scans
from projector.state import (CutRecord, PassRecord, PendingScan, PileInfo, PoseTrack,
                             ProjectorState, around, initial_state, settling_last_pass)

# the config and the state's records are re-exported: callers name them ``F.<name>``, and
# snapshots pickled before they moved name them ``projector.fold.<name>``
__all__ = ["FOLD_VERSION", "FoldConfig", "PileInfo", "PassRecord", "CutRecord", "ProjectorState",
           "initial_state", "apply", "flush", "GEOMETRY_TYPES"]

#: event types that change the geometric state (assays and lots only feed the join)
GEOMETRY_TYPES = ("pile_declared", "machine_declared", "stack_started", "stack_ended",
                  "frame_transform", "scan", "reclaim_cut", "survey")

#: The fold's version: bumped whenever a change makes the same events and config fold to
#: a different state, or changes what a snapshot stores (the classes it pickles, by their
#: module paths).  Snapshots are keyed by it as well as by the config, so those of another
#: version are never used (:class:`projector.query.SnapshotStore`, which reads it from this
#: module, and ``SnapshotStore.drop_other_versions`` deletes them).
FOLD_VERSION = 31

DEFAULT_CELL_M = 0.25
DEFAULT_VOXEL_M = 1.0


def apply(state: ProjectorState, event) -> ProjectorState:
    """Fold one ledger event (a :class:`ledger.records.RecordedEvent`) into the state.

    Events must come in (valid time, global seq) order; other types are ignored.
    Returns the state, updated in place (the caller copies it to keep a snapshot).
    """
    handler = _HANDLERS.get(event.type)
    if event.type == "survey" and (state.pile is None or not state.pile.survey_rebase):
        state.count("surveys_not_rebased")
        return state          # without the policy a survey is not part of the fold at all
    state.high_water = (event.valid_time_ns, event.global_seq)
    if handler is None:
        return state
    handler(state, event, decode_payload(event.type, event.payload))
    return state


def flush(state: ProjectorState) -> ProjectorState:
    """Fuse every waiting scan that has a pose and settle drops (at a query's end);
    updates the state in place and returns it."""
    process_scans(state, final=True)
    if state.stack is not None:
        close_face(state)
        if settling_last_pass(state):
            catch_up_rises(state, state.high_water[0])
        filled = filled_elevation(state)
        floor = complete_unseen(state, state.high_water[0], filled)
        follow_height(state, state.high_water[0], unseen_floor_m=floor, filled_m=filled)
    return state


def _on_pile(state: ProjectorState, event, msg) -> None:
    if msg.pile_id != state.config.pile_id or state.pile is not None:
        if msg.pile_id == state.config.pile_id:
            state.count("pile_redeclared_ignored")
        return
    cell = msg.cell_m or DEFAULT_CELL_M
    pad = (0.1 * max(msg.width_m, msg.length_m) if state.config.pad_m is None
           else max(0.0, float(state.config.pad_m)))
    geometry = GridGeometry.covering(msg.origin_x_m - pad, msg.origin_y_m - pad,
                                     msg.width_m + 2 * pad, msg.length_m + 2 * pad, cell)
    voxel = msg.voxel_m or DEFAULT_VOXEL_M
    # the voxel edge must be a whole number of cells
    voxel = max(cell, round(voxel / cell) * cell)
    state.pile = PileInfo(msg.pile_id, geometry, float(msg.ground_z_m), voxel,
                          float(msg.default_bulk_density_t_m3), bool(msg.survey_rebase))
    config = state.config
    state.point_sd_m = (config.point_sd_m if config.point_sd_m is not None
                        else (0.015 if cell < 0.05 else 0.05))
    state.margin_m = config.margin_m if config.margin_m is not None else 0.4 * state.point_sd_m
    state.process_sd_m = (config.process_sd_m if config.process_sd_m is not None
                          else 0.2 * state.point_sd_m)
    state.height = heightmap.HeightMap.empty(geometry)
    state.stack = LayerStack.empty(geometry, float(msg.ground_z_m))


def _on_machine(state: ProjectorState, event, msg) -> None:
    if msg.kind == 1:  # BUCKET_WHEEL_RECLAIMER
        state.machines[msg.machine_id] = Reclaimer.from_message(msg)


def _on_lot(state: ProjectorState, event, msg) -> None:
    state.lots[msg.lot_id] = grade_from_map(msg.planned_grade)


def _on_stack_started(state: ProjectorState, event, msg) -> None:
    if msg.pile_id != state.config.pile_id or state.stack is None:
        return
    process_scans(state)
    close_face(state)   # the pass's rises are followed everywhere
    # a rise sighted before this pass pours but not yet confirmed is the passes' before
    # it: confirmed later it could not be told from this pass's layer
    seen_before_ns = accounted_ns(state, state.height.grid["last_update_ns"])
    state.height, accepted = heightmap.accept_rises(state.height)
    if accepted.any():
        state.count("rises_accepted_at_pass_start", int(accepted.sum()))
        ix, iy = np.nonzero(accepted)
        follow_height(state, event.valid_time_ns, drops=False,
                      seen_before_ns=seen_before_ns,
                      region=around(ix, iy, state.config.fill_gap_cells + 1,
                                    state.pile.geometry))
    # the passes before this one are complete now (a scanner trailing the stacker saw
    # the last one's end after it ended): the stack catches up with rises the margin held
    # back, and hidden flanks rise to the repose cone
    catch_up_rises(state, event.valid_time_ns)
    complete_unseen(state, event.valid_time_ns)
    index = state.stack.n_deposits + 1
    state.stack = state.stack.open_deposit(
        DepositInfo(index, msg.pass_id, msg.lot_id, event.valid_time_ns))
    state.passes[msg.pass_id] = PassRecord(msg.pass_id, msg.lot_id, msg.machine_id,
                                           event.valid_time_ns, index,
                                           start_y_m=float(msg.start_y_m),
                                           end_y_m=float(msg.end_y_m))
    state.active_pass = msg.pass_id


def _on_stack_ended(state: ProjectorState, event, msg) -> None:
    if msg.pile_id != state.config.pile_id:
        return
    process_scans(state, until_ns=event.valid_time_ns)
    record = state.passes.get(msg.pass_id)
    if record is not None:
        record.ended_ns = event.valid_time_ns
        record.belt_tonnes = float(msg.tonnes)
    if state.active_pass == msg.pass_id:
        state.active_pass = None


def _on_frame_transform(state: ProjectorState, event, msg) -> None:
    if msg.parent_frame_id != "site" or not msg.child_frame_id.endswith("/scanner"):
        return
    t = timestamp_ns(msg.timestamp)
    track = state.poses.get(msg.child_frame_id)
    new_track = track is None
    if new_track:
        track = state.poses[msg.child_frame_id] = PoseTrack()
    if track.t_ns and t <= track.t_ns[-1]:
        if t < track.t_ns[-1]:
            state.count("poses_out_of_order")
        return
    track.t_ns.append(t)
    track.xyz.append((msg.translation.x, msg.translation.y, msg.translation.z))
    track.q.append((msg.rotation.x, msg.rotation.y, msg.rotation.z, msg.rotation.w))
    if len(track.t_ns) > 4096:  # keep the recent track only
        del track.t_ns[:2048], track.xyz[:2048], track.q[:2048]
    note_pose(state, msg.child_frame_id, t, new_track)
    # settled: no waiting scan has its pose, and a pass would fuse nothing
    if len(state.pending) >= state.config.scan_batch and not state.pending_settled:
        process_scans(state)


def _on_scan(state: ProjectorState, event, msg) -> None:
    if state.stack is None:
        return
    note_pending(state, PendingScan(timestamp_ns(msg.timestamp),
                                    np.asarray(msg.ranges, np.float64),
                                    float(msg.start_angle), float(msg.end_angle),
                                    msg.frame_id))
    if len(state.pending) >= 2 * state.config.scan_batch and not state.pending_settled:
        process_scans(state)


def _on_reclaim_cut(state: ProjectorState, event, msg) -> None:
    if msg.pile_id != state.config.pile_id or state.stack is None:
        return
    # every scan taken up to the cut's end watched the bank before or during the cut:
    # fuse them before the cut is applied, never after
    process_scans(state, until_ns=timestamp_ns(msg.end_time))
    start_ns = timestamp_ns(msg.start_time)
    machine = state.machines.get(msg.machine_id)
    floor = None if machine is None else cut_floor(
        state.pile.geometry, machine, msg.travel_m, msg.luff_rad, msg.slew_start_rad,
        msg.slew_end_rad)
    # the face the cut before left slides as the scans since saw it (not this cut's digging)
    close_face(state, floor, start_ns)
    settling = settling_last_pass(state)
    if settling:   # the first cut after a pass: that pass is complete
        catch_up_rises(state, start_ns)
    complete_unseen(state, start_ns)
    if settling:
        fit_buried_boundaries(state)
    restore = None
    if floor is not None:
        # the map the two above followed has seen this cut dig: what rose in its
        # footprint since it started is undone
        undo_digging_rises(state, start_ns, np.isfinite(floor))
        restore = fit_top_for_cut(state, floor) if settling else None
    record = CutRecord(msg.cut_id, msg.bench_id, msg.machine_id, start_ns,
                       timestamp_ns(msg.end_time), float(msg.tonnes))
    if machine is None:
        state.count("cuts_without_machine")
    else:
        _clamp_to_floor(state, record, floor, restore)
    state.cuts.append(record)
    # the scans that watched this cut dig (valid before its end) saw what it took
    # below the envelope: that is the cut's too
    follow_height(state, record.end_ns)


def _clamp_to_floor(state: ProjectorState, record: CutRecord, floor_m: np.ndarray,
                    restore: np.ndarray | None) -> None:
    """Take what stands above a cut's envelope ``floor_m`` (m, (nx, ny), +inf outside) off
    the stack as the cut's removal (then clamp to ``restore``, :func:`fit_top_for_cut`'s,
    when given), open the face it leaves (the stack keeps it as cut until the scans after
    it are fitted, :mod:`projector.material_fit`) and put the predicted slide into the
    height map."""
    before = state.stack.surface()
    state.stack, removal = state.stack.clamp(floor_m)
    if restore is not None:
        # where the fit rose above the floor from a top under it, the cut took the fit's
        # part above the floor; what the rise put under the floor goes again
        state.stack, _rest = state.stack.clamp(restore)
    record.removals.append(removal)
    record.footprint_var_m2 = state.height.variance.ravel()[
        removal.flat_cells(state.pile.geometry.shape)]
    record.predicted_m3 = removal.volume_m3
    predicted = state.stack.surface()
    if removal.volume_m3 > 0:
        predicted = open_face(state, record, floor_m)
    # the height map learns the cut (and the predicted slide) too: the scans after it
    # confirm or correct it
    state.height = predict_height(state.height, predicted, before, state.point_sd_m)


def _on_assay(state: ProjectorState, event, msg) -> None:
    state.assays.append(AssayRecord.from_message(msg, event.recorded_time_ns))


_HANDLERS = {
    "pile_declared": _on_pile, "machine_declared": _on_machine, "lot_declared": _on_lot,
    "stack_started": _on_stack_started, "stack_ended": _on_stack_ended,
    "frame_transform": _on_frame_transform, "scan": _on_scan,
    "reclaim_cut": _on_reclaim_cut, "assay": _on_assay, "survey": rebase_on_survey,
}
