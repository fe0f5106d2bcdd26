"""Where released material comes to rest: the simulator's two deposition models.

Material leaves the stacker boom at a point, or along the short segment the stacker
travels during one release step, and comes to rest on the current surface with no slope
steeper than the angle of repose. Only the newly released material moves (the base is
stable), so it all belongs to the current deposit.

``"quasistatic"`` (:func:`quasistatic_release`, the default)
    The quasi-static limit of the critical-slope (BCRE / Prigozhin) sandpile model: a
    release of volume V along a source segment S settles as
    ``u = max(b, a - tan(repose) * dist(x, S))`` restricted to the part connected to the
    source, where b is the surface before the release and the apex level a is solved
    exactly (sorted cumulative sums, :func:`solve_fill_level`) so that the added volume is
    V to rounding. This is the state the avalanche relaxation converges to as its
    tolerance goes to zero (material flows down repose-angle flanks and rests where the
    slope is subcritical), with an isotropic (Euclidean) slope limit, at a fraction of its
    cost (timings in docs/design-notes.md). Piles are still emergent: the surface is the
    result of thousands of releases on the evolving surface.
``"avalanche"`` (:func:`avalanche_release`)
    The released volume is put on the drop cells, then :func:`sim.relaxation.relax` moves
    it downslope until no column is steeper than the tolerance. Exactly volume conserving.
    On a pile whose flanks are already at repose a thin veneer spreads *diffusively*
    (hundreds to thousands of sweeps per release), so this mode is meant for small grids
    and for cross-checking the quasi-static mode.

Both return the lost volume (m3, material that left the grid) and where the rest lies: a
thickness block (m) and the grid index of its corner, for
:meth:`sim.parcels.ParcelColumns._merge`.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage

from sim.grid import Grid
from sim.relaxation import relax

#: where a release's material lies: (iy0, ix0, thickness block (h, w) in m)
Placement = tuple[int, int, np.ndarray]


def segment_distance(x, y, x0, y0, x1, y1) -> np.ndarray:
    """Euclidean distance from points (x, y) (broadcast) to the segment (x0,y0)-(x1,y1)."""
    dx, dy = x1 - x0, y1 - y0
    ll = dx * dx + dy * dy
    if ll == 0:
        return np.hypot(x - x0, y - y0)
    s = np.clip(((x - x0) * dx + (y - y0) * dy) / ll, 0.0, 1.0)
    return np.hypot(x - (x0 + s * dx), y - (y0 + s * dy))


def solve_fill_level(k: np.ndarray, v_thk: float, a_up: float) -> tuple[float, bool]:
    """Level a with sum(max(0, a - k)) == v_thk, searching below ``a_up``.

    Returns (a, True), or (nan, False) when the cells below ``a_up`` cannot hold v_thk."""
    cand = k[k < a_up]
    if cand.size == 0 or float(np.sum(a_up - cand)) < v_thk:
        return float("nan"), False
    kc = np.sort(cand)
    cs = np.cumsum(kc)
    n = np.arange(1, kc.size + 1)
    a_n = (v_thk + cs) / n
    ok = np.empty(kc.size, bool)
    ok[:-1] = a_n[:-1] <= kc[1:]
    ok[-1] = True
    j = int(np.argmax(ok))
    return float(a_n[j]), True


def _source_top(surf: np.ndarray, grid: Grid, x0, y0, x1, y1) -> float:
    """Highest surface (m) over the cells the segment touches, one cell around them."""
    iy_a, ix_a = grid.index_of([x0, x1], [y0, y1])
    sy0 = int(np.clip(min(iy_a) - 1, 0, grid.ny - 1))
    sy1 = int(np.clip(max(iy_a) + 1, 0, grid.ny - 1))
    sx0 = int(np.clip(min(ix_a) - 1, 0, grid.nx - 1))
    sx1 = int(np.clip(max(ix_a) + 1, 0, grid.nx - 1))
    return float(surf[1 + sy0:2 + sy1, 1 + sx0:2 + sx1].max())


class _Window:
    """The cells within ``reach`` (m) of the segment: the surface there (ground beyond
    the grid: virtual cells) and each cell's distance to the segment (m)."""

    def __init__(self, surf: np.ndarray, grid: Grid, reach: float, x0, y0, x1, y1):
        c = grid.cell_m
        ground = grid.ground_z_m
        # window of cell indices (may extend past the grid: virtual ground cells)
        wy0, wx0 = [int(v) for v in grid.index_of(min(x0, x1) - reach, min(y0, y1) - reach)]
        wy1, wx1 = [int(v) + 1 for v in grid.index_of(max(x0, x1) + reach,
                                                      max(y0, y1) + reach)]
        b = np.full((wy1 - wy0, wx1 - wx0), float(ground))
        gy0, gy1 = max(wy0, 0), min(wy1, grid.ny)
        gx0, gx1 = max(wx0, 0), min(wx1, grid.nx)
        if gy1 > gy0 and gx1 > gx0:
            b[gy0 - wy0:gy1 - wy0, gx0 - wx0:gx1 - wx0] = \
                surf[1 + gy0:1 + gy1, 1 + gx0:1 + gx1]
        xc = grid.origin_x_m + (np.arange(wx0, wx1) + 0.5) * c
        yc = grid.origin_y_m + (np.arange(wy0, wy1) + 0.5) * c
        self.base = b
        self.d = segment_distance(xc[None, :], yc[:, None], x0, y0, x1, y1)
        self.wy0, self.wx0 = wy0, wx0
        self.gy0, self.gy1, self.gx0, self.gx1 = gy0, gy1, gx0, gx1

    @property
    def overlaps(self) -> bool:
        """Whether the window has cells on the grid."""
        return self.gy1 > self.gy0 and self.gx1 > self.gx0

    def on_grid(self, a: np.ndarray) -> np.ndarray:
        """The on-grid part of a window array (a view)."""
        return a[self.gy0 - self.wy0:self.gy1 - self.wy0, self.gx0 - self.wx0:self.gx1 - self.wx0]


def quasistatic_release(surf: np.ndarray, grid: Grid, tan_repose: float,
                        x0, y0, x1, y1, vol: float) -> tuple[float, Placement | None]:
    """Settle ``vol`` (m3) released along the segment (x0,y0)-(x1,y1) (m), quasi-statically.

    ``surf`` is the padded surface (ny + 2, nx + 2) (m, read only). Returns the lost volume
    (m3) and the placement of the rest (None when no on-grid cell gets material).
    """
    c = grid.cell_m
    area = grid.cell_area_m2
    t = tan_repose
    b_src = _source_top(surf, grid, x0, y0, x1, y1)
    # height of a cone of slope 2 tan holding vol: bounds the rise at the source on a
    # stable base (b_i <= b_src + tan * d_i); verified below and doubled if short
    h_up = 1.5 * (3.0 * vol * (2 * t) ** 2 / math.pi) ** (1.0 / 3.0) + 2 * t * c
    blocked = None
    for _ in range(60):
        a_up = b_src + h_up
        reach = (a_up - grid.ground_z_m) / t + c
        win = _Window(surf, grid, reach, x0, y0, x1, y1)
        d = win.d
        k = win.base + t * d
        if blocked is not None:
            if blocked.shape != k.shape:
                blocked = None
            else:
                k[blocked] = np.inf
        a, ok = solve_fill_level(k, vol / area, a_up)
        if not ok:
            h_up *= 2.0
            blocked = None
            continue
        fill = np.maximum(a - k, 0.0)
        drop = _unreachable(fill > 0, d, c)
        if drop is not None:
            blocked = drop if blocked is None else (blocked | drop)
            continue
        break
    else:  # pragma: no cover - defensive
        raise RuntimeError("quasi-static release did not converge")
    return _placed(fill, win, vol, area)


def _unreachable(mask: np.ndarray, d: np.ndarray, cell_m: float) -> np.ndarray | None:
    """The filled cells not connected to the source (None when there are none): only the
    part connected to the source can be reached by flowing material."""
    lab, nlab = ndimage.label(mask, structure=np.ones((3, 3), bool))
    if nlab > 1:
        src = mask & (d <= 0.75 * cell_m)
        keep_labels = np.unique(lab[src])
        if keep_labels.size == 0:  # degenerate: the component nearest the source
            keep_labels = np.array([lab.flat[np.argmin(np.where(mask, d, np.inf))]])
        drop = mask & ~np.isin(lab, keep_labels)
        if drop.any():
            return drop
    return None


def _placed(fill: np.ndarray, win: _Window, vol: float,
            area: float) -> tuple[float, Placement | None]:
    """Lost volume and on-grid placement of a window's fill (rescaled to exactly ``vol``)."""
    # exact volume: rescale the (tiny) rounding residual
    s = fill.sum()
    if s > 0:
        fill *= (vol / area) / s
    # split into on-grid and off-grid (lost) parts
    on = np.zeros_like(fill, bool)
    if win.overlaps:
        win.on_grid(on)[...] = True
    lost = float(fill[~on].sum() * area) if (~on).any() else 0.0
    placement = None
    # touching the outermost grid cells counts as reaching the border too
    if win.overlaps:
        blk = win.on_grid(fill)
        rows = np.flatnonzero(blk.any(axis=1))
        cols = np.flatnonzero(blk.any(axis=0))
        if rows.size:
            r0, r1 = rows[0], rows[-1] + 1
            q0, q1 = cols[0], cols[-1] + 1
            placement = (win.gy0 + r0, win.gx0 + q0, blk[r0:r1, q0:q1])
    return lost, placement


def avalanche_release(surf: np.ndarray, grid: Grid, crit: np.ndarray, tol_m: float,
                      max_iterations: int, x0, y0, x1, y1,
                      vol: float) -> tuple[float, Placement]:
    """Settle ``vol`` (m3) released along the segment (x0,y0)-(x1,y1) (m) by the avalanche
    relaxation (:func:`sim.relaxation.relax` with ``crit``, ``tol_m``, ``max_iterations``).

    ``surf`` is the padded surface (ny + 2, nx + 2) (m, read only). Returns the lost volume
    (m3) and the placement of the rest.
    """
    c = grid.cell_m
    n = max(2, int(math.ceil(math.hypot(x1 - x0, y1 - y0) / c)) * 2 + 1)
    s = (np.arange(n) + 0.5) / n
    xs = x0 + (x1 - x0) * s
    ys = y0 + (y1 - y0) * s
    iy, ix = grid.index_of(xs, ys)
    iy = np.clip(iy, 0, grid.ny - 1)
    ix = np.clip(ix, 0, grid.nx - 1)
    ny, nx = grid.shape
    mob = np.zeros((ny + 2, nx + 2))
    np.add.at(mob, (iy + 1, ix + 1), vol / grid.cell_area_m2 / n)
    bbox = (int(iy.min()) + 1, int(iy.max()) + 2, int(ix.min()) + 1, int(ix.max()) + 2)
    _, lost_thk, touched = relax(surf, mob, bbox, crit, tol_m, max_iterations)
    r0, r1, c0, c1 = touched
    blk = mob[r0:r1, c0:c1]
    # renormalise the rounding residual of the flux arithmetic
    total = blk.sum() + lost_thk
    if total > 0:
        scale = (vol / grid.cell_area_m2) / total
        blk = blk * scale
        lost_thk *= scale
    return float(lost_thk * grid.cell_area_m2), (r0 - 1, c0 - 1, blk)
