"""projector.window_drift: the belt's drift inside an assay window, against simulated walks.

The closed forms (covariances of a Brownian motion) are checked against random walks
drawn step by step, and the rate's estimator against windows of such a walk measured
with lab noise.  Random tests draw from the run's seed (``seed`` fixture, printed).
"""

from __future__ import annotations

import numpy as np
import pytest

from projector.uncertainty import grade_sd
from projector.window_drift import BINS, drift_rate_pp2_s, part_variance_pp2, window_histogram


def _walks(rng, draws: int, steps: int, rate: float, length_s: float) -> np.ndarray:
    """Random walks of ``rate`` (pp^2/s) sampled at ``steps`` midpoints of ``length_s``."""
    dt = length_s / steps
    return np.cumsum(rng.standard_normal((draws, steps)) * np.sqrt(rate * dt), axis=1)


@pytest.mark.parametrize("part", [(0.0, 1 / BINS), (0.25, 0.375), (0.5, 1.0), (0.0, 1.0)])
def test_part_variance_matches_random_walks(seed, part) -> None:
    rng = np.random.default_rng(seed)
    rate, width, steps = 0.01, 600.0, 512
    walks = _walks(rng, 20_000, steps, rate, width)
    t = (np.arange(steps) + 0.5) / steps
    lo, hi = part
    inside = (t >= lo) & (t < hi)
    deviation = walks[:, inside].mean(axis=1) - walks.mean(axis=1)
    hist = window_histogram(t[inside] * 1e9, np.ones(inside.sum()), 0, 1e9)
    analytic = part_variance_pp2(hist[None, :], np.array([width]), np.array([rate]))[0, 0]
    if hi - lo == 1.0:
        assert analytic == pytest.approx(0.0, abs=1e-12)
        return
    assert np.var(deviation) == pytest.approx(analytic, rel=0.05)


def test_a_point_sample_averages_a_sixth() -> None:
    # a point at a random place of the window strays D W / 6 on average; a sample spread
    # evenly over a bin of width h, D W (1 - h) / 6
    v = part_variance_pp2(np.eye(BINS), np.ones(BINS), np.array([1.0]))[:, 0]
    assert v.mean() == pytest.approx((1 - 1 / BINS) / 6, rel=1e-9)
    assert v[0] > v[BINS // 2]        # the ends stray farther from the mean than the middle


def test_drift_rate_recovers_the_walks_rate(seed) -> None:
    rng = np.random.default_rng(seed)
    rate, width, lab, windows = 0.01, 60.0, 0.15, 400
    steps_per = 32
    walk = _walks(rng, 1, windows * steps_per, rate, windows * width)[0]
    means = walk.reshape(windows, steps_per).mean(axis=1) + rng.normal(0, lab, windows)
    start = np.arange(windows) * width
    got = drift_rate_pp2_s(start, start + width, means[:, None], np.full((windows, 1), lab),
                           np.zeros(windows))
    # 399 pairs: the estimate's relative sd is about 12 %
    assert got[0] == pytest.approx(rate, rel=0.4)


def test_drift_rate_pairs_stay_within_a_lot_and_lag() -> None:
    start = np.array([0.0, 60.0, 120.0, 1e6])
    grade = np.array([[60.0], [61.0], [60.0], [50.0]])
    lab = np.zeros((4, 1))
    one_lot = drift_rate_pp2_s(start, start + 60, grade, lab, np.array(["A", "A", "B", "B"]))
    # only the pair (0, 60) is one lot; (120, 1e6) are too far apart
    assert one_lot[0] == pytest.approx(1.0 / (60 - 20))
    assert np.isnan(drift_rate_pp2_s(start[:1], start[:1] + 60, grade[:1], lab[:1],
                                     np.array(["A"])))[0]
    noisy = drift_rate_pp2_s(start[:2], start[:2] + 60, grade[:2], np.full((2, 1), 5.0),
                             np.array(["A", "A"]))
    assert noisy[0] == 0.0             # the lab's errors explain the difference


def test_bad_shapes_raise() -> None:
    with pytest.raises(ValueError):
        drift_rate_pp2_s([0.0], [1.0, 2.0], [[1.0]], [[0.1]], ["A"])
    with pytest.raises(ValueError):
        part_variance_pp2(np.ones((2, BINS - 1)), np.ones(2), np.ones(1))
    with pytest.raises(ValueError):
        window_histogram([1, 2], [1.0], 0, 10)


def test_grade_sd_adds_the_drift_to_assayed_groups_only() -> None:
    tonnes, group, assayed = [1.0, 1.0], [0, 1], [True, False]
    base = grade_sd(tonnes, group, assayed, [0.15], [2.0])
    drift = np.array([[0.04], [9.0]])          # the planned group's row is ignored
    got = grade_sd(tonnes, group, assayed, [0.15], [2.0], drift_var_pp2=drift)
    assert got[0] == pytest.approx(np.sqrt(base[0] ** 2 + 0.04 / 4))
    with pytest.raises(ValueError):
        grade_sd(tonnes, group, assayed, [0.15], [2.0], drift_var_pp2=np.ones((1, 1)))
