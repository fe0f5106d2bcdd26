"""Drive the simulator's true pile with planned cuts, and check them in its own geometry.

The reclaim planner (:mod:`planner`) predicts each cut's tonnes and grade and
claims its landings are collision-free.  This module is the simulator's side of that
comparison, written with the simulator's own model only (:mod:`sim.world`,
:mod:`sim.kinematics`), never the planner's or the projector's code:

- :func:`collisions` checks one cut against the true surface: material inside the wheel
  body's torus (the envelope of :func:`sim.kinematics.envelope_floor_z` with the
  wheel radius Rk for Rv), the boom segment (pivot -> wheel centre, forward kinematics of
  :func:`sim.kinematics.wheel_centre`) under the true surface outside the wheel's
  cutting ellipse, and the true bank above the bench floor against the machine's maximum
  cutting height H;
- :func:`drive_bench` performs planned cuts on a :class:`~sim.world.World` as
  the runner does (the arc in ``CUT_SUBSWEEPS`` steps, the walls slumping after the last)
  and returns what each cut really removed: tonnes and grade from the parcels;
- :func:`truth_stack` turns the true parcels into a
  :class:`projector.layers.LayerStack` on the simulator's grid, so the planner can
  also be run on the true pile (to separate planner error from projector error);
- :func:`stacked_world` runs a scenario's stacking only (sensors at a trickle), for tests
  and benches that need a true pile fast.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from projector.grades import AssayRecord
from projector.grid import GridGeometry
from projector.layers import DepositInfo, LayerStack
from sim.kinematics import Machine, boom_radius_m, envelope_floor_z, wheel_centre
from sim.runner import CUT_SUBSWEEPS, Simulation
from sim.scenario import Scenario
from sim.world import World

__all__ = ["CollisionReport", "DrivenCut", "collisions", "drive_bench", "truth_stack",
           "stacked_world", "lab_assays"]


@dataclass(frozen=True)
class CollisionReport:
    """What the true pile says about one cut before it is made.

    Attributes
    ----------
    wheel_cells : int
        World columns with material inside the wheel body's torus over the slewed arc.
    wheel_intrusion_m : float
        Deepest material above that torus' floor (m); 0 when none.
    boom_points : int
        Boom sample points under the true surface.
    boom_intrusion_m : float
        Deepest (m); 0 when none.
    bank_m : float
        Highest true bank above ``max(c_z - Rv, ground)`` over the columns the cut removes
        material from (m).
    max_bank_m : float
        The machine's H (m).
    """

    wheel_cells: int
    wheel_intrusion_m: float
    boom_points: int
    boom_intrusion_m: float
    bank_m: float
    max_bank_m: float

    @property
    def collided(self) -> bool:
        """Wheel body or boom in the pile, or a bank above H."""
        return bool(self.wheel_cells or self.boom_points or self.bank_m > self.max_bank_m + 1e-9)


@dataclass(frozen=True)
class DrivenCut:
    """One planned cut as the simulator really made it.

    Attributes
    ----------
    travel_m, luff_rad, slew_start_rad, slew_end_rad : float
        The joints it was driven with.
    tonnes : float
        True tonnes removed (t).
    volume_m3 : float
    grade : dict
        Analyte -> mass %, tonnage-weighted over the removed parcels (belt grade).
    slump_m3 : float
        Volume that slumped after the cut (not in its tonnes).
    collision : CollisionReport
        The check made on the true pile just before the cut.
    """

    travel_m: float
    luff_rad: float
    slew_start_rad: float
    slew_end_rad: float
    tonnes: float
    volume_m3: float
    grade: dict
    slump_m3: float
    collision: CollisionReport


def _lookup(world: World, x, y) -> tuple[np.ndarray, np.ndarray]:
    """True surface and whether material lies there, at points (ground off the grid)."""
    grid = world.grid
    iy, ix = grid.index_of(x, y)
    on = (iy >= 0) & (iy < grid.ny) & (ix >= 0) & (ix < grid.nx)
    surface = np.full(np.shape(x), grid.ground_z_m, dtype=np.float64)
    thick = np.zeros(np.shape(x))
    surf = world.surface_z()
    thk = world.thickness()
    surface[on] = surf[iy[on], ix[on]]
    thick[on] = thk[iy[on], ix[on]]
    return surface, thick


def collisions(world: World, machine: Machine, travel_m: float, luff_rad: float,
               slew_start_rad: float, slew_end_rad: float, *,
               slew_step_rad: float = math.radians(0.25),
               min_material_m: float = 1e-6) -> CollisionReport:
    """Check one cut against the true pile, in the simulator's geometry (module docstring).

    Parameters
    ----------
    world : World
        The true pile before the cut.
    machine : Machine
        The simulator's machine (Rk = ``wheel_radius_m``).
    travel_m, luff_rad, slew_start_rad, slew_end_rad : float
        The cut's joints (m, rad).
    slew_step_rad : float
        Boom positions are checked at least this densely along the arc (rad).
    min_material_m : float
        Thinner columns count as bare ground (m).

    Returns
    -------
    CollisionReport
    """
    grid = world.grid
    x, y = grid.centres()
    surf = world.surface_z()
    thk = world.thickness()
    material = thk > min_material_m
    ground = grid.ground_z_m
    c_z = machine.rail_z_m + machine.pivot_height_m + machine.l5_m * math.sin(luff_rad)
    # wheel body: the envelope with Rk for Rv
    body = replace(machine, cutting_radius_m=machine.wheel_radius_m)
    w_floor = envelope_floor_z(body, x, y, travel_m, luff_rad, slew_start_rad, slew_end_rad)
    with np.errstate(invalid="ignore"):
        intrusion = np.where(np.isfinite(w_floor) & material,
                             surf - np.maximum(w_floor, ground), -np.inf)
    wheel = intrusion > 0
    # bank over the columns the true envelope takes material from
    floor = envelope_floor_z(machine, x, y, travel_m, luff_rad, slew_start_rad, slew_end_rad)
    with np.errstate(invalid="ignore"):
        taken = np.isfinite(floor) & material & (surf > floor)
    bank = float(np.max(surf[taken] - max(c_z - machine.cutting_radius_m, ground))) \
        if taken.any() else 0.0
    # boom: pivot -> wheel centre at every slew step, outside the cutting ellipse
    lo, hi = sorted((float(slew_start_rad), float(slew_end_rad)))
    n = max(2, int(math.ceil((hi - lo) / slew_step_rad)) + 1)
    theta = np.linspace(lo, hi, n)
    centre = wheel_centre(machine, travel_m, theta, luff_rad)            # (n, 3)
    pivot = np.stack([machine.rail_x_m + machine.l4_m * np.sin(theta),
                      travel_m + machine.l4_m * np.cos(theta),
                      np.full(n, machine.rail_z_m + machine.pivot_height_m)], axis=1)
    steps = max(2, int(math.ceil(machine.l5_m / (0.5 * grid.cell_m))) + 1)
    w = np.linspace(0.0, 1.0, steps)
    pts = pivot[:, None, :] + w[None, :, None] * (centre - pivot)[:, None, :]  # (n, steps, 3)
    rho = float(boom_radius_m(machine, luff_rad))
    r = np.hypot(pts[..., 0] - machine.rail_x_m, pts[..., 1] - travel_m)
    half = machine.cutting_radius_m * math.cos(machine.wheel_tilt_rad)
    in_ellipse = ((r - rho) / half) ** 2 + ((pts[..., 2] - c_z) / machine.cutting_radius_m) ** 2 < 1
    s_pts, t_pts = _lookup(world, pts[..., 0], pts[..., 1])
    under = (~in_ellipse) & (t_pts > min_material_m) & (s_pts > pts[..., 2])
    boom_in = float(np.max((s_pts - pts[..., 2])[under])) if under.any() else 0.0
    return CollisionReport(int(wheel.sum()), float(intrusion[wheel].max()) if wheel.any() else 0.0,
                           int(under.sum()), boom_in, bank, machine.max_cutting_height_m)


def drive_bench(world: World, machine: Machine, cuts, t0_ns: int, *,
                cut_duration_ns: int = 120_000_000_000) -> list[DrivenCut]:
    """Make planned cuts on the true pile, in order, as the simulator's runner does.

    Parameters
    ----------
    world : World
        Modified in place (copy it first to keep it).
    machine : Machine
    cuts : iterable
        Objects with ``travel_m``, ``luff_rad``, ``slew_start_rad``, ``slew_end_rad``
        (e.g. :class:`planner.plan.PlannedCut`).
    t0_ns : int
        Site time of the first cut (UTC ns); each cut lasts ``cut_duration_ns``.

    Returns
    -------
    list of DrivenCut
    """
    out = []
    t = int(t0_ns)
    for c in cuts:
        travel, luff = float(c.travel_m), float(c.luff_rad)
        a0, a1 = float(c.slew_start_rad), float(c.slew_end_rad)
        report = collisions(world, machine, travel, luff, a0, a1)
        tonnes, volume, slump = 0.0, 0.0, 0.0
        mass = dict.fromkeys(world.analytes, 0.0)
        parts = []
        for k in range(CUT_SUBSWEEPS):
            a = a0 + (a1 - a0) * k / CUT_SUBSWEEPS
            b = a0 + (a1 - a0) * (k + 1) / CUT_SUBSWEEPS
            t_k = t + cut_duration_ns * (k + 1) // CUT_SUBSWEEPS
            part = world.reclaim_cut(machine, travel, luff, a, b, int(t_k), relax=False)
            parts.append(part)
            tonnes += part.tonnes
            volume += part.volume_m3
            if part.tonnes > 0:
                for name in world.analytes:
                    mass[name] += part.tonnes * part.grade[name]
        world.settle_cut(parts)   # the walls of the whole cut slump once the wheel has passed
        slump = sum(p.slump_m3 for p in parts)
        grade = {name: (mass[name] / tonnes if tonnes > 0 else math.nan) for name in world.analytes}
        out.append(DrivenCut(travel, luff, a0, a1, tonnes, volume, grade, slump, report))
        t += cut_duration_ns
    return out


def truth_stack(world: World, refine: int = 1):
    """The true pile as a projector :class:`~projector.layers.LayerStack`.

    One deposit per world slot (bottom to top) with its lot and per-cell deposition times,
    on the world's grid (arrays transposed to ``(nx, ny)``), or on a grid ``refine`` times
    finer (each world cell split into ``refine`` x ``refine`` cells of the same heights).

    Returns
    -------
    stack : LayerStack
    """
    if isinstance(refine, bool) or int(refine) < 1:
        raise ValueError(f"refine must be an integer >= 1, got {refine!r}")
    f = int(refine)
    g = world.grid

    def fine(a: np.ndarray) -> np.ndarray:  # (ny, nx) -> (nx * f, ny * f)
        return np.repeat(np.repeat(a.T, f, axis=0), f, axis=1)

    geometry = GridGeometry(g.origin_x_m, g.origin_y_m, g.cell_m / f, g.nx * f, g.ny * f)
    parcels = world.parcels()
    stack = LayerStack.empty(geometry, g.ground_z_m)
    tops = world.layer_surfaces()  # (S, ny, nx)
    for s in range(world.n_slots):
        thick = fine(parcels["thickness"][s])
        times = np.where(thick > 0, fine(parcels["time_ns"][s]), np.nan)
        opened = int(np.nanmin(times)) if np.isfinite(times).any() else 0
        stack = stack.open_deposit(DepositInfo(s + 1, str(parcels["deposit_id"][s]),
                                               str(parcels["lot"][s]), opened))
        stack, _raised = stack.raise_deposit(s + 1, fine(tops[s]), times)
    return stack


def stacked_world(scenario: Scenario, seed: int, out_dir: Path | str) -> Simulation:
    """Run a scenario's stacking and laboratory only: no reclaim, sensors at a trickle.

    Returns the finished :class:`Simulation` (``.world`` is the true pile,
    ``.lab_results`` every assay, ``.machine`` the reclaimer).
    """
    quiet = replace(scenario, cuts_per_bench=(), scan_hz=0.001, gnss_hz=0.001,
                    encoder_hz=0.001, clock_period_s=600.0)
    sim = Simulation(quiet, seed, Path(out_dir))
    sim.run()
    return sim


def lab_assays(sim: Simulation):
    """The simulator's lab results as the projector's assay records, all known.

    Returns
    -------
    lots : dict
        Lot id -> planned grade (mass %).
    assays : list of AssayRecord
    """
    lots = {lot.lot_id: dict(lot.planned_grade()) for lot in sim.scenario.lots}
    assays = [AssayRecord(r.assay_id, r.lot_id, int(r.window_start_ns), int(r.window_end_ns),
                          dict(r.analytes_pct), float(r.bulk_density_t_m3), r.status,
                          r.supersedes or "", int(r.reported_ns),
                          dict(r.repeatability_pct)) for r in sim.lab_results]
    return lots, assays
