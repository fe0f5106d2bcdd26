"""Where a bucket-wheel cut takes material: its footprint and floor on the deposition grid.

:meth:`sim.world.World.reclaim_cut` removes, in every column whose centre is inside the
swept footprint of a cut, all material above the cutting envelope's floor
(:func:`sim.kinematics.envelope_floor_z`, the simulator's own machine geometry, kept
independent of the planner's and the projector's on purpose: it is the ground truth they
are measured against). :func:`cut_block` finds that footprint and floor; the removal
itself is :meth:`sim.parcels.ParcelColumns._remove_above`. Lengths in metres, angles in
radians (slew from +y toward +x).
"""

from __future__ import annotations

import math

import numpy as np

from sim.grid import Grid
from sim.kinematics import Machine, boom_radius_m, envelope_floor_z


def sector_bbox(cx: float, cy: float, r_in: float, r_out: float, th_lo: float,
                th_hi: float) -> tuple[float, float, float, float]:
    """(x0, x1, y0, y1) bounding the annular sector r in [r_in, r_out], azimuth (from +y
    toward +x) in [th_lo, th_hi] around (cx, cy)."""
    if th_hi - th_lo >= 2 * math.pi:
        return cx - r_out, cx + r_out, cy - r_out, cy + r_out
    angles = [th_lo, th_hi]
    k0 = math.ceil(th_lo / (math.pi / 2))
    k1 = math.floor(th_hi / (math.pi / 2))
    angles += [k * math.pi / 2 for k in range(k0, k1 + 1)]
    xs, ys = [], []
    for r in (r_in, r_out):
        for a in angles:
            xs.append(cx + r * math.sin(a))
            ys.append(cy + r * math.cos(a))
    return min(xs), max(xs), min(ys), max(ys)


#: the block of columns a cut acts on: (rows, cols, floor (h, w) m, inside (h, w) bool);
#: the floor is +inf outside the footprint
CutBlock = tuple[slice, slice, np.ndarray, np.ndarray]


def cut_block(grid: Grid, machine: Machine, travel_m: float, luff_rad: float,
              slew_start_rad: float, slew_end_rad: float) -> tuple[np.ndarray, CutBlock | None]:
    """The footprint of one cut and the block of columns it may take material from.

    Returns
    -------
    footprint : ndarray (ny, nx) of bool
        Columns whose centre is inside the swept footprint.
    block : CutBlock or None
        The footprint's bounding block with the envelope's floor over it; None when the
        footprint is empty.
    """
    ny, nx = grid.shape
    footprint = np.zeros((ny, nx), bool)
    rho_hw = float(boom_radius_m(machine, luff_rad))
    hw = machine.cutting_radius_m * math.cos(machine.wheel_tilt_rad)
    lo, hi = min(slew_start_rad, slew_end_rad), max(slew_start_rad, slew_end_rad)
    bx0, bx1, by0, by1 = sector_bbox(machine.rail_x_m, float(travel_m), max(rho_hw - hw, 0.0),
                                     rho_hw + hw, lo, hi)
    iy0, ix0 = grid.index_of(bx0, by0)
    iy1, ix1 = grid.index_of(bx1, by1)
    iy0, ix0 = max(int(iy0) - 1, 0), max(int(ix0) - 1, 0)
    iy1, ix1 = min(int(iy1) + 2, ny), min(int(ix1) + 2, nx)
    if not (iy1 > iy0 and ix1 > ix0):
        return footprint, None
    xc = grid.x_centres[ix0:ix1]
    yc = grid.y_centres[iy0:iy1]
    floor = envelope_floor_z(machine, xc[None, :], yc[:, None], float(travel_m),
                             float(luff_rad), float(slew_start_rad), float(slew_end_rad))
    inside = ~np.isnan(floor)
    footprint[iy0:iy1, ix0:ix1] = inside
    if not inside.any():
        return footprint, None
    rr = np.flatnonzero(inside.any(axis=1))
    cc = np.flatnonzero(inside.any(axis=0))
    ry0, ry1, cx0, cx1 = rr[0], rr[-1] + 1, cc[0], cc[-1] + 1
    rows = slice(iy0 + ry0, iy0 + ry1)
    cols = slice(ix0 + cx0, ix0 + cx1)
    ins = inside[ry0:ry1, cx0:cx1]
    fl = np.where(ins, floor[ry0:ry1, cx0:cx1], np.inf)
    return footprint, (rows, cols, fl, ins)


def footprint_bbox(footprint: np.ndarray) -> tuple[int, int, int, int]:
    """(iy0, iy1, ix0, ix1): the grid indices one cell around a non-empty footprint, the
    region a cut's walls may fail in (for :meth:`sim.world.World.settle`)."""
    fr = np.flatnonzero(footprint.any(axis=1))
    fc = np.flatnonzero(footprint.any(axis=0))
    return (int(fr[0]) - 1, int(fr[-1]) + 2, int(fc[0]) - 1, int(fc[-1]) + 2)
