"""Tests of the simulated pile (sim.world): mass, geometry, layers, cut truth.

Small piles (about 40 m x 20 m at 0.5 m cells) keep the file fast. Random inputs come from
seeded generators; the seeds are printed (shown by pytest on failure or with -s).
"""

from __future__ import annotations

import copy
import json
import math

import numpy as np
import pytest

from sim.kinematics import FULL_SCALE, envelope_floor_z
from sim.world import ANALYTES, Grid, Pattern, World

H = 3_600 * 10**9  # one hour in ns
T0 = 1_700_000_000 * 10**9  # an arbitrary UTC epoch (ns)

LOT_GRADES = {  # three lots with clearly different grades (mass %)
    "A": {"Fe": 61.0, "SiO2": 3.5, "Al2O3": 1.6, "P": 0.070, "LOI": 4.5},
    "B": {"Fe": 56.5, "SiO2": 6.2, "Al2O3": 2.6, "P": 0.105, "LOI": 6.4},
    "C": {"Fe": 63.2, "SiO2": 2.8, "Al2O3": 1.2, "P": 0.055, "LOI": 3.6},
}
X_CENTRE = 55.0  # the pile's centre line: FULL_SCALE reaches it at luff ~ 0
MODES = ("quasistatic", "avalanche")


def small_grid(cell=0.5):
    # 40 m of crest travel (y 0..40) plus room for the conical ends and the flanks
    return Grid.covering(X_CENTRE - 20, X_CENTRE + 20, -14, 54, cell)


def build_chevron(mode, *, n_passes=6, tonnes=1_000.0, seed=None, repose=37.0,
                  grade_drift=0.0):
    """A small chevron pile: passes alternate direction, lots A, B, C in turn."""
    w = World(small_grid(), repose, deposition=mode)
    rng = None if seed is None else np.random.default_rng(seed)
    lots = list(LOT_GRADES)
    for i in range(n_passes):
        lot = lots[i % 3]
        base = LOT_GRADES[lot]
        t_start = T0 + i * 2 * H

        def grade_fn(t, base=base, t_start=t_start):
            f = 1.0 + grade_drift * (t - t_start) / H  # drifts along the pass
            return {k: v * f for k, v in base.items()}

        a, b = (0.0, 40.0) if i % 2 == 0 else (40.0, 0.0)
        kw = {} if rng is None else {"rng": rng, "jitter_m": 0.3, "rate_cv": 0.15}
        w.stack_pass(Pattern.CHEVRON, a, b, X_CENTRE, tonnes, t_start, t_start + H, 100 + i,
                     lot, grade_fn, 2.4 + 0.1 * (i % 3), **kw)
    return w


@pytest.fixture(scope="module", params=MODES)
def chevron(request):
    seed = 1234
    print(f"seed={seed} mode={request.param}")
    return build_chevron(request.param, seed=seed)


def cut_sequence(world, n, *, start_travel=-2.0, bench_z=None):
    """Joints of ``n`` successive cuts of one bench across the pile's end."""
    top = float(world.surface_z().max())
    cz = (top + 3.0) if bench_z is None else bench_z  # wheel centre height
    luff = math.asin((cz - FULL_SCALE.rail_z_m - FULL_SCALE.pivot_height_m) / FULL_SCALE.l5_m)
    step = FULL_SCALE.cut_depth_m
    return [(start_travel + j * step, luff, math.pi / 2 - 0.3, math.pi / 2 + 0.3)
            for j in range(n)]


# --------------------------------------------------------------------------------------
# grid
# --------------------------------------------------------------------------------------

def test_grid_index_and_centres():
    g = Grid(10.0, -5.0, 0.5, nx=8, ny=6, ground_z_m=1.0)
    X, Y = g.centres()
    assert X.shape == Y.shape == (6, 8)
    iy, ix = g.index_of(X, Y)
    assert np.array_equal(iy, np.repeat(np.arange(6)[:, None], 8, axis=1))
    assert np.array_equal(ix, np.repeat(np.arange(8)[None, :], 6, axis=0))
    assert g.centre_of(0, 0) == (10.25, -4.75)
    assert g.extent == (10.0, 14.0, -5.0, -2.0)
    assert not g.contains(9.99, -4.0) and g.contains(10.0, -5.0)
    with pytest.raises(ValueError):
        Grid(0, 0, 0.0, 5, 5)
    with pytest.raises(ValueError):
        Grid(0, 0, 1.0, 2, 5)


# --------------------------------------------------------------------------------------
# mass
# --------------------------------------------------------------------------------------

@pytest.mark.parametrize("mode", MODES)
def test_mass_conservation_stack_and_reclaim(mode):
    """tonnes stacked == tonnes in pile + tonnes reclaimed (sum of cut truths), < 1e-9."""
    seed = 7
    print(f"seed={seed}")
    w = build_chevron(mode, seed=seed, grade_drift=0.02)
    stacked = sum(r["tonnes"] for r in w.releases())
    assert stacked == pytest.approx(6_000.0, rel=1e-12)
    assert w.mass_balance()["lost_tonnes"] == 0.0 and w.border_contacts == 0
    assert abs(w.tonnes() - stacked) / stacked < 1e-9
    cuts = [w.reclaim_cut(FULL_SCALE, *j, T0 + 20 * H + k)
            for k, j in enumerate(cut_sequence(w, 6, bench_z=w.surface_z().max() + 1.0))]
    reclaimed = sum(c.tonnes for c in cuts)
    assert reclaimed > 100.0
    assert sum(c.slump_m3 for c in cuts) > 0  # the cut walls failed into the holes
    rel = abs(stacked - (w.tonnes() + reclaimed)) / stacked
    print(f"relative mass residual {rel:.2e}")
    assert rel < 1e-9
    # grade mass too: tonnes x grade stacked == pile + reclaimed, per analyte
    stacked_tg = sum(r["tonnes"] * np.array([r["grade"][a] for a in ANALYTES])
                     for r in w.releases())
    pile_tg = w.tonnes() * np.array([w.grade()[a] for a in ANALYTES])
    cut_tg = sum(c.tonnes * np.array([c.grade[a] for a in ANALYTES]) for c in cuts if c.tonnes)
    assert np.all(np.abs(stacked_tg - pile_tg - cut_tg) / stacked_tg < 1e-9)
    assert all(abs(v) < 1e-9 for v in w.grade_balance().values())


def test_material_leaving_the_grid_is_reported():
    g = Grid(0.0, 0.0, 0.5, nx=30, ny=30)
    w = World(g)
    w.deposit(1.0, 7.5, 300.0, T0, "d", "A", LOT_GRADES["A"])  # 1 m from the edge
    mb = w.mass_balance()
    assert mb["lost_tonnes"] > 0 and w.border_contacts == 1
    assert abs(mb["relative_residual"]) < 1e-12


# --------------------------------------------------------------------------------------
# geometry
# --------------------------------------------------------------------------------------

@pytest.mark.parametrize("repose", [37.0, 33.0])
@pytest.mark.parametrize("mode", MODES)
def test_chevron_repose_angle(mode, repose):
    w = build_chevron(mode, repose=repose, n_passes=4)
    est = w.repose_angle_deg()
    print(f"{mode}: repose {repose} -> estimated {est:.2f} deg")
    assert abs(est - repose) < 2.0
    # no column is steeper than repose (beyond the relaxation tolerance)
    assert not w.unstable_columns().any()
    # it is a chevron: one crest line near the centre, symmetric flanks
    z = w.thickness()
    crest_x = w.grid.x_centres[np.argmax(z, axis=1)]
    mid = (w.grid.y_centres > 5) & (w.grid.y_centres < 35)
    assert np.all(np.abs(crest_x[mid] - X_CENTRE) <= 1.0)


def test_windrow_and_cone_shell_patterns():
    g = Grid.covering(20, 90, -15, 55, 0.5)
    w = World(g)
    const = (lambda t: LOT_GRADES["A"])
    w.stack_pass(Pattern.WINDROW, 0, 40, 55.0, 900.0, T0, T0 + H, 1, "A", const, n_rows=3)
    z = w.thickness()[g.ny // 2]
    peaks = np.flatnonzero((z[1:-1] > z[:-2]) & (z[1:-1] >= z[2:]) & (z[1:-1] > 0.5)) + 1
    print("windrow ridges at x =", g.x_centres[peaks])
    assert len(peaks) == 3
    # a second layer offset by half a row fills the valleys
    spacing = float(np.diff(g.x_centres[peaks]).mean())
    w.stack_pass(Pattern.WINDROW, 40, 0, 55.0, 900.0, T0 + 2 * H, T0 + 3 * H, 2, "B",
                 lambda t: LOT_GRADES["B"], n_rows=2, row_spacing_m=spacing,
                 row_offset_m=0.0)
    valley_x = 0.5 * (g.x_centres[peaks[0]] + g.x_centres[peaks[1]])
    p = w.parcel_at(valley_x, 20.0, w.surface_z()[g.index_of(valley_x, 20.0)] - 1e-3)
    assert p is not None and p["deposit_id"] == 2
    # cone shell: cones at the stations
    w2 = World(g)
    w2.stack_pass(Pattern.CONE_SHELL, 0, 40, 55.0, 1200.0, T0, T0 + H, 1, "A", const,
                  n_cones=3)
    zc = w2.thickness()[:, g.index_of(55.0, 0.0)[1]]
    peaks_y = g.y_centres[np.flatnonzero((zc[1:-1] > zc[:-2]) & (zc[1:-1] >= zc[2:])) + 1]
    print("cone apexes at y =", peaks_y)
    assert len(peaks_y) == 3 and np.allclose(peaks_y, [0, 20, 40], atol=1.0)
    for world in (w, w2):
        assert abs(world.mass_balance()["relative_residual"]) < 1e-12
        assert not world.unstable_columns().any()


# --------------------------------------------------------------------------------------
# cuts
# --------------------------------------------------------------------------------------

def _removed_by_difference(before, after, area):
    """Cut truth recomputed from two parcel snapshots (per parcel differences)."""
    d = before["thickness"] - after["thickness"]  # (S, ny, nx) removed thickness
    assert d.min() >= -1e-12, "a cut added material"
    rho = before["density_t_m3"][:, None, None]
    mass = d * rho * area  # tonnes per parcel piece
    tonnes = float(mass.sum())
    grade = {a: float((mass * before["grade"][:, j]).sum() / tonnes)
             for j, a in enumerate(before["analytes"])}
    by_dep, by_lot = {}, {}
    for s in range(d.shape[0]):
        m = float(mass[s].sum())
        if m > 0:
            by_dep[before["deposit_id"][s]] = by_dep.get(before["deposit_id"][s], 0.0) + m
            by_lot[before["lot"][s]] = by_lot.get(before["lot"][s], 0.0) + m
    mean_t = float((mass * before["time_ns"]).sum() / tonnes)
    return tonnes, grade, by_dep, by_lot, mean_t


def test_cut_truth_equals_parcel_difference(chevron):
    w = copy.deepcopy(chevron)
    area = w.grid.cell_area_m2
    n_checked = 0
    for k, joints in enumerate(cut_sequence(w, 8, bench_z=w.surface_z().max() + 1.5)):
        before = w.parcels()
        truth = w.reclaim_cut(FULL_SCALE, *joints, T0 + 30 * H + k, relax=False)
        after = w.parcels()
        if truth.tonnes == 0:
            continue
        tonnes, grade, by_dep, by_lot, mean_t = _removed_by_difference(before, after, area)
        assert truth.tonnes == pytest.approx(tonnes, rel=1e-9)
        for a in ANALYTES:
            assert truth.grade[a] == pytest.approx(grade[a], rel=1e-9)
        assert truth.tonnes_by_deposit.keys() == by_dep.keys()
        for d in by_dep:
            assert truth.tonnes_by_deposit[d] == pytest.approx(by_dep[d], rel=1e-9)
        for lot in by_lot:
            assert truth.tonnes_by_lot[lot] == pytest.approx(by_lot[lot], rel=1e-9)
        assert truth.mean_deposition_time_ns == pytest.approx(mean_t, rel=1e-12)
        # several lots are mixed in a cut: its grade is not any single lot's
        assert len(truth.tonnes_by_lot) >= 2
        n_checked += 1
        w.settle()  # let the walls fail before the next cut, as reclaim_cut(relax=True) does
    assert n_checked >= 5


def test_cut_geometry_against_envelope_floor(chevron):
    w = copy.deepcopy(chevron)
    X, Y = w.grid.centres()
    ground = w.grid.ground_z_m
    for k, joints in enumerate(cut_sequence(w, 6, bench_z=w.surface_z().max() + 0.5)):
        tops0 = w.layer_surfaces()
        s0 = w.surface_z()
        truth = w.reclaim_cut(FULL_SCALE, *joints, T0 + 40 * H + k, relax=False)
        tops1 = w.layer_surfaces()
        floor = envelope_floor_z(FULL_SCALE, X, Y, *joints)
        inside = ~np.isnan(floor)
        assert np.array_equal(inside, truth.footprint)
        # outside the footprint nothing changed at all
        assert np.array_equal(tops0[:, ~inside], tops1[:, ~inside])
        # inside: every layer top is clipped at the floor, nothing below it was touched
        lim = np.maximum(floor[inside], ground)
        assert np.allclose(tops1[:, inside], np.minimum(tops0[:, inside], lim), atol=1e-9,
                           rtol=0)
        # no material left above the floor in the footprint
        s1 = w.surface_z()
        assert np.all(s1[inside] <= lim + 1e-9)
        # removed volume = volume of the old surface above the floor
        expect = float(np.maximum(s0[inside] - lim, 0).sum()) * w.grid.cell_area_m2
        assert truth.volume_m3 == pytest.approx(expect, rel=1e-9, abs=1e-9)
        w.settle()
    assert len(w.cuts) == 6 and sum(c.volume_m3 for c in w.cuts) > 50


def test_slump_after_cut_is_stable_and_not_part_of_the_cut(chevron):
    w = copy.deepcopy(chevron)
    joints = cut_sequence(w, 1, bench_z=w.surface_z().max() - 1.0)[0]
    w_norelax = copy.deepcopy(w)
    a = w.reclaim_cut(FULL_SCALE, *joints, T0 + 50 * H, relax=True)
    b = w_norelax.reclaim_cut(FULL_SCALE, *joints, T0 + 50 * H, relax=False)
    assert a.tonnes == b.tonnes and a.grade == b.grade  # slumped material is not in the cut
    assert a.slump_m3 > 0 and b.slump_m3 == 0
    assert not w.unstable_columns().any()
    assert w_norelax.unstable_columns().any()
    # the slump moved material (the surface changed outside the footprint), conserving it
    assert not np.array_equal(w.surface_z(), w_norelax.surface_z())
    assert w.tonnes() == pytest.approx(w_norelax.tonnes(), rel=1e-12)
    for lot, t in w_norelax.tonnes_by_lot().items():
        assert w.tonnes_by_lot()[lot] == pytest.approx(t, rel=1e-9)
    assert abs(w.mass_balance()["relative_residual"]) < 1e-9
    assert all(abs(v) < 1e-9 for v in w.grade_balance().values())
    assert not np.any(np.diff(w.layer_surfaces(), axis=0) < 0)


# --------------------------------------------------------------------------------------
# layers and attributes
# --------------------------------------------------------------------------------------

def test_layers_in_time_order(chevron):
    w = chevron
    tops = w.layer_surfaces()
    assert tops.shape == (6,) + w.grid.shape
    assert np.all(np.diff(tops, axis=0) >= 0)
    assert np.allclose(tops[-1], w.surface_z())
    p = w.parcels()
    thk, tim = p["thickness"], p["time_ns"]
    present = thk > 1e-9
    # later slot => later deposition time wherever both are present, in every column
    for s in range(thk.shape[0] - 1):
        for s2 in range(s + 1, thk.shape[0]):
            both = present[s] & present[s2]
            assert np.all(tim[s][both] < tim[s2][both])
    # the chevron layers nest: at the crest all six passes are present, newest on top
    iy, ix = w.grid.index_of(X_CENTRE, 20.0)
    assert present[:, iy, ix].all()
    x, y = w.grid.centre_of(iy, ix)
    zs = [0.5 * (a + b) for a, b in zip(np.r_[w.grid.ground_z_m, tops[:-1, iy, ix]],
                                          tops[:, iy, ix])]
    found = [w.parcel_at(x, y, z) for z in zs]
    assert [f["deposit_id"] for f in found] == [100 + i for i in range(6)]
    assert all(f1["time_ns"] < f2["time_ns"] for f1, f2 in zip(found, found[1:]))
    assert w.parcel_at(x, y, float(w.surface_z()[iy, ix]) + 0.01) is None
    assert w.parcel_at(x, y, w.grid.ground_z_m - 0.01) is None


def test_deposition_time_and_grade_follow_the_stacker():
    """The first pass runs y = 0 -> 40 with a drifting belt grade: material near y = 5 was
    laid earlier (and at a lower drifted Fe) than material near y = 35."""
    w = build_chevron("quasistatic", n_passes=1, grade_drift=0.05)
    z = w.surface_z()
    early = w.parcel_at(X_CENTRE, 5.0, z[w.grid.index_of(X_CENTRE, 5.0)] - 0.01)
    late = w.parcel_at(X_CENTRE, 35.0, z[w.grid.index_of(X_CENTRE, 35.0)] - 0.01)
    assert T0 <= early["time_ns"] < late["time_ns"] <= T0 + H
    assert early["grade"]["Fe"] < late["grade"]["Fe"]
    # the world's grade still balances the belt's tonnage-weighted grade exactly
    st = w.stacked_grade()
    for a in ANALYTES:
        assert w.grade()[a] == pytest.approx(st[a], rel=1e-12)


@pytest.mark.parametrize("mode", MODES)
def test_pile_grade_is_tonnage_weighted_lot_grade(mode):
    seed = 99
    print(f"seed={seed}")
    rng = np.random.default_rng(seed)
    tonnes = rng.uniform(500, 1500, size=6)
    w = World(small_grid(), deposition=mode)
    lots = ["A", "B", "C", "B", "A", "C"]
    for i, (lot, t) in enumerate(zip(lots, tonnes)):
        a, b = (0.0, 40.0) if i % 2 == 0 else (40.0, 0.0)
        w.stack_pass("chevron", a, b, X_CENTRE, float(t), T0 + i * 2 * H, T0 + i * 2 * H + H,
                     i, lot, lambda _t, g=LOT_GRADES[lot]: g, 2.5)
    per_lot = {lot: float(sum(t for l2, t in zip(lots, tonnes) if l2 == lot)) for lot in "ABC"}
    total = sum(per_lot.values())
    for a in ANALYTES:
        expect = sum(per_lot[lot] * LOT_GRADES[lot][a] for lot in "ABC") / total
        assert w.grade()[a] == pytest.approx(expect, rel=1e-12)
    for lot in "ABC":
        assert w.tonnes_by_lot()[lot] == pytest.approx(per_lot[lot], rel=1e-12)
    assert w.volume_m3() == pytest.approx(total / 2.5, rel=1e-12)


# --------------------------------------------------------------------------------------
# determinism, export, input checks
# --------------------------------------------------------------------------------------

def test_deterministic_given_the_generator():
    seed = 2024
    print(f"seed={seed}")
    a = build_chevron("quasistatic", n_passes=3, seed=seed)
    b = build_chevron("quasistatic", n_passes=3, seed=seed)
    c = build_chevron("quasistatic", n_passes=3, seed=seed + 1)
    assert np.array_equal(a.surface_z(), b.surface_z())
    assert not np.array_equal(a.surface_z(), c.surface_z())
    with pytest.raises(ValueError):  # randomness only through an explicit generator
        World(small_grid()).stack_pass("chevron", 0, 40, X_CENTRE, 100.0, T0, T0 + H, 1, "A",
                                       lambda t: LOT_GRADES["A"], jitter_m=0.5)


def test_summary_and_npz(tmp_path, chevron):
    w = copy.deepcopy(chevron)
    w.reclaim_cut(FULL_SCALE, *cut_sequence(w, 1, bench_z=w.surface_z().max())[0], T0 + 60 * H)
    s = w.summary()
    text = json.dumps(s)  # JSON-serialisable
    assert json.loads(text)["mass_balance"]["stacked_tonnes"] == pytest.approx(6_000.0)
    assert len(s["cuts"]) == 1 and len(s["slots"]) == 6 and len(s["passes"]) == 6
    assert [d["deposit_id"] for d in s["deposits"]] == [100 + i for i in range(6)]
    assert sum(d["tonnes"] for d in s["deposits"]) == pytest.approx(6_000.0)
    path = tmp_path / "truth.npz"
    w.to_npz(path)
    with np.load(path) as z:
        assert np.array_equal(z["surface_z"], w.surface_z())
        assert z["layer_tops"].shape == (6,) + w.grid.shape
        assert json.loads(str(z["summary_json"]))["tonnes"] == pytest.approx(w.tonnes())


def test_bad_input():
    w = World(small_grid())
    w.deposit(X_CENTRE, 20.0, 10.0, T0 + H, "d", "A", LOT_GRADES["A"])
    with pytest.raises(ValueError):  # new material cannot be older than what it lies on
        w.deposit(X_CENTRE, 20.0, 10.0, T0, "d", "A", LOT_GRADES["A"])
    with pytest.raises(ValueError):
        w.deposit(X_CENTRE, 20.0, 10.0, T0 + 2 * H, "d", "A", {"Fe": 60.0})
    with pytest.raises(ValueError):
        w.deposit(X_CENTRE, 20.0, -1.0, T0 + 2 * H, "d", "A", LOT_GRADES["A"])
    with pytest.raises(TypeError):
        w.deposit(X_CENTRE, 20.0, 1.0, float(T0 + 2 * H), "d", "A", LOT_GRADES["A"])
    with pytest.raises(ValueError):  # off the grid
        w.deposit(X_CENTRE + 100.0, 20.0, 1.0, T0 + 2 * H, "d", "A", LOT_GRADES["A"])
    with pytest.raises(ValueError):
        World(small_grid(), deposition="magic")
    assert w.tonnes() == pytest.approx(10.0) and w.n_slots == 1  # failed calls changed nothing


def test_released_material_does_not_tunnel_through_a_wall():
    """Material only reaches ground connected to the drop point: a 10 m wall (a column of
    unstable base, hand-made) stops it even where the repose cone would pass beyond."""
    g = Grid(0.0, 0.0, 0.5, nx=80, ny=80)
    w = World(g)
    wall_ix = 40  # x in [20, 20.5)
    w._surf[1:-1, 1 + wall_ix] = 10.0  # test-only: a wall that is not material
    w.deposit(16.0, 20.0, 1000.0, T0, "d", "A", LOT_GRADES["A"])
    z = w.thickness()
    beyond = z[:, wall_ix + 1:]
    near = z[:, :wall_ix]
    print("apex", float(near.max()), "at the wall", float(near[:, -1].max()))
    # the cone would reach 4 m past the wall; the material piled up against it instead
    assert near[:, -1].max() > 4.5 * math.tan(math.radians(37.0))
    assert float(beyond.max()) == 0.0
    assert w.mass_balance()["lost_tonnes"] == 0.0
    assert w.volume_m3() == pytest.approx(1000.0 / 2.4, rel=1e-12)


@pytest.mark.parametrize("mode", MODES)
def test_losses_at_the_border_are_accounted(mode):
    """A pile stacked too close to the grid's edge loses material across it (the outside is
    a ground-level sink), both while stacking and when over-steep edge columns fail; the
    balance still closes."""
    g = Grid.covering(X_CENTRE - 12, X_CENTRE + 12, -2.0, 26, 0.5)
    w = World(g, deposition=mode)
    for i in range(3):
        a, b = (0.5, 20.0) if i % 2 == 0 else (20.0, 0.5)
        w.stack_pass("chevron", a, b, X_CENTRE, 700.0, T0 + i * H, T0 + i * H + H // 2, i,
                     "ABC"[i], lambda t, lot="ABC"[i]: LOT_GRADES[lot])
    lost_stacking = w.mass_balance()["lost_tonnes"]
    assert lost_stacking > 0 and w.border_contacts > 0
    res = w.settle()  # edge columns steeper than repose toward the outside fail
    print(f"{mode}: lost stacking {lost_stacking:.2f} t, settle {res}")
    if mode == "quasistatic":  # the released cone was cut off at the edge
        assert res["lost_tonnes"] > 0
    top = float(w.surface_z().max())
    luff = math.asin((top - 4.0 - 11.0) / 50.0)
    w.reclaim_cut(FULL_SCALE, -1.5, luff, math.pi / 2 - 0.3, math.pi / 2 + 0.3, T0 + 9 * H)
    assert abs(w.mass_balance()["relative_residual"]) < 1e-9
    assert all(abs(v) < 1e-9 for v in w.grade_balance().values())
    assert not w.unstable_columns().any()


def test_envelope_floor_handles_a_slew_range_across_pi():
    """A range written as [3.0, 3.4] and as [3.0 - 2 pi, 3.4 - 2 pi] is the same footprint."""
    from sim.kinematics import FULL_SCALE, envelope_floor_z, wheel_centre

    x, y = np.meshgrid(np.linspace(-70, 70, 141), np.linspace(-70, 70, 141))
    a = envelope_floor_z(FULL_SCALE, x, y, 0.0, -0.1, 3.0, 3.4)
    b = envelope_floor_z(FULL_SCALE, x, y, 0.0, -0.1, 3.0 - 2 * np.pi, 3.4 - 2 * np.pi)
    assert np.isfinite(a).sum() > 50
    assert np.array_equal(np.isfinite(a), np.isfinite(b))
    # the wheel centre at slew pi (pointing to -y) is inside the footprint
    c = wheel_centre(FULL_SCALE, 0.0, np.pi, -0.1)
    assert np.isfinite(envelope_floor_z(FULL_SCALE, c[0], c[1], 0.0, -0.1, 3.0, 3.4))
