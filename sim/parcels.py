"""The pile's material: a stack of parcels in every column of the deposition grid.

A :class:`ParcelColumns` holds, per column of a :class:`~sim.grid.Grid`, a stack of
**parcels**: one parcel per *slot*, slots in stacking order (slot 0 at the bottom). A slot is
one deposit (a stacking pass, or a run of :meth:`sim.world.World.deposit` calls with the
same deposit id, lot and bulk density); its deposit id, lot and bulk density are slot
constants. Per slot and cell it stores the parcel thickness (m), the mean deposition time
(ns after the epoch, the first release's time) and the mean grade (mass %, one value per
analyte), i.e. layer-major arrays ``thickness[slot][iy, ix]``, ``time[slot][iy, ix]``,
``grade[slot][analyte, iy, ix]``. A parcel is well mixed: material of one deposit that
reaches the same column at different moments is merged (thickness-weighted mean time and
grade; one density per slot, so thickness weights are mass weights). The top surface is
``ground + sum(thickness)``, kept padded by one ring of ground cells (the border sink of
the relaxation). This module has the state, the primitives that add and remove material
(:meth:`~ParcelColumns._merge`, :meth:`~ParcelColumns._remove_above`) and the read-only
views of the truth (surface, layer tops, tonnes, grade, the parcels); the processes that
move material are :class:`sim.world.World`'s.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping, Sequence

import numpy as np
from scipy import ndimage

from sim.grid import Grid


@dataclass
class Removed:
    """What was taken out of the columns by :meth:`ParcelColumns._remove_above`.

    ``tg`` is tonnes x grade per analyte; ``ttime`` tonnes x relative deposition time
    (t ns); ``by_deposit`` and ``by_lot`` tonnes per deposit id and lot label.
    """

    volume_m3: float = 0.0
    tonnes: float = 0.0
    tg: np.ndarray = field(default_factory=lambda: np.zeros(0))
    ttime: float = 0.0
    by_deposit: dict = field(default_factory=dict)
    by_lot: dict = field(default_factory=dict)


class ParcelColumns:
    """The parcel stacks of every column of ``grid`` (see the module docstring).

    Parameters
    ----------
    grid : Grid
        The deposition grid.
    analytes : sequence of str
        Names of the grade components carried by each parcel (validated by the caller).
    """

    def __init__(self, grid: Grid, analytes: Sequence[str]):
        self.grid = grid
        self.analytes = tuple(analytes)
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

    @property
    def n_slots(self) -> int:
        return len(self._thk)

    @property
    def lots(self) -> list:
        """Lot labels in index order."""
        return list(self._lots)

    # ---------------------------------------------------------------- slots
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

    # ---------------------------------------------------------------- adding and removing
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

    def _column_clip(self, slots: Sequence[int], rows: slice, cols: slice, z_cut: np.ndarray,
                     where: np.ndarray):
        """Clip the columns of a block at height ``z_cut`` (only where ``where``).

        Returns (removed (S, h, w) thickness, keep (S, h, w) thickness)."""
        thk = np.stack([self._thk[s][rows, cols] for s in slots])
        bottom = self.grid.ground_z_m + np.cumsum(thk, axis=0) - thk
        keep = np.clip(z_cut[None] - bottom, 0.0, thk)
        keep = np.where(where[None], keep, thk)
        return thk - keep, keep

    def _refresh_surface(self, rows: slice, cols: slice) -> None:
        """Recompute the top surface of a block of columns from its slots."""
        self._surf[1:-1, 1:-1][rows, cols] = self.grid.ground_z_m + np.sum(
            [self._thk[s][rows, cols] for s in range(self.n_slots)], axis=0)

    def _remove_above(self, rows: slice, cols: slice, z_cut: np.ndarray,
                      where: np.ndarray) -> Removed:
        """Remove all material above ``z_cut`` (m, (h, w)) in the block's columns marked
        ``where``; parcels are clipped from the top (a partly removed parcel keeps its
        lower part). Returns what was removed."""
        out = Removed(tg=np.zeros(len(self.analytes)))
        surf = self._surf[1:-1, 1:-1][rows, cols]
        hit = where & (surf > z_cut)
        slots = [s for s in range(self.n_slots) if self._thk[s][rows, cols][hit].any()] \
            if hit.any() else []
        if not slots:
            return out
        rem, keep = self._column_clip(slots, rows, cols, z_cut, hit)
        area = self.grid.cell_area_m2
        for j, s in enumerate(slots):
            r = rem[j]
            vs = float(r.sum()) * area
            if vs <= 0:
                continue
            rho = self._slot_rho[s]
            ts = vs * rho
            out.volume_m3 += vs
            out.tonnes += ts
            out.tg += rho * area * np.einsum("ahw,hw->a", self._grd[s][:, rows, cols], r)
            out.ttime += rho * area * float((self._tim[s][rows, cols] * r).sum())
            dep = self._slot_deposit[s]
            out.by_deposit[dep] = out.by_deposit.get(dep, 0.0) + ts
            lot = self._lots[self._slot_lot[s]]
            out.by_lot[lot] = out.by_lot.get(lot, 0.0) + ts
            self._thk[s][rows, cols] = keep[j]
        self._refresh_surface(rows, cols)
        return out

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
