"""The planner's view of a bucket-wheel reclaimer: constants, inverse kinematics, the boom.

DOMAIN.md §3 is the contract.  Joints: travel ``d1`` (m, along the rail = +y), slew
``theta2`` (rad, boom azimuth from +y toward +x), luff ``theta3`` (rad, boom elevation
above horizontal).  The cutting envelope itself (forward kinematics, the envelope floor)
is the projector's :mod:`projector.envelope`; this module adds what planning needs
on top of it: the wheel (body) radius Rk, the fall angle phi and the bucket width, which
give the maximum cutting height H = (Rv + Rk sin phi) cos beta (thesis §5.1.2) and the
advance between cuts, 0.9 x bucket width (thesis §2.3).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from projector.envelope import Reclaimer, boom_radius_m, wheel_centre_z_m

__all__ = ["PlannerMachine", "inverse_kinematics", "pivot_position"]


@dataclass(frozen=True)
class PlannerMachine:
    """A reclaimer's constants for planning: the envelope plus the wheel body and buckets.

    Attributes
    ----------
    reclaimer : Reclaimer
        The projector's envelope constants (rail, L2..L5, Rv, beta).
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
        for name in ("wheel_radius_m", "fall_angle_rad", "bucket_width_m"):
            value = getattr(self, name)
            if isinstance(value, bool) or not math.isfinite(float(value)):
                raise ValueError(f"{name} must be a finite number, got {value!r}")
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
        """H = (Rv + Rk sin(phi)) cos(beta) (m): the highest bank above the bench floor."""
        return ((self.reclaimer.cutting_radius_m
                 + self.wheel_radius_m * math.sin(self.fall_angle_rad))
                * math.cos(self.reclaimer.wheel_tilt_rad))

    @property
    def cut_depth_m(self) -> float:
        """Default advance between the cuts of a bench, 0.9 x bucket width (m)."""
        return 0.9 * self.bucket_width_m

    @property
    def pivot_z_m(self) -> float:
        """Height of the boom pivot, z_r + L2 + L3 (m)."""
        return self.reclaimer.rail_z_m + self.reclaimer.pivot_height_m


def inverse_kinematics(machine: PlannerMachine, centre_m) -> tuple[np.ndarray, ...]:
    """Both joint solutions that put the wheel centre at ``centre_m`` (DOMAIN.md §3).

    The luff follows from the height, ``theta3 = asin((c_z - z_r - L2 - L3) / L5)``, and
    with it the boom radius ``rho = L4 + L5 cos(theta3)``.  The slew axis ``(x_r, d1)``
    must lie at horizontal distance ``rho`` from the centre, so with
    ``s = sqrt(rho^2 - (c_x - x_r)^2)`` the travel is ``d1 = c_y - s`` (branch 0, the boom
    points toward +y, ``cos(theta2) >= 0``) or ``d1 = c_y + s`` (branch 1, toward -y).

    Parameters
    ----------
    machine : PlannerMachine
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
    m = machine.reclaimer
    sin_luff = (c[:, 2] - machine.pivot_z_m) / m.l5_m
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


def pivot_position(machine: PlannerMachine, travel_m, slew_rad) -> np.ndarray:
    """The boom pivot ``(x, y, z)`` (m): L4 from the slew axis along the boom, at L2 + L3.

    Parameters
    ----------
    travel_m, slew_rad : float or array_like, broadcastable
        Travel d1 (m) and slew theta2 (rad).

    Returns
    -------
    ndarray, shape (..., 3)
    """
    d1, th2 = np.broadcast_arrays(np.asarray(travel_m, np.float64),
                                  np.asarray(slew_rad, np.float64))
    m = machine.reclaimer
    out = np.empty(d1.shape + (3,))
    out[..., 0] = m.rail_x_m + m.l4_m * np.sin(th2)
    out[..., 1] = d1 + m.l4_m * np.cos(th2)
    out[..., 2] = machine.pivot_z_m
    return out


def centre_height_m(machine: PlannerMachine, luff_rad) -> np.ndarray:
    """Wheel-centre height for a luff (m); the projector's forward kinematics."""
    return np.asarray(wheel_centre_z_m(machine.reclaimer, luff_rad), dtype=np.float64)
