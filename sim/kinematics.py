"""The simulator's own reclaimer kinematics and cutting envelope (docs/domain.md §3).

Joints: travel ``d1`` (m, along the rail = +y), slew ``theta2`` (rad, boom azimuth
measured from +y toward +x), luff ``theta3`` (rad, boom elevation above horizontal).
Site frame: ENU metres, x across the pile, y along the rail, z up.

This is a second copy of the kinematics on purpose.  The product's copy,
:mod:`projector.kinematics` (shared by the projector, the planner, the localizer and the
dashboard), is what the accuracy figures measure; the simulator is the ground truth they
are measured against, so it must not import it: a mistake in one copy then shows up as a
difference instead of cancelling out.  Do not merge the two.

All functions are pure and vectorised over numpy arrays.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Machine:
    """Kinematic constants of a bucket-wheel reclaimer (metres, radians)."""

    rail_x_m: float
    rail_z_m: float
    l2_m: float
    l3_m: float
    l4_m: float
    l5_m: float
    wheel_radius_m: float
    cutting_radius_m: float
    wheel_tilt_rad: float
    bucket_width_m: float
    fall_angle_rad: float

    @property
    def pivot_height_m(self) -> float:
        """Height of the boom pivot above the rail (L2 + L3)."""
        return self.l2_m + self.l3_m

    @property
    def max_cutting_height_m(self) -> float:
        """H = (Rv + Rk sin(phi)) cos(beta) (thesis §5.1.2)."""
        return ((self.cutting_radius_m + self.wheel_radius_m * math.sin(self.fall_angle_rad))
                * math.cos(self.wheel_tilt_rad))

    @property
    def cut_depth_m(self) -> float:
        """Advance between cuts: 0.9 x bucket width (thesis §2.3)."""
        return 0.9 * self.bucket_width_m


#: The reference full-scale machine of docs/domain.md §3 (thesis Table 3.1 / 5.5).
FULL_SCALE = Machine(rail_x_m=0.0, rail_z_m=0.0, l2_m=6.0, l3_m=5.0, l4_m=5.0, l5_m=50.0,
                     wheel_radius_m=7.0, cutting_radius_m=10.0,
                     wheel_tilt_rad=math.radians(5.0), bucket_width_m=1.2,
                     fall_angle_rad=math.radians(15.0))

#: The bench-scale (laboratory) machine: lengths in metres (6, 5, 5, 50 cm ...).
BENCH_SCALE = Machine(rail_x_m=0.0, rail_z_m=0.0, l2_m=0.06, l3_m=0.05, l4_m=0.05, l5_m=0.50,
                      wheel_radius_m=0.04, cutting_radius_m=0.05, wheel_tilt_rad=0.0,
                      bucket_width_m=0.01, fall_angle_rad=math.radians(20.0))


def boom_radius_m(machine: Machine, luff_rad):
    """Horizontal distance of the wheel centre from the slew axis: L4 + L5 cos(theta3)."""
    return machine.l4_m + machine.l5_m * np.cos(luff_rad)


def wheel_centre(machine: Machine, travel_m, slew_rad, luff_rad) -> np.ndarray:
    """Forward kinematics: wheel centre in the site frame.

    Parameters
    ----------
    travel_m, slew_rad, luff_rad : float or array_like, broadcastable
        Joint values (m, rad, rad).

    Returns
    -------
    ndarray, shape (..., 3)
        (x, y, z) in metres.
    """
    travel_m, slew_rad, luff_rad = np.broadcast_arrays(
        np.asarray(travel_m, float), np.asarray(slew_rad, float), np.asarray(luff_rad, float))
    rho = boom_radius_m(machine, luff_rad)
    x = machine.rail_x_m + rho * np.sin(slew_rad)
    y = travel_m + rho * np.cos(slew_rad)
    z = machine.rail_z_m + machine.pivot_height_m + machine.l5_m * np.sin(luff_rad)
    return np.stack([x, y, z], axis=-1)


def inverse_kinematics(machine: Machine, centre, travel_m) -> tuple[np.ndarray, np.ndarray]:
    """Slew and luff (rad) that put the wheel centre at ``centre`` for a given travel.

    Parameters
    ----------
    centre : array_like, shape (..., 3)
        Wheel centre (m).
    travel_m : float or array_like
        Travel d1 (m).

    Raises
    ------
    ValueError
        If the centre's height is out of the boom's reach.
    """
    centre = np.asarray(centre, float)
    if centre.shape[-1] != 3:
        raise ValueError(f"centre must have shape (..., 3), got {centre.shape}")
    sin_luff = (centre[..., 2] - machine.rail_z_m - machine.pivot_height_m) / machine.l5_m
    if np.any(np.abs(sin_luff) > 1):
        raise ValueError("wheel centre height is out of the boom's reach")
    luff = np.arcsin(sin_luff)
    slew = np.arctan2(centre[..., 0] - machine.rail_x_m, centre[..., 1] - np.asarray(travel_m, float))
    return slew, luff


def envelope_floor_z(machine: Machine, x, y, travel_m: float, luff_rad: float,
                     slew_start_rad: float, slew_end_rad: float) -> np.ndarray:
    """Floor of the cutting envelope of one cut over columns at (x, y); NaN outside it.

    During a cut the wheel sweeps an elliptic torus around the slew axis
    (x_r, d1): a point at horizontal distance r from the axis, azimuth theta in the
    slew range, height z is inside iff
    ((r - rho) / (Rv cos beta))^2 + ((z - c_z) / Rv)^2 < 1, so a column's floor is
    c_z - Rv sqrt(1 - ((r - rho) / (Rv cos beta))^2).

    Parameters
    ----------
    x, y : array_like, broadcastable
        Column positions (m, site frame).
    travel_m, luff_rad, slew_start_rad, slew_end_rad : float
        The cut's joints; the slew range is [min, max] of the two slew angles.

    Returns
    -------
    ndarray
        Floor height (m) per column, NaN where the column is outside the footprint.
    """
    x, y = np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float))
    rho = float(boom_radius_m(machine, luff_rad))
    c_z = machine.rail_z_m + machine.pivot_height_m + machine.l5_m * math.sin(luff_rad)
    half_width = machine.cutting_radius_m * math.cos(machine.wheel_tilt_rad)
    dx = x - machine.rail_x_m
    dy = y - travel_m
    r = np.hypot(dx, dy)
    theta = np.arctan2(dx, dy)  # from +y toward +x, like the slew
    lo, hi = min(slew_start_rad, slew_end_rad), max(slew_start_rad, slew_end_rad)
    u = (r - rho) / half_width
    # azimuth measured from the range's start, wrapped: a range may cross +-pi
    in_range = np.mod(theta - lo, 2 * np.pi) <= (hi - lo)
    inside = (np.abs(u) < 1) & in_range
    floor = np.full(x.shape, np.nan)
    floor[inside] = c_z - machine.cutting_radius_m * np.sqrt(1 - u[inside] ** 2)
    return floor
