"""Tests of the projector's material kernels: cutting envelope, layer stack, voxels, grades.

Every check compares against a value computed a different way: per-cell Python loops over
the DOMAIN.md §3 formulas, a parcel-list model of the pile, brute-force voxel overlaps,
Monte Carlo points, and the simulator (``sim``) as the ground truth for cuts.
Random inputs come from seeded generators; the seeds are printed (shown by pytest on
failure or with -s).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from projector.envelope import cut_floor, in_slew_arc
from projector.grades import AssayRecord, effective_assays, grade_at, grade_classes
from projector.grid import GridGeometry, cell_centre
from projector.kinematics import Reclaimer, wheel_centre
from projector.layers import DepositInfo, LayerStack, fit_local_quadratic
from projector.voxels import ClassWeights, integrate

T0 = 1_700_000_000 * 10**9  # an arbitrary UTC epoch (ns)
H = 3_600 * 10**9           # one hour (ns)

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
        # inverse kinematics (DOMAIN.md §3) recovers the joints
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
    """Per-cell loop over DOMAIN.md §3; also marks cells within ``margin`` of a boundary."""
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


# --------------------------------------------------------------------------------------
# layer stack
# --------------------------------------------------------------------------------------

class ParcelModel:
    """Reference pile: per cell a list of parcels [deposit, thickness, mean time] (bottom up)."""

    def __init__(self, ground):
        self.ground = np.array(ground, float)
        self.cols = {ij: [] for ij in np.ndindex(self.ground.shape)}
        self.n = 0

    def top(self, ij):
        return self.ground[ij] + sum(p[1] for p in self.cols[ij])

    def raise_to(self, surf, t):
        """``t``: one time, or an array of a time per cell."""
        added = 0.0
        for ij, col in self.cols.items():
            s = surf[ij]
            if math.isnan(s) or s <= self.top(ij):
                continue
            t_ij = float(t[ij]) if np.ndim(t) else t
            a = s - self.top(ij)
            added += a
            if col and col[-1][0] == self.n:
                p = col[-1]
                p[2] = (p[2] * p[1] + t_ij * a) / (p[1] + a)
                p[1] += a
            else:
                col.append([self.n, a, float(t_ij)])
        return added

    def clamp(self, floor):
        removed = {}  # deposit -> list of (ij, thickness, time)
        for ij, col in self.cols.items():
            f = max(floor[ij], self.ground[ij])
            z = self.ground[ij]
            keep = []
            for dep, thk, tm in col:
                kept = min(max(f - z, 0.0), thk)
                if thk - kept > 0:
                    removed.setdefault(dep, []).append((ij, thk - kept, tm))
                if kept > 0:
                    keep.append([dep, kept, tm])
                z += thk
            self.cols[ij] = keep
        return removed

    def thickness(self, k):
        out = np.zeros(self.ground.shape)
        for ij, col in self.cols.items():
            out[ij] = sum(p[1] for p in col if p[0] == k)
        return out

    def time(self, k):
        out = np.full(self.ground.shape, np.nan)
        for ij, col in self.cols.items():
            for p in col:
                if p[0] == k:
                    out[ij] = p[2]
        return out


def _run_ops(ops, seed):
    """Apply ops to a LayerStack and to the parcel model; check after every step."""
    rng = np.random.default_rng(seed)
    geometry = GridGeometry(0.0, 0.0, 0.5, 3, 4)
    area = geometry.cell_area_m2
    ground = rng.uniform(-0.3, 0.3, geometry.shape)
    stack = LayerStack.empty(geometry, ground)
    ref = ParcelModel(ground)
    added = removed = 0.0
    t = T0
    for op in ops:
        t += int(rng.integers(1, 10**9))
        if op == "open" or stack.n_deposits == 0:
            ref.n += 1
            stack = stack.open_deposit(DepositInfo(ref.n, f"P{ref.n}", "L", t, op != "open"))
        elif op == "raise":
            surf = stack.surface() + rng.uniform(-0.5, 1.0, geometry.shape)
            surf[rng.random(geometry.shape) < 0.2] = np.nan
            before = [stack.surface_k(k).copy() for k in range(stack.n_deposits + 1)]
            old = stack
            # one time for all cells, or (as the fold gives a pass's material) one per cell
            t_raise = t if rng.random() < 0.5 else (
                t - rng.integers(0, 10**9, geometry.shape)).astype(np.float64)
            stack, add = stack.raise_to(surf, t_raise)
            assert add == pytest.approx(ref.raise_to(surf, t_raise) * area, rel=1e-12,
                                        abs=1e-15)
            added += add
            for k in range(old.n_deposits + 1):  # the old stack is unchanged
                assert np.array_equal(old.surface_k(k), before[k])
        else:
            floor = stack.surface() - rng.uniform(-0.2, 1.5, geometry.shape)
            floor[rng.random(geometry.shape) < 0.3] = np.inf
            old = stack
            before = old.surfaces()
            stack, removal = stack.clamp(floor)
            assert np.array_equal(old.surfaces(), before)
            want = ref.clamp(floor)
            got = removal.by_index()
            assert set(got) <= set(want)  # nothing removed from a deposit that lost nothing
            assert {k for k, v in want.items() if sum(x[1] for x in v) > 1e-12} <= set(got)
            for k, pieces in want.items():
                vol = sum(p[1] for p in pieces) * area
                if vol < 1e-12:
                    continue
                d = got[k]
                assert d.volume_m3 == pytest.approx(vol, rel=1e-9)
                per_cell = {(int(a), int(b)): (v, tm) for a, b, v, tm in
                            zip(d.ix, d.iy, d.cell_volume_m3, d.deposition_time_ns)}
                for ij, thk, tm in pieces:
                    if thk * area < 1e-12:
                        continue
                    v, tm_got = per_cell[ij]
                    assert v == pytest.approx(thk * area, rel=1e-9, abs=1e-12)
                    assert tm_got == pytest.approx(tm, abs=1024)
            removed += removal.volume_m3
        # invariants
        s = stack.surfaces()
        assert np.all(np.diff(s, axis=0) >= 0), "surfaces are not monotone"
        assert np.array_equal(s[0], ground)
        total = stack.total_volume_m3()
        assert total == pytest.approx(sum(stack.volume_m3(k) for k in
                                          range(1, stack.n_deposits + 1)), rel=1e-12, abs=1e-12)
        assert added == pytest.approx(total + removed, rel=1e-9, abs=1e-12)
        for k in range(1, stack.n_deposits + 1):
            np.testing.assert_allclose(stack.thickness(k), ref.thickness(k), rtol=0, atol=1e-12)
            got_t = stack.deposition_time_ns(k)
            want_t = ref.time(k)
            has = stack.thickness(k) > 1e-12
            np.testing.assert_allclose(got_t[has], want_t[has], rtol=0, atol=1024)
            assert np.all(np.isnan(got_t[stack.thickness(k) == 0]))


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(ops=st.lists(st.sampled_from(["open", "raise", "raise", "clamp"]), min_size=1,
                    max_size=25),
       seed=st.integers(0, 2**32 - 1))
def test_layer_stack_against_a_parcel_model(ops, seed):
    _run_ops(ops, seed)


def test_layer_stack_basics_and_errors():
    geometry = GridGeometry(0.0, 0.0, 1.0, 2, 3)
    stack = LayerStack.empty(geometry, 1.0)
    with pytest.raises(ValueError):
        stack.raise_to(np.full(geometry.shape, 2.0), T0)  # no deposit open
    with pytest.raises(ValueError):
        stack.open_deposit(DepositInfo(2, "P", "L", T0))  # wrong index
    stack = stack.open_deposit(DepositInfo(1, "P1", "L1", T0))
    with pytest.raises(ValueError):
        stack.raise_to(np.zeros((3, 2)), T0)  # (ny, nx) instead of (nx, ny)
    with pytest.raises(ValueError):
        stack.raise_to(np.full(geometry.shape, np.inf), T0)
    with pytest.raises(TypeError):
        stack.raise_to(np.full(geometry.shape, 2.0), float(T0))
    with pytest.raises(ValueError):  # a time per cell, but (ny, nx)
        stack.raise_to(np.full(geometry.shape, 2.0), np.full((3, 2), float(T0)))
    with pytest.raises(ValueError):  # no time where the surface rises
        stack.raise_to(np.full(geometry.shape, 2.0), np.full(geometry.shape, np.nan))
    with pytest.raises(ValueError):
        stack.clamp(np.full(geometry.shape, np.nan))
    s1, add = stack.raise_to(np.array([[2.0, np.nan, 0.5], [3.0, 1.0, 1.5]]), T0 + H)
    assert add == pytest.approx(1.0 + 2.0 + 0.5)
    assert s1.thickness(1).tolist() == [[1.0, 0.0, 0.0], [2.0, 0.0, 0.5]]
    s2, add2 = s1.raise_to(np.full(geometry.shape, 3.0), T0 + 3 * H)
    # thickness-weighted deposition time: cell (0, 0) had 1 m at T0 + H, gets 1 m at T0 + 3 H
    assert s2.deposition_time_ns(1)[0, 0] == pytest.approx(T0 + 2 * H, abs=512)
    assert s2.deposition_time_ns(1)[1, 0] == pytest.approx(T0 + H, abs=512)
    assert s2.deposition_time_ns(1)[0, 1] == pytest.approx(T0 + 3 * H, abs=512)
    s3 = s2.open_deposit(DepositInfo(2, "P2", "L2", T0 + 4 * H))
    assert s3.volume_m3(2) == 0.0 and np.all(np.isnan(s3.deposition_time_ns(2)))
    s3, _ = s3.raise_to(np.full(geometry.shape, 4.0), T0 + 5 * H)
    # clamp below ground: stops at the ground
    s4, rem = s3.clamp(np.array([[-5.0, np.inf, 2.0], [np.inf, np.inf, 3.5]]))
    assert s4.surface().tolist() == [[1.0, 4.0, 2.0], [4.0, 4.0, 3.5]]
    by = rem.by_index()
    assert by[1].volume_m3 == pytest.approx(2.0 + 1.0)
    assert by[2].volume_m3 == pytest.approx(1.0 + 1.0 + 0.5)
    assert rem.volume_m3 == pytest.approx(5.5)
    assert rem.removed_m(geometry).tolist() == [[3.0, 0.0, 2.0], [0.0, 0.0, 0.5]]
    assert by[2].mean_deposition_time_ns == pytest.approx(T0 + 5 * H, abs=512)
    # nothing above the floor: the same stack, an empty removal
    s5, rem5 = s4.clamp(np.full(geometry.shape, 10.0))
    assert s5 is s4 and rem5.volume_m3 == 0.0 and rem5.deposits == ()
    assert s4.copy().surfaces().tolist() == s4.surfaces().tolist()
    assert not s4.surface().flags.writeable


# --------------------------------------------------------------------------------------
# voxels
# --------------------------------------------------------------------------------------

def _random_stack(seed, nx=7, ny=9, cell=0.5, n=5, quantum=None, ground_sd=0.3):
    rng = np.random.default_rng(seed)
    geometry = GridGeometry(10.0, -4.0, cell, nx, ny)
    ground = 2.0 + rng.uniform(-ground_sd, ground_sd, geometry.shape)
    if quantum:
        ground = np.round(ground / quantum) * quantum
    stack = LayerStack.empty(geometry, ground)
    for k in range(1, n + 1):
        stack = stack.open_deposit(DepositInfo(k, f"P{k}", f"L{k % 2}", T0 + k * H))
        thick = rng.choice([0.0, 0.05, 0.3, 1.2, 2.7], size=geometry.shape) \
            * rng.uniform(0.5, 1.5, geometry.shape)
        surf = stack.surface() + thick
        if quantum:
            surf = np.maximum(np.round(surf / quantum) * quantum, stack.surface())
        stack, _ = stack.raise_to(surf, T0 + k * H)
        if k == 3:  # a cut in the middle, so bands are not all full
            floor = np.where(rng.random(geometry.shape) < 0.4,
                             stack.surface() - rng.uniform(0, 2, geometry.shape), np.inf)
            stack, _ = stack.clamp(floor)
    return stack


def _voxels_brute(stack, voxel_m, weights=None):
    """Per cell, per deposit, per z bin: the overlap formula of the brief, in Python."""
    g = stack.geometry
    m = int(round(voxel_m / g.cell_m))
    z0 = float(stack.ground().min())
    qvo, wq = {}, {}
    for ix in range(g.nx):
        for iy in range(g.ny):
            for k in range(1, stack.n_deposits + 1):
                lo = float(stack.surface_k(k - 1)[ix, iy])
                hi = float(stack.surface_k(k)[ix, iy])
                if hi <= lo:
                    continue
                for iz in range(int((hi - z0) // voxel_m) + 2):
                    za, zb = z0 + iz * voxel_m, z0 + (iz + 1) * voxel_m
                    v = max(0.0, min(hi, zb) - max(lo, za)) * g.cell_area_m2
                    if v > 0:
                        key = (ix // m, iy // m, iz, k)
                        qvo[key] = qvo.get(key, 0.0) + v
                        if weights is not None:
                            w = weights[k - 1]
                            wq[key] = wq.get(key, 0.0) + v * w[ix, iy]
    return qvo, wq


@pytest.mark.parametrize("seed,quantum", [(1, None), (2, None), (3, 0.25), (4, 0.5)])
def test_voxels_against_a_brute_force_loop(seed, quantum):
    print(f"seed={seed}")
    stack = _random_stack(seed, quantum=quantum)
    rng = np.random.default_rng(seed + 100)
    weights = [rng.uniform(1.5, 3.0, stack.geometry.shape + (3,))
               for _ in range(stack.n_deposits)]
    vg = integrate(stack, 1.0, weights)
    want, want_w = _voxels_brute(stack, 1.0, weights)
    got = {(int(a), int(b), int(c), int(d)): v for a, b, c, d, v in
           zip(vg.qvo.ix, vg.qvo.iy, vg.qvo.iz, vg.qvo.deposit, vg.qvo.volume_m3)}
    big = {k for k, v in want.items() if v > 1e-12}
    assert big <= set(got) and set(got) <= set(want)
    for key, v in want.items():
        assert got.get(key, 0.0) == pytest.approx(v, rel=1e-9, abs=1e-12)
    # voxel volumes are the sums of their QVOs; weighted sums too
    vol = np.zeros(vg.shape)
    wsum = np.zeros(vg.shape + (3,))
    for (a, b, c, d), v in want.items():
        vol[a, b, c] += v
        wsum[a, b, c] += want_w[(a, b, c, d)]
    np.testing.assert_allclose(vg.volume_m3, vol, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(vg.weighted, wsum, rtol=1e-9, atol=1e-12)
    rows = {(int(a), int(b), int(c), int(d)): i for i, (a, b, c, d) in
            enumerate(zip(vg.qvo.ix, vg.qvo.iy, vg.qvo.iz, vg.qvo.deposit))}
    for key, i in rows.items():
        np.testing.assert_allclose(vg.qvo.weighted[i], want_w[key], rtol=1e-9, atol=1e-12)
    assert vg.shape[:2] == (4, 5)  # ceil(7 / 2), ceil(9 / 2): partial voxel columns
    assert vg.voxel_origin == (10.0, -4.0, float(stack.ground().min()))
    assert vg.total_volume_m3() == pytest.approx(stack.total_volume_m3(), rel=1e-9)


@pytest.mark.parametrize("seed", [7, 8, 9])
def test_voxel_total_equals_the_stack_volume(seed):
    print(f"seed={seed}")
    stack = _random_stack(seed, nx=40, ny=50, cell=0.25, n=12)
    for voxel in (0.25, 0.5, 1.0, 1.25):
        vg = integrate(stack, voxel)
        assert vg.total_volume_m3() == pytest.approx(stack.total_volume_m3(), rel=1e-9)
        per_dep = np.bincount(vg.qvo.deposit, weights=vg.qvo.volume_m3,
                              minlength=stack.n_deposits + 1)
        for k in range(1, stack.n_deposits + 1):
            assert per_dep[k] == pytest.approx(stack.volume_m3(k), rel=1e-9, abs=1e-12)
        assert np.all(vg.qvo.volume_m3 > 0)
        assert np.all(vg.volume_m3 <= voxel ** 3 * (1 + 1e-12))


def test_voxels_against_monte_carlo_points():
    seed = 21
    print(f"seed={seed}")
    stack = _random_stack(seed, nx=8, ny=8, cell=0.5, n=4)
    g = stack.geometry
    vg = integrate(stack, 2.0)
    rng = np.random.default_rng(seed)
    surfaces = stack.surfaces()
    n_pts = 200_000
    checked = 0
    for (vx, vy, vz) in [(0, 0, 0), (1, 1, 1), (0, 1, 1), (1, 0, 2)]:
        x = g.origin_x_m + (vx + rng.random(n_pts)) * 2.0
        y = g.origin_y_m + (vy + rng.random(n_pts)) * 2.0
        z = vg.z0_m + (vz + rng.random(n_pts)) * 2.0
        ix = ((x - g.origin_x_m) // g.cell_m).astype(int)
        iy = ((y - g.origin_y_m) // g.cell_m).astype(int)
        cols = surfaces[:, ix, iy]  # (n + 1, N)
        dep = np.sum(z[None, :] > cols, axis=0)  # k with S(k-1) < z <= S(k), 0 below ground
        dep[z > cols[-1]] = 0  # above the top: air
        for k in range(1, stack.n_deposits + 1):
            p = np.mean(dep == k)
            mc = p * 8.0
            sel = (vg.qvo.ix == vx) & (vg.qvo.iy == vy) & (vg.qvo.iz == vz) & \
                (vg.qvo.deposit == k)
            exact = float(vg.qvo.volume_m3[sel].sum())
            sigma = 8.0 * math.sqrt(max(p * (1 - p), 1e-6) / n_pts)
            assert abs(mc - exact) < 5 * sigma + 1e-9, (vx, vy, vz, k, mc, exact)
            checked += exact > 0.1
    assert checked >= 4


def test_voxel_weights_give_tonnes_and_grades():
    stack = _random_stack(31, nx=12, ny=10, cell=0.5, n=3)
    g = stack.geometry
    rng = np.random.default_rng(31)
    density = [2.2, 2.4, 2.6]
    fe = [rng.uniform(55, 65, g.shape) for _ in range(3)]
    per_cell = [np.stack([np.full(g.shape, d), d * f / 100], axis=-1) for d, f in zip(density, fe)]
    vg = integrate(stack, 1.0, per_cell)
    tonnes = vg.weighted[..., 0]
    fe_t = vg.weighted[..., 1]
    want_t = sum(density[k - 1] * stack.volume_m3(k) for k in range(1, 4))
    want_fe = sum(density[k - 1] * float(np.sum(stack.thickness(k) * fe[k - 1] / 100))
                  * g.cell_area_m2 for k in range(1, 4))
    assert tonnes.sum() == pytest.approx(want_t, rel=1e-9)
    assert fe_t.sum() == pytest.approx(want_fe, rel=1e-9)
    grade = np.divide(100 * fe_t, tonnes, out=np.full(tonnes.shape, np.nan), where=tonnes > 0)
    assert np.nanmin(grade) >= 55 - 1e-9 and np.nanmax(grade) <= 65 + 1e-9
    # one weight vector per deposit == the same value in every cell
    const = integrate(stack, 1.0, [np.array([d, d]) for d in density])
    full = integrate(stack, 1.0, [np.full(g.shape + (2,), d) for d in density])
    np.testing.assert_allclose(const.weighted, full.weighted, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(const.weighted[..., 0],
                               sum(density[k - 1] * _qvo_dense(const, k) for k in range(1, 4)),
                               rtol=1e-12, atol=1e-12)
    # NaN weights where a deposit has no material are ignored
    nan_w = []
    for k, d in enumerate(density, start=1):
        w = np.full(g.shape + (1,), d)
        w[stack.thickness(k) == 0] = np.nan
        nan_w.append(w)
    vg_nan = integrate(stack, 1.0, nan_w)
    assert np.all(np.isfinite(vg_nan.weighted))
    np.testing.assert_allclose(vg_nan.weighted[..., 0], tonnes, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("seed", [51, 52])
def test_class_weights_against_the_brute_force_loop(seed):
    """Weights given as a class per cell and a table (one to four classes per deposit, NaN
    in a class no cell of the deposit uses) equal the brute-force sums of table[class]."""
    print(f"seed={seed}")
    stack = _random_stack(seed, quantum=0.25 if seed % 2 else None)
    g = stack.geometry
    rng = np.random.default_rng(seed)
    classed, per_cell = [], []
    for k in range(1, stack.n_deposits + 1):
        n_c = int(rng.integers(1, 5))
        table = rng.uniform(1.0, 3.0, (n_c + 1, 3))
        table[n_c] = np.nan                      # an extra class no cell uses
        index = rng.integers(0, n_c, g.shape).astype(np.uint8)
        classed.append(ClassWeights(index, table))
        per_cell.append(table[index])
    vg = integrate(stack, 1.0, classed)
    want, want_w = _voxels_brute(stack, 1.0, per_cell)
    rows = {(int(a), int(b), int(c), int(d)): i for i, (a, b, c, d) in
            enumerate(zip(vg.qvo.ix, vg.qvo.iy, vg.qvo.iz, vg.qvo.deposit))}
    assert set(rows) <= set(want)
    for key, v in want.items():
        if key in rows:
            np.testing.assert_allclose(vg.qvo.weighted[rows[key]], want_w[key], rtol=1e-9,
                                       atol=1e-12)
        else:
            assert v < 1e-12
    wsum = np.zeros(vg.shape + (3,))
    for (a, b, c, _d), wv in want_w.items():
        wsum[a, b, c] += wv
    np.testing.assert_allclose(vg.weighted, wsum, rtol=1e-9, atol=1e-12)
    with pytest.raises(ValueError):
        ClassWeights(np.full(g.shape, 5, np.uint8), np.ones((2, 3)))  # class 5 of 2
    with pytest.raises(ValueError):
        integrate(stack, 1.0, [ClassWeights(np.zeros((2, 2), np.uint8), np.ones((1, 3)))]
                  * stack.n_deposits)                                  # wrong grid


def _qvo_dense(vg, k):
    out = np.zeros(vg.shape)
    sel = vg.qvo.deposit == k
    np.add.at(out, (vg.qvo.ix[sel], vg.qvo.iy[sel], vg.qvo.iz[sel]), vg.qvo.volume_m3[sel])
    return out


def test_voxel_errors_and_empty_stack():
    stack = _random_stack(41, n=2)
    with pytest.raises(ValueError):
        integrate(stack, 0.75)  # not a multiple of 0.5
    with pytest.raises(ValueError):
        integrate(stack, 0.0)
    with pytest.raises(ValueError):
        integrate(stack, 1.0, [np.ones(2)])  # one weight array for two deposits
    with pytest.raises(ValueError):
        integrate(stack, 1.0, [np.ones((3, 3, 2)), np.ones((3, 3, 2))])
    empty = LayerStack.empty(GridGeometry(0, 0, 0.5, 4, 4), 0.0)
    vg = integrate(empty, 1.0)
    assert vg.shape == (2, 2, 1) and vg.total_volume_m3() == 0.0 and len(vg.qvo) == 0
    assert vg.weighted.shape == (2, 2, 1, 0)


# --------------------------------------------------------------------------------------
# grades
# --------------------------------------------------------------------------------------

PLANNED = {"Fe": 60.0, "SiO2": 5.0, "P": 0.08}
ANALYTES = ("Fe", "SiO2", "P")


def _assay(aid, lot, start_h, end_h, fe, *, status="FINAL", supersedes="", rec_h=10.0,
           density=2.4, analytes=None):
    return AssayRecord(aid, lot, T0 + int(start_h * H), T0 + int(end_h * H),
                       analytes if analytes is not None else {"Fe": fe, "SiO2": 4.0, "P": 0.07},
                       density, status, supersedes, T0 + int(rec_h * H))


def test_assay_from_message():
    from schemas.stockpile.v1 import events_pb2 as pb

    msg = pb.Assay(assay_id="AS-2", lot_id="L1", analytes={"Fe": 61.2, "SiO2": 4.4},
                   bulk_density_t_m3=2.45, status=pb.FINAL, supersedes="AS-1", lab_id="lab1")
    msg.window_start.FromNanoseconds(T0)
    msg.window_end.FromNanoseconds(T0 + 1_200 * 10**9 + 7)
    rec = AssayRecord.from_message(msg, T0 + 5 * H)
    assert rec == AssayRecord("AS-2", "L1", T0, T0 + 1_200 * 10**9 + 7,
                              {"Fe": 61.2, "SiO2": 4.4}, 2.45, "FINAL", "AS-1", T0 + 5 * H)
    msg.status = pb.PROVISIONAL
    assert AssayRecord.from_message(msg, 0).status == "PROVISIONAL"
    msg.status = pb.ASSAY_STATUS_UNSPECIFIED
    with pytest.raises(ValueError):
        AssayRecord.from_message(msg, 0)


def test_supersede_and_the_known_time():
    prov = _assay("A1", "L", 0, 1, 58.0, status="PROVISIONAL", rec_h=3)
    final = _assay("A2", "L", 0, 1, 62.0, supersedes="A1", rec_h=5)
    t = np.array([T0 + H // 2])
    for k_ns, want_fe, want_id in ((T0 + 3 * H - 1, PLANNED["Fe"], None),
                                   (T0 + 3 * H, 58.0, "A1"),
                                   (T0 + 5 * H - 1, 58.0, "A1"),
                                   (T0 + 5 * H, 62.0, "A2")):
        eff = effective_assays([final, prov], k_ns)
        assert [a.assay_id for a in eff] == ([want_id] if want_id else [])
        grade, assayed, dens = grade_at("L", PLANNED, eff, t, ANALYTES)
        assert grade[0, 0] == want_fe
        assert assayed[0] == (want_id is not None)
        assert (dens[0] == 2.4) if want_id else math.isnan(dens[0])
    # a chain: A1 <- A2 <- A3, every replaced link is dropped
    a3 = _assay("A3", "L", 0, 1, 61.0, supersedes="A2", rec_h=7)
    assert [a.assay_id for a in effective_assays([prov, final, a3], T0 + 8 * H)] == ["A3"]
    # superseding works across statuses and windows: a FINAL replaced by a corrected one
    other = _assay("B1", "L", 2, 3, 59.0, rec_h=4)
    fix = _assay("B2", "L", 2, 3, 59.5, supersedes="B1", rec_h=6, status="PROVISIONAL")
    assert [a.assay_id for a in effective_assays([other, fix], T0 + 6 * H)] == ["B2"]


def test_final_replaces_an_overlapping_provisional_of_the_same_lot():
    prov = _assay("P1", "L", 0.0, 1.0, 57.0, status="PROVISIONAL", rec_h=2)
    final_overlap = _assay("F1", "L", 0.5, 1.5, 63.0, rec_h=4)      # no supersedes field
    final_touch = _assay("F2", "L", 1.0, 2.0, 64.0, rec_h=4)        # touches at 1 h only
    final_other_lot = _assay("F3", "M", 0.0, 1.0, 65.0, rec_h=4)
    eff = effective_assays([prov, final_touch, final_other_lot], T0 + 5 * H)
    assert {a.assay_id for a in eff} == {"P1", "F2", "F3"}
    eff = effective_assays([prov, final_overlap, final_touch], T0 + 5 * H)
    assert {a.assay_id for a in eff} == {"F1", "F2"}
    # before the FINAL is recorded the PROVISIONAL still counts
    eff = effective_assays([prov, final_overlap], T0 + 4 * H - 1)
    assert [a.assay_id for a in eff] == ["P1"]
    # where both a FINAL and a PROVISIONAL contain t, the FINAL wins, then the latest recorded
    p_late = _assay("P9", "L", 0.0, 3.0, 50.0, status="PROVISIONAL", rec_h=9)
    f_a = _assay("FA", "L", 2.0, 2.5, 61.0, rec_h=3)   # overlaps P9 -> P9 dropped anyway
    eff = effective_assays([p_late, f_a], T0 + 10 * H)
    assert [a.assay_id for a in eff] == ["FA"]
    f_b = _assay("FB", "L", 2.25, 2.75, 62.0, rec_h=6)
    times = np.array([T0 + int(2.1 * H), T0 + int(2.4 * H), T0 + int(2.6 * H), T0 + 3 * H])
    grade, assayed, _ = grade_at("L", PLANNED, [f_a, f_b], times, ANALYTES)
    assert grade[:, 0].tolist() == [61.0, 62.0, 62.0, PLANNED["Fe"]]
    assert assayed.tolist() == [True, True, True, False]
    # precedence inside grade_at when a PROVISIONAL and a FINAL both contain t
    pv = _assay("PV", "L", 2.0, 2.5, 40.0, status="PROVISIONAL", rec_h=20)
    grade, _, _ = grade_at("L", PLANNED, [pv, f_a], times[:1], ANALYTES)
    assert grade[0, 0] == 61.0


@pytest.mark.parametrize("seed", [11, 12])
def test_grade_classes_sum_like_a_per_cell_loop(seed):
    """Tonnes and grade-tonnes summed per class equal a loop over the cells applying the
    precedence rule of the module docstring to each time."""
    print(f"seed={seed}")
    rng = np.random.default_rng(seed)
    assays = [_assay("A", "L", 0.0, 1.0, 61.0, rec_h=3, density=2.5),
              _assay("B", "L", 0.5, 2.0, 58.0, status="PROVISIONAL", rec_h=6, density=0.0),
              _assay("C", "L", 1.5, 2.5, 63.5, rec_h=4, density=2.2,
                     analytes={"Fe": 63.5, "SiO2": 3.0}),
              _assay("D", "M", 0.0, 3.0, 40.0)]
    n = 500
    times = T0 + rng.uniform(-0.5, 3.0, n) * H
    times[rng.random(n) < 0.05] = np.nan
    volumes = rng.uniform(0.0, 1.0, n)
    c = grade_classes("L", PLANNED, assays, times, ANALYTES)
    tonnes_c = np.bincount(c.index, weights=volumes, minlength=len(c.assayed)) * np.where(
        np.isfinite(c.density_t_m3), c.density_t_m3, 2.0)
    graded = np.isfinite(c.grade).all(axis=1)
    fe_c = float(tonnes_c[graded] @ c.grade[graded, 0])
    tonnes, fe_t, assayed_t = 0.0, 0.0, 0.0
    rank = {"PROVISIONAL": 0, "FINAL": 1}
    for t, v in zip(times, volumes):
        if np.isnan(t):
            tonnes += v * 2.0
            continue
        hits = [a for a in assays if a.lot_id == "L" and a.window_start_ns <= t <= a.window_end_ns]
        best = max(hits, key=lambda a: (rank[a.status], a.recorded_ns, a.assay_id), default=None)
        d = best.bulk_density_t_m3 if best is not None and best.bulk_density_t_m3 > 0 else 2.0
        fe = best.analytes["Fe"] if best is not None else PLANNED["Fe"]
        tonnes += v * d
        fe_t += v * d * fe
        assayed_t += v * d if best is not None else 0.0
    assert float(tonnes_c.sum()) == pytest.approx(tonnes, rel=1e-12)
    assert fe_c == pytest.approx(fe_t, rel=1e-12)
    assert float(tonnes_c[c.assayed].sum()) == pytest.approx(assayed_t, rel=1e-12)
    # grade_at is the same classes, per cell
    grade, assayed, dens = grade_at("L", PLANNED, assays, times, ANALYTES)
    np.testing.assert_array_equal(grade, c.grade[c.index])
    np.testing.assert_array_equal(assayed, c.assayed[c.index])


def test_grade_at_planned_fallback_nan_times_and_missing_analytes():
    a = _assay("A", "L", 1.0, 2.0, 62.0, analytes={"Fe": 62.0}, density=0.0)
    other_lot = _assay("B", "M", 0.0, 10.0, 40.0)
    times = np.array([T0, T0 + H, T0 + int(1.5 * H), T0 + 2 * H, T0 + 2 * H + 1],
                     dtype=np.int64)
    grade, assayed, dens = grade_at("L", PLANNED, [a, other_lot], times, ANALYTES)
    assert assayed.tolist() == [False, True, True, True, False]  # window ends inclusive
    assert grade[:, 0].tolist() == [60.0, 62.0, 62.0, 62.0, 60.0]
    assert grade[1, 1] == PLANNED["SiO2"]  # the assay lacks SiO2: planned value
    assert np.all(np.isnan(dens))  # density 0 = unknown
    # float times with NaN (no material): NaN grade, not assayed
    ft = np.array([np.nan, float(T0 + int(1.5 * H))])
    grade, assayed, dens = grade_at("L", PLANNED, [a], ft, ANALYTES)
    assert np.all(np.isnan(grade[0])) and not assayed[0]
    assert grade[1, 0] == 62.0 and assayed[1]
    # a planned grade without an analyte gives NaN for it
    grade, _, _ = grade_at("L", {"Fe": 60.0}, [], np.array([T0]), ANALYTES)
    assert grade[0, 0] == 60.0 and np.all(np.isnan(grade[0, 1:]))
    with pytest.raises(ValueError):
        grade_at("L", PLANNED, [a], np.zeros((2, 2)), ANALYTES)
    assert grade_at("L", PLANNED, [a], np.zeros(0), ANALYTES)[0].shape == (0, 3)


def test_raise_deposit_fills_a_lower_band_only_where_the_bands_above_are_empty():
    g = GridGeometry(0.0, 0.0, 1.0, 3, 1)
    stack = LayerStack.empty(g, 0.0)
    stack = stack.open_deposit(DepositInfo(1, "P1", "A", 0))
    stack, _ = stack.raise_to(np.array([[1.0], [1.0], [1.0]]), 10)
    stack = stack.open_deposit(DepositInfo(2, "P2", "B", 100))
    stack, _ = stack.raise_to(np.array([[np.nan], [1.5], [np.nan]]), 110)  # P2 only in cell 1
    before = stack.total_volume_m3()
    new, raised = stack.raise_deposit(1, np.array([[1.4], [2.0], [np.nan]]), 50)
    # cell 0: band 2 empty -> band 1 grows to 1.4; cell 1: band 2 holds material -> untouched
    assert raised[:, 0].tolist() == [True, False, False]
    assert new.thickness(1)[:, 0].tolist() == pytest.approx([1.4, 1.0, 1.0])
    assert new.thickness(2)[:, 0].tolist() == pytest.approx([0.0, 0.5, 0.0])
    assert new.total_volume_m3() == pytest.approx(before + 0.4)
    # deposition time of cell 0's band 1: thickness-weighted mean of 10 (1.0 m) and 50 (0.4 m)
    assert new.deposition_time_ns(1)[0, 0] == pytest.approx((10 * 1.0 + 50 * 0.4) / 1.4)
    assert stack.thickness(1)[0, 0] == 1.0  # the old stack is unchanged
    surfaces = new.surfaces()
    assert np.all(np.diff(surfaces, axis=0) >= 0)  # still monotone


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_raise_deposits_in_one_call_equals_raising_them_one_by_one(seed):
    print(f"seed={seed}")
    rng = np.random.default_rng(seed)
    g = GridGeometry(0.0, 0.0, 1.0, 6, 5)
    stack = LayerStack.empty(g, 0.0)
    for k in range(1, 5):
        stack = stack.open_deposit(DepositInfo(k, f"P{k}", "A", 100 * k))
        level = stack.surface() + np.where(rng.random(g.shape) < 0.5, rng.random(g.shape), np.nan)
        stack, _ = stack.raise_to(level, 100 * k + 10)
    frozen = stack.surfaces()
    updates = []
    for k in rng.integers(1, 5, size=4):
        cells = rng.choice(g.nx * g.ny, size=12, replace=False)
        z = stack.surface().ravel()[cells] + rng.normal(0.3, 0.3, cells.size)
        updates.append((int(k), cells, z, 1000.0 + rng.random(cells.size) * 100))
    one_by_one, raised_each = stack, []
    for k, cells, z, t in updates:
        level = np.full(g.shape, np.nan)
        level.ravel()[cells] = z
        when = np.zeros(g.shape)
        when.ravel()[cells] = t
        one_by_one, raised = one_by_one.raise_deposit(k, level, when)
        raised_each.append(raised.ravel()[cells])
    batch, raised_batch = stack.raise_deposits(updates)
    assert any(r.any() for r in raised_batch) and not all(r.all() for r in raised_batch)
    for a, b in zip(raised_each, raised_batch):
        assert a.tolist() == b.tolist()
    assert np.array_equal(batch.surfaces(), one_by_one.surfaces())
    for k in range(1, 5):
        assert np.array_equal(batch.deposition_time_ns(k), one_by_one.deposition_time_ns(k),
                              equal_nan=True)
    assert np.array_equal(stack.surfaces(), frozen)   # the stack raised from is unchanged
    for k in range(1, 5):   # deposit_cells: the same figures as the full-grid accessors
        cells, thick, times = batch.deposit_cells(k)
        full = batch.thickness(k).ravel()
        assert cells.tolist() == np.flatnonzero(full > 0).tolist()
        assert np.array_equal(thick, full[cells])
        assert np.array_equal(times, batch.deposition_time_ns(k).ravel()[cells])
    with pytest.raises(ValueError):
        stack.raise_deposits([(1, np.array([g.nx * g.ny]), np.array([1.0]), 0.0)])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_removal_split_by_a_mask_is_the_clamp_of_each_part(seed):
    # one clamp of two cell sets, split by a mask, equals two clamps, one per set
    print("seed", seed)
    stack = _random_stack(seed)
    rng = np.random.default_rng(seed + 100)
    floor = np.where(rng.random(stack.geometry.shape) < 0.6,
                     stack.surface() - rng.random(stack.geometry.shape), np.inf)
    mask = rng.random(stack.geometry.shape) < 0.5
    whole_stack, whole = stack.clamp(floor)
    a_stack, a = stack.clamp(np.where(mask, floor, np.inf))
    b_stack, b = a_stack.clamp(np.where(mask, np.inf, floor))
    np.testing.assert_array_equal(whole_stack.surfaces(), b_stack.surfaces())
    for part, expect in ((whole.within(mask), a), (whole.within(~mask), b)):
        assert [d.index for d in part.deposits] == [d.index for d in expect.deposits]
        for got, ref in zip(part.deposits, expect.deposits):
            np.testing.assert_array_equal(got.ix, ref.ix)
            np.testing.assert_array_equal(got.iy, ref.iy)
            np.testing.assert_allclose(got.cell_volume_m3, ref.cell_volume_m3, rtol=1e-12)
            np.testing.assert_array_equal(got.deposition_time_ns, ref.deposition_time_ns)
            assert math.isclose(got.volume_m3, ref.volume_m3, rel_tol=1e-12)
    assert math.isclose(whole.within(mask).volume_m3 + whole.within(~mask).volume_m3,
                        whole.volume_m3, rel_tol=1e-12)


# --------------------------------------------------------------------------------------
# buried boundaries: a local quadratic fit
# --------------------------------------------------------------------------------------

def _quadratic_per_cell(z, mask, window):
    """Per masked cell, numpy's lstsq over the masked cells of its window (a Python loop)."""
    half, out = window // 2, z.copy()
    for ix, iy in zip(*np.nonzero(mask)):
        rows, values = [], []
        for dx in range(-half, half + 1):
            for dy in range(-half, half + 1):
                jx, jy = ix + dx, iy + dy
                if 0 <= jx < z.shape[0] and 0 <= jy < z.shape[1] and mask[jx, jy]:
                    rows.append([1.0, dx, dy, dx * dx, dx * dy, dy * dy])
                    values.append(z[jx, jy])
        a = np.array(rows).reshape(-1, 6)
        if np.linalg.matrix_rank(a) == 6:
            out[ix, iy] = np.linalg.lstsq(a, np.array(values), rcond=None)[0][0]
    return out


@pytest.mark.parametrize("seed, window, p_mask", [(1, 5, 0.8), (2, 7, 0.6), (3, 3, 0.9),
                                                  (4, 7, 0.2)])
def test_fit_local_quadratic_against_a_per_cell_least_squares(seed, window, p_mask):
    print(f"seed={seed}")
    rng = np.random.default_rng(seed)
    z = rng.normal(0.0, 1.0, (17, 13))
    mask = rng.random(z.shape) < p_mask
    got = fit_local_quadratic(z, mask, window)
    want = _quadratic_per_cell(z, mask, window)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)
    assert np.array_equal(got[~mask], z[~mask])           # unmasked cells are not touched
    assert not np.allclose(got[mask], z[mask])            # and the masked ones are fitted


def test_fit_local_quadratic_keeps_a_quadratic_and_cuts_the_noise():
    seed = 7
    print(f"seed={seed}")
    rng = np.random.default_rng(seed)
    x, y = np.meshgrid(np.arange(80.0), np.arange(60.0), indexing="ij")
    # a rounded crest along y on a tilted plane, in a disc that cuts windows short
    z = 3.0 + 0.02 * x - 0.01 * y - 0.004 * (x - 40.0) ** 2 + 0.0005 * (x - 40) * (y - 30)
    disc = (x - 40.0) ** 2 + (y - 30.0) ** 2 < 25.0 ** 2
    np.testing.assert_allclose(fit_local_quadratic(z, disc, 7)[disc], z[disc], atol=1e-9)
    noise = rng.normal(0.0, 0.01, z.shape)
    fitted = fit_local_quadratic(z + noise, disc, 7)
    inner = (x - 40.0) ** 2 + (y - 30.0) ** 2 < 20.0 ** 2   # full windows
    ratio = np.std((fitted - z)[inner]) / np.std(noise[inner])
    assert 0.22 < ratio < 0.32, ratio   # 0.274 for a full 7 x 7 window
    with pytest.raises(ValueError, match="odd"):
        fit_local_quadratic(z, disc, 4)
    with pytest.raises(ValueError, match="shape"):
        fit_local_quadratic(z, disc[:-1], 5)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_fit_boundaries_moves_material_between_the_two_deposits_only(seed):
    print(f"seed={seed}")
    stack = _random_stack(seed, nx=15, ny=12, n=4)
    # its random thicknesses make every buried top rough: the fit has work to do
    fitted = stack.fit_boundaries([2], 5)
    before, after = stack.surfaces(), fitted.surfaces()
    assert np.array_equal(after[[0, 1, 3, 4]], before[[0, 1, 3, 4]])  # only S2 moves
    assert np.all(np.diff(after, axis=0) >= 0)                          # still monotone
    moved = after[2] != before[2]
    assert moved.any()
    # only where both deposit 2 and deposit 3 had material
    assert np.all((before[2] > before[1])[moved] & (before[3] > before[2])[moved])
    assert fitted.total_volume_m3() == pytest.approx(stack.total_volume_m3(), rel=1e-12)
    assert (fitted.volume_m3(2) + fitted.volume_m3(3)
            == pytest.approx(stack.volume_m3(2) + stack.volume_m3(3), rel=1e-12))
    for k in (1, 2, 3, 4):   # every cell keeps each deposit's time where it keeps material
        keep = fitted.thickness(k) > 0
        np.testing.assert_array_equal(fitted.deposition_time_ns(k)[keep],
                                      stack.deposition_time_ns(k)[keep])
    # the fit, where it stays between its neighbours, is fit_local_quadratic's
    mask = (before[2] > before[1]) & (before[3] > before[2])
    free = fit_local_quadratic(before[2], mask, 5)
    inside = mask & (free > before[1]) & (free < before[3])
    np.testing.assert_allclose(after[2][inside], free[inside], rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match="top one"):
        stack.fit_boundaries([4])
    with pytest.raises(ValueError, match="odd"):
        stack.fit_boundaries([1], 6)
    with pytest.raises(ValueError, match="deposit index"):
        stack.fit_boundaries([0])


@pytest.mark.parametrize("seed", [3, 4])
def test_fit_top_above_takes_the_noise_out_of_a_thin_cut(seed):
    """A floor a few cell-noises under a tilted top: the volume above it measured on the
    noisy top is biased high (the positive part of the noise near the floor), on
    ``fit_top_above``'s fit much less.  Truth: the noise-free top."""
    print(f"seed={seed}")
    rng = np.random.default_rng(seed)
    geometry = GridGeometry(0.0, 0.0, 0.005, 64, 48)
    x, _ = cell_centre(geometry, *np.meshgrid(np.arange(64), np.arange(48), indexing="ij"))
    true_top = 0.05 + 0.05 * x                          # 0.25 mm of rise per cell
    floor = np.full(geometry.shape, np.nan)
    floor[:, 8:40] = 0.05 + 0.05 * 0.16                 # a level floor across the middle
    cut = np.isfinite(floor)
    area = geometry.cell_m ** 2
    truth = np.clip(true_top - floor, 0, None)[cut].sum() * area
    raw, fitted = [], []
    for _ in range(6):
        stack = LayerStack.empty(geometry, 0.0).open_deposit(DepositInfo(1, "P1", "L1", T0))
        stack, _ = stack.raise_to(true_top + rng.normal(0.0, 0.002, geometry.shape), T0 + H)
        after = stack.fit_top_above(floor, 7)
        raw.append(np.clip(stack.surface() - floor, 0, None)[cut].sum() * area / truth - 1)
        fitted.append(np.clip(after.surface() - floor, 0, None)[cut].sum() * area / truth - 1)
        changed = after.surface() != stack.surface()
        assert changed.any() and not changed[~cut].any()        # only under the cut
        assert np.all(after.surface()[changed] >= floor[changed])
        np.testing.assert_array_equal(after.deposition_time_ns(1), stack.deposition_time_ns(1))
        far = cut & (true_top < floor - 0.02)                   # 10 noise sds under the floor
        assert not changed[far].any()
        # on the cut's cells, the fit over the whole top (the method computes a block)
        whole = fit_local_quadratic(stack.surface(), np.ones(geometry.shape, bool), 7)
        np.testing.assert_allclose(after.surface()[changed],
                                   np.maximum(whole, floor)[changed], rtol=0, atol=1e-12)
    print(f"raw bias {np.mean(raw):+.4f}, fitted {np.mean(fitted):+.4f}")
    # the bias goes with the noise left: a 7 x 7 fit keeps 0.27 of it (raw 7 %, fitted 1.4 %)
    assert np.mean(raw) > 0.03
    assert abs(np.mean(fitted)) < np.mean(raw) / 3
    with pytest.raises(ValueError, match="odd"):
        stack.fit_top_above(floor, 6)
    with pytest.raises(ValueError, match="shape"):
        stack.fit_top_above(floor[:-1], 7)
