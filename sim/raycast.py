"""Ray casting on a heightmap: the simulated scanner's true ranges.

:func:`raycast_heightmap` finds where rays first meet the bilinear surface through a
grid's cell-centre heights (vectorised over rays): the simulator's own geometry, used by
:class:`sim.scanner.ScannerModel` to cast each beam on the true pile. Lengths in metres,
site frame (x across the pile, y along the rail, z up; docs/domain.md §2).
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["raycast_heightmap"]


def _bilinear(hflat: np.ndarray, nx: int, ny: int, gx: np.ndarray, gy: np.ndarray) -> np.ndarray:
    """Bilinear height at grid coordinates gx, gy (in cells, 0 = first cell centre).

    Indices are clamped, so the outer half cell holds the edge values.  Any NaN among the
    four corners gives NaN.
    """
    i0 = np.clip(np.floor(gx), 0, nx - 2).astype(np.intp)
    j0 = np.clip(np.floor(gy), 0, ny - 2).astype(np.intp)
    fx = np.clip(gx - i0, 0.0, 1.0)
    fy = np.clip(gy - j0, 0.0, 1.0)
    k = j0 * nx + i0
    h00 = hflat[k]
    h01 = hflat[k + 1]
    h10 = hflat[k + nx]
    h11 = hflat[k + nx + 1]
    a = h00 + fx * (h01 - h00)
    b = h10 + fx * (h11 - h10)
    return a + fy * (b - a)


def _block_max_halo(h: np.ndarray, b: int) -> np.ndarray:
    """Maximum over each b x b block of ``h`` plus a one-cell halo around it.

    Returns an (ceil(ny/b), ceil(nx/b)) array; NaN cells are ignored, -inf where a block
    and its halo hold no finite height.
    """
    def pass_rows(a: np.ndarray) -> np.ndarray:   # max over rows b*J - 1 .. b*J + b
        n, m = a.shape
        nb = -(-n // b)
        out = np.full((nb, m), -np.inf)
        for off in range(-1, b + 1):
            j0 = 1 if off < 0 else 0
            sl = a[b * j0 + off::b]
            k = min(sl.shape[0], nb - j0)
            if k > 0:
                np.fmax(out[j0:j0 + k], sl[:k], out=out[j0:j0 + k])
        return out
    return pass_rows(pass_rows(h).T).T


def raycast_heightmap(height_m, origin_x_m: float, origin_y_m: float, cell_m: float,
                      ray_origin_m, ray_dir, max_range_m: float, *,
                      step_frac: float = 0.5, coarse_cells: int = 8) -> np.ndarray:
    """First intersection of rays with a heightmap surface (vectorised over rays).

    The surface is the **bilinear interpolation of cell-centre heights**: ``height_m[j, i]``
    is the height at the centre of cell (i, j), i.e. at ``x = origin_x_m + (i + 0.5) *
    cell_m``, ``y = origin_y_m + (j + 0.5) * cell_m`` (``origin`` = the grid corner, as in
    ``PileDeclared``).  Over the outer half cell the edge values are held (clamped), so the
    surface covers exactly ``[origin_x, origin_x + nx * cell] x [origin_y, origin_y + ny *
    cell]``; the region is solid below the surface (columns), so a ray entering the grid's
    footprint from the side below the edge height hits the side at the border.  A NaN cell
    means "no surface": every point whose four bilinear neighbours include a NaN is empty
    (so a NaN removes the surface within one cell of its centre).

    Method (vectorised over all rays): clip each ray to the grid footprint and to below
    the highest cell; skip segments of ``coarse_cells`` cells that lie above the maximum
    height of the blocks under them (a one-level max pyramid with a one-cell halo, so
    skipping is exact); march the remaining segments in steps of ``step_frac * cell_m``
    (one segment per ray per numpy pass); refine the first crossing step by 6 bisections
    and 2 false-position steps.  The range is exact on the bilinear surface to about
    10 micrometres (f is quadratic along a ray within a cell); at the edge of a NaN region
    (a vertical wall) to 1/64 of a step.  Limitation: a ray grazing a ridge that enters
    and leaves the surface within one step (less than ``step_frac * cell_m`` of travel
    below it) can be missed.  A ray starting below the surface returns 0.

    Parameters
    ----------
    height_m : ndarray, shape (ny, nx), ny, nx >= 2
        Heights (m, site z); NaN = no surface.
    origin_x_m, origin_y_m : float
        Grid corner (m, site frame).
    cell_m : float
        Cell size (m), > 0.
    ray_origin_m : array_like, shape (3,) or (N, 3)
        Ray origins (m, site frame).
    ray_dir : array_like, shape (N, 3)
        Ray directions (normalised here; must be non-zero).
    max_range_m : float
        Maximum range (m), > 0.
    step_frac : float
        Marching step as a fraction of ``cell_m`` (keyword-only).
    coarse_cells : int
        Block size (cells) of the max-height pyramid level used to skip empty space
        (keyword-only; a speed knob, no effect on the result).

    Returns
    -------
    ndarray, shape (N,)
        Range (m) along each ray to the first hit; NaN if nothing is hit within
        ``max_range_m``.
    """
    h, o, d = _checked_inputs(height_m, cell_m, max_range_m, step_frac, coarse_cells,
                              ray_origin_m, ray_dir)
    n = d.shape[0]
    out = np.full(n, np.nan)
    if n == 0:
        return out
    hmax = float(np.fmax.reduce(h, axis=None))   # NaN-ignoring; NaN only if all NaN
    hmin = float(np.fmin.reduce(h, axis=None))
    if math.isnan(hmax):
        return out
    if math.isinf(hmax) or math.isinf(hmin):
        raise ValueError("height_m must not contain infinities (use NaN for no surface)")
    all_finite = not np.isnan(h).any()
    rays = _Rays(h, float(origin_x_m), float(origin_y_m), cell_m, o, d)
    t_in, t_out = rays.clipped(max_range_m, hmax, hmin, all_finite)
    active = np.flatnonzero(t_in <= t_out)
    if active.size == 0:
        return out
    ts, te = t_in[active], t_out[active]
    b = int(coarse_cells)
    rows, segs = _candidate_segments(rays, h, b, active, ts, te)
    if rows.size == 0:
        return out
    crossings = _march(rays, b, step_frac, active, ts, te, rows, segs)
    if crossings is None:
        return out
    lo_t, hi_t, hit_idx = crossings
    out[hit_idx] = _refine(rays, lo_t, hi_t, hit_idx)
    out[out > max_range_m] = np.nan
    return out


def _checked_inputs(height_m, cell_m, max_range_m, step_frac, coarse_cells, ray_origin_m,
                    ray_dir) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The heightmap (ny, nx), ray origins (N, 3) and unit directions (N, 3) of a
    :func:`raycast_heightmap` call, checked (ValueError on bad input)."""
    h = np.ascontiguousarray(height_m, dtype=float)
    if h.ndim != 2 or h.shape[0] < 2 or h.shape[1] < 2:
        raise ValueError(f"height_m must be a 2-D (ny, nx) array with ny, nx >= 2, got {h.shape}")
    if not (cell_m > 0 and math.isfinite(cell_m)):
        raise ValueError(f"cell_m must be > 0, got {cell_m}")
    if not (max_range_m > 0):
        raise ValueError(f"max_range_m must be > 0, got {max_range_m}")
    if not step_frac > 0 or int(coarse_cells) < 2:
        raise ValueError("step_frac must be > 0 and coarse_cells >= 2")
    d = np.asarray(ray_dir, float)
    if d.ndim != 2 or d.shape[1] != 3:
        raise ValueError(f"ray_dir must have shape (N, 3), got {d.shape}")
    n = d.shape[0]
    o = np.asarray(ray_origin_m, float)
    if o.shape == (3,):
        o = np.broadcast_to(o, (n, 3))
    elif o.shape != (n, 3):
        raise ValueError(f"ray_origin_m must have shape (3,) or ({n}, 3), got {o.shape}")
    norm = np.linalg.norm(d, axis=1)
    if np.any(~(norm > 0)) or not np.all(np.isfinite(o)):
        raise ValueError("ray directions must be non-zero and finite, origins finite")
    d = d / norm[:, None]
    return h, o, d


class _Rays:
    """Rays (origins ``o`` (N, 3) m, unit directions ``d`` (N, 3)) over a heightmap ``h``
    (ny, nx) whose grid corner is (x0, y0) m, in site and in grid coordinates (cells,
    0 = first cell centre)."""

    def __init__(self, h: np.ndarray, x0: float, y0: float, cell_m: float, o: np.ndarray,
                 d: np.ndarray):
        self.ny, self.nx = h.shape
        self.hflat = h.ravel()
        self.cell_m = cell_m
        self.x0, self.y0 = x0, y0
        self.x1, self.y1 = x0 + self.nx * cell_m, y0 + self.ny * cell_m
        self.ox, self.oy, self.oz = o[:, 0], o[:, 1], o[:, 2]
        self.dx, self.dy, self.dz = d[:, 0], d[:, 1], d[:, 2]
        inv = 1.0 / cell_m
        self.gx0 = (self.ox - x0) * inv - 0.5          # grid coordinates (cells, 0 = first centre)
        self.gy0 = (self.oy - y0) * inv - 0.5
        self.gdx, self.gdy = self.dx * inv, self.dy * inv

    def clipped(self, max_range_m: float, hmax: float, hmin: float,
                all_finite: bool) -> tuple[np.ndarray, np.ndarray]:
        """Each ray's span (t_in, t_out) (N,) m inside the grid's footprint, within
        ``max_range_m``, at or below the highest surface ``hmax`` and (when every cell
        has a height) above the lowest ``hmin``; empty where t_in > t_out."""
        ox, oy, oz, dx, dy, dz = self.ox, self.oy, self.oz, self.dx, self.dy, self.dz
        n = ox.shape[0]
        t_in = np.zeros(n)
        t_out = np.full(n, float(max_range_m))
        with np.errstate(divide="ignore", invalid="ignore"):
            for oc, dc, lo, hi in ((ox, dx, self.x0, self.x1), (oy, dy, self.y0, self.y1)):
                ta = (lo - oc) / dc
                tb = (hi - oc) / dc
                par = dc == 0
                inside = (oc >= lo) & (oc <= hi)
                ta = np.where(par, np.where(inside, -np.inf, np.inf), ta)
                tb = np.where(par, np.where(inside, np.inf, -np.inf), tb)
                t_in = np.maximum(t_in, np.minimum(ta, tb))
                t_out = np.minimum(t_out, np.maximum(ta, tb))
            # only where the ray is at or below the highest surface can it hit
            tz_top = np.where(dz < 0, (hmax - oz) / dz, np.where(oz <= hmax, -np.inf, np.inf))
            t_in = np.maximum(t_in, tz_top)
            if all_finite:  # below the lowest surface the ray is surely inside
                tz_bot = np.where(dz < 0, (hmin - oz) / dz, np.inf)
                t_out = np.minimum(t_out, tz_bot + 1e-9)
        return t_in, t_out

    def above(self, tt: np.ndarray, idx: np.ndarray) -> np.ndarray:
        """Ray height minus surface height (m) at ranges ``tt`` (m, k) of the rays ``idx``
        (m,); +inf where there is no surface (NaN)."""
        val = (self.oz[idx, None] + tt * self.dz[idx, None]
               - _bilinear(self.hflat, self.nx, self.ny,
                           self.gx0[idx, None] + tt * self.gdx[idx, None],
                           self.gy0[idx, None] + tt * self.gdy[idx, None]))
        val[np.isnan(val)] = np.inf
        return val


def _candidate_segments(rays: _Rays, h: np.ndarray, b: int, active: np.ndarray,
                        ts: np.ndarray, te: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Coarse pass: the segments of length ``b`` cells that may touch the surface.

    Segments that lie above the maxima of the blocks under them (with a one-cell halo for
    the bilinear support) are skipped. Returns (rows into ``active``, segment numbers),
    row-major: each ray's candidate segments in order.
    """
    ny, nx = h.shape
    nyc, nxc = -(-ny // b), -(-nx // b)
    mhalo = _block_max_halo(h, b)
    seg = b * rays.cell_m
    nseg = np.maximum(np.ceil((te - ts) / seg).astype(np.int64), 1)
    kk = np.arange(int(nseg.max()) + 1)[None, :]
    tk = np.minimum(ts[:, None] + kk * seg, te[:, None])          # segment ends
    ai = active[:, None]
    bi = np.clip(np.floor((rays.ox[ai] + tk * rays.dx[ai] - rays.x0) / seg), 0,
                 nxc - 1).astype(np.intp)
    bj = np.clip(np.floor((rays.oy[ai] + tk * rays.dy[ai] - rays.y0) / seg), 0,
                 nyc - 1).astype(np.intp)
    zk = rays.oz[ai] + tk * rays.dz[ai]
    # a segment (length <= one block) touches at most the 2 x 2 blocks of its two ends
    ia, ib, ja, jb = bi[:, :-1], bi[:, 1:], bj[:, :-1], bj[:, 1:]
    top = np.maximum(np.maximum(mhalo[ja, ia], mhalo[jb, ib]),
                     np.maximum(mhalo[ja, ib], mhalo[jb, ia]))
    cand = (np.minimum(zk[:, :-1], zk[:, 1:]) <= top) & (kk[:, :-1] < nseg[:, None])
    return np.nonzero(cand)


def _march(rays: _Rays, b: int, step_frac: float, active: np.ndarray, ts: np.ndarray,
           te: np.ndarray, rows: np.ndarray, segs: np.ndarray):
    """Fine march inside the candidate segments, one segment per ray per round, in steps
    of ``step_frac`` cells.

    Returns (lo, hi, ray index) of each ray's first crossing step (the ray is above the
    surface at range lo, at or below it at hi, m), or None when no ray crosses.
    """
    seg = b * rays.cell_m
    step = step_frac * rays.cell_m
    first_of_row = np.r_[True, rows[1:] != rows[:-1]]
    starts = np.flatnonzero(first_of_row)
    rank = np.arange(rows.size) - np.repeat(starts, np.diff(np.r_[starts, rows.size]))
    sub = np.arange(int(math.ceil(b / step_frac)) + 1) * step   # samples incl. both ends
    done = np.zeros(active.size, bool)
    los, his, hits = [], [], []
    for r in range(int(rank.max()) + 1):
        pick = rank == r
        rr, kr = rows[pick], segs[pick]
        keep = ~done[rr]
        rr, kr = rr[keep], kr[keep]
        if rr.size == 0:
            break
        t_seg = ts[rr] + kr * seg
        tt = np.minimum(t_seg[:, None] + sub[None, :], te[rr, None])
        below = rays.above(tt, active[rr]) <= 0.0
        anyb = below.any(axis=1)
        if anyb.any():
            hr = np.flatnonzero(anyb)
            first = below[hr].argmax(axis=1)
            t_hi = tt[hr, first]
            t_lo = np.where(first > 0, tt[hr, np.maximum(first - 1, 0)], t_hi)
            los.append(t_lo)
            his.append(t_hi)
            hits.append(active[rr[hr]])
            done[rr[hr]] = True
    if not hits:
        return None
    return np.concatenate(los), np.concatenate(his), np.concatenate(hits)


def _refine(rays: _Rays, lo_t: np.ndarray, hi_t: np.ndarray,
            hit_idx: np.ndarray) -> np.ndarray:
    """The crossing's range (m) in each bracket [lo, hi] (f(lo) > 0 >= f(hi)) of the rays
    ``hit_idx``: bisection to 1/64 of a step, then two false-position steps (f is
    quadratic along a ray within a cell)."""
    def f(t: np.ndarray) -> np.ndarray:
        return rays.above(t[:, None], hit_idx)[:, 0]

    for _ in range(6):
        mid = 0.5 * (lo_t + hi_t)
        fb = f(mid) <= 0.0
        hi_t = np.where(fb, mid, hi_t)
        lo_t = np.where(fb, lo_t, mid)
    f_lo = f(lo_t)
    f_hi = f(hi_t)
    t_hit = hi_t
    for _ in range(2):
        denom = f_lo - f_hi
        ok = np.isfinite(f_lo) & (denom > 0)
        frac = np.divide(f_lo, denom, where=ok, out=np.ones_like(f_lo))
        t_hit = np.where(ok, lo_t + (hi_t - lo_t) * np.clip(frac, 0.0, 1.0), hi_t)
        f_new = f(t_hit)
        below = f_new <= 0.0
        hi_t, f_hi = np.where(below, t_hit, hi_t), np.where(below, f_new, f_hi)
        lo_t, f_lo = np.where(below, lo_t, t_hit), np.where(below, f_lo, f_new)
    return np.clip(t_hit, lo_t, hi_t)
