"""Where the simulated reclaimer goes: joint motions, patrol and cut poses, the scanner's pose.

The runner moves the bucket-wheel reclaimer (which carries the scanner and the GNSS
antenna) along straight joint-space :class:`Motion` segments: patrolling above the pile's
centre line while the stacker works (:func:`patrol_pose`), and cutting benches it plans
online from the true surface (:func:`bench_luff`, :func:`slew_range`). Poses come from the
simulator's own forward kinematics (:mod:`sim.kinematics`), kept independent of the
localizer's and the projector's on purpose: they are the truth those are measured against.
Joints are (travel m, slew rad from +y toward +x, luff rad); site frame ENU metres.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from sim.grid import Grid
from sim.kinematics import FULL_SCALE, Machine, boom_radius_m, envelope_floor_z, wheel_centre
from schemas.times import NS_PER_S
from sim.scenario import Scenario
from sim.timetable import CHUNK_S, PATROL_LAG_S
from sim.world import World

#: Rotation of the scanner frame in the wheel frame: looking straight down, scan plane
#: containing the boom (scanner x = down, y = along the boom, z = x cross y).
SCANNER_IN_WHEEL = np.array([[0.0, 1.0, 0.0],
                             [0.0, 0.0, -1.0],
                             [-1.0, 0.0, 0.0]])

MOVE_SPEED_M_S = 0.5     # travel speed between cuts and while patrolling (full-scale machine)
SLEW_STEP_RAD = math.radians(0.5)  # cut slew ranges are whole steps of this


def wheel_rotation(slew_rad: float) -> np.ndarray:
    """Rotation of the wheel frame in the site frame: x along the boom (horizontal), z up."""
    c, s = math.sin(slew_rad), math.cos(slew_rad)  # boom direction (sin slew, cos slew, 0)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@dataclass
class Motion:
    """Linear joint motion between two times (travel m, slew rad, luff rad)."""

    t0_ns: int
    t1_ns: int
    start: tuple[float, float, float]
    end: tuple[float, float, float]

    def at(self, t_ns: int) -> tuple[float, float, float]:
        if self.t1_ns <= self.t0_ns:
            return self.end
        w = min(max((t_ns - self.t0_ns) / (self.t1_ns - self.t0_ns), 0.0), 1.0)
        return tuple(a + (b - a) * w for a, b in zip(self.start, self.end))  # type: ignore[return-value]


def move_speed_m_s(machine: Machine) -> float:
    """Travel speed between cuts and on the patrol's run-on (m/s): MOVE_SPEED_M_S for
    the full-scale machine, scaled down with the boom for a smaller one (a laboratory
    model crossing its 1.2 m pile in 2 s would scan its end slope once)."""
    return MOVE_SPEED_M_S * min(1.0, machine.l5_m / FULL_SCALE.l5_m)


def expected_crest_m(sc: Scenario) -> float:
    """The crest height (m, site z) of the scenario's pile once stacked: a ridge of its
    volume at the angle of repose, no higher than the pile's width allows."""
    volume = sc.lot_count * sc.passes_per_lot * sc.tonnes_per_pass / sc.bulk_density_t_m3
    tan = math.tan(math.radians(sc.repose_deg))
    h = math.sqrt(volume / sc.pile_length_m * tan)
    return sc.ground_z_m + min(h, sc.pile_width_m / 2 * tan)


def patrol_pose(sc: Scenario, machine: Machine, travel_m: float) -> tuple[float, float, float]:
    """Joints that hold the wheel above the pile's centre line at ``travel_m`` along the
    rail, clear of the crest."""
    m = machine
    clearance = max(0.5 * expected_crest_m(sc), 3 * m.cutting_radius_m)
    z = expected_crest_m(sc) + clearance
    sin_luff = (z - m.rail_z_m - m.pivot_height_m) / m.l5_m
    luff = math.asin(min(max(sin_luff, -0.95), 0.95))
    rho = float(boom_radius_m(m, luff))
    x_c = sc.pile_origin_x_m + sc.pile_width_m / 2
    slew = math.asin(min(max((x_c - m.rail_x_m) / rho, -1.0), 1.0))
    return (travel_m - rho * math.cos(slew), slew, luff)


def patrol_legs(sc: Scenario, move_m_s: float, p: dict) -> tuple[int, int, float, float]:
    """The reclaimer's patrol with the scanner during the pass ``p``
    (:func:`sim.timetable.stacking_plan`).

    It trails the stacker by up to PATROL_LAG_S so that it sees every stretch after the
    pass laid its layer there (a scanner that met the stacker half way would see half the
    pile before each pass and could not tell two passes' layers apart there): it waits at
    the end the pass starts from, follows the stacker to the pass's last position, then
    runs on over the far end's slope (at ``move_m_s``), done before the next pass starts
    pouring. Returns the lag behind the stacker and the run-on's duration (ns), and the
    start end and far end of the pile (m along y).
    """
    forward = p["y1"] >= p["y0"]
    y_lo, y_hi = sc.pile_origin_y_m, sc.pile_origin_y_m + sc.pile_length_m
    start_end, far_end = (y_lo, y_hi) if forward else (y_hi, y_lo)
    # the run over the far end's slope ends before the next pass starts pouring
    run_on_s = abs(far_end - p["y1"]) / move_m_s
    lag_s = max(min(PATROL_LAG_S, sc.pass_gap_s - run_on_s - 10.0), CHUNK_S + 5.0)
    lag, run_on = int(lag_s * NS_PER_S), int(run_on_s * NS_PER_S)
    return lag, run_on, start_end, far_end


def scanner_pose(machine: Machine, scanner_offset_m, joints) -> tuple[np.ndarray, np.ndarray]:
    """The scanner's position (3,) m and rotation (3, 3) (scanner frame -> site frame) at
    ``joints``; ``scanner_offset_m`` (3,) is its mount in the wheel frame."""
    centre = wheel_centre(machine, *joints)
    r_wheel = wheel_rotation(joints[1])
    position = centre + r_wheel @ np.asarray(scanner_offset_m)
    return position, r_wheel @ SCANNER_IN_WHEEL


def bench_luff(sc: Scenario, machine: Machine, world: World, bench: int) -> float:
    """Luff (rad) that puts the wheel centre at bench ``bench``'s height: the scenario's
    bench height, or below the true crest by the scenario's steps; never so low that the
    wheel cuts the ground."""
    m = machine
    crest = float(np.max(world.surface_z()))
    z = crest - sc.first_bench_below_crest_m - bench * sc.bench_step_m
    if sc.bench_heights_m is not None:
        z = sc.ground_z_m + sc.bench_heights_m[bench]
    z = max(z, sc.ground_z_m + m.cutting_radius_m * 0.98)
    return math.asin((z - m.rail_z_m - m.pivot_height_m) / m.l5_m)


def slew_range(machine: Machine, grid: Grid, world: World, travel: float,
               luff: float) -> tuple[float, float] | None:
    """Slew angles (rad, whole SLEW_STEP_RAD steps) where the envelope meets material at
    this travel (m) and luff (rad); None where it meets none."""
    m, g = machine, grid
    x, y = np.meshgrid(g.x_centres, g.y_centres)
    floor = envelope_floor_z(m, x, y, travel, luff, 0.0, math.pi)
    surface = world.surface_z()
    material = world.thickness() > 0.01 * m.cutting_radius_m  # not bare ground
    hit = material & np.isfinite(floor) & (surface > floor + 0.01 * m.cutting_radius_m)
    if not hit.any():
        return None
    theta = np.arctan2(x[hit] - m.rail_x_m, y[hit] - travel)
    lo = math.floor(theta.min() / SLEW_STEP_RAD) * SLEW_STEP_RAD
    hi = math.ceil(theta.max() / SLEW_STEP_RAD) * SLEW_STEP_RAD
    return lo, hi


def landing_travel(sc: Scenario, machine: Machine, grid: Grid, world: World,
                   luff: float) -> float:
    """Travel (m) of a bench's first cut: approach from the low-y end, a cut depth at a
    time, until the wheel meets a face at least ``landing_min_slew_deg`` wide, then land
    half a cutting radius into the bank (not on its toe)."""
    m = machine
    rho = float(boom_radius_m(m, luff))
    travel = sc.pile_origin_y_m - rho - m.cutting_radius_m
    limit = sc.pile_origin_y_m + sc.pile_length_m
    min_face = math.radians(sc.landing_min_slew_deg)
    while travel < limit:
        slews = slew_range(m, grid, world, travel, luff)
        if slews is not None and slews[1] - slews[0] >= min_face:
            break
        travel += m.cut_depth_m
    travel += 0.5 * m.cutting_radius_m  # land into the bank, not on its toe
    return travel
