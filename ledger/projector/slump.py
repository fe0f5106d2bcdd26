"""The angle of repose: what a granular pile's surface can and cannot be.

Dry ore fines hold no slope steeper than their angle of repose (iron-ore fines about
35-38 deg, DOMAIN.md §4).  The fold uses two consequences of that:

- **slump**: the face a reclaim cut leaves is steeper than repose; it slides until no
  slope exceeds it.  Material moves from the top of the face to its toe, mass conserved,
  its composition moving with it (:func:`relax_surface`, :func:`slump`);
- **the repose cone**: no point of a settled pile lies below ``z(q) - tan(repose) |p - q|``
  for any surface point ``q``.  A flank the scanner cannot see (the far side of the crest
  from a machine on one rail) is at least that high (:func:`repose_floor`).

The angle is estimated from the surface the scanner does see
(:func:`estimate_repose_deg`): the mode of the slopes between 25 and 50 deg, where the
flanks of a stacked pile pile up.

All functions are pure: numpy arrays in, numpy arrays out.  Arrays are ``(nx, ny)``
indexed ``[ix, iy]`` (:mod:`ledger.projector.grid`); heights in metres.
"""

from __future__ import annotations

import math

import numpy as np

from ledger.projector.layers import LayerStack, Removal

__all__ = ["estimate_repose_deg", "repose_floor", "relax_surface", "slump"]

_SQRT2 = math.sqrt(2.0)
# neighbour pairs: (slice of a, slice of b, distance in cells); b is a's neighbour
_PAIRS = (
    ((slice(1, None), slice(None)), (slice(None, -1), slice(None)), 1.0),
    ((slice(None), slice(1, None)), (slice(None), slice(None, -1)), 1.0),
    ((slice(1, None), slice(1, None)), (slice(None, -1), slice(None, -1)), _SQRT2),
    ((slice(1, None), slice(None, -1)), (slice(None, -1), slice(1, None)), _SQRT2),
)


def _check_2d(name: str, a) -> np.ndarray:
    arr = np.asarray(a, dtype=np.float64)
    if arr.ndim != 2:
        raise ValueError(f"{name} must be a 2-D (nx, ny) array, got shape {arr.shape}")
    return arr


def _check_tan(tan_repose: float) -> float:
    if not (math.isfinite(tan_repose) and tan_repose > 0):
        raise ValueError(f"tan_repose must be finite and > 0, got {tan_repose!r}")
    return float(tan_repose)


def estimate_repose_deg(elevation_m, cell_m: float, *, baseline_cells: int = 4,
                        lo_deg: float = 25.0, hi_deg: float = 50.0, bin_deg: float = 0.5,
                        min_cells: int = 200) -> float:
    """The angle of repose seen on a surface: the mode of its steep slopes (deg).

    Slopes are central differences over ``2 * baseline_cells`` cells (a long baseline
    keeps the height noise out of the slope); the mode of those between ``lo_deg`` and
    ``hi_deg`` is refined by the mean of the slopes within 1.5 deg of it.

    Parameters
    ----------
    elevation_m : array_like, shape (nx, ny)
        Heights (m), NaN = not seen.
    cell_m : float
        Cell edge (m).

    Returns
    -------
    float
        The angle (deg), or NaN when fewer than ``min_cells`` slopes fall in the window.
    """
    e = _check_2d("elevation_m", elevation_m)
    if not cell_m > 0:
        raise ValueError(f"cell_m must be > 0, got {cell_m!r}")
    b = int(baseline_cells)
    if b < 1 or e.shape[0] <= 2 * b or e.shape[1] <= 2 * b:
        return math.nan
    run = 2 * b * cell_m
    gx = (e[2 * b:, b:-b] - e[:-2 * b, b:-b]) / run
    gy = (e[b:-b, 2 * b:] - e[b:-b, :-2 * b]) / run
    with np.errstate(invalid="ignore"):
        slope = np.degrees(np.arctan(np.hypot(gx, gy)))
        slope = slope[np.isfinite(slope) & (slope >= lo_deg) & (slope <= hi_deg)]
    if slope.size < min_cells:
        return math.nan
    counts, edges = np.histogram(slope, bins=np.arange(lo_deg, hi_deg + bin_deg, bin_deg))
    mode = 0.5 * (edges[counts.argmax()] + edges[counts.argmax() + 1])
    near = slope[np.abs(slope - mode) <= 1.5]
    return float(near.mean())


def repose_floor(elevation_m, cell_m: float, tan_repose: float) -> np.ndarray:
    """The lowest surface a settled pile through these heights can have.

    ``floor(p) = max_q (z(q) - tan_repose * d(p, q))`` over the seen cells q, with d the
    8-neighbour chamfer distance ``max(|dx|, |dy|) + (sqrt 2 - 1) min(|dx|, |dy|)`` (exact
    along the axes and the diagonals, at most 8 % longer in between, so the floor is never
    above the Euclidean cone's).

    The chamfer ball is the octagon spanned by the axis and diagonal steps, so the cone
    is four one-dimensional cones in a row (along x, y and both diagonals), each a running
    maximum: ``z'(j) = max_{i <= j} (z(i) + k i) - k j`` both ways.

    Parameters
    ----------
    elevation_m : array_like, shape (nx, ny)
        Heights (m), NaN = not seen.
    cell_m : float
        Cell edge (m).
    tan_repose : float
        Tangent of the angle of repose (> 0).

    Returns
    -------
    ndarray, shape (nx, ny)
        The floor (m), >= the elevation where seen; NaN where nothing is seen.
    """
    e = _check_2d("elevation_m", elevation_m)
    k = _check_tan(tan_repose) * float(cell_m)
    z = np.where(np.isfinite(e), e, -np.inf)
    if not np.isfinite(z).any():
        return np.full(e.shape, np.nan)
    z = _cone_1d(z, k, axis=0)
    z = _cone_1d(z, k, axis=1)
    for sign in (1, -1):
        z = _unshear(_cone_1d(_shear(z, sign), k * _SQRT2, axis=0), sign, e.shape)
    return np.where(np.isfinite(z), z, np.nan)


def _cone_1d(z: np.ndarray, k: float, axis: int) -> np.ndarray:
    """``max_i (z(i) - k |i - j|)`` along one axis (running maxima both ways)."""
    n = z.shape[axis]
    ramp = k * np.arange(n, dtype=np.float64)
    ramp = ramp[:, None] if axis == 0 else ramp[None, :]
    with np.errstate(invalid="ignore"):
        forward = np.maximum.accumulate(z + ramp, axis=axis) - ramp
        rev = ramp[::-1] if axis == 0 else ramp[:, ::-1]
        backward = np.flip(np.maximum.accumulate(np.flip(z + rev, axis=axis), axis=axis),
                           axis=axis) - rev
    return np.maximum(forward, backward)


def _shear(z: np.ndarray, sign: int) -> np.ndarray:
    """Rows shifted so each diagonal (sign 1: ix - iy const ... ) becomes a column."""
    nx, ny = z.shape
    out = np.full((nx, nx + ny - 1), -np.inf)
    for ix in range(nx):
        start = (nx - 1 - ix) if sign == 1 else ix
        out[ix, start:start + ny] = z[ix]
    return out


def _unshear(sheared: np.ndarray, sign: int, shape: tuple[int, int]) -> np.ndarray:
    nx, ny = shape
    out = np.empty(shape)
    for ix in range(nx):
        start = (nx - 1 - ix) if sign == 1 else ix
        out[ix] = sheared[ix, start:start + ny]
    return out


def relax_surface(top_m, base_m, cell_m: float, tan_repose: float, *, rate: float = 0.25,
                  tol_m: float = 1e-4, max_iter: int = 20000) -> np.ndarray:
    """Let a surface slide until no slope between neighbours exceeds the repose angle.

    Material moves between neighbouring columns (the 4 axis and 4 diagonal neighbours),
    from the higher to the lower, by ``rate`` times the height above the repose slope
    per sweep, never below ``base_m``: the total volume is conserved exactly.

    Parameters
    ----------
    top_m, base_m : array_like, shape (nx, ny)
        Surface and the level below which nothing moves (the ground) (m, finite).
    cell_m : float
        Cell edge (m).
    tan_repose : float
        Tangent of the steepest slope left standing (> 0).
    rate : float
        Share of the excess moved per sweep (0 < rate <= 0.25 keeps the sweeps stable).
    tol_m : float
        Stop when no sweep moves more than this (m).
    max_iter : int
        At most this many sweeps.

    Returns
    -------
    ndarray, shape (nx, ny)
        The relaxed surface (m): same volume above ``base_m``.
    """
    h = _check_2d("top_m", top_m).copy()
    base = _check_2d("base_m", base_m)
    if h.shape != base.shape:
        raise ValueError(f"base_m must have the shape of top_m {h.shape}, got {base.shape}")
    if not (np.all(np.isfinite(h)) and np.all(np.isfinite(base))):
        raise ValueError("top_m and base_m must be finite")
    if not 0 < rate <= 0.25:
        raise ValueError(f"rate must be in (0, 0.25], got {rate!r}")
    k = _check_tan(tan_repose) * float(cell_m)
    for _ in range(int(max_iter)):
        largest = 0.0
        for a, b, d in _PAIRS:
            diff = h[a] - h[b]
            move = rate * (np.abs(diff) - k * d)
            np.maximum(move, 0.0, out=move)
            if not move.any():
                continue
            # positive flow: a -> b; limited to half of what lies above the source's base
            flow = np.where(diff > 0, np.minimum(move, 0.5 * (h[a] - base[a])),
                            -np.minimum(move, 0.5 * (h[b] - base[b])))
            h[a] -= flow
            h[b] += flow
            largest = max(largest, float(np.abs(flow).max()))
        if largest < tol_m:
            break
    return h


def slump(stack: LayerStack, tan_repose: float, region: tuple[slice, slice] | None = None,
          **relax) -> tuple[LayerStack, Removal, np.ndarray]:
    """Relax a layer stack's over-steep faces, moving the slid material's composition.

    The top surface is relaxed (:func:`relax_surface`) inside ``region``; the stack is
    clamped to it where it fell (what slid, per deposit) and the slid material is laid
    on the cells that rose, each deposit in proportion to its share of what slid, at
    that share's mean deposition time (:meth:`LayerStack.add_material`).

    Parameters
    ----------
    stack : LayerStack
    tan_repose : float
        Tangent of the angle of repose.
    region : (slice, slice), optional
        The block of cells allowed to move (default: all).
    **relax
        Passed to :func:`relax_surface`.

    Returns
    -------
    stack : LayerStack
        The settled stack (same volume, to rounding).
    moved : Removal
        What slid, per deposit (its volume is the volume moved, m3).
    raised_m : ndarray, shape (nx, ny)
        Thickness laid on each cell (m).
    """
    region = region or (slice(None), slice(None))
    top = stack.surface()
    new_top = top.copy()
    new_top[region] = relax_surface(top[region], stack.ground()[region],
                                    stack.geometry.cell_m, tan_repose, **relax)
    with np.errstate(invalid="ignore"):
        fell = new_top < top
    settled, moved = stack.clamp(np.where(fell, new_top, np.inf))
    raised = np.where(new_top > top, new_top - top, 0.0)
    total = moved.volume_m3
    if total <= 0 or not raised.any():
        return settled, moved, raised
    for part in moved.deposits:
        settled = settled.add_material(part.index, raised * (part.volume_m3 / total),
                                       part.mean_deposition_time_ns)
    return settled, moved, raised
