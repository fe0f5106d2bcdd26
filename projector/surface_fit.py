"""Local least-squares surface fits over a square window of cells.

A surface estimated per cell carries each cell's own noise; these kernels replace a cell's
value by the value at the window's centre of a low-order surface fitted to the cells
around it:

- :func:`plane_fit_of_seen`: the plane through the seen (non-NaN) cells of the window,
  for a fused elevation (:mod:`projector.heightmap`);
- :func:`fit_local_quadratic`: the quadratic through the masked cells of the window, for
  the surfaces of a layer stack (:meth:`projector.layers.LayerStack.fit_boundaries`);
- :func:`fit_top_above_floor`: that fit of a stack's top where a cut down to a floor
  measures it (:meth:`projector.layers.LayerStack.fit_top_above`).

Pure functions on ``float64 (nx, ny)`` arrays indexed ``[ix, iy]`` (:mod:`projector.grid`);
heights in metres, windows in cells.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage

from projector.grid import check_elevation

__all__ = ["plane_fit_of_seen", "fit_local_quadratic", "fit_top_above_floor", "check_window"]


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
    e = check_elevation(elevation)
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


def _quadratic_basis(window: int) -> np.ndarray:
    """The terms ``1, dx, dy, dx^2, dx dy, dy^2`` at each offset of a square window,
    shape (window * window, 6), offsets in cells, row-major over (dx, dy)."""
    half = window // 2
    dx, dy = np.meshgrid(np.arange(-half, half + 1, dtype=np.float64),
                         np.arange(-half, half + 1, dtype=np.float64), indexing="ij")
    dx, dy = dx.ravel(), dy.ravel()
    return np.stack([np.ones_like(dx), dx, dy, dx * dx, dx * dy, dy * dy], axis=1)


def check_window(window) -> None:
    """ValueError unless ``window`` (cells) is an odd int >= 3."""
    if isinstance(window, bool) or not isinstance(window, (int, np.integer)) \
            or window < 3 or window % 2 == 0:
        raise ValueError(f"window must be an odd int >= 3, got {window!r}")


def fit_local_quadratic(z_m, mask, window: int = 7) -> np.ndarray:
    """Each masked cell's value on the least-squares quadratic surface through the masked
    cells of the ``window`` x ``window`` square around it.

    A surface estimated per cell carries each cell's own noise.  The fit takes it down
    (the standard deviation times 0.39, 0.27 and 0.21 for full 5, 7 and 9 cell windows)
    and, unlike a mean, returns any surface that is quadratic over the window unchanged:
    a plane, a rounded crest, a toe, also where the mask cuts the window short.

    Parameters
    ----------
    z_m : array_like, shape (nx, ny)
        The surface (m).
    mask : array_like of bool, shape (nx, ny)
        The cells to fit and to fit from (NaN cells never count).
    window : int
        The square's edge in cells: odd, >= 3.

    Returns
    -------
    ndarray, shape (nx, ny), float64
        The fit on the masked cells.  Elsewhere ``z_m``; also where a window's masked cells
        do not determine a quadratic (fewer than six, or all on two lines).

    Raises
    ------
    ValueError
        On shapes that differ or are not 2-D, or a window that is even or below 3.
    """
    z = np.asarray(z_m, dtype=np.float64)
    m = np.asarray(mask, dtype=bool)
    if z.ndim != 2 or m.shape != z.shape:
        raise ValueError(f"z_m and mask must be 2-D of one shape, got {z.shape} and {m.shape}")
    check_window(window)
    m = m & np.isfinite(z)
    out = z.copy()
    if not m.any():
        return out
    window, half = int(window), int(window) // 2
    basis = _quadratic_basis(window)
    # a full window: one fixed kernel, the least-squares weights of the centre value
    # (Savitzky-Golay)
    centre = np.linalg.pinv(basis)[0].reshape(window, window)
    zm = np.where(m, z, 0.0)
    counts = ndimage.correlate(m.astype(np.float64), np.ones((window, window)), mode="constant")
    full = m & (counts > window * window - 0.5)
    out[full] = ndimage.correlate(zm, centre, mode="constant")[full]
    # a window the mask cuts short: its own least squares, from the cells it holds
    part = np.flatnonzero(m & ~full)
    if part.size:
        ny = z.shape[1]
        zp, mp = np.pad(zm, half), np.pad(m, half)
        ix, iy = np.unravel_index(part, z.shape)
        offsets = (np.arange(window)[:, None] * (ny + 2 * half)
                   + np.arange(window)[None, :]).ravel()
        flat = (ix * (ny + 2 * half) + iy)[:, None] + offsets[None, :]   # window's top-left
        w = mp.ravel()[flat].astype(np.float64)                           # (p, window^2)
        products = (basis[:, :, None] * basis[:, None, :]).reshape(len(basis), 36)
        a = (w @ products).reshape(-1, 6, 6)                      # the normal equations
        b = (w * zp.ravel()[flat]) @ basis
        # singular where the cells do not determine a quadratic: the determinant against
        # the product of the diagonal (1 for orthogonal terms, 0 for dependent ones)
        sign, logdet = np.linalg.slogdet(a)
        diagonal = np.einsum("pii->pi", a)
        with np.errstate(divide="ignore", invalid="ignore"):
            ok = (sign > 0) & (logdet - np.sum(np.log(diagonal), axis=1) > math.log(1e-10))
        if ok.any():
            sol = np.linalg.solve(a[ok], b[ok][..., None])[..., 0]
            out.ravel()[part[ok]] = sol[:, 0]
    return out


def fit_top_above_floor(lower_m, top_m, floor_m, window: int = 7) -> np.ndarray | None:
    """The top surface of a band, where it or its fit stands above a floor, replaced by
    :func:`fit_local_quadratic` over the band's cells.

    The band is ``(lower_m, top_m]``; where it holds material, the floor is finite and
    the top or its fit stands above the floor, the top becomes the fit, kept at or above
    both the floor and ``lower_m``.  Only the floor's bounding box, padded by half a
    window, is fitted: the fit at a cell sees the window around it, so there it gives the
    values the whole grid would.

    Parameters
    ----------
    lower_m, top_m : array_like, shape (nx, ny)
        The band's bottom and top (m), ``lower_m <= top_m``.
    floor_m : array_like, shape (nx, ny)
        The floor (m), NaN outside the cut.
    window : int
        The fit's square, in cells (odd, >= 3).

    Returns
    -------
    ndarray, shape (nx, ny), or None
        A new top (m); None when no cell changes.

    Raises
    ------
    ValueError
        On arrays of different shapes or not 2-D, or a bad window.
    """
    lower = np.asarray(lower_m, dtype=np.float64)
    top = np.asarray(top_m, dtype=np.float64)
    floor = np.asarray(floor_m, dtype=np.float64)
    if top.ndim != 2 or lower.shape != top.shape or floor.shape != top.shape:
        raise ValueError(f"lower_m, top_m and floor_m must be 2-D of one shape, got "
                         f"{lower.shape}, {top.shape} and {floor.shape}")
    check_window(window)
    ix, iy = np.nonzero(np.isfinite(floor))
    if ix.size == 0:
        return None
    pad = window // 2
    block = (slice(max(0, ix.min() - pad), ix.max() + pad + 1),
             slice(max(0, iy.min() - pad), iy.max() + pad + 1))
    lo, z, f = lower[block], top[block], floor[block]
    mask = z > lo
    if not mask.any():
        return None
    fitted = fit_local_quadratic(z, mask, window)
    with np.errstate(invalid="ignore"):
        near = mask & np.isfinite(f) & ((z > f) | (fitted > f))
    if not near.any():
        return None
    out = np.array(top)
    out[block] = np.where(near, np.maximum(np.fmax(fitted, f), lo), z)
    return out
