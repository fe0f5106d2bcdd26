"""Tests of the projector's cutting envelope (projector.envelope): the reclaimer's joints,
the floor a cut leaves (a torus section swept over a slew arc) and what that floor removes
from a layer stack, each compared with per-cell Python loops over the docs/domain.md §3
formulas or with the simulator (``sim``), the ground truth for cuts; random inputs come from
seeded generators whose seeds are printed (shown by pytest on failure or with -s).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from projector.envelope import cut_floor, in_slew_arc
from projector.kinematics import Reclaimer, wheel_centre
from projector.grid import GridGeometry, cell_centre
from projector.layers import DepositInfo, LayerStack
from projector_helpers import H, T0


FULL = Reclaimer(rail_x_m=0.0, rail_z_m=0.0, l2_m=6.0, l3_m=5.0, l4_m=5.0, l5_m=50.0,
                 cutting_radius_m=10.0, wheel_tilt_rad=math.radians(5.0))


# --------------------------------------------------------------------------------------
# envelope
# --------------------------------------------------------------------------------------

def test_reclaimer_from_message_reads_machine_declared():
    from schemas.stockpile.v1 import events_pb2 as pb

    msg = pb.MachineDeclared(machine_id="bwr1", rail_x_m=1.5, rail_z_m=0.25, l2_m=6, l3_m=5,
                             l4_m=5, l5_m=50, wheel_radius_m=7, cutting_radius_m=10,
                             wheel_tilt_rad=0.0872, bucket_width_m=1.2)
    m = Reclaimer.from_message(msg)
    assert m == Reclaimer(1.5, 0.25, 6.0, 5.0, 5.0, 50.0, 10.0, 0.0872)
    with pytest.raises(ValueError):
        Reclaimer(0, 0, 6, 5, 5, 50, 0.0, 0.0)  # no cutting radius


def test_wheel_centre_matches_the_domain_formula():
    seed = 11
    print(f"seed={seed}")
    rng = np.random.default_rng(seed)
    m = Reclaimer(3.0, 1.0, 6.0, 5.0, 5.0, 50.0, 10.0, 0.1)
    for _ in range(50):
        d1, th2, th3 = rng.uniform(-100, 100), rng.uniform(-4, 4), rng.uniform(-0.5, 0.5)
        rho = m.l4_m + m.l5_m * math.cos(th3)
        expected = (m.rail_x_m + rho * math.sin(th2), d1 + rho * math.cos(th2),
                    m.rail_z_m + m.l2_m + m.l3_m + m.l5_m * math.sin(th3))
        c = wheel_centre(m, d1, th2, th3)
        assert c.shape == (3,)
        assert c == pytest.approx(expected, abs=1e-12)
        # inverse kinematics (docs/domain.md §3) recovers the joints
        assert math.asin((c[2] - m.rail_z_m - m.l2_m - m.l3_m) / m.l5_m) == pytest.approx(th3)
        slew = math.atan2(c[0] - m.rail_x_m, c[1] - d1)
        assert math.remainder(slew - th2, 2 * math.pi) == pytest.approx(0.0, abs=1e-12)
    # vectorised over broadcast joints
    c = wheel_centre(m, np.zeros(4), np.linspace(0, 1, 4), 0.1)
    assert c.shape == (4, 3)
    assert c[2] == pytest.approx(wheel_centre(m, 0.0, 1 / 3 * 2, 0.1))


def _on_arc_brute(theta: float, lo: float, hi: float) -> bool:
    """theta on the arc [lo, hi] modulo 2 pi: some theta + 2 pi n lies in [lo, hi]."""
    if hi - lo >= 2 * math.pi:
        return True
    return any(lo <= theta + 2 * math.pi * n <= hi for n in range(-4, 5))


def _floor_brute(geometry, m, d1, luff, s0, s1, margin=1e-9):
    """Per-cell loop over docs/domain.md §3; also marks cells within ``margin`` of a boundary."""
    lo, hi = min(s0, s1), max(s0, s1)
    rho = m.l4_m + m.l5_m * math.cos(luff)
    cz = m.rail_z_m + m.l2_m + m.l3_m + m.l5_m * math.sin(luff)
    half = m.cutting_radius_m * math.cos(m.wheel_tilt_rad)
    out = np.full(geometry.shape, math.inf)
    ambiguous = np.zeros(geometry.shape, bool)
    for ix in range(geometry.nx):
        for iy in range(geometry.ny):
            x, y = cell_centre(geometry, ix, iy)
            dx, dy = float(x) - m.rail_x_m, float(y) - d1
            r = math.hypot(dx, dy)
            theta = math.atan2(dx, dy)
            near_edge = (abs(abs(r - rho) - half) < margin
                         or any(abs(math.remainder(theta - e, 2 * math.pi)) < margin
                                for e in (lo, hi)))
            ambiguous[ix, iy] = near_edge
            if abs(r - rho) < half and _on_arc_brute(theta, lo, hi):
                out[ix, iy] = cz - m.cutting_radius_m * math.sqrt(1 - ((r - rho) / half) ** 2)
    return out, ambiguous


@pytest.mark.parametrize("seed", [1, 2, 3, 4, 5, 6])
def test_cut_floor_against_a_per_cell_loop(seed):
    print(f"seed={seed}")
    rng = np.random.default_rng(seed)
    m = Reclaimer(rng.uniform(-5, 5), rng.uniform(-1, 1), 6.0, 5.0, rng.uniform(2, 6),
                  rng.uniform(15, 30), rng.uniform(3, 8), rng.uniform(0, 0.2))
    geometry = GridGeometry(rng.uniform(-60, -40), rng.uniform(-60, -40), 1.0, 100, 110)
    d1 = rng.uniform(-10, 10)
    luff = rng.uniform(-0.3, 0.3)
    s0 = rng.uniform(-4, 4)
    s1 = s0 + rng.choice([-1, 1]) * rng.uniform(0.3, 3)
    got = cut_floor(geometry, m, d1, luff, s0, s1)
    want, ambiguous = _floor_brute(geometry, m, d1, luff, s0, s1)
    assert got.shape == geometry.shape
    ok = ~ambiguous
    assert np.isfinite(want[ok]).sum() > 20
    assert np.array_equal(np.isinf(got[ok]), np.isinf(want[ok]))
    both = ok & np.isfinite(want)
    np.testing.assert_allclose(got[both], want[both], rtol=0, atol=1e-9)
    assert np.all(np.isposinf(got[~np.isfinite(got)]))  # +inf, never NaN, outside


def test_cut_floor_arcs_across_pi():
    geometry = GridGeometry(-80.0, -80.0, 0.5, 320, 320)
    d1, luff = 0.0, -0.1
    rho = 5.0 + 50.0 * math.cos(luff)

    def hit(floor, azimuth):
        x, y = rho * math.sin(azimuth), d1 + rho * math.cos(azimuth)
        ix = int((x - geometry.origin_x_m) // geometry.cell_m)
        iy = int((y - geometry.origin_y_m) // geometry.cell_m)
        return bool(np.isfinite(floor[ix, iy]))

    short = cut_floor(geometry, FULL, d1, luff, 3.0, 3.5)  # crosses +pi, 0.5 rad wide
    for az in (3.1, math.pi, -3.1, 3.5 - 2 * math.pi - 0.02):
        assert hit(short, az), az
    for az in (2.9, -2.7, 0.0, 1.5):
        assert not hit(short, az), az
    # the direction of the slew does not matter, nor a shift of the joint angles by 2 pi
    assert np.array_equal(short, cut_floor(geometry, FULL, d1, luff, 3.5, 3.0))
    shifted = cut_floor(geometry, FULL, d1, luff, 3.0 - 2 * math.pi, 3.5 - 2 * math.pi)
    assert np.array_equal(np.isfinite(short), np.isfinite(shifted))
    # 3.0 -> -3.0 is the long way round (6 rad through +y), not the short way across pi
    long = cut_floor(geometry, FULL, d1, luff, 3.0, -3.0)
    assert hit(long, 0.0) and hit(long, 2.9) and hit(long, -2.9)
    assert not hit(long, math.pi)
    # a slew of 2 pi or more covers the whole ring
    ring = cut_floor(geometry, FULL, d1, luff, -1.0, -1.0 + 2 * math.pi)
    for az in np.linspace(-math.pi, math.pi, 37):
        assert hit(ring, az)
    # the arc test itself, with both ends included
    assert in_slew_arc(np.array([3.0, 3.5, -math.pi, 2.99]), 3.0, 3.5).tolist() == \
        [True, True, True, False]


def test_cut_floor_matches_the_simulator_envelope():
    """The simulator is the ground truth: same footprint and floor on random cuts."""
    from sim.kinematics import FULL_SCALE, envelope_floor_z

    m = Reclaimer(FULL_SCALE.rail_x_m, FULL_SCALE.rail_z_m, FULL_SCALE.l2_m, FULL_SCALE.l3_m,
                  FULL_SCALE.l4_m, FULL_SCALE.l5_m, FULL_SCALE.cutting_radius_m,
                  FULL_SCALE.wheel_tilt_rad)
    geometry = GridGeometry(-70.0, -70.0, 0.5, 280, 280)
    xc = geometry.origin_x_m + (np.arange(geometry.nx) + 0.5) * geometry.cell_m
    yc = geometry.origin_y_m + (np.arange(geometry.ny) + 0.5) * geometry.cell_m
    seed = 77
    print(f"seed={seed}")
    rng = np.random.default_rng(seed)
    for _ in range(20):
        d1, luff = rng.uniform(-5, 5), rng.uniform(-0.3, 0.2)
        s0 = rng.uniform(-7, 7)
        s1 = s0 + rng.uniform(-2.5, 2.5)
        ours = cut_floor(geometry, m, d1, luff, s0, s1)
        sim = envelope_floor_z(FULL_SCALE, xc[:, None], yc[None, :], d1, luff, s0, s1)
        assert np.array_equal(np.isfinite(ours), np.isfinite(sim))
        fin = np.isfinite(sim)
        np.testing.assert_allclose(ours[fin], sim[fin], rtol=0, atol=1e-9)


def test_cut_removes_what_the_simulator_removes_in_sub_slews():
    """One clamp over the whole arc == the simulator's cut in 8 sub-slews (runner.py)."""
    from sim.kinematics import FULL_SCALE
    from sim.world import Grid, World

    grid = Grid.covering(35.0, 75.0, -10.0, 30.0, 0.5)
    world = World(grid, 37.0, analytes=("Fe",))
    seed = 5
    print(f"seed={seed}")
    rng = np.random.default_rng(seed)
    for i in range(4):  # four deposits, each a few releases along the crest
        for j in range(3):
            world.deposit(55.0 + rng.normal(0, 0.5), 5.0 + 5 * j + rng.normal(0, 0.5), 900.0,
                          T0 + i * H + j, 10 + i, f"L{i}", {"Fe": 60.0 + i}, 2.4)
    geometry = GridGeometry(grid.origin_x_m, grid.origin_y_m, grid.cell_m, grid.nx, grid.ny)
    tops = world.layer_surfaces()  # (slots, ny, nx)
    stack = LayerStack.empty(geometry, grid.ground_z_m)
    for k in range(tops.shape[0]):
        stack = stack.open_deposit(DepositInfo(k + 1, f"P{k}", f"L{k}", T0 + k * H))
        stack, _ = stack.raise_to(tops[k].T, T0 + k * H)
    assert stack.total_volume_m3() == pytest.approx(world.volume_m3(), rel=1e-12)
    m = Reclaimer(FULL_SCALE.rail_x_m, FULL_SCALE.rail_z_m, FULL_SCALE.l2_m, FULL_SCALE.l3_m,
                  FULL_SCALE.l4_m, FULL_SCALE.l5_m, FULL_SCALE.cutting_radius_m,
                  FULL_SCALE.wheel_tilt_rad)
    top = float(world.surface_z().max())
    luff = math.asin((top + 4.0 - FULL_SCALE.pivot_height_m) / FULL_SCALE.l5_m)
    n_cut = 0
    for c, travel in enumerate((-12.0, -10.0, -8.0, -6.0)):
        s0, s1 = (math.pi / 2 + 0.35, math.pi / 2 - 0.35) if c % 2 else \
            (math.pi / 2 - 0.35, math.pi / 2 + 0.35)
        truths = []
        for k in range(8):  # the runner's sub-slews
            a = s0 + (s1 - s0) * k / 8
            b = s0 + (s1 - s0) * (k + 1) / 8
            truths.append(world.reclaim_cut(FULL_SCALE, travel, luff, a, b, T0 + 10 * H + c,
                                            relax=False))
        stack, removal = stack.clamp(cut_floor(geometry, m, travel, luff, s0, s1))
        sim_m3 = sum(t.volume_m3 for t in truths)
        assert removal.volume_m3 == pytest.approx(sim_m3, rel=1e-9, abs=1e-9)
        by_dep = {}
        for t in truths:
            for dep, tonnes in t.tonnes_by_deposit.items():
                by_dep[dep - 9] = by_dep.get(dep - 9, 0.0) + tonnes / 2.4
        ours = {d.index: d.volume_m3 for d in removal.deposits}
        assert ours.keys() == by_dep.keys()
        for k, vol in by_dep.items():
            assert ours[k] == pytest.approx(vol, rel=1e-9)
        n_cut += sim_m3 > 1.0
        np.testing.assert_allclose(stack.surfaces(),
                                   np.concatenate([np.full((1,) + geometry.shape, 0.0),
                                                   np.transpose(world.layer_surfaces(),
                                                                (0, 2, 1))]),
                                   rtol=0, atol=1e-9)
    assert n_cut >= 2
