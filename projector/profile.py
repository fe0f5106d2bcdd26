"""Cleaning of 2-D laser profiles before they are georeferenced, and pile/ground separation.

A profile is one scan: B ranges along the beam index (the LaserScan convention of
:mod:`projector.georef`), NaN = no return.  Every test here works along the beam
index of each scan independently, vectorised over all scans at once.

What is rejected (set to NaN), and why
--------------------------------------
1. **Range discontinuities: mixed pixels and spikes.**  The LMS200's beam footprint can
   straddle the edge of a near and a far surface and return a range in between
   ("phantom" points, thesis §3.4, docs/domain.md §5).  Such a return sits on neither surface.
   A step between beams ``k`` and ``k + 1`` is a *jump* when

       |r[k+1] - r[k]| > max(jump_m, jump_ratio * s_k)

   where ``s_k`` is the running median of ``|r[j+1] - r[j]|`` over ``window`` steps
   around ``k`` (the local range change per beam).  The relative test keeps a smooth
   surface seen at grazing incidence, where the range changes a lot from beam to beam
   but steadily (every step is large, so none is a jump).  A *run* of one or two returns
   bounded by jumps on both sides is then

   - a **mixed pixel** when both jumps go the same way (near -> run -> far, or back): the
     run lies between the two surfaces;
   - a **spike** when they go opposite ways (the run stands in front of or behind both
     neighbours): dust, a bird, a multipath return.

   Both are removed.  A mixed pixel lying within ``jump_m`` of one of the surfaces
   cannot be told from that surface by its range and is kept (its error is < ``jump_m``
   and it lies at the edge).  Returns next to a NaN are not tested against it (no
   jump is defined across a missing return).

2. **Isolated outliers.**  The residual from a running median of ``window`` beams,
   ``res = r - median_w(r)``, is compared with a robust noise scale per scan,
   ``sigma = max(1.4826 * median(|r[b+1] - 2 r[b] + r[b-1]|) / sqrt(6), min_sd_m)`` (the
   MAD of second differences, whose noise sd is sqrt(6) sigma; ``min_sd_m`` keeps a
   noise-free scan from having a zero scale).  On a straight or smooth profile the
   running median of a monotone run is its centre value, so the residual is just noise;
   but at a *sharp* apex (the crest of a triangular pile: a V in range) the median of a
   window is about ``ceil(h/2)`` beams' range change away from the apex (h = window // 2),
   which is not noise.  So a return is an outlier only when it is also off both *linear
   continuations* of the profile, from the left ``2 r[b-1] - r[b-2]`` and from the right
   ``2 r[b+1] - r[b+2]``:

       |res| > mad_k * sigma   and   min(|r - L|, |r - R|) > mad_k * sqrt(6) * sigma

   (sqrt(6) sigma is the noise sd of ``r - L``).  An apex, a toe or any kink lies on the
   continuation of at least one side; a spike lies on neither.  A continuation that
   needs a missing return is not available; with neither available only the median
   test applies.  Limitation: on a surface seen almost edge-on the range changes by
   more than a metre per beam; an error smaller than that step keeps the profile
   monotone and cannot be told from the surface in range (its height error is only the
   range error times the sine of the grazing angle).

3. **Optional light smoothing** (``smooth=True``): a 3-beam median along the beam index,
   applied after the rejections (NaN neighbours are ignored).  A 3-median leaves every
   monotone run and every step exactly as it is (it does not blur edges or flatten a
   slope) and removes one-beam wiggles.  It does lower a one-beam *sharp* apex by at
   most one beam's range change, so it is off by default: the height fusion averages
   noise anyway.

4. **Optional line fit** (``fit_beams`` > 1; the fold uses 3): each kept return is
   replaced by the value at its beam of the least-squares line through the kept
   returns within ``fit_beams // 2`` beams on either side, never across a jump of
   test 1 nor any step over ``jump_m`` between two kept returns (with missing returns
   beside a step the relative test can miss it; a steady grazing run with larger
   steps then goes unfitted, which costs nothing).

   - A straight run of the profile (a planar flank) is left exactly as it is.
   - The range noise of each return drops, to sd/sqrt(3) for 3 beams.
   - No return is averaged with the far side of an edge (that would make a mixed
     pixel).
   - A sharp apex (a crest seen as a V in range) moves by two thirds of one beam's
     range change for 3 beams.

   The fusion averages the height noise of the points in a cell, but not the spread of
   a point along its beam over neighbouring cells, which the fit reduces (see
   docs/design-notes.md).

5. **Returns mixed on a grazing run** (``grazing_frac`` > 0; the fold uses
   ``FoldConfig.grazing_mixed_frac``).  Where the range changes by more than ``jump_m``
   from one beam to the next but steadily (a flank or the ground seen at grazing
   incidence, which test 1 keeps), a beam's footprint spans its neighbours' ranges, and
   a mixed return lies between its own range and that of the neighbour across the larger
   step (usually the farther one: the steps grow away from the scanner, and such a
   return lies below the surface, carried along its beam past it).  It lies beyond the
   midpoint of its two neighbours toward that neighbour; an unmixed return lies short of
   the midpoint (by half the growth of the step).  So a return of a monotone run,
   neither of whose steps is a jump of test 1 and one of which is over ``jump_m``, is
   removed when it lies beyond the midpoint of its neighbours, toward the side of the
   larger step, by more than ``grazing_frac`` times their mean step (and more than
   ``mad_k * min_sd_m``, the noise).  Which side's step is larger is judged by the mean
   step over the 8 beams beyond each neighbour, which the mixing of any one return
   changes little (where those beams are missing: the farther side).  The test uses the
   ranges as they came, before the other rejections.  Why: docs/fidelity.md, "The
   pile's volume".

The running medians treat NaN returns by carrying the nearest earlier valid return
into them (then the nearest later one at the start of a scan) before filtering; that
only changes the medians next to dropouts, never a return's own value.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage

__all__ = ["clean_profile", "above_ground"]

_MAD_TO_SD = 1.482602218505602   # 1 / Phi^-1(3/4): MAD -> sd for Gaussian noise


def _fill_nan_along_beams(a: np.ndarray) -> np.ndarray:
    """Carry the last valid value forward along axis 1 (then backward at the start).

    All-NaN rows stay NaN.  Vectorised (index accumulation), no loop over beams.
    """
    valid = ~np.isnan(a)
    if valid.all():
        return a
    n = a.shape[1]
    idx = np.where(valid, np.arange(n), 0)
    np.maximum.accumulate(idx, axis=1, out=idx)
    filled = np.take_along_axis(a, idx, axis=1)
    # leading NaNs (before the first valid value): take the first valid value
    first = np.argmax(valid, axis=1)
    lead = np.isnan(filled)
    if lead.any():
        filled = np.where(lead, np.take_along_axis(a, first[:, None], axis=1), filled)
    return filled


def _running_median(a: np.ndarray, window: int) -> np.ndarray:
    """Running median along axis 1 (centred, edge-replicated), NaNs filled first."""
    f = _fill_nan_along_beams(a)
    nan_rows = np.isnan(f)
    if nan_rows.any():                         # all-NaN rows: keep them NaN
        f = np.where(nan_rows, 0.0, f)
    out = ndimage.median_filter(f, size=(1, window), mode="nearest")
    if nan_rows.any():
        out[nan_rows] = np.nan
    return out


def _median_rows(a: np.ndarray) -> np.ndarray:
    """NaN-ignoring median of each row of a 2-D array (NaN for all-NaN rows)."""
    s = np.sort(a, axis=1)                     # NaNs sort last
    k = np.count_nonzero(~np.isnan(a), axis=1)
    lo = np.maximum((k - 1) // 2, 0)
    hi = np.maximum(k // 2, 0)
    hi = np.minimum(hi, a.shape[1] - 1)
    rows = np.arange(a.shape[0])
    med = 0.5 * (s[rows, lo] + s[rows, hi])
    med[k == 0] = np.nan
    return med


def clean_profile(ranges_m, *, jump_m: float = 0.3, jump_ratio: float = 4.0,
                  mad_k: float = 5.0, window: int = 7, min_sd_m: float = 0.01,
                  smooth: bool = False, fit_beams: int = 1,
                  grazing_frac: float = 0.0) -> np.ndarray:
    """Reject mixed pixels, spikes and isolated outliers of laser profiles.

    See the module docstring for the tests and their rationale.

    Parameters
    ----------
    ranges_m : array_like, shape (S, B)
        Ranges (m) of S scans of B beams, beam index = bearing order; NaN = no return.
    jump_m : float
        Smallest range step between adjacent beams that counts as a discontinuity (m).
        Keep it several times the range noise sd (the LMS200's 0.3 m default here is
        about 15 sd of its 14.5 mm noise at full scale).
    jump_ratio : float
        A step must also exceed ``jump_ratio`` times the local typical step (running
        median of ``|diff|``) to be a jump, so grazing-incidence surfaces are kept.
    mad_k : float
        Outlier threshold in robust standard deviations.
    window : int
        Beams in the running medians; odd, >= 3.
    min_sd_m : float
        Floor of the robust noise scale (m), e.g. the range resolution.
    smooth : bool
        Apply a 3-beam median after the rejections (off by default).
    fit_beams : int
        Odd, >= 1.  After the rejections (and the median), each return becomes the
        value at its own beam of the least-squares line through the kept returns within
        ``fit_beams // 2`` beams on either side, never across a jump (section 4 of the
        module docstring); 1 (default) leaves the returns as they are.
    grazing_frac : float
        >= 0.  Remove returns of a grazing run that lie beyond the midpoint of their
        neighbours, toward the larger step, by more than this fraction of their mean
        step (section 5 of the module docstring); 0 (default) keeps them.

    Returns
    -------
    ndarray, shape (S, B)
        A new array: the ranges with rejected returns set to NaN (and smoothed when
        ``smooth``).  Existing NaNs stay NaN.

    Raises
    ------
    ValueError
        On a non-2-D input or invalid parameters.
    """
    r = np.array(ranges_m, dtype=np.float64)   # a copy: the input is never modified
    if r.ndim != 2:
        raise ValueError(f"ranges_m must have shape (S, B) (scans, beams), got {r.shape}")
    window = int(window)
    if window < 3 or window % 2 == 0:
        raise ValueError(f"window must be odd and >= 3, got {window}")
    if not (jump_m > 0 and jump_ratio > 0 and mad_k > 0 and min_sd_m >= 0):
        raise ValueError("jump_m, jump_ratio, mad_k must be > 0 and min_sd_m >= 0")
    if not (math.isfinite(grazing_frac) and grazing_frac >= 0):
        raise ValueError(f"grazing_frac must be finite and >= 0, got {grazing_frac}")
    fit_beams = int(fit_beams)
    if fit_beams < 1 or fit_beams % 2 == 0:
        raise ValueError(f"fit_beams must be odd and >= 1, got {fit_beams}")
    s, b = r.shape
    if s == 0 or b < 3:
        return r
    d = np.diff(r, axis=1)                              # (S, B-1); NaN next to a NaN
    # 1. jumps: mixed pixels and spikes; 2. isolated outliers
    jump = _jumps(d, window, jump_m, jump_ratio)
    bad = _runs_between_jumps(jump) | _isolated_outliers(r, d, window, mad_k, min_sd_m)
    if grazing_frac > 0:                                # 5. pulled on a grazing run
        bad |= _pulled_on_grazing_run(r, d, jump, jump_m, grazing_frac, mad_k * min_sd_m)
    r[bad] = np.nan
    if smooth:                                          # 3. optional 3-median
        r = _median_of_3(r)
    if fit_beams > 1:                                   # 4. optional line fit
        # never across a jump, nor a step over jump_m between consecutive kept returns:
        # dropouts beside a step fill the running median of the steps with it, so that
        # the relative test of a jump can miss it
        kept_steps = np.abs(np.diff(_fill_nan_along_beams(r), axis=1))
        with np.errstate(invalid="ignore"):
            edges = jump | (kept_steps > jump_m)
        r = _line_fit_along_beams(r, edges, fit_beams // 2)
    return r


def _jumps(d: np.ndarray, window: int, jump_m: float, jump_ratio: float) -> np.ndarray:
    """Which steps ``d`` (m, shape (S, B-1), ``r[:, k+1] - r[:, k]``) are jumps: over
    ``jump_m`` and over ``jump_ratio`` times the running median of the step sizes over
    ``window`` steps; False next to a NaN."""
    ad = np.abs(d)
    step = _running_median(ad, window)                  # local typical step per beam
    with np.errstate(invalid="ignore"):
        return ad > np.maximum(jump_m, jump_ratio * step)   # NaN -> False


def _runs_between_jumps(jump: np.ndarray) -> np.ndarray:
    """Which returns (bool, shape (S, B)) form a run of one or two bounded by jumps on
    both sides (``jump``: bool, shape (S, B-1)): mixed pixels (both jumps the same way)
    and spikes (opposite ways)."""
    s, b = jump.shape[0], jump.shape[1] + 1
    bad = np.zeros((s, b), dtype=bool)
    # run of one return at beam i (1 <= i <= B-2): jumps at steps i-1 and i
    j_in, j_out = jump[:, :-1], jump[:, 1:]
    bad[:, 1:-1] |= j_in & j_out     # same direction: mixed pixel; opposite: spike
    # run of two returns at beams i, i+1 (1 <= i <= B-3): jumps at steps i-1 and i+1,
    # no jump inside the run
    if b >= 4:
        pair = jump[:, :-2] & ~jump[:, 1:-1] & jump[:, 2:]
        bad[:, 1:-2] |= pair
        bad[:, 2:-1] |= pair
    return bad


def _isolated_outliers(r: np.ndarray, d: np.ndarray, window: int, mad_k: float,
                       min_sd_m: float) -> np.ndarray:
    """Which returns (bool, shape (S, B)) are far from the running median of ``window``
    beams and off both linear continuations of the profile, in robust sd (test 2 of the
    module docstring); ``r`` ranges (m, shape (S, B)), ``d`` their steps (m, (S, B-1))."""
    s, b = r.shape
    med = _running_median(r, window)
    res = r - med
    # noise scale from second differences (sd sqrt(6) sigma for white noise; a smooth
    # profile adds little): the MAD of the median residuals would collapse to 0 wherever
    # the range changes by more than the noise per beam (a monotone run is its own median)
    d2 = np.full((s, b), np.nan)
    d2[:, 1:-1] = d[:, 1:] - d[:, :-1]
    sigma = _MAD_TO_SD * _median_rows(np.abs(d2)) / math.sqrt(6.0)           # (S,)
    sigma = np.where(np.isnan(sigma), min_sd_m, np.maximum(sigma, min_sd_m))[:, None]
    # linear continuations from the left and from the right (NaN where unavailable)
    left = np.full((s, b), np.nan)
    right = np.full((s, b), np.nan)
    left[:, 2:] = 2.0 * r[:, 1:-1] - r[:, :-2]
    right[:, :-2] = 2.0 * r[:, 1:-1] - r[:, 2:]
    off_line = np.fmin(np.abs(r - left), np.abs(r - right))   # NaN only if both missing
    with np.errstate(invalid="ignore"):
        far = np.abs(res) > mad_k * sigma
        unexplained = ~(off_line <= mad_k * math.sqrt(6.0) * sigma)     # NaN -> True
        return far & unexplained


#: beams over which test 5 judges which side of a return has the larger step
_GRAZING_SPAN = 8


def _pulled_on_grazing_run(r: np.ndarray, d: np.ndarray, jump: np.ndarray, jump_m: float,
                           frac: float, floor_m: float) -> np.ndarray:
    """Which returns (bool, shape (S, B)) of a grazing run lie beyond the midpoint of their
    two neighbours, toward the larger step, by more than ``frac`` times the mean of their
    two steps and more than ``floor_m`` (test 5 of the module docstring); ``d`` the steps
    of ``r`` (m, (S, B-1)), ``jump`` the jumps of test 1."""
    bad = np.zeros(r.shape, dtype=bool)
    s, b = r.shape
    if b < 3:
        return bad
    left, right = d[:, :-1], d[:, 1:]                    # steps into and out of beam i
    # the larger step beside beam i, judged by the mean step over the _GRAZING_SPAN
    # beams beyond each neighbour (from beam i-1-n to i-1 and from i+1 to i+1+n: a
    # mixed return moves one step at most, which a span's mean divides by n); where a
    # span is missing (the scan's end, a dropout), the farther neighbour's
    n = _GRAZING_SPAN
    outer_l = np.full((s, b - 2), np.nan)
    outer_r = np.full((s, b - 2), np.nan)
    if b - 2 > n:
        outer_l[:, n:] = np.abs(r[:, n:b - 2] - r[:, :b - 2 - n]) / n    # r[i-1] - r[i-1-n]
        outer_r[:, :-n] = np.abs(r[:, 2 + n:] - r[:, 2:b - n]) / n      # r[i+1+n] - r[i+1]
    with np.errstate(invalid="ignore"):                 # NaN -> False
        known = np.isfinite(outer_l) & np.isfinite(outer_r)
        # +1 where that neighbour's range is larger than beam i's, -1 where smaller;
        # unknown: the farther neighbour's (+1), the steps grow away from the scanner
        toward = np.where(known, np.where(outer_r >= outer_l, np.sign(right), -np.sign(left)),
                          1.0)
        grazing = ((np.fmax(np.abs(left), np.abs(right)) > jump_m)
                   & (np.sign(left) == np.sign(right)) & ~jump[:, :-1] & ~jump[:, 1:])
        excess = (r[:, 1:-1] - 0.5 * (r[:, :-2] + r[:, 2:])) * toward
        limit = np.maximum(frac * 0.5 * (np.abs(left) + np.abs(right)), floor_m)
        bad[:, 1:-1] = grazing & (excess > limit)
    return bad


def _median_of_3(r: np.ndarray) -> np.ndarray:
    """3-beam median along axis 1 where a return and both neighbours are there; the
    other returns (and NaNs) as they are."""
    left = np.empty_like(r)
    right = np.empty_like(r)
    left[:, 0] = np.nan
    left[:, 1:] = r[:, :-1]
    right[:, -1] = np.nan
    right[:, :-1] = r[:, 1:]
    both = ~np.isnan(left) & ~np.isnan(right) & ~np.isnan(r)
    trio = np.stack([left, r, right], axis=-1)
    m3 = np.median(np.where(both[..., None], trio, 0.0), axis=-1)
    return np.where(both, m3, r)


def _line_fit_along_beams(r: np.ndarray, jump: np.ndarray, half: int) -> np.ndarray:
    """Each return's value on the least-squares line through the returns within ``half``
    beams of it on the same side of every jump (``jump[:, i]``: a jump between beams
    ``i`` and ``i + 1``); NaN stays NaN.  The window sums (of 1, k, k^2, r, k r over the
    offsets k) are accumulated offset by offset, vectorised over scans and beams."""
    s, b = r.shape
    ok = ~np.isnan(r)
    z = np.where(ok, r, 0.0)
    side = np.zeros((s, b), np.int64)          # how many jumps lie before each beam
    np.cumsum(jump, axis=1, out=side[:, 1:])
    s0, s1, s2, sr, skr = (np.zeros((s, b)) for _ in range(5))
    for k in range(-half, half + 1):
        lo, hi = max(0, -k), min(b, b - k)     # centres whose neighbour lo+k.. exists
        if lo >= hi:
            continue
        w = (ok[:, lo + k:hi + k] & ok[:, lo:hi]
             & (side[:, lo + k:hi + k] == side[:, lo:hi])).astype(np.float64)
        rk = z[:, lo + k:hi + k] * w
        s0[:, lo:hi] += w
        s1[:, lo:hi] += k * w
        s2[:, lo:hi] += k * k * w
        sr[:, lo:hi] += rk
        skr[:, lo:hi] += k * rk
    det = s0 * s2 - s1 * s1
    with np.errstate(invalid="ignore", divide="ignore"):
        # a lone return (det 0: no neighbour on its side of the jumps) keeps its value
        fit = np.where(det > 0.5, (s2 * sr - s1 * skr) / det, r)
    return np.where(ok, fit, np.nan)


def above_ground(z_m, ground_z_m: float, tolerance_m: float) -> np.ndarray:
    """Which points belong to the pile rather than to the ground.

    Parameters
    ----------
    z_m : array_like, any shape
        Site heights (m); NaN = no point.
    ground_z_m : float
        The pile's declared ground level (m, ``PileDeclared.ground_z_m``).
    tolerance_m : float
        Margin above the ground (m, >= 0), e.g. 3 sd of the height noise plus the
        ground's unevenness: points within it are ground.

    Returns
    -------
    ndarray of bool, same shape as ``z_m``
        ``z > ground_z_m + tolerance_m``; False for NaN.
    """
    if not (math.isfinite(ground_z_m) and math.isfinite(tolerance_m) and tolerance_m >= 0):
        raise ValueError("ground_z_m must be finite and tolerance_m finite and >= 0")
    z = np.asarray(z_m, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        return z > ground_z_m + tolerance_m
