"""Standard deviations of a pile's or a cut's tonnes and grade: the numerical kernels.

Pure functions on numpy arrays, shapes and values checked up front (``ValueError``).
Errors are zero-mean, propagated to first order; each kernel's model and what it leaves
out are in its docstring and docs/uncertainty.md.

How the query calls them (:mod:`projector.summary_sd`; docs/uncertainty.md has the detail)
------------------------------------------------------------------------------------------
- The pile: ``var_m2 = state.height.variance``, ``mask`` = the cells with material;
  pieces = every deposit's grade classes: ``group`` an id per assay (assayed classes) or
  per lot (the planned class), ``density_reported`` where the assay gave a density;
  boundaries between consecutive deposits of different lots from
  :func:`boundary_band_thickness_m` on ``S(k-1), S(k), S(k+1)``.
- A cut: the same from its ``removals``, ``mask`` = its envelope's removed cells with
  the variances the fold kept of them just before the cut, ``residual_m3`` from the cut
  record (its floor is the envelope's, so no survey after it is added).
- ``plan``, ``audit`` and the dashboard read the figures the query returns.

Units: m, m^2, m^3 (variances m^6), tonnes, t/m^3, mass % (grade sds in percentage
points, pp).  Grids are ``(nx, ny)`` arrays indexed ``[ix, iy]`` (:mod:`projector.grid`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import NamedTuple

import numpy as np

__all__ = ["VolumeVariance", "volume_variance", "tonnes_sd", "weighted_mean_sd", "density_rel_sd",
           "boundary_band_thickness_m", "grade_sd", "UncertaintyConfig", "figure_sd"]


def _finite_nonneg(name: str, value, top: float = math.inf) -> float:
    if not (math.isfinite(v := float(value)) and 0 <= v <= top):
        raise ValueError(f"{name} must be finite and in [0, {top}], got {value!r}")
    return v


def _bools(name: str, values, shape: tuple) -> np.ndarray:
    if (a := np.asarray(values)).shape != shape or (a.dtype != bool and a.size):
        raise ValueError(f"{name} must be a bool array of shape {shape}, got {a.shape}")
    return a.astype(bool)


class VolumeVariance(NamedTuple):
    """A region's volume variance (m^6) by term, its never-seen cells and all its cells."""

    independent_m6: float
    correlated_m6: float
    unseen_m6: float
    unseen_cells: int
    cells: int

    @property
    def variance_m6(self) -> float:
        return self.independent_m6 + self.correlated_m6 + self.unseen_m6

    @property
    def sd_m3(self) -> float:
        return math.sqrt(self.variance_m6)

    def plus(self, other: VolumeVariance) -> VolumeVariance:
        """Two independent surveys' sum or difference (a cut: before less after)."""
        return VolumeVariance(*(a + b for a, b in zip(self[:4], other[:4])), self.cells)


def _block_ids(shape: tuple[int, int], corr_cells) -> np.ndarray:
    """Block index of every cell (nx, ny): ``bx x by`` cells from the grid's corner."""
    b = np.asarray(corr_cells)
    if b.dtype.kind not in "iu" or b.shape not in ((), (2,)) or (b < 1).any():
        raise ValueError(f"corr_cells must be an integer >= 1 or a pair, got {corr_cells!r}")
    bx, by = (int(v) for v in np.broadcast_to(b, (2,)))
    ix, iy = np.indices(shape)
    return (ix // bx) * -(-shape[1] // by) + iy // by


def volume_variance(var_m2, mask, cell_area_m2: float, *, corr_cells=10,
                    corr_share: float = 0.5, unseen_sd_m: float = 0.5) -> VolumeVariance:
    """Variance of a region's volume from the height map's per-cell variances.

    The volume's error is ``cell_area_m2`` times the sum of the region's height errors.
    A seen cell ``c`` (``s_c = sqrt(var_m2[c])``) errs by ``sqrt(1 - r) s_c e_c +
    sqrt(r) s_c n_b``: a part of its own and a part shared by its block ``b`` (a pose
    error moves a stretch of scan lines together), ``r = corr_share``; a never-seen cell
    by ``unseen_sd_m u_b``, one guess per block (a hole is filled as a whole); ``e``,
    ``n``, ``u`` independent standard normals.  Blocks of ``corr_cells`` cells a side
    tile the grid from its corner.  So::

        var = A^2 [ (1 - r) sum_c s_c^2 + r sum_b (sum_{c in b} s_c)^2
                    + unseen_sd_m^2 sum_b n_unseen(b)^2 ]

    It leaves out correlation across block edges, errors shared by the whole region (a
    scanner height, ground or localizer bias), a persistent pose error that the Kalman
    fusion averages as if independent, and the region's edge (the mask is exact).

    Parameters
    ----------
    var_m2 : array_like, shape (nx, ny)
        Each cell's fused height variance (m^2), NaN = never seen (``HeightMap.variance``).
    mask : array_like of bool, shape (nx, ny)
        The region (a cut's footprint, the pile's cells).
    cell_area_m2 : float
        Area of one cell (m^2), > 0.
    corr_cells, corr_share, unseen_sd_m : int or (int, int), float, float
        The block edge (cells along x and y, >= 1; 1: every cell independent), ``r`` (in
        [0, 1]) and the never-seen cells' prior sd (m).

    Returns
    -------
    VolumeVariance
    """
    var = np.asarray(var_m2, dtype=np.float64)
    if var.ndim != 2:
        raise ValueError(f"var_m2 must have shape (nx, ny), got {var.shape}")
    region = _bools("mask", mask, var.shape)
    if np.isinf(var).any() or (var < 0).any():
        raise ValueError("var_m2 must be >= 0 and finite (NaN = never seen)")
    area = _finite_nonneg("cell_area_m2", cell_area_m2)
    prior = _finite_nonneg("unseen_sd_m", unseen_sd_m)
    r = _finite_nonneg("corr_share", corr_share, 1.0)
    if area == 0:
        raise ValueError("cell_area_m2 must be > 0")
    blocks = _block_ids(var.shape, corr_cells)
    unseen = region & np.isnan(var)
    seen = region & ~unseen
    s = np.sqrt(var[seen])
    per_block_s = np.bincount(blocks[seen], weights=s)              # sum of sds per block
    per_block_u = np.bincount(blocks[unseen]).astype(np.float64)   # unseen cells per block
    return VolumeVariance(area ** 2 * (1.0 - r) * float(np.sum(s * s)),
                          area ** 2 * r * float(np.sum(per_block_s ** 2)),
                          (area * prior) ** 2 * float(np.sum(per_block_u ** 2)),
                          int(unseen.sum()), int(region.sum()))


def tonnes_sd(volume_m3: float, volume_sd_m3: float, density_t_m3: float,
              density_rel_sd: float, residual_sd_m3: float = 0.0) -> float:
    """Sd of ``tonnes = volume x density`` (t), to first order, errors independent.

    ``sd^2 = (density volume_sd)^2 + (volume density density_rel_sd)^2
    + (density residual_sd)^2``.  It leaves out the second-order product of the two
    errors and any correlation of volume with density (compaction).

    Parameters
    ----------
    volume_m3, volume_sd_m3, residual_sd_m3 : float
        The volume, its sd and a cut's geometry-residual sd (0 for a pile), m^3, >= 0.
    density_t_m3, density_rel_sd : float
        The mean bulk density (t/m^3: tonnes / volume) and its relative sd (1 = 100 %).

    Returns
    -------
    float
        The tonnes' sd (t).
    """
    v, sv, rho, rel, sr = (_finite_nonneg(n, x) for n, x in zip(
        ("volume_m3", "volume_sd_m3", "density_t_m3", "density_rel_sd", "residual_sd_m3"),
        (volume_m3, volume_sd_m3, density_t_m3, density_rel_sd, residual_sd_m3)))
    return math.sqrt((rho * sv) ** 2 + (v * rho * rel) ** 2 + (rho * sr) ** 2)


def _pieces(tonnes, group) -> tuple[np.ndarray, np.ndarray]:
    t, g = np.asarray(tonnes, dtype=np.float64), np.asarray(group)
    if (t.ndim != 1 or g.shape != t.shape or (g.dtype.kind not in "iu" and g.size) or (g < 0).any()
            or not np.isfinite(t).all() or (t < 0).any()):
        raise ValueError(f"tonnes (finite, >= 0) and group (integers >= 0) must share one "
                         f"shape (N,), got {t.shape} and {g.dtype} {g.shape}")
    return t, g.astype(np.int64)


def weighted_mean_sd(tonnes, group, group_sd) -> np.ndarray:
    """Sd of a tonnage-weighted mean whose pieces share one error per group.

    ``sum_i t_i (x_i + d_g(i)) / T`` with ``d_k`` of sd ``sd_k``, independent across groups
    (assay windows, lots), has the sd ``sqrt(sum_k (T_k / T)^2 sd_k^2)``, ``T_k`` the
    group's tonnes: ``N`` equal groups give ``sd / sqrt(N)``.

    Parameters
    ----------
    tonnes, group : array_like, shape (N,)
        The pieces' tonnes (t, >= 0) and integer group ids (``0 .. K - 1``).
    group_sd : array_like, shape (K,) or (K, A)
        Each group's error sd (pp, or relative), per analyte with (K, A); NaN = unknown
        (NaN result if that group has tonnes).

    Returns
    -------
    ndarray, shape () or (A,)
        The mean's sd in ``group_sd``'s unit (0 when ``T`` is 0).
    """
    t, g = _pieces(tonnes, group)
    sd = np.asarray(group_sd, dtype=np.float64)
    if (sd.ndim not in (1, 2) or (g.size and sd.shape[0] <= g.max()) or np.isinf(sd).any()
            or (sd < 0).any()):
        raise ValueError(f"group_sd must be (K,) or (K, A), K > every group id, >= 0 or NaN; "
                         f"got shape {sd.shape}")
    total = float(t.sum())
    if total <= 0:
        return np.zeros(sd.shape[1:])
    share = np.bincount(g, weights=t, minlength=sd.shape[0]) / total
    used = share > 0      # an unknown sd of a group with no tonnes does not count
    terms = (share[used] ** 2).reshape((-1,) + (1,) * (sd.ndim - 1)) * sd[used] ** 2
    return np.sqrt(terms.sum(axis=0))


def density_rel_sd(tonnes, group, reported, repeat_rel: float, default_rel: float) -> float:
    """Relative sd of the tonnage-weighted bulk density of some pieces.

    A piece's density is its assay's (``reported``: relative sd ``repeat_rel``, one
    error per window) or the pile's default (one error shared by all such pieces, relative
    sd ``default_rel``): :func:`weighted_mean_sd` over the windows and that one group.

    Parameters
    ----------
    tonnes, group : array_like, shape (N,)
        The pieces' tonnes (t) and assay window ids (ignored where not ``reported``).
    reported : array_like of bool, shape (N,)
        Whether an assay reported the piece's density.
    repeat_rel, default_rel : float
        Relative sds (1 = 100 %), >= 0.

    Returns
    -------
    float
    """
    t, g = _pieces(tonnes, group)
    rep = _bools("reported", reported, t.shape)
    rr, dr = _finite_nonneg("repeat_rel", repeat_rel), _finite_nonneg("default_rel", default_rel)
    k = int(g.max()) + 1 if g.size else 0
    groups = np.where(rep, g, k)          # the defaulted pieces: one more group
    return float(weighted_mean_sd(t, groups, np.append(np.full(k, rr), dr)))


def boundary_band_thickness_m(lower_bottom_m, boundary_m, upper_top_m, band_m: float):
    """Thickness (m) of material within ``band_m`` of a buried boundary, per cell.

    ``max(0, min(boundary + band, upper_top) - max(boundary - band, lower_bottom))``
    of the deposits ``(lower_bottom, boundary]`` and ``(boundary, upper_top]`` (for a cut,
    clipped to what it removed).

    Parameters
    ----------
    lower_bottom_m, boundary_m, upper_top_m, band_m : array_like (one shape), float
        Heights (m), ``lower_bottom <= boundary <= upper_top``; the band's half-width (m).

    Returns
    -------
    ndarray
        Thickness (m), >= 0, in the inputs' shape.
    """
    lo, z, hi = (np.asarray(a, float) for a in (lower_bottom_m, boundary_m, upper_top_m))
    if not (lo.shape == z.shape == hi.shape):
        raise ValueError(f"heights must share one shape, got {lo.shape, z.shape, hi.shape}")
    b = _finite_nonneg("band_m", band_m)
    return np.maximum(0.0, np.minimum(z + b, hi) - np.maximum(z - b, lo))


def grade_sd(tonnes, group, assayed, lab_sd_pp, planned_sd_pp, boundary_tonnes=(),
             boundary_grade_diff_pp=None, drift_var_pp2=None) -> np.ndarray:
    """Sd (pp) per analyte of the grade of a mixture of pieces.

    Independent terms in quadrature: (a) assayed pieces, the lab's error, one per
    assay window (``group``), sd ``lab_sd_pp``; (d) with it, the drift of the belt's grade
    inside the window: the pieces of a window hold part of its material, whose grade
    differs from the window's by the variance ``drift_var_pp2``
    (:func:`projector.window_drift.part_variance_pp2`); (b) pieces graded from planned
    grades, one error per group (a lot), sd ``planned_sd_pp``; (c) per buried boundary
    ``b``, the ``boundary_tonnes[b]`` within its band could belong to either lot: the true
    boundary lies anywhere in the band (uniform), so the tonnes given to the wrong lot are
    uniform in ``+-t_b / 2`` (sd ``t_b / (2 sqrt 3)``) and move the grade by that x
    ``diff_b / T``; boundaries independent.  (a), (b), (d): :func:`weighted_mean_sd` over
    all pieces (``T`` t).  Left out: the lab's bias, correlation between groups.

    Parameters
    ----------
    tonnes, group : array_like, shape (N,)
        The pieces' tonnes (t) and groups (``0 .. K - 1``): an assay window when assayed,
        a lot (or a lot's stretch of belt) when not; a group is all assayed or all not.
    assayed : array_like of bool, shape (N,)
    lab_sd_pp, planned_sd_pp : array_like, shape (A,) or (K, A)
        The lab's repeatability, and a planned grade's sd about the truth (pp): one for
        all groups or a row per group (the other kind's rows ignored); NaN = unknown.
    boundary_tonnes, boundary_grade_diff_pp : array_like, shape (B,) and (B, A)
        Tonnes within each boundary's band (t), and the upper lot's grade less the
        lower's (pp; None when B is 0).
    drift_var_pp2 : array_like, shape (K, A), optional
        Per group, the variance (pp^2, >= 0) of its pieces' grade about its window's
        (assayed groups only; NaN: unknown, taken as 0).  None: no drift term.

    Returns
    -------
    ndarray, shape (A,)
        The grade's sd (pp); NaN for an analyte whose needed sd is unknown.
    """
    t, g = _pieces(tonnes, group)
    k = int(g.max()) + 1 if g.size else 0
    n_assayed = np.bincount(g[_bools("assayed", assayed, t.shape)], minlength=k)
    if ((n_assayed > 0) & (n_assayed < np.bincount(g, minlength=k))).any():
        raise ValueError("a group must be all assayed or all graded from planned grades")
    lab, plan = (np.asarray(a, dtype=np.float64) for a in (lab_sd_pp, planned_sd_pp))
    n_a = lab.shape[-1] if lab.ndim in (1, 2) else -1
    if (n_a < 0 or plan.shape[-1:] != (n_a,) or max(lab.ndim, plan.ndim) > 2
            or any(a.ndim == 2 and a.shape[0] < k for a in (lab, plan))):
        raise ValueError(f"lab_sd_pp and planned_sd_pp must have shape (A,) or (K, A), "
                         f"K >= {k}, one A, got {lab.shape} and {plan.shape}")
    lab, plan = (np.broadcast_to(a, (k, n_a)) if a.ndim == 1 else a for a in (lab, plan))
    per_group = np.where((n_assayed > 0)[:, None], lab[:k], plan[:k])
    if drift_var_pp2 is not None:
        drift = np.asarray(drift_var_pp2, dtype=np.float64)
        if drift.ndim != 2 or drift.shape[0] < k or drift.shape[1] != n_a or (drift < 0).any():
            raise ValueError(f"drift_var_pp2 must have shape (K, A), K >= {k}, A {n_a}, "
                             f">= 0 or NaN; got {drift.shape}")
        drift = np.where((n_assayed > 0)[:, None], np.nan_to_num(drift[:k], nan=0.0), 0.0)
        per_group = np.sqrt(per_group ** 2 + drift)
    var = weighted_mean_sd(t, g, per_group) ** 2
    bt = np.asarray(boundary_tonnes, dtype=np.float64)
    diff = np.asarray(boundary_grade_diff_pp if bt.size else np.zeros((0, n_a)), float)
    if (bt.ndim != 1 or not np.isfinite(bt).all() or (bt < 0).any()
            or diff.shape != (bt.size, n_a) or np.isinf(diff).any()):
        raise ValueError(f"boundary_tonnes must be (B,), finite, >= 0 and boundary_grade_"
                         f"diff_pp (B, {n_a}), got {bt.shape} and {diff.shape}")
    total = float(t.sum())
    moved_share = bt / (2.0 * math.sqrt(3.0) * total) if total > 0 else 0.0 * bt  # sd / T
    return np.sqrt(var + np.sum((moved_share[:, None] * diff) ** 2, axis=0))


@dataclass(frozen=True)
class UncertaintyConfig:
    """The error model's parameters (docs/uncertainty.md says why each default).

    Attributes
    ----------
    corr_cells, corr_share, unseen_sd_m
        :func:`volume_variance`'s block edge (cells), correlated share, prior sd (m).
    density_repeat_rel, density_default_rel : float
        Relative sds of an assay's bulk density and of the pile's default one.
    lab_sd_pp, planned_sd_pp : mapping
        Analyte -> the lab's repeatability sd (pp), where an assay states none; the sd of
        a lot's planned grade about the truth (pp).
    boundary_band_m, residual_sd_share : float
        Half-width (m) of the band about a buried boundary whose lot is uncertain; the
        share of a cut's geometry residual (m^3) taken as its volume sd.
    window_drift : bool
        Whether the grade adds the belt's drift inside each assay window (term (d)).
    """

    corr_cells: int = 20
    corr_share: float = 1.0
    unseen_sd_m: float = 0.5
    density_repeat_rel: float = 0.01
    density_default_rel: float = 0.05
    lab_sd_pp: Mapping[str, float] = field(hash=False, default_factory=lambda: {
        "Fe": 0.15, "SiO2": 0.08, "Al2O3": 0.04, "P": 0.003, "LOI": 0.1})
    planned_sd_pp: Mapping[str, float] = field(hash=False, default_factory=lambda: {
        "Fe": 2.5, "SiO2": 1.2, "Al2O3": 0.25, "P": 0.01, "LOI": 0.4})
    boundary_band_m: float = 0.06
    boundary_sliver_m: float = 0.12
    residual_sd_share: float = 0.5
    window_drift: bool = True

    def __post_init__(self) -> None:
        _block_ids((1, 1), self.corr_cells)
        _finite_nonneg("corr_share", self.corr_share, 1.0)
        for name in ("unseen_sd_m", "density_repeat_rel", "density_default_rel",
                     "boundary_band_m", "boundary_sliver_m", "residual_sd_share"):
            _finite_nonneg(name, getattr(self, name))
        for name in ("lab_sd_pp", "planned_sd_pp"):   # read-only, checked
            table = {str(k): _finite_nonneg(f"{name}[{k}]", v)
                     for k, v in getattr(self, name).items()}
            object.__setattr__(self, name, MappingProxyType(table))


def figure_sd(config: UncertaintyConfig, analytes: Sequence[str], *, volume: VolumeVariance,
              volume_m3: float, tonnes, group, assayed, density_reported,
              boundary_tonnes=(), boundary_grade_diff_pp=None, residual_m3: float = 0.0,
              lab_sd_pp=None, drift_var_pp2=None) -> dict:
    """The sds of a pile's or a cut's tonnes and grade.

    Parameters
    ----------
    config : UncertaintyConfig
    analytes : sequence of str
        The grade's analytes (A of them, in order).
    volume : VolumeVariance
        The region's :func:`volume_variance` (a cut: both surveys, ``plus``).
    volume_m3 : float
        The region's volume (m^3); density = ``sum(tonnes) / volume_m3``.
    tonnes, group, assayed, boundary_tonnes, boundary_grade_diff_pp, density_reported
        As :func:`grade_sd` (boundary tonnes within ``config.boundary_band_m``) and
        :func:`density_rel_sd` (``reported``).
    residual_m3 : float
        A cut's geometry residual (m^3, either sign; x ``config.residual_sd_share``: a sd).
    lab_sd_pp : array_like, shape (A,) or (K, A), optional
        The lab's stated repeatability (a row per group); where NaN or not given, the
        configured one.
    drift_var_pp2 : array_like, shape (K, A), optional
        As :func:`grade_sd` (ignored unless ``config.window_drift``).

    Returns
    -------
    dict
        ``{"tonnes_sd": t, "grade_sd": {analyte: pp}}``.
    """
    analytes, (t, g) = tuple(analytes), _pieces(tonnes, group)
    v = _finite_nonneg("volume_m3", volume_m3)
    density = float(t.sum()) / v if v > 0 else 0.0
    rel = density_rel_sd(t, g, density_reported, config.density_repeat_rel,
                         config.density_default_rel)
    t_sd = tonnes_sd(v, volume.sd_m3, density, rel,
                     config.residual_sd_share * abs(float(residual_m3)))
    lab, plan = ([table.get(a, math.nan) for a in analytes]     # NaN: not configured
                 for table in (config.lab_sd_pp, config.planned_sd_pp))
    if lab_sd_pp is not None:
        stated = np.asarray(lab_sd_pp, dtype=np.float64)
        lab = np.where(np.isnan(stated), np.asarray(lab, dtype=np.float64), stated)
    sd = grade_sd(t, g, assayed, lab, plan, boundary_tonnes, boundary_grade_diff_pp,
                  drift_var_pp2 if config.window_drift else None)
    return {"tonnes_sd": t_sd, "grade_sd": {a: float(s) for a, s in zip(analytes, sd)}}
