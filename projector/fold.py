"""The projection as a fold: ``apply(state, event) -> state``, no I/O inside.

Events are folded in (valid time, global seq) order, the order
:meth:`ledger.store.LedgerStore.as_of` returns.  The state holds the geometry of one
pile (the fused height map and the layer stack with its deposits), the reclaim cuts
with what they removed, and what grades are joined from at query time: lots' planned
grades and the assays the fold has seen.  Grades are never folded into the geometry:
:mod:`projector.query` joins them as known at K.

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
``reclaim_cut``       clamps every surface to the cutting-envelope floor; the removed
                      bands are the cut's composition
``assay``             kept (with its recorded time) for the grade join

After each batch of scans the layer stack follows the height map: a cell that rose
beyond the noise margin adds to the open pass's deposit (outside any pass: to a
flagged deposit); a cell that fell beyond the margin is clamped to the measurement
and the removed material is attributed to the latest cut as its geometry residual
when the cell is in that cut's footprint (before any cut: flagged as unexplained loss;
after one, a drop away from the latest cut is by default not followed: the stack keeps
its own slid face there).
The scans that watched a cut dig are fused before it is applied;
what rose in its footprint since its start is undone first (those scans see the walls
the wheel leaves standing, not material).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from scipy import ndimage

from schemas.events import decode_payload, timestamp_ns

from projector import georef, ground, heightmap, profile, slump
from projector.envelope import cut_floor
from projector.grades import AssayRecord
from projector.grid import GridGeometry, cell_centre
from projector.kinematics import Reclaimer
from projector.layers import DepositInfo, LayerStack, Removal

__all__ = ["FOLD_VERSION", "FoldConfig", "PileInfo", "PassRecord", "CutRecord", "ProjectorState",
           "initial_state", "apply", "flush", "GEOMETRY_TYPES"]

#: event types that change the geometric state (assays and lots only feed the join)
GEOMETRY_TYPES = ("pile_declared", "machine_declared", "stack_started", "stack_ended",
                  "frame_transform", "scan", "reclaim_cut")

#: The fold's version: bumped whenever a change makes the same events and config fold to
#: a different state.  Snapshots are keyed by it as well as by the config, so those of an
#: older fold are never used (:class:`projector.query.SnapshotStore`).
FOLD_VERSION = 22

DEFAULT_CELL_M = 0.25
DEFAULT_VOXEL_M = 1.0


@dataclass(frozen=True)
class FoldConfig:
    """Tuning of the fold (defaults suit an LMS200 on a full-scale reclaimer).

    Attributes
    ----------
    pile_id : str
        The pile this state projects.
    point_sd_m : float or None
        Height noise of one scan point, metres.  None: from the pile's cell size, 5 cm
        for a yard (LMS200 range noise plus pose error) and 15 mm (the LMS200's own
        noise) for a laboratory pile with cells under 5 cm.
    scan_batch : int
        Scans georeferenced and fused together.
    max_pose_gap_ns : int
        Longest gap between two scanner poses a scan time may be interpolated across.
    max_scan_wait_ns : int
        A scan with no pose after it this long after its time is dropped (counted).
    margin_sigma : float
        A cell's stack surface follows the height map when they differ by more than
        this many sigma of the fused height (plus ``margin_m``).
    margin_m : float or None
        Fixed part of that margin, metres (None: 0.4 x ``point_sd_m``).
    process_sd_m : float or None
        Random-walk creep of a cell's height per observation in the fusion, metres
        (None: 0.2 x ``point_sd_m``, 1 cm at a yard, 3 mm at a laboratory pile).
    gate_sigma : float
        Mahalanobis gate of the height fusion.
    change_count : int
        Agreeing out-of-gate observations before a sparsely seen cell changes.
    strong_points : int
        A cell with at least this many points in one batch changes at once.
    attribute_by_crossing : bool
        Give a rise to the passes whose stacker crossed the cell since it was last seen
        (from ``stack_started``'s start/end along the rail), deposited when it crossed;
        False: to the pass active when the rise is seen.
    slump_in_place : bool
        Rises outside a pass after a cut are slumped material: counted as the cut's
        ``returned_m3`` but not added (the face it came from is still in the stack).
        False (default): they are added as well (a flagged deposit), since the drops of
        the face they came from are applied (the cut's geometry residual) -- keeping the
        one and not the other lost 1-1.5 % of a bench-scale pile.
    fill_gap_cells : int
        Unseen runs of at most this many cells between seen cells are interpolated
        (linearly) before the stack follows the height map; 0 = no filling.
    pad_m : float or None
        The grid extends this far beyond the declared footprint on every side (the toes
        of a pile's ends and flanks run out past it), metres; None: a tenth of the
        footprint's longer side.
    repose_deg : float or None
        Angle of repose of the ore (deg); None: estimated from the observed slopes
        (:func:`projector.slump.estimate_repose_deg`), 35 deg until enough are seen.
    slump_after_cut : bool
        After a cut, the face it left slides to the angle of repose in the model
        (mass and composition conserved; :func:`projector.slump.slump`).
    complete_unseen : bool
        When the next pass starts, at a cut and at a query's end, cells a pass crossed
        since they were last seen (or never seen) that lie more than ``margin_m`` below
        the repose cone of the seen surface (a flank hidden behind the crest) rise to
        it, the material given to the passes that crossed them since they were last seen.
    refresh_crossed : bool
        Before a batch of scans is fused, cells a stacking pass reached since they were
        last seen get a variance of at least ``(refresh_sd_factor * point_sd_m)^2``, so
        the height map takes the layer the pass laid there at its next look rather than a
        Kalman step from the level before (:func:`_refresh_crossed`).
    refresh_sd_factor : float
        That variance, in point sds (10: the old level is as good as forgotten, the next
        look weighs about 99 %; 3 left bench-scale flanks 1-2 mm low, -1.06 % of the pile).
    refresh_reach : bool
        A pass reaches a cell when its stacker comes within the pile's height /
        tan(repose) of it along the rail (poured material runs down the flanks that far);
        False: only when it passes the cell's own position.
    residual_near_cut : bool
        A drop seen after a cut is the cut's geometry residual only in its footprint
        (grown by a cell, :func:`_near_cut`); elsewhere (the face sliding into the hole)
        it is not material the cut delivered (see ``follow_far_drops``).
    follow_far_drops : bool
        Whether the stack follows such a drop away from the latest cut (its volume counted
        as an unexplained loss, counter ``unexplained_loss_mm3``, in 1e-3 m3).  False
        (default): the stack keeps the slid face its own model predicts (a cut's face
        slides to the angle of repose), and how far the measurement lies below it there
        is reported (``far_drops_mm3``, the latest follow's).  Followed, the scans of a
        live demo whose times were off by seconds (the boom slewing meanwhile) dug 56 m3
        more beside the cuts than with their true times (pile -1.92 % against -0.53 %);
        not followed, -0.83 %.  On the ten simulator-posed runs, not following moved every
        pile by +0.01 to +0.06 points and took one Fe miss away (bench-scale seed 4).
    cut_fit_cells : int
        At the first cut after a pass, the top where it stands above the cut's floor is
        replaced by a local quadratic fit over this many x this many cells before the cut
        takes what is above the floor (:meth:`projector.layers.LayerStack.fit_top_above`;
        odd; 1: as fused).  The volume above a floor of a noisy surface is biased high where
        the surface runs close to it, and a first cut takes a slice a few mm thick off a
        laboratory pile whose fused cells carry about 2 mm of noise: on bench-scale seeds
        1-5 with four draws of the sensors' noise each, the first cut came 2.1 % heavy on
        average (sd 2.0 % between runs; the true surface with 2.3 mm of white noise gives
        +1.4 to +2.2 %), fitted +0.04 % (sd 1.9 %); over all 300 cuts the tonnes' rms
        went from 1.32 to 1.20 % and the cuts beyond 3 % from 9 to 6.
    relax_slack : float
        Faces steeper than ``(1 + relax_slack) * tan(repose)`` slide (a little slack keeps
        the estimated angle's error from creeping standing flanks).
    accept_rises_at_pass_start : bool
        When a pass starts, rises sighted but not yet confirmed (``change_count``) are
        accepted and given to the passes before it (:func:`heightmap.accept_rises`).
    catch_up_cells : int
        When a pass starts (and at the first cut or a query's end after the last pass),
        the stack catches up with rises smaller than a cell's margin
        where the mean rise over this many x this many cells is significant; < 2: never.
    dig_journal_s : float
        The stack's rises are remembered this long (s), so that a cut up to this long
        undoes those its own digging caused in its footprint (:func:`_undo_digging_rises`).
    boundary_fit_cells : int
        At the first cut after a pass (the layers below the top one are complete), each
        deposit's top that no such cut has fitted yet, other than the top one, is replaced
        by a local quadratic fit over this many x this many cells
        (:meth:`projector.layers.LayerStack.fit_boundaries`; odd; 1: as fused).
        A buried top keeps the height map's per-cell noise (2.8-3.7 mm rms against the
        simulator's layer tops on the five bench-scale seeds; fitted, 1.4-2.0 mm, and
        3.0-3.2 mm for the one whose error has structure), and a cut whose floor runs
        close to it takes the lower deposit wherever the noise lifted it: bench-scale
        seed 3's B1-C06 took 2.3 cm3 of lot C where the simulator's took 0.7 (-0.45 pp
        Fe; -0.18 pp fitted).  Exact-lab Fe rms per seed went from 0.051 / 0.122 /
        0.155 / 0.114 / 0.130 to 0.034 / 0.117 / 0.130 / 0.097 / 0.102 pp; the means
        over 3 x 3 and 5 x 5 cells did as well or better on some seeds but shift every
        lot (a mean lowers crests and raises toes).
    cone_smooth_cells : int
        A never-seen cell's repose cone rises from the seen heights fitted with a plane
        over this many x this many cells (odd; 1: the heights as fused), so that it is
        not the maximum of their noise (:func:`_unseen_floor`).
    pouring_tail : bool
        A cell last seen while the cone of the last pass to cross it could still reach
        it (:func:`_seen_while_pouring`) counts as crossed since it was seen: a hidden
        flank's layer is completed to the repose cone at the next pass rather than taken
        with the one after it.
    profile_fit_beams : int
        Each scan's kept ranges are fitted with a line over this many beams (odd; 1: as
        measured), never across a range jump, before they are georeferenced
        (:func:`projector.profile.clean_profile`, ``fit_beams``): the range noise
        that spreads points along their beams drops by sqrt(3) for 3.
    ground_reference : bool
        Each scan's height is referenced to the declared ground it sees
        (:func:`_reference_ground`): the median offset of the bare-ground points of the
        scans within ``ground_window_s`` is subtracted from its points' heights, when it
        lies outside the deadband below.  A localizer's scanner height drifts (its luff
        is seen only through GNSS height); the ground does not.
    ground_window_s : float
        Half width (s) of the window whose scans' offsets are pooled.
    ground_hold_s : float
        A scan with no ground in its window takes the last offset applied this recently
        (s); older, it is left as posed (counted ``scans_ground_unreferenced``).
    ground_min_points : int
        Fewest ground points for a scan to have an offset of its own.
    ground_max_offset_m : float or None
        Largest offset looked for (m); None: 20 x ``point_sd_m`` (1 m at a yard).
    ground_deadband_sigma : float
        Offsets within this many standard errors of 0 are not applied (a well posed
        scanner's heights are left alone: its offsets are noise).
    ground_deadband_m : float or None
        Nor are offsets within this of 0 (m); None: half of ``point_sd_m`` (2.5 cm at a
        yard, 7.5 mm at a laboratory pile).  Ground seen over bare cells reads a little
        high (toes thinner than the margin, the LMS200's rounding): about 1 mm at
        bench scale, where 2-3 mm applied to the scans that watch a cut changed its
        tonnes by up to 15 %.
    """

    pile_id: str
    point_sd_m: float | None = None
    scan_batch: int = 50
    max_pose_gap_ns: int = 2_000_000_000
    max_scan_wait_ns: int = 10_000_000_000
    margin_sigma: float = 3.0
    margin_m: float | None = None
    process_sd_m: float | None = None
    gate_sigma: float = 3.0
    change_count: int = 3
    strong_points: int = 3
    attribute_by_crossing: bool = True
    slump_in_place: bool = False
    fill_gap_cells: int = 16
    pad_m: float | None = None
    repose_deg: float | None = None
    slump_after_cut: bool = True
    complete_unseen: bool = True
    refresh_crossed: bool = True
    refresh_sd_factor: float = 10.0
    refresh_reach: bool = True
    residual_near_cut: bool = True
    follow_far_drops: bool = False
    relax_slack: float = 0.0
    accept_rises_at_pass_start: bool = True
    catch_up_cells: int = 5
    boundary_fit_cells: int = 7
    cut_fit_cells: int = 7
    dig_journal_s: float = 3600.0
    cone_smooth_cells: int = 5
    pouring_tail: bool = True
    profile_fit_beams: int = 3
    ground_reference: bool = True
    ground_window_s: float = 1.0
    ground_hold_s: float = 5.0
    ground_min_points: int = 15
    ground_max_offset_m: float | None = None
    ground_deadband_sigma: float = 3.0
    ground_deadband_m: float | None = None

    def ground_kwargs(self, point_sd_m: float) -> dict[str, Any]:
        """The keyword arguments of :func:`projector.ground.height_corrections` for
        this config and a point height noise (m): the defaults resolved."""
        sd = float(point_sd_m)
        return {"point_sd_m": sd, "half_window_ns": int(self.ground_window_s * 1e9),
                "min_points": self.ground_min_points,
                "max_offset_m": (20.0 * sd if self.ground_max_offset_m is None
                                 else float(self.ground_max_offset_m)),
                "deadband_sigma": self.ground_deadband_sigma,
                "deadband_m": (0.5 * sd if self.ground_deadband_m is None
                               else float(self.ground_deadband_m))}

    def __post_init__(self) -> None:
        for name in ("cone_smooth_cells", "profile_fit_beams", "boundary_fit_cells",
                     "cut_fit_cells"):
            value = int(getattr(self, name))
            if value < 1 or value % 2 == 0:
                raise ValueError(f"{name} must be odd and >= 1, got {getattr(self, name)}")


@dataclass(frozen=True)
class PileInfo:
    """What ``pile_declared`` said."""

    pile_id: str
    geometry: GridGeometry
    ground_z_m: float
    voxel_m: float
    default_bulk_density_t_m3: float


@dataclass
class PassRecord:
    """One stacking pass."""

    pass_id: str
    lot_id: str
    machine_id: str
    started_ns: int
    deposit_index: int
    ended_ns: int | None = None
    belt_tonnes: float | None = None
    start_y_m: float = math.nan
    end_y_m: float = math.nan


@dataclass
class CutRecord:
    """One reclaim cut: what the envelope removed and what scans attributed to it later."""

    cut_id: str
    bench_id: str
    machine_id: str
    start_ns: int
    end_ns: int
    belt_tonnes: float
    removals: list[Removal] = field(default_factory=list)
    predicted_m3: float = 0.0
    residual_m3: float = 0.0
    returned_m3: float = 0.0
    slumped_m3: float = 0.0


@dataclass
class _Scan:
    t_ns: int
    ranges_m: np.ndarray
    start_angle_rad: float
    end_angle_rad: float


@dataclass
class ProjectorState:
    """Everything the fold knows about one pile.  Build with :func:`initial_state`."""

    config: FoldConfig
    pile: PileInfo | None = None
    machines: dict[str, Reclaimer] = field(default_factory=dict)
    lots: dict[str, dict[str, float]] = field(default_factory=dict)
    passes: dict[str, PassRecord] = field(default_factory=dict)
    active_pass: str | None = None
    height: Any = None              # heightmap.HeightMap
    stack: LayerStack | None = None
    cuts: list[CutRecord] = field(default_factory=list)
    assays: list[AssayRecord] = field(default_factory=list)
    pose_t_ns: list[int] = field(default_factory=list)
    pose_xyz: list[tuple[float, float, float]] = field(default_factory=list)
    pose_q: list[tuple[float, float, float, float]] = field(default_factory=list)
    pending: list[_Scan] = field(default_factory=list)
    flagged_loss_m3: float = 0.0
    #: recent rises of the stack's top, ``(t_ns, flat cell indices, top before (m))``
    #: (:func:`_journal_rises`), so a cut can undo those its own digging caused
    rises_journal: list[tuple[int, np.ndarray, np.ndarray]] = field(default_factory=list)
    #: when each cell was last completed to the repose cone (UTC ns, NaN = never; shape
    #: (nx, ny); None until the first completion; replaced, never written in place): its
    #: material up to there is accounted for (:func:`_accounted_ns`)
    completed_ns: np.ndarray | None = None
    point_sd_m: float = 0.05       # resolved from the config and the pile
    margin_m: float = 0.02
    process_sd_m: float = 0.01     # the height map's creep per observation (resolved)
    tan_repose: float = math.nan   # last estimate of tan(angle of repose)
    #: the tops of deposits 1 .. this one are fitted (:func:`_fit_buried_boundaries`)
    boundaries_fitted: int = 0
    #: the last scan height offset applied, ``(scan t_ns, offset m)`` (:func:`_reference_ground`)
    ground_offset: tuple[int, float] = (-(2 ** 62), 0.0)
    counters: dict[str, int] = field(default_factory=dict)
    high_water: tuple[int, int] = (-(2 ** 62), -1)   # (valid ns, global seq) folded so far

    def count(self, key: str, n: int = 1) -> None:
        self.counters[key] = self.counters.get(key, 0) + n

    def copy(self) -> "ProjectorState":
        """A deep enough copy for a snapshot (arrays are copied; records are immutable)."""
        return replace(
            self, machines=dict(self.machines), lots={k: dict(v) for k, v in self.lots.items()},
            passes={k: replace(v) for k, v in self.passes.items()},
            height=None if self.height is None else self.height.copy(),
            stack=None if self.stack is None else self.stack.copy(),
            cuts=[replace(c, removals=list(c.removals)) for c in self.cuts],
            assays=list(self.assays), pose_t_ns=list(self.pose_t_ns),
            pose_xyz=list(self.pose_xyz), pose_q=list(self.pose_q),
            pending=list(self.pending), counters=dict(self.counters),
            rises_journal=list(self.rises_journal))


def initial_state(config: FoldConfig | str) -> ProjectorState:
    """The state before any event (``config`` may be just the pile id)."""
    if isinstance(config, str):
        config = FoldConfig(pile_id=config)
    return ProjectorState(config=config)


# -- the fold -----------------------------------------------------------------------------


def apply(state: ProjectorState, event) -> ProjectorState:
    """Fold one ledger event (a :class:`ledger.records.RecordedEvent`) into the state.

    Events must come in (valid time, global seq) order; other types are ignored.
    Returns the state (updated in place: the caller copies it to keep a snapshot).
    """
    handler = _HANDLERS.get(event.type)
    state.high_water = (event.valid_time_ns, event.global_seq)
    if handler is None:
        return state
    handler(state, event, decode_payload(event.type, event.payload))
    return state


def flush(state: ProjectorState) -> ProjectorState:
    """Fuse every waiting scan that has a pose and settle drops (at a query's end)."""
    _process_scans(state, final=True)
    if state.stack is not None:
        if _settling_last_pass(state):
            _catch_up_rises(state, state.high_water[0])
        filled = _filled_elevation(state)
        floor = _complete_unseen(state, state.high_water[0], filled)
        _follow_height(state, state.high_water[0], unseen_floor_m=floor, filled_m=filled)
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
                          float(msg.default_bulk_density_t_m3))
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
    state.lots[msg.lot_id] = dict(msg.planned_grade)


def _on_stack_started(state: ProjectorState, event, msg) -> None:
    if msg.pile_id != state.config.pile_id or state.stack is None:
        return
    _process_scans(state)
    if state.config.accept_rises_at_pass_start:
        # a rise sighted before this pass pours but not yet confirmed is the passes'
        # before it: confirmed later it could not be told from this pass's layer
        seen_before_ns = _accounted_ns(state, state.height.grid["last_update_ns"])
        state.height, accepted = heightmap.accept_rises(state.height)
        if accepted.any():
            state.count("rises_accepted_at_pass_start", int(accepted.sum()))
            ix, iy = np.nonzero(accepted)
            _follow_height(state, event.valid_time_ns, drops=False,
                           seen_before_ns=seen_before_ns,
                           region=_around(ix, iy, state.config.fill_gap_cells + 1,
                                          state.pile.geometry))
    # the passes before this one are complete now (a scanner trailing the stacker saw
    # the last one's end after it ended): the stack catches up with rises the margin held
    # back, and hidden flanks rise to the repose cone
    _catch_up_rises(state, event.valid_time_ns)
    _complete_unseen(state, event.valid_time_ns)
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
    _process_scans(state, until_ns=event.valid_time_ns)
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
    if state.pose_t_ns and t <= state.pose_t_ns[-1]:
        if t < state.pose_t_ns[-1]:
            state.count("poses_out_of_order")
        return
    state.pose_t_ns.append(t)
    state.pose_xyz.append((msg.translation.x, msg.translation.y, msg.translation.z))
    state.pose_q.append((msg.rotation.x, msg.rotation.y, msg.rotation.z, msg.rotation.w))
    if len(state.pose_t_ns) > 4096:  # keep the recent track only
        del state.pose_t_ns[:2048], state.pose_xyz[:2048], state.pose_q[:2048]
    if len(state.pending) >= state.config.scan_batch:
        _process_scans(state)


def _on_scan(state: ProjectorState, event, msg) -> None:
    if state.stack is None:
        return
    state.pending.append(_Scan(timestamp_ns(msg.timestamp), np.asarray(msg.ranges, np.float64),
                               float(msg.start_angle), float(msg.end_angle)))
    if len(state.pending) >= 2 * state.config.scan_batch:
        _process_scans(state)


def _on_reclaim_cut(state: ProjectorState, event, msg) -> None:
    if msg.pile_id != state.config.pile_id or state.stack is None:
        return
    # every scan taken up to the cut's end watched the bank before or during the cut:
    # fuse them before the cut is applied, never after
    _process_scans(state, until_ns=timestamp_ns(msg.end_time))
    start_ns = timestamp_ns(msg.start_time)
    machine = state.machines.get(msg.machine_id)
    floor = None if machine is None else cut_floor(
        state.pile.geometry, machine, msg.travel_m, msg.luff_rad, msg.slew_start_rad,
        msg.slew_end_rad)
    settling = _settling_last_pass(state)
    if settling:   # the first cut after a pass: that pass is complete
        _catch_up_rises(state, start_ns)
    _complete_unseen(state, start_ns)
    if settling:
        _fit_buried_boundaries(state)
    restore = None
    if floor is not None:
        # the map the two above followed has seen this cut dig: what rose in its
        # footprint since it started is undone
        _undo_digging_rises(state, start_ns, np.isfinite(floor))
        restore = _fit_top_for_cut(state, floor) if settling else None
    record = CutRecord(msg.cut_id, msg.bench_id, msg.machine_id, start_ns,
                       timestamp_ns(msg.end_time), float(msg.tonnes))
    if machine is None:
        state.count("cuts_without_machine")
    else:
        before = state.stack.surface()
        state.stack, removal = state.stack.clamp(floor)
        if restore is not None:
            # where the fit rose above the floor from a top under it, the cut took the
            # fit's part above the floor; what the rise put under the floor goes again
            state.stack, _rest = state.stack.clamp(restore)
        record.removals.append(removal)
        record.predicted_m3 = removal.volume_m3
        if state.config.slump_after_cut and removal.volume_m3 > 0:
            record.slumped_m3 = _slump_face(state, floor)
        # the height map learns the cut (and the slide) too: the scans after it confirm
        # or correct it
        state.height = _predict_height(state.height, state.stack.surface(), before,
                                       state.point_sd_m)
    state.cuts.append(record)
    # the scans that watched this cut dig (valid before its end) saw what it took
    # below the envelope: that is the cut's too
    _follow_height(state, record.end_ns)


def _on_assay(state: ProjectorState, event, msg) -> None:
    state.assays.append(AssayRecord.from_message(msg, event.recorded_time_ns))


_HANDLERS = {
    "pile_declared": _on_pile, "machine_declared": _on_machine, "lot_declared": _on_lot,
    "stack_started": _on_stack_started, "stack_ended": _on_stack_ended,
    "frame_transform": _on_frame_transform, "scan": _on_scan,
    "reclaim_cut": _on_reclaim_cut, "assay": _on_assay,
}


# -- scans -> height map -> layer stack -----------------------------------------------------


def _reference_ground(state: ProjectorState, t_ns: np.ndarray, points: np.ndarray) -> np.ndarray:
    """The height offset (m) to subtract from each scan's points, shape (S,).

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
    hold_ns = state.config.ground_hold_s * 1e9
    for i in np.argsort(t_ns, kind="stable").tolist():
        if seen[i]:
            last_t, last_offset = int(t_ns[i]), float(applied[i])
        elif abs(int(t_ns[i]) - last_t) <= hold_ns:
            applied[i] = last_offset
            state.count("scans_ground_held")
        else:
            state.count("scans_ground_unreferenced")
    state.ground_offset = (last_t, last_offset)


def _process_scans(state: ProjectorState, *, until_ns: int | None = None,
                   final: bool = False) -> None:
    """Fuse the waiting scans that have a pose after them (all up to ``until_ns``)."""
    if not state.pending or state.pile is None:
        return
    last_pose = state.pose_t_ns[-1] if state.pose_t_ns else None
    ready, waiting = [], []
    for scan in state.pending:
        if last_pose is not None and scan.t_ns <= last_pose:
            ready.append(scan)
        elif final or (until_ns is not None and scan.t_ns <= until_ns
                       and (last_pose is None or scan.t_ns < last_pose)) \
                or (last_pose is not None and last_pose - scan.t_ns > state.config.max_scan_wait_ns):
            state.count("scans_without_pose")
        else:
            waiting.append(scan)
    state.pending = waiting
    if not ready:
        return
    by_beams: dict[tuple[int, float, float], list[_Scan]] = {}
    for scan in ready:
        by_beams.setdefault((scan.ranges_m.size, scan.start_angle_rad, scan.end_angle_rad),
                            []).append(scan)
    pose_t = np.asarray(state.pose_t_ns, np.int64)
    pose_xyz = np.asarray(state.pose_xyz, np.float64)
    pose_q = np.asarray(state.pose_q, np.float64)
    for (beams, start, end), scans in by_beams.items():
        if beams < 2:
            state.count("scans_unusable", len(scans))
            continue
        t = np.asarray([s.t_ns for s in scans], np.int64)
        xyz, q = georef.interpolate_poses(t, pose_t, pose_xyz, pose_q,
                                          max_gap_ns=state.config.max_pose_gap_ns)
        ranges = np.stack([s.ranges_m for s in scans])
        ranges = profile.clean_profile(ranges, fit_beams=state.config.profile_fit_beams)
        increment = (end - start) / (beams - 1)
        points = georef.georeference(ranges, start, increment, xyz, q)
        if state.config.ground_reference:
            points[..., 2] -= _reference_ground(state, t, points)[:, None]
        points = points.reshape(-1, 3)
        points = points[np.isfinite(points).all(axis=1)]
        state.count("scans_fused", len(scans))
        state.count("points_fused", len(points))
        if len(points) == 0:
            continue
        obs = heightmap.rasterize(state.pile.geometry, points)
        seen_before_ns = state.height.grid["last_update_ns"].copy()
        # A cell seen by several points of this batch that agree is strong evidence of
        # a change on its own (a stacked layer rises between two patrols, so waiting
        # for agreeing patrols would never accept it); a cell seen by a point or two
        # needs repeated agreeing observations.
        if state.config.refresh_crossed:
            _refresh_crossed(state, obs, int(t.max()), seen_before_ns)
        strong = obs.count >= state.config.strong_points
        for subset, change_count in ((strong, 1), (~strong, state.config.change_count)):
            if subset.any():
                state.height, _stats = heightmap.fuse(
                    state.height, _subset(obs, subset), int(t.max()), state.point_sd_m,
                    gate_sigma=state.config.gate_sigma, change_count=change_count,
                    process_sd_m=state.process_sd_m, inplace=True)
        _follow_height(state, int(t.max()), drops=False,
                       seen_before_ns=_accounted_ns(state, seen_before_ns),
                       sighted_before_ns=seen_before_ns,
                       region=_around(obs.ix, obs.iy, state.config.fill_gap_cells + 1,
                                      state.pile.geometry))


def _refresh_crossed(state: ProjectorState, obs, t_ns: int,
                     seen_before_ns: np.ndarray) -> None:
    """Cells a stacking pass reached since they were last seen may have risen by a layer:
    their fused heights' variance grows to at least ``(refresh_sd_factor * point_sd)^2``
    before this batch is fused, so the observations after the pass weigh as fresh ones.

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
    y = _row_y_m(g)[obs.iy]
    earliest = float(np.min(prev[seen]))
    passes = list(state.passes.values())
    typical = _typical_pass_s(passes)
    # material poured at the crest runs down the flanks: the stacker "crossed" a cell when
    # it came that close along the rail
    reach_m = _flank_reach_m(state) if state.config.refresh_reach else 0.0
    crossed = np.zeros(obs.ix.size, bool)
    for record in passes:
        if record.ended_ns is not None and record.ended_ns <= earliest:
            continue
        a = _crossing_ns(record, y - reach_m, t_ns, typical)
        b = _crossing_ns(record, y + reach_m, t_ns, typical)
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
    pick = (lambda a: None if a is None else a[mask])
    return heightmap.CellObservations(obs.ix[mask], obs.iy[mask], obs.z_mean_m[mask],
                                      obs.z_var_m2[mask], obs.count[mask],
                                      pick(obs.x_offset_m), pick(obs.y_offset_m))


def _around(ix: np.ndarray, iy: np.ndarray, pad: int, geometry: GridGeometry):
    """The block of cells holding (ix, iy), padded by ``pad`` cells: (slice, slice)."""
    return (slice(max(0, int(ix.min()) - pad), min(geometry.nx, int(ix.max()) + pad + 1)),
            slice(max(0, int(iy.min()) - pad), min(geometry.ny, int(iy.max()) + pad + 1)))


def _follow_height(state: ProjectorState, t_ns: int, *, drops: bool = True,
                   seen_before_ns: np.ndarray | None = None,
                   sighted_before_ns: np.ndarray | None = None, region=None,
                   unseen_floor_m: np.ndarray | None = None,
                   filled_m: np.ndarray | None = None) -> None:
    """Move the layer stack's top to the height map where they differ beyond the margin.

    Rises follow at once.  Drops follow only when ``drops`` (at a cut, or at the end of
    a query): a cut is known only when its event arrives at its end time, after the
    scans that watched it dig, so a drop seen by those scans must wait for that cut
    rather than be charged to the one before.  ``unseen_floor_m``: the
    :func:`_unseen_floor` of the current height map, when the caller has it;
    ``filled_m`` its :func:`_filled_elevation` (with no ``region``).
    """
    if region is not None:
        if drops:
            raise ValueError("a region is for rises only (drops=False)")
        # only the block a batch of scans saw can have risen (rises only: drops wait)
        elevation = state.height.elevation[region]
        if state.config.fill_gap_cells:
            # an unseen strip between seen cells (between two scan lines, behind a
            # crest) is interpolated rather than left at the ground
            elevation = heightmap.fill_holes(elevation, method="linear",
                                             max_gap_cells=state.config.fill_gap_cells)
    else:
        region = (slice(None), slice(None))
        elevation = _filled_elevation(state) if filled_m is None else filled_m
    if drops and state.config.complete_unseen:
        # a cell below the repose cone of the seen surface that a pass crossed since it
        # was seen is no lower than the cone (and was raised to it), not a drop
        if unseen_floor_m is None:
            unseen_floor_m = _unseen_floor(state, elevation, t_ns)
        elevation = np.fmax(elevation, unseen_floor_m)
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
    if elevation.shape != shape:
        block, elevation = elevation, np.full(shape, np.nan)
        elevation[region] = block
    top = state.stack.surface()
    rising = np.flatnonzero(up)
    if up.any() and seen_before_ns is not None and state.config.attribute_by_crossing:
        up = _rise_to_crossing_passes(state, np.where(up, elevation, np.nan), seen_before_ns,
                                      t_ns, observed_ns=state.height.grid["observed_ns"]) & up
    slump = (state.config.slump_in_place and state.active_pass is None and bool(state.cuts)
             and not _settling_last_pass(state))
    if up.any() and slump:
        # Material rising outside a pass after a cut slid into the cut's hole from its
        # face.  The face's drop is spread thin and mostly under the noise margin, so
        # adding the toe would count the slid material twice: the stack keeps it where
        # it was (same material, a few metres up the face) and the rise is only counted.
        with np.errstate(invalid="ignore"):
            state.cuts[-1].returned_m3 += float(
                np.sum(np.where(up, elevation - top, 0.0)) * state.pile.geometry.cell_area_m2)
        up = np.zeros_like(up)
    if up.any():
        if state.active_pass is None and not _settling_last_pass(state):
            info = state.stack.deposits[-1] if state.stack.n_deposits else None
            if info is None or not info.flagged or (not state.cuts
                                                   and info.opened_ns < _last_event_ns(state)):
                # after the cuts began, one flagged deposit (the top one) takes every
                # slide's material: a deposit per cut would grow the state by a layer each
                state.stack = state.stack.open_deposit(
                    DepositInfo(state.stack.n_deposits + 1, "", "", t_ns, flagged=True))
        state.stack, added = state.stack.raise_to(np.where(up, elevation, np.nan),
                                                  _deposition_ns(state, t_ns, up))
        state.count("rises")
        if state.active_pass is None and state.cuts and not _settling_last_pass(state):
            # material rising outside a pass after a cut is what slumped into the cut's
            # hole from its face: the cut did not take it
            state.cuts[-1].returned_m3 += added
    if rising.size:
        first_sight = None
        if sighted_before_ns is not None:
            first_sight = _stale(state, t_ns, seen_ns=sighted_before_ns)
        _journal_rises(state, t_ns, rising, top, first_sight=first_sight)
    if drops and down.any():
        near = down
        if state.cuts and state.config.residual_near_cut:
            near = down & _near_cut(state, state.cuts[-1])
        far = down & ~near
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


def _journal_rises(state: ProjectorState, t_ns: int, cells: np.ndarray,
                   top_before_m: np.ndarray, first_sight: np.ndarray | None = None) -> None:
    """Note in which of ``cells`` (flat indices) the stack's top rose, from what level
    (``top_before_m``, (nx, ny)), at ``t_ns``; entries older than ``dig_journal_s``
    before it are dropped.  A rise that was the height map's first sight of its cell since
    a pass crossed it (``first_sight``, (nx, ny) bool; None for a catch-up or a
    completion, which follow no sighting of their own) is not noted: its level before was
    never measured, so no cut undoes it (:func:`_undo_digging_rises`)."""
    rose = state.stack.surface().reshape(-1)[cells] > top_before_m.reshape(-1)[cells]
    if first_sight is not None:
        rose &= ~first_sight.reshape(-1)[cells]
    cells = cells[rose]
    if cells.size:
        state.rises_journal.append((int(t_ns), cells.astype(np.int32),
                                    top_before_m.reshape(-1)[cells]))
    oldest = t_ns - int(state.config.dig_journal_s * 1e9)
    while state.rises_journal and state.rises_journal[0][0] < oldest:
        state.rises_journal.pop(0)


def _undo_digging_rises(state: ProjectorState, start_ns: int, footprint: np.ndarray) -> float:
    """Lower the stack in a cut's footprint to where it was before the rises seen from its
    start on; returns the volume taken off (m3).

    While the wheel digs, scans see the walls it leaves standing (the face slides only
    once it has passed) and, rasterised into the cells around them, read the footprint
    high: bench-scale, +3 to +5 mm over a cut 1 cm deep.  What rose there then is not
    material the cut found, and it is not added to it.

    A rise in a cell the map had not seen since a pass last crossed it stays (it is not
    journaled, :func:`_journal_rises`): its level before was never measured (a pile end's
    toe, hidden from the rail, is first seen from the reclaimer).  Undoing those took the
    demo scenario's first cuts 1-3 % light (seed 3: the stack above the floor 167.5 m3
    before the undo, 162.1 m3 after, 167.4 m3 true).
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


def _near_cut(state: ProjectorState, cut: "CutRecord") -> np.ndarray:
    """Cells a cut can have taken material from: its footprint (where its envelope
    removed material) grown by one cell (a wall point rasterised beside it), shape
    (nx, ny).

    A drop further out is the face sliding into the hole the cut left (it shows there
    as a rise): the material moved, it did not go onto the belt.  Charging such drops to
    the cut made bench-scale cuts 3-10 % heavy, at every second cut (those after which
    the scanner looked at the face).
    """
    g = state.pile.geometry
    footprint = np.zeros(g.shape, bool)
    for removal in cut.removals[:1]:       # the envelope's own removal
        for d in removal.deposits:
            footprint[d.ix, d.iy] = True
    if not footprint.any():
        return footprint
    return ndimage.binary_dilation(footprint, structure=np.ones((3, 3), bool))


def _flank_reach_m(state: ProjectorState) -> float:
    """How far a flank runs out horizontally: the pile's height / tan(repose) (m), with the
    last repose estimate (no new one)."""
    height = max(float(np.max(state.stack.surface() - state.stack.ground())), 0.0)
    return height / _tan_repose(state, estimate=False)


def _predict_height(height, new_top_m: np.ndarray, old_top_m: np.ndarray, sd_m: float):
    """The height map after a cut: cells whose stack top the cut (or the slide of its
    face) moved take the new top.

    Their variance becomes one point's (the prediction is as good as a fresh
    observation) and pending change evidence is dropped, so the scans after the cut
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


# -- the angle of repose: slides after a cut, flanks hidden behind the crest ------------------


def _tan_repose(state: ProjectorState, *, estimate: bool = True) -> float:
    """tan(angle of repose): configured, else estimated from the seen slopes (35 deg
    until enough are seen; the last good estimate is kept).  ``estimate=False`` takes the
    last estimate without a new one (cheap enough for every batch of scans)."""
    if state.config.repose_deg is not None:
        return math.tan(math.radians(state.config.repose_deg))
    if estimate:
        cell = state.pile.geometry.cell_m
        deg = slump.estimate_repose_deg(state.height.elevation, cell,
                                        baseline_cells=_slope_baseline_cells(state))
        if math.isfinite(deg):
            state.tan_repose = math.tan(math.radians(deg))
    return state.tan_repose if math.isfinite(state.tan_repose) else math.tan(math.radians(35.0))


def _slope_baseline_cells(state: ProjectorState) -> int:
    """Half the run (cells) the repose angle's slopes are measured over: at least 4, and
    the run at least 8 point sds, but within a quarter of a flank's run.

    Noise in the heights makes a slope read steep, ``|g + n|^2 = |g|^2 + |n|^2``.  A
    laboratory pile's fused heights carry a few mm of it; over a 4 cm run (4 cells of
    5 mm either side) the angle read 0.1-0.2 deg steep, and every cut after the first, mostly
    material that slid off the face at that angle, came 1-4 % short.  At a yard (5 cm
    point sd, 25 cm cells) 4 cells already make a 2 m run.

    A young pile's flanks are short: the first pass's ridge at a laboratory stands about
    10 cm, its flanks about 14 cm across, and most 12 cm runs straddle the crest or the
    toe.  The angle read 31.8-36.1 deg where the simulator's is 37, and hidden flanks
    completed to that cone made the first lot 2-5 % heavy and the second as much light
    (bench-scale seeds 2 and 4).  So the half run is at most a quarter of the seen
    pile's height over tan(35 deg) (the angle assumed before one is estimated), and never
    under 4 cells.
    """
    cell = state.pile.geometry.cell_m
    half_run = max(4, math.ceil(4.0 * state.point_sd_m / cell))
    if state.stack is not None and state.height is not None and np.isfinite(
            state.height.elevation).any():
        height = float(np.nanmax(state.height.elevation)) - float(np.min(state.stack.ground()))
        flank_cells = height / math.tan(math.radians(35.0)) / cell
        half_run = min(half_run, max(4, int(flank_cells / 4)))
    return half_run


def _cone(state: ProjectorState, elevation: np.ndarray) -> np.ndarray:
    """The repose cone under the seen surface (NaN where no seen cell reaches)."""
    # the same slope as the slide's: a face left standing at it is not lifted again
    tan = _tan_repose(state) * (1.0 + state.config.relax_slack)
    return slump.repose_floor(elevation, state.pile.geometry.cell_m, tan)


def _unseen_floor(state: ProjectorState, elevation: np.ndarray, t_ns: int,
                  pouring_ns: np.ndarray | None = None) -> np.ndarray:
    """The repose cone of the (gap-filled) ``elevation`` where a pass crossed a cell since
    it was last seen (or it was seen while the pass still poured on it,
    :func:`_seen_while_pouring`), NaN elsewhere: a cell seen since is as measured,
    whatever the cone.

    A never-seen cell's cone rises from the seen heights fitted with a plane over
    ``cone_smooth_cells`` x ``cone_smooth_cells`` cells
    (:func:`heightmap.plane_fit_of_seen`).  Below a flank at repose every seen cell up
    the flank gives it the same cone height, give or take its noise, and the cone is
    their maximum: from the raw heights it stood 2-3 sigma of their noise high.  A
    laboratory pile's never-seen ends (half of their material is completed) came 7 %
    heavy, and the first cut of a bench there 10-12 %; with fitted heights they are
    within 1 %.  A cell seen while poured on lies down a flank seen with few points, so
    its cone rises from the fitted heights too.  ``pouring_ns``: the
    :func:`_seen_while_pouring` of this state, when the caller has it.
    """
    stale = _stale(state, t_ns)
    fitted = stale & ~np.isfinite(state.height.grid["last_update_ns"])
    if state.config.pouring_tail:
        if pouring_ns is None:
            pouring_ns = _seen_while_pouring(state, t_ns)
        pouring = np.isfinite(pouring_ns) & ~stale
        stale = stale | pouring
        fitted = fitted | pouring
    cone = _cone(state, elevation)
    n = int(state.config.cone_smooth_cells)
    if n > 1 and fitted.any():
        cone = np.where(fitted, _cone(state, heightmap.plane_fit_of_seen(elevation, n)), cone)
    return np.where(stale, cone, np.nan)


def _seen_while_pouring(state: ProjectorState, t_ns: int) -> np.ndarray:
    """When the last pass to cross each cell by ``t_ns`` crossed it (UTC ns, float64,
    (nx, ny)) where the cell was last seen after that crossing but while the pass's cone
    could still reach it; NaN elsewhere.  The pass has ended, and the look came less than
    :func:`slump.pour_reach_m` of rail travel after the crossing.

    A pass's flow varies, and each surge of the cone on its line reaches far down the
    flanks, behind the boom as well as ahead of it (by the pass's median layer, offset
    from the crest of each row).  A flank the scanner looked at only just after the
    stacker passed was still filling: bench-scale seed 3, the far flank looked at 8-30 s
    after the crossing was 4-13 mm low, and the next pass's layer took the rest (lot C
    -4.2 %, D +2.7 % of the pile).  Only the last crossing of each row counts.
    """
    geometry = state.pile.geometry
    out = np.full(geometry.shape, np.nan)
    passes, latest, last_crossing = _last_crossings(state, t_ns)
    if not passes or state.stack is None:
        return out
    typical = _typical_pass_s(passes)
    seen = state.height.grid["last_update_ns"]
    x, crest = _row_crests_m(geometry, state.stack.surface())
    for i in np.unique(latest):
        record = passes[int(i)]
        rows = (latest == i) & np.isfinite(last_crossing)
        speed = _stacker_speed_m_s(record, typical)
        if record.ended_ns is None or not rows.any() or not speed > 0:
            continue
        thickness = state.stack.thickness(record.deposit_index)
        layer = thickness[thickness > 0]
        if layer.size == 0:
            continue
        offset = x[:, None] - crest[None, rows]
        reach = slump.pour_reach_m(np.full(offset.shape, float(np.median(layer))), offset,
                                   _tan_repose(state, estimate=False))
        crossed = np.broadcast_to(last_crossing[rows][None, :], offset.shape)
        look = seen[:, rows]
        with np.errstate(invalid="ignore"):
            poured_on = (look >= crossed) & (look < np.minimum(crossed + reach / speed * 1e9,
                                                                float(t_ns)))
        out[:, rows] = np.where(poured_on, crossed, np.nan)
    return out


def _filled_elevation(state: ProjectorState) -> np.ndarray:
    """The height map's elevation with gaps of up to ``fill_gap_cells`` interpolated."""
    if not state.config.fill_gap_cells:
        return state.height.elevation
    return heightmap.fill_holes(state.height.elevation, method="linear",
                                max_gap_cells=state.config.fill_gap_cells)


def _complete_unseen(state: ProjectorState, t_ns: int,
                     filled_m: np.ndarray | None = None) -> np.ndarray | None:
    """Raise the stack to the repose cone of the seen surface where it is below it.

    A flank hidden behind the crest keeps its last seen (older, lower) height in the
    height map; the pile there is at least as high as the cone.  Its material goes to
    the passes that crossed the cell since it was last seen.  Returns the
    :func:`_unseen_floor` it used (None when it had none), for :func:`_follow_height`.
    ``filled_m``: the :func:`_filled_elevation`, when the caller has it.
    """
    if not state.config.complete_unseen or state.stack is None or state.stack.n_deposits == 0:
        return None
    elevation = _filled_elevation(state) if filled_m is None else filled_m
    if not np.isfinite(elevation).any():
        return None
    pouring_ns = _seen_while_pouring(state, t_ns) if state.config.pouring_tail else None
    floor = _unseen_floor(state, elevation, t_ns, pouring_ns)
    top = state.stack.surface()
    # A stale cell's margin is the fixed part only.  A never-seen cell has no variance
    # of its own (one point's sd there, 3 x 15 mm + 6 mm at a laboratory pile, held
    # hidden flanks a centimetre or more below the cone, and every slide off them came
    # up short: bench-scale cuts 5-27 % low even on noise-free scans); a seen one's says
    # how well its old level was known, not whether the pile is still there: a pass
    # crossed it since.
    margin = state.margin_m
    with np.errstate(invalid="ignore"):
        lift = (floor > top + margin) & ~(elevation >= floor - margin)
    if not lift.any():
        return floor
    level = np.where(lift, floor, np.nan)
    before = state.stack.total_volume_m3()
    accounted = _accounted_ns(state, state.height.grid["last_update_ns"])
    if pouring_ns is not None:
        # a look while a pass still poured saw part of its layer: that pass crossed since
        # (unless a completion after its crossing already took the layer)
        with np.errstate(invalid="ignore"):
            open_ = np.isfinite(pouring_ns) & ~(accounted > state.height.grid["last_update_ns"])
        accounted = np.where(open_, pouring_ns - 1.0, accounted)
    left = _rise_to_crossing_passes(state, level, accounted, t_ns)
    if left.any() and state.stack.n_deposits:
        # no pass crossed since the cell was seen: the top deposit's (it stands above it)
        state.stack, _added = state.stack.raise_to(np.where(left, level, np.nan),
                                                   _deposition_ns(state, t_ns, left))
    # a new array each time (never written in place: a snapshot's arrays are read-only)
    state.completed_ns = np.where(lift, float(t_ns), np.nan if state.completed_ns is None
                                  else state.completed_ns)
    _journal_rises(state, t_ns, np.flatnonzero(lift), top)
    state.count("cells_completed", int(lift.sum()))
    state.count("completed_mm3", int(round((state.stack.total_volume_m3() - before) * 1e3)))
    return floor


def _accounted_ns(state: ProjectorState, seen_ns: np.ndarray) -> np.ndarray:
    """Since when each cell's material is accounted for: the later of when it was last
    seen (``seen_ns``, (nx, ny)) and when it was last completed to the repose cone.

    A rise is given to the passes that crossed a cell since then.  A never-seen cell is
    completed at each pass's start as the cone of the growing pile rises; counted from
    never, each increment was shared by every pass so far, and the outer layer's material
    went to the layers under it (demo seed 2: the first cut +0.45 pp Fe).
    """
    if state.completed_ns is None:
        return seen_ns.copy()
    return np.fmax(seen_ns, state.completed_ns)


def _catch_up_rises(state: ProjectorState, t_ns: int) -> None:
    """Raise the stack to the height map where it is below it by less than the margin but
    the cells around agree that it rose.

    Each cell follows a rise only beyond its own noise margin, so a layer thinner than
    the margin is taken up only partly.  Pooled over ``catch_up_cells`` x
    ``catch_up_cells`` seen cells the mean rise is known far better: where it exceeds
    3 sigma of that mean, the cells that are above the stack rise to the height map,
    their material the top deposit's (the pass before the next).

    The test is the pooled mean's own 3 sigma and nothing more.  A floor of a quarter of
    ``margin_m`` on top of it (1.5 mm at bench scale, where a pass lays 30-60 mm) left
    every bench-scale pile's stack 0.2-0.3 mm below its height map: the five seeds'
    piles read -0.63, -0.26, -0.83, -0.20 and -0.57 % with it, -0.38, -0.01, -0.56,
    +0.02 and -0.39 % without (the demo's within 0.03 points of before).
    """
    n = int(state.config.catch_up_cells)
    if n < 2 or state.stack is None or state.stack.n_deposits == 0:
        return
    from scipy import ndimage

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
                                               _deposition_ns(state, t_ns, up))
    _journal_rises(state, t_ns, np.flatnonzero(up), top)
    state.count("cells_caught_up", int(up.sum()))
    state.count("caught_up_mm3", int(round((state.stack.total_volume_m3() - before) * 1e3)))


def _seen_nearby_ns(state: ProjectorState, seen_ns: np.ndarray) -> np.ndarray:
    """``seen_ns`` with each never-seen cell given the latest time a cell within
    ``fill_gap_cells`` of it was seen (NaN where none was)."""
    from scipy import ndimage

    size = 2 * max(int(state.config.fill_gap_cells), 1) + 1
    filled = ndimage.maximum_filter(np.where(np.isfinite(seen_ns), seen_ns, -np.inf),
                                    size=size, mode="constant", cval=-np.inf)
    return np.where(np.isfinite(seen_ns), seen_ns, np.where(np.isfinite(filled), filled, np.nan))


def _stale(state: ProjectorState, t_ns: int, seen_ns: np.ndarray | None = None) -> np.ndarray:
    """Cells (nx, ny) never seen, or crossed by a pass's stacker since last seen by ``t_ns``
    (``seen_ns``: when each cell was last seen, UTC ns, NaN never; default the height
    map's ``last_update_ns``)."""
    seen = state.height.grid["last_update_ns"] if seen_ns is None else seen_ns
    _passes, _latest, last_crossing = _last_crossings(state, t_ns)
    with np.errstate(invalid="ignore"):
        return ~np.isfinite(seen) | (seen < last_crossing[None, :])


def _last_crossings(state: ProjectorState,
                    t_ns: int) -> tuple[list[PassRecord], np.ndarray, np.ndarray]:
    """The passes, and for each row along the rail (shape (ny,)) the index into them of the
    pass whose stacker crossed it last by ``t_ns`` and when (UTC ns, float64; -inf where
    none has, index 0 there)."""
    passes = list(state.passes.values())
    ny = state.pile.geometry.ny
    if not passes:
        return passes, np.zeros(ny, dtype=np.intp), np.full(ny, -np.inf)
    typical = _typical_pass_s(passes)
    y = _row_y_m(state.pile.geometry)
    crossings = np.stack([_crossing_ns(record, y, t_ns, typical) for record in passes])
    crossings[crossings > t_ns] = -np.inf
    latest = np.argmax(crossings, axis=0)
    return passes, latest, crossings[latest, np.arange(ny)]


def _slump_face(state: ProjectorState, floor_m: np.ndarray) -> float:
    """Let the face a cut left slide to the angle of repose; returns the volume moved (m3)."""
    geometry = state.pile.geometry
    tan = _tan_repose(state) * (1.0 + state.config.relax_slack)
    top = state.stack.surface()
    ix, iy = np.nonzero(np.isfinite(floor_m))
    if ix.size == 0:
        return 0.0
    height = float(np.max(top) - np.min(state.stack.ground()))
    pad = int(math.ceil(height / tan / geometry.cell_m)) + 2
    region = (slice(max(0, ix.min() - pad), min(geometry.nx, ix.max() + pad + 1)),
              slice(max(0, iy.min() - pad), min(geometry.ny, iy.max() + pad + 1)))
    state.stack, moved, _raised = slump.slump(state.stack, tan, region)
    state.count("slumps")
    return moved.volume_m3


def _row_y_m(geometry: GridGeometry) -> np.ndarray:
    """Where each row of cells lies along the rail: the y (m) of its centres, shape (ny,)."""
    return cell_centre(geometry, 0, np.arange(geometry.ny))[1]


def _typical_pass_s(passes) -> float | None:
    """The median duration of the passes that ended (s), None when none has."""
    ended = [(p.ended_ns - p.started_ns) / 1e9 for p in passes if p.ended_ns is not None]
    return float(np.median(ended)) if ended else None


def _assumed_end_ns(record: PassRecord, typical_s: float | None) -> float | None:
    """When a pass ended (UTC ns, float), or for one still running when it will, after the
    typical duration of the passes before it (None when none has ended)."""
    if record.ended_ns is not None:
        return float(record.ended_ns)
    return None if typical_s is None else float(record.started_ns) + typical_s * 1e9


def _crossing_ns(record: PassRecord, y_m: np.ndarray, now_ns: int,
                 typical_s: float | None) -> np.ndarray:
    """When the stacker of a pass passed each position along the rail (UTC ns, float).

    The stacker moves from ``start_y_m`` to ``end_y_m`` at a steady speed between the
    pass's start and end; a pass still running ends, by assumption, after the typical
    duration of the passes before it (or now when none ended yet).
    """
    t0 = float(record.started_ns)
    t1 = _assumed_end_ns(record, typical_s)
    if t1 is None:
        t1 = float(max(now_ns, record.started_ns + 1))
    span = record.end_y_m - record.start_y_m
    if not math.isfinite(span) or span == 0:
        return np.full(y_m.shape, t0)
    frac = np.clip((y_m - record.start_y_m) / span, 0.0, 1.0)
    return t0 + frac * (t1 - t0)


def _rise_to_crossing_passes(state: ProjectorState, surface: np.ndarray,
                             seen_before_ns: np.ndarray, t_ns: int,
                             observed_ns: np.ndarray | None = None) -> np.ndarray:
    """Give each risen cell's material to the passes whose stacker crossed it since it
    was last seen, in equal shares, deposited when the stacker crossed (earlier near
    and past the end of its run: :func:`_crossing_dates`); returns the cells still
    risen (no such pass, or a later deposit already holds material there).

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
    typical = _typical_pass_s(passes)
    geometry = state.pile.geometry
    iy = cells % geometry.ny
    y = _row_y_m(geometry)[iy]
    seen = seen_before_ns.ravel()[cells]
    if not np.isfinite(seen).all():
        # a cell never seen itself lies between (or beside) seen ones: it was last seen
        # when they were, not never (else every pass so far would share its rise)
        blind = ~np.isfinite(seen)
        bx, by = np.divmod(cells[blind], geometry.ny)
        box = _around(bx, by, max(int(state.config.fill_gap_cells), 1), geometry)
        seen = seen.copy()
        seen[blind] = _seen_nearby_ns(state, seen_before_ns[box])[bx - box[0].start,
                                                                   by - box[1].start]
    prev = np.where(np.isfinite(seen), seen, -np.inf)
    upto = np.full(cells.size, float(t_ns))
    if observed_ns is not None:
        upto = np.fmin(upto, observed_ns.ravel()[cells])
    cands = []
    for record in passes:
        crossing = _crossing_ns(record, y, t_ns, typical)
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
                crests = _row_crests_m(geometry, state.stack.surface())
            updates.append((record.deposit_index, cells[hit],
                            (top + rise * (position / np.maximum(count, 1)))[hit],
                            _crossing_dates(state, record, cells[hit], share, crossing[hit],
                                            typical, crests)))
    state.stack, raised = state.stack.raise_deposits(updates)
    done = sum(int(r.sum()) for r in raised)
    if done:
        state.count("rises_by_crossing", done)
    # what is left: cells not fully raised (a later deposit already held material)
    with np.errstate(invalid="ignore"):
        return risen & (surface > state.stack.surface())


def _crossing_dates(state: ProjectorState, record: PassRecord, cells: np.ndarray,
                    thickness_m: np.ndarray, crossing_ns: np.ndarray,
                    typical_s: float | None,
                    crests: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """When a pass laid its material in ``cells`` (flat indices, ``thickness_m`` of it
    each), given when its stacker crossed them (UTC ns, float64, shape of ``cells``);
    ``crests``: :func:`_row_crests_m` of the stack's top, when the caller has it.

    Along the run the crossing stands: the cone's front lays a cell's layer before the
    boom comes (:func:`slump.pour_front_lead_m`), but a varying flow lays part of it
    after the boom has passed, for about as far again (:func:`slump.pour_reach_m`), and
    the two offset (dated by the front alone, a pass's material was 7-9 s early on
    bench-scale seed 2).  Toward the end of the run fewer releases come after the
    crossing: with less run left than the cone's reach the front's lead counts in
    proportion, in full at the end, and past the end (the pile's end slope, where the
    crossing is the pass's end) the boom stops short of the cell and the lead is the
    mean travel it still had to go (:func:`slump.pour_end_lead_m`).  Dated at the
    crossing, the bench-scale passes' last 0.12 m and the end slope past them (where
    the reclaimer's first cuts take from) read 9-32 s after the simulator's times (seed
    3), 5-18 s with this; a lot's assays there cover 30 s.  Never before the pass
    started.
    """
    speed_m_s = _stacker_speed_m_s(record, typical_s)
    if not speed_m_s > 0 or cells.size == 0:
        return crossing_ns
    geometry = state.pile.geometry
    ix, iy = np.divmod(cells, geometry.ny)
    x, crest = crests or _row_crests_m(geometry, state.stack.surface())   # the boom's line
    offset = (x[ix] - crest[iy])[None, :]
    thickness = np.asarray(thickness_m, np.float64)[None, :]
    ahead = (record.end_y_m - _row_y_m(geometry)[iy]) * np.sign(record.end_y_m
                                                                 - record.start_y_m)
    tan = _tan_repose(state, estimate=False)
    lead_m = slump.pour_end_lead_m(thickness, offset, np.clip(-ahead, 0.0, None)[None, :],
                                   tan)[0]
    reach = slump.pour_reach_m(thickness, offset, tan)[0]
    with np.errstate(invalid="ignore", divide="ignore"):
        weight = np.where(ahead <= 0, 1.0, np.clip(1.0 - ahead / reach, 0.0, 1.0))
    weight = np.where(reach > 0, weight, 0.0)
    return np.maximum(crossing_ns - weight * lead_m / speed_m_s * 1e9, float(record.started_ns))


def _deposition_ns(state: ProjectorState, t_ns: int,
                   rising: np.ndarray | None = None) -> int | np.ndarray:
    """When the top deposit's material seen rising at ``t_ns`` was deposited: one integer
    (UTC ns) for every cell, or a float64 array of shape (nx, ny).  ``rising``: the cells
    (bool, (nx, ny)) about to rise, the only ones whose times are used (default all).

    Material of a pass was stacked as the stacker came over it (:func:`_crossing_ns`, a
    run along the rail), not when the scanner, which trails the stacker, saw it; the
    lot's grade is looked up by this time, in assay windows of tens of seconds.  The
    poured cone's front reaches a cell before the boom does, the more so the thicker
    the layer and the further down the flank: the crossing less :func:`_pour_lead_s`,
    with the layer as the height map (or the stack) stands over the deposit below.  It
    is never after ``t_ns`` nor outside the pass.  A pass without rail positions gives
    the time seen, clipped to the pass; material outside any pass, ``t_ns``.
    (Bench-scale seed 2: the time seen lagged the simulator's deposition time by 30-70 s
    on average, the crossing by 13-18 s.)

    Only the material this dates (a rise no crossing explains, a catch-up, a completed
    flank) gets the lead; a rise given to the passes that crossed a cell since it was
    last seen keeps their crossings (:func:`_rise_to_crossing_passes`): the lead there
    overshot the simulator's times by 7-9 s on average, bench-scale seed 2, and its cuts'
    Fe moved from within 0.27 pp to 0.51 pp.
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
    y = _row_y_m(geometry)
    typical = _typical_pass_s(state.passes.values())
    times = np.repeat(_crossing_ns(record, y, t_ns, typical)[None, :], geometry.nx, axis=0)
    ix, iy = np.nonzero(np.ones(geometry.shape, bool) if rising is None else rising)
    top = state.stack.surface()
    # the pass's layer as it stands now: the map's level (or the stack's) over the deposit
    # below the pass's
    level = np.fmax(state.height.elevation[ix, iy], top[ix, iy])
    below = state.stack.surface_k(state.stack.n_deposits - 1)[ix, iy]
    times[ix, iy] -= _pour_lead_s(state, record, level - below, ix, iy, top, typical) * 1e9
    return np.clip(times, float(record.started_ns), float(seen))


def _pour_lead_s(state: ProjectorState, record: PassRecord, thickness_m: np.ndarray,
                 ix: np.ndarray, iy: np.ndarray, top_m: np.ndarray,
                 typical_s: float | None) -> np.ndarray:
    """How long before its stacker crossed cells ``(ix, iy)`` a pass laid its layer there,
    on average (s, shape of ``ix``; 0 where unknown): :func:`slump.pour_front_lead_m` over
    the stacker's speed along the rail.

    The boom pours on the crest: each row's line is where the stack's top (``top_m``,
    (nx, ny)) is highest.  ``thickness_m``: the pass's layer at each cell (m);
    ``typical_s``: the duration assumed for a pass still running (:func:`_typical_pass_s`).
    """
    geometry = state.pile.geometry
    speed_m_s = _stacker_speed_m_s(record, typical_s)
    if not speed_m_s > 0 or ix.size == 0:
        return np.zeros(ix.shape)
    x, crest = _row_crests_m(geometry, top_m)
    offset = x[ix] - crest[iy]
    lead_m = slump.pour_front_lead_m(thickness_m[None, :], offset[None, :],
                                     _tan_repose(state, estimate=False))[0]
    return lead_m / speed_m_s


def _row_crests_m(geometry: GridGeometry, top_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(x, crest)``: the cells' x centres (nx,) and, per row, the x of the highest cell of
    ``top_m`` (ny,), where a stacker's boom pours (m)."""
    x = cell_centre(geometry, np.arange(geometry.nx), 0)[0]
    return x, x[np.argmax(top_m, axis=0)]


def _stacker_speed_m_s(record: PassRecord, typical_s: float | None) -> float:
    """The pass's stacker speed along the rail (m/s; NaN when its run or duration is
    unknown): its run over its duration (:func:`_assumed_end_ns` for a running pass)."""
    t1 = _assumed_end_ns(record, typical_s)
    run_m = abs(record.end_y_m - record.start_y_m)
    if t1 is None or t1 <= record.started_ns or not run_m > 0:
        return math.nan
    return run_m / ((t1 - record.started_ns) / 1e9)


def _fit_buried_boundaries(state: ProjectorState) -> None:
    """Fit the tops of the deposits below the top one that are not fitted yet
    (``FoldConfig.boundary_fit_cells``): the passes that laid them are complete."""
    window, n = int(state.config.boundary_fit_cells), state.stack.n_deposits
    if window < 3 or n - 1 <= state.boundaries_fitted:
        return
    state.stack = state.stack.fit_boundaries(range(state.boundaries_fitted + 1, n), window)
    state.count("boundaries_fitted", n - 1 - state.boundaries_fitted)
    state.boundaries_fitted = n - 1


def _fit_top_for_cut(state: ProjectorState, floor_m: np.ndarray) -> np.ndarray | None:
    """Put the top a cut is about to take on a local quadratic fit where it stands above
    the cut's floor (``FoldConfig.cut_fit_cells``); counter ``cut_top_fit_mm3``: the
    volume the fit added to the stack less what it removed (before the caller restores
    the part under the floor after the cut).

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


def _settling_last_pass(state: ProjectorState) -> bool:
    """Whether rises now still belong to the pass that ended last.

    The scanner sees a stacked layer only when it passes over it, often after the
    pass has ended: until the next cut, a rise is that pass's material (it is the top
    deposit then).
    """
    if not state.passes or state.stack.n_deposits == 0:
        return False
    last = max(state.passes.values(), key=lambda p: p.started_ns)
    if last.deposit_index != state.stack.n_deposits:
        return False
    last_cut = max((c.end_ns for c in state.cuts), default=None)
    return last_cut is None or (last.ended_ns or last.started_ns) > last_cut


def _last_event_ns(state: ProjectorState) -> int:
    """The latest pass or cut boundary: a flagged deposit opened before it is not reused."""
    times = [p.ended_ns or p.started_ns for p in state.passes.values()]
    times += [c.end_ns for c in state.cuts]
    return max(times) if times else -(2 ** 62)
