"""Scanner poses at scan times, and 2-D laser scans turned into site-frame points.

Conventions
-----------
- Site frame: ENU metres (docs/domain.md §2): x across the pile, y along the rail, z up.
- A pose of a child frame (the scanner) in a parent frame (the site) is a translation
  ``t`` (metres) and a unit quaternion ``q`` in Foxglove order ``(x, y, z, w)``; a point
  maps as ``p_parent = R(q) @ p_child + t``.  ``q`` and ``-q`` are the same rotation.
- Scans follow the Foxglove ``LaserScan`` / ROS convention (the one the simulator's
  LMS200 uses, ``sim/scanner.py``): the scan plane is the sensor's x-y plane;
  beam ``b`` has bearing ``a_b = angle_min + b * angle_increment`` (radians, counter-
  clockwise about the sensor's +z axis, 0 = +x) and direction ``(cos a_b, sin a_b, 0)``.
  A downward-looking scanner sweeping across the pile has ``R = [[0, 1, 0], [0, 0, -1],
  [-1, 0, 0]]`` (sensor x -> site -z, y -> site +x, z -> site -y).
- A NaN range means "no return" (no hit, dropout, error code); it stays NaN.
- Times are int64 UTC nanoseconds.

All functions are pure and vectorised over scans and beams; no I/O.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from projector.kinematics import quaternion_to_matrix

__all__ = ["interpolate_poses", "sensor_points", "georeference"]


def _as_quaternions(q, name: str, n: int | None = None) -> np.ndarray:
    q = np.asarray(q, dtype=np.float64)
    if q.ndim != 2 or q.shape[1] != 4 or (n is not None and q.shape[0] != n):
        want = f"({n}, 4)" if n is not None else "(M, 4)"
        raise ValueError(f"{name} must have shape {want} (x, y, z, w), got {q.shape}")
    return q


def _integer_times(t_ns, pose_t_ns) -> tuple[np.ndarray, np.ndarray]:
    """Query and pose times as 1-D int64 arrays (ValueError otherwise, or without poses)."""
    t = np.asarray(t_ns)
    pt = np.asarray(pose_t_ns)
    if t.ndim != 1 or pt.ndim != 1:
        raise ValueError(f"t_ns and pose_t_ns must be 1-D, got {t.shape} and {pt.shape}")
    if not (np.issubdtype(t.dtype, np.integer) or t.size == 0) \
            or not (np.issubdtype(pt.dtype, np.integer) or pt.size == 0):
        raise ValueError("t_ns and pose_t_ns must be integer nanoseconds (int64)")
    if pt.shape[0] < 1:
        raise ValueError("need at least one pose")
    return t.astype(np.int64), pt.astype(np.int64)


def _checked_poses(pt: np.ndarray, translations_m, quaternions_xyzw
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Finite translations (M, 3) and unit quaternions (M, 4) of poses at sorted times ``pt``."""
    m = pt.shape[0]
    tr = np.asarray(translations_m, dtype=np.float64)
    if tr.shape != (m, 3):
        raise ValueError(f"translations_m must have shape ({m}, 3), got {tr.shape}")
    if not np.isfinite(tr).all():
        raise ValueError("translations_m must be finite")
    q = _as_quaternions(quaternions_xyzw, "quaternions_xyzw", m)
    norm = np.linalg.norm(q, axis=-1)
    if not np.isfinite(norm).all():
        raise ValueError("quaternions_xyzw must be finite")
    if np.any(~(norm > 1e-12)):
        raise ValueError("quaternions_xyzw contains a zero quaternion")
    if np.any(np.diff(pt) < 0):
        raise ValueError("pose_t_ns must be sorted (non-decreasing)")
    return tr, q / norm[:, None]


def _brackets(t: np.ndarray, pt: np.ndarray, max_gap_ns: int):
    """Where each query time falls among the pose times.

    Returns ``exact`` (bool (N,): on a pose), ``at`` (that pose's index, one per exact
    query), ``inner`` (bool (N,): strictly between two poses at most ``max_gap_ns``
    apart), ``a``, ``b`` (the bracketing poses' indices, one per inner query) and ``s``
    (the fraction of the bracket elapsed, float (n_inner, 1)).
    """
    m = pt.shape[0]
    i1 = np.searchsorted(pt, t, side="left")          # first pose at or after t
    i1c = np.minimum(i1, m - 1)
    exact = (i1 < m) & (pt[i1c] == t)
    i0 = i1 - 1
    inner = ~exact & (i0 >= 0) & (i1 < m)
    i0c = np.clip(i0, 0, m - 1)
    gap = pt[i1c] - pt[i0c]                            # int64, no float rounding
    inner &= gap <= max_gap_ns
    a, b = i0c[inner], i1c[inner]
    s = ((t[inner] - pt[a]).astype(np.float64) / gap[inner].astype(np.float64))[:, None]
    return exact, i1c[exact], inner, a, b, s


def _slerp(q0: np.ndarray, q1: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Slerp from unit quaternions ``q0`` to ``q1`` (rows) by fractions ``s`` (n, 1).

    scipy's :class:`~scipy.spatial.transform.Slerp` formula,
    ``r0 * exp(s * log(r0^-1 r1))``, pair by pair: the rotation vector of ``r0^-1 r1`` has
    an angle of at most pi, so the interpolation takes the short way round whatever the
    signs of ``q0`` and ``q1``.
    """
    r0 = Rotation.from_quat(q0)
    rel = (r0.inv() * Rotation.from_quat(q1)).as_rotvec()
    return (r0 * Rotation.from_rotvec(s * rel)).as_quat()


def interpolate_poses(t_ns, pose_t_ns, translations_m, quaternions_xyzw, *,
                      max_gap_ns: int) -> tuple[np.ndarray, np.ndarray]:
    """Poses at query times: linear in translation, slerp in rotation.

    Parameters
    ----------
    t_ns : array_like of int, shape (N,)
        Query times (UTC ns, int64), in any order.
    pose_t_ns : array_like of int, shape (M,), M >= 1
        Pose times (UTC ns, int64), non-decreasing.
    translations_m : array_like, shape (M, 3)
        Pose translations (m), finite.
    quaternions_xyzw : array_like, shape (M, 4)
        Pose rotations, (x, y, z, w), finite and non-zero (normalised here).
    max_gap_ns : int
        Keyword-only.  A query strictly between two poses more than ``max_gap_ns``
        apart is not interpolated (NaN), e.g. across a localiser outage.

    Returns
    -------
    translations_m : ndarray, shape (N, 3)
    quaternions_xyzw : ndarray, shape (N, 4)
        Unit quaternions.  Rows are NaN for times before the first pose, after the last
        pose, or inside a bracket wider than ``max_gap_ns``.  A time equal to a pose's
        time returns that pose (the first of equal-time poses) whatever the gaps.

    Notes
    -----
    The rotation is the shortest-arc slerp (:func:`_slerp`, scipy's ``Slerp`` formula):
    ``q`` and ``-q`` are the same rotation, and the interpolation never takes the long way
    round.  Vectorised over all queries.

    Raises
    ------
    ValueError
        On mismatched shapes, unsorted pose times, non-finite poses, a zero quaternion or
        a negative ``max_gap_ns``.
    """
    t, pt = _integer_times(t_ns, pose_t_ns)
    tr, q = _checked_poses(pt, translations_m, quaternions_xyzw)
    if max_gap_ns < 0:
        raise ValueError(f"max_gap_ns must be >= 0, got {max_gap_ns}")
    n = t.shape[0]
    out_t = np.full((n, 3), np.nan)
    out_q = np.full((n, 4), np.nan)
    if n == 0:
        return out_t, out_q
    exact, at, inner, a, b, s = _brackets(t, pt, max_gap_ns)
    out_t[exact] = tr[at]
    out_q[exact] = q[at]
    out_t[inner] = tr[a] + s * (tr[b] - tr[a])
    out_q[inner] = _slerp(q[a], q[b], s)
    return out_t, out_q


def _check_ranges(ranges_m) -> np.ndarray:
    r = np.asarray(ranges_m, dtype=np.float64)
    if r.ndim != 2:
        raise ValueError(f"ranges_m must have shape (S, B) (scans, beams), got {r.shape}")
    return r


def _beam_angles(n_beams: int, angle_min_rad: float, angle_increment_rad: float) -> np.ndarray:
    if not (np.isfinite(angle_min_rad) and np.isfinite(angle_increment_rad)):
        raise ValueError("angle_min_rad and angle_increment_rad must be finite")
    return angle_min_rad + angle_increment_rad * np.arange(n_beams, dtype=np.float64)


def sensor_points(ranges_m, angle_min_rad: float, angle_increment_rad: float) -> np.ndarray:
    """Scan returns as points in the sensor frame (LaserScan convention).

    Parameters
    ----------
    ranges_m : array_like, shape (S, B)
        Ranges (m) of S scans of B beams; NaN = no return.
    angle_min_rad, angle_increment_rad : float
        Bearing of beam 0 and the step between beams (rad).

    Returns
    -------
    ndarray, shape (S, B, 3)
        ``r_b * (cos a_b, sin a_b, 0)`` (m); NaN ranges give NaN points.
    """
    r = _check_ranges(ranges_m)
    a = _beam_angles(r.shape[1], angle_min_rad, angle_increment_rad)
    out = np.empty(r.shape + (3,))
    out[..., 0] = r * np.cos(a)
    out[..., 1] = r * np.sin(a)
    out[..., 2] = np.where(np.isnan(r), np.nan, 0.0)
    return out


def georeference(ranges_m, angle_min_rad: float, angle_increment_rad: float,
                 translations_m, quaternions_xyzw) -> np.ndarray:
    """Scan returns as points in the parent (site) frame.

    ``p_site = R(q_s) @ (r_sb * (cos a_b, sin a_b, 0)) + t_s`` for scan ``s``, beam ``b``.

    Parameters
    ----------
    ranges_m : array_like, shape (S, B)
        Ranges (m); NaN = no return.
    angle_min_rad, angle_increment_rad : float
        Beam bearings ``a_b = angle_min_rad + b * angle_increment_rad`` (rad).
    translations_m : array_like, shape (S, 3)
        Scanner position of each scan in the site frame (m), e.g. from
        :func:`interpolate_poses`; NaN rows allowed.
    quaternions_xyzw : array_like, shape (S, 4)
        Scanner rotation of each scan (x, y, z, w); NaN rows allowed.

    Returns
    -------
    ndarray, shape (S, B, 3)
        Site-frame points (m).  NaN for NaN ranges and for every beam of a scan whose
        pose is NaN (not covered by the pose stream).

    Raises
    ------
    ValueError
        On shape mismatches or a finite zero quaternion.
    """
    r = _check_ranges(ranges_m)
    s, b = r.shape
    tr = np.asarray(translations_m, dtype=np.float64)
    if tr.shape != (s, 3):
        raise ValueError(f"translations_m must have shape ({s}, 3), got {tr.shape}")
    rot = quaternion_to_matrix(_as_quaternions(quaternions_xyzw, "quaternions_xyzw", s))
    a = _beam_angles(b, angle_min_rad, angle_increment_rad)
    # the scan plane is the sensor x-y plane: only the first two columns of R are needed
    xs = r * np.cos(a)                                   # (S, B) sensor x
    ys = r * np.sin(a)                                   # (S, B) sensor y
    out = np.empty((s, b, 3))
    for k in range(3):                                   # 3 output axes, not points
        out[..., k] = xs * rot[:, k, 0, None] + ys * rot[:, k, 1, None] + tr[:, k, None]
    return out
