"""Candidate landing points on the top surface, their wheel centres and joints (thesis §5.1.2).

Candidates
----------
1. A square grid over the surface: every ``k``-th cell centre in x and y (``k`` =
   ``spacing_m`` / cell, rounded, at least 1), at the surface height there, on material.
2. The effective cutting region (docs/domain.md §3): without a bench height, the top H of the
   pile, ``z >= z_top - H`` (``z_top`` the highest surface; thesis: De = max(PL_z) - H);
   with a bench floor Z (the lowest point of the envelope, ``c_z - Rv``), the slice
   ``Z < z <= Z + H`` that bench cuts.
3. Facing the rail: the horizontal part of the surface normal points toward the rail,
   ``n_x (x_r - p_x) > 0``.
4. Wheel centre: ``c = p + Rv n`` (thesis: Cbw = pq + Rv Ns).  With a bench floor Z the
   centre must be at ``Z + Rv``: ``c = p + t n_h / |n_h| + (Z + Rv - p_z) z`` with
   ``t = sqrt(Rv^2 - (Z + Rv - p_z)^2)``, so the cutting circle still passes through p.
5. Joints by inverse kinematics (:func:`projector.kinematics.inverse_kinematics`); of
   the two travel solutions the one whose slew axis the normal faces (the smaller
   ``n_h . (c - axis)``, thesis Fig. 5.3: V points to the slew axis).  The bench then
   advances the way the boom points (``sign(cos theta2)``), into the bank.

The surface normal at p is that of the least-squares plane over a square window of
``normal_window_m`` around it (thesis: "the least square surface at pq").
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from projector.grid import GridGeometry
from projector.kinematics import PlannerMachine, inverse_kinematics

__all__ = ["surface_normals", "Candidates", "landing_candidates"]


def surface_normals(geometry: GridGeometry, surface_m, window_m: float) -> np.ndarray:
    """Unit upward normals of the least-squares plane over a window around every cell.

    Parameters
    ----------
    geometry : GridGeometry
    surface_m : array_like, shape (nx, ny)
        Heights (m), finite.
    window_m : float
        Window width (m, > 0); the half-width in cells is ``max(1, round(window / 2 / cell))``.

    Returns
    -------
    ndarray, shape (nx, ny, 3)
        ``(n_x, n_y, n_z)``, ``n_z > 0``.

    Raises
    ------
    ValueError
        On a wrong shape, non-finite heights or window.
    """
    z = np.asarray(surface_m, dtype=np.float64)
    if z.shape != geometry.shape:
        raise ValueError(f"surface_m must have shape {geometry.shape} (nx, ny), got {z.shape}")
    if not np.all(np.isfinite(z)):
        raise ValueError("surface_m must be finite")
    if not (math.isfinite(window_m) and window_m > 0):
        raise ValueError(f"window_m must be > 0, got {window_m!r}")
    k = max(1, int(round(window_m / 2 / geometry.cell_m)))
    offsets = np.arange(-k, k + 1) * geometry.cell_m
    slope_w = offsets / np.sum(offsets ** 2)       # LSQ slope along one axis
    mean_w = np.full(2 * k + 1, 1.0 / (2 * k + 1))  # uniform over the other
    gx = ndimage.correlate1d(ndimage.correlate1d(z, slope_w, axis=0, mode="nearest"),
                             mean_w, axis=1, mode="nearest")
    gy = ndimage.correlate1d(ndimage.correlate1d(z, slope_w, axis=1, mode="nearest"),
                             mean_w, axis=0, mode="nearest")
    n = np.stack([-gx, -gy, np.ones_like(z)], axis=-1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


@dataclass(frozen=True)
class Candidates:
    """Candidate landings (module docstring), N of them.

    Attributes
    ----------
    point_m : ndarray, shape (N, 3)
        Landing points on the surface (m).
    normal : ndarray, shape (N, 3)
        Unit surface normals there.
    centre_m : ndarray, shape (N, 3)
        Wheel centres (m).
    travel_m, slew_rad, luff_rad : ndarray, shape (N,)
        Joints (m, rad, rad).
    direction : ndarray, shape (N,), int
        Advance direction of the bench along y, +1 or -1.
    in_region : int
        Grid points on material in the effective cutting region and facing the rail
        (before the reachability test).
    spacing_m : float
        The grid spacing used (whole cells).
    """

    point_m: np.ndarray
    normal: np.ndarray
    centre_m: np.ndarray
    travel_m: np.ndarray
    slew_rad: np.ndarray
    luff_rad: np.ndarray
    direction: np.ndarray
    in_region: int
    spacing_m: float

    def __len__(self) -> int:
        return int(self.point_m.shape[0])


def landing_candidates(geometry: GridGeometry, surface_m, ground_m, machine: PlannerMachine, *,
                       spacing_m: float, normal_window_m: float, min_bite_m: float,
                       bench_floor_m: float | None = None) -> Candidates:
    """The candidate landings on a surface (module docstring).

    Parameters
    ----------
    geometry : GridGeometry
    surface_m, ground_m : array_like, shape (nx, ny)
        Top surface and ground (m).
    machine : PlannerMachine
    spacing_m : float
        Candidate grid spacing (m, > 0), rounded to whole cells.
    normal_window_m : float
        Width of the plane fit for normals (m).
    min_bite_m : float
        A point must be this far above the ground to be on material (m).
    bench_floor_m : float, optional
        The bench floor Z (m): the wheel centre is then at ``Z + Rv``.

    Returns
    -------
    Candidates
    """
    surface = np.asarray(surface_m, dtype=np.float64)
    ground = np.asarray(ground_m, dtype=np.float64)
    for name, a in (("surface_m", surface), ("ground_m", ground)):
        if a.shape != geometry.shape:
            raise ValueError(f"{name} must have shape {geometry.shape} (nx, ny), got {a.shape}")
    if not (math.isfinite(spacing_m) and spacing_m > 0):
        raise ValueError(f"spacing_m must be > 0, got {spacing_m!r}")
    if bench_floor_m is not None and not math.isfinite(float(bench_floor_m)):
        raise ValueError(f"bench_floor_m must be finite, got {bench_floor_m!r}")
    m = machine.reclaimer
    rv = m.cutting_radius_m
    h = machine.max_cutting_height_m
    k = max(1, int(round(spacing_m / geometry.cell_m)))
    material = surface > ground + min_bite_m
    empty = Candidates(*(np.zeros((0, 3)),) * 3, *(np.zeros(0),) * 3, np.zeros(0, int), 0,
                       k * geometry.cell_m)
    if not material.any():
        return empty
    z_top = float(surface[material].max())
    grid = np.zeros(geometry.shape, bool)
    grid[k // 2::k, k // 2::k] = True
    if bench_floor_m is None:
        region = surface >= z_top - h
    else:
        region = (surface > float(bench_floor_m)) & (surface <= float(bench_floor_m) + h)
    ix, iy = np.nonzero(grid & material & region)
    if ix.size == 0:
        return empty
    normals_all = surface_normals(geometry, surface, normal_window_m)
    n = normals_all[ix, iy]
    p = np.stack([geometry.origin_x_m + (ix + 0.5) * geometry.cell_m,
                  geometry.origin_y_m + (iy + 0.5) * geometry.cell_m, surface[ix, iy]], axis=1)
    facing = n[:, 0] * (m.rail_x_m - p[:, 0]) > 0
    p, n = p[facing], n[facing]
    in_region = int(p.shape[0])
    if bench_floor_m is None:
        c = p + rv * n
    else:
        cz = float(bench_floor_m) + rv
        dz = cz - p[:, 2]
        t = np.sqrt(np.clip(rv * rv - dz * dz, 0.0, None))
        nh = n[:, :2] / np.linalg.norm(n[:, :2], axis=1, keepdims=True)
        c = np.column_stack([p[:, :2] + t[:, None] * nh, np.full(len(p), cz)])
    if len(c) == 0:
        return empty
    travel, slew, luff, ok = inverse_kinematics(machine, c)
    # the branch whose slew axis the normal faces
    axis_y = travel
    along = n[:, 0:1] * (c[:, 0:1] - m.rail_x_m) + n[:, 1:2] * (c[:, 1:2] - axis_y)
    branch = np.argmin(np.where(np.isfinite(along), along, np.inf), axis=1)
    rows = np.arange(len(c))
    travel, slew = travel[rows, branch], slew[rows, branch]
    keep = ok
    direction = np.where(np.cos(slew) >= 0, 1, -1)
    return Candidates(p[keep], n[keep], c[keep], travel[keep], slew[keep], luff[keep],
                      direction[keep].astype(int), in_region, k * geometry.cell_m)
