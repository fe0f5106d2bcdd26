"""The simulated stockyard's pile: ground truth on a fine deposition grid.

This module is the simulator's own physical model of a stockpile. Every accuracy figure of
the product (surfaces, layers, cut tonnes and grades) is measured against it, so it models
the pile from physics (material dropped by the stacker, slope failure, the reclaimer's
cutting envelope) and keeps an exact account of every tonne; it never evaluates an
idealised pile shape (prism, cone formula) that a projector could also use, and it uses
the simulator's own machine geometry (:mod:`sim.kinematics`), never the projector's or the
planner's.

A :class:`World` is the pile's parcels (:class:`sim.parcels.ParcelColumns`: per column of
a :class:`~sim.grid.Grid`, one parcel per deposit, with thickness, deposition time and
grade) and the processes that change them:

- :meth:`World.deposit` / :meth:`World.stack_pass`: material released by the stacker comes
  to rest at the angle of repose (:mod:`sim.deposition`, the release plan of a pass in
  :mod:`sim.stacking`);
- :meth:`World.reclaim_cut`: a bucket-wheel cut removes everything above the cutting
  envelope's floor in its footprint (:mod:`sim.reclaiming`); the returned
  :class:`~sim.truth.CutTruth` is exactly what was removed;
- :meth:`World.settle`: afterwards the walls of the cut may fail: the avalanche relaxation
  runs with *all* material mobile (the walls erode), and the moving material's composition
  is routed through the recorded edge fluxes (:mod:`sim.relaxation`). Material that slumps
  into the hole is **not** part of the cut that made the hole; the next cut picks it up.
  Slumped material is stored in its own deposit's slot, so in a receiving column the slot
  order (deposit order) is kept: if older material slides onto a column whose top is a
  newer deposit, it is recorded under it (mass and grade exact, vertical position
  approximate, only inside the slump zone). With ``angle_deg`` only what is steeper than
  that fails (a cohesive face, :mod:`sim.material`, which decides what a cut's walls do).

Mass accounting: ``stacked == in pile + reclaimed + lost`` to floating-point rounding
(lost = material that left the grid across its border; make the grid big enough and it
stays 0). Timings of the deposition models are in docs/design-notes.md.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from sim.deposition import avalanche_release, quasistatic_release
from sim.grid import ANALYTES, DEFAULT_DENSITY_T_M3, DEFAULT_REPOSE_DEG, Grid, Pattern
from sim.kinematics import Machine
from sim.parcels import ParcelColumns, Removed
from sim.reclaiming import cut_block, footprint_bbox
from sim.relaxation import DIST, SlumpFlow, relax, routed_deposits, slump_flow, unstable_mask
from sim.stacking import chevron_pile, release_segments, release_shares, release_times
from sim.truth import CutTruth, deposits_from_releases, json_float, jsonable

__all__ = ["ANALYTES", "DEFAULT_DENSITY_T_M3", "DEFAULT_REPOSE_DEG", "CutTruth", "Grid",
           "Pattern", "World", "chevron_pile"]


class World(ParcelColumns):
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
        Deposition model (:mod:`sim.deposition`).
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
        super().__init__(grid, analytes)
        self.repose_deg = float(repose_deg)
        self.deposition = deposition
        self.relax_tol = float(relax_tol)
        self.max_relax_iterations = int(max_relax_iterations)
        self._tan = math.tan(math.radians(self.repose_deg))
        self._crit = self._tan * grid.cell_m * DIST  # critical drop to each neighbour (m)
        self._tol_m = self.relax_tol * self._tan * grid.cell_m
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

    @property
    def tan_repose(self) -> float:
        return self._tan

    @staticmethod
    def _check_time(time_ns) -> int:
        if isinstance(time_ns, bool) or not isinstance(time_ns, (int, np.integer)):
            raise TypeError(f"time_ns must be an integer (ns), got {type(time_ns).__name__}")
        return int(time_ns)

    # ---------------------------------------------------------------- stacking
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
                lost_vol, placed = quasistatic_release(self._surf, self.grid, self._tan,
                                                       float(x_m), float(y_m), x1, y1, vol)
            else:
                lost_vol, placed = avalanche_release(
                    self._surf, self.grid, self._crit, self._tol_m, self.max_relax_iterations,
                    float(x_m), float(y_m), x1, y1, vol)
            if placed is not None:
                self._merge(slot, *placed, trel, g)
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
        segs = release_segments(
            pattern, y0, y1, xc, step,
            volume_m3=tonnes / rho, tan_repose=self._tan, n_rows=n_rows, row_spacing_m=row_spacing_m,
            row_offset_m=row_offset_m, n_cones=n_cones, cone_spacing_m=cone_spacing_m,
            releases_per_cone=releases_per_cone)
        n = len(segs)
        w = release_shares(pattern, segs, rng, rate_cv)
        tonnes_k = tonnes * w
        times = release_times(w, t_start_ns, t_end_ns)
        jit = rng.normal(0.0, jitter_m, n) if jitter_m > 0 else np.zeros(n)
        lost = 0.0
        tg = np.zeros(len(self.analytes))
        for k, (xa, ya, xb, yb) in enumerate(segs):
            tm = times[k]
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
        footprint, block = cut_block(self.grid, machine, travel_m, luff_rad, slew_start_rad,
                                     slew_end_rad)
        if block is None:
            removed = Removed(tg=np.zeros(len(self.analytes)))
        else:
            rows, cols, floor, inside = block
            removed = self._remove_above(rows, cols, floor, inside)
        tonnes, tg = removed.tonnes, removed.tg
        grade = {a: (float(v / tonnes) if tonnes > 0 else float("nan"))
                 for a, v in zip(self.analytes, tg)}
        mean_t = (removed.ttime / tonnes + self._epoch_ns) if tonnes > 0 else None
        self._reclaimed_t += tonnes
        self._reclaimed_tg += tg
        truth = CutTruth(time_ns=time_ns, travel_m=float(travel_m), luff_rad=float(luff_rad),
                         slew_start_rad=float(slew_start_rad), slew_end_rad=float(slew_end_rad),
                         tonnes=tonnes, volume_m3=removed.volume_m3, grade=grade,
                         tonnes_by_deposit=removed.by_deposit, tonnes_by_lot=removed.by_lot,
                         mean_deposition_time_ns=mean_t, footprint=footprint)
        self.cuts.append(truth)
        if relax and removed.volume_m3 > 0:
            res = self.settle(bbox=footprint_bbox(footprint))
            truth.slump_m3 = res["moved_m3"]
            truth.slump_lost_tonnes = res["lost_tonnes"]
        return truth

    def settle_cut(self, parts: list[CutTruth], *, angle_deg: float | None = None) -> dict | None:
        """Let the walls of a cut made in sub-sweeps (``reclaim_cut(..., relax=False)``)
        slump once the wheel has passed, if any sub-sweep took material, to the angle of
        repose or to ``angle_deg``; the slump is recorded on the last part. Returns
        :meth:`settle`'s record, None when no sub-sweep took material."""
        if not parts or sum(p.volume_m3 for p in parts) <= 0:
            return None
        footprint = np.logical_or.reduce([p.footprint for p in parts])
        res = self.settle(bbox=footprint_bbox(footprint), angle_deg=angle_deg)
        parts[-1].slump_m3 = res["moved_m3"]
        parts[-1].slump_lost_tonnes = res["lost_tonnes"]
        return res

    # ---------------------------------------------------------------- slope failure
    def unstable_columns(self) -> np.ndarray:
        """Bool (ny, nx): columns steeper than repose (beyond tolerance) toward a neighbour
        and holding material."""
        return unstable_mask(self._surf, self._crit, self._tol_m, self.grid.ground_z_m)

    def settle(self, bbox: tuple[int, int, int, int] | None = None, *,
               angle_deg: float | None = None) -> dict:
        """Let over-steep material fail (avalanche relaxation of the whole column content).

        ``bbox`` = (iy0, iy1, ix0, ix1) grid indices covering every unstable column (default:
        found by scanning the grid). Material steeper than the angle of repose fails, or
        with ``angle_deg`` (deg) steeper than that (a cohesive face standing steeper).
        Moving material is routed through the recorded edge fluxes with complete mixing in
        each cell it passes; each deposited piece goes to its own deposit's slot. Returns
        {moved_m3, lost_tonnes, iterations, cells}."""
        ny, nx = self.grid.shape
        crit, tol_m = self._crit, self._tol_m
        if angle_deg is not None:
            if not (0.0 < float(angle_deg) < 90.0):
                raise ValueError(f"angle_deg must be in (0, 90), got {angle_deg}")
            tan = math.tan(math.radians(float(angle_deg)))
            crit, tol_m = tan * self.grid.cell_m * DIST, self.relax_tol * tan * self.grid.cell_m
        if bbox is None:
            un = unstable_mask(self._surf, crit, tol_m, self.grid.ground_z_m)
            if not un.any():
                return {"moved_m3": 0.0, "lost_tonnes": 0.0, "iterations": 0, "cells": 0}
            rr = np.flatnonzero(un.any(axis=1))
            cc = np.flatnonzero(un.any(axis=0))
            bbox = (int(rr[0]) - 1, int(rr[-1]) + 2, int(cc[0]) - 1, int(cc[-1]) + 2)
        pb = (max(bbox[0], 0) + 1, min(bbox[1], ny) + 1, max(bbox[2], 0) + 1,
              min(bbox[3], nx) + 1)
        if pb[1] <= pb[0] or pb[3] <= pb[2] or self.n_slots == 0:
            return {"moved_m3": 0.0, "lost_tonnes": 0.0, "iterations": 0, "cells": 0}
        ground = self.grid.ground_z_m
        base = np.full_like(self._surf, ground)
        mob0 = self._surf - ground
        mob0[0, :] = mob0[-1, :] = 0.0
        mob0[:, 0] = mob0[:, -1] = 0.0
        mob = mob0.copy()
        flux = np.zeros((8,) + mob.shape)
        its, lost_thk, touched = relax(base, mob, pb, crit, tol_m, self.max_relax_iterations,
                                       flux=flux)
        rec = {"moved_m3": 0.0, "lost_tonnes": 0.0, "iterations": its, "cells": 0}
        if its == 0:
            self._settles.append(rec)
            return rec
        flow = slump_flow(flux, mob, mob0, touched, ny, nx)
        if flow.n_nodes == 0:
            self._settles.append(rec)
            return rec
        src = self._slump_sources(flow)
        add = routed_deposits(flow, src.rhs, src.eroded_by_slot, src.ncomp)
        # apply erosion
        for j, s in enumerate(src.slots):
            self._thk[s][src.rows, src.cols] = src.keep[j]
        lost_t, lost_tg = self._slump_lost(flow, src, add)
        self._slump_deposit(flow, src, add)
        # surface of the window (covers every touched column) from the slots
        self._refresh_surface(src.rows, src.cols)
        self._lost_t += lost_t
        self._lost_tg += lost_tg
        rec = {"moved_m3": float(src.eroded_by_slot.sum() * self.grid.cell_area_m2),
               "lost_tonnes": float(lost_t), "iterations": its, "cells": int(src.er_cells.sum())}
        self._settles.append(rec)
        return rec

    def _slump_sources(self, flow: SlumpFlow) -> "_SlumpSources":
        """Clip the eroding columns of a slump (not yet applied) and gather what each node
        of the network receives from them."""
        ny, nx = self.grid.shape
        hh, ww = flow.idx.shape
        nn = flow.n_nodes
        er_cells = (flow.ero > 0) & ~flow.pad
        gy0, gx0 = flow.gy0, flow.gx0  # grid index of window (0, 0)
        rows = slice(max(gy0, 0), min(gy0 + hh, ny))
        cols = slice(max(gx0, 0), min(gx0 + ww, nx))
        oy, ox = rows.start - gy0, cols.start - gx0
        h_in, w_in = rows.stop - rows.start, cols.stop - cols.start
        er_in = er_cells[oy:oy + h_in, ox:ox + w_in]
        z_new = (self._surf[1:-1, 1:-1][rows, cols] - flow.ero[oy:oy + h_in, ox:ox + w_in])
        slots = [s for s in range(self.n_slots) if self._thk[s][rows, cols][er_in].any()]
        rem, keep = self._column_clip(slots, rows, cols, z_new, er_in)
        ns = len(slots)
        ncomp = 2 + len(self.analytes)  # volume, volume*time, volume*grade
        rhs = np.zeros((nn, ns * ncomp))
        node_in = flow.idx[oy:oy + h_in, ox:ox + w_in]
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
        return _SlumpSources(slots, rows, cols, keep, rhs, eroded_by_slot, er_cells, ncomp)

    def _slump_lost(self, flow: SlumpFlow, src: "_SlumpSources",
                    add: np.ndarray) -> tuple[float, np.ndarray]:
        """Tonnes and tonnes x grade of the routed material deposited on the pad (lost)."""
        area = self.grid.cell_area_m2
        ncomp = src.ncomp
        pad_nodes = flow.idx[flow.pad & flow.node]
        lost_t = 0.0
        lost_tg = np.zeros(len(self.analytes))
        for j, s in enumerate(src.slots):
            v = add[pad_nodes, j * ncomp].sum() * area
            if v > 0:
                rho = self._slot_rho[s]
                lost_t += v * rho
                lost_tg += rho * area * add[pad_nodes, j * ncomp + 2:(j + 1) * ncomp].sum(axis=0)
        return lost_t, lost_tg

    def _slump_deposit(self, flow: SlumpFlow, src: "_SlumpSources", add: np.ndarray) -> None:
        """Add the routed material deposited inside the grid to its own slot in each cell."""
        ncomp = src.ncomp
        gnode = flow.node & ~flow.pad & (flow.dep > 0)
        dy_, dx_ = np.nonzero(gnode)
        nid = flow.idx[dy_, dx_]
        gyy, gxx = dy_ + flow.gy0, dx_ + flow.gx0
        for j, s in enumerate(src.slots):
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
        return deposits_from_releases(self._releases, self.analytes)

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
            "grade": {k: json_float(v) for k, v in self.grade().items()},
            "tonnes_by_deposit": {str(k): v for k, v in self.tonnes_by_deposit().items()},
            "tonnes_by_lot": {str(k): v for k, v in self.tonnes_by_lot().items()},
            "repose_angle_estimate_deg": json_float(self.repose_angle_deg()),
            "max_height_m": float(self.surface_z().max()),
            "mass_balance": mb,
            "grade_balance": self.grade_balance(),
            "stacked_grade": {k: json_float(v) for k, v in self.stacked_grade().items()},
            "border_contacts": self.border_contacts,
            "slots": [{**s, "deposit_id": jsonable(s["deposit_id"]), "lot": jsonable(s["lot"])}
                      for s in self.slots()],
            "deposits": [{**d, "deposit_id": jsonable(d["deposit_id"]),
                          "lots": [jsonable(x) for x in d["lots"]]} for d in self.deposits()],
            "passes": [{**p, "deposit_id": jsonable(p["deposit_id"]), "lot": jsonable(p["lot"])}
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


@dataclass
class _SlumpSources:
    """What the walls lose in one slump, before it is applied.

    ``slots`` are the eroding slots, clipped over the block ``rows, cols`` to ``keep``
    (ns, h, w) m; ``rhs`` (n_nodes, ns * ncomp) what each network node receives from them
    (thickness m, thickness x time, thickness x grade: ``ncomp`` columns per slot);
    ``eroded_by_slot`` (ns,) the eroded thickness per slot summed over the cells (m);
    ``er_cells`` the eroding cells of the flow's window.
    """

    slots: list
    rows: slice
    cols: slice
    keep: np.ndarray
    rhs: np.ndarray
    eroded_by_slot: np.ndarray
    er_cells: np.ndarray
    ncomp: int
