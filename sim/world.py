"""The simulated stockyard's pile: ground truth on a fine deposition grid.

This module is the simulator's own physical model of a stockpile. Every accuracy figure of
the product (surfaces, layers, cut tonnes and grades) is measured against it, so it models
the pile from physics (material dropped by the stacker, slope failure, the reclaimer's
cutting envelope) and keeps an exact account of every tonne; it never evaluates an
idealised pile shape (prism, cone formula) that a projector could also use.

Representation
--------------
A :class:`Grid` of square columns (cells). Each column holds a stack of **parcels**: one
parcel per *slot*, slots in stacking order (slot 0 at the bottom). A slot is one deposit
(a stacking pass, or a run of :meth:`World.deposit` calls with the same deposit id, lot
and bulk density); its deposit id, lot and bulk density are slot constants. Per slot and
cell the world stores the parcel thickness (m), the mean deposition time (ns) and the
mean grade (mass %, one value per analyte), i.e. layer-major arrays
``thickness[slot][iy, ix]``, ``time[slot][iy, ix]``, ``grade[slot][analyte, iy, ix]``.
A parcel is well mixed: material of one deposit that reaches the same column at
different moments is merged (thickness-weighted mean time and grade; one density per slot
so thickness weights are mass weights). The top surface is ``ground + sum(thickness)``.

Deposition
----------
Material leaves the stacker boom at a point or along the short segment the stacker
travels during one release step and comes to rest on the current surface with no slope
steeper than the angle of repose. Two models:

``"quasistatic"`` (default)
    The quasi-static limit of the critical-slope (BCRE / Prigozhin) sandpile model: a
    release of volume V along a source segment S settles as
    ``u = max(b, a - tan(repose) * dist(x, S))`` restricted to the part connected to the
    source, where b is the surface before the release and the apex level a is solved
    exactly (sorted cumulative sums) so that the added volume is V to rounding. This is
    the state the avalanche relaxation below converges to as its tolerance goes to zero
    (material flows down repose-angle flanks and rests where the slope is subcritical),
    with an isotropic (Euclidean) slope limit. It costs a few ms per release, so a
    full-scale pile (about 2,000 releases) builds in seconds. Piles are still emergent:
    the surface is the result of thousands of releases on the evolving surface, jittered
    and rate-modulated when a generator is given.
``"avalanche"``
    The explicit avalanche relaxation: the released volume is put on the drop cells, then
    Jacobi sweeps move material downslope wherever the drop to one of the 8 neighbours
    exceeds ``tan(repose) * distance`` (each unstable column sends half its largest excess,
    split among its lower neighbours in proportion to their excess, never more than its
    mobile material), until no column is steeper than the tolerance. Exactly volume
    conserving. On a pile whose flanks are already at repose a thin veneer spreads
    *diffusively* (hundreds to thousands of sweeps per release), so this mode is meant for
    small grids and for cross-checking the quasi-static mode.

In both modes only the newly released material moves (the base is stable), so it all
belongs to the current deposit (it slides off the top).

Reclaiming and slumping
-----------------------
:meth:`World.reclaim_cut` removes, in every column whose centre is inside the swept
footprint of a bucket-wheel cut, all material above the cutting envelope's floor
(:func:`sim.kinematics.envelope_floor_z`); parcels are clipped from the top (a
partly removed parcel keeps its lower part). The returned :class:`CutTruth` is exactly
what was removed. Afterwards (``relax=True``, the default) the walls of the cut are
allowed to fail: :meth:`World.settle` runs the avalanche relaxation with *all* material
mobile (the walls erode), records the flux through every cell edge and routes the
composition of the moving material through that flux network assuming each cell mixes
what passes through it (a sparse linear solve). Material that slumps into the hole is
**not** part of the cut that made the hole; the next cut picks it up. Slumped material is
stored in its own deposit's slot, so in a receiving column the slot order (deposit order)
is kept: if older material slides onto a column whose top is a newer deposit, it is
recorded under it (mass and grade exact, vertical position approximate, only inside the
slump zone).

Performance (2 cores, numpy): a full-scale chevron pile (0.25 m cells, 307,200 columns,
20 passes x 10,000 t, 1,800 releases) builds in about 11 s in the quasi-static mode; a cut
with its slump relaxation takes about 0.2-1 s. The avalanche mode needs minutes per pass at
that scale.

Mass accounting
---------------
``stacked == in pile + reclaimed + lost`` to floating-point rounding (lost = material that
left the grid across its border; make the grid big enough and it stays 0).
"""

from __future__ import annotations

import enum
import json
import math
from dataclasses import dataclass, field
from typing import Callable, Iterable, Mapping, Sequence

import numpy as np
from scipy import ndimage, sparse
from scipy.sparse import linalg as sparse_linalg

from sim.kinematics import Machine, boom_radius_m, envelope_floor_z

#: Analytes carried by every parcel (mass %), in this order.
ANALYTES: tuple[str, ...] = ("Fe", "SiO2", "Al2O3", "P", "LOI")

#: Default angle of repose of iron-ore fines (deg, DOMAIN.md §4).
DEFAULT_REPOSE_DEG = 37.0

#: Default bulk density of crushed iron ore (t/m3, DOMAIN.md §4).
DEFAULT_DENSITY_T_M3 = 2.4

# 8-neighbour stencil (dy, dx) and the distance to each neighbour in cells
_DIRS: tuple[tuple[int, int], ...] = ((-1, 0), (1, 0), (0, -1), (0, 1),
                                      (-1, -1), (-1, 1), (1, -1), (1, 1))
_DIST = np.array([1.0, 1.0, 1.0, 1.0, math.sqrt(2), math.sqrt(2), math.sqrt(2), math.sqrt(2)])


# --------------------------------------------------------------------------------------
# geometry
# --------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Grid:
    """A regular grid of square columns in the site frame.

    ``origin_x_m, origin_y_m`` is the *corner* of cell (0, 0); cell (iy, ix) spans
    ``[origin_x + ix*cell, origin_x + (ix+1)*cell) x [origin_y + iy*cell, ...)`` and its
    centre is half a cell further. Arrays over the grid have shape ``(ny, nx)`` (rows
    along y, the rail / the pile's long axis; columns along x, across the pile).
    """

    origin_x_m: float
    origin_y_m: float
    cell_m: float
    nx: int
    ny: int
    ground_z_m: float = 0.0

    def __post_init__(self):
        for name in ("origin_x_m", "origin_y_m", "cell_m", "ground_z_m"):
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ValueError(f"{name} must be a finite number, got {v!r}")
        if self.cell_m <= 0:
            raise ValueError(f"cell_m must be > 0, got {self.cell_m}")
        for name in ("nx", "ny"):
            v = getattr(self, name)
            if not isinstance(v, (int, np.integer)) or v < 3:
                raise ValueError(f"{name} must be an integer >= 3, got {v!r}")

    @classmethod
    def covering(cls, x_min_m: float, x_max_m: float, y_min_m: float, y_max_m: float,
                 cell_m: float, ground_z_m: float = 0.0) -> "Grid":
        """The smallest grid with cell ``cell_m`` whose cells cover the given rectangle."""
        if not (x_max_m > x_min_m and y_max_m > y_min_m):
            raise ValueError("empty rectangle")
        nx = max(3, int(math.ceil((x_max_m - x_min_m) / cell_m - 1e-9)))
        ny = max(3, int(math.ceil((y_max_m - y_min_m) / cell_m - 1e-9)))
        return cls(float(x_min_m), float(y_min_m), float(cell_m), nx, ny, float(ground_z_m))

    @property
    def shape(self) -> tuple[int, int]:
        return (self.ny, self.nx)

    @property
    def cell_area_m2(self) -> float:
        return self.cell_m * self.cell_m

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """(x_min, x_max, y_min, y_max) of the grid's outer edges (m)."""
        return (self.origin_x_m, self.origin_x_m + self.nx * self.cell_m,
                self.origin_y_m, self.origin_y_m + self.ny * self.cell_m)

    @property
    def x_centres(self) -> np.ndarray:
        """Cell-centre x of every column index, shape (nx,)."""
        return self.origin_x_m + (np.arange(self.nx) + 0.5) * self.cell_m

    @property
    def y_centres(self) -> np.ndarray:
        """Cell-centre y of every row index, shape (ny,)."""
        return self.origin_y_m + (np.arange(self.ny) + 0.5) * self.cell_m

    def centres(self) -> tuple[np.ndarray, np.ndarray]:
        """Cell-centre coordinates ``(X, Y)``, each of shape (ny, nx)."""
        return np.meshgrid(self.x_centres, self.y_centres)

    def index_of(self, x_m, y_m) -> tuple[np.ndarray, np.ndarray]:
        """Indices ``(iy, ix)`` of the cells containing the points (may be out of range)."""
        ix = np.floor((np.asarray(x_m, float) - self.origin_x_m) / self.cell_m).astype(np.int64)
        iy = np.floor((np.asarray(y_m, float) - self.origin_y_m) / self.cell_m).astype(np.int64)
        return iy, ix

    def contains(self, x_m, y_m) -> np.ndarray:
        """True where the point lies on the grid."""
        iy, ix = self.index_of(x_m, y_m)
        return (iy >= 0) & (iy < self.ny) & (ix >= 0) & (ix < self.nx)

    def centre_of(self, iy, ix) -> tuple[np.ndarray, np.ndarray]:
        """Cell-centre ``(x, y)`` of cell indices."""
        return (self.origin_x_m + (np.asarray(ix, float) + 0.5) * self.cell_m,
                self.origin_y_m + (np.asarray(iy, float) + 0.5) * self.cell_m)

    def to_dict(self) -> dict:
        return {"origin_x_m": float(self.origin_x_m), "origin_y_m": float(self.origin_y_m),
                "cell_m": float(self.cell_m), "nx": int(self.nx), "ny": int(self.ny),
                "ground_z_m": float(self.ground_z_m)}


class Pattern(str, enum.Enum):
    """Stacking patterns (thesis §2.1, Fig. 2.1)."""

    CHEVRON = "chevron"
    WINDROW = "windrow"
    CONE_SHELL = "cone_shell"


# --------------------------------------------------------------------------------------
# truth records
# --------------------------------------------------------------------------------------

@dataclass
class CutTruth:
    """Exactly what one reclaimer cut removed from the pile.

    ``tonnes`` = sum over removed parcel pieces of volume x bulk density; ``grade`` is the
    mass-weighted mean of the removed pieces per analyte (NaN when nothing was removed).
    ``footprint`` (bool, grid shape) marks the columns whose centre is inside the swept
    footprint. ``slump_m3`` is the volume that moved in the relaxation after the cut (not
    part of this cut's tonnes).
    """

    time_ns: int
    travel_m: float
    luff_rad: float
    slew_start_rad: float
    slew_end_rad: float
    tonnes: float
    volume_m3: float
    grade: dict
    tonnes_by_deposit: dict
    tonnes_by_lot: dict
    mean_deposition_time_ns: float | None
    footprint: np.ndarray = field(repr=False)
    slump_m3: float = 0.0
    slump_lost_tonnes: float = 0.0

    @property
    def footprint_cells(self) -> int:
        return int(np.count_nonzero(self.footprint))

    def to_dict(self) -> dict:
        """JSON-serialisable record (the footprint as a cell count and index bounds)."""
        fp = np.nonzero(self.footprint)
        bounds = None
        if fp[0].size:
            bounds = [int(fp[0].min()), int(fp[0].max()), int(fp[1].min()), int(fp[1].max())]
        return {"time_ns": int(self.time_ns), "travel_m": float(self.travel_m),
                "luff_rad": float(self.luff_rad), "slew_start_rad": float(self.slew_start_rad),
                "slew_end_rad": float(self.slew_end_rad), "tonnes": float(self.tonnes),
                "volume_m3": float(self.volume_m3),
                "grade": {k: _json_float(v) for k, v in self.grade.items()},
                "tonnes_by_deposit": {str(k): float(v) for k, v in self.tonnes_by_deposit.items()},
                "tonnes_by_lot": {str(k): float(v) for k, v in self.tonnes_by_lot.items()},
                "mean_deposition_time_ns": _json_float(self.mean_deposition_time_ns),
                "footprint_cells": self.footprint_cells, "footprint_index_bounds": bounds,
                "slump_m3": float(self.slump_m3),
                "slump_lost_tonnes": float(self.slump_lost_tonnes)}


def _json_float(v):
    if v is None:
        return None
    v = float(v)
    return v if math.isfinite(v) else None


# --------------------------------------------------------------------------------------
# the world
# --------------------------------------------------------------------------------------

class World:
    """Mutable state of one simulated pile (see the module docstring).

    Parameters
    ----------
    grid : Grid
        The deposition grid (e.g. 0.25 m cells full scale, 2 mm bench scale).
    repose_deg : float
        Angle of repose of the material (deg).
    analytes : sequence of str
        Names of the grade components carried by each parcel.
    deposition : {"quasistatic", "avalanche"}
        Deposition model (module docstring).
    relax_tol : float
        Stability tolerance of the avalanche relaxation as a fraction of the critical drop
        ``tan(repose) * cell`` (a column is stable when no drop to a neighbour exceeds the
        critical drop by more than this).
    max_relax_iterations : int
        Safety limit on Jacobi sweeps per relaxation (RuntimeError beyond it).

    Deterministic: the same calls give the same state; randomness enters only through
    generators passed to :meth:`stack_pass`.
    """

    def __init__(self, grid: Grid, repose_deg: float = DEFAULT_REPOSE_DEG, *,
                 analytes: Sequence[str] = ANALYTES, deposition: str = "quasistatic",
                 relax_tol: float = 0.01, max_relax_iterations: int = 200_000):
        if not isinstance(grid, Grid):
            raise TypeError("grid must be a Grid")
        if not (0.0 < float(repose_deg) < 89.0):
            raise ValueError(f"repose_deg must be in (0, 89), got {repose_deg}")
        if deposition not in ("quasistatic", "avalanche"):
            raise ValueError(f"deposition must be 'quasistatic' or 'avalanche', got {deposition!r}")
        if not (0.0 < relax_tol < 1.0):
            raise ValueError("relax_tol must be in (0, 1)")
        analytes = tuple(str(a) for a in analytes)
        if not analytes or len(set(analytes)) != len(analytes):
            raise ValueError("analytes must be unique names")
        self.grid = grid
        self.repose_deg = float(repose_deg)
        self.analytes = analytes
        self.deposition = deposition
        self.relax_tol = float(relax_tol)
        self.max_relax_iterations = int(max_relax_iterations)
        self._tan = math.tan(math.radians(self.repose_deg))
        self._crit = self._tan * grid.cell_m * _DIST  # critical drop to each neighbour (m)
        self._tol_m = self.relax_tol * self._tan * grid.cell_m
        ny, nx = grid.ny, grid.nx
        # surface, padded by one cell of ground all round (the pad is the border sink)
        self._surf = np.full((ny + 2, nx + 2), float(grid.ground_z_m))
        # slots
        self._thk: list[np.ndarray] = []
        self._tim: list[np.ndarray] = []   # mean deposition time, ns after the epoch
        self._grd: list[np.ndarray] = []   # (n_analytes, ny, nx)
        self._slot_deposit: list = []
        self._slot_lot: list[int] = []
        self._slot_rho: list[float] = []
        self._lots: list = []
        self._lot_index: dict = {}
        self._epoch_ns: int | None = None
        self._last_time_ns: int | None = None
        # ledgers (tonnes and tonnes x grade)
        na = len(analytes)
        self._stacked_t = 0.0
        self._stacked_tg = np.zeros(na)
        self._stacked_by_dep: dict = {}
        self._stacked_by_lot: dict = {}
        self._reclaimed_t = 0.0
        self._reclaimed_tg = np.zeros(na)
        self._lost_t = 0.0
        self._lost_tg = np.zeros(na)
        self._releases: list[dict] = []
        self._passes: list[dict] = []
        self.cuts: list[CutTruth] = []
        self._settles: list[dict] = []
        self.border_contacts = 0  # releases whose material reached the grid border

    # ---------------------------------------------------------------- small helpers
    @property
    def tan_repose(self) -> float:
        return self._tan

    @property
    def n_slots(self) -> int:
        return len(self._thk)

    @property
    def lots(self) -> list:
        """Lot labels in index order."""
        return list(self._lots)

    def _grade_vector(self, grade) -> np.ndarray:
        if isinstance(grade, Mapping):
            missing = [a for a in self.analytes if a not in grade]
            if missing:
                raise ValueError(f"grade lacks analytes {missing}")
            g = np.array([float(grade[a]) for a in self.analytes])
        else:
            g = np.asarray(grade, float).reshape(-1)
            if g.size != len(self.analytes):
                raise ValueError(f"grade must have {len(self.analytes)} values, got {g.size}")
        if not np.all(np.isfinite(g)):
            raise ValueError("grade values must be finite")
        return g

    def _lot_idx(self, lot) -> int:
        if lot is None or isinstance(lot, (float, bool)):
            raise ValueError(f"lot must be an int or str label, got {lot!r}")
        key = lot.item() if isinstance(lot, np.integer) else lot
        if key not in self._lot_index:
            self._lot_index[key] = len(self._lots)
            self._lots.append(key)
        return self._lot_index[key]

    def _check_time(self, time_ns) -> int:
        if isinstance(time_ns, bool) or not isinstance(time_ns, (int, np.integer)):
            raise TypeError(f"time_ns must be an integer (ns), got {type(time_ns).__name__}")
        return int(time_ns)

    def _rel_time(self, time_ns: int) -> float:
        if self._epoch_ns is None:
            self._epoch_ns = int(time_ns)
        return float(int(time_ns) - self._epoch_ns)

    def _slot_for(self, deposit_id, lot_idx: int, rho: float) -> int:
        if self._thk and (self._slot_deposit[-1] == deposit_id and self._slot_lot[-1] == lot_idx
                          and self._slot_rho[-1] == rho):
            return len(self._thk) - 1
        ny, nx = self.grid.shape
        self._thk.append(np.zeros((ny, nx)))
        self._tim.append(np.zeros((ny, nx)))
        self._grd.append(np.zeros((len(self.analytes), ny, nx)))
        self._slot_deposit.append(deposit_id)
        self._slot_lot.append(lot_idx)
        self._slot_rho.append(rho)
        return len(self._thk) - 1

    # ---------------------------------------------------------------- deposition
    def deposit(self, x_m: float, y_m: float, tonnes: float, time_ns: int, deposit_id, lot,
                grade, bulk_density_t_m3: float = DEFAULT_DENSITY_T_M3, *,
                x_end_m: float | None = None, y_end_m: float | None = None) -> dict:
        """Release ``tonnes`` at a point (or uniformly along the segment to ``x_end/y_end``)
        and let it settle. Returns the release record (tonnes, lost tonnes, slot)."""
        time_ns = self._check_time(time_ns)
        tonnes = float(tonnes)
        if not (math.isfinite(tonnes) and tonnes >= 0):
            raise ValueError(f"tonnes must be finite and >= 0, got {tonnes}")
        rho = float(bulk_density_t_m3)
        if not (math.isfinite(rho) and rho > 0):
            raise ValueError(f"bulk density must be > 0, got {bulk_density_t_m3}")
        for v in (x_m, y_m) + tuple(v for v in (x_end_m, y_end_m) if v is not None):
            if not math.isfinite(float(v)):
                raise ValueError("positions must be finite")
        if (x_end_m is None) != (y_end_m is None):
            raise ValueError("give both x_end_m and y_end_m or neither")
        x1 = float(x_m if x_end_m is None else x_end_m)
        y1 = float(y_m if y_end_m is None else y_end_m)
        if not np.all(self.grid.contains([x_m, x1], [y_m, y1])):
            raise ValueError("the release point (segment) must lie on the grid")
        if self._last_time_ns is not None and time_ns < self._last_time_ns:
            raise ValueError(f"deposition time {time_ns} is before the previous release "
                             f"{self._last_time_ns}: new material lies on top, so times must "
                             "not decrease")
        g = self._grade_vector(grade)
        lot_idx = self._lot_idx(lot)
        self._last_time_ns = time_ns
        slot = self._slot_for(deposit_id, lot_idx, rho)
        trel = self._rel_time(time_ns)
        vol = tonnes / rho
        lost_vol = 0.0
        if vol > 0:
            if self.deposition == "quasistatic":
                lost_vol = self._release_quasistatic(float(x_m), float(y_m), x1, y1, vol, slot,
                                                     trel, g)
            else:
                lost_vol = self._release_avalanche(float(x_m), float(y_m), x1, y1, vol, slot,
                                                   trel, g)
        lost_t = lost_vol * rho
        # ledgers
        self._stacked_t += tonnes
        self._stacked_tg += tonnes * g
        self._stacked_by_dep[deposit_id] = self._stacked_by_dep.get(deposit_id, 0.0) + tonnes
        lot_key = self._lots[lot_idx]
        self._stacked_by_lot[lot_key] = self._stacked_by_lot.get(lot_key, 0.0) + tonnes
        self._lost_t += lost_t
        self._lost_tg += lost_t * g
        if lost_vol > 0:
            self.border_contacts += 1
        rec = {"time_ns": time_ns, "x_m": float(x_m), "y_m": float(y_m), "x_end_m": x1,
               "y_end_m": y1, "tonnes": tonnes, "lost_tonnes": lost_t, "deposit_id": deposit_id,
               "lot": lot_key, "slot": slot, "density_t_m3": rho,
               "grade": {a: float(v) for a, v in zip(self.analytes, g)}}
        self._releases.append(rec)
        return rec

    def _merge(self, slot: int, iy0: int, ix0: int, add: np.ndarray, trel, g):
        """Add thickness ``add`` (block at (iy0, ix0)) to ``slot`` with time ``trel`` and
        grade ``g`` (scalars/vector, or arrays per cell: trel (h, w), g (A, h, w))."""
        h, w = add.shape
        sl = (slice(iy0, iy0 + h), slice(ix0, ix0 + w))
        pos = add > 0
        if not pos.any():
            return
        thk = self._thk[slot][sl]
        tim = self._tim[slot][sl]
        grd = self._grd[slot][(slice(None),) + sl]
        old = thk[pos]
        a = add[pos]
        new = old + a
        tv = trel[pos] if np.ndim(trel) == 2 else trel
        tim[pos] = (tim[pos] * old + tv * a) / new
        gv = g[:, pos] if np.ndim(g) == 3 else np.asarray(g)[:, None]
        grd[:, pos] = (grd[:, pos] * old + gv * a) / new
        thk[pos] = new
        sv = self._surf[1 + iy0:1 + iy0 + h, 1 + ix0:1 + ix0 + w]
        sv[pos] += a

    def _release_quasistatic(self, x0, y0, x1, y1, vol, slot, trel, g) -> float:
        """Settle ``vol`` released along segment (x0,y0)-(x1,y1); returns lost volume."""
        grid = self.grid
        c = grid.cell_m
        area = grid.cell_area_m2
        t = self._tan
        ground = grid.ground_z_m
        # surface at the source: max over the cells the segment touches (+1 cell)
        iy_a, ix_a = grid.index_of([x0, x1], [y0, y1])
        sy0 = int(np.clip(min(iy_a) - 1, 0, grid.ny - 1))
        sy1 = int(np.clip(max(iy_a) + 1, 0, grid.ny - 1))
        sx0 = int(np.clip(min(ix_a) - 1, 0, grid.nx - 1))
        sx1 = int(np.clip(max(ix_a) + 1, 0, grid.nx - 1))
        b_src = float(self._surf[1 + sy0:2 + sy1, 1 + sx0:2 + sx1].max())
        # height of a cone of slope 2 tan holding vol: bounds the rise at the source on a
        # stable base (b_i <= b_src + tan * d_i); verified below and doubled if short
        h_up = 1.5 * (3.0 * vol * (2 * t) ** 2 / math.pi) ** (1.0 / 3.0) + 2 * t * c
        blocked = None
        for _ in range(60):
            a_up = b_src + h_up
            reach = (a_up - ground) / t + c
            # window of cell indices (may extend past the grid: virtual ground cells)
            wy0, wx0 = [int(v) for v in grid.index_of(min(x0, x1) - reach, min(y0, y1) - reach)]
            wy1, wx1 = [int(v) + 1 for v in grid.index_of(max(x0, x1) + reach,
                                                          max(y0, y1) + reach)]
            b = np.full((wy1 - wy0, wx1 - wx0), float(ground))
            gy0, gy1 = max(wy0, 0), min(wy1, grid.ny)
            gx0, gx1 = max(wx0, 0), min(wx1, grid.nx)
            if gy1 > gy0 and gx1 > gx0:
                b[gy0 - wy0:gy1 - wy0, gx0 - wx0:gx1 - wx0] = \
                    self._surf[1 + gy0:1 + gy1, 1 + gx0:1 + gx1]
            xc = grid.origin_x_m + (np.arange(wx0, wx1) + 0.5) * c
            yc = grid.origin_y_m + (np.arange(wy0, wy1) + 0.5) * c
            d = _segment_distance(xc[None, :], yc[:, None], x0, y0, x1, y1)
            k = b + t * d
            if blocked is not None:
                if blocked.shape != k.shape:
                    blocked = None
                else:
                    k[blocked] = np.inf
            a, ok = _solve_fill_level(k, vol / area, a_up)
            if not ok:
                h_up *= 2.0
                blocked = None
                continue
            fill = np.maximum(a - k, 0.0)
            mask = fill > 0
            # only the part connected to the source can be reached by flowing material
            lab, nlab = ndimage.label(mask, structure=np.ones((3, 3), bool))
            if nlab > 1:
                src = mask & (d <= 0.75 * c)
                keep_labels = np.unique(lab[src])
                if keep_labels.size == 0:  # degenerate: the component nearest the source
                    keep_labels = np.array([lab.flat[np.argmin(np.where(mask, d, np.inf))]])
                drop = mask & ~np.isin(lab, keep_labels)
                if drop.any():
                    blocked = drop if blocked is None else (blocked | drop)
                    continue
            break
        else:  # pragma: no cover - defensive
            raise RuntimeError("quasi-static release did not converge")
        # exact volume: rescale the (tiny) rounding residual
        s = fill.sum()
        if s > 0:
            fill *= (vol / area) / s
        # split into on-grid and off-grid (lost) parts
        on = np.zeros_like(fill, bool)
        if gy1 > gy0 and gx1 > gx0:
            on[gy0 - wy0:gy1 - wy0, gx0 - wx0:gx1 - wx0] = True
        lost = float(fill[~on].sum() * area) if (~on).any() else 0.0
        # touching the outermost grid cells counts as reaching the border too
        if gy1 > gy0 and gx1 > gx0:
            blk = fill[gy0 - wy0:gy1 - wy0, gx0 - wx0:gx1 - wx0]
            rows = np.flatnonzero(blk.any(axis=1))
            cols = np.flatnonzero(blk.any(axis=0))
            if rows.size:
                r0, r1 = rows[0], rows[-1] + 1
                q0, q1 = cols[0], cols[-1] + 1
                self._merge(slot, gy0 + r0, gx0 + q0, blk[r0:r1, q0:q1], trel, g)
        return lost

    def _release_avalanche(self, x0, y0, x1, y1, vol, slot, trel, g) -> float:
        grid = self.grid
        c = grid.cell_m
        n = max(2, int(math.ceil(math.hypot(x1 - x0, y1 - y0) / c)) * 2 + 1)
        s = (np.arange(n) + 0.5) / n
        xs = x0 + (x1 - x0) * s
        ys = y0 + (y1 - y0) * s
        iy, ix = grid.index_of(xs, ys)
        iy = np.clip(iy, 0, grid.ny - 1)
        ix = np.clip(ix, 0, grid.nx - 1)
        ny, nx = grid.shape
        mob = np.zeros((ny + 2, nx + 2))
        np.add.at(mob, (iy + 1, ix + 1), vol / grid.cell_area_m2 / n)
        bbox = (int(iy.min()) + 1, int(iy.max()) + 2, int(ix.min()) + 1, int(ix.max()) + 2)
        _, lost_thk, touched = self._relax(self._surf, mob, bbox)
        r0, r1, c0, c1 = touched
        blk = mob[r0:r1, c0:c1]
        # renormalise the rounding residual of the flux arithmetic
        total = blk.sum() + lost_thk
        if total > 0:
            scale = (vol / grid.cell_area_m2) / total
            blk = blk * scale
            lost_thk *= scale
        self._merge(slot, r0 - 1, c0 - 1, blk, trel, g)
        return float(lost_thk * grid.cell_area_m2)

    # ---------------------------------------------------------------- relaxation kernel
    def _relax(self, base: np.ndarray, mob: np.ndarray, bbox, flux: np.ndarray | None = None):
        """Jacobi avalanche relaxation of the mobile layer ``mob`` on ``base`` (both padded
        (ny+2, nx+2); modified in place). ``bbox`` = (r0, r1, c0, c1) in padded indices
        covers every column that may be unstable. Material pushed into the pad (the
        border) is removed and reported as lost. With ``flux`` (8, ny+2, nx+2), the volume
        (in m of thickness) sent from each cell to each neighbour is accumulated.

        Returns (iterations, lost thickness sum, touched bbox incl. receivers)."""
        nyp, nxp = mob.shape
        r0, r1, c0, c1 = (max(1, bbox[0]), min(nyp - 1, bbox[1]), max(1, bbox[2]),
                          min(nxp - 1, bbox[3]))
        t0, t1, u0, u1 = r0 - 1, r1 + 1, c0 - 1, c1 + 1
        crit = self._crit
        tol = self._tol_m
        lost = 0.0
        it = 0
        while r1 > r0 and c1 > c0:
            if it >= self.max_relax_iterations:
                raise RuntimeError(f"avalanche relaxation did not settle in {it} sweeps")
            hblk = base[r0 - 1:r1 + 1, c0 - 1:c1 + 1] + mob[r0 - 1:r1 + 1, c0 - 1:c1 + 1]
            h, w = r1 - r0, c1 - c0
            centre = hblk[1:-1, 1:-1]
            excess = []
            emax = None
            esum = None
            for k, (dy, dx) in enumerate(_DIRS):
                e = centre - hblk[1 + dy:1 + dy + h, 1 + dx:1 + dx + w]
                e -= crit[k]
                np.maximum(e, 0.0, out=e)
                excess.append(e)
                if emax is None:
                    emax = e.copy()
                    esum = e.copy()
                else:
                    np.maximum(emax, e, out=emax)
                    esum += e
            mc = mob[r0:r1, c0:c1]
            send = (emax > tol) & (mc > 0)
            if not send.any():
                break
            out = np.minimum(mc, 0.5 * emax)
            out *= send
            wgt = np.zeros_like(out)
            np.divide(out, esum, out=wgt, where=send)
            mc -= out
            for k, (dy, dx) in enumerate(_DIRS):
                f = excess[k]
                f *= wgt
                mob[r0 + dy:r1 + dy, c0 + dx:c1 + dx] += f
                if flux is not None:
                    flux[k, r0:r1, c0:c1] += f
            if r0 == 1 or c0 == 1 or r1 == nyp - 1 or c1 == nxp - 1:
                lost += (mob[0, :].sum() + mob[-1, :].sum() + mob[1:-1, 0].sum()
                         + mob[1:-1, -1].sum())
                mob[0, :] = 0.0
                mob[-1, :] = 0.0
                mob[:, 0] = 0.0
                mob[:, -1] = 0.0
            rows = np.flatnonzero(send.any(axis=1))
            cols = np.flatnonzero(send.any(axis=0))
            nr0, nr1 = r0 + rows[0] - 1, r0 + rows[-1] + 2
            nc0, nc1 = c0 + cols[0] - 1, c0 + cols[-1] + 2
            t0, t1 = min(t0, nr0 - 1), max(t1, nr1 + 1)
            u0, u1 = min(u0, nc0 - 1), max(u1, nc1 + 1)
            r0, r1 = max(1, nr0), min(nyp - 1, nr1)
            c0, c1 = max(1, nc0), min(nxp - 1, nc1)
            it += 1
        touched = (max(1, t0), min(nyp - 1, t1), max(1, u0), min(nxp - 1, u1))
        return it, float(lost), touched

    # ---------------------------------------------------------------- stacking patterns
    def stack_pass(self, pattern, start_y_m: float, end_y_m: float, x_centre_m: float,
                   tonnes: float, t_start_ns: int, t_end_ns: int, deposit_id, lot,
                   grade_fn: Callable[[int], object],
                   bulk_density_t_m3: float = DEFAULT_DENSITY_T_M3, *,
                   step_m: float | None = None, n_rows: int = 3,
                   row_spacing_m: float | None = None, row_offset_m: float = 0.0,
                   n_cones: int | None = None, cone_spacing_m: float | None = None,
                   releases_per_cone: int = 4, rng: np.random.Generator | None = None,
                   jitter_m: float = 0.0, rate_cv: float = 0.0) -> dict:
        """One stacking pass, released in small time steps.

        The stacker releases ``tonnes`` between ``t_start_ns`` and ``t_end_ns`` (uniform
        rate, or modulated by ``rate_cv``); each release step drops the material of its
        time interval along the path the boom covers in it, at the belt grade
        ``grade_fn(mid-time of the step)``, and lets it settle before the next step.

        - CHEVRON: one run along y from ``start_y_m`` to ``end_y_m`` at ``x = x_centre_m``.
        - WINDROW: ``n_rows`` parallel runs (alternating direction) at
          ``x_centre_m + row_offset_m + (j - (n_rows-1)/2) * row_spacing_m``; the default
          spacing puts neighbouring ridges toe to toe. Offset a later pass by half a spacing
          to fill the valleys.
        - CONE_SHELL: ``n_cones`` stations evenly from ``start_y_m`` to ``end_y_m``; the
          stacker stands at each and releases its share in ``releases_per_cone`` steps.

        ``step_m`` (default 8 cells) is the boom travel per release. With ``rng``,
        ``jitter_m`` (sd of the release point across the pile, m) and ``rate_cv``
        (coefficient of variation of the per-step tonnes, renormalised to ``tonnes``)
        make the pass irregular. Returns the pass record.
        """
        pattern = Pattern(pattern)
        t_start_ns = self._check_time(t_start_ns)
        t_end_ns = self._check_time(t_end_ns)
        if t_end_ns < t_start_ns:
            raise ValueError("t_end_ns < t_start_ns")
        tonnes = float(tonnes)
        if not (math.isfinite(tonnes) and tonnes >= 0):
            raise ValueError("tonnes must be finite and >= 0")
        rho = float(bulk_density_t_m3)
        if not (math.isfinite(rho) and rho > 0):
            raise ValueError("bulk density must be > 0")
        if (jitter_m > 0 or rate_cv > 0) and rng is None:
            raise ValueError("jitter_m / rate_cv need a numpy Generator (rng)")
        step = float(step_m) if step_m is not None else 8.0 * self.grid.cell_m
        if step <= 0:
            raise ValueError("step_m must be > 0")
        y0, y1, xc = float(start_y_m), float(end_y_m), float(x_centre_m)
        length = abs(y1 - y0)

        # build the release list: (xa, ya, xb, yb, weight)
        segs: list[tuple[float, float, float, float]] = []
        if pattern is Pattern.CHEVRON:
            segs = _split_run(xc, y0, y1, step)
        elif pattern is Pattern.WINDROW:
            if n_rows < 1:
                raise ValueError("n_rows must be >= 1")
            if row_spacing_m is None:
                a_row = tonnes / rho / max(length, step) / n_rows
                row_spacing_m = 2.0 * math.sqrt(max(a_row, 0.0) / self._tan)
            for j in range(n_rows):
                xr = xc + row_offset_m + (j - (n_rows - 1) / 2.0) * float(row_spacing_m)
                segs += _split_run(xr, y0, y1, step) if j % 2 == 0 else _split_run(xr, y1, y0, step)
        else:  # CONE_SHELL
            if n_cones is None:
                spacing = float(cone_spacing_m) if cone_spacing_m else 4.0 * step
                n_cones = max(1, int(round(length / spacing)) + 1)
            if n_cones < 1 or releases_per_cone < 1:
                raise ValueError("n_cones and releases_per_cone must be >= 1")
            ys = [y0] if n_cones == 1 else list(np.linspace(y0, y1, n_cones))
            for yy in ys:
                segs += [(xc, float(yy), xc, float(yy))] * int(releases_per_cone)
        n = len(segs)
        w = np.ones(n)
        if rate_cv > 0:
            sig = math.sqrt(math.log(1.0 + rate_cv ** 2))
            w = rng.lognormal(-0.5 * sig * sig, sig, n)
        w_lengths = np.array([max(math.hypot(s[2] - s[0], s[3] - s[1]), 0.0) for s in segs])
        if pattern is not Pattern.CONE_SHELL and w_lengths.sum() > 0:
            w = w * w_lengths  # uniform tonnes per metre of boom travel
        w = w / w.sum()
        tonnes_k = tonnes * w
        # time: each release covers a share of the pass time proportional to its tonnes
        edges = np.concatenate([[0.0], np.cumsum(w)])
        edges[-1] = 1.0
        mids = 0.5 * (edges[:-1] + edges[1:])
        dur = t_end_ns - t_start_ns
        jit = rng.normal(0.0, jitter_m, n) if jitter_m > 0 else np.zeros(n)
        lost = 0.0
        tg = np.zeros(len(self.analytes))
        for k, (xa, ya, xb, yb) in enumerate(segs):
            tm = t_start_ns + int(round(dur * float(mids[k])))
            tm = min(max(tm, t_start_ns), t_end_ns)
            if self._last_time_ns is not None and tm < self._last_time_ns:
                tm = self._last_time_ns
            g = self._grade_vector(grade_fn(tm))
            same = (xa == xb and ya == yb)
            rec = self.deposit(xa + jit[k], ya, float(tonnes_k[k]), tm, deposit_id, lot, g, rho,
                               x_end_m=None if same else xb + jit[k],
                               y_end_m=None if same else yb)
            lost += rec["lost_tonnes"]
            tg += float(tonnes_k[k]) * g
        rec = {"pattern": pattern.value, "deposit_id": deposit_id, "lot": lot, "tonnes": tonnes,
               "volume_m3": tonnes / rho, "density_t_m3": rho, "t_start_ns": t_start_ns,
               "t_end_ns": t_end_ns, "start_y_m": y0, "end_y_m": y1, "x_centre_m": xc,
               "n_releases": n, "lost_tonnes": lost,
               "grade": {a: (float(v / tonnes) if tonnes > 0 else None)
                         for a, v in zip(self.analytes, tg)},
               "slot": self.n_slots - 1}
        self._passes.append(rec)
        return rec

    # ---------------------------------------------------------------- reclaiming
    def _column_clip(self, slots: Sequence[int], rows: slice, cols: slice, z_cut: np.ndarray,
                     where: np.ndarray):
        """Clip the columns of a block at height ``z_cut`` (only where ``where``).

        Returns (removed (S, h, w) thickness, keep (S, h, w) thickness)."""
        thk = np.stack([self._thk[s][rows, cols] for s in slots])
        bottom = self.grid.ground_z_m + np.cumsum(thk, axis=0) - thk
        keep = np.clip(z_cut[None] - bottom, 0.0, thk)
        keep = np.where(where[None], keep, thk)
        return thk - keep, keep

    def reclaim_cut(self, machine: Machine, travel_m: float, luff_rad: float,
                    slew_start_rad: float, slew_end_rad: float, time_ns: int, *,
                    relax: bool = True) -> CutTruth:
        """One bucket-wheel cut: remove everything above the envelope floor in the footprint.

        With ``relax`` the pile then settles (:meth:`settle`); what slumps into the hole is
        not part of this cut (see ``CutTruth.slump_m3``)."""
        time_ns = self._check_time(time_ns)
        for v in (travel_m, luff_rad, slew_start_rad, slew_end_rad):
            if not math.isfinite(float(v)):
                raise ValueError("cut joints must be finite")
        grid = self.grid
        ny, nx = grid.shape
        footprint = np.zeros((ny, nx), bool)
        na = len(self.analytes)
        rho_hw = float(boom_radius_m(machine, luff_rad))
        hw = machine.cutting_radius_m * math.cos(machine.wheel_tilt_rad)
        lo, hi = min(slew_start_rad, slew_end_rad), max(slew_start_rad, slew_end_rad)
        bx0, bx1, by0, by1 = _sector_bbox(machine.rail_x_m, float(travel_m), max(rho_hw - hw, 0.0),
                                          rho_hw + hw, lo, hi)
        iy0, ix0 = grid.index_of(bx0, by0)
        iy1, ix1 = grid.index_of(bx1, by1)
        iy0, ix0 = max(int(iy0) - 1, 0), max(int(ix0) - 1, 0)
        iy1, ix1 = min(int(iy1) + 2, ny), min(int(ix1) + 2, nx)
        removed_vol = 0.0
        tonnes = 0.0
        tg = np.zeros(na)
        ttime = 0.0
        by_dep: dict = {}
        by_lot: dict = {}
        if iy1 > iy0 and ix1 > ix0:
            xc = grid.x_centres[ix0:ix1]
            yc = grid.y_centres[iy0:iy1]
            floor = envelope_floor_z(machine, xc[None, :], yc[:, None], float(travel_m),
                                     float(luff_rad), float(slew_start_rad), float(slew_end_rad))
            inside = ~np.isnan(floor)
            footprint[iy0:iy1, ix0:ix1] = inside
            if inside.any():
                rr = np.flatnonzero(inside.any(axis=1))
                cc = np.flatnonzero(inside.any(axis=0))
                ry0, ry1, cx0, cx1 = rr[0], rr[-1] + 1, cc[0], cc[-1] + 1
                rows = slice(iy0 + ry0, iy0 + ry1)
                cols = slice(ix0 + cx0, ix0 + cx1)
                ins = inside[ry0:ry1, cx0:cx1]
                fl = np.where(ins, floor[ry0:ry1, cx0:cx1], np.inf)
                surf = self._surf[1:-1, 1:-1][rows, cols]
                hit = ins & (surf > fl)
                slots = [s for s in range(self.n_slots) if self._thk[s][rows, cols][hit].any()] \
                    if hit.any() else []
                if slots:
                    rem, keep = self._column_clip(slots, rows, cols, fl, hit)
                    area = grid.cell_area_m2
                    for j, s in enumerate(slots):
                        r = rem[j]
                        vs = float(r.sum()) * area
                        if vs <= 0:
                            continue
                        rho = self._slot_rho[s]
                        ts = vs * rho
                        removed_vol += vs
                        tonnes += ts
                        tg += rho * area * np.einsum("ahw,hw->a", self._grd[s][:, rows, cols], r)
                        ttime += rho * area * float((self._tim[s][rows, cols] * r).sum())
                        dep = self._slot_deposit[s]
                        by_dep[dep] = by_dep.get(dep, 0.0) + ts
                        lot = self._lots[self._slot_lot[s]]
                        by_lot[lot] = by_lot.get(lot, 0.0) + ts
                        self._thk[s][rows, cols] = keep[j]
                    self._surf[1:-1, 1:-1][rows, cols] = grid.ground_z_m + np.sum(
                        [self._thk[s][rows, cols] for s in range(self.n_slots)], axis=0)
        grade = {a: (float(v / tonnes) if tonnes > 0 else float("nan"))
                 for a, v in zip(self.analytes, tg)}
        mean_t = (ttime / tonnes + self._epoch_ns) if tonnes > 0 else None
        self._reclaimed_t += tonnes
        self._reclaimed_tg += tg
        truth = CutTruth(time_ns=time_ns, travel_m=float(travel_m), luff_rad=float(luff_rad),
                         slew_start_rad=float(slew_start_rad), slew_end_rad=float(slew_end_rad),
                         tonnes=tonnes, volume_m3=removed_vol, grade=grade,
                         tonnes_by_deposit=by_dep, tonnes_by_lot=by_lot,
                         mean_deposition_time_ns=mean_t, footprint=footprint)
        self.cuts.append(truth)
        if relax and removed_vol > 0:
            fr = np.flatnonzero(footprint.any(axis=1))
            fc = np.flatnonzero(footprint.any(axis=0))
            res = self.settle(bbox=(int(fr[0]) - 1, int(fr[-1]) + 2, int(fc[0]) - 1,
                                    int(fc[-1]) + 2))
            truth.slump_m3 = res["moved_m3"]
            truth.slump_lost_tonnes = res["lost_tonnes"]
        return truth

    def settle_cut(self, parts: list[CutTruth]) -> None:
        """Let the walls of a cut made in sub-sweeps (``reclaim_cut(..., relax=False)``)
        slump once the wheel has passed, if any sub-sweep took material; the slump is
        recorded on the last part."""
        if not parts or sum(p.volume_m3 for p in parts) <= 0:
            return
        footprint = np.logical_or.reduce([p.footprint for p in parts])
        fr = np.flatnonzero(footprint.any(axis=1))
        fc = np.flatnonzero(footprint.any(axis=0))
        res = self.settle(bbox=(int(fr[0]) - 1, int(fr[-1]) + 2, int(fc[0]) - 1,
                                int(fc[-1]) + 2))
        parts[-1].slump_m3 = res["moved_m3"]
        parts[-1].slump_lost_tonnes = res["lost_tonnes"]

    # ---------------------------------------------------------------- slope failure
    def unstable_columns(self) -> np.ndarray:
        """Bool (ny, nx): columns steeper than repose (beyond tolerance) toward a neighbour
        and holding material."""
        s = self._surf
        ny, nx = self.grid.shape
        centre = s[1:-1, 1:-1]
        emax = np.zeros((ny, nx))
        for k, (dy, dx) in enumerate(_DIRS):
            np.maximum(emax, centre - s[1 + dy:1 + dy + ny, 1 + dx:1 + dx + nx] - self._crit[k],
                       out=emax)
        return (emax > self._tol_m) & (centre > self.grid.ground_z_m)

    def settle(self, bbox: tuple[int, int, int, int] | None = None) -> dict:
        """Let over-steep material fail (avalanche relaxation of the whole column content).

        ``bbox`` = (iy0, iy1, ix0, ix1) grid indices covering every unstable column (default:
        found by scanning the grid). Moving material is routed through the recorded edge
        fluxes with complete mixing in each cell it passes; each deposited piece goes to its
        own deposit's slot. Returns {moved_m3, lost_tonnes, iterations, cells}."""
        grid = self.grid
        ny, nx = grid.shape
        if bbox is None:
            un = self.unstable_columns()
            if not un.any():
                return {"moved_m3": 0.0, "lost_tonnes": 0.0, "iterations": 0, "cells": 0}
            rr = np.flatnonzero(un.any(axis=1))
            cc = np.flatnonzero(un.any(axis=0))
            bbox = (int(rr[0]) - 1, int(rr[-1]) + 2, int(cc[0]) - 1, int(cc[-1]) + 2)
        pb = (max(bbox[0], 0) + 1, min(bbox[1], ny) + 1, max(bbox[2], 0) + 1,
              min(bbox[3], nx) + 1)
        if pb[1] <= pb[0] or pb[3] <= pb[2] or self.n_slots == 0:
            return {"moved_m3": 0.0, "lost_tonnes": 0.0, "iterations": 0, "cells": 0}
        ground = grid.ground_z_m
        base = np.full_like(self._surf, ground)
        mob0 = self._surf - ground
        mob0[0, :] = mob0[-1, :] = 0.0
        mob0[:, 0] = mob0[:, -1] = 0.0
        mob = mob0.copy()
        flux = np.zeros((8,) + mob.shape)
        its, lost_thk, touched = self._relax(base, mob, pb, flux=flux)
        rec = {"moved_m3": 0.0, "lost_tonnes": 0.0, "iterations": its, "cells": 0}
        if its == 0:
            self._settles.append(rec)
            return rec
        r0, r1, c0, c1 = touched
        # window including the pad ring around the touched block (sinks)
        w0, w1, v0, v1 = r0 - 1, r1 + 1, c0 - 1, c1 + 1
        fw = flux[:, w0:w1, v0:v1]
        dlt = (mob - mob0)[w0:w1, v0:v1]
        # border cells received lost material (mob was zeroed there): their "deposit" is
        # their inflow; reconstruct it from the fluxes
        hh, ww = dlt.shape
        inflow = np.zeros((hh, ww))
        for k, (dy, dx) in enumerate(_DIRS):
            src = fw[k]
            ys0, ys1 = max(0, -dy), hh - max(0, dy)
            xs0, xs1 = max(0, -dx), ww - max(0, dx)
            inflow[ys0 + dy:ys1 + dy, xs0 + dx:xs1 + dx] += src[ys0:ys1, xs0:xs1]
        pad = np.zeros((hh, ww), bool)
        gy = np.arange(w0, w1)
        gx = np.arange(v0, v1)
        pad[(gy == 0) | (gy == ny + 1), :] = True
        pad[:, (gx == 0) | (gx == nx + 1)] = True
        dlt = np.where(pad, inflow, dlt)
        ero = np.maximum(-dlt, 0.0)
        dep = np.maximum(dlt, 0.0)
        node = (inflow + ero) > 0
        nn = int(node.sum())
        if nn == 0:
            self._settles.append(rec)
            return rec
        idx = -np.ones((hh, ww), np.int64)
        idx[node] = np.arange(nn)
        # eroded composition: clip the eroding columns (grid coords = window - 1)
        er_cells = (ero > 0) & ~pad
        ey, ex = np.nonzero(er_cells)
        gy0, gx0 = w0 - 1, v0 - 1  # grid index of window (0, 0)
        area = grid.cell_area_m2
        na = len(self.analytes)
        rows = slice(max(gy0, 0), min(gy0 + hh, ny))
        cols = slice(max(gx0, 0), min(gx0 + ww, nx))
        oy, ox = rows.start - gy0, cols.start - gx0
        h_in, w_in = rows.stop - rows.start, cols.stop - cols.start
        er_in = er_cells[oy:oy + h_in, ox:ox + w_in]
        z_new = (self._surf[1:-1, 1:-1][rows, cols] - ero[oy:oy + h_in, ox:ox + w_in])
        slots = [s for s in range(self.n_slots) if self._thk[s][rows, cols][er_in].any()]
        rem, keep = self._column_clip(slots, rows, cols, z_new, er_in)
        ns = len(slots)
        ncomp = 2 + na  # volume, volume*time, volume*grade
        rhs = np.zeros((nn, ns * ncomp))
        node_in = idx[oy:oy + h_in, ox:ox + w_in]
        sel = er_in
        nodes_sel = node_in[sel]
        eroded_by_slot = np.zeros(ns)
        for j, s in enumerate(slots):
            r = rem[j][sel]
            eroded_by_slot[j] = r.sum()
            rhs[nodes_sel, j * ncomp] = r
            rhs[nodes_sel, j * ncomp + 1] = r * self._tim[s][rows, cols][sel]
            rhs[nodes_sel, j * ncomp + 2:(j + 1) * ncomp] = \
                (r[:, None] * self._grd[s][:, rows, cols][:, sel].T)
        # linear system: (E_i + In_i) c_i - sum_j F_ji c_j = s_i
        diag = (inflow + ero)[node]
        ri, ci, vv = [np.arange(nn)], [np.arange(nn)], [diag]
        for k, (dy, dx) in enumerate(_DIRS):
            fk = fw[k]
            sy, sx = np.nonzero(fk > 0)
            ty, tx = sy + dy, sx + dx
            ok = (ty >= 0) & (ty < hh) & (tx >= 0) & (tx < ww)
            sy, sx, ty, tx = sy[ok], sx[ok], ty[ok], tx[ok]
            ok = (idx[ty, tx] >= 0) & (idx[sy, sx] >= 0)
            sy, sx, ty, tx = sy[ok], sx[ok], ty[ok], tx[ok]
            ri.append(idx[ty, tx])
            ci.append(idx[sy, sx])
            vv.append(-fk[sy, sx])
        amat = sparse.csc_matrix((np.concatenate(vv), (np.concatenate(ri), np.concatenate(ci))),
                                 shape=(nn, nn))
        conc = rhs
        if ns:
            lu = sparse_linalg.splu(amat)
            # one right-hand side at a time: SuperLU's 2-D solve is ~10x slower here
            conc = np.column_stack([lu.solve(np.ascontiguousarray(rhs[:, j]))
                                    for j in range(rhs.shape[1])])
        dep_n = dep[node]
        add = conc * dep_n[:, None]  # per node: deposited volume(-weighted) components
        # exact per-slot conservation: scale deposits to the eroded volumes
        for j in range(ns):
            tot = add[:, j * ncomp].sum()
            if tot > 0:
                add[:, j * ncomp:(j + 1) * ncomp] *= eroded_by_slot[j] / tot
        # apply erosion
        for j, s in enumerate(slots):
            self._thk[s][rows, cols] = keep[j]
        # lost (pad) deposits
        pad_nodes = idx[pad & node]
        lost_t = 0.0
        lost_tg = np.zeros(na)
        for j, s in enumerate(slots):
            v = add[pad_nodes, j * ncomp].sum() * area
            if v > 0:
                rho = self._slot_rho[s]
                lost_t += v * rho
                lost_tg += rho * area * add[pad_nodes, j * ncomp + 2:(j + 1) * ncomp].sum(axis=0)
        # deposits inside the grid
        gnode = node & ~pad & (dep > 0)
        dy_, dx_ = np.nonzero(gnode)
        nid = idx[dy_, dx_]
        gyy, gxx = dy_ + gy0, dx_ + gx0
        for j, s in enumerate(slots):
            vol_thk = add[nid, j * ncomp]
            okk = vol_thk > 0
            if not okk.any():
                continue
            yy, xx, nd = gyy[okk], gxx[okk], nid[okk]
            a = vol_thk[okk]
            old = self._thk[s][yy, xx]
            new = old + a
            self._tim[s][yy, xx] = (self._tim[s][yy, xx] * old + add[nd, j * ncomp + 1]) / new
            self._grd[s][:, yy, xx] = ((self._grd[s][:, yy, xx] * old
                                        + add[nd, j * ncomp + 2:(j + 1) * ncomp].T) / new)
            self._thk[s][yy, xx] = new
        # surface of the window (covers every touched column) from the slots
        self._surf[1:-1, 1:-1][rows, cols] = ground + np.sum(
            [self._thk[s][rows, cols] for s in range(self.n_slots)], axis=0)
        self._lost_t += lost_t
        self._lost_tg += lost_tg
        rec = {"moved_m3": float(eroded_by_slot.sum() * area), "lost_tonnes": float(lost_t),
               "iterations": its, "cells": int(er_cells.sum())}
        self._settles.append(rec)
        return rec

    # ---------------------------------------------------------------- truth accessors
    def surface_z(self) -> np.ndarray:
        """Top surface (m), shape (ny, nx) (a copy)."""
        return self._surf[1:-1, 1:-1].copy()

    def thickness(self) -> np.ndarray:
        """Total material thickness per column (m)."""
        return self._surf[1:-1, 1:-1] - self.grid.ground_z_m

    def _slot_tonnes(self) -> np.ndarray:
        a = self.grid.cell_area_m2
        return np.array([float(self._thk[s].sum()) * a * self._slot_rho[s]
                         for s in range(self.n_slots)])

    def volume_m3(self) -> float:
        """Volume of material in the pile (sum of parcel thicknesses x cell area)."""
        a = self.grid.cell_area_m2
        return float(sum(float(t.sum()) for t in self._thk) * a)

    def tonnes(self) -> float:
        """Tonnes in the pile (sum of parcel volume x bulk density)."""
        return float(self._slot_tonnes().sum())

    def _pile_tg(self) -> np.ndarray:
        a = self.grid.cell_area_m2
        tg = np.zeros(len(self.analytes))
        for s in range(self.n_slots):
            tg += self._slot_rho[s] * a * np.einsum("ahw,hw->a", self._grd[s], self._thk[s])
        return tg

    def grade(self) -> dict:
        """Mass-weighted mean grade of the whole pile (mass %)."""
        t = self.tonnes()
        tg = self._pile_tg()
        return {a: (float(v / t) if t > 0 else float("nan")) for a, v in zip(self.analytes, tg)}

    def tonnes_by_deposit(self) -> dict:
        out: dict = {}
        for s, t in enumerate(self._slot_tonnes()):
            d = self._slot_deposit[s]
            out[d] = out.get(d, 0.0) + float(t)
        return out

    def tonnes_by_lot(self) -> dict:
        out: dict = {}
        for s, t in enumerate(self._slot_tonnes()):
            lot = self._lots[self._slot_lot[s]]
            out[lot] = out.get(lot, 0.0) + float(t)
        return out

    def slots(self) -> list[dict]:
        """Per slot (bottom to top): deposit id, lot, density, tonnes."""
        tt = self._slot_tonnes()
        return [{"slot": s, "deposit_id": self._slot_deposit[s],
                 "lot": self._lots[self._slot_lot[s]], "density_t_m3": self._slot_rho[s],
                 "tonnes": float(tt[s])} for s in range(self.n_slots)]

    def layer_surfaces(self) -> np.ndarray:
        """Top of each slot per column, shape (n_slots, ny, nx): ground + cumulative
        thickness, so non-decreasing with slot index (where a slot is absent its top equals
        the top of the slot below). Slot s is deposit ``slots()[s]['deposit_id']``."""
        if not self._thk:
            return np.zeros((0,) + self.grid.shape)
        return self.grid.ground_z_m + np.cumsum(np.stack(self._thk), axis=0)

    def parcels(self) -> dict:
        """Snapshot (copies) of the parcel arrays: thickness (S, ny, nx), grade (S, A, ny, nx),
        deposition time as ``time_rel_ns`` (float ns after ``epoch_ns``, exact to well under
        1 ns) and ``time_ns`` (absolute, float: about 256 ns resolution at current epochs),
        density / deposit_id / lot per slot."""
        S = self.n_slots
        ny, nx = self.grid.shape
        epoch = float(self._epoch_ns or 0)
        return {"thickness": np.stack(self._thk) if S else np.zeros((0, ny, nx)),
                "time_ns": (np.stack(self._tim) + epoch) if S else np.zeros((0, ny, nx)),
                "time_rel_ns": np.stack(self._tim) if S else np.zeros((0, ny, nx)),
                "epoch_ns": self._epoch_ns,
                "grade": np.stack(self._grd) if S else np.zeros((0, len(self.analytes), ny, nx)),
                "density_t_m3": np.array(self._slot_rho, float),
                "deposit_id": list(self._slot_deposit),
                "lot": [self._lots[i] for i in self._slot_lot],
                "analytes": list(self.analytes)}

    def parcel_at(self, x_m: float, y_m: float, z_m: float) -> dict | None:
        """The parcel containing point (x, y, z): deposit id, lot, slot, deposition time
        (ns) and grade; None above the surface, below ground or off the grid."""
        grid = self.grid
        iy, ix = grid.index_of(x_m, y_m)
        iy, ix = int(iy), int(ix)
        if not (0 <= iy < grid.ny and 0 <= ix < grid.nx):
            return None
        z = grid.ground_z_m
        if z_m < z:
            return None
        for s in range(self.n_slots):
            th = self._thk[s][iy, ix]
            if th > 0 and z_m < z + th:
                return {"slot": s, "deposit_id": self._slot_deposit[s],
                        "lot": self._lots[self._slot_lot[s]],
                        "time_ns": int(round(float(self._tim[s][iy, ix]))) + self._epoch_ns,
                        "grade": {a: float(v) for a, v in zip(self.analytes,
                                                               self._grd[s][:, iy, ix])},
                        "density_t_m3": self._slot_rho[s]}
            z += th
        return None

    def repose_angle_deg(self, band: tuple[float, float] = (0.2, 0.8)) -> float:
        """Robust estimate of the flank slope: median slope angle (surface gradient by
        central differences) over columns whose height above ground lies in the ``band``
        fraction of the maximum height (excludes crest and toe). NaN for an empty pile."""
        z = self.thickness()
        hmax = float(z.max()) if z.size else 0.0
        if hmax <= 0:
            return float("nan")
        surf = self._surf[1:-1, 1:-1]
        gy, gx = np.gradient(surf, self.grid.cell_m)
        sel = (z > band[0] * hmax) & (z < band[1] * hmax)
        # central differences straddle the crest/toe: also demand all 8 neighbours inside
        # the pile (material present)
        inner = ndimage.binary_erosion(z > 0, structure=np.ones((3, 3), bool), iterations=2)
        sel &= inner
        if not sel.any():
            return float("nan")
        return float(np.degrees(np.arctan(np.median(np.hypot(gx, gy)[sel]))))

    # ---------------------------------------------------------------- ledgers & export
    def mass_balance(self) -> dict:
        """stacked = in pile + reclaimed + lost (tonnes) and the relative residual."""
        pile = self.tonnes()
        res = self._stacked_t - (pile + self._reclaimed_t + self._lost_t)
        return {"stacked_tonnes": self._stacked_t, "pile_tonnes": pile,
                "reclaimed_tonnes": self._reclaimed_t, "lost_tonnes": self._lost_t,
                "residual_tonnes": res,
                "relative_residual": (res / self._stacked_t) if self._stacked_t > 0 else 0.0}

    def grade_balance(self) -> dict:
        """Per analyte: stacked tonnes x grade minus (pile + reclaimed + lost), relative."""
        pile = self._pile_tg()
        out = {}
        for j, a in enumerate(self.analytes):
            st = self._stacked_tg[j]
            r = st - (pile[j] + self._reclaimed_tg[j] + self._lost_tg[j])
            out[a] = float(r / st) if st != 0 else float(r)
        return out

    def stacked_grade(self) -> dict:
        t = self._stacked_t
        return {a: (float(v / t) if t > 0 else float("nan"))
                for a, v in zip(self.analytes, self._stacked_tg)}

    def releases(self) -> list[dict]:
        """Every release (time, path, tonnes, grade, lost) in order."""
        return [dict(r) for r in self._releases]

    def deposits(self) -> list[dict]:
        """What was stacked per deposit id (from the release log): tonnes, first and last
        release time, lots and the tonnage-weighted belt grade, in order of first release."""
        out: dict = {}
        for r in self._releases:
            d = out.setdefault(r["deposit_id"], {"deposit_id": r["deposit_id"], "tonnes": 0.0,
                                                 "lost_tonnes": 0.0, "t_first_ns": r["time_ns"],
                                                 "t_last_ns": r["time_ns"], "lots": [],
                                                 "_tg": np.zeros(len(self.analytes))})
            d["tonnes"] += r["tonnes"]
            d["lost_tonnes"] += r["lost_tonnes"]
            d["t_last_ns"] = r["time_ns"]
            if r["lot"] not in d["lots"]:
                d["lots"].append(r["lot"])
            d["_tg"] += r["tonnes"] * np.array([r["grade"][a] for a in self.analytes])
        res = []
        for d in out.values():
            tg = d.pop("_tg")
            d["grade"] = {a: (float(v / d["tonnes"]) if d["tonnes"] > 0 else None)
                          for a, v in zip(self.analytes, tg)}
            res.append(d)
        return res

    def summary(self) -> dict:
        """JSON-serialisable truth summary (for truth.json)."""
        mb = self.mass_balance()
        return {
            "grid": self.grid.to_dict(),
            "repose_deg": self.repose_deg,
            "deposition": self.deposition,
            "analytes": list(self.analytes),
            "epoch_ns": self._epoch_ns,
            "volume_m3": self.volume_m3(),
            "tonnes": self.tonnes(),
            "grade": {k: _json_float(v) for k, v in self.grade().items()},
            "tonnes_by_deposit": {str(k): v for k, v in self.tonnes_by_deposit().items()},
            "tonnes_by_lot": {str(k): v for k, v in self.tonnes_by_lot().items()},
            "repose_angle_estimate_deg": _json_float(self.repose_angle_deg()),
            "max_height_m": float(self.surface_z().max()),
            "mass_balance": mb,
            "grade_balance": self.grade_balance(),
            "stacked_grade": {k: _json_float(v) for k, v in self.stacked_grade().items()},
            "border_contacts": self.border_contacts,
            "slots": [{**s, "deposit_id": _jsonable(s["deposit_id"]), "lot": _jsonable(s["lot"])}
                      for s in self.slots()],
            "deposits": [{**d, "deposit_id": _jsonable(d["deposit_id"]),
                          "lots": [_jsonable(x) for x in d["lots"]]} for d in self.deposits()],
            "passes": [{**p, "deposit_id": _jsonable(p["deposit_id"]), "lot": _jsonable(p["lot"])}
                       for p in self._passes],
            "cuts": [c.to_dict() for c in self.cuts],
            "settles": list(self._settles),
        }

    def to_npz(self, path, *, parcels: bool = True) -> None:
        """Write the truth arrays (surface, layer tops, optionally every parcel array) and
        the summary (as a JSON string under ``summary_json``) to a compressed .npz."""
        arrays = {"surface_z": self.surface_z(), "layer_tops": self.layer_surfaces(),
                  "x_centres": self.grid.x_centres, "y_centres": self.grid.y_centres,
                  "summary_json": np.array(json.dumps(self.summary()))}
        if parcels:
            p = self.parcels()
            arrays.update(thickness=p["thickness"], time_ns=p["time_ns"], grade=p["grade"],
                          density_t_m3=p["density_t_m3"])
        np.savez_compressed(path, **arrays)


# --------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------

def _jsonable(v):
    if isinstance(v, (np.integer,)):
        return int(v)
    if isinstance(v, (int, str, float)) or v is None:
        return v
    return str(v)


def _segment_distance(x, y, x0, y0, x1, y1) -> np.ndarray:
    """Euclidean distance from points (x, y) (broadcast) to the segment (x0,y0)-(x1,y1)."""
    dx, dy = x1 - x0, y1 - y0
    ll = dx * dx + dy * dy
    if ll == 0:
        return np.hypot(x - x0, y - y0)
    s = np.clip(((x - x0) * dx + (y - y0) * dy) / ll, 0.0, 1.0)
    return np.hypot(x - (x0 + s * dx), y - (y0 + s * dy))


def _solve_fill_level(k: np.ndarray, v_thk: float, a_up: float) -> tuple[float, bool]:
    """Level a with sum(max(0, a - k)) == v_thk, searching below ``a_up``.

    Returns (a, True), or (nan, False) when the cells below ``a_up`` cannot hold v_thk."""
    cand = k[k < a_up]
    if cand.size == 0 or float(np.sum(a_up - cand)) < v_thk:
        return float("nan"), False
    kc = np.sort(cand)
    cs = np.cumsum(kc)
    n = np.arange(1, kc.size + 1)
    a_n = (v_thk + cs) / n
    ok = np.empty(kc.size, bool)
    ok[:-1] = a_n[:-1] <= kc[1:]
    ok[-1] = True
    j = int(np.argmax(ok))
    return float(a_n[j]), True


def _split_run(x: float, y0: float, y1: float,
               step: float) -> list[tuple[float, float, float, float]]:
    """Split a run along y at fixed x into segments of at most ``step`` (at least one)."""
    length = abs(y1 - y0)
    n = max(1, int(math.ceil(length / step - 1e-9)))
    ys = np.linspace(y0, y1, n + 1)
    return [(x, float(ys[i]), x, float(ys[i + 1])) for i in range(n)]


def _sector_bbox(cx: float, cy: float, r_in: float, r_out: float, th_lo: float,
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


def chevron_pile(world: World, *, x_centre_m: float, y_start_m: float, y_end_m: float,
                 passes: Iterable[dict], t0_ns: int, pass_duration_ns: int,
                 gap_ns: int = 0, **kwargs) -> list[dict]:
    """Convenience: stack consecutive chevron passes, alternating direction.

    ``passes`` items: {"tonnes", "lot", "grade_fn" (or "grade"), optional "deposit_id",
    "density_t_m3"}. Returns the pass records."""
    out = []
    t = int(t0_ns)
    for i, p in enumerate(passes):
        gf = p.get("grade_fn")
        if gf is None:
            gconst = p["grade"]
            gf = (lambda _t, _g=gconst: _g)
        a, b = (y_start_m, y_end_m) if i % 2 == 0 else (y_end_m, y_start_m)
        out.append(world.stack_pass(Pattern.CHEVRON, a, b, x_centre_m, p["tonnes"], t,
                                    t + int(pass_duration_ns), p.get("deposit_id", i), p["lot"],
                                    gf, p.get("density_t_m3", DEFAULT_DENSITY_T_M3), **kwargs))
        t += int(pass_duration_ns) + int(gap_ns)
    return out
