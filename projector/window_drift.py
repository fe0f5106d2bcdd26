"""The belt's grade drift inside an assay window, and what it does to part of a window.

An assay reports one grade for a window of belt flow, but the grade drifts along the belt
inside the window.  A cut takes only the part of each window that was stacked where it
digs (a few seconds of each pass), and that part's grade differs from the window's mean.
The model: inside a window the grade drifts as a random walk (Brownian motion) with a
rate ``D`` (pp^2/s) per analyte, the belt carries constant tonnes per second, and the
drifts of different windows are independent.

- :func:`drift_rate_pp2_s` estimates ``D`` from the assays themselves: the mean of two
  disjoint windows ``a``, ``b`` (lengths ``W_a``, ``W_b``, centres ``dc`` apart) differs
  by the variance ``D (dc - (W_a + W_b) / 6)``, plus both lab errors.
- :func:`part_variance_pp2` gives the variance of the tonnage-weighted mean grade of some
  of a window's material about the window's mean: ``D W Q``, with ``Q`` from the
  material's spread over the window's time (a point sample: ``Q`` 1/6 on average; the
  whole window evenly: 0).

docs/uncertainty.md, term (d), says why and what it leaves out.  Times in s (or ns where
named), grades in mass % and their sds in percentage points (pp).
"""

from __future__ import annotations

import numpy as np

__all__ = ["drift_rate_pp2_s", "part_variance_pp2", "window_histogram", "BINS"]

#: Bins of a window's normalised time (0 at its start, 1 at its end) for :func:`part_variance_pp2`.
BINS = 16


def drift_rate_pp2_s(start_s, end_s, grade_pp, lab_sd_pp, series, max_lag_windows: float = 3.0):
    """The drift rate ``D`` (pp^2/s) per analyte, pooled over successive assays.

    Pairs are successive windows of one series (a lot), sorted by start, that do not
    overlap and whose centres lie at most ``max_lag_windows`` mean window lengths apart
    (beyond that a bounded drift no longer grows like a random walk).  Pooled over the
    pairs, ``D = sum(d^2 - s_a^2 - s_b^2) / sum(dc - (W_a + W_b) / 6)``, floored at 0
    (the lab's errors can explain all of the differences).

    Parameters
    ----------
    start_s, end_s : array_like, shape (N,)
        Each assay's window (s, any common origin), ``end >= start``.
    grade_pp, lab_sd_pp : array_like, shape (N, A)
        Each assay's grade (mass %) and its lab's repeatability (pp, one sd).
    series : array_like, shape (N,)
        Which lot each assay belongs to (any hashable values; pairs stay within one).
    max_lag_windows : float

    Returns
    -------
    ndarray, shape (A,)
        ``D`` (pp^2/s, >= 0); NaN for an analyte with no pair (or a NaN grade in every
        pair).
    """
    start, end = np.asarray(start_s, np.float64), np.asarray(end_s, np.float64)
    grade, lab = np.asarray(grade_pp, np.float64), np.asarray(lab_sd_pp, np.float64)
    keys = np.asarray(series)
    n = start.shape[0] if start.ndim == 1 else -1
    if (n < 0 or end.shape != (n,) or keys.shape != (n,) or grade.ndim != 2
            or grade.shape[0] != n or lab.shape != grade.shape or (end < start).any()):
        raise ValueError(f"start_s, end_s, series must be (N,) and grade_pp, lab_sd_pp (N, A), "
                         f"end >= start; got {start.shape}, {end.shape}, {keys.shape}, "
                         f"{grade.shape}, {lab.shape}")
    n_a = grade.shape[1]
    if n < 2:
        return np.full(n_a, np.nan)
    width = end - start
    reach = max_lag_windows * float(width.mean())
    order = np.lexsort((start, keys))
    a, b = order[:-1], order[1:]
    centre = (start + end) / 2
    lag = centre[b] - centre[a] - (width[a] + width[b]) / 6
    pair = (keys[a] == keys[b]) & (start[b] >= end[a]) & (centre[b] - centre[a] <= reach)
    excess = (grade[b] - grade[a]) ** 2 - lab[a] ** 2 - lab[b] ** 2     # (P, A)
    ok = pair[:, None] & np.isfinite(excess)
    den = np.where(ok, lag[:, None], 0.0).sum(axis=0)
    num = np.where(ok, excess, 0.0).sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 0, np.maximum(num / np.where(den > 0, den, 1.0), 0.0), np.nan)


def window_histogram(times_ns, tonnes, start_ns, end_ns) -> np.ndarray:
    """Tonnes per bin of normalised window time, shape (BINS,), of material deposited at
    ``times_ns`` (shape (N,)) in the window ``[start_ns, end_ns]`` (clipped to it)."""
    t = np.asarray(times_ns, np.float64)
    w = np.asarray(tonnes, np.float64)
    if t.ndim != 1 or w.shape != t.shape:
        raise ValueError(f"times_ns and tonnes must share one shape (N,), got {t.shape}, {w.shape}")
    span = float(end_ns) - float(start_ns)
    rel = (t - float(start_ns)) / span if span > 0 else np.full(t.shape, 0.5)
    bins = np.clip((rel * BINS).astype(np.int64), 0, BINS - 1)
    return np.bincount(bins, weights=w, minlength=BINS)


def _q_matrix(bins: int) -> tuple[np.ndarray, np.ndarray]:
    """``(M, c)``: ``E[min(s, s')]`` for s, s' uniform in bins i, j of [0, 1], and
    ``E[min(s, u)]`` for s in bin i, u uniform on [0, 1]."""
    h = 1.0 / bins
    mid = (np.arange(bins) + 0.5) * h
    m = np.minimum.outer(mid, mid)
    np.fill_diagonal(m, mid - h / 6)
    c = mid - (mid * mid + h * h / 12) / 2
    return m, c


_M, _C = _q_matrix(BINS)


def part_variance_pp2(histograms, window_s, drift_pp2_s) -> np.ndarray:
    """Variance (pp^2) of a part of each window's material about the window's mean grade.

    For a part spread over the window's time as ``p`` (shares per bin), the grade a
    random walk of rate ``D`` gives it differs from the window's mean by the variance
    ``D W Q``, ``Q = p M p - 2 p c + 1/3`` (``M``, ``c``: the walk's covariances, in units of
    ``D W``).

    Parameters
    ----------
    histograms : array_like, shape (K, BINS)
        Tonnes of the part per bin of each window's normalised time (:func:`window_histogram`).
    window_s : array_like, shape (K,)
        Each window's length (s, >= 0).
    drift_pp2_s : array_like, shape (A,)
        :func:`drift_rate_pp2_s` (NaN: unknown, gives NaN).

    Returns
    -------
    ndarray, shape (K, A)
        Variance (pp^2), >= 0; 0 for a window with no tonnes.
    """
    h = np.asarray(histograms, np.float64)
    w = np.asarray(window_s, np.float64)
    d = np.asarray(drift_pp2_s, np.float64)
    if (h.ndim != 2 or h.shape[1] != BINS or w.shape != (h.shape[0],) or d.ndim != 1
            or (h < 0).any() or not np.isfinite(h).all() or (w < 0).any()):
        raise ValueError(f"histograms must be (K, {BINS}) >= 0, window_s (K,) >= 0 and "
                         f"drift_pp2_s (A,); got {h.shape}, {w.shape}, {d.shape}")
    total = h.sum(axis=1, keepdims=True)
    p = np.divide(h, total, out=np.zeros_like(h), where=total > 0)
    q = np.einsum("ki,ij,kj->k", p, _M, p) - 2 * p @ _C + 1.0 / 3.0
    q = np.where(total[:, 0] > 0, np.maximum(q, 0.0), 0.0)
    return (q * w)[:, None] * d[None, :]
