"""Kernels on a fused elevation layer: holes, heights at cell centres, volume.

A height map's ``elevation`` (:mod:`projector.heightmap`) is an ``(nx, ny)`` layer of
heights in metres, NaN where a cell was never seen.  This module reads such a layer:

- :func:`fill_holes` fills the never-seen cells inside the data's footprint (nearest
  seen cell, or linear along the bracketing axis), leaving the margin outside it NaN;
- :func:`centre_elevation` moves each cell's height from where in the cell it was
  measured to the cell's centre (first-order slope correction);
- :func:`volume_above` integrates the filled layer above a ground level (m^3).

Pure functions on numpy arrays, no I/O.  Units: metres, m^2, m^3.  Layers are ``float64
(nx, ny)`` arrays indexed ``[ix, iy]`` as in :mod:`projector.grid`.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage

from projector.grid import check_elevation

__all__ = ["fill_holes", "centre_elevation", "volume_above"]


# --------------------------------------------------------------------------------------
# Holes
# --------------------------------------------------------------------------------------

#: at most this many bracketing passes in :func:`fill_holes`
_FILL_PASSES = 8


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
    e = check_elevation(elevation)
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



# --------------------------------------------------------------------------------------
# Heights at cell centres
# --------------------------------------------------------------------------------------

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
    e = check_elevation(elevation)
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



# --------------------------------------------------------------------------------------
# Volume
# --------------------------------------------------------------------------------------

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
    e = check_elevation(elevation)
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
