"""The bucket-wheel reclaimer's kinematics: its constants, forward and inverse kinematics.

The one copy the projector, the planner, the localizer and the dashboard share
(docs/domain.md §3 is the contract); the simulator keeps its own on purpose
(:mod:`sim.kinematics`, the independent ground truth of every accuracy figure).

Joints: travel ``d1`` (m, along the rail = +y), slew ``theta2`` (rad, boom azimuth measured
from +y toward +x), luff ``theta3`` (rad, boom elevation above horizontal).  Site frame:
ENU metres, x across the pile, y along the rail, z up.  Rotations are
:class:`scipy.spatial.transform.Rotation`; quaternions are in Foxglove order
``(x, y, z, w)``.

Machine constants: :class:`Linkage` (the rail and the link lengths L2..L5, all the joint
chain needs) and its two views, :class:`Reclaimer` (plus the cutting wheel Rv, beta: the
envelope the projector cuts) and :class:`MachineGeometry` (plus the GNSS antenna and the
scanner mount: the poses the localizer publishes); :class:`PlannerMachine` wraps a
:class:`Reclaimer` with the wheel body and the buckets (planning).  Every function taking
a ``machine`` reads only its :class:`Linkage` fields, so a :class:`Reclaimer` or a
:class:`MachineGeometry` will do (:func:`pivot_position` and :func:`inverse_kinematics`
also take a :class:`PlannerMachine`).

Forward kinematics: the boom pivot, a point on the boom (the wheel centre, the antenna),
the wheel frame's rotation, the scanner pose.  Inverse kinematics: the joints that put
the wheel centre at a point, the joints of a wheel pose, the wheel pose of a scanner pose.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

__all__ = [
    "Linkage", "Reclaimer", "MachineGeometry", "PlannerMachine",
    "boom_radius_m", "boom_height_m", "pivot_position", "boom_point_m", "boom_point_scalar_m",
    "wheel_centre", "wheel_centre_m", "antenna_position_m", "antenna_jacobian",
    "wheel_orientation", "wheel_rotation", "wheel_quaternion_xyzw", "scanner_pose",
    "quaternion_to_matrix", "inverse_kinematics", "joints_from_wheel_pose",
    "wheel_from_scanner",
]

_LINKAGE_FIELDS = ("rail_x_m", "rail_z_m", "l2_m", "l3_m", "l4_m", "l5_m")
_IDENTITY_XYZW = (0.0, 0.0, 0.0, 1.0)


def _check_finite(obj: Any, names: tuple[str, ...]) -> None:
    for name in names:
        value = getattr(obj, name)
        if isinstance(value, bool) or not math.isfinite(float(value)):
            raise ValueError(f"{name} must be a finite number, got {value!r}")


# -- machine constants -------------------------------------------------------------------

@dataclass(frozen=True)
class Linkage:
    """The joint chain of a bucket-wheel reclaimer (docs/domain.md §3), metres.

    Attributes
    ----------
    rail_x_m, rail_z_m : float
        Rail position across the pile (x_r) and rail height (z_r), site frame.
    l2_m, l3_m : float
        L2 + L3 = height of the boom pivot above the rail.
    l4_m : float
        Horizontal offset of the pivot from the slew axis.
    l5_m : float
        Boom length, pivot -> wheel centre.
    """

    rail_x_m: float
    rail_z_m: float
    l2_m: float
    l3_m: float
    l4_m: float
    l5_m: float

    def __post_init__(self) -> None:
        _check_finite(self, _LINKAGE_FIELDS)

    @property
    def pivot_height_m(self) -> float:
        """Height of the boom pivot above the rail, L2 + L3 (m)."""
        return self.l2_m + self.l3_m

    @property
    def pivot_z_m(self) -> float:
        """Height of the boom pivot, z_r + L2 + L3 (m)."""
        return self.rail_z_m + self.pivot_height_m


@dataclass(frozen=True)
class Reclaimer(Linkage):
    """A reclaimer's linkage and cutting wheel: what its cutting envelope needs (radians).

    Attributes
    ----------
    rail_x_m, rail_z_m, l2_m, l3_m, l4_m, l5_m : float
        The :class:`Linkage`.
    cutting_radius_m : float
        Rv, wheel plus buckets (> 0).
    wheel_tilt_rad : float
        beta, |beta| < pi/2.
    """

    cutting_radius_m: float
    wheel_tilt_rad: float

    def __post_init__(self) -> None:
        super().__post_init__()
        _check_finite(self, ("cutting_radius_m", "wheel_tilt_rad"))
        if not self.cutting_radius_m > 0:
            raise ValueError(f"cutting_radius_m must be > 0, got {self.cutting_radius_m}")
        if not abs(self.wheel_tilt_rad) < math.pi / 2:
            raise ValueError(f"wheel_tilt_rad must be in (-pi/2, pi/2), got {self.wheel_tilt_rad}")

    @classmethod
    def from_message(cls, msg) -> "Reclaimer":
        """The constants of a ``MachineDeclared`` message (or any object with those attributes)."""
        names = _LINKAGE_FIELDS + ("cutting_radius_m", "wheel_tilt_rad")
        return cls(**{name: float(getattr(msg, name)) for name in names})

    @property
    def half_width_m(self) -> float:
        """Horizontal half-width of the envelope's cross-section, Rv cos(beta) (m)."""
        return self.cutting_radius_m * math.cos(self.wheel_tilt_rad)


@dataclass(frozen=True)
class MachineGeometry(Linkage):
    """A reclaimer's linkage, its GNSS antenna and its scanner mount: what its poses need.

    Attributes
    ----------
    rail_x_m, rail_z_m, l2_m, l3_m, l4_m, l5_m : float
        The :class:`Linkage`; ``l5_m > 0``.
    antenna_along_boom_m : float
        GNSS antenna beyond the wheel centre along the boom (negative = toward the pivot);
        0 = at the wheel centre (the simulator's default).
    antenna_up_m : float
        Antenna mast height above that boom point (site +z, m).
    scanner_translation_m : tuple of 3 float
        Scanner origin in the wheel frame (m); ``MachineDeclared.scanner.translation``.
    scanner_rotation_xyzw : tuple of 4 float
        Scanner orientation in the wheel frame, unit quaternion (x, y, z, w);
        ``MachineDeclared.scanner.rotation``.
    """

    antenna_along_boom_m: float = 0.0
    antenna_up_m: float = 0.0
    scanner_translation_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    scanner_rotation_xyzw: tuple[float, float, float, float] = _IDENTITY_XYZW

    def __post_init__(self) -> None:
        if len(self.scanner_translation_m) != 3 or len(self.scanner_rotation_xyzw) != 4:
            raise ValueError("scanner_translation_m needs 3 values and scanner_rotation_xyzw 4")
        super().__post_init__()
        _check_finite(self, ("antenna_along_boom_m", "antenna_up_m"))
        if not all(math.isfinite(v) for v in (*self.scanner_translation_m,
                                               *self.scanner_rotation_xyzw)):
            raise ValueError("the scanner mount must be finite")
        if not self.l5_m > 0:
            raise ValueError(f"l5_m (boom length) must be > 0, got {self.l5_m}")
        if not math.isclose(float(np.linalg.norm(self.scanner_rotation_xyzw)), 1.0,
                            abs_tol=1e-3):
            raise ValueError("scanner_rotation_xyzw must be a unit quaternion")

    @classmethod
    def from_machine_declared(cls, message: Any, *, antenna_along_boom_m: float = 0.0,
                              antenna_up_m: float = 0.0) -> MachineGeometry:
        """Geometry from a ``stockpile.v1.MachineDeclared`` message (ValueError if impossible).

        The schema has no antenna mount yet, so the antenna offsets are parameters
        (default: antenna at the wheel centre, as in the simulator).  A declaration
        without a scanner mount gets the identity mount.
        """
        scanner = message.scanner
        if message.HasField("scanner"):
            t = (scanner.translation.x, scanner.translation.y, scanner.translation.z)
            q = (scanner.rotation.x, scanner.rotation.y, scanner.rotation.z, scanner.rotation.w)
        else:
            t, q = (0.0, 0.0, 0.0), _IDENTITY_XYZW
        return cls(**{name: getattr(message, name) for name in _LINKAGE_FIELDS},
                   antenna_along_boom_m=float(antenna_along_boom_m),
                   antenna_up_m=float(antenna_up_m), scanner_translation_m=tuple(map(float, t)),
                   scanner_rotation_xyzw=tuple(map(float, q)))

    @property
    def scanner_mount(self) -> tuple[np.ndarray, np.ndarray]:
        """The scanner mount as ``(R_wheel_scanner (3, 3), t_wheel_scanner (3,) m)``."""
        return (quaternion_to_matrix(self.scanner_rotation_xyzw),
                np.asarray(self.scanner_translation_m, dtype=np.float64))


@dataclass(frozen=True)
class PlannerMachine:
    """A reclaimer's constants for planning: the envelope plus the wheel body and buckets.

    Attributes
    ----------
    reclaimer : Reclaimer
        The linkage and the cutting wheel (rail, L2..L5, Rv, beta).
    wheel_radius_m : float
        Rk, the radius of the wheel body without buckets (m), ``0 < Rk <= Rv``.
    fall_angle_rad : float
        phi, the angle at which material starts to fall from a bucket (rad), in [0, pi/2].
    bucket_width_m : float
        Bucket width (m, > 0); the default advance between cuts is 0.9 x this.
    """

    reclaimer: Reclaimer
    wheel_radius_m: float
    fall_angle_rad: float
    bucket_width_m: float

    def __post_init__(self) -> None:
        if not isinstance(self.reclaimer, Reclaimer):
            raise TypeError(f"reclaimer must be a Reclaimer, got {type(self.reclaimer).__name__}")
        _check_finite(self, ("wheel_radius_m", "fall_angle_rad", "bucket_width_m"))
        if not 0 < self.wheel_radius_m <= self.reclaimer.cutting_radius_m:
            raise ValueError(f"wheel_radius_m must be in (0, Rv = "
                             f"{self.reclaimer.cutting_radius_m}], got {self.wheel_radius_m}")
        if not 0 <= self.fall_angle_rad <= math.pi / 2:
            raise ValueError(f"fall_angle_rad must be in [0, pi/2], got {self.fall_angle_rad}")
        if not self.bucket_width_m > 0:
            raise ValueError(f"bucket_width_m must be > 0, got {self.bucket_width_m}")

    @classmethod
    def from_message(cls, msg) -> "PlannerMachine":
        """The constants of a ``MachineDeclared`` message (or any object with its fields)."""
        return cls(Reclaimer.from_message(msg), float(msg.wheel_radius_m),
                   float(msg.fall_angle_rad), float(msg.bucket_width_m))

    @property
    def cutting_radius_m(self) -> float:
        """Rv, wheel plus buckets (m)."""
        return self.reclaimer.cutting_radius_m

    @property
    def max_cutting_height_m(self) -> float:
        """H = (Rv + Rk sin(phi)) cos(beta) (m): the highest bank above the bench floor
        (thesis §5.1.2)."""
        return ((self.reclaimer.cutting_radius_m
                 + self.wheel_radius_m * math.sin(self.fall_angle_rad))
                * math.cos(self.reclaimer.wheel_tilt_rad))

    @property
    def cut_depth_m(self) -> float:
        """Default advance between the cuts of a bench, 0.9 x bucket width (m, thesis §2.3)."""
        return 0.9 * self.bucket_width_m

    @property
    def pivot_z_m(self) -> float:
        """Height of the boom pivot, z_r + L2 + L3 (m)."""
        return self.reclaimer.pivot_z_m


def _linkage(machine) -> Linkage:
    """The linkage of a machine: a :class:`PlannerMachine`'s reclaimer, else the machine."""
    return machine.reclaimer if isinstance(machine, PlannerMachine) else machine


# -- forward kinematics ------------------------------------------------------------------

def boom_radius_m(machine: Linkage, luff_rad, along_m: float = 0.0):
    """Horizontal distance of a boom point from the slew axis, ``L4 + (L5 + a) cos(theta3)`` (m).

    ``luff_rad``: theta3 (rad), float or array (the result has its shape); ``along_m``:
    the point's distance ``a`` beyond the wheel centre along the boom (m), 0 = the wheel
    centre.
    """
    return machine.l4_m + (machine.l5_m + along_m) * np.cos(np.asarray(luff_rad, dtype=np.float64))


def boom_height_m(machine: Linkage, luff_rad, along_m: float = 0.0):
    """Height of a boom point, ``z_r + L2 + L3 + (L5 + a) sin(theta3)`` (m).

    ``along_m`` (``a``) as in :func:`boom_radius_m`; 0 gives the wheel centre's height.
    """
    return (machine.rail_z_m + machine.pivot_height_m
            + (machine.l5_m + along_m) * np.sin(np.asarray(luff_rad, dtype=np.float64)))


def pivot_position(machine, travel_m, slew_rad) -> np.ndarray:
    """The boom pivot ``(x, y, z)`` (m), shape (..., 3): L4 from the slew axis along the boom,
    at L2 + L3, for travel d1 (m) and slew theta2 (rad) (broadcastable); ``machine`` is a
    :class:`Linkage` or a :class:`PlannerMachine`."""
    d1, th2 = np.broadcast_arrays(np.asarray(travel_m, np.float64),
                                  np.asarray(slew_rad, np.float64))
    m = _linkage(machine)
    out = np.empty(d1.shape + (3,))
    out[..., 0] = m.rail_x_m + m.l4_m * np.sin(th2)
    out[..., 1] = d1 + m.l4_m * np.cos(th2)
    out[..., 2] = m.pivot_z_m
    return out


def boom_point_m(machine: Linkage, travel_m, slew_rad, luff_rad, along_m: float = 0.0,
                 up_m: float = 0.0) -> np.ndarray:
    """A point on the boom in the site frame: ``along_m`` beyond the wheel centre along the
    (luffed) boom, then ``up_m`` straight up (m; both 0 give the wheel centre).

    ``travel_m``, ``slew_rad``, ``luff_rad``: d1 (m), theta2 (rad, from +y toward +x),
    theta3 (rad), floats or broadcastable arrays.  Returns ``(x, y, z)`` (m), shape
    (..., 3); ``(3,)`` for scalar joints.
    """
    d1, th2, th3 = np.broadcast_arrays(np.asarray(travel_m, dtype=np.float64),
                                       np.asarray(slew_rad, dtype=np.float64),
                                       np.asarray(luff_rad, dtype=np.float64))
    rho = boom_radius_m(machine, th3, along_m)
    out = np.empty(d1.shape + (3,), dtype=np.float64)
    out[..., 0] = machine.rail_x_m + rho * np.sin(th2)
    out[..., 1] = d1 + rho * np.cos(th2)
    out[..., 2] = boom_height_m(machine, th3, along_m) + up_m
    return out


def boom_point_scalar_m(machine: Linkage, travel_m: float, slew_rad: float, luff_rad: float,
                        along_m: float = 0.0, up_m: float = 0.0) -> np.ndarray:
    """:func:`boom_point_m` for one joint triple of Python floats, shape (3,) (m).

    A fast path for the localizer's sigma points (``math`` instead of numpy ufuncs).
    """
    boom = machine.l5_m + along_m
    rho = machine.l4_m + boom * math.cos(luff_rad)
    return np.array([machine.rail_x_m + rho * math.sin(slew_rad),
                     travel_m + rho * math.cos(slew_rad),
                     machine.rail_z_m + machine.pivot_height_m + boom * math.sin(luff_rad) + up_m])


def wheel_centre(machine: Linkage, travel_m, slew_rad, luff_rad) -> np.ndarray:
    """Forward kinematics: the wheel centre in the site frame (docs/domain.md §3), (..., 3) m.

    :func:`boom_point_m` without offsets; joints as there (broadcastable).
    """
    return boom_point_m(machine, travel_m, slew_rad, luff_rad)


def _joint_columns(joints) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    j = np.asarray(joints, float)
    if j.ndim < 1 or j.shape[-1] != 3:
        raise ValueError(f"joints must have shape (..., 3), got {j.shape}")
    return j[..., 0], j[..., 1], j[..., 2]


def wheel_centre_m(machine: Linkage, joints) -> np.ndarray:
    """:func:`wheel_centre` of joint rows ``(..., 3)`` (travel m, slew rad, luff rad).

    Returns the centres, shape (..., 3) (m); ValueError if the last axis is not 3.
    """
    return boom_point_m(machine, *_joint_columns(joints))


def antenna_position_m(geometry: MachineGeometry, joints) -> np.ndarray:
    """The GNSS antenna in the site frame: a point on the boom, shape (..., 3) (m).

    ``antenna_along_boom_m`` beyond the wheel centre along the (luffed) boom, then
    ``antenna_up_m`` straight up.  See :func:`wheel_centre_m` for ``joints``.
    """
    return boom_point_m(geometry, *_joint_columns(joints), geometry.antenna_along_boom_m,
                        geometry.antenna_up_m)


def antenna_jacobian(geometry: MachineGeometry, joints) -> np.ndarray:
    """d(antenna position) / d(travel, slew, luff) at ``joints`` (3,), shape (3, 3).

    Rows: site x, y, z (m); columns: per m of travel, per rad of slew and of luff.
    """
    boom = geometry.l5_m + geometry.antenna_along_boom_m
    _t, slew, luff = (float(v) for v in joints)
    rho = geometry.l4_m + boom * math.cos(luff)
    ss, cs, sl, cl = math.sin(slew), math.cos(slew), math.sin(luff), math.cos(luff)
    return np.array([[0.0, rho * cs, -boom * sl * ss],
                     [1.0, -rho * ss, -boom * sl * cs],
                     [0.0, 0.0, boom * cl]])


def wheel_orientation(slew_rad: float) -> Rotation:
    """The wheel frame's orientation in the site frame: a yaw of ``pi/2 - slew``.

    The wheel frame is level: x along the boom's horizontal direction
    ``(sin slew, cos slew, 0)``, z up, y = z x x.  The luff does not tilt it (the scanner
    hangs level below the wheel, as in the simulator's scanner pose).
    """
    return Rotation.from_euler("z", 0.5 * math.pi - slew_rad)


def wheel_rotation(slew_rad: float) -> np.ndarray:
    """:func:`wheel_orientation` as a rotation matrix, shape (3, 3)."""
    return wheel_orientation(slew_rad).as_matrix()


def wheel_quaternion_xyzw(slew_rad: float) -> np.ndarray:
    """:func:`wheel_orientation` as a unit quaternion (x, y, z, w), shape (4,)."""
    return wheel_orientation(slew_rad).as_quat()


def scanner_pose(geometry: MachineGeometry, joints) -> tuple[np.ndarray, np.ndarray]:
    """Scanner pose in the site frame: the wheel pose composed with the scanner mount.

    ``position = wheel_centre + R_wheel @ t_mount``; ``R = R_wheel R_mount``.

    Parameters
    ----------
    geometry : MachineGeometry
    joints : array_like, shape (3,)
        (travel m, slew rad, luff rad); ValueError for another shape.

    Returns
    -------
    position_m : ndarray (3,)
    rotation_xyzw : ndarray (4,)
        Unit quaternion, w >= 0.
    """
    j = np.asarray(joints, float)
    if j.shape != (3,):
        raise ValueError(f"joints must have shape (3,), got {j.shape}")
    wheel = wheel_orientation(float(j[1]))
    position = wheel_centre_m(geometry, j) + wheel.apply(geometry.scanner_translation_m)
    rotation = wheel * Rotation.from_quat(geometry.scanner_rotation_xyzw)
    return position, rotation.as_quat(canonical=True)


def quaternion_to_matrix(quaternions_xyzw) -> np.ndarray:
    """Rotation matrices of quaternions (x, y, z, w), normalised first.

    Parameters
    ----------
    quaternions_xyzw : array_like, shape (4,) or (N, 4)
        Non-zero quaternions; NaN rows give NaN matrices.

    Returns
    -------
    ndarray, shape (3, 3) or (N, 3, 3)
        ``R`` with ``p_parent = R @ p_child + t``; its columns are the child's axes in the
        parent frame.

    Raises
    ------
    ValueError
        On another shape or a zero quaternion.
    """
    q = np.asarray(quaternions_xyzw, dtype=np.float64)
    if q.ndim not in (1, 2) or q.shape[-1] != 4:
        raise ValueError(f"quaternions_xyzw must have shape (4,) or (N, 4) (x, y, z, w), "
                         f"got {q.shape}")
    rows = q.reshape(-1, 4)
    norm = np.linalg.norm(rows, axis=-1)
    finite = np.isfinite(norm)
    if np.any(finite & ~(norm > 1e-12)):
        raise ValueError("quaternions_xyzw contains a zero quaternion")
    out = np.full((rows.shape[0], 3, 3), np.nan)
    if finite.any():
        out[finite] = Rotation.from_quat(rows[finite] / norm[finite, None]).as_matrix()
    return out.reshape(q.shape[:-1] + (3, 3))


# -- inverse kinematics ------------------------------------------------------------------

def inverse_kinematics(machine, centre_m) -> tuple[np.ndarray, ...]:
    """Both joint solutions that put the wheel centre at ``centre_m`` (docs/domain.md §3).

    The luff follows from the height, ``theta3 = asin((c_z - z_r - L2 - L3) / L5)``, and
    with it the boom radius ``rho = L4 + L5 cos(theta3)``.  The slew axis ``(x_r, d1)``
    must lie at horizontal distance ``rho`` from the centre, so with
    ``s = sqrt(rho^2 - (c_x - x_r)^2)`` the travel is ``d1 = c_y - s`` (branch 0, the boom
    points toward +y, ``cos(theta2) >= 0``) or ``d1 = c_y + s`` (branch 1, toward -y).

    Parameters
    ----------
    machine : Linkage or PlannerMachine
    centre_m : array_like, shape (N, 3)
        Wheel centres (m, site frame).

    Returns
    -------
    travel_m : ndarray, shape (N, 2)
        d1 (m) per branch; NaN where unreachable.
    slew_rad : ndarray, shape (N, 2)
        theta2 (rad, in (-pi, pi]) per branch; NaN where unreachable.
    luff_rad : ndarray, shape (N,)
        theta3 (rad); NaN where the height is out of the boom's reach.
    reachable : ndarray of bool, shape (N,)
        Whether a solution exists (both branches then exist).

    Raises
    ------
    ValueError
        If ``centre_m`` is not (N, 3) or holds non-finite values.
    """
    c = np.asarray(centre_m, dtype=np.float64)
    if c.ndim != 2 or c.shape[1] != 3:
        raise ValueError(f"centre_m must have shape (N, 3), got {c.shape}")
    if not np.all(np.isfinite(c)):
        raise ValueError("centre_m must be finite")
    m = _linkage(machine)
    sin_luff = (c[:, 2] - m.pivot_z_m) / m.l5_m
    ok = np.abs(sin_luff) <= 1.0
    luff = np.where(ok, np.arcsin(np.clip(sin_luff, -1.0, 1.0)), np.nan)
    rho = np.asarray(boom_radius_m(m, np.where(ok, luff, 0.0)), dtype=np.float64)
    dx = c[:, 0] - m.rail_x_m
    s2 = rho * rho - dx * dx
    ok &= s2 >= 0
    s = np.sqrt(np.where(ok, s2, 0.0))
    travel = np.stack([c[:, 1] - s, c[:, 1] + s], axis=1)
    slew = np.stack([np.arctan2(dx, s), np.arctan2(dx, -s)], axis=1)
    travel[~ok] = np.nan
    slew[~ok] = np.nan
    luff[~ok] = np.nan
    return travel, slew, luff, ok


def joints_from_wheel_pose(machine: Linkage, centre, rotation) -> tuple[float, float, float]:
    """(travel m, slew rad, luff rad) of a wheel pose (docs/domain.md §3).

    The luff follows from the centre's height (clipped into the boom's reach), the slew
    from the wheel frame's x axis, the boom's horizontal direction
    ``(sin slew, cos slew, 0)``; the travel puts the slew axis ``rho`` behind the centre.

    ``centre``: the wheel centre in the site frame, (3,) (m); ``rotation``: the wheel
    frame's rotation in the site frame, (3, 3) (:func:`wheel_rotation`).
    """
    c = np.asarray(centre, float)
    s = (c[2] - machine.rail_z_m - machine.pivot_height_m) / machine.l5_m
    luff = math.asin(min(1.0, max(-1.0, s)))
    rho = machine.l4_m + machine.l5_m * math.cos(luff)
    slew = math.atan2(rotation[0, 0], rotation[1, 0])
    travel = c[1] - rho * math.cos(slew)
    return travel, slew, luff


def wheel_from_scanner(position, quaternion_xyzw, mount) -> tuple[np.ndarray, np.ndarray]:
    """The wheel frame's pose from the scanner's site pose and its mount on the wheel.

    The inverse of ``p_scanner = c + R_wheel t_mount``, ``R_scanner = R_wheel R_mount``.

    ``position`` (3,) (m) and ``quaternion_xyzw`` (4,) (non-zero) are the scanner's pose in
    the site frame; ``mount`` is ``(R_wheel_scanner (3, 3), t_wheel_scanner (3,) m)``, e.g.
    :attr:`MachineGeometry.scanner_mount`.  Returns the wheel centre (3,) (m) and the
    wheel frame's rotation (3, 3), both in the site frame.
    """
    r_site_scanner = quaternion_to_matrix(quaternion_xyzw)
    r_wheel_scanner, t_wheel_scanner = mount
    r_site_wheel = r_site_scanner @ np.asarray(r_wheel_scanner).T
    return np.asarray(position, float) - r_site_wheel @ np.asarray(t_wheel_scanner), r_site_wheel
