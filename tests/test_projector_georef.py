"""Tests of the projector's georeferencing (projector.georef): pose interpolation against
scipy's Rotation and Slerp, coverage and gaps, and scanner returns turned into site points
against the simulator's own scan geometry and a round trip from site points; every random
test prints its seed (shown by pytest on failure, or with ``-s``) and
``--seed N`` (``STOCKPILE_TEST_SEED=N``) reruns it with the base seed N.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from projector.georef import georeference, interpolate_poses, sensor_points
from projector.kinematics import quaternion_to_matrix
from projector_helpers import LOOK_DOWN, NS, T0_NS, make_rng


#: the random tests here draw from the run's seed (tests/seeding.py)
pytestmark = pytest.mark.seeded


def rotation_angle_between(q_a, q_b) -> np.ndarray:
    """Angle (rad) of the rotation taking q_a to q_b, via scipy (independent of ours)."""
    return (Rotation.from_quat(q_a).inv() * Rotation.from_quat(q_b)).magnitude()


# ------------------------------------------------------------------------ poses

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


# ----------------------------------------------------------------- georeference

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
