"""Measurements overrule the prior: a cut's face slide fitted to the scans after it.

After a cut the fold predicts how its face slides (the prior: the angle the pile's faces
have been seen to stand at, else the angle of repose) and puts that prediction into the
height map, but keeps the stack as the cut left it, unslid (:func:`open_face`).  The
face stays open until the next cut, the next pass or a query's end; the stack does not
follow the map over it meanwhile (:func:`face_cells`).  Then (:func:`close_face`) the
slide angle between repose and 90 deg that best explains the heights the scans saw on
the face since the cut (:func:`fit_slide_angle`) slides the stack's face, mass and
composition conserved (:func:`projector.slump.slump`); cells never seen since the cut
keep that fit's prediction and are counted (``face_cells_seen`` /
``face_cells_predicted``, per cut and in the counters).

A drop the scans see later on a closed face, away from the latest cut, is a delayed
failure: the face there slides to the angle of repose when the drop is seen
(:func:`slide_seen_failure`).  :func:`material_estimate` aggregates the fitted angles
per pile.  How the rules were chosen and what they measured: docs/fidelity.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from projector import slump
from projector.cuts import slide_region
from projector.repose import tan_repose
from projector.state import CutRecord, ProjectorState

__all__ = ["OpenFace", "SlideFit", "fit_slide_angle", "open_face", "close_face",
           "face_cells", "note_sightings", "slide_seen_failure", "material_estimate", "prior_tan"]

#: the coarse step (deg) of the angles tried between repose and 90 deg; two halvings refine it
FIT_STEP_DEG = 5.0
#: fewest face cells seen since the cut for a fit (fewer: the prior stays) ...
MIN_FIT_CELLS = 12
#: ... and the least share of the face's cells seen
MIN_FIT_FRACTION = 0.02
#: a face whose fitted angle is this much (deg) steeper than repose stood
STOOD_DEG = 5.0
#: a fitted angle less than this much (deg) steeper than repose is read as repose: the
#: repose estimate's own error and the fit's resolution near it are of that order
SNAP_DEG = 2.5
#: fewest cells of a drop away from the latest cut that can be a delayed failure
MIN_FAILURE_CELLS = 25
#: a cell of the next cut's footprint first seen within this many margins of its floor
#: may have been dug when it was seen
DUG_MARGINS = 3.0
#: a residual beyond this many margins counts no more than that (walls, strays)
RESIDUAL_CLIP_MARGINS = 10.0


@dataclass(frozen=True)
class OpenFace:
    """A cut's face waiting for the scans after it.

    ``cut_index``: the cut's index in ``state.cuts``; ``end_ns``: its end (UTC ns);
    ``region``: the block (slice, slice) its slide may move; ``cells``: bool over the
    region, the cells a slide to repose moves (grown by a cell); ``repose_top_m``: the
    stack's top over the region slid to repose (m); ``tan_repose`` and ``tan_prior``: the
    slopes of the slide to repose and of the predicted one.
    """

    cut_index: int
    end_ns: int
    region: tuple[slice, slice]
    cells: np.ndarray
    repose_top_m: np.ndarray
    tan_repose: float
    tan_prior: float


@dataclass(frozen=True)
class SlideFit:
    """What :func:`fit_slide_angle` found: the angle (deg; NaN: too few cells seen), the
    face cells seen and those not seen, and the sum of squared residuals (m2) per angle
    tried (deg -> m2)."""

    angle_deg: float
    cells_seen: int
    cells_predicted: int
    sse_m2: dict[float, float]


def _slope(angle_deg: float) -> float:
    """The slope (rise over run) of ``angle_deg``; 90 deg and steeper: infinite (as cut)."""
    return math.inf if angle_deg >= 90.0 else math.tan(math.radians(angle_deg))


def _relaxed(top_m: np.ndarray, base_m: np.ndarray, cell_m: float, tan: float) -> np.ndarray:
    """``top_m`` slid to slope ``tan`` (an infinite slope: as it stands)."""
    if not math.isfinite(tan):
        return top_m.copy()
    return slump.relax_surface(top_m, base_m, cell_m, tan)


def fit_slide_angle(top_m, base_m, seen_m, cell_m: float, repose_deg: float, *,
                    change_m: float, clip_m: float | None = None,
                    step_deg: float = FIT_STEP_DEG, min_cells: int = MIN_FIT_CELLS,
                    min_fraction: float = MIN_FIT_FRACTION) -> SlideFit:
    """The slide angle between ``repose_deg`` and 90 deg whose slide of ``top_m`` best
    explains the heights seen, ``seen_m``.

    The face's cells are those a slide to repose moves by more than ``change_m``; the
    angle minimises the sum of squared residuals (each clipped at ``clip_m``) over those
    seen (at least ``min_cells`` and ``min_fraction`` of the face's cells, else no fit:
    NaN).  Angles are tried from repose up in steps of ``step_deg`` and at 90 deg (the
    face as cut), then twice at half the step either side of the best; of angles that
    explain the heights alike (a face steeper than the grid resolves) the steepest.

    Parameters
    ----------
    top_m, base_m : array_like, shape (nx, ny)
        The surface as the cut left it and the level nothing moves below (m, finite).
    seen_m : array_like, shape (nx, ny)
        Heights seen since the cut (m); NaN = not seen.
    cell_m : float
        Cell edge (m).
    repose_deg : float
        The angle of repose (deg, in (0, 90)).
    change_m : float
        A cell a slide to repose moves by more than this (m) belongs to the face.
    clip_m : float, optional
        Largest residual counted (m); default ``RESIDUAL_CLIP_MARGINS * change_m``.

    Returns
    -------
    SlideFit
    """
    top = np.asarray(top_m, np.float64)
    base = np.asarray(base_m, np.float64)
    seen = np.asarray(seen_m, np.float64)
    if not (top.shape == base.shape == seen.shape and top.ndim == 2):
        raise ValueError(f"top_m {top.shape}, base_m {base.shape} and seen_m {seen.shape} "
                         "must be 2-D arrays of one shape")
    if not (math.isfinite(repose_deg) and 0.0 < repose_deg < 90.0):
        raise ValueError(f"repose_deg must be in (0, 90), got {repose_deg!r}")
    clip = RESIDUAL_CLIP_MARGINS * change_m if clip_m is None else float(clip_m)
    surfaces: dict[float, np.ndarray] = {}

    def surface(angle: float) -> np.ndarray:
        if angle not in surfaces:
            surfaces[angle] = _relaxed(top, base, cell_m, _slope(angle))
        return surfaces[angle]

    face = np.abs(surface(repose_deg) - top) > change_m
    observed = face & np.isfinite(seen)
    n_seen, n_face = int(observed.sum()), int(face.sum())
    if n_seen < max(min_cells, min_fraction * n_face):
        return SlideFit(math.nan, n_seen, n_face - n_seen, {})
    z = seen[observed]
    sse: dict[float, float] = {}

    def cost(angle: float) -> float:
        if angle not in sse:
            r = np.minimum(np.abs(surface(angle)[observed] - z), clip)
            sse[angle] = float(np.sum(r * r))
        return sse[angle]

    def key(angle: float) -> tuple[float, float]:
        return cost(angle), -angle     # of angles that slide alike, the steepest

    angles = [float(a) for a in np.arange(repose_deg, 90.0, step_deg)] + [90.0]
    best = min(angles, key=key)
    for half in (step_deg / 2, step_deg / 4):
        near = [a for a in (best - half, best + half) if repose_deg <= a <= 90.0]
        best = min([best, *near], key=key)
    return SlideFit(float(best), n_seen, n_face - n_seen, sse)


def prior_tan(state: ProjectorState, tan_rep: float) -> float:
    """The slope a new face is predicted to slide to: the angle the pile's faces were
    fitted to (the median), when they stood (:data:`STOOD_DEG` steeper than repose);
    else ``tan_rep``."""
    angles = [a for _cut, a, _n in state.slide_fits]
    if not angles:
        return tan_rep
    median = float(np.median(angles))
    if median < math.degrees(math.atan(tan_rep)) + STOOD_DEG:
        return tan_rep
    return _slope(median)


def open_face(state: ProjectorState, record: CutRecord, floor_m: np.ndarray) -> np.ndarray:
    """Open the face a cut (``record``, the next in ``state.cuts``) left in the stack:
    the stack stays as cut; returns the predicted top (m, (nx, ny)), the stack's top with
    the face slid at the prior (:func:`prior_tan`), for the height map."""
    top = state.stack.surface().copy()
    if not np.isfinite(floor_m).any():
        return top
    tan_rep = tan_repose(state) * (1.0 + state.config.relax_slack)
    region = slide_region(state, np.isfinite(floor_m), tan_rep)
    base = state.stack.ground()[region]
    at_repose = _relaxed(top[region], base, state.pile.geometry.cell_m, tan_rep)
    moved = np.abs(at_repose - top[region]) > 1e-9
    if not moved.any():
        return top
    tan_pri = prior_tan(state, tan_rep)
    predicted = (at_repose.copy() if tan_pri == tan_rep
                 else _relaxed(top[region], base, state.pile.geometry.cell_m, tan_pri))
    cells = ndimage.binary_dilation(moved, structure=np.ones((3, 3), bool))
    at_repose.setflags(write=False)
    cells.setflags(write=False)
    state.open_face = OpenFace(len(state.cuts), record.end_ns, region, cells, at_repose,
                               tan_rep, tan_pri)
    state.face_sightings = (np.full(cells.shape, np.nan), np.full(cells.shape, np.nan))
    top[region] = predicted
    state.count("faces_opened")
    return top


def face_cells(state: ProjectorState, elevation: np.ndarray | None = None
               ) -> tuple[np.ndarray, np.ndarray] | None:
    """What the stack does not follow until the open face closes, ``(rises, drops)``
    (bool, (nx, ny)): rises on the face's cells, and drops there that a slide explains,
    not below the face slid to repose by more than the margin (``elevation``, m, the
    heights followed, (nx, ny); None: every drop there).  None when no face is open.
    A drop below any slide (the wheel dug deeper than its envelope) is followed."""
    face = state.open_face
    if face is None:
        return None
    rises = np.zeros(state.pile.geometry.shape, bool)
    rises[face.region] = face.cells
    drops = rises.copy()
    if elevation is not None and elevation.shape == rises.shape:
        with np.errstate(invalid="ignore"):
            below = elevation[face.region] < face.repose_top_m - state.margin_m
        drops[face.region] &= ~below
    return rises, drops


def note_sightings(state: ProjectorState) -> None:
    """Keep (in place) the height the map first took on each open face cell after the
    face's cut, and when: the next cut's digging changes them again later."""
    face = state.open_face
    if face is None or state.face_sightings is None:
        return
    first_z, first_ns = state.face_sightings
    grid = state.height.grid
    updated = grid["last_update_ns"][face.region]
    with np.errstate(invalid="ignore"):
        new = face.cells & np.isnan(first_ns) & (updated > face.end_ns)
    if new.any():
        first_z[new] = grid["elevation"][face.region][new]
        first_ns[new] = updated[new]


def _seen_since(state: ProjectorState, face: OpenFace, next_floor_m: np.ndarray | None,
                next_start_ns: int | None) -> np.ndarray:
    """The heights (m, over the face's region) the scans first saw since the face's cut
    (:func:`note_sightings`); NaN where they did not, or where the next cut
    (``next_floor_m``, +inf outside its footprint; started at ``next_start_ns``) may have
    dug what they saw: first seen after it started, in its footprint at its floor
    (within :data:`DUG_MARGINS` margins) or just beside it.  A cell of its footprint
    first seen clearly above its floor was seen before the wheel got there."""
    note_sightings(state)
    first_z, first_ns = state.face_sightings
    with np.errstate(invalid="ignore"):
        seen = np.isfinite(first_z)
        if next_floor_m is not None and next_start_ns is not None:
            floor = next_floor_m[face.region]
            inside = np.isfinite(floor)
            near = ndimage.binary_dilation(inside, structure=np.ones((3, 3), bool))
            late = first_ns >= next_start_ns
            at_floor = np.abs(first_z - floor) <= DUG_MARGINS * state.margin_m
            dug = late & ((inside & at_floor) | (near & ~inside))
            seen &= ~dug
    return np.where(seen, first_z, np.nan)


def close_face(state: ProjectorState, next_floor_m: np.ndarray | None = None,
               next_start_ns: int | None = None) -> None:
    """Slide the open face (in place) at the angle fitted to the scans after its cut
    (:func:`fit_slide_angle`; too few seen: the prior), record the fit in its
    :class:`CutRecord` and ``state.slide_fits``, and put the slid top into the height map
    where the face was not seen since the cut.  ``next_floor_m`` / ``next_start_ns``: the
    cut about to be applied (what its digging was seen to do is left out of the fit)."""
    face = state.open_face
    if face is None:
        return
    record = state.cuts[face.cut_index]
    geometry = state.pile.geometry
    region = face.region
    top = state.stack.surface()[region]
    base = state.stack.ground()[region]
    seen = _seen_since(state, face, next_floor_m, next_start_ns)
    state.open_face, state.face_sightings = None, None
    repose_deg = math.degrees(math.atan(face.tan_repose))
    fit = fit_slide_angle(top, base, np.where(face.cells, seen, np.nan), geometry.cell_m,
                          repose_deg, change_m=state.margin_m)
    if math.isfinite(fit.angle_deg):
        angle = repose_deg if fit.angle_deg < repose_deg + SNAP_DEG else fit.angle_deg
        tan = face.tan_repose if angle <= repose_deg else _slope(angle)
        state.slide_fits.append((record.cut_id, angle, fit.cells_seen))
        state.count("faces_fitted")
    else:
        tan = face.tan_prior
        angle = 90.0 if not math.isfinite(tan) else math.degrees(math.atan(tan))
    record.slide_angle_deg = angle
    record.face_cells_seen, record.face_cells_predicted = fit.cells_seen, fit.cells_predicted
    state.count("face_cells_seen", fit.cells_seen)
    state.count("face_cells_predicted", fit.cells_predicted)
    if math.isfinite(tan):
        state.stack, moved, _raised = slump.slump(state.stack, tan, region)
        record.slumped_m3 = moved.volume_m3
        state.count("slumps")
    _predict_unseen(state, face)


def _predict_unseen(state: ProjectorState, face: OpenFace) -> None:
    """The height map takes the stack's top (as good as one point) on the face's cells
    not seen since its cut: they keep the fitted prediction."""
    grid = state.height.grid
    region = face.region
    elevation = grid["elevation"][region]
    new_top = state.stack.surface()[region]
    with np.errstate(invalid="ignore"):
        unseen = face.cells & ~(grid["last_update_ns"][region] > face.end_ns) & np.isfinite(
            elevation) & (np.abs(elevation - new_top) > 1e-9)
    if not unseen.any():
        return
    elevation[unseen] = new_top[unseen]
    grid["variance"][region][unseen] = state.point_sd_m ** 2
    for name in ("pending_z", "pending_var", "pending_x_offset_m", "pending_y_offset_m",
                 "pending_since_ns"):
        grid[name][region][unseen] = np.nan
    grid["pending_count"][region][unseen] = 0.0


def slide_seen_failure(state: ProjectorState, far: np.ndarray, elevation: np.ndarray,
                       t_ns: int) -> float:
    """A drop the scans see away from the latest cut (``far``, bool (nx, ny); the seen
    heights ``elevation``, m) that a face failing to repose explains: the stack's faces
    around it slide to the angle of repose (in place, mass and composition conserved) at
    ``t_ns`` (UTC ns, recorded in ``state.delayed_failures``); returns the volume moved
    (m3; 0: not a failure, nothing changed).  The flagged material the toe was seen to
    gain there before (:func:`_strip_flagged`) is that slide's, and goes first.

    A failure needs at least :data:`MIN_FAILURE_CELLS` cells dropping by more than four
    margins on average, and the slide must lower those cells by at least half its volume.
    """
    if int(far.sum()) < MIN_FAILURE_CELLS:
        return 0.0
    top = state.stack.surface()
    with np.errstate(invalid="ignore"):
        drop = np.where(far, top - np.maximum(elevation, state.stack.ground()), 0.0)
    drop = np.clip(np.nan_to_num(drop, nan=0.0), 0.0, None)
    if drop.sum() < 4.0 * state.margin_m * far.sum():
        return 0.0
    tan_rep = tan_repose(state, estimate=False) * (1.0 + state.config.relax_slack)
    geometry = state.pile.geometry
    region = slide_region(state, far, tan_rep)
    stack, stripped_m3 = _strip_flagged(state.stack, region)
    stack, moved, _raised = slump.slump(stack, tan_rep, region)
    lowered = np.clip(top - stack.surface(), 0.0, None)
    explained_m3 = float(np.sum(np.minimum(lowered, drop)[far])) * geometry.cell_area_m2
    if moved.volume_m3 <= 0 or explained_m3 < 0.5 * moved.volume_m3:
        state.count("failures_unexplained")
        return 0.0
    state.stack = stack
    state.delayed_failures.append((int(t_ns), moved.volume_m3))
    state.count("delayed_failures")
    state.count("failure_flagged_mm3", int(round(stripped_m3 * 1e3)))
    return moved.volume_m3


def _strip_flagged(stack, region: tuple[slice, slice]):
    """The stack without the top deposit's material in ``region`` when that deposit is a
    flagged one (the rises seen outside a pass after the cuts: a failing face's toe, seen
    rising before its crest is seen to fall, is that face's material), and the volume
    taken off (m3)."""
    n = stack.n_deposits
    if n < 2 or not stack.deposits[-1].flagged:
        return stack, 0.0
    floor = np.full(stack.geometry.shape, np.inf)
    floor[region] = stack.surface_k(n - 1)[region]
    stripped, removal = stack.clamp(floor)
    return stripped, removal.volume_m3


def material_estimate(state: ProjectorState) -> dict:
    """The pile's material as its scans show it: ``stand_angle_deg`` (the median angle
    the cut faces were fitted to, deg; None before any fit), ``repose_deg`` (the angle of
    repose in use), ``cuts_fitted``, ``cuts_stood`` (faces fitted :data:`STOOD_DEG` or
    more steeper than repose), ``delayed_failures`` (later failures seen) and the face
    cells seen and predicted since the cuts.  For the pile summary's JSON."""
    repose_deg = (math.degrees(math.atan(tan_repose(state, estimate=False)))
                  if state.pile is not None else math.nan)
    angles = [a for _cut, a, _n in state.slide_fits]
    return {"stand_angle_deg": float(np.median(angles)) if angles else None,
            "repose_deg": repose_deg if math.isfinite(repose_deg) else None,
            "cuts_fitted": len(angles),
            "cuts_stood": sum(a >= repose_deg + STOOD_DEG for a in angles),
            "delayed_failures": len(state.delayed_failures),
            "face_cells_seen": state.counters.get("face_cells_seen", 0),
            "face_cells_predicted": state.counters.get("face_cells_predicted", 0)}
