"""Standard deviations of a projected pile's and cut's tonnes and grade.

The query's side of :mod:`projector.uncertainty`: it gathers what the kernels need from a
folded state and the grade join, and returns ``{"tonnes_sd": t, "grade_sd": {analyte:
pp}}`` per figure (:func:`pile_sd`, :func:`cut_sd`); :func:`projector.query.summarise`
calls them.  docs/uncertainty.md says how each term is formed and what it leaves out.

- **Volume.**  The pile: the height map's fused variances over the cells with material
  (never-seen cells: the configured prior).  A cut: the variances the fold kept of its
  footprint just before it (``CutRecord.footprint_var_m2``;
  a planned cut, which has none, takes the map's current ones); its floor is the cutting
  envelope's (the machine's kinematics), and what the scans after it saw below that
  floor is its geometry residual, a further volume error.
- **Pieces.**  The material's grade classes (:func:`projector.grades.grade_classes`), in
  groups that share one error: one per assay (keyed by the lot and the assay's grade
  and density) for assayed material, one per lot for material graded from its plan.
  An assayed group also carries the belt's drift inside its window
  (:mod:`projector.window_drift`): how its tonnes spread over the window's time, and the
  drift's rate estimated from successive assays of each lot (:func:`drift_rate`).
- **Buried boundaries.**  Between consecutive deposits of different lots: the material
  within ``UncertaintyConfig.boundary_band_m`` of the boundary, wherever both deposits
  hold material (a cut: both lost some, and one at least ``boundary_sliver_m``: slid
  material lies in thin slivers of every deposit), its grade difference the lots'
  planned one.

Units: m, m^2, m^3, tonnes, t/m^3, mass % (sds of grades in percentage points, pp).
"""

from __future__ import annotations

import math

import numpy as np

from projector.grades import grade_classes
from projector.uncertainty import (UncertaintyConfig, VolumeVariance, boundary_band_thickness_m,
                                   figure_sd, volume_variance)
from projector.window_drift import BINS, drift_rate_pp2_s, part_variance_pp2, window_histogram
from schemas.times import NS_PER_S

__all__ = ["pile_sd", "cut_sd"]


class _Pieces:
    """Material gathered into pieces (one per grade class of one call) with their groups."""

    def __init__(self, join) -> None:
        self.join = join
        self.tonnes: list[np.ndarray] = []
        self.group: list[np.ndarray] = []
        self.assayed: list[np.ndarray] = []
        self.reported: list[np.ndarray] = []
        self._ids: dict[tuple, int] = {}
        self._stated: dict[int, np.ndarray] = {}     # group -> the lab's stated sd (pp)
        self._hist: dict[int, np.ndarray] = {}       # assayed group -> tonnes per window bin
        self._window_s: dict[int, float] = {}        # assayed group -> its window (s)

    def add(self, lot_id: str, times_ns, volumes_m3) -> None:
        """Some material of one lot: deposition times (UTC ns) and volumes (m^3) per cell."""
        volumes = np.asarray(volumes_m3, np.float64)
        if volumes.size == 0:
            return
        join = self.join
        planned = join.lots.get(lot_id)
        if planned is None:    # an undeclared lot: one planned group, default density
            index, assayed = np.zeros(volumes.size, np.int64), np.zeros(1, bool)
            grade, density = np.full((1, len(join.analytes)), np.nan), np.full(1, np.nan)
            stated = np.full((1, len(join.analytes)), np.nan)
        else:
            c = grade_classes(lot_id, planned, join.by_lot.get(lot_id, []),
                              np.asarray(times_ns), join.analytes)
            index, assayed, grade, density = c.index, c.assayed, c.grade, c.density_t_m3
            stated = c.lab_sd_pp
        reported = np.isfinite(density)
        rho = np.where(reported, density, join.density_default)
        self.tonnes.append(np.bincount(index, weights=volumes, minlength=len(assayed)) * rho)
        # an assay is known by its lot, grade, density and stated repeatability (bytes: NaN
        # equals itself)
        groups = [self._id(("assay", lot_id, grade[i].tobytes(), density[i].tobytes(),
                            stated[i].tobytes()) if assayed[i] else ("lot", lot_id))
                  for i in range(len(assayed))]
        times, cell_tonnes = np.asarray(times_ns), volumes * rho[index]
        for i, g in enumerate(groups):
            if assayed[i]:
                self._stated[g] = stated[i]
                mine = index == i
                self._add_window(g, c.window_ns[i], times[mine], cell_tonnes[mine])
        self.group.append(np.array(groups, np.int64))
        self.assayed.append(assayed)
        self.reported.append(reported)

    def _add_window(self, group: int, window_ns, times_ns, tonnes) -> None:
        start, end = (int(v) for v in window_ns)
        hist = window_histogram(times_ns, tonnes, start, end)
        self._hist[group] = self._hist.get(group, 0.0) + hist
        self._window_s[group] = (end - start) / NS_PER_S

    def _id(self, key: tuple) -> int:
        return self._ids.setdefault(key, len(self._ids))

    def arrays(self) -> dict:
        """``tonnes``, ``group``, ``assayed``, ``density_reported`` and ``lab_sd_pp`` (a
        row per group: an assay's stated repeatability, NaN where it states none) as
        :func:`figure_sd` takes them."""
        cat = (lambda parts, dtype: np.concatenate(parts).astype(dtype) if parts
               else np.zeros(0, dtype))
        stated = np.full((len(self._ids), len(self.join.analytes)), np.nan)
        for g, row in self._stated.items():
            stated[g] = row
        return {"tonnes": cat(self.tonnes, np.float64), "group": cat(self.group, np.int64),
                "assayed": cat(self.assayed, bool), "density_reported": cat(self.reported, bool),
                "lab_sd_pp": stated}

    def drift_var_pp2(self, drift_pp2_s: np.ndarray) -> np.ndarray:
        """Per group (K, A): the variance of its pieces' grade about its window's
        (:func:`projector.window_drift.part_variance_pp2`; 0 for a planned group)."""
        k = len(self._ids)
        hist, width = np.zeros((k, BINS)), np.zeros(k)
        for g, h in self._hist.items():
            hist[g], width[g] = h, self._window_s[g]
        return part_variance_pp2(hist, width, drift_pp2_s)


def drift_rate(join, config: UncertaintyConfig) -> np.ndarray:
    """The belt's drift rate inside a window (pp^2/s, per analyte), estimated from the
    effective assays of every lot (:func:`projector.window_drift.drift_rate_pp2_s`; each
    assay's stated repeatability, else the configured one); 0 where it cannot be
    estimated (no lot with two assays), so the term then adds nothing."""
    assays = [a for lot in sorted(join.by_lot) for a in join.by_lot[lot]]
    n_a = len(join.analytes)
    if len(assays) < 2:
        return np.zeros(n_a)
    configured = [config.lab_sd_pp.get(name, math.nan) for name in join.analytes]
    grade = np.array([[a.analytes.get(name, math.nan) for name in join.analytes]
                      for a in assays]).reshape(len(assays), n_a)
    lab = np.array([[a.repeatability_pp.get(name, configured[j])
                     for j, name in enumerate(join.analytes)] for a in assays]).reshape(
        len(assays), n_a)
    rate = drift_rate_pp2_s(np.array([a.window_start_ns for a in assays]) / NS_PER_S,
                            np.array([a.window_end_ns for a in assays]) / NS_PER_S,
                            grade, np.nan_to_num(lab, nan=0.0),
                            np.array([a.lot_id for a in assays]))
    return np.nan_to_num(rate, nan=0.0)


def _lot_diff_pp(join, lower_lot: str, upper_lot: str) -> np.ndarray | None:
    """The upper lot's planned grade less the lower's (pp, per analyte); None when the two
    are one lot or either is undeclared."""
    lo, hi = join.lots.get(lower_lot), join.lots.get(upper_lot)
    if lower_lot == upper_lot or lo is None or hi is None:
        return None
    diff = np.array([hi.get(a, math.nan) - lo.get(a, math.nan) for a in join.analytes])
    return np.nan_to_num(diff)     # an analyte one plan lacks: no known difference


def _figure(config: UncertaintyConfig, join, pieces: _Pieces, volume: VolumeVariance,
            volume_m3: float, boundaries: list[tuple[float, np.ndarray]],
            residual_m3: float = 0.0) -> dict:
    """:func:`figure_sd` of gathered pieces; ``boundaries``: ``(band volume m^3, diff pp)``,
    the band's tonnes at the pieces' mean density."""
    p = pieces.arrays()
    density = float(p["tonnes"].sum()) / volume_m3 if volume_m3 > 0 else 0.0
    n_a = len(join.analytes)
    bt = np.array([v * density for v, _d in boundaries], np.float64)
    diff = np.array([d for _v, d in boundaries], np.float64).reshape(len(boundaries), n_a)
    return figure_sd(config, join.analytes, volume=volume, volume_m3=max(volume_m3, 0.0),
                     boundary_tonnes=bt, boundary_grade_diff_pp=diff,
                     residual_m3=residual_m3,
                     drift_var_pp2=(pieces.drift_var_pp2(drift_rate(join, config))
                                    if config.window_drift else None), **p)


def pile_sd(state, join, config: UncertaintyConfig) -> dict:
    """``{"tonnes_sd", "grade_sd"}`` of a folded state's whole pile (module docstring)."""
    stack, geometry = state.stack, state.pile.geometry
    area = geometry.cell_area_m2
    pieces, boundaries, volume_m3 = _Pieces(join), [], 0.0
    for k in range(1, stack.n_deposits + 1):
        cells, thick, times = stack.deposit_cells(k)
        pieces.add(stack.info(k).lot_id, times, thick * area)
        volume_m3 += float(thick.sum() * area)
        if k < stack.n_deposits:
            diff = _lot_diff_pp(join, stack.info(k).lot_id, stack.info(k + 1).lot_id)
            if diff is not None:
                lo, z, hi = stack.surface_k(k - 1), stack.surface_k(k), stack.surface_k(k + 1)
                both = (z > lo) & (hi > z)
                band = boundary_band_thickness_m(lo[both], z[both], hi[both],
                                                 config.boundary_band_m)
                boundaries.append((float(band.sum() * area), diff))
    var = (state.height.variance if state.height is not None
           else np.full(geometry.shape, np.nan))
    volume = _volume(config, var, stack.surface() > stack.ground(), area)
    return _figure(config, join, pieces, volume, volume_m3, boundaries)


def _volume(config: UncertaintyConfig, var_m2, mask, area_m2: float) -> VolumeVariance:
    return volume_variance(var_m2, mask, area_m2, corr_cells=config.corr_cells,
                           corr_share=config.corr_share, unseen_sd_m=config.unseen_sd_m)


def cut_sd(cut, state, join, config: UncertaintyConfig) -> dict:
    """``{"tonnes_sd", "grade_sd"}`` of one cut record of a folded state (a planned cut's
    too: its ``footprint_var_m2`` None) (module docstring)."""
    geometry = state.pile.geometry
    area = geometry.cell_area_m2
    pieces, volume_m3 = _Pieces(join), 0.0
    removed: dict[int, tuple] = {}          # deposit -> (info, removed thickness (nx*ny,))
    for removal in cut.removals:
        for d in removal.deposits:
            pieces.add(d.info.lot_id, d.deposition_time_ns, d.cell_volume_m3)
            volume_m3 += d.volume_m3
            info, thick = removed.get(d.index, (d.info, np.zeros(geometry.nx * geometry.ny)))
            np.add.at(thick, np.ravel_multi_index((d.ix, d.iy), geometry.shape),
                      d.cell_volume_m3 / area)
            removed[d.index] = (info, thick)
    boundaries = []
    order = sorted(removed)
    for lower, upper in zip(order, order[1:]):
        (lo_info, lo_m), (hi_info, hi_m) = removed[lower], removed[upper]
        diff = _lot_diff_pp(join, lo_info.lot_id, hi_info.lot_id)
        both = (lo_m > 0) & (hi_m > 0) & (np.maximum(lo_m, hi_m) >= config.boundary_sliver_m)
        if diff is not None and both.any():
            band = boundary_band_thickness_m(-lo_m[both], np.zeros(int(both.sum())), hi_m[both],
                                             config.boundary_band_m)
            boundaries.append((float(band.sum() * area), diff))
    volume = _volume(config, *_footprint_grid(cut, state), area)
    return _figure(config, join, pieces, volume, volume_m3, boundaries, cut.residual_m3)


def _footprint_grid(cut, state) -> tuple[np.ndarray, np.ndarray]:
    """``(variance (nx, ny) m^2, mask)`` of a cut's footprint before it: the variances the
    fold kept (over its envelope's removal), else (a planned cut: over all its removals)
    the height map's current ones, else never seen."""
    shape = state.pile.geometry.shape
    kept = cut.footprint_var_m2
    parts = cut.removals[:1] if kept is not None else cut.removals
    cells = np.unique(np.concatenate([r.flat_cells(shape) for r in parts] + [
        np.zeros(0, np.int64)]))
    var, mask = np.full(shape, np.nan), np.zeros(shape, bool)
    mask.ravel()[cells] = True
    if kept is not None and kept.shape == cells.shape:
        var.ravel()[cells] = kept
    elif state.height is not None:
        var.ravel()[cells] = state.height.variance.ravel()[cells]
    return var, mask
