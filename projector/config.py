"""The fold's tuning: :class:`FoldConfig`, one frozen record per projection.

Its defaults suit an LMS200 on a full-scale reclaimer; a laboratory pile (cells under
5 cm) resolves the noise-dependent ones differently (:func:`projector.fold.apply` on
``pile_declared``).  Snapshots are keyed by the config's ``repr``, so one
folded with another config never serves a query.  Why each rule and its default were
chosen: see docs/design-notes.md.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from schemas.times import NS_PER_S

__all__ = ["FoldConfig"]


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
    complete_unseen : bool
        When the next pass starts, at a cut and at a query's end, cells a pass crossed
        since they were last seen (or never seen) that lie more than ``margin_m`` below
        the repose cone of the seen surface (a flank hidden behind the crest) rise to
        it, the material given to the passes that crossed them since they were last seen
        (:func:`projector.completion.complete_unseen`).  False: they keep their last
        seen height.
    refresh_crossed : bool
        Before a batch of scans is fused, cells a stacking pass reached since they were
        last seen get a variance of at least ``(refresh_sd_factor * point_sd_m)^2``, so
        the height map takes the layer the pass laid there at its next look rather than a
        Kalman step from the level before (:func:`projector.scans.refresh_crossed`).
    refresh_sd_factor : float
        That variance, in point sds (10: the old level is as good as forgotten, the next
        look weighs about 99 %).
    refresh_reach : bool
        A pass reaches a cell when its stacker comes within the pile's height /
        tan(repose) of it along the rail (poured material runs down the flanks that far);
        False: only when it passes the cell's own position.
    follow_far_drops : bool
        Whether the stack follows a drop seen after a cut away from the latest cut's
        footprint (grown by a cell, :func:`projector.cuts.near_cut`): True, its volume is
        counted as an unexplained loss (counter ``unexplained_loss_mm3``, in 1e-3 m3).
        False (default): the stack keeps the slid face its own model predicts (a cut's
        face slides to the angle of repose), and how far the measurement lies below it
        there is reported (``far_drops_mm3``, the latest follow's).
    relax_slack : float
        Faces steeper than ``(1 + relax_slack) * tan(repose)`` slide (a little slack keeps
        the estimated angle's error from creeping standing flanks).
    catch_up_cells : int
        When a pass starts (and at the first cut or a query's end after the last pass),
        the stack catches up with rises smaller than a cell's margin
        where the mean rise over this many x this many cells is significant; < 2: never.
    boundary_fit_cells : int
        At the first cut after a pass (the layers below the top one are complete), each
        deposit's top that no such cut has fitted yet, other than the top one, is replaced
        by a local quadratic fit over this many x this many cells
        (:meth:`projector.layers.LayerStack.fit_boundaries`; odd; 1: as fused).
    cut_fit_cells : int
        At the first cut after a pass, the top where it stands above the cut's floor is
        replaced by a local quadratic fit over this many x this many cells before the cut
        takes what is above the floor (:meth:`projector.layers.LayerStack.fit_top_above`;
        odd; 1: as fused).
    dig_journal_s : float
        The stack's rises are remembered this long (s), so that a cut up to this long
        undoes those its own digging caused in its footprint
        (:func:`projector.cuts.undo_digging_rises`).
    cone_smooth_cells : int
        A never-seen cell's repose cone rises from the seen heights fitted with a plane
        over this many x this many cells (odd; 1: the heights as fused), so that it is
        not the maximum of their noise (:func:`projector.completion.unseen_floor`).
    pouring_tail : bool
        A cell last seen while the cone of the last pass to cross it could still reach
        it (:func:`projector.completion.seen_while_pouring`) counts as crossed since it
        was seen: a hidden flank's layer is completed to the repose cone at the next pass
        rather than taken with the one after it.
    profile_fit_beams : int
        Each scan's kept ranges are fitted with a line over this many beams (odd; 1: as
        measured), never across a range jump, before they are georeferenced
        (:func:`projector.profile.clean_profile`, ``fit_beams``): the range noise
        that spreads points along their beams drops by sqrt(3) for 3.
    grazing_mixed_frac : float
        On a run of a scan seen at grazing incidence (steps over the jump threshold), a
        return farther than the midpoint of its two neighbours by more than this fraction
        of their mean step is a mixed pixel and is dropped
        (:func:`projector.profile.clean_profile`, ``grazing_frac``; 0: kept).
    ground_reference : bool
        Each scan's height is referenced to the declared ground it sees
        (:func:`projector.scans.reference_ground`): the median offset of the bare-ground
        points of the scans within ``ground_window_s`` is subtracted from its points'
        heights, when it lies outside the deadband below.  A localizer's scanner height
        drifts (its luff is seen only through GNSS height); the ground does not.
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
        yard, 7.5 mm at a laboratory pile).
    """

    pile_id: str
    point_sd_m: float | None = None
    scan_batch: int = 50
    max_pose_gap_ns: int = 2 * NS_PER_S
    max_scan_wait_ns: int = 10 * NS_PER_S
    margin_sigma: float = 3.0
    margin_m: float | None = None
    process_sd_m: float | None = None
    gate_sigma: float = 3.0
    change_count: int = 3
    strong_points: int = 3
    fill_gap_cells: int = 16
    pad_m: float | None = None
    repose_deg: float | None = None
    complete_unseen: bool = True
    refresh_crossed: bool = True
    refresh_sd_factor: float = 10.0
    refresh_reach: bool = True
    follow_far_drops: bool = False
    relax_slack: float = 0.0
    catch_up_cells: int = 5
    boundary_fit_cells: int = 7
    cut_fit_cells: int = 7
    dig_journal_s: float = 3600.0
    cone_smooth_cells: int = 5
    pouring_tail: bool = True
    profile_fit_beams: int = 3
    grazing_mixed_frac: float = 0.25
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
        return {"point_sd_m": sd, "half_window_ns": int(self.ground_window_s * NS_PER_S),
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
