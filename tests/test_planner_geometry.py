"""The reclaim planner's pure parts against independent references.

Every reference here is a different implementation: the simulator's kinematics and
envelope (:mod:`sim.kinematics`), closed-form planes and volumes, or brute force.
Random inputs print their seed.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from planner.bench import PlanParams, cell_set, cut_step, simulate_bench
from planner.grades import check_bounds, predict_cuts
from planner.landing import landing_candidates, surface_normals
from planner.settle import level_down, level_up, relax_region, settle_stack
from projector.envelope import cut_floor
from projector.grades import AssayRecord
from projector.grid import GridGeometry, cell_centres
from projector.kinematics import PlannerMachine, inverse_kinematics, pivot_position
from projector.layers import DepositInfo, LayerStack
from sim import kinematics as simk

SIM_MACHINE = replace(simk.FULL_SCALE, rail_x_m=-25.0)
MACHINE = PlannerMachine.from_message(SIM_MACHINE)


def _prism(geometry: GridGeometry, crest_x_m: float, crest_z_m: float, slope: float,
           y0_m: float, y1_m: float) -> np.ndarray:
    """A ridge along y with flanks of ``slope`` and ends of the same slope (m)."""
    x, y = cell_centres(geometry)
    across = crest_z_m - slope * np.abs(x - crest_x_m)
    along = crest_z_m - slope * np.maximum(np.maximum(y0_m - y, y - y1_m), 0.0)
    return np.clip(np.minimum(across, along), 0.0, None)


def test_inverse_kinematics_matches_the_simulators_forward_kinematics():
    seed = 20261101
    rng = np.random.default_rng(seed)
    print("seed", seed)
    n = 400
    travel = rng.uniform(-50, 250, n)
    slew = rng.uniform(-math.pi, math.pi, n)
    luff = rng.uniform(-0.5, 0.6, n)
    centres = simk.wheel_centre(SIM_MACHINE, travel, slew, luff)
    d1, th2, th3, ok = inverse_kinematics(MACHINE, centres)
    assert ok.all()
    np.testing.assert_allclose(th3, luff, atol=1e-12)
    for branch in (0, 1):
        back = simk.wheel_centre(SIM_MACHINE, d1[:, branch], th2[:, branch], th3)
        np.testing.assert_allclose(back, centres, atol=1e-9)
    # the drawn joints are one of the two branches
    same = np.isclose(d1, travel[:, None], atol=1e-9) & np.isclose(
        np.mod(th2 - slew[:, None] + math.pi, 2 * math.pi) - math.pi, 0.0, atol=1e-9)
    assert same.any(axis=1).all()
    # the pivot is one boom length from the wheel centre, at L2 + L3
    piv = pivot_position(MACHINE, d1[:, 0], th2[:, 0])
    np.testing.assert_allclose(np.linalg.norm(piv - centres, axis=1), SIM_MACHINE.l5_m,
                               atol=1e-9)


def test_inverse_kinematics_reports_unreachable_centres_and_checks_shapes():
    far = np.array([[500.0, 0.0, 10.0], [0.0, 0.0, 200.0]])
    d1, th2, th3, ok = inverse_kinematics(MACHINE, far)
    assert not ok.any() and np.isnan(d1).all() and np.isnan(th3).all()
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        inverse_kinematics(MACHINE, np.zeros((4, 2)))
    with pytest.raises(ValueError, match="finite"):
        inverse_kinematics(MACHINE, np.array([[np.nan, 0.0, 0.0]]))


def test_machine_constants_follow_domain_section_3():
    # H = (Rv + Rk sin phi) cos beta; the advance is 0.9 x bucket width
    assert MACHINE.max_cutting_height_m == pytest.approx(SIM_MACHINE.max_cutting_height_m,
                                                         abs=1e-12)
    assert MACHINE.cut_depth_m == pytest.approx(SIM_MACHINE.cut_depth_m, abs=1e-12)
    with pytest.raises(ValueError, match="wheel_radius_m"):
        PlannerMachine(MACHINE.reclaimer, 11.0, 0.2, 1.0)  # Rk > Rv


def test_normals_of_a_plane_and_of_a_prism_flank():
    geometry = GridGeometry(0.0, 0.0, 0.25, 120, 100)
    x, y = cell_centres(geometry)
    plane = 0.3 * x - 0.2 * y + 5.0
    n = surface_normals(geometry, plane, 2.0)
    expect = np.array([-0.3, 0.2, 1.0]) / math.sqrt(0.3 ** 2 + 0.2 ** 2 + 1)
    np.testing.assert_allclose(n[10:-10, 10:-10], np.broadcast_to(expect, n[10:-10, 10:-10].shape),
                               atol=1e-12)
    with pytest.raises(ValueError, match="shape"):
        surface_normals(geometry, plane[:, :-1], 2.0)


def test_candidates_face_the_rail_lie_in_the_effective_region_and_touch_the_surface():
    geometry = GridGeometry(10.0, 0.0, 0.25, 160, 240)
    slope = math.tan(math.radians(37.0))
    surface = _prism(geometry, 30.0, 10.0, slope, 8.0, 52.0)
    ground = np.zeros(geometry.shape)
    rv = MACHINE.cutting_radius_m
    cands = landing_candidates(geometry, surface, ground, MACHINE, spacing_m=1.0,
                               normal_window_m=2.0, min_bite_m=0.1)
    assert len(cands) > 20
    h = MACHINE.max_cutting_height_m
    assert np.all(cands.point_m[:, 2] >= surface.max() - h - 1e-9)
    # facing the rail (x_r = -25 < every point)
    assert np.all(cands.normal[:, 0] < 0)
    # the wheel centre is Rv along the normal, and inverse kinematics reproduce it
    np.testing.assert_allclose(cands.centre_m - cands.point_m, rv * cands.normal, atol=1e-9)
    back = simk.wheel_centre(SIM_MACHINE, cands.travel_m, cands.slew_rad, cands.luff_rad)
    np.testing.assert_allclose(back, cands.centre_m, atol=1e-9)
    # on the rail-side flank the normal is the flank's: (-sin a, 0, cos a)
    # (away from the crest and the toe by more than the 2 m fitting window)
    z = cands.point_m[:, 2]
    flank = (cands.point_m[:, 0] < 30.0) & (cands.point_m[:, 1] > 20) \
        & (cands.point_m[:, 1] < 40) & (z > 1.1 * slope) & (z < 10.0 - 1.1 * slope)
    assert flank.any()
    a = math.atan(slope)
    np.testing.assert_allclose(cands.normal[flank], np.broadcast_to(
        [-math.sin(a), 0.0, math.cos(a)], cands.normal[flank].shape), atol=1e-9)
    # with a bench floor Z the centre is at Z + Rv and the cutting circle passes the point
    z = 4.0
    fixed = landing_candidates(geometry, surface, ground, MACHINE, spacing_m=1.0,
                               normal_window_m=2.0, min_bite_m=0.1, bench_floor_m=z)
    assert len(fixed) > 0
    np.testing.assert_allclose(fixed.centre_m[:, 2], z + rv)
    np.testing.assert_allclose(np.linalg.norm(fixed.centre_m - fixed.point_m, axis=1), rv)
    assert np.all((fixed.point_m[:, 2] > z) & (fixed.point_m[:, 2] <= z + h))


def _ridge_setup():
    geometry = GridGeometry(10.0, -10.0, 0.25, 160, 320)
    slope = math.tan(math.radians(37.0))
    surface = _prism(geometry, 30.0, 9.0, slope, 5.0, 55.0)
    return geometry, surface, np.zeros(geometry.shape)


def test_slew_range_is_tight_in_the_simulators_envelope():
    """The planner's arc holds every column the simulator's envelope takes material from,
    and no narrower arc does."""
    geometry, surface, ground = _ridge_setup()
    params = PlanParams(slump=False, clearance_m=0.0).resolved(MACHINE, surface, geometry.cell_m)
    cells = cell_set(geometry, surface, ground, 0.0)
    x, y = cell_centres(geometry)
    seed = 7
    rng = np.random.default_rng(seed)
    print("seed", seed)
    checked = 0
    for _ in range(12):
        travel = float(rng.uniform(-45.0, 20.0))
        c_z = float(rng.uniform(2.0, 14.0))
        luff = math.asin((c_z - MACHINE.pivot_z_m) / SIM_MACHINE.l5_m)
        cut = cut_step(surface.copy(), cells, MACHINE, travel, luff, math.pi / 2, params,
                       apply=False)
        bite = params.min_bite_m

        def hits(lo, hi):
            f = simk.envelope_floor_z(SIM_MACHINE, x, y, travel, luff, lo, hi)
            with np.errstate(invalid="ignore"):
                return np.isfinite(f) & (surface > f + bite) & (surface > ground + bite)

        every = hits(0.0, math.pi)
        if cut.empty:
            assert not every.any()
            continue
        checked += 1
        assert cut.hit_cells == int(every.sum())
        assert (hits(cut.slew_lo_rad, cut.slew_hi_rad) == every).all()
        eps = 1e-7
        assert hits(cut.slew_lo_rad + eps, cut.slew_hi_rad).sum() < every.sum()
        assert hits(cut.slew_lo_rad, cut.slew_hi_rad - eps).sum() < every.sum()
    assert checked >= 5


def test_the_cut_lowers_the_surface_exactly_as_the_projectors_clamp():
    geometry, surface, ground = _ridge_setup()
    stack = LayerStack.empty(geometry, 0.0).open_deposit(DepositInfo(1, "P1", "LOT", 0))
    stack, _ = stack.raise_to(surface, 1)
    params = PlanParams(slump=False).resolved(MACHINE, surface, geometry.cell_m)
    cells = cell_set(geometry, surface, ground, 0.0)
    luff = math.asin((6.0 - MACHINE.pivot_z_m) / SIM_MACHINE.l5_m)
    work = surface.copy()
    cuts = simulate_bench(work, cells, MACHINE, -40.0, luff, 1.0, 1, 6, params,
                          stop_on_invalid=False)
    assert len(cuts) == 6 and sum(c.removed_m3 for c in cuts) > 100
    for c in cuts:
        stack, removal = stack.clamp(cut_floor(geometry, MACHINE.reclaimer, c.travel_m,
                                               c.luff_rad, c.slew_lo_rad, c.slew_hi_rad))
        assert removal.volume_m3 == pytest.approx(c.removed_m3, rel=1e-9, abs=1e-9)
    np.testing.assert_allclose(stack.surface(), work, atol=1e-9)


def test_wheel_body_check_agrees_with_the_simulators_torus():
    """With no clearance, the planner finds material inside the wheel body's torus exactly
    where the simulator's envelope with Rk for Rv has material above its floor."""
    geometry, surface, ground = _ridge_setup()
    params = PlanParams(slump=False, clearance_m=0.0).resolved(MACHINE, surface, geometry.cell_m)
    cells = cell_set(geometry, surface, ground, 0.0)
    body = replace(SIM_MACHINE, cutting_radius_m=SIM_MACHINE.wheel_radius_m)
    x, y = cell_centres(geometry)
    seen = set()
    for travel in np.linspace(-40.0, 10.0, 11):
        for c_z in (4.0, 8.0, 12.0):
            luff = math.asin((c_z - MACHINE.pivot_z_m) / SIM_MACHINE.l5_m)
            cut = cut_step(surface.copy(), cells, MACHINE, float(travel), luff, math.pi / 2,
                           params, apply=False)
            if cut.empty:
                continue
            f = simk.envelope_floor_z(body, x, y, float(travel), luff, cut.slew_lo_rad,
                                      cut.slew_hi_rad)
            with np.errstate(invalid="ignore"):
                inside = (np.isfinite(f) & (surface > np.maximum(f, 0.0))
                          & (surface > params.min_bite_m))
            assert cut.wheel_cells == int(inside.sum())
            seen.add(cut.wheel_cells > 0)
    assert seen == {True, False}


def test_boom_check_finds_a_bank_under_the_boom():
    geometry = GridGeometry(-20.0, -30.0, 0.25, 200, 240)
    ground = np.zeros(geometry.shape)
    x, y = cell_centres(geometry)
    # a wall 8 m high at x = 14..18 (14 m short of the wheel's ring), under a boom that
    # runs down from the pivot at 11 m to the wheel centre at 6 m; material for the wheel
    surface = np.where((x > 14) & (x < 18), 8.0, 0.0) + np.where(x > 20, 3.0, 0.0)
    params = PlanParams(slump=False, clearance_m=0.0).resolved(MACHINE, surface, geometry.cell_m)
    cells = cell_set(geometry, surface, ground, 0.0)
    luff = math.asin((6.0 - MACHINE.pivot_z_m) / SIM_MACHINE.l5_m)
    cut = cut_step(surface, cells, MACHINE, 0.0, luff, math.pi / 2, params, apply=False)
    assert not cut.empty and cut.boom_cells > 0 and "boom" in cut.reasons
    # brute force: the boom line z_p + (r - L4) tan(luff) over the wall's cells, at every
    # slew of the arc, up to where it enters the wheel's cutting ellipse
    hw = SIM_MACHINE.cutting_radius_m * math.cos(SIM_MACHINE.wheel_tilt_rad)
    rho = SIM_MACHINE.l4_m + SIM_MACHINE.l5_m * math.cos(luff)
    e = 1.0 / math.sqrt(1 / hw ** 2 + (math.tan(luff) / SIM_MACHINE.cutting_radius_m) ** 2)
    theta = np.linspace(cut.slew_lo_rad, cut.slew_hi_rad, 1500)[:, None]
    r = np.linspace(SIM_MACHINE.l4_m, rho - e, 3000)[None, :]
    bx = SIM_MACHINE.rail_x_m + r * np.sin(theta)
    cx = geometry.origin_x_m + (np.floor((bx - geometry.origin_x_m) / 0.25) + 0.5) * 0.25
    on_wall = (cx > 14) & (cx < 18)
    z_boom = MACHINE.pivot_z_m + (r - SIM_MACHINE.l4_m) * math.tan(luff) + 0 * theta
    assert cut.boom_intrusion_m == pytest.approx(float((8.0 - z_boom[on_wall]).max()), abs=0.01)
    z_boom = z_boom[on_wall]
    lower = np.where(surface == 8.0, float(z_boom.min()) - 0.1, surface)
    again = cut_step(lower, cell_set(geometry, lower, ground, 0.0), MACHINE, 0.0, luff,
                     math.pi / 2, params, apply=False)
    assert again.boom_cells == 0


def test_level_down_and_up_conserve_and_respect_the_floor():
    seed = 3
    rng = np.random.default_rng(seed)
    print("seed", seed)
    v = rng.uniform(0.0, 5.0, (50, 16))
    floor = rng.uniform(0.0, 0.5, (50, 16))
    v = np.maximum(v, floor)
    take = rng.uniform(0.0, 1.0, 50) * np.sum(v - floor, axis=1) * 0.9
    down = level_down(v, take, floor)
    np.testing.assert_allclose(np.sum(v - down, axis=1), take, rtol=1e-9, atol=1e-9)
    assert np.all(down <= v + 1e-12) and np.all(down >= floor - 1e-12)
    # what is taken comes off the top: no remaining cell above a lowered one's old height
    add = rng.uniform(0.0, 20.0, 50)
    up = level_up(v, add)
    np.testing.assert_allclose(np.sum(up - v, axis=1), add, rtol=1e-9, atol=1e-9)
    assert np.all(up >= v - 1e-12)
    raised = up > v + 1e-12
    # a raised cell ends at the row's level, which no unraised cell is below
    for row in range(50):
        if raised[row].any():
            level = up[row][raised[row]].max()
            assert np.all(up[row][~raised[row]] >= level - 1e-9)


def test_relax_region_conserves_volume_and_lays_a_wall_back():
    geometry = GridGeometry(0.0, 0.0, 0.25, 96, 96)
    x, _y = cell_centres(geometry)
    surface = np.where(x < 12.0, 8.0, 0.0)        # a vertical wall 8 m high
    ground = np.zeros(geometry.shape)
    before = surface.sum()
    tan = math.tan(math.radians(37.0))
    moved = relax_region(surface, ground, geometry.cell_m, tan,
                         (slice(None), slice(None)), 4, tol_m=1e-4)
    assert surface.sum() == pytest.approx(before, rel=1e-12)
    assert moved > 10.0
    # the face now runs out: material beyond the old wall, none lost from far behind it
    assert surface[(x > 12.5) & (x < 14.0)].mean() > 1.0
    assert surface[x < 2.0].min() == pytest.approx(8.0)


def test_settle_stack_moves_composition_and_conserves_each_deposit():
    geometry = GridGeometry(0.0, 0.0, 0.5, 40, 40)
    x, _y = cell_centres(geometry)
    stack = LayerStack.empty(geometry, 0.0)
    for k, level in enumerate((3.0, 6.0), 1):
        stack = stack.open_deposit(DepositInfo(k, f"P{k}", f"L{k}", k))
        stack, _ = stack.raise_to(np.where(x < 10.0, level, 0.0), 10 ** 18 + k)
    work = np.array(stack.surface())
    relax_region(work, np.zeros(geometry.shape), 0.5, math.tan(math.radians(37.0)),
                 (slice(None), slice(None)), 2, tol_m=1e-4)
    total = [stack.volume_m3(k) for k in (1, 2)]
    settled, moved = settle_stack(stack, work)
    np.testing.assert_allclose(settled.surface(), work, atol=1e-9)
    assert [settled.volume_m3(k) for k in (1, 2)] == pytest.approx(total, rel=1e-9)
    # the top of the wall slides: the upper deposit moves, and lies on the toe now
    assert moved.volume_m3 > 1.0 and 2 in {d.index for d in moved.deposits}
    assert np.all(settled.thickness(2)[x > 10.5] >= 0) and settled.thickness(2)[x > 10.5].sum() > 0


def test_predicted_grade_is_the_projectors_join_as_known_at_k():
    geometry = GridGeometry(0.0, 0.0, 1.0, 10, 10)
    t0 = 1_793_491_200_000_000_000
    stack = LayerStack.empty(geometry, 0.0).open_deposit(DepositInfo(1, "P1", "LOT-A", t0))
    stack, _ = stack.raise_to(np.full(geometry.shape, 2.0), t0 + 60_000_000_000)
    floor = np.where(np.arange(10)[:, None] < 5, 0.5, np.inf) * np.ones((1, 10))
    _after, removal = stack.clamp(floor)
    assert removal.volume_m3 == pytest.approx(5 * 10 * 1.5)
    lots = {"LOT-A": {"Fe": 60.0, "SiO2": 5.0}}
    recorded = t0 + 4 * 3600 * 10 ** 9
    assay = AssayRecord("A-1", "LOT-A", t0, t0 + 600 * 10 ** 9, {"Fe": 62.5, "SiO2": 4.2},
                        2.5, "FINAL", "", recorded)
    before, = predict_cuts(geometry, [removal], lots, [assay], recorded - 1, 2.4)
    after, = predict_cuts(geometry, [removal], lots, [assay], recorded, 2.4)
    assert before.tonnes == pytest.approx(75.0 * 2.4) and before.assayed_fraction == 0.0
    assert before.grade["Fe"] == pytest.approx(60.0)
    assert after.tonnes == pytest.approx(75.0 * 2.5) and after.assayed_fraction == 1.0
    assert after.grade == pytest.approx({"Fe": 62.5, "SiO2": 4.2})
    report = check_bounds([before, after], {"Fe": (61.0, None), "SiO2": (None, 4.5)})
    assert [(o["cut"], o["analyte"]) for o in report.outside] == [(1, "Fe"), (1, "SiO2")]
    w = 75.0 * 2.4
    assert report.bench_grade["Fe"] == pytest.approx((w * 60.0 + 75.0 * 2.5 * 62.5) / (w + 187.5))
    with pytest.raises(ValueError, match="min"):
        check_bounds([after], {"Fe": (63.0, 61.0)})


def test_bad_shapes_and_values_are_refused():
    geometry = GridGeometry(0.0, 0.0, 1.0, 10, 12)
    with pytest.raises(ValueError, match=r"shape \(10, 12\)"):
        cell_set(geometry, np.zeros((12, 10)), np.zeros((10, 12)), 0.0)
    with pytest.raises(ValueError, match="finite"):
        cell_set(geometry, np.full((10, 12), np.nan), np.zeros((10, 12)), 0.0)
    with pytest.raises(ValueError, match="shape"):
        landing_candidates(geometry, np.zeros((10, 11)), np.zeros((10, 12)), MACHINE,
                           spacing_m=1.0, normal_window_m=1.0, min_bite_m=0.0)
    with pytest.raises(ValueError, match="slew_step_rad"):
        PlanParams(slew_step_rad=math.radians(1.0))
    with pytest.raises(ValueError, match="clearance_m"):
        PlanParams(clearance_m=-1.0)
