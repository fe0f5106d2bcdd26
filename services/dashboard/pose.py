"""The reclaimer geometry the dashboard draws: poses and joints, line strips, footprints.

The kinematics are the shared reclaimer kinematics of :mod:`projector.kinematics`
(re-exported here for the dashboard's modules: :func:`wheel_from_scanner`,
:func:`joints_from_wheel_pose`); this module draws with them:

- :func:`quat_matrix`: rotation matrix of a quaternion, the identity for an unset one
- :func:`machine_strips`: line strips of the machine at given joints
- :func:`cut_outline`: a cut's swept footprint at the bottom of its envelope
- :func:`scanner_pose_at`, :func:`scan_points`: the scanner's pose at a scan's time
  (interpolated between the latest poses) and the scan georeferenced with it

Frames and units as in docs/domain.md §2 and §3: site ENU, metres, radians, UTC ns;
quaternions ``(x, y, z, w)``; a reclaimer is a :class:`projector.kinematics.Reclaimer`.
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from projector import georef
from projector.kinematics import (boom_height_m, boom_radius_m, joints_from_wheel_pose,
                                  pivot_position, quaternion_to_matrix, wheel_centre,
                                  wheel_from_scanner)
from schemas.times import NS_PER_S

__all__ = ["quat_matrix", "wheel_from_scanner", "joints_from_wheel_pose", "machine_strips",
           "cut_outline", "scanner_pose_at", "scan_points", "MAX_POSE_GAP_NS"]

#: a scanner pose of the ring interpolated only across gaps up to this, ns
MAX_POSE_GAP_NS = 10 * NS_PER_S


def quat_matrix(q) -> np.ndarray:
    """Rotation matrix (3, 3) of a quaternion ``(x, y, z, w)``; the identity for an unset
    (all-zero) quaternion, such as a machine declared without a scanner mount."""
    q = np.asarray([float(v) for v in q])
    if not np.any(q):
        return np.eye(3)
    return quaternion_to_matrix(q)


def machine_strips(machine, travel_m: float, slew_rad: float, luff_rad: float,
                   wheel_radius_m: float) -> list[np.ndarray]:
    """Line strips of a reclaimer: slew tower, pivot arm, boom, wheel (site frame, m).

    Returns four arrays of points (n, 3), m: tower and pivot arm (3), boom (2), the
    wheel's rim (33) and its spokes (5).
    """
    base = np.array([machine.rail_x_m, travel_m, machine.rail_z_m])
    top = base + [0.0, 0.0, machine.pivot_height_m]
    d = np.array([math.sin(slew_rad), math.cos(slew_rad), 0.0])
    pivot = pivot_position(machine, travel_m, slew_rad)
    centre = wheel_centre(machine, travel_m, slew_rad, luff_rad)
    a = np.linspace(0.0, 2 * math.pi, 33)
    up = np.array([0.0, 0.0, 1.0])
    wheel = centre + wheel_radius_m * (np.cos(a)[:, None] * d + np.sin(a)[:, None] * up)
    spokes = np.array([centre + wheel_radius_m * d, centre - wheel_radius_m * d, centre,
                       centre + wheel_radius_m * up, centre - wheel_radius_m * up])
    return [np.array([base, top, pivot]), np.array([pivot, centre]), wheel, spokes]


def cut_outline(machine, travel_m: float, luff_rad: float, slew_start_rad: float,
                slew_end_rad: float, n: int = 24) -> np.ndarray:
    """Closed outline of a cut's swept footprint at the envelope's bottom (site frame, m).

    Returns the outline's points (2 n + 1, 3), m: the outer arc, the inner arc back, and
    the first point again.
    """
    rho = float(boom_radius_m(machine, luff_rad))
    c_z = float(boom_height_m(machine, luff_rad))
    hw = machine.half_width_m
    lo, hi = sorted((slew_start_rad, slew_end_rad))
    if hi - lo >= 2 * math.pi:
        lo, hi = 0.0, 2 * math.pi
    a = np.linspace(lo, hi, n)
    z = c_z - machine.cutting_radius_m
    out = [(machine.rail_x_m + r * np.sin(a), travel_m + r * np.cos(a))
           for r in (rho + hw, max(rho - hw, 0.0))]
    xs = np.concatenate([out[0][0], out[1][0][::-1], out[0][0][:1]])
    ys = np.concatenate([out[0][1], out[1][1][::-1], out[0][1][:1]])
    return np.column_stack([xs, ys, np.full(xs.size, z)])


def scanner_pose_at(t_ns: int, poses: Sequence[tuple]) -> tuple[np.ndarray, np.ndarray]:
    """The scanner's site pose at ``t_ns`` from its latest poses.

    Parameters
    ----------
    t_ns : int
        The scan's time, UTC ns.
    poses : sequence of (int, ndarray (3,), tuple (4,))
        ``(time ns, position m, quaternion xyzw)``, in any order (at least one).

    Returns
    -------
    position : ndarray, shape (1, 3)
        m; the nearest pose's outside the poses' span, NaN across a gap longer than
        :data:`MAX_POSE_GAP_NS` (:func:`projector.georef.interpolate_poses`).
    quaternion : ndarray, shape (1, 4)
    """
    pt = np.array([p[0] for p in poses], np.int64)
    order = np.argsort(pt, kind="stable")
    pt = pt[order]
    xyz = np.array([poses[i][1] for i in order])
    q = np.array([poses[i][2] for i in order])
    if t_ns <= pt[0]:
        return xyz[:1], q[:1]
    if t_ns >= pt[-1]:
        return xyz[-1:], q[-1:]
    return georef.interpolate_poses(np.array([t_ns]), pt, xyz, q, max_gap_ns=MAX_POSE_GAP_NS)


def scan_points(ranges: np.ndarray, start_angle_rad: float, end_angle_rad: float,
                position: np.ndarray, quaternion: np.ndarray) -> np.ndarray:
    """A scan's finite points in the site frame (n, 3), m.

    ``ranges`` (m, at least two) run evenly from ``start_angle_rad`` to ``end_angle_rad``;
    ``position`` (1, 3) and ``quaternion`` (1, 4) are the scanner's pose
    (:func:`scanner_pose_at`).
    """
    inc = (end_angle_rad - start_angle_rad) / (ranges.size - 1)
    pts = georef.georeference(ranges[None, :], start_angle_rad, inc, position,
                              quaternion).reshape(-1, 3)
    return pts[np.isfinite(pts).all(axis=1)]
