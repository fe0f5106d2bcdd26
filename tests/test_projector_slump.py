"""The angle of repose kernels: slides conserve mass and composition, the repose cone,
the repose estimate.  Each is checked against a brute-force or analytic ground truth."""

from __future__ import annotations

import math

import numpy as np
import pytest

from projector.grid import GridGeometry
from projector.layers import DepositInfo, LayerStack
from projector.slump import (estimate_repose_deg, pour_end_lead_m, pour_front_lead_m,
                                    pour_reach_m,
                                    relax_surface, repose_floor, slump)

CELL = 0.25
TAN37 = math.tan(math.radians(37.0))


def _chamfer_cone_brute(z: np.ndarray, cell_m: float, tan: float) -> np.ndarray:
    """max over every seen q of z(q) - tan * chamfer distance (O(N^2), a different method)."""
    nx, ny = z.shape
    ix, iy = np.nonzero(np.isfinite(z))
    out = np.full(z.shape, -np.inf)
    for px in range(nx):
        for py in range(ny):
            dx, dy = np.abs(ix - px), np.abs(iy - py)
            d = (np.maximum(dx, dy) + (math.sqrt(2) - 1) * np.minimum(dx, dy)) * cell_m
            out[px, py] = np.max(z[ix, iy] - tan * d)
    return out


def test_repose_floor_equals_the_brute_force_cone():
    seed = 11
    print("seed", seed)
    rng = np.random.default_rng(seed)
    z = np.full((23, 17), np.nan)
    picks = rng.choice(z.size, 12, replace=False)
    z.ravel()[picks] = rng.uniform(0, 5, 12)
    got = repose_floor(z, CELL, TAN37)
    want = _chamfer_cone_brute(z, CELL, TAN37)
    np.testing.assert_allclose(got, want, atol=1e-9)
    seen = np.isfinite(z)
    assert np.all(got[seen] >= z[seen])


def test_repose_floor_leaves_a_settled_pile_alone_and_lifts_a_hidden_flank():
    x = (np.arange(80) + 0.5) * CELL
    ridge = np.maximum(0.0, 8.0 - TAN37 * np.abs(x - 10.0))      # a prism at repose
    z = np.repeat(ridge[:, None], 20, axis=1)
    np.testing.assert_allclose(repose_floor(z, CELL, TAN37), z, atol=1e-9)
    hidden = z.copy()
    hidden[x > 10.5] = 1.0             # the far flank last seen when it was 1 m high
    lifted = repose_floor(hidden, CELL, TAN37)
    far = (x > 10.5) & (ridge > 1.0)
    np.testing.assert_allclose(lifted[far], z[far], atol=0.03)


def test_relax_surface_conserves_volume_and_leaves_no_slope_steeper_than_repose():
    base = np.zeros((40, 30))
    top = np.zeros((40, 30))
    top[:, :15] = 6.0                   # a vertical cliff 6 m high
    out = relax_surface(top, base, CELL, TAN37, tol_m=1e-6)
    assert out.sum() == pytest.approx(top.sum(), rel=1e-12)
    assert np.all(out >= base - 1e-12)
    steepest = max(np.abs(np.diff(out, axis=0)).max(), np.abs(np.diff(out, axis=1)).max())
    assert steepest <= TAN37 * CELL * 1.01
    # the cliff's top fell and its foot rose
    assert out[:, 0].max() < 6.0 and out[:, 29].min() >= 0.0 and out[:, 16].min() > 0.0


def _relax_brute(top, base, cell_m, tan, tol_m):
    """The same avalanche rule as relax_surface, column by column over the whole grid
    every sweep (no block tracking), in plain Python."""
    h = top.astype(float).copy()
    nx, ny = h.shape
    nbrs = [(dx, dy) for dx in (-1, 0, 1) for dy in (-1, 0, 1) if (dx, dy) != (0, 0)]
    while True:
        sends = []
        for i in range(nx):
            for j in range(ny):
                ex = {}
                for dx, dy in nbrs:
                    a, b = i + dx, j + dy
                    if 0 <= a < nx and 0 <= b < ny:
                        e = h[i, j] - h[a, b] - tan * cell_m * math.hypot(dx, dy)
                        if e > 0:
                            ex[(a, b)] = e
                mobile = h[i, j] - base[i, j]
                if ex and max(ex.values()) > tol_m and mobile > 0:
                    out = min(mobile, 0.5 * max(ex.values()))
                    total = sum(ex.values())
                    sends.append(((i, j), out, {c: out * e / total for c, e in ex.items()}))
        if not sends:
            return h
        for (i, j), out, to in sends:     # all columns at once (Jacobi)
            h[i, j] -= out
            for c, v in to.items():
                h[c] += v


@pytest.mark.parametrize("seed", [3, 4])
def test_relax_surface_equals_the_rule_applied_to_every_column(seed):
    """Following only the block that moved gives what sweeping every column gives."""
    print(f"seed={seed}")
    rng = np.random.default_rng(seed)
    base = rng.uniform(0.0, 0.2, (14, 17))
    top = base + rng.uniform(0.0, 0.3, base.shape)
    top[2:5, 3:6] += 2.0               # a tower that collapses
    top[10:12, 12:16] += 1.2           # and a second one apart from it
    tol = 0.01 * TAN37 * CELL
    got = relax_surface(top, base, CELL, TAN37)
    want = _relax_brute(top, base, CELL, TAN37, tol)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)
    assert got.sum() == pytest.approx(top.sum(), rel=1e-12)
    assert np.all(got >= base - 1e-12)


def test_relax_surface_rejects_bad_input():
    with pytest.raises(ValueError, match="shape"):
        relax_surface(np.zeros((3, 3)), np.zeros((3, 4)), CELL, TAN37)
    with pytest.raises(ValueError, match="tan_repose"):
        relax_surface(np.zeros((3, 3)), np.zeros((3, 3)), CELL, -1.0)
    with pytest.raises(ValueError, match="finite"):
        relax_surface(np.full((3, 3), np.nan), np.zeros((3, 3)), CELL, TAN37)
    with pytest.raises(ValueError, match="tol_m"):
        relax_surface(np.zeros((3, 3)), np.zeros((3, 3)), CELL, TAN37, tol_m=-1.0)


def test_slump_moves_material_with_its_composition():
    geometry = GridGeometry(0.0, 0.0, CELL, 40, 30)
    stack = LayerStack.empty(geometry, 0.0)
    for k, (level, t) in enumerate(((3.0, 100), (6.0, 200)), start=1):
        stack = stack.open_deposit(DepositInfo(k, f"P{k}", f"L{k}", t))
        surface = np.full(geometry.shape, np.nan)
        surface[:, :15] = level
        stack, _ = stack.raise_to(surface, t)
    volumes = [stack.volume_m3(k) for k in (1, 2)]
    settled, moved, raised = slump(stack, TAN37, tol_m=1e-6)
    assert settled.total_volume_m3() == pytest.approx(stack.total_volume_m3(), rel=1e-9)
    assert moved.volume_m3 > 1.0
    assert raised.sum() * geometry.cell_area_m2 == pytest.approx(moved.volume_m3, rel=1e-9)
    # each deposit keeps its volume: what slid off the top landed at the foot
    for k, before in zip((1, 2), volumes):
        assert settled.volume_m3(k) == pytest.approx(before, rel=1e-9)
    # the foot (beyond the old cliff) holds the slid material's deposits
    foot = settled.thickness(2)[:, 15:].sum() + settled.thickness(1)[:, 15:].sum()
    assert foot * geometry.cell_area_m2 == pytest.approx(moved.volume_m3, rel=1e-6)


def test_estimate_repose_deg_finds_a_noisy_cone():
    seed = 5
    print("seed", seed)
    rng = np.random.default_rng(seed)
    x = (np.arange(160) + 0.5) * CELL - 20.0
    xx, yy = np.meshgrid(x, x, indexing="ij")
    for deg in (33.0, 37.0):
        cone = np.maximum(0.0, 12.0 - math.tan(math.radians(deg)) * np.hypot(xx, yy))
        noisy = cone + rng.normal(0, 0.02, cone.shape)
        assert estimate_repose_deg(noisy, CELL) == pytest.approx(deg, abs=0.5)
    assert math.isnan(estimate_repose_deg(np.zeros((50, 50)), CELL))   # flat: no flank


def test_the_fold_measures_slopes_over_a_run_long_enough_for_its_noise():
    # a laboratory pile's plane flank at 37 deg on 5 mm cells, its fused heights 2 mm
    # noisy: over 4 cells a side the slopes read steep, |g + n|^2 = |g|^2 + |n|^2, by
    # about 0.2 deg; over the fold's baseline (run >= 8 point sds of 15 mm) by ~0.03 deg
    # (plus the estimator's own binning, a few hundredths)
    import projector.fold as F
    from projector import repose

    seed = 11
    print("seed", seed)
    rng = np.random.default_rng(seed)
    cell = 0.005
    x = (np.arange(200) + 0.5) * cell
    plane = np.broadcast_to(TAN37 * x[:, None], (200, 200)).copy()
    noisy = plane + rng.normal(0, 0.002, plane.shape)
    state = F.initial_state("P1")
    state.pile = F.PileInfo("P1", GridGeometry(0.0, 0.0, cell, 200, 200), 0.0, 0.02, 1.65)
    state.point_sd_m = 0.015
    b = repose.slope_baseline_cells(state)
    assert b == 12
    run = 2 * 4 * cell
    steep = math.degrees(math.atan(math.sqrt(TAN37 ** 2 + 2 * (2 * 0.002 ** 2) / run ** 2)))
    assert estimate_repose_deg(noisy, cell, baseline_cells=4) == pytest.approx(steep, abs=0.05)
    assert steep - 37.0 > 0.15
    long_run = estimate_repose_deg(noisy, cell, baseline_cells=b)
    assert long_run == pytest.approx(37.0, abs=0.1)
    assert abs(long_run - 37.0) < 0.5 * (steep - 37.0)
    # a yard's 25 cm cells and 5 cm point sd keep 4 cells (a 2 m run)
    state.pile = F.PileInfo("P1", GridGeometry(0.0, 0.0, 0.25, 10, 10), 0.0, 1.0, 1.65)
    state.point_sd_m = 0.05
    assert repose.slope_baseline_cells(state) == 4


def test_a_young_pile_s_slopes_are_measured_over_a_run_its_flanks_hold():
    # the first pass's ridge at a laboratory: 10 cm high at 37 deg, flanks 13 cm across
    # (27 cells of 5 mm), crest and toes rounded over 2 cm either side (as poured),
    # fused heights 2 mm noisy.  Runs of 2 x 12 cells mostly straddle the crest or a toe
    # and read the angle shallow; the fold keeps the half run within a quarter of a
    # flank's run (at tan 35 deg, 0.1 / 0.700 / 0.005 / 4: 6 or 7 cells)
    import projector.fold as F
    from projector import repose
    from projector.heightmap import HeightMap

    seed = 5
    print("seed", seed)
    rng = np.random.default_rng(seed)
    cell, n, soft = 0.005, 120, 0.02
    g = GridGeometry(0.0, 0.0, cell, n, n)
    x = (np.arange(n) + 0.5) * cell
    u = np.abs(x - x[n // 2])
    z = 0.1 - TAN37 * np.where(u > soft, u, u * u / (2 * soft) + soft / 2)
    toe = soft * TAN37
    z = np.where(z > toe, z, np.where(z > -toe, (z + toe) ** 2 / (4 * toe), 0.0))
    ridge = np.broadcast_to(z[:, None], (n, n)).copy()
    noisy = ridge + rng.normal(0, 0.002, ridge.shape)
    state = F.initial_state("P1")
    state.pile = F.PileInfo("P1", g, 0.0, 0.02, 1.65)
    state.point_sd_m = 0.015
    state.stack = LayerStack.empty(g, 0.0)
    state.height = HeightMap.empty(g)
    state.height.grid["elevation"][:] = noisy
    b = repose.slope_baseline_cells(state)
    assert b == int(noisy.max() / math.tan(math.radians(35.0)) / cell / 4) in (6, 7)
    young = estimate_repose_deg(noisy, cell, baseline_cells=b)
    long_run = estimate_repose_deg(noisy, cell, baseline_cells=12)
    assert young == pytest.approx(37.0, abs=1.0)
    assert long_run < 35.5 and abs(young - 37.0) < 0.5 * abs(long_run - 37.0)
    # once the pile stands 30 cm its flanks hold the long run again
    state.height.grid["elevation"][:] = 3.0 * noisy
    assert repose.slope_baseline_cells(state) == 12


def _poured_mean_distance_m(thickness_m: float, offset_m: float, tan_repose: float) -> float:
    """Pour a cone from a boom closing in along a line, step by step, and weigh the boom's
    distance by what each step added at a cell ``offset_m`` across the line that ends
    ``thickness_m`` higher: the process itself, not the closed form."""
    apex = thickness_m + tan_repose * offset_m         # the cone's level on the line
    level, moments, added = 0.0, 0.0, 0.0
    for s in np.linspace(10.0, 0.0, 400_001):          # the boom 10 m away, then closer
        cone = apex - tan_repose * math.hypot(offset_m, s)
        if cone > level:
            moments += s * (cone - level)
            added += cone - level
            level = cone
    assert math.isclose(level, thickness_m, rel_tol=1e-9)
    return moments / added


@pytest.mark.parametrize("thickness_m, offset_m", [(0.5, 0.0), (0.5, 3.0), (0.02, 0.1),
                                                   (2.0, 12.0)])
def test_pour_front_lead_is_the_poured_cone_s_mean_distance(thickness_m, offset_m):
    tan = math.tan(math.radians(37.0))
    got = pour_front_lead_m(np.array([[thickness_m]]), np.array([[offset_m]]), tan)
    assert got.shape == (1, 1)
    assert math.isclose(got[0, 0], _poured_mean_distance_m(thickness_m, offset_m, tan),
                        rel_tol=1e-3)


def test_pour_front_lead_on_the_line_is_half_the_reach_and_nothing_without_a_layer():
    tan = 0.75
    got = pour_front_lead_m(np.array([[0.3, 0.0, np.nan, -0.1]]), np.array([[0.0, 1.0, 1.0, 1.0]]),
                            tan)
    np.testing.assert_allclose(got, [[0.3 / tan / 2, 0.0, 0.0, 0.0]])
    # the sign of the offset does not matter; further down the flank, earlier
    both = pour_front_lead_m(np.full((1, 3), 0.3), np.array([[-2.0, 2.0, 4.0]]), tan)
    assert both[0, 0] == both[0, 1] < both[0, 2]


@pytest.mark.parametrize("thickness_m, offset_m", [(0.5, 0.0), (0.5, 3.0), (0.02, 0.1),
                                                   (2.0, 12.0)])
def test_pour_reach_is_where_the_cone_on_the_line_meets_the_layer_below(thickness_m, offset_m):
    # the boom s away along its line: the cone there stands thickness + tan * offset on
    # the line and reaches the cell while tan * (hypot(offset, s) - offset) < thickness;
    # the bisection finds the s where it stops
    tan = math.tan(math.radians(37.0))
    lo, hi = 0.0, 100.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if tan * (math.hypot(offset_m, mid) - offset_m) < thickness_m:
            lo = mid
        else:
            hi = mid
    got = pour_reach_m(np.array([[thickness_m, 0.0]]), np.array([[offset_m, offset_m]]), tan)
    assert math.isclose(got[0, 0], lo, rel_tol=1e-9)
    assert got[0, 1] == 0.0                                # no layer, no reach
    assert pour_reach_m(np.array([[thickness_m]]), np.array([[-offset_m]]), tan)[0, 0] == got[0, 0]


def test_pour_front_lead_rejects_bad_input():
    with pytest.raises(ValueError, match="differ in shape"):
        pour_front_lead_m(np.zeros((2, 3)), np.zeros((3, 2)), 0.7)
    with pytest.raises(ValueError, match="2-D"):
        pour_front_lead_m(np.zeros(3), np.zeros(3), 0.7)
    with pytest.raises(ValueError, match="tan_repose"):
        pour_front_lead_m(np.zeros((2, 2)), np.zeros((2, 2)), 0.0)


def test_pour_front_lead_under_a_thin_layer_far_down_a_flank_is_two_thirds_of_the_reach():
    # D << offset: the closed form cancels there (D r - x^2 asinh(D / x) ~ D^3 / 3x);
    # the front arrives D = sqrt(2 h x) away and the cell fills like a parabola's chord
    tan = 0.75
    thickness = np.array([[1e-320, 1e-12, 1e-7, 1e-4]])
    offset = np.full(thickness.shape, 50.0)
    with np.errstate(over="raise", divide="raise", invalid="raise"):
        got = pour_front_lead_m(thickness, offset, tan)
    reach = np.sqrt((thickness / tan) ** 2 + 2 * (thickness / tan) * offset)
    np.testing.assert_allclose(got, 2 * reach / 3, rtol=1e-4)
    assert np.all(np.isfinite(got)) and np.all(got > 0)


def _poured_end_travel_m(thickness_m: float, offset_m: float, beyond_m: float,
                         tan_repose: float) -> float:
    """Pour from a boom closing in along its line that stops ``beyond_m`` short of a cell
    (the cell lies past the end of its run), step by step, and weigh the travel the boom
    still had to go by what each step added at the cell, which ends ``thickness_m``
    higher: the process itself, not the closed form."""
    apex = thickness_m + tan_repose * math.hypot(offset_m, beyond_m)
    level, moments, added = 0.0, 0.0, 0.0
    for s in np.linspace(10.0, beyond_m, 400_001):
        cone = apex - tan_repose * math.hypot(offset_m, s)
        if cone > level:
            moments += (s - beyond_m) * (cone - level)
            added += cone - level
            level = cone
    assert math.isclose(level, thickness_m, rel_tol=1e-9)
    return moments / added


@pytest.mark.parametrize("thickness_m, offset_m, beyond_m", [
    (0.03, 0.0, 0.02), (0.03, 0.1, 0.05), (0.5, 3.0, 1.0), (2.0, 12.0, 0.5), (0.5, 0.0, 4.0)])
def test_pour_end_lead_is_the_travel_left_while_the_cone_fills_a_cell_past_the_end(
        thickness_m, offset_m, beyond_m):
    got = pour_end_lead_m(np.array([[thickness_m]]), np.array([[offset_m]]),
                          np.array([[beyond_m]]), TAN37)
    assert got.shape == (1, 1)
    assert math.isclose(got[0, 0], _poured_end_travel_m(thickness_m, offset_m, beyond_m, TAN37),
                        rel_tol=1e-3)


def test_pour_end_lead_at_the_end_is_the_front_lead_and_past_it_shorter_down_a_flank():
    thickness = np.full((1, 4), 0.3)
    offset = np.array([[0.0, 1.0, 2.0, -2.0]])
    at_end = pour_end_lead_m(thickness, offset, np.zeros((1, 4)), TAN37)
    np.testing.assert_array_equal(at_end, pour_front_lead_m(thickness, offset, TAN37))
    past = pour_end_lead_m(thickness, offset, np.full((1, 4), 0.5), TAN37)
    # on the line the cone's front is a straight slope: the same lead wherever the boom
    # stops; beside it the cell past the end gets only the cone's last stretch
    assert past[0, 0] == pytest.approx(at_end[0, 0], rel=1e-9)
    assert np.all(past[0, 1:] < at_end[0, 1:]) and past[0, 2] == past[0, 3]
    # no layer, no lead; thin layers stay finite
    np.testing.assert_array_equal(
        pour_end_lead_m(np.array([[0.0, np.nan, -1.0]]), np.ones((1, 3)), np.ones((1, 3)),
                        TAN37), np.zeros((1, 3)))
    thin = pour_end_lead_m(np.array([[1e-12, 1e-7]]), np.full((1, 2), 0.1),
                           np.full((1, 2), 0.05), TAN37)
    assert np.all(np.isfinite(thin)) and np.all(thin >= 0) and np.all(thin < 1e-5)


def test_pour_end_lead_rejects_bad_input():
    with pytest.raises(ValueError, match="differ in shape"):
        pour_end_lead_m(np.zeros((2, 2)), np.zeros((2, 2)), np.zeros((2, 3)), 0.7)
    with pytest.raises(ValueError, match="beyond_m must be >= 0"):
        pour_end_lead_m(np.zeros((1, 1)), np.zeros((1, 1)), np.full((1, 1), -0.1), 0.7)


def test_a_pass_s_material_is_dated_earlier_only_toward_and_past_the_end_of_its_run():
    """Along the run a crossing-attributed rise keeps the crossing; within the cone's
    reach of the run's end the front's lead counts in proportion, in full at the end, and
    past the end the travel the boom still had to go (slump.pour_end_lead_m)."""
    import projector.fold as F
    from projector import attribution, crossings

    g = GridGeometry(0.0, 0.0, 0.01, 60, 200)              # 0.6 m x 2 m, 1 cm cells
    state = F.initial_state(F.FoldConfig(pile_id="P1", repose_deg=37.0))
    state.pile = F.PileInfo("P1", g, 0.0, 0.02, 1.65)
    x = (np.arange(g.nx) + 0.5) * g.cell_m
    ridge = np.clip(0.2 - TAN37 * np.abs(x - 0.305), 0.0, None)   # crest on cell 30
    stack = LayerStack.empty(g, 0.0).open_deposit(DepositInfo(1, "P", "L", 0))
    stack, _ = stack.raise_to(np.repeat(ridge[:, None], g.ny, axis=1), 0)
    state.stack = stack
    s_ns = 1_000_000_000
    record = F.PassRecord("P", "L", "stk", 0, 1, ended_ns=100 * s_ns, start_y_m=0.2,
                          end_y_m=1.2)                      # 1 m in 100 s: 1 cm/s
    rows = np.array([50, 100, 110, 115, 119, 125, 150])     # y = 0.505 ... 1.505 m
    ix = np.full(rows.shape, 30)                            # the crest
    ix_flank = np.full(rows.shape, 45)                      # 0.15 m down the flank
    thickness = np.full(rows.shape, 0.03)
    tan = TAN37
    for cols in (ix, ix_flank):
        cells = cols * g.ny + rows
        crossing = crossings.crossing_ns(record, (rows + 0.5) * g.cell_m, 200 * s_ns, None)
        got = attribution.crossing_dates(state, record, cells, thickness, crossing, None)
        y = (rows + 0.5) * g.cell_m
        offset = np.abs((cols - 30) * g.cell_m)[None, :]
        reach = pour_reach_m(thickness[None, :], offset, tan)[0]
        front = pour_front_lead_m(thickness[None, :], offset, tan)[0]
        ahead = 1.2 - y
        mid = ahead >= reach
        assert mid.any() and (~mid).any()
        np.testing.assert_array_equal(got[mid], crossing[mid])
        near = ~mid & (ahead > 0)
        np.testing.assert_allclose((crossing - got)[near] / s_ns,
                                   (front * (1 - ahead / reach) / 0.01)[near], rtol=1e-9)
        past = ahead <= 0
        assert np.all(crossing[past] == 100 * s_ns)
        end = pour_end_lead_m(thickness[None, :], offset, np.clip(-ahead, 0, None)[None, :],
                              tan)[0]
        np.testing.assert_allclose((crossing - got)[past] / s_ns, (end / 0.01)[past], rtol=1e-9)
    # never before the pass started
    early = attribution.crossing_dates(state, record, np.array([30 * g.ny + 150]), np.array([5.0]),
                              np.array([1.0 * s_ns]), None)
    assert early[0] == 0.0
