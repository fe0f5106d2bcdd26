"""Tests of the material the projector finds in a pile: voxel volumes and weighted sums of a
layer stack (projector.voxels) against brute-force voxel overlaps and Monte Carlo points,
and lot grades from assays (projector.grades: superseding, precedence, planned fallback)
against per-cell loops; random inputs come from seeded generators whose seeds are printed
(shown by pytest on failure or with -s).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from projector.grades import AssayRecord, effective_assays, grade_at, grade_classes
from projector.grid import GridGeometry
from projector.layers import LayerStack
from projector.voxels import ClassWeights, integrate
from projector_helpers import H, T0
from projector_helpers import random_stack as _random_stack


# --------------------------------------------------------------------------------------
# voxels
# --------------------------------------------------------------------------------------

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
