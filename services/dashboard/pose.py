"""The reclaimer geometry the dashboard draws: poses and joints, line strips, footprints.

The one place of the dashboard's geometry, so it can be pointed at shared reclaimer
kinematics without touching what is logged:

- :func:`quat_matrix`: rotation matrix of a quaternion
- :func:`wheel_from_scanner`: the wheel frame's site pose from the scanner's and its mount
- :func:`joints_from_wheel_pose`: (travel, slew, luff) from the wheel frame's pose
- :func:`machine_strips`: line strips of the machine at given joints
- :func:`cut_outline`: a cut's swept footprint at the bottom of its envelope
- :func:`scanner_pose_at`, :func:`scan_points`: the scanner's pose at a scan's time
  (interpolated between the latest poses) and the scan georeferenced with it

Frames and units as in docs/domain.md §2 and §3: site ENU, metres, radians, UTC ns;
quaternions ``(x, y, z, w)``; a reclaimer is a :class:`projector.envelope.Reclaimer`.
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from projector import georef
from schemas.times import NS_PER_S

#: a scanner pose of the ring interpolated only across gaps up to this, ns
MAX_POSE_GAP_NS = 10 * NS_PER_S


def quat_matrix(q) -> np.ndarray:
    """Rotation matrix (3, 3) of a quaternion ``(x, y, z, w)`` (normalised first)."""
    x, y, z, w = (float(v) for v in q)
    n = math.sqrt(x * x + y * y + z * z + w * w) or 1.0
    x, y, z, w = x / n, y / n, z / n, w / n
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def wheel_from_scanner(position, quaternion_xyzw, mount) -> tuple[np.ndarray, np.ndarray]:
    """The wheel frame's pose (centre, rotation) from the scanner's site pose and the
    declared mount ``(R_wheel_scanner, t_wheel_scanner)``: the inverse of
    ``p_scanner = c + R_wheel t_mount``, ``R_scanner = R_wheel R_mount``.

    Parameters
    ----------
    position : array_like, shape (3,)
        The scanner's position in the site frame, m.
    quaternion_xyzw : array_like, shape (4,)
        The scanner's orientation in the site frame.
    mount : tuple of ndarray
        ``(R (3, 3), t (3,) m)``: the scanner in the wheel frame.

    Returns
    -------
    centre : ndarray, shape (3,)
        The wheel frame's origin in the site frame, m.
    rotation : ndarray, shape (3, 3)
        ``R_site_wheel``.
    """
    r_site_scanner = quat_matrix(quaternion_xyzw)
    r_wheel_scanner, t_wheel_scanner = mount
    r_site_wheel = r_site_scanner @ np.asarray(r_wheel_scanner).T
    return np.asarray(position, float) - r_site_wheel @ np.asarray(t_wheel_scanner), r_site_wheel


def joints_from_wheel_pose(machine, centre, rotation: np.ndarray) -> tuple[float, float, float]:
    """(travel m, slew rad, luff rad) from the wheel frame's pose (docs/domain.md §3).

    The wheel frame's x axis is the boom's horizontal direction ``(sin slew, cos slew, 0)``.
    ``centre`` is the wheel frame's origin (3,) in m, ``rotation`` its ``R_site_wheel``.
    """
    c = np.asarray(centre, float)
    s = (c[2] - machine.rail_z_m - machine.pivot_height_m) / machine.l5_m
    luff = math.asin(min(1.0, max(-1.0, s)))
    rho = machine.l4_m + machine.l5_m * math.cos(luff)
    slew = math.atan2(rotation[0, 0], rotation[1, 0])
    travel = c[1] - rho * math.cos(slew)
    return travel, slew, luff


def machine_strips(machine, travel_m: float, slew_rad: float, luff_rad: float,
                   wheel_radius_m: float) -> list[np.ndarray]:
    """Line strips of a reclaimer: slew tower, pivot arm, boom, wheel (site frame, m).

    Returns four arrays of points (n, 3), m: tower and pivot arm (3), boom (2), the
    wheel's rim (33) and its spokes (5).
    """
    base = np.array([machine.rail_x_m, travel_m, machine.rail_z_m])
    top = base + [0.0, 0.0, machine.pivot_height_m]
    d = np.array([math.sin(slew_rad), math.cos(slew_rad), 0.0])
    pivot = top + machine.l4_m * d
    centre = pivot + machine.l5_m * (math.cos(luff_rad) * d + [0.0, 0.0, math.sin(luff_rad)])
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
    rho = machine.l4_m + machine.l5_m * math.cos(luff_rad)
    c_z = machine.rail_z_m + machine.pivot_height_m + machine.l5_m * math.sin(luff_rad)
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
