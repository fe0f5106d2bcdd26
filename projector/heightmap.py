"""Per-cell Kalman height fusion with Mahalanobis gating: the fused 2.5D height map.

After ANYbotics ``elevation_mapping`` (Fankhauser et al. 2014, 2018): each cell of a
2.5D grid (:mod:`projector.grid`) carries a height estimate and its variance;
a new measurement of the cell is fused by a 1-D Kalman step when it is consistent with
the estimate (its Mahalanobis distance is within a gate), and otherwise rejected.  Unlike
a robot's map, a stockpile's surface really does jump by tens of centimetres (a stacking
layer, a reclaim cut), so a rejected measurement is kept as *change evidence*: when
``change_count`` consecutive rejected measurements agree with each other, the cell is
reset to them.  So

- noise never creates or erases material: a single spike (or a burst of inconsistent
  ones) is gated and forgotten at the next consistent measurement;
- a real change of the surface is accepted after ``change_count`` consistent looks.

Fusion of one observed cell (:func:`fuse`, vectorised over cells)
-----------------------------------------------------------------
- measurement ``z = obs.z_mean_m`` with variance
  ``R = (point_sd_m**2 + obs.z_var_m2) / obs.count``: the noise of a mean of ``count``
  points plus the spread of the points within the cell (slope across the cell,
  roughness) as a sampling error of that mean;
- **never seen**: initialise ``h = z``, ``P = R``;
- otherwise predict ``P- = P + process_sd_m**2`` (a random walk per observation: the
  surface may creep), and test the Mahalanobis distance ``d = |z - h| / sqrt(P- + R)``;
- **in gate** (``d <= gate_sigma``): Kalman step ``K = P- / (P- + R)``,
  ``h += K (z - h)``, ``P = (1 - K) P-``; any change evidence is cleared;
- **out of gate**: the observation is held as change evidence.  If it agrees with the
  evidence already held (``|z - z_e| / sqrt(P_e + R) <= gate_sigma``) the two are
  fused (inverse-variance); otherwise the evidence restarts from it.  When
  ``change_count`` consecutive agreeing observations are held the cell is reset to
  the evidence (``h = z_e``, ``P = P_e``): a real rise (stacking) or drop (reclaim).

The position of the measurement in the cell (``obs.x_offset_m``, ``obs.y_offset_m``) is
carried with the same weights, so ``x_offset_m``/``y_offset_m`` say where in the cell
``elevation`` was measured (:func:`projector.elevation.centre_elevation`).

Pipeline (all pure functions, no I/O)::

    points (N, 3) --rasterize--> CellObservations --fuse--> HeightMap
        --centre_elevation--> heights at cell centres --volume_above--> m3

The last two steps, and the filling of holes inside the data's footprint, are in
:mod:`projector.elevation`; the local plane fit of the seen cells is in
:mod:`projector.surface_fit`.

Units: metres, m^2, m^3, UTC nanoseconds.  Layers are ``float64 (nx, ny)`` arrays
indexed ``[ix, iy]`` as in :mod:`projector.grid`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from projector.elevation import centre_elevation
from projector.grid import GridGeometry, GridMap, cell_index

__all__ = ["CellObservations", "rasterize", "HeightMap", "FuseStats", "fuse", "accept_rises",
           "clear_evidence"]


# --------------------------------------------------------------------------------------
# Rasterisation
# --------------------------------------------------------------------------------------

@dataclass(frozen=True)
class CellObservations:
    """Points aggregated per grid cell: one row per occupied cell, flat arrays of length K.

    Attributes
    ----------
    ix, iy : ndarray of int64, shape (K,)
        Cell indices (unique pairs, sorted by ``ix * ny + iy``).
    z_mean_m : ndarray of float64, shape (K,)
        Mean height of the points in the cell (m).
    z_var_m2 : ndarray of float64, shape (K,)
        Sample variance (ddof = 1) of those heights (m^2); 0 for a single point.
    count : ndarray of int64, shape (K,)
        Number of points (>= 1).
    x_offset_m, y_offset_m : ndarray of float64, shape (K,), or None
        Mean position of the points relative to the cell centre (m, within +-cell/2):
        ``z_mean_m`` is the height *there*, not at the centre (see
        :func:`projector.elevation.centre_elevation`).  None = at the centre.
    """

    ix: np.ndarray
    iy: np.ndarray
    z_mean_m: np.ndarray
    z_var_m2: np.ndarray
    count: np.ndarray
    x_offset_m: np.ndarray | None = None
    y_offset_m: np.ndarray | None = None

    def __post_init__(self) -> None:
        k = np.shape(self.ix)
        for name in ("ix", "iy", "z_mean_m", "z_var_m2", "count", "x_offset_m", "y_offset_m"):
            a = getattr(self, name)
            if a is None and name in ("x_offset_m", "y_offset_m"):
                continue
            if not isinstance(a, np.ndarray) or a.ndim != 1 or a.shape != k:
                raise ValueError(f"CellObservations.{name} must be a 1-D array of shape {k}, "
                                 f"got {np.shape(a)}")

    def __len__(self) -> int:
        return int(self.ix.shape[0])

    @property
    def points(self) -> int:
        """Total number of points aggregated."""
        return int(self.count.sum())


def rasterize(geometry: GridGeometry, points_m) -> CellObservations:
    """Aggregate points into grid cells (mean, sample variance, count of heights).

    Parameters
    ----------
    geometry : GridGeometry
        The grid (cell ``(ix, iy)`` covers ``[x0 + ix*cell, x0 + (ix+1)*cell)`` x ...).
    points_m : array_like, shape (N, 3) or (..., 3)
        Site-frame points (m); leading axes are flattened (e.g. ``(S, B, 3)`` from
        :func:`projector.georef.georeference`).  Points with a non-finite
        coordinate or outside the grid are ignored.

    Returns
    -------
    CellObservations
        One row per occupied cell, sorted by flat index ``ix * ny + iy``, with the mean
        point position relative to the cell centre (``x_offset_m``, ``y_offset_m``).

    Notes
    -----
    Vectorised: cells are found by ``np.unique`` (sparse) or ``np.bincount`` over the whole
    grid (when there are many points per cell); the variance is two-pass (mean first,
    then squared deviations), so large heights do not cancel.
    """
    p = np.asarray(points_m, dtype=np.float64)
    if p.ndim < 2 or p.shape[-1] != 3:
        raise ValueError(f"points_m must have shape (N, 3) or (..., 3), got {p.shape}")
    p = p.reshape(-1, 3)
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    ok = np.isfinite(x) & np.isfinite(y) & np.isfinite(z)
    if not ok.all():
        x, y, z = x[ok], y[ok], z[ok]
    ix, iy = cell_index(geometry, x, y)
    nx, ny = geometry.nx, geometry.ny
    ok = (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)
    if not ok.all():
        ix, iy, x, y, z = ix[ok], iy[ok], x[ok], y[ok], z[ok]
    cell = geometry.cell_m
    # position within the cell relative to its centre, in [-cell/2, cell/2)
    dx = x - (geometry.origin_x_m + (ix + 0.5) * cell)
    dy = y - (geometry.origin_y_m + (iy + 0.5) * cell)
    lin = ix * ny + iy
    n_cells = nx * ny
    if lin.size > n_cells // 4:          # dense: bincount over the whole grid
        cnt_all = np.bincount(lin, minlength=n_cells)
        occ = np.flatnonzero(cnt_all)
        cnt = cnt_all[occ]
        key, k = lin, n_cells
    else:                                 # sparse: sort the flat indices
        occ, key, cnt = np.unique(lin, return_inverse=True, return_counts=True)
        k = occ.size
    sel = occ if key is lin else slice(None)
    inv_cnt = 1.0 / cnt
    mean = np.bincount(key, weights=z, minlength=k)[sel] * inv_cnt
    mx = np.bincount(key, weights=dx, minlength=k)[sel] * inv_cnt
    my = np.bincount(key, weights=dy, minlength=k)[sel] * inv_cnt
    if key is lin:
        mean_all = np.zeros(n_cells)
        mean_all[occ] = mean
        dev = z - mean_all[lin]
    else:
        dev = z - mean[key]
    ss = np.bincount(key, weights=dev * dev, minlength=k)[sel]
    cnt = cnt.astype(np.int64)
    var = np.where(cnt > 1, ss / np.maximum(cnt - 1, 1), 0.0)
    return CellObservations(ix=(occ // ny).astype(np.int64), iy=(occ % ny).astype(np.int64),
                            z_mean_m=mean, z_var_m2=var, count=cnt, x_offset_m=mx,
                            y_offset_m=my)


# --------------------------------------------------------------------------------------
# The height map and its fusion
# --------------------------------------------------------------------------------------

#: layers of a :class:`HeightMap` and their initial values
_LAYERS = {
    "elevation": math.nan,        # m; NaN = never seen
    "variance": math.nan,         # m^2 of the elevation estimate; NaN = never seen
    "last_update_ns": math.nan,   # UTC ns (as float64) of the last init/update/change
    "pending_z": math.nan,        # m; fused height of the current change evidence
    "pending_var": math.nan,      # m^2 of pending_z
    "pending_count": 0.0,         # consecutive agreeing out-of-gate observations held
    "x_offset_m": math.nan,       # m; where in the cell the elevation was measured,
    "y_offset_m": math.nan,       #    relative to the centre (weighted like the heights)
    "pending_x_offset_m": math.nan,
    "pending_y_offset_m": math.nan,
    "pending_since_ns": math.nan,  # UTC ns of the first observation of the change evidence
    "observed_ns": math.nan,      # UTC ns when the elevation's level was first observed
}


#: the layers holding a cell's change evidence; cleared, they take their initial values
_EVIDENCE = ("pending_z", "pending_var", "pending_count", "pending_x_offset_m",
             "pending_y_offset_m", "pending_since_ns")


def clear_evidence(layers, index) -> None:
    """Drop the change evidence held at ``index`` (a mask or indices) of ``layers``: a
    :class:`HeightMap`'s grid, or a dict of the same layers (e.g. flat views)."""
    for name in _EVIDENCE:
        layers[name][index] = _LAYERS[name]


@dataclass
class HeightMap:
    """A fused 2.5D height map: a :class:`GridMap` with the layers below.

    Layers (``float64 (nx, ny)``)
    -----------------------------
    elevation : m, NaN = never seen
    variance : m^2, variance of ``elevation``
    last_update_ns : UTC ns of the last initialisation, update or change, as float64
        (so about 256 ns resolution at present-day epochs); NaN = never.
    pending_z, pending_var : m, m^2; the fused height of the change evidence (NaN = none)
    pending_count : number of consecutive, mutually agreeing out-of-gate observations
    x_offset_m, y_offset_m : m; the mean position, relative to the cell centre, of the
        points behind ``elevation`` (weighted as the heights were); ``elevation`` is the
        height *there*.  :meth:`centred_elevation` moves it to the centre.
    pending_x_offset_m, pending_y_offset_m : the same for the change evidence
    pending_since_ns : UTC ns of the first observation of the change evidence (NaN = none)
    observed_ns : UTC ns when the cell was first seen at its current level: the time of
        its last initialisation or in-gate update, or for an accepted change the first
        observation of the change evidence (a change seen once and confirmed later was
        there from the first sighting).

    Use :meth:`empty` to create one and :func:`fuse` to update it (it returns a new map).
    """

    grid: GridMap

    LAYERS = tuple(_LAYERS)

    def __post_init__(self) -> None:
        missing = [k for k in _LAYERS if k not in self.grid]
        if missing:
            raise ValueError(f"HeightMap grid lacks layers {missing}")

    @classmethod
    def empty(cls, geometry: GridGeometry) -> "HeightMap":
        """A map of ``geometry`` where no cell has been seen."""
        grid = GridMap(geometry)
        for name, fill in _LAYERS.items():
            grid.add(name, fill)
        return cls(grid)

    def copy(self) -> "HeightMap":
        """A deep copy (all layers copied)."""
        return HeightMap(self.grid.copy())

    @property
    def geometry(self) -> GridGeometry:
        return self.grid.geometry

    @property
    def elevation(self) -> np.ndarray:
        """``(nx, ny)`` heights (m), NaN never seen (the array itself, not a copy)."""
        return self.grid["elevation"]

    @property
    def variance(self) -> np.ndarray:
        """``(nx, ny)`` variances (m^2), NaN never seen."""
        return self.grid["variance"]

    @property
    def seen(self) -> np.ndarray:
        """``(nx, ny)`` bool: cells with an estimate."""
        return ~np.isnan(self.grid["elevation"])

    def centred_elevation(self) -> np.ndarray:
        """``(nx, ny)`` heights (m) at the cell centres, see
        :func:`projector.elevation.centre_elevation`."""
        return centre_elevation(self.grid["elevation"], self.grid["x_offset_m"],
                                self.grid["y_offset_m"], self.geometry.cell_m)


@dataclass(frozen=True)
class FuseStats:
    """What one :func:`fuse` call did, counted in cells.

    Attributes
    ----------
    cells_initialised : first observation of a cell
    cells_updated : in-gate observations fused by a Kalman step
    cells_gated : out-of-gate observations held as change evidence (not yet a change)
    cells_changed_up, cells_changed_down : cells reset to their change evidence, above or
        below the previous estimate
    """

    cells_initialised: int = 0
    cells_updated: int = 0
    cells_gated: int = 0
    cells_changed_up: int = 0
    cells_changed_down: int = 0

    @property
    def cells_observed(self) -> int:
        return (self.cells_initialised + self.cells_updated + self.cells_gated
                + self.cells_changed_up + self.cells_changed_down)


def fuse(heightmap: HeightMap, obs: CellObservations, t_ns: int, point_sd_m: float, *,
         gate_sigma: float = 3.0, change_count: int = 3,
         process_sd_m: float = 0.01, inplace: bool = False) -> tuple[HeightMap, FuseStats]:
    """Fuse one batch of cell observations into a height map (returns a new map, or the
    same one updated with ``inplace=True``).

    Each observed cell is initialised, updated by a Kalman step, or holds the observation
    as change evidence (and is reset to it after ``change_count`` agreeing ones), by the
    rules of the module docstring.

    Parameters
    ----------
    heightmap : HeightMap
        The prior map (not modified unless ``inplace``).
    obs : CellObservations
        At most one observation per cell (as from :func:`rasterize`), inside the grid.
    t_ns : int
        Time of the batch (UTC ns), written to ``last_update_ns``.
    point_sd_m : float
        Height noise sd of one point (m), >= 0.  With ``point_sd_m = 0`` a single-point
        observation has zero variance; a positive value is recommended.
    gate_sigma : float
        Mahalanobis gate (sd), > 0.
    change_count : int
        Consecutive agreeing out-of-gate observations needed for a change, >= 1.
    process_sd_m : float
        Process noise sd per observation of a cell (m), >= 0.
    inplace : bool
        Update ``heightmap`` itself instead of a copy (for a caller that owns its map and
        fuses batch after batch into it; see docs/design-notes.md).

    Returns
    -------
    heightmap : HeightMap
        A new map (``heightmap`` itself with ``inplace=True``).
    stats : FuseStats

    Raises
    ------
    ValueError
        On cells outside the grid, duplicate cells, non-finite or negative inputs.
    """
    _check_fuse_parameters(point_sd_m, gate_sigma, change_count, process_sd_m)
    batch = _batch_of(heightmap.geometry, obs, point_sd_m)
    out = heightmap if inplace else heightmap.copy()
    layers = {k: out.grid[k].reshape(-1) for k in _LAYERS}   # flat views into the copy
    t = float(t_ns)
    g2 = float(gate_sigma) ** 2

    h = layers["elevation"][batch.lin]
    new = np.isnan(h)
    p_pred = layers["variance"][batch.lin] + process_sd_m ** 2
    innov = batch.z - h
    s = p_pred + batch.r
    with np.errstate(invalid="ignore", divide="ignore"):
        d2 = np.where(s > 0, innov * innov / s, np.where(innov == 0, 0.0, np.inf))
    ingate = ~new & (d2 <= g2)
    gated = ~new & ~ingate

    _initialise(layers, batch.at(new), t)
    _kalman_update(layers, batch.at(ingate), h[ingate], innov[ingate], p_pred[ingate],
                   s[ingate], t)
    kept, up = _hold_evidence(layers, batch.at(gated), h[gated], t, g2, change_count)
    stats = FuseStats(cells_initialised=int(new.sum()), cells_updated=int(ingate.sum()),
                      cells_gated=int(kept.sum()), cells_changed_up=int(up.sum()),
                      cells_changed_down=int((~up).sum()))
    return out, stats


def _check_fuse_parameters(point_sd_m: float, gate_sigma: float, change_count: int,
                           process_sd_m: float) -> None:
    """ValueError unless :func:`fuse`'s noise, gate and change parameters are in range."""
    if not (math.isfinite(point_sd_m) and point_sd_m >= 0):
        raise ValueError(f"point_sd_m must be finite and >= 0, got {point_sd_m}")
    if not (gate_sigma > 0 and math.isfinite(gate_sigma)):
        raise ValueError(f"gate_sigma must be finite and > 0, got {gate_sigma}")
    if int(change_count) < 1:
        raise ValueError(f"change_count must be >= 1, got {change_count}")
    if not (math.isfinite(process_sd_m) and process_sd_m >= 0):
        raise ValueError(f"process_sd_m must be finite and >= 0, got {process_sd_m}")


class _Batch(NamedTuple):
    """One batch of observations as flat arrays of length K, the cells ``lin`` being flat
    indices ``ix * ny + iy``: heights ``z`` (m), their variances ``r`` (m^2) and the
    measured positions' offsets from the cell centres ``ox``, ``oy`` (m)."""

    lin: np.ndarray
    z: np.ndarray
    r: np.ndarray
    ox: np.ndarray
    oy: np.ndarray

    def at(self, mask: np.ndarray) -> "_Batch":
        """The observations where ``mask`` (bool, (K,)) is True."""
        return _Batch(self.lin[mask], self.z[mask], self.r[mask], self.ox[mask],
                      self.oy[mask])


def _batch_of(g: GridGeometry, obs: CellObservations, point_sd_m: float) -> _Batch:
    """``obs`` checked against the grid ``g`` (inside it, one row per cell, finite, counts
    >= 1) as a :class:`_Batch`, its variance ``(point_sd_m**2 + z_var_m2) / count``."""
    ix = np.asarray(obs.ix, dtype=np.int64)
    iy = np.asarray(obs.iy, dtype=np.int64)
    if ix.size and (ix.min() < 0 or ix.max() >= g.nx or iy.min() < 0 or iy.max() >= g.ny):
        raise ValueError("observations lie outside the grid")
    z = np.asarray(obs.z_mean_m, dtype=np.float64)
    zvar = np.asarray(obs.z_var_m2, dtype=np.float64)
    cnt = np.asarray(obs.count)
    zero = np.zeros(z.shape)
    ox = zero if obs.x_offset_m is None else np.asarray(obs.x_offset_m, dtype=np.float64)
    oy = zero if obs.y_offset_m is None else np.asarray(obs.y_offset_m, dtype=np.float64)
    if not (np.isfinite(z).all() and np.isfinite(zvar).all() and np.isfinite(ox).all()
            and np.isfinite(oy).all()):
        raise ValueError("observation heights, variances and offsets must be finite")
    if zvar.size and (zvar.min() < 0 or cnt.min() < 1):
        raise ValueError("observation variances must be >= 0 and counts >= 1")
    lin = ix * g.ny + iy
    if lin.size > 1 and not np.all(np.diff(lin) > 0):
        if np.unique(lin).size != lin.size:
            raise ValueError("observations must hold at most one row per cell")
    return _Batch(lin, z, (point_sd_m ** 2 + zvar) / cnt, ox, oy)


def _initialise(layers: dict, obs: _Batch, t: float) -> None:
    """First observation of cells never seen: the estimate is the observation."""
    c = obs.lin
    layers["elevation"][c] = obs.z
    layers["variance"][c] = obs.r
    layers["x_offset_m"][c], layers["y_offset_m"][c] = obs.ox, obs.oy
    layers["last_update_ns"][c] = t
    layers["observed_ns"][c] = t
    clear_evidence(layers, c)


def _kalman_update(layers: dict, obs: _Batch, h: np.ndarray, innov: np.ndarray,
                   p_pred: np.ndarray, s: np.ndarray, t: float) -> None:
    """In-gate observations: one Kalman step from the prior heights ``h`` (m) with
    innovations ``innov`` (m), predicted variances ``p_pred`` and innovation variances
    ``s`` (m^2); any change evidence is cleared."""
    c = obs.lin
    xo, yo = layers["x_offset_m"], layers["y_offset_m"]
    with np.errstate(invalid="ignore", divide="ignore"):
        k = np.where(s > 0, p_pred / s, 1.0)
    layers["elevation"][c] = h + k * innov
    layers["variance"][c] = (1.0 - k) * p_pred
    xo[c] += k * (obs.ox - xo[c])
    yo[c] += k * (obs.oy - yo[c])
    layers["last_update_ns"][c] = t
    layers["observed_ns"][c] = t
    clear_evidence(layers, c)


def _hold_evidence(layers: dict, obs: _Batch, h: np.ndarray, t: float, g2: float,
                   change_count: int) -> tuple[np.ndarray, np.ndarray]:
    """Out-of-gate observations: fused into (or restarting) each cell's change evidence;
    a cell holding ``change_count`` agreeing ones is reset to its evidence.

    ``h`` are the cells' prior heights (m), ``g2`` the squared gate (sd^2).  Returns the
    mask (over ``obs``) of the observations still held, and whether each change (over
    the cells reset) went up.
    """
    pz, pv, pc = layers["pending_z"], layers["pending_var"], layers["pending_count"]
    pxo, pyo = layers["pending_x_offset_m"], layers["pending_y_offset_m"]
    since = layers["pending_since_ns"]
    c = obs.lin
    zg, rg = obs.z, obs.r
    ez, ev, ec = pz[c], pv[c], pc[c]
    held = ec > 0
    se = ev + rg
    with np.errstate(invalid="ignore", divide="ignore"):
        de2 = np.where(se > 0, (zg - ez) ** 2 / se, np.where(zg == ez, 0.0, np.inf))
        agree = held & (de2 <= g2)
        # weight of the new observation in the fused evidence (1 = restart from it)
        w = np.where(agree, np.where(se > 0, ev / se, 1.0), 1.0)
    ez_new = np.where(agree, ez + w * (zg - ez), zg)
    ev_new = np.where(agree, (1.0 - w) * ev, rg)
    ex_new = np.where(agree, pxo[c] + w * (obs.ox - pxo[c]), obs.ox)
    ey_new = np.where(agree, pyo[c] + w * (obs.oy - pyo[c]), obs.oy)
    ec_new = np.where(agree, ec + 1.0, 1.0)
    since_new = np.where(agree & np.isfinite(since[c]), since[c], t)
    change = ec_new >= change_count
    keep = ~change
    ck = c[keep]
    pz[ck], pv[ck], pc[ck] = ez_new[keep], ev_new[keep], ec_new[keep]
    pxo[ck], pyo[ck] = ex_new[keep], ey_new[keep]
    since[ck] = since_new[keep]
    cc = c[change]
    up = ez_new[change] > h[change]
    layers["elevation"][cc] = ez_new[change]
    layers["variance"][cc] = ev_new[change]
    layers["x_offset_m"][cc], layers["y_offset_m"][cc] = ex_new[change], ey_new[change]
    layers["last_update_ns"][cc] = t
    layers["observed_ns"][cc] = since_new[change]
    clear_evidence(layers, cc)
    return keep, up


def accept_rises(heightmap: HeightMap) -> tuple[HeightMap, np.ndarray]:
    """Accept the held change evidence that lies above the elevation.

    Used at a boundary after which the evidence could no longer be told apart from
    what comes next (a new stacking pass starts pouring): a rise sighted before the
    boundary but not yet confirmed by enough observations becomes the elevation, as
    first observed when it was first sighted (``observed_ns`` and ``last_update_ns`` =
    ``pending_since_ns``).  Held evidence below the elevation is kept waiting.

    Returns
    -------
    (HeightMap, ndarray of bool (nx, ny))
        The new map and the cells whose evidence was accepted.
    """
    out = heightmap.copy()
    g = out.grid
    with np.errstate(invalid="ignore"):
        rise = (g["pending_count"] > 0) & (g["pending_z"] > g["elevation"])
    if not rise.any():
        return out, rise
    g["elevation"][rise] = g["pending_z"][rise]
    g["variance"][rise] = g["pending_var"][rise]
    g["x_offset_m"][rise] = g["pending_x_offset_m"][rise]
    g["y_offset_m"][rise] = g["pending_y_offset_m"][rise]
    g["last_update_ns"][rise] = g["pending_since_ns"][rise]
    g["observed_ns"][rise] = g["pending_since_ns"][rise]
    clear_evidence(g, rise)
    return out, rise
