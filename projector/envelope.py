"""The floor of a bucket-wheel reclaimer's cutting envelope: what one cut removes.

docs/domain.md §3 is the contract; the machine's constants and its forward kinematics are
:mod:`projector.kinematics`.  Joints: travel ``d1`` (m, along the rail = +y), slew
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

import numpy as np

from projector.grid import GridGeometry
from projector.kinematics import Reclaimer, boom_height_m, boom_radius_m

__all__ = ["cut_floor", "in_slew_arc"]

_TWO_PI = 2.0 * math.pi


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
    c_z = float(boom_height_m(machine, float(luff_rad)))
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
