"""Plan a reclaim bench on a layer stack: choose the landing, then cut the bench on a copy.

:func:`plan_reclaim` is the whole planner on one pile state:

1. candidate landings (:mod:`planner.landing`);
2. stage 1, every candidate: its first cut (:func:`planner.bench.cut_step`) must
   meet the pile, stay inside the grid, keep the wheel body and boom clear and face a
   bank no higher than H (the collision model of :mod:`planner.bench`).  Its
   *cutting depth* is the bank that first cut faces, ``surface - max(c_z - Rv, ground)``
   over the columns it hits (m, at most H);
3. stage 2, in decreasing cutting depth: the whole bench is cut on a copy of the height
   map, every cut checked the same way.  The first landing whose bench passes is chosen:
   the largest cutting depth among the valid landings (thesis §5.3.4).  With
   ``exhaustive`` every stage-1 survivor is checked, so ``valid`` counts them all;
4. the chosen bench is cut on the layer stack with the projector's own removal code,
   :func:`projector.envelope.cut_floor` then
   :meth:`projector.layers.LayerStack.clamp`, which gives each cut's removal per
   deposit (volumes and deposition times) for the grade join
   (:mod:`planner.grades`).  The stack is immutable: the caller's is untouched.

All lengths are metres, angles radians.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from projector.envelope import cut_floor
from projector.kinematics import PlannerMachine, wheel_centre
from projector.layers import LayerStack, Removal
from planner.bench import (CellSet, CutGeometry, PlanParams, cell_set, cut_step,
                           simulate_bench, slew_motion)
from planner.landing import Candidates, landing_candidates
from planner.settle import settle_stack

__all__ = ["Landing", "LandingSearch", "PlannedCut", "BenchPlan", "LandingTable",
           "plan_reclaim", "plan_bench_from", "evaluate_landings", "landing_from_joints"]


@dataclass(frozen=True)
class Landing:
    """The chosen landing.

    Attributes
    ----------
    point_m, normal, centre_m : tuple of float
        Landing point on the surface (m), unit surface normal, wheel centre (m).
    travel_m, slew_rad, luff_rad : float
        Joints at the landing (m, rad, rad).
    direction : int
        The bench advances along +y (1) or -y (-1).
    cutting_depth_m : float
        Bank height the first cut faces (m).
    bench_floor_m : float
        Lowest point of the envelope, ``c_z - Rv`` (m).
    """

    point_m: tuple[float, float, float]
    normal: tuple[float, float, float]
    centre_m: tuple[float, float, float]
    travel_m: float
    slew_rad: float
    luff_rad: float
    direction: int
    cutting_depth_m: float
    bench_floor_m: float


@dataclass(frozen=True)
class LandingSearch:
    """How the landing was found.

    Attributes
    ----------
    spacing_m : float
        Candidate grid spacing (m).
    in_region : int
        Grid points in the effective cutting region, facing the rail.
    tried : int
        Candidates with a joint solution, each checked at its first cut.
    landing_valid : int
        Candidates whose first cut passed (stage 1).
    bench_checked : int
        Stage-1 survivors whose whole bench was cut (stage 2).
    valid : int
        Of those, the ones whose every cut passed.
    exhaustive : bool
        Whether stage 2 checked every stage-1 survivor.
    rejected : dict
        Reason -> number of candidates (``"no material"``, ``"wheel"``, ``"boom"``,
        ``"bank"``, ``"edge"``; a candidate may count under several); stage 2 rejections
        are prefixed ``"bench "``.
    """

    spacing_m: float
    in_region: int
    tried: int
    landing_valid: int
    bench_checked: int
    valid: int
    exhaustive: bool
    rejected: dict[str, int] = field(default_factory=dict)


@dataclass(frozen=True, eq=False)
class PlannedCut:
    """One cut of the planned bench.

    Attributes
    ----------
    index : int
        0-based position in the bench.
    travel_m, luff_rad : float
    slew_start_rad, slew_end_rad : float
        The slew in the order the boom moves (rad).
    geometry : CutGeometry
        The height-map cut with its collision checks.
    removal : Removal
        What :meth:`LayerStack.clamp` removed, per deposit.
    """

    index: int
    travel_m: float
    luff_rad: float
    slew_start_rad: float
    slew_end_rad: float
    geometry: CutGeometry
    removal: Removal

    @property
    def volume_m3(self) -> float:
        """Volume removed from the layer stack (m3)."""
        return self.removal.volume_m3


@dataclass(frozen=True, eq=False)
class BenchPlan:
    """A planned bench (module docstring).

    Attributes
    ----------
    landing : Landing or None
        None when no landing is valid.
    search : LandingSearch
    cuts : list of PlannedCut
    stack_after : LayerStack
        The layer stack after the planned cuts (the input stack when nothing is cut).
    model_mismatch_m : float
        Largest difference between the height map the cuts were planned on and the top of
        ``stack_after`` (m); rounding only.
    params : PlanParams
        The resolved parameters.
    """

    landing: Landing | None
    search: LandingSearch
    cuts: list[PlannedCut]
    stack_after: LayerStack
    model_mismatch_m: float
    params: PlanParams


@dataclass(frozen=True)
class _Stage1:
    cuts: list[CutGeometry]
    ok: np.ndarray
    depth_m: np.ndarray


def _stage1(surface: np.ndarray, cells: CellSet, machine: PlannerMachine, cands: Candidates,
            params: PlanParams) -> _Stage1:
    cuts = [cut_step(surface, cells, machine, float(cands.travel_m[i]), float(cands.luff_rad[i]),
                     float(cands.slew_rad[i]), params, apply=False) for i in range(len(cands))]
    ok = np.array([c.ok for c in cuts], bool)
    depth = np.array([c.bank_m if not c.empty else -math.inf for c in cuts])
    return _Stage1(cuts, ok, depth)


@dataclass(frozen=True, eq=False)
class LandingTable:
    """Every candidate landing with its verdicts (:func:`evaluate_landings`).

    Attributes
    ----------
    candidates : Candidates
    first_cuts : list of CutGeometry
        Each candidate's first cut (stage 1).
    landing_ok : ndarray of bool, shape (N,)
        Stage 1 passed.
    checked : ndarray of bool, shape (N,)
        The whole bench was cut (stage 2).
    valid : ndarray of bool, shape (N,)
        Checked and every cut passed.
    benches : list
        Per candidate: its bench's cuts (stopped at the first failing one), or [] when
        not checked.
    params : PlanParams
        Resolved.
    machine : PlannerMachine
    """

    candidates: Candidates
    first_cuts: list[CutGeometry]
    landing_ok: np.ndarray
    checked: np.ndarray
    valid: np.ndarray
    benches: list
    params: PlanParams
    machine: PlannerMachine

    def landing(self, i: int) -> "Landing":
        """Candidate ``i`` as a :class:`Landing`."""
        return _landing(self.candidates, int(i), float(self.first_cuts[i].bank_m), self.machine)


def _landing(cands: Candidates, i: int, depth_m: float, machine: PlannerMachine) -> "Landing":
    c = cands
    return Landing(tuple(map(float, c.point_m[i])), tuple(map(float, c.normal[i])),
                   tuple(map(float, c.centre_m[i])), float(c.travel_m[i]), float(c.slew_rad[i]),
                   float(c.luff_rad[i]), int(c.direction[i]), float(depth_m),
                   float(c.centre_m[i][2]) - machine.cutting_radius_m)


def evaluate_landings(stack: LayerStack, machine: PlannerMachine, *, n_cuts: int = 10,
                      bench_floor_m: float | None = None, params: PlanParams | None = None,
                      sample: int | None = None) -> LandingTable:
    """Every candidate landing's stage-1 verdict, and the whole bench of some or all.

    Parameters
    ----------
    stack : LayerStack
    machine : PlannerMachine
    n_cuts : int
    bench_floor_m : float, optional
    params : PlanParams, optional
    sample : int, optional
        Cut the whole bench of only this many stage-1 survivors, evenly spaced in
        candidate order (None: all of them).

    Returns
    -------
    LandingTable
    """
    surface, params, cells, cands, s1 = _screened_candidates(stack, machine, params,
                                                             bench_floor_m)
    survivors = np.flatnonzero(s1.ok)
    if sample is not None and len(survivors) > sample:
        pick = np.unique(np.round(np.linspace(0, len(survivors) - 1, int(sample))).astype(int))
        survivors = survivors[pick]
    checked = np.zeros(len(cands), bool)
    valid = np.zeros(len(cands), bool)
    benches: list = [[] for _ in range(len(cands))]
    for i in survivors:
        cuts, _surfaces = _bench_run(surface, cells, machine, float(cands.travel_m[i]),
                                     float(cands.luff_rad[i]), float(cands.slew_rad[i]),
                                     int(cands.direction[i]), n_cuts, params)
        benches[i] = cuts
        checked[i] = True
        valid[i] = bool(cuts) and all(c.ok for c in cuts)
    return LandingTable(cands, s1.cuts, s1.ok, checked, valid, benches, params, machine)


def _screened_candidates(stack: LayerStack, machine: PlannerMachine,
                         params: PlanParams | None, bench_floor_m: float | None):
    """``(surface, params, cells, candidates, stage-1 result)`` of a pile's landings."""
    geometry = stack.geometry
    surface = np.array(stack.surface(), dtype=np.float64)
    params = (params or PlanParams()).resolved(machine, surface, geometry.cell_m)
    ground = np.asarray(stack.ground())
    cells = cell_set(geometry, surface, ground, 0.0)
    cands = landing_candidates(geometry, surface, ground, machine, spacing_m=params.spacing_m,
                               normal_window_m=params.normal_window_m,
                               min_bite_m=params.min_bite_m, bench_floor_m=bench_floor_m)
    return surface, params, cells, cands, _stage1(surface, cells, machine, cands, params)


def plan_reclaim(stack: LayerStack, machine: PlannerMachine, *, n_cuts: int = 10,
                 bench_floor_m: float | None = None, params: PlanParams | None = None,
                 exhaustive: bool = False) -> BenchPlan:
    """Choose a landing and plan the bench on a copy of the pile (module docstring).

    Parameters
    ----------
    stack : LayerStack
        The pile (e.g. ``project(...).state.stack``); not modified.
    machine : PlannerMachine
    n_cuts : int
        Cuts in the bench (>= 1).
    bench_floor_m : float, optional
        Bench floor Z (m, site frame): the wheel centre at ``Z + Rv``.  None: any height
        in the top H of the pile.
    params : PlanParams, optional
    exhaustive : bool
        Check every stage-1 survivor's bench (``search.valid`` then counts all).

    Returns
    -------
    BenchPlan
    """
    if not isinstance(stack, LayerStack):
        raise TypeError(f"stack must be a LayerStack, got {type(stack).__name__}")
    if not isinstance(machine, PlannerMachine):
        raise TypeError(f"machine must be a PlannerMachine, got {type(machine).__name__}")
    if isinstance(n_cuts, bool) or not isinstance(n_cuts, (int, np.integer)) or n_cuts < 1:
        raise ValueError(f"n_cuts must be an integer >= 1, got {n_cuts!r}")
    surface, params, cells, cands, s1 = _screened_candidates(stack, machine, params,
                                                             bench_floor_m)
    rejected: dict[str, int] = {}
    for c in s1.cuts:
        for reason in (("no material",) if c.empty else c.reasons):
            rejected[reason] = rejected.get(reason, 0) + 1
    survivors = np.flatnonzero(s1.ok)
    removed = np.array([s1.cuts[i].removed_m3 for i in survivors])
    order = survivors[np.lexsort((survivors, -removed, -s1.depth_m[survivors]))]
    chosen, checked, valid, record = None, 0, 0, None
    for i in order:
        cuts, surfaces = _bench_run(surface, cells, machine, float(cands.travel_m[i]),
                                    float(cands.luff_rad[i]), float(cands.slew_rad[i]),
                                    int(cands.direction[i]), n_cuts, params)
        checked += 1
        bad = [c for c in cuts if not c.ok]
        if bad:
            for reason in bad[0].reasons:
                key = f"bench {reason}"
                rejected[key] = rejected.get(key, 0) + 1
            continue
        valid += 1
        if chosen is None:
            chosen, record = int(i), (cuts, surfaces)
            if not exhaustive:
                break
    search = LandingSearch(params.spacing_m if len(cands) == 0 else cands.spacing_m,
                           cands.in_region, len(cands), int(s1.ok.sum()), checked, valid,
                           bool(exhaustive), dict(sorted(rejected.items())))
    if chosen is None:
        return BenchPlan(None, search, [], stack, 0.0, params)
    landing = _landing(cands, chosen, float(s1.depth_m[chosen]), machine)
    planned, after, mismatch = _mirror(stack, machine, landing, *record)
    return BenchPlan(landing, search, planned, after, mismatch, params)


def _bench_run(surface: np.ndarray, cells: CellSet, machine: PlannerMachine, travel_m: float,
               luff_rad: float, slew_rad: float, direction: int, n_cuts: int,
               params: PlanParams) -> tuple[list[CutGeometry], list[np.ndarray]]:
    """A bench on a copy of ``surface``: its cuts and the surface after each allowed one."""
    after: list[np.ndarray] = []
    cuts = simulate_bench(surface.copy(), cells, machine, travel_m, luff_rad, slew_rad,
                          direction, n_cuts, params,
                          on_cut=lambda _c, surf: after.append(surf.copy()))
    return cuts, after


def _mirror(stack: LayerStack, machine: PlannerMachine, landing: Landing,
            cuts: list[CutGeometry], surfaces: list[np.ndarray]):
    """The planned cuts on the layer stack, with the projector's removal code.

    Each cut clamps the stack to :func:`cut_floor`; where its faces slid the stack then
    settles to the planned surface (:func:`settle_stack`).
    """
    geometry = stack.geometry
    allowed = [c for c in cuts if c.ok]
    motion = slew_motion(allowed, landing.slew_rad)
    planned = []
    after = stack
    mismatch = 0.0
    for k, (c, surf, (start, end)) in enumerate(zip(allowed, surfaces, motion)):
        floor = cut_floor(geometry, machine.reclaimer, c.travel_m, c.luff_rad, c.slew_lo_rad,
                          c.slew_hi_rad)
        after, removal = after.clamp(floor)
        if c.slumped_m3 > 0:
            after, _moved = settle_stack(after, surf)
        mismatch = max(mismatch, float(np.max(np.abs(np.asarray(after.surface()) - surf))))
        planned.append(PlannedCut(k, c.travel_m, c.luff_rad, start, end, c, removal))
    return planned, after, mismatch


def plan_bench_from(stack: LayerStack, machine: PlannerMachine, landing: Landing, *,
                    n_cuts: int = 10, params: PlanParams | None = None) -> BenchPlan:
    """Cut the bench of a given landing on a copy of the pile (steps 3-4 of the module).

    The cuts are checked like every candidate's (stopping at the first that fails, which
    is then not cut); ``stack`` is not modified.
    """
    geometry = stack.geometry
    surface = np.array(stack.surface(), dtype=np.float64)
    params = (params or PlanParams()).resolved(machine, surface, geometry.cell_m)
    cells = cell_set(geometry, surface, stack.ground(), 0.0)
    cuts, surfaces = _bench_run(surface, cells, machine, landing.travel_m, landing.luff_rad,
                                landing.slew_rad, landing.direction, n_cuts, params)
    planned, after, mismatch = _mirror(stack, machine, landing, cuts, surfaces)
    search = LandingSearch(params.spacing_m, 0, 0, 0, 0, 0, False, {})
    return BenchPlan(landing, search, planned, after, mismatch, params)


def landing_from_joints(machine: PlannerMachine, stack: LayerStack, travel_m: float,
                        slew_rad: float, luff_rad: float, direction: int) -> Landing:
    """A :class:`Landing` for given joints (the wheel centre by forward kinematics)."""
    c = wheel_centre(machine.reclaimer, travel_m, slew_rad, luff_rad)
    return Landing((math.nan,) * 3, (math.nan,) * 3, tuple(map(float, c)), float(travel_m),
                   float(slew_rad), float(luff_rad), int(direction), math.nan,
                   float(c[2]) - machine.cutting_radius_m)
