"""Per-cell Kalman height fusion with Mahalanobis gating, and the volume of a heightmap.

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

Pipeline (all pure functions, no I/O)::

    points (N, 3) --rasterize--> CellObservations --fuse--> HeightMap
        --centre_elevation--> heights at cell centres --volume_above--> m3

``volume_above`` fills holes inside the data's footprint (:func:`fill_holes`) and counts
never-seen cells outside it as ground.

Units: metres, m^2, m^3, UTC nanoseconds.  Layers are ``float64 (nx, ny)`` arrays
indexed ``[ix, iy]`` as in :mod:`projector.grid`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from projector.grid import GridGeometry, GridMap, cell_index

__all__ = ["CellObservations", "rasterize", "HeightMap", "FuseStats", "fuse", "accept_rises",
           "clear_evidence", "fill_holes", "centre_elevation", "volume_above"]


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
        :func:`centre_elevation`).  None = at the centre.
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
        """``(nx, ny)`` heights (m) at the cell centres, see :func:`centre_elevation`."""
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

    Per observed cell (vectorised over cells):

    - measurement ``z = obs.z_mean_m`` with variance
      ``R = (point_sd_m**2 + obs.z_var_m2) / obs.count``: the noise of a mean of ``count``
      points plus the spread of the points within the cell (slope across the cell,
      roughness) as a sampling error of that mean;
    - **never seen**: initialise ``h = z``, ``P = R``;
    - otherwise predict ``P- = P + process_sd_m**2`` (a random walk per observation: the
      surface may creep), and test the Mahalanobis distance
      ``d = |z - h| / sqrt(P- + R)``;
    - **in gate** (``d <= gate_sigma``): Kalman step ``K = P- / (P- + R)``,
      ``h += K (z - h)``, ``P = (1 - K) P-``; any change evidence is cleared;
    - **out of gate**: the observation is held as change evidence.  If it agrees with the
      evidence already held (``|z - z_e| / sqrt(P_e + R) <= gate_sigma``) the two are
      fused (inverse-variance); otherwise the evidence restarts from it.  When
      ``change_count`` consecutive agreeing observations are held the cell is reset to
      the evidence (``h = z_e``, ``P = P_e``): a real rise (stacking) or drop (reclaim).

    The position of the measurement in the cell (``obs.x_offset_m``, ``obs.y_offset_m``)
    is carried with the same weights, so ``x_offset_m``/``y_offset_m`` say where in the
    cell ``elevation`` was measured (see :func:`centre_elevation`).

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
        Update ``heightmap`` itself instead of a copy (the fold owns its map; copying
        a full-scale map's eleven layers cost 10 ms a batch).

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
    if not (math.isfinite(point_sd_m) and point_sd_m >= 0):
        raise ValueError(f"point_sd_m must be finite and >= 0, got {point_sd_m}")
    if not (gate_sigma > 0 and math.isfinite(gate_sigma)):
        raise ValueError(f"gate_sigma must be finite and > 0, got {gate_sigma}")
    if int(change_count) < 1:
        raise ValueError(f"change_count must be >= 1, got {change_count}")
    if not (math.isfinite(process_sd_m) and process_sd_m >= 0):
        raise ValueError(f"process_sd_m must be finite and >= 0, got {process_sd_m}")
    g = heightmap.geometry
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

    out = heightmap if inplace else heightmap.copy()
    layers = {k: out.grid[k].reshape(-1) for k in _LAYERS}   # flat views into the copy
    elev, var = layers["elevation"], layers["variance"]
    pz, pv, pc = layers["pending_z"], layers["pending_var"], layers["pending_count"]
    last = layers["last_update_ns"]
    xo, yo = layers["x_offset_m"], layers["y_offset_m"]
    pxo, pyo = layers["pending_x_offset_m"], layers["pending_y_offset_m"]
    since, seen_at = layers["pending_since_ns"], layers["observed_ns"]
    t = float(t_ns)
    g2 = float(gate_sigma) ** 2
    r = (point_sd_m ** 2 + zvar) / cnt

    h = elev[lin]
    new = np.isnan(h)
    p_pred = var[lin] + process_sd_m ** 2
    innov = z - h
    s = p_pred + r
    with np.errstate(invalid="ignore", divide="ignore"):
        d2 = np.where(s > 0, innov * innov / s, np.where(innov == 0, 0.0, np.inf))
    ingate = ~new & (d2 <= g2)
    gated = ~new & ~ingate

    # first observation
    c = lin[new]
    elev[c] = z[new]
    var[c] = r[new]
    xo[c], yo[c] = ox[new], oy[new]
    last[c] = t
    seen_at[c] = t
    clear_evidence(layers, c)

    # in gate: Kalman step, evidence cleared
    c = lin[ingate]
    with np.errstate(invalid="ignore", divide="ignore"):
        k = np.where(s[ingate] > 0, p_pred[ingate] / s[ingate], 1.0)
    elev[c] = h[ingate] + k * innov[ingate]
    var[c] = (1.0 - k) * p_pred[ingate]
    xo[c] += k * (ox[ingate] - xo[c])
    yo[c] += k * (oy[ingate] - yo[c])
    last[c] = t
    seen_at[c] = t
    clear_evidence(layers, c)

    # out of gate: change evidence
    c = lin[gated]
    zg, rg = z[gated], r[gated]
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
    ex_new = np.where(agree, pxo[c] + w * (ox[gated] - pxo[c]), ox[gated])
    ey_new = np.where(agree, pyo[c] + w * (oy[gated] - pyo[c]), oy[gated])
    ec_new = np.where(agree, ec + 1.0, 1.0)
    since_new = np.where(agree & np.isfinite(since[c]), since[c], t)
    change = ec_new >= change_count
    keep = ~change
    ck = c[keep]
    pz[ck], pv[ck], pc[ck] = ez_new[keep], ev_new[keep], ec_new[keep]
    pxo[ck], pyo[ck] = ex_new[keep], ey_new[keep]
    since[ck] = since_new[keep]
    cc = c[change]
    up = ez_new[change] > h[gated][change]
    elev[cc] = ez_new[change]
    var[cc] = ev_new[change]
    xo[cc], yo[cc] = ex_new[change], ey_new[change]
    last[cc] = t
    seen_at[cc] = since_new[change]
    clear_evidence(layers, cc)

    stats = FuseStats(cells_initialised=int(new.sum()), cells_updated=int(ingate.sum()),
                      cells_gated=int(keep.sum()), cells_changed_up=int(up.sum()),
                      cells_changed_down=int((~up).sum()))
    return out, stats


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


# --------------------------------------------------------------------------------------
# Holes and volume
# --------------------------------------------------------------------------------------

def _brackets(valid: np.ndarray, axis: int) -> tuple[np.ndarray, np.ndarray]:
    """Index of the previous and the next valid cell along ``axis`` (-1 / n if none)."""
    n = valid.shape[axis]
    shape = [1, 1]
    shape[axis] = n
    idx = np.arange(n).reshape(shape)
    prev = np.where(valid, idx, -1)
    np.maximum.accumulate(prev, axis=axis, out=prev)
    nxt = np.where(valid, idx, n)
    nxt = np.flip(np.minimum.accumulate(np.flip(nxt, axis=axis), axis=axis), axis=axis)
    return prev, nxt


def _check_elevation(elevation) -> np.ndarray:
    e = np.asarray(elevation, dtype=np.float64)
    if e.ndim != 2:
        raise ValueError(f"elevation must have shape (nx, ny), got {e.shape}")
    if np.isinf(e).any():
        raise ValueError("elevation must not contain infinities (NaN = never seen)")
    return e


def plane_fit_of_seen(elevation, size_cells: int) -> np.ndarray:
    """Each seen cell's height from the least-squares plane through the seen cells of the
    ``size_cells`` x ``size_cells`` window centred on it (never-seen cells stay NaN).

    A local mean would do as well on a flat top, but beside a slope's last seen row the
    window is one-sided and the mean stands up the slope; a plane is exact on a planar
    flank up to the edge of what was seen.  Where a window's seen cells do not span a
    plane (fewer than three, or all in a line) their mean is taken.

    Parameters
    ----------
    elevation : array_like, shape (nx, ny)
        Heights (m), NaN = never seen.
    size_cells : int
        Window edge (cells), odd and >= 1 (1 returns a copy).

    Returns
    -------
    ndarray, shape (nx, ny)
        The fitted heights (m), NaN where ``elevation`` is.
    """
    from scipy import ndimage

    e = _check_elevation(elevation)
    n = int(size_cells)
    if n < 1 or n % 2 == 0:
        raise ValueError(f"size_cells must be odd and >= 1, got {size_cells}")
    seen = np.isfinite(e)
    if n == 1 or not seen.any():
        return e.copy()
    w = seen.astype(np.float64)
    z = np.where(seen, e, 0.0)
    # window sums of w, w u, w v, w uu, w uv, w vv, z, z u, z v with (u, v) the offset
    # (cells) from the window's centre: separable 1-D correlations with the kernels 1, u
    # and u^2 along each axis
    h = n // 2
    k0 = np.ones(n)
    k1 = np.arange(-h, h + 1, dtype=np.float64)
    k2 = k1 * k1

    def along(a, k, axis):
        return ndimage.correlate1d(a, k, axis=axis, mode="constant")

    # the passes along x are shared: 14 one-dimensional passes, not 18
    w0, w1, w2 = along(w, k0, 0), along(w, k1, 0), along(w, k2, 0)
    z0, z1 = along(z, k0, 0), along(z, k1, 0)
    # only the seen cells are fitted
    sel = np.flatnonzero(seen)

    def at_seen(a, k):
        return along(a, k, 1).ravel()[sel]

    a11, a13, a33 = at_seen(w0, k0), at_seen(w0, k1), at_seen(w0, k2)
    a12, a23, a22 = at_seen(w1, k0), at_seen(w1, k1), at_seen(w2, k0)
    b1, b3, b2 = at_seen(z0, k0), at_seen(z0, k1), at_seen(z1, k0)
    # the plane's height at the centre by Cramer's rule (the matrix is symmetric)
    c11 = a22 * a33 - a23 * a23
    det = a11 * c11 - a12 * (a12 * a33 - a23 * a13) + a13 * (a12 * a23 - a22 * a13)
    det1 = b1 * c11 - a12 * (b2 * a33 - a23 * b3) + a13 * (b2 * a23 - a22 * b3)
    with np.errstate(invalid="ignore", divide="ignore"):
        # det scales as count^3 x spread^2 (cells): a line of cells has det ~ 0
        planar = (a11 >= 3) & (np.abs(det) > 1e-6 * np.maximum(a11, 1.0) ** 3)
        fit = np.where(planar, det1 / det, b1 / a11)
    out = np.full(e.shape, np.nan)
    out.ravel()[sel] = fit
    return out


def fill_holes(elevation, *, method: str = "nearest",
               max_gap_cells: int | None = None) -> np.ndarray:
    """Fill never-seen cells that lie inside the data's footprint.

    A NaN cell is a **hole** when, along x (its row ``[:, iy]``) or along y (its column
    ``[ix, :]``), it lies between two seen cells with at most ``max_gap_cells`` NaN cells
    between them (any number when None).  This is the footprint test: an unseen strip
    between two scan lines, or an unseen column of cells between two beams, is a hole;
    the unseen margin outside the outermost seen cells is not (it stays NaN).  The test
    is repeated on the filled map (up to 8 passes), so a hole where an unseen row and an
    unseen column cross is filled once they are.

    Methods
    -------
    ``"nearest"``
        The value of the nearest seen cell (Euclidean distance between cell centres,
        ``scipy.ndimage.distance_transform_edt``); equidistant seen cells are averaged
        (symmetric tie-break: a one-sided one would bias a filled slope).
    ``"linear"``
        Linear interpolation between the two bracketing seen cells along each axis that
        brackets the hole (within ``max_gap_cells``), the axes weighted by the inverse
        square of their bracket length (the shorter, more local bracket dominates: an
        unseen column between two beams is filled across the column, not along it from
        the ground beyond the pile's ends).  Exact for a
        surface that is linear along the bracketing axis (a planar flank, a ridge line).

    Parameters
    ----------
    elevation : array_like, shape (nx, ny)
        Heights (m), NaN = never seen.
    method : {"nearest", "linear"}
    max_gap_cells : int or None
        Largest run of NaN cells that is still a hole (cells), >= 1; None = no limit.

    Returns
    -------
    ndarray, shape (nx, ny)
        A new array; holes filled, the rest unchanged (NaN outside the footprint).
    """
    e = _check_elevation(elevation)
    if method not in ("nearest", "linear"):
        raise ValueError(f"method must be 'nearest' or 'linear', got {method!r}")
    if max_gap_cells is not None and int(max_gap_cells) < 1:
        raise ValueError(f"max_gap_cells must be >= 1 or None, got {max_gap_cells}")
    out = e.copy()
    valid = ~np.isnan(e)
    if valid.all() or not valid.any():
        return out
    limit = np.inf if max_gap_cells is None else int(max_gap_cells)
    # passes: a hole at the crossing of two unseen strips (a row and a column) is not
    # bracketed by seen cells along either axis, but is once the strips are filled
    footprint = valid.copy()
    for _ in range(_FILL_PASSES):
        if method == "linear":
            filled, new = _fill_linear_pass(out, ~np.isnan(out), limit)
            out = filled
        else:
            new = _bracketed(footprint, limit)
            footprint |= new
        if not new.any():
            break
    if method == "nearest":
        hole = footprint & ~valid
        if hole.any():
            out[hole] = _nearest_symmetric(e, valid)[hole]
    return out


def _nearest_symmetric(e: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Value of the nearest valid cell; equidistant cells averaged (tie-symmetric).

    ``distance_transform_edt`` breaks ties by its scan order, always toward the same
    side, which biases a filled slope (a one-cell gap takes the lower neighbour's value
    every time).  Running it on the four mirror images of the grid and averaging the four
    picks gives the mean of the tied cells (exact for a plane across a symmetric gap).
    """
    nx, ny = e.shape
    acc = np.zeros(e.shape)
    for fx in (False, True):
        for fy in (False, True):
            sl = (slice(None, None, -1 if fx else 1), slice(None, None, -1 if fy else 1))
            _, (ii, jj) = ndimage.distance_transform_edt(~valid[sl], return_indices=True)
            ii, jj = ii[sl], jj[sl]
            if fx:
                ii = nx - 1 - ii
            if fy:
                jj = ny - 1 - jj
            acc += e[ii, jj]
    return acc / 4.0


#: at most this many bracketing passes in :func:`fill_holes`
_FILL_PASSES = 8


def _bracketed(valid: np.ndarray, limit: float) -> np.ndarray:
    """NaN cells bracketed by valid cells along x or y within ``limit`` cells."""
    hole = np.zeros(valid.shape, dtype=bool)
    for axis in (0, 1):
        prev, nxt = _brackets(valid, axis)
        hole |= ~valid & (prev >= 0) & (nxt < valid.shape[axis]) & (nxt - prev - 1 <= limit)
    return hole


def _fill_linear_pass(e: np.ndarray, valid: np.ndarray, limit: float):
    """One pass of axis-wise linear filling; returns (filled copy, newly filled mask)."""
    hx, hy = np.nonzero(~valid)          # work on the unseen cells only
    num = np.zeros(hx.size)
    den = np.zeros(hx.size)
    for axis, pos in ((0, hx), (1, hy)):
        n = e.shape[axis]
        prev, nxt = _brackets(valid, axis)
        p, q = prev[hx, hy], nxt[hx, hy]
        ok = (p >= 0) & (q < n) & (q - p - 1 <= limit)
        if not ok.any():
            continue
        p, q, pos, cx, cy = p[ok], q[ok], pos[ok], hx[ok], hy[ok]
        a, b = (e[p, cy], e[q, cy]) if axis == 0 else (e[cx, p], e[cx, q])
        span = (q - p).astype(np.float64)
        w = 1.0 / (span * span)
        num[ok] += w * (a + (pos - p) / span * (b - a))
        den[ok] += w
    new = np.zeros(e.shape, dtype=bool)
    hit = den > 0
    new[hx[hit], hy[hit]] = True
    out = e.copy()
    out[hx[hit], hy[hit]] = num[hit] / den[hit]
    return out, new


def _shifted(a: np.ndarray, k: int, axis: int, fill) -> np.ndarray:
    """``out[i] = a[i + k]`` along ``axis`` (``fill`` beyond the edge)."""
    out = np.full(a.shape, fill, dtype=a.dtype)
    if k == 0:
        out[...] = a
        return out
    src = [slice(None)] * 2
    dst = [slice(None)] * 2
    if k > 0:
        src[axis], dst[axis] = slice(k, None), slice(None, -k)
    else:
        src[axis], dst[axis] = slice(None, k), slice(-k, None)
    out[tuple(dst)] = a[tuple(src)]
    return out


#: sample pairs (offsets along the axis) tried in order for a cell's slope: central,
#: one-sided over two cells, one-sided over one cell (baselines >= 1, 1, 0 cells)
_PAIRS = ((-1, 1), (0, 2), (-2, 0), (0, 1), (-1, 0))


def _pair_differences(z: np.ndarray, px: np.ndarray, py: np.ndarray, cell_m: float,
                      axis: int, lo: int, hi: int):
    """Height and *measured position* differences between cells ``i + lo`` and ``i + hi``.

    Positions are centre + offset.  Returns ``(dz, dx, dy, ok)`` (m); ``ok`` where both
    samples have data and they are at least half a cell apart along ``axis``.
    """
    valid = ~np.isnan(z)
    zi = np.where(valid, z, 0.0)
    ok = _shifted(valid, lo, axis, False) & _shifted(valid, hi, axis, False)
    dz = _shifted(zi, hi, axis, 0.0) - _shifted(zi, lo, axis, 0.0)
    dx = _shifted(px, hi, axis, 0.0) - _shifted(px, lo, axis, 0.0)
    dy = _shifted(py, hi, axis, 0.0) - _shifted(py, lo, axis, 0.0)
    if axis == 0:
        dx = dx + (hi - lo) * cell_m
        ok &= np.abs(dx) >= 0.5 * cell_m
    else:
        dy = dy + (hi - lo) * cell_m
        ok &= np.abs(dy) >= 0.5 * cell_m
    return dz, dx, dy, ok


def centre_elevation(elevation, x_offset_m, y_offset_m, cell_m: float) -> np.ndarray:
    """Move each cell's height from where it was measured to the cell centre.

    A cell's fused height is the mean height of the points that fell in it, i.e. the
    surface height at their mean position, which is generally not the centre: on a
    slope that is an error of ``slope * offset`` (up to half a cell times the slope).
    With a straight scanner ride the beams hit the same x in every scan, so the offsets
    repeat along y and these errors do not average out in a volume.  This corrects them
    to first order:

        z_centre = z - (dz/dx) * x_offset - (dz/dy) * y_offset

    The slope at a cell comes from its neighbours along x and along y (central
    differences; one-sided next to a NaN or the grid's edge) *at their measured
    positions* (centre + offset): the two height differences and the two position
    differences give a 2 x 2 linear system for (dz/dx, dz/dy), so a plane is corrected
    exactly whatever the offsets.  Seen cells are used where there are any (the two
    neighbours; else the cell and the cell two away; else the cell and a neighbour, if
    at least half a cell apart); else holes filled linearly (taken at their centres); a
    cell with a pair along one axis only gets that axis' slope.

    Parameters
    ----------
    elevation : array_like, shape (nx, ny)
        Heights (m), NaN = never seen.
    x_offset_m, y_offset_m : array_like, shape (nx, ny)
        Where in each cell the height was measured, relative to the centre (m); NaN
        (never seen) counts as 0.
    cell_m : float
        Cell size (m).

    Returns
    -------
    ndarray, shape (nx, ny)
        Heights at the cell centres; NaN where ``elevation`` is NaN.
    """
    e = _check_elevation(elevation)
    ox = np.asarray(x_offset_m, dtype=np.float64)
    oy = np.asarray(y_offset_m, dtype=np.float64)
    if ox.shape != e.shape or oy.shape != e.shape:
        raise ValueError(f"offsets must have the elevation's shape {e.shape}, got "
                         f"{ox.shape} and {oy.shape}")
    if not (math.isfinite(cell_m) and cell_m > 0):
        raise ValueError(f"cell_m must be finite and > 0, got {cell_m}")
    seen = ~np.isnan(e)
    z = fill_holes(e, method="linear")
    px = np.where(seen, np.nan_to_num(ox), 0.0)
    py = np.where(seen, np.nan_to_num(oy), 0.0)
    # per axis, the first pair available of: the two seen neighbours; the cell and the
    # seen cell two away; the cell and a seen neighbour; then the same on the hole-filled
    # map (a filled hole sits at its centre).  Pairs closer than half a cell (offsets can
    # shrink a one-cell baseline to nothing) are skipped.
    pairs = []
    for axis in (0, 1):
        chosen = None
        for cand_z, (lo, hi) in [(m, pair) for m in (e, z) for pair in _PAIRS]:
            cand = _pair_differences(cand_z, px, py, cell_m, axis, lo, hi)
            if chosen is None:
                chosen = list(cand)
            else:
                use = ~chosen[3] & cand[3]
                chosen = [np.where(use, b, a) for a, b in zip(chosen[:3], cand[:3])] \
                    + [chosen[3] | cand[3]]
        pairs.append(chosen)
    (dz1, dx1, dy1, ok1), (dz2, dx2, dy2, ok2) = pairs
    gx = np.zeros(e.shape)
    gy = np.zeros(e.shape)
    with np.errstate(invalid="ignore", divide="ignore"):
        det = dx1 * dy2 - dy1 * dx2
        both = ok1 & ok2 & (np.abs(det) > 1e-9 * cell_m * cell_m)
        gx = np.where(both, (dz1 * dy2 - dy1 * dz2) / det, gx)
        gy = np.where(both, (dx1 * dz2 - dz1 * dx2) / det, gy)
        only_x = ok1 & ~both & (np.abs(dx1) > 1e-9 * cell_m)
        only_y = ok2 & ~both & ~only_x & (np.abs(dy2) > 1e-9 * cell_m)
        gx = np.where(only_x, dz1 / dx1, gx)
        gy = np.where(only_y, dz2 / dy2, gy)
    return e - gx * px - gy * py


def volume_above(elevation, ground_z_m: float, cell_area_m2: float, *, fill: str = "nearest",
                 max_gap_cells: int | None = None, clip_below: bool = False) -> float:
    """Volume (m^3) of material above the ground level.

    ``sum over cells of (elevation - ground_z_m) * cell_area_m2`` after
    :func:`fill_holes`; never-seen cells outside the data's footprint count as ground
    (they add nothing).

    Parameters
    ----------
    elevation : array_like, shape (nx, ny)
        Heights (m), NaN = never seen.
    ground_z_m : float
        The declared ground level (m).
    cell_area_m2 : float
        Area of one cell (m^2), > 0.
    fill : {"nearest", "linear", "none"}
        How holes inside the footprint are filled (see :func:`fill_holes`); ``"none"``
        counts them as ground, which under-estimates.
    max_gap_cells : int or None
        See :func:`fill_holes`.
    clip_below : bool
        Count cells below the ground as zero instead of negative.  Off by default: with
        noisy heights on bare ground clipping keeps the positive half of the noise and
        biases the volume up (by about ``sd / sqrt(2 pi)`` per ground cell); the signed
        sum is unbiased.

    Returns
    -------
    float
        Volume in m^3.
    """
    e = _check_elevation(elevation)
    if not (math.isfinite(ground_z_m)):
        raise ValueError("ground_z_m must be finite")
    if not (math.isfinite(cell_area_m2) and cell_area_m2 > 0):
        raise ValueError(f"cell_area_m2 must be finite and > 0, got {cell_area_m2}")
    if fill not in ("nearest", "linear", "none"):
        raise ValueError(f"fill must be 'nearest', 'linear' or 'none', got {fill!r}")
    if fill != "none":
        e = fill_holes(e, method=fill, max_gap_cells=max_gap_cells)
    h = e - ground_z_m
    if clip_below:
        h = np.maximum(h, 0.0)
    return float(np.nansum(h) * cell_area_m2)
