"""The angle of repose: what a granular pile's surface can and cannot be.

Dry ore fines hold no slope steeper than their angle of repose (iron-ore fines about
35-38 deg, docs/domain.md §4).  The fold uses three consequences of that:

- **slump**: the face a reclaim cut leaves is steeper than repose; it slides until no
  slope exceeds it.  Material moves from the top of the face to its toe, mass conserved,
  its composition moving with it (:func:`relax_surface`, :func:`slump`);
- **the repose cone**: no point of a settled pile lies below ``z(q) - tan(repose) |p - q|``
  for any surface point ``q``.  A flank the scanner cannot see (the far side of the crest
  from a machine on one rail) is at least that high (:func:`repose_floor`);
- **the pouring front**: ore poured from a moving boom settles as a repose cone around
  the discharge point, so a cell gets its layer while the cone's front sweeps over it,
  before the boom is above it (:func:`pour_front_lead_m`).

The angle is estimated from the surface the scanner does see
(:func:`estimate_repose_deg`): the mode of the slopes between 25 and 50 deg, where the
flanks of a stacked pile pile up.

All functions are pure: numpy arrays in, numpy arrays out.  Arrays are ``(nx, ny)``
indexed ``[ix, iy]`` (:mod:`projector.grid`); heights in metres.
"""

from __future__ import annotations

import math

import numpy as np

from projector.layers import LayerStack, Removal

__all__ = ["estimate_repose_deg", "pour_front_lead_m", "pour_end_lead_m", "pour_reach_m",
           "repose_floor",
           "relax_surface", "slump"]

_SQRT2 = math.sqrt(2.0)
# the 8 neighbours of a column, (dx, dy) in cells
_NEIGHBOURS = ((-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1))


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


def pour_front_lead_m(thickness_m, offset_m, tan_repose: float) -> np.ndarray:
    """How far ahead of a moving boom a cell's layer is laid, on average (m).

    A boom pouring along a line settles its ore as a repose cone around the discharge
    point: the surface reaches ``a - tan_repose * r`` at distance r from it, a the apex.
    At a cell ``offset_m`` from the line (across it) that ends with ``thickness_m`` of new
    material, the cone's front arrives when the boom is still
    ``D = sqrt(h^2 + 2 h |offset|)`` away along the line (``h = thickness / tan_repose``),
    and the cell fills as the boom closes in: with ``f(s) = tan_repose sqrt(offset^2 +
    s^2)`` its level when the boom is s away, the thickness-weighted mean of s is
    ``(D f(D) - int_0^D f) / (f(D) - f(0))``; D / 2 on the line itself.  Once the boom has
    passed, the cell is already at the cone's level and, in a steady flow, gets nothing
    more (where the flow varies it does, for as far again: :func:`pour_reach_m`).

    Parameters
    ----------
    thickness_m, offset_m, tan_repose
        As for :func:`pour_reach_m` (NaN or <= 0 thickness: no lead).

    Returns
    -------
    ndarray, shape (nx, ny)
        The thickness-weighted mean distance (m, >= 0) between the boom and the cell
        while the cell's layer was laid; divided by the boom's speed it is a time.
    """
    x = np.abs(_check_2d("offset_m", offset_m))
    reach = pour_reach_m(thickness_m, x, tan_repose)       # D
    r = np.hypot(x, reach)                                 # sqrt(offset^2 + D^2)
    with np.errstate(invalid="ignore", divide="ignore"):
        u = np.where(x > 0, reach / np.where(x > 0, x, 1.0), np.inf)
        # (D f(D) - int_0^D f) / tan = (D r - x^2 asinh(D / x)) / 2, over
        # (f(D) - f(0)) / tan = r - x = D^2 / (r + x) (no cancellation)
        closed = (0.5 * (reach * r - np.where(x > 0, x * x * np.arcsinh(u), 0.0))
                  * (r + x) / (reach * reach))
        # far down a flank under a thin layer (D << x) the closed form cancels; its
        # series there, x u (1/3 - u^2/10) (sqrt(1 + u^2) + 1), is exact to O(u^4)
        series = reach * (1.0 / 3.0 - u * u / 10.0) * (np.sqrt(1.0 + u * u) + 1.0)
        lead = np.where(u < 1e-2, series, closed)
    return np.where(reach > 0, lead, 0.0)


def pour_end_lead_m(thickness_m, offset_m, beyond_m, tan_repose: float) -> np.ndarray:
    """How far before the end of its run a boom laid a cell's layer, on average (m), for a
    cell ``beyond_m`` past the run's end along its line.

    The boom stops ``e = beyond_m`` short of the cell (along the line), so the cell fills
    only while the boom closes in from the front's arrival ``D`` to ``e``: the cone
    stands ``h + sqrt(offset^2 + e^2) tan_repose`` above the layer below on the line
    (``h = thickness / tan_repose``) so that the cell ends ``thickness_m`` higher, its
    front arrives ``D = sqrt((h + sqrt(offset^2 + e^2))^2 - offset^2)`` away, and the
    thickness-weighted mean distance is ``[(s r - offset^2 asinh(s / offset)) / 2]_e^D
    / (r(D) - r(e))`` with ``r(s) = sqrt(offset^2 + s^2)``.  Returned: that mean less
    ``e``, the boom's travel still to go (divided by its speed, how long before the end
    of the pass).  At ``e = 0`` it is :func:`pour_front_lead_m`.

    Parameters
    ----------
    thickness_m, offset_m, tan_repose
        As for :func:`pour_reach_m` (NaN or <= 0 thickness: no lead).
    beyond_m : array_like, shape (nx, ny)
        How far past the end of the run each cell lies along the line (m, >= 0).

    Returns
    -------
    ndarray, shape (nx, ny)
        The mean travel left (m, >= 0) while the cell's layer was laid.
    """
    t = _check_2d("thickness_m", thickness_m)
    x = np.abs(_check_2d("offset_m", offset_m))
    e = _check_2d("beyond_m", beyond_m)
    if not (t.shape == x.shape == e.shape):
        raise ValueError(f"thickness_m {t.shape}, offset_m {x.shape} and beyond_m {e.shape} "
                         "differ in shape")
    if np.any(e < 0):
        raise ValueError("beyond_m must be >= 0")
    h = np.where(np.isfinite(t) & (t > 0), t, 0.0) / _check_tan(tan_repose)
    r_e = np.hypot(x, e)
    reach = np.sqrt(np.maximum((h + r_e) ** 2 - x * x, 0.0))          # D >= e
    r_d = r_e + h
    with np.errstate(invalid="ignore", divide="ignore"):
        def moment(s, r):       # int s^2 / r ds = (s r - x^2 asinh(s / x)) / 2
            return 0.5 * (s * r - np.where(x > 0, x * x * np.arcsinh(
                s / np.where(x > 0, x, 1.0)), 0.0))
        mean = (moment(reach, r_d) - moment(e, r_e)) / h     # r(D) - r(e) = h
        # a layer too thin for the difference to hold its digits: the cell fills evenly
        # over the boom's last stretch
        thin = h < 1e-9 * np.maximum(1.0, reach)
        mean = np.where(thin, 0.5 * (reach + e), mean)
    lead = np.clip(mean - e, 0.0, None)
    lead = np.where(e > 0, lead, pour_front_lead_m(t, x, tan_repose))
    return np.where(h > 0, lead, 0.0)


def pour_reach_m(thickness_m, offset_m, tan_repose: float) -> np.ndarray:
    """How far along its line a moving boom's cone reaches a cell: ``D = sqrt(h^2 + 2 h
    |offset|)`` with ``h = thickness / tan_repose`` (m).

    The cone poured on the line stands ``h`` above the layer below at the discharge
    point and meets it where ``tan_repose (sqrt(offset^2 + s^2) - |offset|) = thickness``,
    the boom ``s = D`` away: a cell beside the line gets material while the boom is
    within ``D`` of it, ahead of it (:func:`pour_front_lead_m`) and, where the flow
    varies, after it has passed.  Far down a flank (large offset) the reach is long.

    Parameters
    ----------
    thickness_m : array_like, shape (nx, ny)
        The layer's thickness (m, >= 0; NaN or <= 0: no reach).
    offset_m : array_like, shape (nx, ny)
        Distance from the boom's line, across it (m; the sign is ignored).
    tan_repose : float
        Tangent of the angle of repose (> 0).

    Returns
    -------
    ndarray, shape (nx, ny)
        The reach (m, >= 0).
    """
    t = _check_2d("thickness_m", thickness_m)
    x = np.abs(_check_2d("offset_m", offset_m))
    if t.shape != x.shape:
        raise ValueError(f"thickness_m {t.shape} and offset_m {x.shape} differ in shape")
    h = np.where(np.isfinite(t) & (t > 0), t, 0.0) / _check_tan(tan_repose)
    return np.sqrt(h * h + 2.0 * h * x)


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


def relax_surface(top_m, base_m, cell_m: float, tan_repose: float, *,
                  tol_m: float | None = None, max_iter: int = 100_000) -> np.ndarray:
    """Let a surface slide until no column is steeper than the repose angle.

    The avalanche relaxation of a critical-slope sandpile: in every sweep each column
    whose drop to one of its 8 neighbours exceeds ``tan_repose`` x distance by more than
    ``tol_m`` sends half of its largest excess (never more than it holds above
    ``base_m``) to its lower neighbours, split in proportion to their excess.  All columns
    send at once (Jacobi); nothing crosses the edge of the array, so the volume above
    ``base_m`` is conserved exactly.  Sweeps after the first work on the block of columns
    that sent in the sweep before, grown by one cell: nothing else can have become
    unstable.  (The simulator's ``World._relax`` follows the same physical rule in its own
    code on purpose: it is the ground truth the projector is measured against.)

    Parameters
    ----------
    top_m, base_m : array_like, shape (nx, ny)
        Surface and the level below which nothing moves (the ground) (m, finite).
    cell_m : float
        Cell edge (m).
    tan_repose : float
        Tangent of the steepest slope left standing (> 0).
    tol_m : float, optional
        Drop (m) beyond the repose slope that is left standing; default a hundredth of
        the repose drop across one cell, ``0.01 * tan_repose * cell_m``.
    max_iter : int
        At most this many sweeps.

    Returns
    -------
    ndarray, shape (nx, ny)
        The relaxed surface (m): same volume above ``base_m``; no drop to a neighbour
        exceeds ``tan_repose`` x distance by more than ``tol_m`` where material is left
        to move (after ``max_iter`` sweeps, possibly less settled).
    """
    top = _check_2d("top_m", top_m)
    base = _check_2d("base_m", base_m)
    if top.shape != base.shape:
        raise ValueError(f"base_m must have the shape of top_m {top.shape}, got {base.shape}")
    if not (np.all(np.isfinite(top)) and np.all(np.isfinite(base))):
        raise ValueError("top_m and base_m must be finite")
    k = _check_tan(tan_repose) * float(cell_m)
    tol = 0.01 * k if tol_m is None else float(tol_m)
    if not (math.isfinite(tol) and tol >= 0):
        raise ValueError(f"tol_m must be finite and >= 0, got {tol_m!r}")
    nx, ny = top.shape
    # a ring of walls (+inf) round the surface: no drop toward it, nothing leaves
    h = np.full((nx + 2, ny + 2), np.inf)
    h[1:-1, 1:-1] = top
    critical = [k * math.hypot(dx, dy) for dx, dy in _NEIGHBOURS]
    r0, r1, c0, c1 = 1, nx + 1, 1, ny + 1      # the block swept (padded indices)
    with np.errstate(invalid="ignore"):
        for _ in range(int(max_iter)):
            if r1 <= r0 or c1 <= c0:
                break
            block = h[r0 - 1:r1 + 1, c0 - 1:c1 + 1]
            centre = block[1:-1, 1:-1]            # a view: the sweep updates h itself
            rows, cols = r1 - r0, c1 - c0
            excess = []
            for (dx, dy), drop in zip(_NEIGHBOURS, critical):
                e = centre - block[1 + dx:1 + dx + rows, 1 + dy:1 + dy + cols]
                e -= drop
                np.maximum(e, 0.0, out=e)        # -inf toward a wall -> 0
                excess.append(e)
            largest = np.maximum.reduce(excess)
            mobile = centre - base[r0 - 1:r1 - 1, c0 - 1:c1 - 1]
            send = (largest > tol) & (mobile > 0)
            if not send.any():
                break
            out = np.minimum(mobile, 0.5 * largest)
            out *= send
            share = np.zeros_like(out)
            np.divide(out, np.add.reduce(excess), out=share, where=send)
            centre -= out
            for (dx, dy), e in zip(_NEIGHBOURS, excess):
                e *= share
                h[r0 + dx:r1 + dx, c0 + dy:c1 + dy] += e
            sx = np.flatnonzero(send.any(axis=1))
            sy = np.flatnonzero(send.any(axis=0))
            r0, r1 = max(1, r0 + int(sx[0]) - 1), min(nx + 1, r0 + int(sx[-1]) + 2)
            c0, c1 = max(1, c0 + int(sy[0]) - 1), min(ny + 1, c0 + int(sy[-1]) + 2)
    return h[1:-1, 1:-1].copy()


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
