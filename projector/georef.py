"""Scanner poses at scan times, and 2-D laser scans turned into site-frame points.

Conventions
-----------
- Site frame: ENU metres (DOMAIN.md §2): x across the pile, y along the rail, z up.
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

__all__ = ["interpolate_poses", "quaternion_to_matrix", "sensor_points", "georeference"]

#: below this angle between two quaternions (rad) slerp is replaced by a normalised lerp
#: (the two agree to ~1e-17 there; sin(theta) would lose precision)
_SLERP_LERP_THRESHOLD_RAD = 1e-6


def _as_quaternions(q, name: str, n: int | None = None) -> np.ndarray:
    q = np.asarray(q, dtype=np.float64)
    if q.ndim != 2 or q.shape[1] != 4 or (n is not None and q.shape[0] != n):
        want = f"({n}, 4)" if n is not None else "(M, 4)"
        raise ValueError(f"{name} must have shape {want} (x, y, z, w), got {q.shape}")
    return q


def _normalised(q: np.ndarray, name: str, *, allow_nan: bool) -> np.ndarray:
    norm = np.linalg.norm(q, axis=-1)
    finite = np.isfinite(norm)
    if not allow_nan and not finite.all():
        raise ValueError(f"{name} must be finite")
    if np.any(finite & ~(norm > 1e-12)):
        raise ValueError(f"{name} contains a zero quaternion")
    with np.errstate(invalid="ignore", divide="ignore"):
        return q / norm[..., None]


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
    The rotation is the shortest-arc slerp: when the two bracketing quaternions have a
    negative dot product the second is negated (``q`` and ``-q`` are the same rotation),
    so the interpolation never takes the long way round.  Vectorised over all queries.

    Raises
    ------
    ValueError
        On mismatched shapes, unsorted pose times, non-finite poses, a zero quaternion or
        a negative ``max_gap_ns``.
    """
    t = np.asarray(t_ns)
    pt = np.asarray(pose_t_ns)
    if t.ndim != 1 or pt.ndim != 1:
        raise ValueError(f"t_ns and pose_t_ns must be 1-D, got {t.shape} and {pt.shape}")
    if not (np.issubdtype(t.dtype, np.integer) or t.size == 0) \
            or not (np.issubdtype(pt.dtype, np.integer) or pt.size == 0):
        raise ValueError("t_ns and pose_t_ns must be integer nanoseconds (int64)")
    t = t.astype(np.int64)
    pt = pt.astype(np.int64)
    m = pt.shape[0]
    if m < 1:
        raise ValueError("need at least one pose")
    tr = np.asarray(translations_m, dtype=np.float64)
    if tr.shape != (m, 3):
        raise ValueError(f"translations_m must have shape ({m}, 3), got {tr.shape}")
    if not np.isfinite(tr).all():
        raise ValueError("translations_m must be finite")
    q = _normalised(_as_quaternions(quaternions_xyzw, "quaternions_xyzw", m),
                    "quaternions_xyzw", allow_nan=False)
    if np.any(np.diff(pt) < 0):
        raise ValueError("pose_t_ns must be sorted (non-decreasing)")
    if max_gap_ns < 0:
        raise ValueError(f"max_gap_ns must be >= 0, got {max_gap_ns}")

    n = t.shape[0]
    out_t = np.full((n, 3), np.nan)
    out_q = np.full((n, 4), np.nan)
    if n == 0:
        return out_t, out_q

    i1 = np.searchsorted(pt, t, side="left")          # first pose at or after t
    i1c = np.minimum(i1, m - 1)
    exact = (i1 < m) & (pt[i1c] == t)
    i0 = i1 - 1
    inner = ~exact & (i0 >= 0) & (i1 < m)
    i0c = np.clip(i0, 0, m - 1)
    gap = pt[i1c] - pt[i0c]                            # int64, no float rounding
    inner &= gap <= max_gap_ns

    out_t[exact] = tr[i1c[exact]]
    out_q[exact] = q[i1c[exact]]

    a, b = i0c[inner], i1c[inner]
    s = ((t[inner] - pt[a]).astype(np.float64) / gap[inner].astype(np.float64))[:, None]
    out_t[inner] = tr[a] + s * (tr[b] - tr[a])

    q0, q1 = q[a], q[b]
    dot = np.einsum("ij,ij->i", q0, q1)
    flip = dot < 0.0
    q1 = np.where(flip[:, None], -q1, q1)
    dot = np.minimum(np.abs(dot), 1.0)
    theta = np.arccos(dot)[:, None]
    small = theta < _SLERP_LERP_THRESHOLD_RAD
    sin_theta = np.where(small, 1.0, np.sin(theta))
    w0 = np.where(small, 1.0 - s, np.sin((1.0 - s) * theta) / sin_theta)
    w1 = np.where(small, s, np.sin(s * theta) / sin_theta)
    qi = w0 * q0 + w1 * q1
    out_q[inner] = qi / np.linalg.norm(qi, axis=1, keepdims=True)
    return out_t, out_q


def quaternion_to_matrix(quaternions_xyzw) -> np.ndarray:
    """Rotation matrices of quaternions (x, y, z, w), normalised first.

    Parameters
    ----------
    quaternions_xyzw : array_like, shape (N, 4)
        Non-zero quaternions; NaN rows give NaN matrices.

    Returns
    -------
    ndarray, shape (N, 3, 3)
        ``R`` with ``p_parent = R @ p_child + t``; its columns are the child's axes in the
        parent frame.
    """
    q = _normalised(_as_quaternions(quaternions_xyzw, "quaternions_xyzw"),
                    "quaternions_xyzw", allow_nan=True)
    x, y, z, w = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    r = np.empty((q.shape[0], 3, 3))
    r[:, 0, 0] = 1 - 2 * (y * y + z * z)
    r[:, 0, 1] = 2 * (x * y - z * w)
    r[:, 0, 2] = 2 * (x * z + y * w)
    r[:, 1, 0] = 2 * (x * y + z * w)
    r[:, 1, 1] = 1 - 2 * (x * x + z * z)
    r[:, 1, 2] = 2 * (y * z - x * w)
    r[:, 2, 0] = 2 * (x * z - y * w)
    r[:, 2, 1] = 2 * (y * z + x * w)
    r[:, 2, 2] = 1 - 2 * (x * x + y * y)
    return r


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
