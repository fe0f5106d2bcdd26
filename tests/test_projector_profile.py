"""Tests of the projector's profile cleaning (projector.profile): what clean_profile keeps of
noise-free, noisy, stepped and grazing piles (rays cast by bisection onto a known surface),
the spikes and mixed pixels it removes, its line fit against np.polyfit, and above_ground;
every random test prints its seed (shown by pytest on failure, or with ``-s``) and
``--seed N`` (``STOCKPILE_TEST_SEED=N``) reruns it with the base seed N.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from projector.profile import above_ground, clean_profile
from projector_helpers import cast_profile, make_rng


#: the random tests here draw from the run's seed (tests/seeding.py)
pytestmark = pytest.mark.seeded


BEAMS = np.radians(np.arange(-50.0, 50.0001, 0.25))       # 401 beams


def smooth_pile(x):
    """A smooth pile (hyperbolic section, 35 deg flanks) on flat ground at z = 0."""
    m = math.tan(math.radians(35.0))
    return np.maximum(32.0 - np.sqrt(4.0 + (m * (x - 1.0)) ** 2), 0.0)


def sharp_pile(x):
    return np.maximum(17.4 - 0.564 * np.abs(x + 2.0), 0.0)


@pytest.mark.parametrize("surface", [smooth_pile, sharp_pile], ids=["smooth", "sharp crest"])
def test_clean_profile_keeps_a_noise_free_pile(surface):
    r = cast_profile(surface, 3.0, 45.0, BEAMS)[None, :]
    out = clean_profile(r)
    assert out.shape == r.shape
    assert np.isfinite(out).all(), np.flatnonzero(np.isnan(out))
    np.testing.assert_array_equal(out, r)
    # 3-median smoothing leaves the smooth flanks (monotone runs) as they are
    sm = clean_profile(r, smooth=True)
    changed = np.flatnonzero(sm[0] != r[0])
    assert changed.size <= 3                            # at most the crest and the toes


def test_clean_profile_keeps_a_noisy_smooth_pile_and_removes_spikes():
    rng = make_rng(4)
    base = cast_profile(smooth_pile, 3.0, 45.0, BEAMS)
    s = 200
    r = base[None, :] + rng.normal(0.0, 0.0145, (s, base.size))
    r[rng.random(r.shape) < 0.002] = np.nan               # dropouts
    out = clean_profile(r)
    lost = np.isfinite(r) & np.isnan(out)
    assert lost.mean() < 5e-4, lost.sum()                 # a smooth pile stays
    # plant isolated outliers (dust in front, multipath behind) away from dropouts, where
    # the surface is not seen edge-on: on a grazing flank the range changes by more than
    # a metre per beam, a -1 m error keeps the profile monotone and cannot be told from
    # the surface in range (its height error there is only ~0.1 m)
    spikes = np.zeros(r.shape, bool)
    seen_well = np.flatnonzero(np.convolve(np.abs(np.diff(base)) < 0.3, [1, 1], "valid") == 2) + 1
    seen_well = seen_well[(seen_well >= 5) & (seen_well < base.size - 5)]
    assert seen_well.size > 200
    cols = rng.choice(seen_well, s)
    spikes[np.arange(s), cols] = True
    spikes &= np.isfinite(r)
    spikes[:, 1:] &= np.isfinite(r[:, :-1])
    spikes[:, :-1] &= np.isfinite(r[:, 1:])
    planted = r.copy()
    planted[spikes] += np.where(rng.random(spikes.sum()) < 0.5, -1.0, 1.5)
    out = clean_profile(planted)
    assert np.isnan(out[spikes]).all()
    others = np.isfinite(planted) & ~spikes
    assert (np.isnan(out) & others).mean() < 1e-3
    np.testing.assert_array_equal(out[others & np.isfinite(out)],
                                  planted[others & np.isfinite(out)])


def test_clean_profile_removes_mixed_pixels_at_a_step():
    """A box (a stacker's bench, a wall) on the ground: phantom returns between the levels."""
    def box(x):
        return np.where(np.abs(x) < 8.0, 6.0, 0.0)

    r = cast_profile(box, 0.0, 30.0, BEAMS)
    # the edges: the last beam on the box top and the first on the ground (each side)
    top = np.abs(30.0 - r * np.cos(BEAMS) - 6.0) < 1e-6
    edges = np.flatnonzero(np.diff(top.astype(int)))     # step between edges[i] and +1
    assert edges.size == 2
    scans = np.tile(r, (4, 1))
    planted = np.zeros(scans.shape, bool)
    # scan 0: one phantom at the left edge; scan 1: two phantoms in a row at the right edge
    # (the beam hit the ground replaced), scan 2: one at each edge; scan 3: clean
    e0, e1 = edges
    for row, cols in ((0, [e0 + 1]), (1, [e1 + 1, e1 + 2]), (2, [e0 + 1, e1 + 1])):
        for c in cols:
            near = scans[row, e0] if c <= e0 + 2 else scans[row, e1]
            far = scans[row, c + 1] if c <= e0 + 2 else scans[row, e1 + 3]
            scans[row, c] = near + (0.35 + 0.1 * (c - cols[0])) * (far - near)
            planted[row, c] = True
    out = clean_profile(scans)
    assert np.isnan(out[planted]).all()
    assert np.isfinite(out[~planted]).all()               # the true edges survive


def test_clean_profile_keeps_a_grazing_surface():
    """A flank seen almost edge-on: big but steady range steps are not jumps."""
    beams = np.radians(np.arange(0.0, 47.0001, 0.25))
    r = cast_profile(lambda x: 30.0 - 0.7 * x, 0.0, 45.0, beams, t_max=400.0)[None, :]
    steps = np.abs(np.diff(r[0]))
    assert steps.max() > 2.0                               # far larger than jump_m
    out = clean_profile(r)
    assert np.isfinite(out).all()
    rng = make_rng(10)
    noisy = r + rng.normal(0.0, 0.0145, (50, r.shape[1]))
    assert np.isfinite(clean_profile(noisy)).all()


def _line_fit_by_polyfit(r: np.ndarray, half: int, jump_m: float) -> np.ndarray:
    """Brute force: per beam, np.polyfit of degree 1 through the kept returns within
    ``half`` beams that no step of more than ``jump_m`` separates from it."""
    out = r.copy()
    for s_i, row in enumerate(r):
        for b in range(row.size):
            if np.isnan(row[b]):
                continue
            ks = [0]
            for direction in (-1, 1):
                last = row[b]                  # the last kept return on this side
                for k in range(1, half + 1):
                    j = b + direction * k
                    if not 0 <= j < row.size:
                        break
                    if np.isnan(row[j]):       # a dropout: the window goes on past it
                        continue
                    if abs(row[j] - last) > jump_m:
                        break                  # a jump: nothing beyond it
                    ks.append(direction * k)
                    last = row[j]
            ks = sorted(ks)
            if len(ks) >= 2:
                out[s_i, b] = np.polyval(np.polyfit(ks, row[b + np.array(ks)], 1), 0.0)
    return out


@pytest.mark.parametrize("fit_beams", [3, 5])
def test_line_fit_of_profiles_matches_polyfit_and_never_crosses_a_jump(fit_beams):
    rng = make_rng(20 + fit_beams)
    print("seed offset", 20 + fit_beams)
    k = np.arange(200)
    # straight runs with steps of 2 m between them (jumps), noise, and dropouts
    r = 10.0 + 0.01 * k + 2.0 * (k >= 70) - 2.0 * (k >= 140)
    scans = np.tile(r, (6, 1)) + rng.normal(0.0, 0.005, (6, k.size))
    scans[rng.random(scans.shape) < 0.05] = np.nan
    out = clean_profile(scans, fit_beams=fit_beams, mad_k=50.0)   # no outlier rejection
    kept = clean_profile(scans, mad_k=50.0)
    # the level steps are the only steps over 0.3 m between kept returns, also where
    # a dropout lies on the step
    expected = _line_fit_by_polyfit(kept, fit_beams // 2, 0.3)
    np.testing.assert_allclose(out, expected, atol=1e-9)
    # no fitted return lies between the two levels (it would be a mixed pixel)
    level = np.abs(out - (10.0 + 0.01 * k + 2.0 * ((k >= 70) & (k < 140))))
    assert np.nanmax(level) < 0.05


def test_line_fit_of_profiles_keeps_a_straight_run_and_cuts_the_noise():
    rng = make_rng(30)
    k = np.arange(400)
    straight = np.tile(5.0 + 0.003 * k, (40, 1))
    np.testing.assert_allclose(clean_profile(straight, fit_beams=3), straight, atol=1e-12)
    noisy = straight + rng.normal(0.0, 0.0145, straight.shape)
    fitted = clean_profile(noisy, fit_beams=3)
    raw_sd = np.std((clean_profile(noisy) - straight)[:, 1:-1])
    fit_sd = np.std((fitted - straight)[:, 1:-1])
    assert fit_sd == pytest.approx(raw_sd / math.sqrt(3.0), rel=0.05)


def test_clean_profile_validates():
    with pytest.raises(ValueError, match=r"\(S, B\)"):
        clean_profile(np.ones(10))
    with pytest.raises(ValueError, match="odd"):
        clean_profile(np.ones((2, 10)), window=4)
    with pytest.raises(ValueError, match="fit_beams must be odd"):
        clean_profile(np.ones((2, 10)), fit_beams=2)
    r = np.ones((2, 10))
    out = clean_profile(r)
    assert out is not r and np.array_equal(out, r)


def test_above_ground():
    z = np.array([[0.0, 0.05, 0.2], [np.nan, -1.0, 3.0]])
    np.testing.assert_array_equal(above_ground(z, 0.0, 0.1),
                                  [[False, False, True], [False, False, True]])
    with pytest.raises(ValueError):
        above_ground(z, 0.0, -0.1)
