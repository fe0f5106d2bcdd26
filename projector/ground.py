"""Scanner heights referenced to the declared ground each scan sees.

A reclaimer's scanner pose comes from the localizer, whose luff is observable only
through GNSS height, so its scanner height carries a slowly varying error, and every
point of a scan is off by that much (the scanner's orientation does not depend on the
luff, so the error is a vertical translation); folded as is, it makes the pile read
heavy (figures: docs/design-notes.md).  Most scans also see bare ground beside the pile,
whose height the pile's declaration gives: the lowest dense cluster of a scan's points
over cells the layer stack holds as bare is that ground, and its offset from the
declared level is the scan's height error.

Pure functions, vectorised over the scans of a batch; no I/O:

- :func:`ground_candidates`: the points that may be ground (near its level, over bare
  cells);
- :func:`scan_ground_offsets`: each scan's offset (m) from its ground points alone;
- :func:`smooth_offsets`: the median of the offsets within a time window of each scan
  (the error varies over seconds; single-scan estimates carry range noise and, rarely,
  a flat cut floor mistaken for ground) with its standard error;
- :func:`height_corrections`: the three above, and a deadband: the offset to subtract
  from each scan's heights.

Units: metres, int64 UTC nanoseconds.
"""

from __future__ import annotations

import numpy as np

from projector.grid import GridGeometry, cell_index, inside

__all__ = ["ground_candidates", "scan_ground_offsets", "smooth_offsets", "height_corrections"]

#: efficiency of the median against the mean for Gaussian noise: se = 1.2533 sd / sqrt(n)
_MEDIAN_SE_FACTOR = 1.2533


def _row_medians(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Median of each row's finite values (NaN for none) and their count, by one sort
    (``np.nanmedian`` loops over rows in Python when they are mostly NaN)."""
    finite = np.isfinite(values)
    k = finite.sum(axis=1)
    if values.shape[1] == 0:
        return np.full(values.shape[0], np.nan), k
    v = np.sort(np.where(finite, values, np.inf), axis=1)
    rows = np.arange(v.shape[0])
    lo = v[rows, np.maximum(k - 1, 0) // 2]
    hi = v[rows, k // 2 - (k == 0)]
    with np.errstate(invalid="ignore"):
        med = np.where(k > 0, 0.5 * (lo + hi), np.nan)
    return med, k


def ground_candidates(points_m, geometry: GridGeometry, bare, ground_z_m: float,
                      reach_m: float) -> np.ndarray:
    """The points that may be ground: within ``reach_m`` of its level, over a bare cell.

    Parameters
    ----------
    points_m : array_like, shape (S, B, 3)
        Site-frame points (m); NaN = no point.
    geometry : GridGeometry
        The grid ``bare`` is on.
    bare : array_like of bool, shape (nx, ny)
        Cells holding no material (points outside the grid are never candidates).
    ground_z_m : float
        The declared ground level (m).
    reach_m : float
        Largest height difference from it looked at (m), >= 0.

    Returns
    -------
    ndarray of bool, shape (S, B)

    Raises
    ------
    ValueError
        On wrong shapes or a negative reach.
    """
    p = np.asarray(points_m, dtype=np.float64)
    bare = np.asarray(bare, dtype=bool)
    if p.ndim != 3 or p.shape[-1] != 3 or bare.shape != geometry.shape:
        raise ValueError(f"points_m must be (S, B, 3) and bare {geometry.shape}; got "
                         f"{p.shape}, {bare.shape}")
    if not reach_m >= 0:
        raise ValueError(f"reach_m must be >= 0, got {reach_m}")
    with np.errstate(invalid="ignore"):
        near = np.abs(p[..., 2] - ground_z_m) <= reach_m
    out = np.zeros(near.shape, dtype=bool)
    if near.any():
        x, y = p[..., 0][near], p[..., 1][near]
        ok = inside(geometry, x, y)
        ix, iy = cell_index(geometry, x[ok], y[ok])
        flags = np.zeros(x.shape, dtype=bool)
        flags[ok] = bare[ix, iy]
        out[near] = flags
    return out


def scan_ground_offsets(z_m, candidate, ground_z_m: float, *, window_m: float,
                        min_points: int, max_offset_m: float,
                        iterations: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Each scan's height offset: its ground points' level minus the declared ground.

    Per scan, among the candidate points within ``max_offset_m + window_m`` of
    ``ground_z_m``, the lowest pair of half-window bins (``window_m`` wide together)
    holding ``min_points`` points starts the estimate; it is refined ``iterations``
    times to the median of the points within ``window_m`` of it (so it settles on the
    mode of the ground's noise, not on its low tail).  Material on the ground is above it and never the lowest cluster.

    Parameters
    ----------
    z_m : array_like, shape (S, B)
        Heights of the scans' points (m); NaN = no point.
    candidate : array_like of bool, shape (S, B)
        Points that may be ground (e.g. over cells holding no material).
    ground_z_m : float
        The declared ground level (m).
    window_m : float
        Half width of the refining window and width of the search's bin pairs (m),
        > 0: about twice a point's height noise.
    min_points : int
        Fewest points in the window for a scan to have an offset, >= 1.
    max_offset_m : float
        Largest offset looked for (m), > 0.
    iterations : int
        Refinements of the window's centre, >= 1.

    Returns
    -------
    offset_m : ndarray, shape (S,)
        Ground level seen minus ``ground_z_m`` (m); NaN where a scan has too few
        ground points or its offset exceeds ``max_offset_m``.
    n_points : ndarray of int, shape (S,)
        Points in the final window (0 where the offset is NaN).

    Raises
    ------
    ValueError
        On mismatched shapes or out-of-range parameters.
    """
    z = np.asarray(z_m, dtype=np.float64)
    cand = np.asarray(candidate, dtype=bool)
    if z.ndim != 2 or cand.shape != z.shape:
        raise ValueError(f"z_m must be (S, B) and candidate the same shape; got {z.shape}, "
                         f"{cand.shape}")
    if not (window_m > 0 and max_offset_m > 0 and int(min_points) >= 1
            and int(iterations) >= 1 and np.isfinite(ground_z_m)):
        raise ValueError("window_m and max_offset_m must be > 0, min_points and iterations "
                         ">= 1, ground_z_m finite")
    s = z.shape[0]
    offset = np.full(s, np.nan)
    count = np.zeros(s, dtype=np.int64)
    if s == 0:
        return offset, count
    reach = max_offset_m + window_m
    with np.errstate(invalid="ignore"):
        d = np.where(cand & (np.abs(z - ground_z_m) <= reach), z - ground_z_m, np.nan)
    # search: half-window bins, a pair of them is one window
    half = 0.5 * window_m
    n_bins = int(np.ceil(2 * reach / half)) + 1
    rows, cols = np.nonzero(np.isfinite(d))
    if rows.size == 0:
        return offset, count
    bins = np.minimum(((d[rows, cols] + reach) / half).astype(np.int64), n_bins - 1)
    hist = np.bincount(rows * n_bins + bins, minlength=s * n_bins).reshape(s, n_bins)
    pair = hist[:, :-1] + hist[:, 1:]
    enough = pair >= int(min_points)
    has = enough.any(axis=1)
    first = np.argmax(enough, axis=1)
    centre = np.where(has, -reach + (first + 1) * half, np.nan)
    for _ in range(int(iterations)):
        with np.errstate(invalid="ignore"):
            near = np.abs(d - centre[:, None]) <= window_m
        med, n = _row_medians(np.where(near, d, np.nan))
        has = has & (n >= int(min_points))
        centre = np.where(has, med, np.nan)
    good = has & (np.abs(centre) <= max_offset_m)
    offset[good] = centre[good]
    count[good] = n[good]
    return offset, count


def smooth_offsets(t_ns, offset_m, n_points, *, half_window_ns: int,
                   point_sd_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Per scan, the median of the finite offsets within ``half_window_ns`` of its time.

    Parameters
    ----------
    t_ns : array_like of int, shape (S,)
        Scan times (UTC ns).
    offset_m : array_like, shape (S,)
        Per-scan offsets (m), NaN = none (:func:`scan_ground_offsets`).
    n_points : array_like of int, shape (S,)
        Ground points behind each offset.
    half_window_ns : int
        Half width of the time window (ns), >= 0.
    point_sd_m : float
        Height noise of one point (m), > 0, for the standard error.

    Returns
    -------
    smoothed_m : ndarray, shape (S,)
        The window's median offset (m); NaN where the window holds none.
    se_m : ndarray, shape (S,)
        Its standard error (m): ``1.2533 * point_sd_m / sqrt(points in the window)``;
        NaN where ``smoothed_m`` is.

    Raises
    ------
    ValueError
        On mismatched shapes or out-of-range parameters.
    """
    t = np.asarray(t_ns, dtype=np.int64)
    off = np.asarray(offset_m, dtype=np.float64)
    npts = np.asarray(n_points, dtype=np.float64)
    if t.ndim != 1 or off.shape != t.shape or npts.shape != t.shape:
        raise ValueError(f"t_ns, offset_m and n_points must be (S,); got {t.shape}, "
                         f"{off.shape}, {npts.shape}")
    if not (int(half_window_ns) >= 0 and point_sd_m > 0):
        raise ValueError("half_window_ns must be >= 0 and point_sd_m > 0")
    within = np.abs(t[:, None] - t[None, :]) <= int(half_window_ns)
    valid = within & np.isfinite(off)[None, :]
    has = valid.any(axis=1)
    smoothed = np.full(t.shape, np.nan)
    se = np.full(t.shape, np.nan)
    if has.any():
        smoothed[has] = _row_medians(np.where(valid[has], off[None, :], np.nan))[0]
        total = np.where(valid[has], npts[None, :], 0.0).sum(axis=1)
        se[has] = _MEDIAN_SE_FACTOR * point_sd_m / np.sqrt(np.maximum(total, 1.0))
    return smoothed, se


def height_corrections(t_ns, points_m, geometry: GridGeometry, bare, ground_z_m: float, *,
                       point_sd_m: float, half_window_ns: int, min_points: int,
                       max_offset_m: float, deadband_sigma: float,
                       deadband_m: float) -> tuple[np.ndarray, np.ndarray]:
    """The offset (m) to subtract from each scan's heights, from the ground it sees.

    :func:`ground_candidates` (within ``max_offset_m`` + the window of the ground),
    :func:`scan_ground_offsets` (window ``2 * point_sd_m``), :func:`smooth_offsets`;
    a pooled offset within ``deadband_sigma`` standard errors or ``deadband_m`` of 0 is
    not applied (a well posed scanner's offsets are noise, and ground seen over bare
    cells reads a little high where thin toes lie on it).

    Parameters
    ----------
    t_ns : array_like of int, shape (S,)
        Scan times (UTC ns).
    points_m : array_like, shape (S, B, 3)
        The scans' site-frame points (m), NaN = none.
    geometry, bare, ground_z_m
        As for :func:`ground_candidates`.
    point_sd_m : float
        Height noise of one point (m), > 0.
    half_window_ns, min_points, max_offset_m
        As for :func:`smooth_offsets` and :func:`scan_ground_offsets`.
    deadband_sigma, deadband_m : float
        The deadband, >= 0.

    Returns
    -------
    correction_m : ndarray, shape (S,)
        0 where no offset is applied.
    seen : ndarray of bool, shape (S,)
        Whether a scan's window saw ground at all (a caller may hold an earlier
        correction for the others).

    Raises
    ------
    ValueError
        On wrong shapes or out-of-range parameters.
    """
    if not (deadband_sigma >= 0 and deadband_m >= 0):
        raise ValueError("deadband_sigma and deadband_m must be >= 0")
    window = 2.0 * point_sd_m
    points = np.asarray(points_m, dtype=np.float64)
    candidate = ground_candidates(points, geometry, bare, ground_z_m, max_offset_m + window)
    raw, n = scan_ground_offsets(points[..., 2], candidate, ground_z_m, window_m=window,
                                 min_points=min_points, max_offset_m=max_offset_m)
    pooled, se = smooth_offsets(t_ns, raw, n, half_window_ns=half_window_ns,
                                point_sd_m=point_sd_m)
    seen = np.isfinite(pooled)
    with np.errstate(invalid="ignore"):
        keep = seen & (np.abs(pooled) > np.maximum(deadband_sigma * se, deadband_m))
    return np.where(keep, pooled, 0.0), seen
