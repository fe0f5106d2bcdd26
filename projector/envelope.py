"""The bucket-wheel reclaimer's forward kinematics and the floor of its cutting envelope.

DOMAIN.md §3 is the contract.  Joints: travel ``d1`` (m, along the rail = +y), slew
``theta2`` (rad, boom azimuth measured from +y toward +x), luff ``theta3`` (rad, boom
elevation above horizontal).  Site frame: ENU metres, x across the pile, y along the rail.

A cut at travel ``d1`` and luff ``theta3`` that slews from ``theta_start`` to
``theta_end`` sweeps an elliptic torus around the slew axis ``(x_r, d1)``.  A column at
horizontal distance ``r`` from the axis and azimuth ``theta`` lies in the swept footprint iff
its azimuth lies on the slewed arc and ``|r - rho| < Rv cos(beta)``; its envelope floor is

    z_floor = c_z - Rv sqrt(1 - ((r - rho) / (Rv cos beta))^2)

and everything of the pile above that floor is reclaimed.

The slewed arc
--------------
Slew angles are *joint* angles: they are not wrapped.  The arc is the set of azimuths
``theta`` with ``theta = a + 2 pi n`` for some integer ``n`` and some ``a`` in
``[min(start, end), max(start, end)]`` (both ends included); the direction of the slew does
not matter.  So a slew from 3.0 to 3.5 rad crosses +-pi and covers the short 0.5 rad arc
around the -y axis, whereas a slew from 3.0 to -3.0 rad covers the long 6 rad arc through
+y; a range of 2 pi or more covers every azimuth.  This is the simulator's convention.

The arc's ends
--------------
The footprint is the azimuth sector and nothing more: no end caps are added for the
wheel's own extent at the first and last slew positions (the simulator does not add them
either).  The simulator removes a cut's material in several consecutive sub-slews of the
same arc at the same travel and luff; their union is the whole arc and the floor does not
depend on the slew angle, so one :func:`cut_floor` over the whole arc removes the same
material (the walls only slump after the last sub-slew, and the slumped material belongs
to the next cut).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from projector.grid import GridGeometry

__all__ = ["Reclaimer", "wheel_centre", "boom_radius_m", "wheel_centre_z_m", "cut_floor",
           "in_slew_arc"]

_TWO_PI = 2.0 * math.pi


@dataclass(frozen=True)
class Reclaimer:
    """Kinematic constants of a bucket-wheel reclaimer (DOMAIN.md §3), metres and radians.

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
    cutting_radius_m : float
        Rv, wheel plus buckets (> 0).
    wheel_tilt_rad : float
        beta, |beta| < pi/2.
    """

    rail_x_m: float
    rail_z_m: float
    l2_m: float
    l3_m: float
    l4_m: float
    l5_m: float
    cutting_radius_m: float
    wheel_tilt_rad: float

    def __post_init__(self) -> None:
        for name in ("rail_x_m", "rail_z_m", "l2_m", "l3_m", "l4_m", "l5_m", "cutting_radius_m",
                     "wheel_tilt_rad"):
            value = getattr(self, name)
            if isinstance(value, bool) or not math.isfinite(float(value)):
                raise ValueError(f"{name} must be a finite number, got {value!r}")
        if not self.cutting_radius_m > 0:
            raise ValueError(f"cutting_radius_m must be > 0, got {self.cutting_radius_m}")
        if not abs(self.wheel_tilt_rad) < math.pi / 2:
            raise ValueError(f"wheel_tilt_rad must be in (-pi/2, pi/2), got {self.wheel_tilt_rad}")

    @classmethod
    def from_message(cls, msg) -> "Reclaimer":
        """The constants of a ``MachineDeclared`` message (or any object with those attributes)."""
        names = ("rail_x_m", "rail_z_m", "l2_m", "l3_m", "l4_m", "l5_m", "cutting_radius_m",
                 "wheel_tilt_rad")
        return cls(**{name: float(getattr(msg, name)) for name in names})

    @property
    def pivot_height_m(self) -> float:
        """Height of the boom pivot above the rail, L2 + L3 (m)."""
        return self.l2_m + self.l3_m

    @property
    def half_width_m(self) -> float:
        """Horizontal half-width of the envelope's cross-section, Rv cos(beta) (m)."""
        return self.cutting_radius_m * math.cos(self.wheel_tilt_rad)


def boom_radius_m(machine: Reclaimer, luff_rad):
    """Horizontal distance of the wheel centre from the slew axis, ``L4 + L5 cos(theta3)`` (m)."""
    return machine.l4_m + machine.l5_m * np.cos(np.asarray(luff_rad, dtype=np.float64))


def wheel_centre_z_m(machine: Reclaimer, luff_rad):
    """Height of the wheel centre, ``z_r + L2 + L3 + L5 sin(theta3)`` (m)."""
    return (machine.rail_z_m + machine.pivot_height_m
            + machine.l5_m * np.sin(np.asarray(luff_rad, dtype=np.float64)))


def wheel_centre(machine: Reclaimer, travel_m, slew_rad, luff_rad) -> np.ndarray:
    """Forward kinematics: the wheel centre in the site frame (DOMAIN.md §3).

    Parameters
    ----------
    machine : Reclaimer
    travel_m, slew_rad, luff_rad : float or array_like, broadcastable
        Travel d1 (m), slew theta2 (rad, from +y toward +x), luff theta3 (rad).

    Returns
    -------
    ndarray, shape (..., 3)
        ``(x, y, z)`` in metres; shape ``(3,)`` for scalar joints.
    """
    d1, th2, th3 = np.broadcast_arrays(np.asarray(travel_m, dtype=np.float64),
                                       np.asarray(slew_rad, dtype=np.float64),
                                       np.asarray(luff_rad, dtype=np.float64))
    rho = boom_radius_m(machine, th3)
    out = np.empty(d1.shape + (3,), dtype=np.float64)
    out[..., 0] = machine.rail_x_m + rho * np.sin(th2)
    out[..., 1] = d1 + rho * np.cos(th2)
    out[..., 2] = wheel_centre_z_m(machine, th3)
    return out


def in_slew_arc(azimuth_rad, slew_start_rad: float, slew_end_rad: float) -> np.ndarray:
    """Whether azimuths lie on the arc slewed from ``slew_start_rad`` to ``slew_end_rad``.

    The arc is ``[min, max]`` of the two joint angles taken modulo 2 pi, both ends included
    (module docstring); an arc of 2 pi or more contains every azimuth.

    Parameters
    ----------
    azimuth_rad : array_like
        Azimuths (rad, from +y toward +x), any real values.
    slew_start_rad, slew_end_rad : float
        The slew joint angles at the start and the end of the cut (rad, unwrapped).

    Returns
    -------
    ndarray of bool, the shape of ``azimuth_rad``.
    """
    azimuth = np.asarray(azimuth_rad, dtype=np.float64)
    start, end = float(slew_start_rad), float(slew_end_rad)
    if not (math.isfinite(start) and math.isfinite(end)):
        raise ValueError("slew angles must be finite")
    lo, hi = (start, end) if start <= end else (end, start)
    span = hi - lo
    if span >= _TWO_PI:
        return np.isfinite(azimuth)
    # counter-clockwise (increasing azimuth) offset from the arc's low end, in [0, 2 pi)
    offset = np.mod(azimuth - lo, _TWO_PI)
    return offset <= span


def cut_floor(geometry: GridGeometry, machine: Reclaimer, travel_m: float, luff_rad: float,
              slew_start_rad: float, slew_end_rad: float) -> np.ndarray:
    """The floor of one cut's cutting envelope at every cell centre; +inf outside the footprint.

    Parameters
    ----------
    geometry : GridGeometry
        The layer grid.
    machine : Reclaimer
    travel_m : float
        Travel d1 during the cut (m).
    luff_rad : float
        Luff theta3 during the cut (rad).
    slew_start_rad, slew_end_rad : float
        Slew joint angles at the start and the end of the cut (rad, unwrapped; see the
        module docstring for arcs across +-pi).

    Returns
    -------
    ndarray, shape (nx, ny), float64
        ``c_z - Rv sqrt(1 - ((r - rho) / (Rv cos beta))^2)`` (m) at cells whose centre is in
        the swept footprint (azimuth on the arc and ``|r - rho| < Rv cos beta``), ``+inf``
        elsewhere.  Clamping a layer stack to it removes the cut's material.

    Raises
    ------
    ValueError
        If a joint value is not finite.
    """
    for name, value in (("travel_m", travel_m), ("luff_rad", luff_rad),
                        ("slew_start_rad", slew_start_rad), ("slew_end_rad", slew_end_rad)):
        if not math.isfinite(float(value)):
            raise ValueError(f"{name} must be finite, got {value!r}")
    d1 = float(travel_m)
    rho = float(boom_radius_m(machine, float(luff_rad)))
    c_z = float(wheel_centre_z_m(machine, float(luff_rad)))
    half_width = machine.half_width_m
    floor = np.full(geometry.shape, np.inf, dtype=np.float64)

    # cells whose centres can be in the annulus |r - rho| < half_width
    r_out = abs(rho) + half_width
    cell = geometry.cell_m
    ix0 = max(math.floor((machine.rail_x_m - r_out - geometry.origin_x_m) / cell) - 1, 0)
    ix1 = min(math.ceil((machine.rail_x_m + r_out - geometry.origin_x_m) / cell) + 1, geometry.nx)
    iy0 = max(math.floor((d1 - r_out - geometry.origin_y_m) / cell) - 1, 0)
    iy1 = min(math.ceil((d1 + r_out - geometry.origin_y_m) / cell) + 1, geometry.ny)
    if ix1 <= ix0 or iy1 <= iy0:
        return floor
    dx = geometry.origin_x_m + (np.arange(ix0, ix1) + 0.5) * cell - machine.rail_x_m
    dy = geometry.origin_y_m + (np.arange(iy0, iy1) + 0.5) * cell - d1
    dx2, dy2 = dx[:, None], dy[None, :]
    r = np.hypot(dx2, dy2)
    u = (r - rho) / half_width
    in_ring = np.abs(u) < 1.0
    azimuth = np.arctan2(np.broadcast_to(dx2, r.shape), np.broadcast_to(dy2, r.shape))
    hit = in_ring & in_slew_arc(azimuth, slew_start_rad, slew_end_rad)
    block = np.full(r.shape, np.inf)
    block[hit] = c_z - machine.cutting_radius_m * np.sqrt(1.0 - u[hit] ** 2)
    floor[ix0:ix1, iy0:iy1] = block
    return floor
