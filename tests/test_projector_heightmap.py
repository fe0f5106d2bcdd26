"""Tests of the projector's height map (projector.heightmap): rasterising points against a
brute-force loop, Kalman height fusion and its change gate (stacked layers, cuts, spikes),
volumes against closed-form integrals, centring heights, plane fits of what was seen, and
scans of a ridge through every step to its volume; every random test prints its seed (shown
by pytest on failure, or with ``-s``) and ``--seed N`` (``STOCKPILE_TEST_SEED=N``) reruns it with
the base seed N.
"""

from __future__ import annotations

import math
import statistics

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from projector.georef import georeference, interpolate_poses
from projector.grid import GridGeometry, cell_centres
from projector.elevation import centre_elevation, fill_holes, volume_above
from projector.heightmap import CellObservations, FuseStats, HeightMap, fuse, rasterize
from projector.profile import clean_profile
from projector.surface_fit import plane_fit_of_seen
from projector_helpers import LOOK_DOWN, NS, T0_NS, cast_profile, make_rng


#: the random tests here draw from the run's seed (tests/seeding.py)
pytestmark = pytest.mark.seeded


# -------------------------------------------------------------------- rasterize

def test_rasterize_matches_a_brute_force_loop():
    rng = make_rng(5)
    g = GridGeometry(-3.0, 10.0, 0.5, 12, 9)
    n = 3000
    pts = np.column_stack([rng.uniform(-4.0, 4.0, n), rng.uniform(9.0, 15.5, n),
                           rng.normal(20.0, 1.0, n)])
    pts[rng.random(n) < 0.02, rng.integers(0, 3)] = np.nan
    for k in range(2):                                       # sparse and dense paths
        sample = pts[: (200 if k == 0 else n)]
        obs = rasterize(g, sample)
        cells: dict[tuple[int, int], list[tuple[float, float, float]]] = {}
        for x, y, z in sample.tolist():
            if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
                continue
            ix, iy = math.floor((x + 3.0) / 0.5), math.floor((y - 10.0) / 0.5)
            if 0 <= ix < 12 and 0 <= iy < 9:
                cells.setdefault((ix, iy), []).append((x, y, z))
        assert len(obs) == len(cells)
        assert obs.points == sum(len(v) for v in cells.values())
        got = {(int(a), int(b)): i for i, (a, b) in enumerate(zip(obs.ix, obs.iy))}
        assert set(got) == set(cells)
        for key, members in cells.items():
            i = got[key]
            zs = [p[2] for p in members]
            assert obs.count[i] == len(zs)
            assert obs.z_mean_m[i] == pytest.approx(statistics.fmean(zs), abs=1e-12)
            want_var = statistics.variance(zs) if len(zs) > 1 else 0.0
            assert obs.z_var_m2[i] == pytest.approx(want_var, abs=1e-10)
            xc = -3.0 + (key[0] + 0.5) * 0.5
            yc = 10.0 + (key[1] + 0.5) * 0.5
            assert obs.x_offset_m[i] == pytest.approx(statistics.fmean(p[0] for p in members) - xc,
                                                      abs=1e-12)
            assert obs.y_offset_m[i] == pytest.approx(statistics.fmean(p[1] for p in members) - yc,
                                                      abs=1e-12)
    # (S, B, 3) input is flattened; bad shapes are refused
    assert rasterize(g, pts[:200].reshape(10, 20, 3)).points == rasterize(g, pts[:200]).points
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        rasterize(g, pts[:, :2])


def test_rasterize_variance_is_not_cancelled_by_large_heights():
    g = GridGeometry(0.0, 0.0, 1.0, 1, 1)
    z = 1.0e6 + np.array([0.0, 0.001, 0.002])
    obs = rasterize(g, np.column_stack([np.full(3, 0.5), np.full(3, 0.5), z]))
    assert obs.z_var_m2[0] == pytest.approx(1e-6, rel=1e-6)


# ----------------------------------------------------------------------- fusion

def flat_obs(rng, g, z_true, sd, max_count=5):
    """One noisy observation of every cell of a flat surface (points drawn per cell)."""
    n = g.nx * g.ny
    count = rng.integers(1, max_count + 1, n)
    # per-cell mean and sample variance of `count` Gaussian points, drawn point by point
    cell = np.repeat(np.arange(n), count)
    z = z_true + rng.normal(0.0, sd, cell.size)
    mean = np.bincount(cell, z) / count
    ss = np.bincount(cell, (z - mean[cell]) ** 2)
    var = np.where(count > 1, ss / np.maximum(count - 1, 1), 0.0)
    ix, iy = np.divmod(np.arange(n), g.ny)
    return CellObservations(ix, iy, mean, var, count.astype(np.int64)), count


def test_fuse_noise_on_a_flat_surface_neither_moves_nor_creates_material():
    rng = make_rng(6)
    g = GridGeometry(0.0, 0.0, 0.5, 20, 20)
    sd, z0 = 0.05, 2.0
    hm = HeightMap.empty(g)
    total = np.zeros(g.nx * g.ny)
    changes = 0
    for k in range(30):
        obs, count = flat_obs(rng, g, z0, sd)
        total += count
        hm, st = fuse(hm, obs, T0_NS + k * NS, sd, process_sd_m=0.0)
        changes += st.cells_changed_up + st.cells_changed_down
        if k == 0:
            assert st.cells_initialised == g.nx * g.ny
    err = hm.elevation.ravel() - z0
    # every cell within 6 sd of the mean of its points (Kalman weights are not exactly
    # 1/count, so allow a little more than the optimum sd / sqrt(n))
    assert np.max(np.abs(err) / (sd / np.sqrt(total))) < 6.0
    # no material created or removed: the mean error is noise-sized
    assert abs(err.mean()) < 4.0 * sd / math.sqrt(total.sum()) * 1.5
    vol = volume_above(hm.elevation, z0, g.cell_area_m2, fill="none")
    assert abs(vol) < 4.0 * 1.5 * sd / math.sqrt(total.sum()) * g.nx * g.ny * g.cell_area_m2
    # no change detected from noise alone, but for a rare false alarm: three agreeing
    # out-of-gate looks in a row at one of 400 cells over 30 looks (seeds 0-299: none in
    # 298 runs, one in 2, never two)
    assert changes <= 1


def test_fuse_first_observation_and_one_kalman_step_by_hand():
    g = GridGeometry(0.0, 0.0, 1.0, 2, 1)
    obs = CellObservations(np.array([0]), np.array([0]), np.array([1.0]), np.array([0.0]),
                           np.array([1]))
    hm0 = HeightMap.empty(g)
    hm1, st = fuse(hm0, obs, T0_NS, 0.1, process_sd_m=0.0)
    assert st == FuseStats(cells_initialised=1)
    assert np.isnan(hm0.elevation).all()                        # the input is untouched
    assert hm1.elevation[0, 0] == 1.0 and hm1.variance[0, 0] == pytest.approx(0.01)
    assert np.isnan(hm1.elevation[1, 0])
    assert hm1.grid["last_update_ns"][0, 0] == float(T0_NS)
    # second look: z = 1.1 with R = (0.1^2 + 0.02) / 2 = 0.015 -> K = 0.01 / 0.025 = 0.4
    obs2 = CellObservations(np.array([0]), np.array([0]), np.array([1.1]), np.array([0.02]),
                            np.array([2]))
    hm2, st2 = fuse(hm1, obs2, T0_NS + NS, 0.1, process_sd_m=0.0)
    assert st2.cells_updated == 1
    assert hm2.elevation[0, 0] == pytest.approx(1.0 + 0.4 * 0.1)
    assert hm2.variance[0, 0] == pytest.approx(0.6 * 0.01)
    assert hm1.elevation[0, 0] == 1.0


def test_fuse_in_place_updates_the_map_itself_with_the_same_result():
    rng = make_rng(61)
    g = GridGeometry(0.0, 0.0, 0.5, 12, 9)
    pure = HeightMap.empty(g)
    own = HeightMap.empty(g)
    for k in range(12):
        obs, _count = flat_obs(rng, g, 2.0 + (0.3 if k >= 6 else 0.0), 0.05)
        pure, st_pure = fuse(pure, obs, T0_NS + k * NS, 0.05, change_count=2)
        same, st_own = fuse(own, obs, T0_NS + k * NS, 0.05, change_count=2, inplace=True)
        assert same is own and st_own == st_pure
    assert st_pure.cells_observed > 0
    for name in own.grid.layers:
        assert np.array_equal(own.grid[name], pure.grid[name], equal_nan=True), name
    assert np.nanmean(own.elevation) > 2.2         # the 0.3 m rise was accepted


def _constant_obs(g, z, sd=0.05, count=4):
    n = g.nx * g.ny
    ix, iy = np.divmod(np.arange(n), g.ny)
    return CellObservations(ix, iy, np.full(n, float(z)), np.full(n, sd * sd),
                            np.full(n, count, dtype=np.int64))


def _settled(g, z0, sd, looks=10):
    hm = HeightMap.empty(g)
    for k in range(looks):
        hm, _ = fuse(hm, _constant_obs(g, z0, sd), T0_NS + k * NS, sd)
    return hm


@pytest.mark.parametrize("change_count", [1, 3, 5])
def test_fuse_accepts_a_stacked_layer_after_change_count_looks(change_count):
    g = GridGeometry(0.0, 0.0, 0.25, 6, 4)
    sd = 0.05
    hm = _settled(g, 2.0, sd)
    n = g.nx * g.ny
    for k in range(change_count):
        hm, st = fuse(hm, _constant_obs(g, 2.5, sd), T0_NS + (100 + k) * NS, sd,
                      change_count=change_count)
        if k < change_count - 1:
            assert st.cells_gated == n and st.cells_changed_up == 0
            np.testing.assert_allclose(hm.elevation, 2.0, atol=1e-9)   # not yet
            assert (hm.grid["pending_count"] == k + 1).all()
    assert st.cells_changed_up == n and st.cells_gated == 0
    np.testing.assert_allclose(hm.elevation, 2.5, atol=1e-9)
    assert (hm.grid["pending_count"] == 0).all()
    assert (hm.grid["last_update_ns"] == float(T0_NS + (100 + change_count - 1) * NS)).all()


def test_fuse_dates_an_accepted_change_from_its_first_sighting():
    g = GridGeometry(0.0, 0.0, 0.25, 4, 3)
    sd = 0.05
    hm = _settled(g, 2.0, sd)
    assert (hm.grid["observed_ns"] == hm.grid["last_update_ns"]).all()
    for k in range(3):
        hm, _st = fuse(hm, _constant_obs(g, 2.5, sd), T0_NS + (100 + k) * NS, sd, change_count=3)
        if k < 2:
            assert (hm.grid["pending_since_ns"] == float(T0_NS + 100 * NS)).all()
    np.testing.assert_allclose(hm.elevation, 2.5, atol=1e-9)
    # the layer was there from the first look; it was confirmed at the third
    assert (hm.grid["observed_ns"] == float(T0_NS + 100 * NS)).all()
    assert (hm.grid["last_update_ns"] == float(T0_NS + 102 * NS)).all()
    assert np.isnan(hm.grid["pending_since_ns"]).all()


def test_accept_rises_takes_held_rises_and_keeps_held_drops():
    from projector.heightmap import accept_rises

    g = GridGeometry(0.0, 0.0, 0.25, 4, 2)
    sd = 0.05
    hm = _settled(g, 2.0, sd)
    obs = _constant_obs(g, 2.6, sd)
    obs.z_mean_m[: g.ny] = 1.4          # the first row of cells sees a drop
    hm, st = fuse(hm, obs, T0_NS + 50 * NS, sd, change_count=3)
    assert st.cells_gated == g.nx * g.ny and st.cells_changed_up == 0
    out, accepted = accept_rises(hm)
    assert accepted.sum() == (g.nx - 1) * g.ny and not accepted[0].any()
    np.testing.assert_allclose(out.elevation[1:], 2.6, atol=1e-9)
    np.testing.assert_allclose(out.elevation[0], 2.0, atol=1e-9)     # a drop waits
    assert (out.grid["pending_count"][0] == 1).all() and (out.grid["pending_count"][1:] == 0).all()
    assert (out.grid["observed_ns"][1:] == float(T0_NS + 50 * NS)).all()
    np.testing.assert_allclose(hm.elevation, 2.0, atol=1e-9)          # the input is unchanged


def test_fuse_accepts_a_reclaim_cut():
    g = GridGeometry(0.0, 0.0, 0.25, 3, 3)
    sd = 0.05
    hm = _settled(g, 5.0, sd)
    for k in range(3):
        hm, st = fuse(hm, _constant_obs(g, 4.0, sd), T0_NS + (50 + k) * NS, sd)
    assert st.cells_changed_down == g.nx * g.ny and st.cells_changed_up == 0
    np.testing.assert_allclose(hm.elevation, 4.0, atol=1e-9)


def test_fuse_a_single_spike_is_not_accepted():
    g = GridGeometry(0.0, 0.0, 0.25, 5, 5)
    sd = 0.05
    hm = _settled(g, 2.0, sd)
    before = hm.elevation.copy()
    hm, st = fuse(hm, _constant_obs(g, 2.5, sd), T0_NS + 20 * NS, sd)
    assert st.cells_gated == g.nx * g.ny
    np.testing.assert_array_equal(hm.elevation, before)
    hm, st = fuse(hm, _constant_obs(g, 2.0, sd), T0_NS + 21 * NS, sd)
    assert st.cells_updated == g.nx * g.ny
    assert (hm.grid["pending_count"] == 0).all()              # the evidence is cleared
    # two more out-of-gate looks: not three in a row, so still no change
    for k in range(2):
        hm, st = fuse(hm, _constant_obs(g, 2.5, sd), T0_NS + (22 + k) * NS, sd)
        assert st.cells_changed_up == 0
    np.testing.assert_allclose(hm.elevation, 2.0, atol=1e-9)


def test_fuse_disagreeing_outliers_restart_the_evidence():
    g = GridGeometry(0.0, 0.0, 0.25, 2, 2)
    sd = 0.05
    hm = _settled(g, 2.0, sd)
    for k, z in enumerate([2.6, 1.4, 2.6, 1.4, 2.6]):
        hm, st = fuse(hm, _constant_obs(g, z, sd), T0_NS + (30 + k) * NS, sd)
        assert st.cells_changed_up == 0 and st.cells_changed_down == 0
        assert (hm.grid["pending_count"] == 1).all()
    np.testing.assert_allclose(hm.elevation, 2.0, atol=1e-9)


def test_fuse_validates():
    g = GridGeometry(0.0, 0.0, 1.0, 2, 2)
    hm = HeightMap.empty(g)
    dup = CellObservations(np.array([0, 0]), np.array([1, 1]), np.ones(2), np.zeros(2),
                           np.ones(2, dtype=np.int64))
    with pytest.raises(ValueError, match="one row per cell"):
        fuse(hm, dup, T0_NS, 0.05)
    out = CellObservations(np.array([2]), np.array([0]), np.ones(1), np.zeros(1),
                           np.ones(1, dtype=np.int64))
    with pytest.raises(ValueError, match="outside"):
        fuse(hm, out, T0_NS, 0.05)
    with pytest.raises(ValueError, match="shape"):
        CellObservations(np.array([0]), np.array([0, 1]), np.ones(1), np.zeros(1),
                         np.ones(1, dtype=np.int64))


# ----------------------------------------------------------------------- volume

def test_volume_of_a_plane_with_holes_and_an_unseen_margin():
    """A tilted slab over a rectangle, holes inside, never-seen margin around it."""
    g = GridGeometry(0.0, 0.0, 0.5, 40, 60)
    x, y = cell_centres(g)
    inside = (x > 3.0) & (x < 17.0) & (y > 2.0) & (y < 28.0)      # 28 x 52 cells
    z = np.where(inside, 1.0 + 0.2 * x + 0.05 * y, np.nan)
    # closed form: int over [3,17] x [2,28] of (1 + 0.2 x + 0.05 y) dx dy
    exact = (14 * 26) * 1.0 + 0.2 * (17**2 - 3**2) / 2 * 26 + 0.05 * (28**2 - 2**2) / 2 * 14
    assert volume_above(z, 0.0, g.cell_area_m2) == pytest.approx(exact, rel=1e-12)
    rng = make_rng(7)
    holey = z.copy()
    # holes off the footprint's edge cells (an edge hole has no seen cell beyond it to
    # interpolate from): single cells, and whole unseen cross-pile columns between beams
    inner = np.argwhere((x > 3.5) & (x < 16.5) & (y > 2.5) & (y < 27.5))
    pick = inner[rng.choice(len(inner), 150, replace=False)]
    holey[pick[:, 0], pick[:, 1]] = np.nan
    holey[10, 5:56] = np.nan
    holey[25, 5:56] = np.nan
    holey[6:35, 30] = np.nan
    linear = volume_above(holey, 0.0, g.cell_area_m2, fill="linear")
    assert linear == pytest.approx(exact, rel=1e-12)
    near = volume_above(holey, 0.0, g.cell_area_m2, fill="nearest")
    assert near == pytest.approx(exact, rel=2e-4)   # ties averaged: no one-sided bias
    none = volume_above(holey, 0.0, g.cell_area_m2, fill="none")
    assert none < exact * 0.95                      # holes as ground: an under-estimate
    filled = fill_holes(holey, method="linear")
    assert np.array_equal(np.isnan(filled), ~inside)  # the margin stays unseen
    # a limited gap: the 51-cell column holes along y are bracketed along x anyway
    np.testing.assert_allclose(fill_holes(holey, method="linear", max_gap_cells=2)[inside],
                               z[inside], rtol=1e-12)


def test_volume_of_a_cone_by_cell_centres():
    """A 35 deg cone sampled at cell centres against pi r^2 h / 3."""
    g = GridGeometry(-30.0, -30.0, 0.1, 600, 600)
    x, y = cell_centres(g)
    h, r = 10.0, 10.0 / math.tan(math.radians(35.0))
    z = np.maximum(0.0, h - np.hypot(x, y) * h / r)
    exact = math.pi * r * r * h / 3
    assert volume_above(z, 0.0, g.cell_area_m2) == pytest.approx(exact, rel=2e-4)
    # ground at 5 m: only the top (a cone of half the size) counts once clipped
    clipped = volume_above(z, 5.0, g.cell_area_m2, clip_below=True)
    assert clipped == pytest.approx(exact / 8, rel=2e-3)
    assert volume_above(z, 5.0, g.cell_area_m2) < clipped     # signed: ground cells < 0


def test_centre_elevation_moves_heights_to_the_cell_centres():
    rng = make_rng(8)
    g = GridGeometry(0.0, 0.0, 0.25, 30, 20)
    x, y = cell_centres(g)
    ox = rng.uniform(-0.125, 0.125, g.shape)
    oy = rng.uniform(-0.125, 0.125, g.shape)

    def plane(xx, yy):
        return 3.0 + 0.7 * xx - 0.3 * yy

    measured = plane(x + ox, y + oy)
    measured[4, 7] = np.nan                          # a hole
    centred = centre_elevation(measured, ox, oy, g.cell_m)
    ok = ~np.isnan(measured)
    # a plane: exact wherever the neighbours give the slope (everywhere here)
    np.testing.assert_allclose(centred[ok], plane(x, y)[ok], atol=1e-9)
    assert np.isnan(centred[4, 7])
    raw = np.nansum(measured - plane(x, y))
    assert abs(raw) > 1e-3                           # the uncorrected heights were off


def test_fuse_carries_the_measurement_position():
    g = GridGeometry(0.0, 0.0, 1.0, 1, 1)
    hm = HeightMap.empty(g)
    mk = lambda z, ox: CellObservations(np.array([0]), np.array([0]), np.array([z]),  # noqa: E731
                                        np.array([0.0]), np.array([1]), np.array([ox]),
                                        np.array([0.0]))
    hm, _ = fuse(hm, mk(1.0, 0.2), T0_NS, 0.1, process_sd_m=0.0)
    hm, _ = fuse(hm, mk(1.0, -0.2), T0_NS + 1, 0.1, process_sd_m=0.0)  # K = 1/2
    assert hm.grid["x_offset_m"][0, 0] == pytest.approx(0.0, abs=1e-12)
    assert hm.grid["y_offset_m"][0, 0] == 0.0


# ------------------------------------------------------------------- end to end

def test_scans_of_a_prism_to_volume_end_to_end():
    """LOOK_DOWN scans of a long triangular ridge -> clean -> georeference -> fuse -> m3."""
    rng = make_rng(9)
    half_w, height = 20.0, 10.0

    def ridge(xx):
        return np.maximum(0.0, height - np.abs(xx) * height / half_w)

    beams = np.radians(np.arange(-45.0, 45.0001, 0.5))
    profile = cast_profile(ridge, 1.5, 30.0, beams)
    ys = np.arange(-2.0, 42.0, 0.2)                 # along the ridge, past the grid's ends
    s = ys.size
    ranges = profile[None, :] + rng.normal(0.0, 0.02, (s, beams.size))
    quat = Rotation.from_matrix(LOOK_DOWN).as_quat()
    t_scan = T0_NS + np.arange(s) * (NS // 5)
    pose_t = T0_NS + np.arange(-1, s + 1) * (NS // 5) + 1000
    pose_tr = np.column_stack([np.full(pose_t.size, 1.5),
                               -2.0 + (pose_t - T0_NS) / (NS // 5) * 0.2,
                               np.full(pose_t.size, 30.0)])
    tr, q = interpolate_poses(t_scan, pose_t, pose_tr, np.tile(quat, (pose_t.size, 1)),
                              max_gap_ns=NS)
    pts = georeference(clean_profile(ranges), beams[0], beams[1] - beams[0], tr, q)
    g = GridGeometry(-24.0, 0.0, 0.5, 96, 80)        # y in [0, 40): the ridge's middle
    hm, st = fuse(HeightMap.empty(g), rasterize(g, pts), int(t_scan[-1]), 0.02)
    assert st.cells_initialised > 0.8 * g.nx * g.ny
    vol = volume_above(hm.centred_elevation(), 0.0, g.cell_area_m2, fill="linear")
    exact = half_w * height * 40.0                   # section area x length
    assert vol == pytest.approx(exact, rel=2e-3)


def test_plane_fit_of_seen_is_exact_on_a_plane_up_to_the_edge_of_what_was_seen():
    ix, iy = np.meshgrid(np.arange(30.0), np.arange(40.0), indexing="ij")
    plane = 0.3 * ix - 0.7 * iy + 5.0
    holey = plane.copy()
    holey[:, 25:] = np.nan          # never seen beyond a row (the window is one-sided there)
    holey[3, 3] = holey[10:12, 7] = np.nan
    fitted = plane_fit_of_seen(holey, 5)
    seen = np.isfinite(holey)
    np.testing.assert_array_equal(np.isfinite(fitted), seen)
    np.testing.assert_allclose(fitted[seen], plane[seen], atol=1e-9)
    # a local mean stands up the slope beside the last seen row: the reason for a plane
    rows = holey[:, 22:25]
    assert np.mean(rows, axis=1).mean() > plane[:, 24].mean() + 0.5


def test_plane_fit_of_seen_averages_noise_down_by_the_window_s_cell_count():
    seed = 20261126
    print("seed", seed)
    rng = np.random.default_rng(seed)
    ix, iy = np.meshgrid(np.arange(200.0), np.arange(200.0), indexing="ij")
    plane = 0.02 * ix + 0.05 * iy
    sd = 0.01
    noisy = plane + rng.normal(0.0, sd, plane.shape)
    fitted = plane_fit_of_seen(noisy, 5)
    inner = (slice(2, -2), slice(2, -2))
    # at the centre of a full window the plane's height has variance sd^2 / 25
    assert abs(np.std((fitted - plane)[inner]) / (sd / 5.0) - 1.0) < 0.05
    assert abs(np.mean((fitted - plane)[inner])) < 0.02 * sd


def test_plane_fit_of_seen_falls_back_to_the_mean_and_validates():
    line = np.full((9, 9), np.nan)
    line[4, :] = np.arange(9.0) ** 2          # one row: no plane through it
    fitted = plane_fit_of_seen(line, 3)
    expect = [np.mean(line[4, max(0, j - 1):j + 2]) for j in range(9)]
    np.testing.assert_allclose(fitted[4], expect)
    assert np.isnan(fitted[3]).all()
    np.testing.assert_array_equal(plane_fit_of_seen(line, 1), line)
    for bad in (0, 4):
        with pytest.raises(ValueError, match="odd"):
            plane_fit_of_seen(line, bad)
    with pytest.raises(ValueError, match="shape"):
        plane_fit_of_seen(np.zeros(5), 3)
