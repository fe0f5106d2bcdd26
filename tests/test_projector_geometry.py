"""Projector geometry: pose interpolation, georeferencing, profile cleaning, rasterising,
Kalman height fusion and volumes (projector.georef / profile / heightmap).

Every random test prints its seed (shown by pytest on failure, or with ``-s``); set
``PROJECTOR_GEOMETRY_SEED`` to rerun with another base seed.  Ground truths are computed
another way than the code under test: scipy's Rotation/Slerp, the simulator's own
scan-geometry functions, brute-force Python loops, bisection ray casting, closed-form
integrals.
"""

from __future__ import annotations

import math
import os
import statistics

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from projector.georef import (
    georeference, interpolate_poses, quaternion_to_matrix, sensor_points)
from projector.grid import GridGeometry, cell_centres
from projector.heightmap import (
    CellObservations, FuseStats, HeightMap, centre_elevation, fill_holes, fuse,
    plane_fit_of_seen, rasterize, volume_above)
from projector.profile import above_ground, clean_profile

BASE_SEED = int(os.environ.get("PROJECTOR_GEOMETRY_SEED", "20261107"))
T0_NS = 1_793_491_200_000_000_000
NS = 1_000_000_000
#: scanner x -> site -z, y -> site +x, z -> site -y (the simulator's LOOK_DOWN)
LOOK_DOWN = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, -1.0], [-1.0, 0.0, 0.0]])


def make_rng(offset: int = 0) -> np.random.Generator:
    seed = BASE_SEED + offset
    print(f"seed={seed}")
    return np.random.default_rng(seed)


def rotation_angle_between(q_a, q_b) -> np.ndarray:
    """Angle (rad) of the rotation taking q_a to q_b, via scipy (independent of ours)."""
    return (Rotation.from_quat(q_a).inv() * Rotation.from_quat(q_b)).magnitude()


# ----------------------------------------------------------------------------- poses

def test_slerp_matches_scipy_on_random_rotations():
    rng = make_rng(1)
    m = 30
    pose_t = T0_NS + np.cumsum(rng.integers(50_000_000, 150_000_000, m))
    rots = Rotation.random(m, random_state=int(rng.integers(2**31)))
    quats = rots.as_quat()
    quats[rng.random(m) < 0.5] *= -1.0             # either sign: the same rotation
    trans = rng.normal(0.0, 50.0, (m, 3))
    t = np.sort(rng.integers(pose_t[0], pose_t[-1], 500))
    tr, q = interpolate_poses(t, pose_t, trans, quats, max_gap_ns=NS)
    assert tr.shape == (500, 3) and q.shape == (500, 4)
    assert np.all(np.isfinite(q))
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-12)
    # scipy's Slerp works in float seconds; relative times keep full precision
    ts = (pose_t - pose_t[0]) / NS
    want = Slerp(ts, Rotation.from_quat(quats))((t - pose_t[0]) / NS)
    assert np.max(rotation_angle_between(q, want.as_quat())) < 1e-9
    for k in range(3):
        np.testing.assert_allclose(tr[:, k], np.interp(t - pose_t[0], pose_t - pose_t[0],
                                                       trans[:, k]), rtol=0, atol=1e-9)


@pytest.mark.parametrize("flip", [False, True], ids=["q", "-q"])
def test_slerp_known_rotation_and_sign(flip):
    """Halfway from identity to 90 deg about z is 45 deg about z, whatever the sign of q1."""
    q0 = np.array([0.0, 0.0, 0.0, 1.0])
    q1 = np.array([0.0, 0.0, math.sin(math.pi / 4), math.cos(math.pi / 4)])
    if flip:
        q1 = -q1
    pose_t = np.array([T0_NS, T0_NS + NS])
    tr, q = interpolate_poses(np.array([T0_NS + NS // 2, T0_NS + NS // 4]), pose_t,
                              np.zeros((2, 3)), np.stack([q0, q1]), max_gap_ns=NS)
    r = quaternion_to_matrix(q)
    c45, s45 = math.cos(math.pi / 4), math.sin(math.pi / 4)
    np.testing.assert_allclose(r[0], [[c45, -s45, 0], [s45, c45, 0], [0, 0, 1]], atol=1e-12)
    a = math.pi / 8   # a quarter of the way: 22.5 deg (the short way round, not -67.5)
    np.testing.assert_allclose(r[1], [[math.cos(a), -math.sin(a), 0],
                                      [math.sin(a), math.cos(a), 0], [0, 0, 1]], atol=1e-12)


def test_poses_nan_outside_coverage_and_across_gaps_exact_on_poses():
    pose_t = T0_NS + np.array([0, 100, 200, 5_000, 5_100]) * 1_000_000   # a 4.8 s gap
    trans = np.arange(15, dtype=float).reshape(5, 3)
    quats = Rotation.from_euler("z", np.array([0.0, 10, 20, 30, 40])[:, None],
                                degrees=True).as_quat()
    t = T0_NS + np.array([-1, 0, 50, 200, 201, 2_000, 4_999, 5_000, 5_050, 5_100,
                          5_100_000_001 // 1_000_000]) * 1_000_000
    t[-1] = pose_t[-1] + 1
    tr, q = interpolate_poses(t, pose_t, trans, quats, max_gap_ns=500_000_000)
    nan_rows = np.isnan(tr).any(axis=1)
    assert np.array_equal(nan_rows, np.isnan(q).any(axis=1))
    # before the first pose, inside the gap (3 times), after the last pose
    assert nan_rows.tolist() == [True, False, False, False, True, True, True, False, False,
                                 False, True]
    # exactly on a pose: that pose (also on both sides of the gap)
    for row, pose in ((1, 0), (3, 2), (7, 3), (9, 4)):
        np.testing.assert_array_equal(tr[row], trans[pose])
        assert rotation_angle_between(q[row], quats[pose]) < 1e-12
    np.testing.assert_allclose(tr[2], (trans[0] + trans[1]) / 2)
    assert abs(Rotation.from_quat(q[2]).as_euler("zyx", degrees=True)[0] - 5.0) < 1e-9
    np.testing.assert_allclose(tr[8], (trans[3] + trans[4]) / 2)
    # a single pose covers only its own time
    tr1, q1 = interpolate_poses(np.array([pose_t[0], pose_t[0] + 1]), pose_t[:1], trans[:1],
                                quats[:1], max_gap_ns=NS)
    assert np.isfinite(tr1[0]).all() and np.isnan(tr1[1]).all() and np.isnan(q1[1]).all()


def test_interpolate_poses_validates_inputs():
    pose_t = np.array([T0_NS, T0_NS + 10])
    good = dict(max_gap_ns=NS)
    q = np.tile([0.0, 0.0, 0.0, 1.0], (2, 1))
    with pytest.raises(ValueError, match="sorted"):
        interpolate_poses(np.array([T0_NS]), pose_t[::-1], np.zeros((2, 3)), q, **good)
    with pytest.raises(ValueError, match="shape"):
        interpolate_poses(np.array([T0_NS]), pose_t, np.zeros((3, 3)), q, **good)
    with pytest.raises(ValueError, match="shape"):
        interpolate_poses(np.array([T0_NS]), pose_t, np.zeros((2, 3)), q[:, :3], **good)
    with pytest.raises(ValueError, match="zero quaternion"):
        interpolate_poses(np.array([T0_NS]), pose_t, np.zeros((2, 3)), np.zeros((2, 4)), **good)
    with pytest.raises(ValueError, match="integer"):
        interpolate_poses(np.array([1.5]), pose_t, np.zeros((2, 3)), q, **good)


# ----------------------------------------------------------------------------- georeference

def test_sensor_points_laserscan_convention():
    pts = sensor_points(np.array([[1.0, 2.0, 3.0, np.nan]]), -math.pi / 2, math.pi / 2)
    assert pts.shape == (1, 4, 3)
    np.testing.assert_allclose(pts[0, :3], [[0, -1, 0], [2, 0, 0], [0, 3, 0]], atol=1e-15)
    assert np.isnan(pts[0, 3]).all()
    with pytest.raises(ValueError, match=r"\(S, B\)"):
        sensor_points(np.ones(5), 0.0, 0.1)


def test_georeference_matches_the_simulator_scan_geometry():
    """Same points as sim.scanner: position + R @ (range * direction)."""
    from sim.scanner import beam_angles_rad, beam_directions_scanner_frame, rotation_matrix

    rng = make_rng(2)
    fov, step = 100.0, 0.5
    dirs = beam_directions_scanner_frame(fov, step)                     # (B, 3)
    angles = beam_angles_rad(fov, step)
    s = 6
    rots = [LOOK_DOWN, *Rotation.random(s - 1, random_state=int(rng.integers(2**31))).as_matrix()]
    quats = Rotation.from_matrix(np.stack(rots)).as_quat()
    pos = rng.normal(0.0, 100.0, (s, 3))
    ranges = rng.uniform(1.0, 80.0, (s, dirs.shape[0]))
    want = np.stack([pos[k] + (ranges[k][:, None] * dirs) @ rotation_matrix(quats[k]).T
                     for k in range(s)])
    got = georeference(ranges, angles[0], angles[1] - angles[0], pos, quats)
    np.testing.assert_allclose(got, want, atol=1e-9)
    # the LOOK_DOWN scanner: beam 0 (-50 deg) goes down and toward -x, the middle one down
    assert got[0, 0, 0] < pos[0, 0] and got[0, 0, 2] < pos[0, 2]
    mid = dirs.shape[0] // 2
    np.testing.assert_allclose(got[0, mid], pos[0] + [0, 0, -ranges[0, mid]], atol=1e-9)


def test_georeference_round_trip_from_site_points():
    """Site points -> sensor frame (scipy, independently) -> ranges -> georeference back."""
    rng = make_rng(3)
    s, b = 8, 181
    angle_min, inc = math.radians(-90.0), math.radians(1.0)
    a = angle_min + inc * np.arange(b)
    rot = Rotation.random(s, random_state=int(rng.integers(2**31)))
    t = rng.uniform(-500, 500, (s, 3))
    mats = rot.as_matrix()
    # site points on the scan plane of each pose, along each beam, at random distances
    dist = rng.uniform(0.5, 60.0, (s, b))
    site = (t[:, None, :] + dist[..., None] * (np.cos(a)[None, :, None] * mats[:, None, :, 0]
                                               + np.sin(a)[None, :, None] * mats[:, None, :, 1]))
    # into the sensor frame with scipy's inverse rotation
    local = np.stack([rot[k].inv().apply(site[k] - t[k]) for k in range(s)])
    assert np.max(np.abs(local[..., 2])) < 1e-9                 # on the scan plane
    ranges = np.hypot(local[..., 0], local[..., 1])
    bearing = np.arctan2(local[..., 1], local[..., 0])
    np.testing.assert_allclose(bearing, np.broadcast_to(a, (s, b)), atol=1e-9)
    ranges[0, 5] = np.nan                                       # a dropout
    quats = rot.as_quat()
    quats[1] = np.nan                                           # a scan without a pose
    back = georeference(ranges, angle_min, inc, t, quats)
    assert back.shape == (s, b, 3)
    ok = np.ones((s, b), bool)
    ok[0, 5] = False
    ok[1] = False
    assert np.isnan(back[~ok]).all()
    np.testing.assert_allclose(back[ok], site[ok], atol=1e-8)


# ----------------------------------------------------------------------------- profiles

def cast_profile(surface, x0: float, z0: float, angles_rad: np.ndarray,
                 t_max: float = 200.0) -> np.ndarray:
    """Ranges from (x0, z0) along (sin a, -cos a) to the first crossing of z = surface(x).

    Dense march + bisection (a different method from the bench's closed form).
    """
    u, v = np.sin(angles_rad), np.cos(angles_rad)
    ts = np.linspace(0.0, t_max, 40_001)
    h = (z0 - ts[None, :] * v[:, None]) - surface(x0 + ts[None, :] * u[:, None])
    below = h <= 0
    first = np.argmax(below, axis=1)
    if not below.any(axis=1).all():
        raise AssertionError("a ray misses the surface")
    lo, hi = ts[first - 1], ts[first]
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        under = (z0 - mid * v) - surface(x0 + mid * u) <= 0
        hi = np.where(under, mid, hi)
        lo = np.where(under, lo, mid)
    return 0.5 * (lo + hi)


BEAMS = np.radians(np.arange(-50.0, 50.0001, 0.25))       # 401 beams


def smooth_pile(x):
    """A smooth pile (hyperbolic section, 35 deg flanks) on flat ground at z = 0."""
    m = math.tan(math.radians(35.0))
    return np.maximum(32.0 - np.sqrt(4.0 + (m * (x - 1.0)) ** 2), 0.0)


def sharp_pile(x):
    return np.maximum(17.4 - 0.564 * np.abs(x + 2.0), 0.0)


@pytest.mark.parametrize("surface", [smooth_pile, sharp_pile], ids=["smooth", "sharp crest"])
def test_clean_profile_keeps_a_noise_free_pile(surface):
    r = cast_profile(surface, 3.0, 45.0, BEAMS)[None, :]
    out = clean_profile(r)
    assert out.shape == r.shape
    assert np.isfinite(out).all(), np.flatnonzero(np.isnan(out))
    np.testing.assert_array_equal(out, r)
    # 3-median smoothing leaves the smooth flanks (monotone runs) as they are
    sm = clean_profile(r, smooth=True)
    changed = np.flatnonzero(sm[0] != r[0])
    assert changed.size <= 3                            # at most the crest and the toes


def test_clean_profile_keeps_a_noisy_smooth_pile_and_removes_spikes():
    rng = make_rng(4)
    base = cast_profile(smooth_pile, 3.0, 45.0, BEAMS)
    s = 200
    r = base[None, :] + rng.normal(0.0, 0.0145, (s, base.size))
    r[rng.random(r.shape) < 0.002] = np.nan               # dropouts
    out = clean_profile(r)
    lost = np.isfinite(r) & np.isnan(out)
    assert lost.mean() < 5e-4, lost.sum()                 # a smooth pile stays
    # plant isolated outliers (dust in front, multipath behind) away from dropouts, where
    # the surface is not seen edge-on: on a grazing flank the range changes by more than
    # a metre per beam, a -1 m error keeps the profile monotone and cannot be told from
    # the surface in range (its height error there is only ~0.1 m)
    spikes = np.zeros(r.shape, bool)
    seen_well = np.flatnonzero(np.convolve(np.abs(np.diff(base)) < 0.3, [1, 1], "valid") == 2) + 1
    seen_well = seen_well[(seen_well >= 5) & (seen_well < base.size - 5)]
    assert seen_well.size > 200
    cols = rng.choice(seen_well, s)
    spikes[np.arange(s), cols] = True
    spikes &= np.isfinite(r)
    spikes[:, 1:] &= np.isfinite(r[:, :-1])
    spikes[:, :-1] &= np.isfinite(r[:, 1:])
    planted = r.copy()
    planted[spikes] += np.where(rng.random(spikes.sum()) < 0.5, -1.0, 1.5)
    out = clean_profile(planted)
    assert np.isnan(out[spikes]).all()
    others = np.isfinite(planted) & ~spikes
    assert (np.isnan(out) & others).mean() < 1e-3
    np.testing.assert_array_equal(out[others & np.isfinite(out)],
                                  planted[others & np.isfinite(out)])


def test_clean_profile_removes_mixed_pixels_at_a_step():
    """A box (a stacker's bench, a wall) on the ground: phantom returns between the levels."""
    def box(x):
        return np.where(np.abs(x) < 8.0, 6.0, 0.0)

    r = cast_profile(box, 0.0, 30.0, BEAMS)
    # the edges: the last beam on the box top and the first on the ground (each side)
    top = np.abs(30.0 - r * np.cos(BEAMS) - 6.0) < 1e-6
    edges = np.flatnonzero(np.diff(top.astype(int)))     # step between edges[i] and +1
    assert edges.size == 2
    scans = np.tile(r, (4, 1))
    planted = np.zeros(scans.shape, bool)
    # scan 0: one phantom at the left edge; scan 1: two phantoms in a row at the right edge
    # (the beam hit the ground replaced), scan 2: one at each edge; scan 3: clean
    e0, e1 = edges
    for row, cols in ((0, [e0 + 1]), (1, [e1 + 1, e1 + 2]), (2, [e0 + 1, e1 + 1])):
        for c in cols:
            near = scans[row, e0] if c <= e0 + 2 else scans[row, e1]
            far = scans[row, c + 1] if c <= e0 + 2 else scans[row, e1 + 3]
            scans[row, c] = near + (0.35 + 0.1 * (c - cols[0])) * (far - near)
            planted[row, c] = True
    out = clean_profile(scans)
    assert np.isnan(out[planted]).all()
    assert np.isfinite(out[~planted]).all()               # the true edges survive


def test_clean_profile_keeps_a_grazing_surface():
    """A flank seen almost edge-on: big but steady range steps are not jumps."""
    beams = np.radians(np.arange(0.0, 47.0001, 0.25))
    r = cast_profile(lambda x: 30.0 - 0.7 * x, 0.0, 45.0, beams, t_max=400.0)[None, :]
    steps = np.abs(np.diff(r[0]))
    assert steps.max() > 2.0                               # far larger than jump_m
    out = clean_profile(r)
    assert np.isfinite(out).all()
    rng = make_rng(10)
    noisy = r + rng.normal(0.0, 0.0145, (50, r.shape[1]))
    assert np.isfinite(clean_profile(noisy)).all()


def _line_fit_by_polyfit(r: np.ndarray, half: int, jump_m: float) -> np.ndarray:
    """Brute force: per beam, np.polyfit of degree 1 through the kept returns within
    ``half`` beams that no step of more than ``jump_m`` separates from it."""
    out = r.copy()
    for s_i, row in enumerate(r):
        for b in range(row.size):
            if np.isnan(row[b]):
                continue
            ks = [0]
            for direction in (-1, 1):
                last = row[b]                  # the last kept return on this side
                for k in range(1, half + 1):
                    j = b + direction * k
                    if not 0 <= j < row.size:
                        break
                    if np.isnan(row[j]):       # a dropout: the window goes on past it
                        continue
                    if abs(row[j] - last) > jump_m:
                        break                  # a jump: nothing beyond it
                    ks.append(direction * k)
                    last = row[j]
            ks = sorted(ks)
            if len(ks) >= 2:
                out[s_i, b] = np.polyval(np.polyfit(ks, row[b + np.array(ks)], 1), 0.0)
    return out


@pytest.mark.parametrize("fit_beams", [3, 5])
def test_line_fit_of_profiles_matches_polyfit_and_never_crosses_a_jump(fit_beams):
    rng = make_rng(20 + fit_beams)
    print("seed offset", 20 + fit_beams)
    k = np.arange(200)
    # straight runs with steps of 2 m between them (jumps), noise, and dropouts
    r = 10.0 + 0.01 * k + 2.0 * (k >= 70) - 2.0 * (k >= 140)
    scans = np.tile(r, (6, 1)) + rng.normal(0.0, 0.005, (6, k.size))
    scans[rng.random(scans.shape) < 0.05] = np.nan
    out = clean_profile(scans, fit_beams=fit_beams, mad_k=50.0)   # no outlier rejection
    kept = clean_profile(scans, mad_k=50.0)
    # the level steps are the only steps over 0.3 m between kept returns, also where
    # a dropout lies on the step
    expected = _line_fit_by_polyfit(kept, fit_beams // 2, 0.3)
    np.testing.assert_allclose(out, expected, atol=1e-9)
    # no fitted return lies between the two levels (it would be a mixed pixel)
    level = np.abs(out - (10.0 + 0.01 * k + 2.0 * ((k >= 70) & (k < 140))))
    assert np.nanmax(level) < 0.05


def test_line_fit_of_profiles_keeps_a_straight_run_and_cuts_the_noise():
    rng = make_rng(30)
    k = np.arange(400)
    straight = np.tile(5.0 + 0.003 * k, (40, 1))
    np.testing.assert_allclose(clean_profile(straight, fit_beams=3), straight, atol=1e-12)
    noisy = straight + rng.normal(0.0, 0.0145, straight.shape)
    fitted = clean_profile(noisy, fit_beams=3)
    raw_sd = np.std((clean_profile(noisy) - straight)[:, 1:-1])
    fit_sd = np.std((fitted - straight)[:, 1:-1])
    assert fit_sd == pytest.approx(raw_sd / math.sqrt(3.0), rel=0.05)


def test_clean_profile_validates():
    with pytest.raises(ValueError, match=r"\(S, B\)"):
        clean_profile(np.ones(10))
    with pytest.raises(ValueError, match="odd"):
        clean_profile(np.ones((2, 10)), window=4)
    with pytest.raises(ValueError, match="fit_beams must be odd"):
        clean_profile(np.ones((2, 10)), fit_beams=2)
    r = np.ones((2, 10))
    out = clean_profile(r)
    assert out is not r and np.array_equal(out, r)


def test_above_ground():
    z = np.array([[0.0, 0.05, 0.2], [np.nan, -1.0, 3.0]])
    np.testing.assert_array_equal(above_ground(z, 0.0, 0.1),
                                  [[False, False, True], [False, False, True]])
    with pytest.raises(ValueError):
        above_ground(z, 0.0, -0.1)


# ----------------------------------------------------------------------------- rasterize

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


# ----------------------------------------------------------------------------- fusion

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
    assert changes == 0


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


# ----------------------------------------------------------------------------- volume

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
    inner = np.argwhere(inside)
    # holes: single cells, and whole unseen cross-pile columns between beams
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


# ----------------------------------------------------------------------------- end to end

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
