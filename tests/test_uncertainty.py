"""projector.uncertainty: each kernel against Monte Carlo draws of the same error model.

The draws form each error explicitly (per cell, per block, per assay window, per
boundary) and recompute the figure from the perturbed inputs; the kernels use closed
forms.  Random tests draw from the run's seed (``seed`` fixture, printed).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from projector.uncertainty import (
    UncertaintyConfig,
    VolumeVariance,
    boundary_band_thickness_m,
    density_rel_sd,
    figure_sd,
    grade_sd,
    tonnes_sd,
    volume_variance,
    weighted_mean_sd,
)

DRAWS = 20_000
REL_TOL = 0.03     # the sd of a 20,000-draw sample sd is 0.5 % of it: 3 % is 6 sigma


def _close(mc_sd, analytic_sd) -> None:
    assert np.all(np.abs(np.asarray(mc_sd) / np.asarray(analytic_sd) - 1.0) < REL_TOL), \
        (mc_sd, analytic_sd)


# -- volume ----------------------------------------------------------------------------------


def _volume_draws(rng, var, mask, area, bx, by, share, prior, draws=DRAWS):
    """Volume errors (m^3) of ``draws`` fields of the model, formed cell by cell."""
    nx, ny = var.shape
    blocks = {}
    for ix in range(nx):
        for iy in range(ny):
            blocks.setdefault((ix // bx, iy // by), []).append((ix, iy))
    out = np.zeros(draws)
    for cells in blocks.values():
        shared_seen = rng.standard_normal(draws)
        shared_unseen = rng.standard_normal(draws)
        for ix, iy in cells:
            if not mask[ix, iy]:
                continue
            if math.isnan(var[ix, iy]):
                out += area * prior * shared_unseen
            else:
                s = math.sqrt(var[ix, iy])
                own = rng.standard_normal(draws)
                out += area * s * (math.sqrt(1 - share) * own + math.sqrt(share) * shared_seen)
    return out


@pytest.mark.parametrize("share, cells", [(0.0, 1), (0.4, (5, 4)), (1.0, 6)])
def test_volume_sd_matches_monte_carlo(seed, share, cells):
    rng = np.random.default_rng([seed, 1])
    var = rng.uniform(0.0004, 0.01, (17, 13))
    var[rng.random(var.shape) < 0.15] = np.nan
    mask = rng.random(var.shape) < 0.8
    bx, by = (cells, cells) if np.ndim(cells) == 0 else cells
    got = volume_variance(var, mask, 0.25, corr_cells=cells, corr_share=share, unseen_sd_m=0.3)
    errors = _volume_draws(rng, var, mask, 0.25, bx, by, share, 0.3)
    _close(errors.std(), got.sd_m3)
    assert got.unseen_cells == int((mask & np.isnan(var)).sum()) > 0
    assert got.cells == int(mask.sum())


def test_volume_zero_variance_gives_zero_sd():
    var = np.zeros((8, 9))
    got = volume_variance(var, np.ones((8, 9), bool), 1.0, corr_cells=3, corr_share=0.7)
    assert got.sd_m3 == 0.0 and got.unseen_cells == 0 and got.cells == 72


def test_volume_empty_region_gives_zero():
    got = volume_variance(np.full((4, 4), 0.01), np.zeros((4, 4), bool), 1.0)
    assert got == VolumeVariance(0.0, 0.0, 0.0, 0, 0)


def test_volume_all_never_seen():
    var = np.full((6, 6), np.nan)
    mask = np.ones((6, 6), bool)
    one_block = volume_variance(var, mask, 2.0, corr_cells=6, unseen_sd_m=0.5)
    assert one_block.unseen_cells == 36
    assert one_block.sd_m3 == pytest.approx(2.0 * 36 * 0.5)       # one shared guess
    per_cell = volume_variance(var, mask, 2.0, corr_cells=1, unseen_sd_m=0.5)
    assert per_cell.sd_m3 == pytest.approx(2.0 * 0.5 * 6.0)       # sqrt(36) independent
    assert one_block.independent_m6 == one_block.correlated_m6 == 0.0


def test_volume_independent_cells_add_variances():
    var = np.arange(1, 13, dtype=float).reshape(3, 4) * 1e-3
    got = volume_variance(var, np.ones((3, 4), bool), 0.5, corr_cells=1, corr_share=0.3)
    assert got.variance_m6 == pytest.approx(0.25 * var.sum())


def test_two_surveys_add():
    a = VolumeVariance(1.0, 2.0, 3.0, 4, 10)
    b = VolumeVariance(0.5, 0.25, 0.125, 1, 10)
    both = a.plus(b)
    assert both.variance_m6 == pytest.approx(a.variance_m6 + b.variance_m6)
    assert both.unseen_cells == 5 and both.cells == 10


# -- tonnes ----------------------------------------------------------------------------------


def test_tonnes_sd_matches_monte_carlo(seed):
    rng = np.random.default_rng([seed, 2])
    volume, sd_v, density, rel, sd_res = 1200.0, 25.0, 2.4, 0.02, 12.0
    v = volume + sd_v * rng.standard_normal(DRAWS) + sd_res * rng.standard_normal(DRAWS)
    rho = density * (1.0 + rel * rng.standard_normal(DRAWS))
    _close((v * rho).std(), tonnes_sd(volume, sd_v, density, rel, sd_res))


def test_tonnes_sd_zero_errors():
    assert tonnes_sd(500.0, 0.0, 2.4, 0.0) == 0.0


# -- tonnage-weighted means ------------------------------------------------------------------


def test_weighted_mean_sd_matches_monte_carlo(seed):
    rng = np.random.default_rng([seed, 3])
    tonnes = rng.uniform(1.0, 50.0, 40)
    group = rng.integers(0, 7, 40)
    sd = rng.uniform(0.05, 1.0, (7, 3))
    errors = rng.standard_normal((DRAWS, 7, 3)) * sd
    means = np.einsum("i,dia->da", tonnes, errors[:, group, :]) / tonnes.sum()
    _close(means.std(axis=0), weighted_mean_sd(tonnes, group, sd))


def test_weighted_mean_sd_scales_as_one_over_sqrt_n():
    for n in (1, 4, 25):
        tonnes = np.full(n, 10.0)
        many = weighted_mean_sd(tonnes, np.arange(n), np.full(n, 0.3))
        one = weighted_mean_sd(tonnes, np.zeros(n, np.int64), np.full(1, 0.3))
        assert float(many) == pytest.approx(0.3 / math.sqrt(n))
        assert float(one) == pytest.approx(0.3)


def test_weighted_mean_sd_ignores_unknown_sd_of_an_empty_group():
    got = weighted_mean_sd([1.0, 3.0], [0, 0], [0.2, np.nan])
    assert float(got) == pytest.approx(0.2)
    assert math.isnan(float(weighted_mean_sd([1.0, 3.0], [0, 1], [0.2, np.nan])))


def test_no_pieces_give_zero_sd():
    assert float(weighted_mean_sd([], [], [0.1])) == 0.0
    assert grade_sd([], [], [], [0.1, 0.2], [0.5, 0.6]).tolist() == [0.0, 0.0]
    assert density_rel_sd([], [], [], 0.01, 0.05) == 0.0


def test_density_rel_sd_matches_monte_carlo(seed):
    rng = np.random.default_rng([seed, 4])
    tonnes = rng.uniform(5.0, 30.0, 30)
    window = rng.integers(0, 6, 30)
    reported = rng.random(30) < 0.6
    density = 2.4
    own = rng.standard_normal((DRAWS, 6)) * 0.01
    shared = rng.standard_normal(DRAWS) * 0.05
    rho = density * (1.0 + np.where(reported, own[:, window], shared[:, None]))
    mean = (rho * tonnes).sum(axis=1) / tonnes.sum()
    _close(mean.std() / density, density_rel_sd(tonnes, window, reported, 0.01, 0.05))


# -- grade -----------------------------------------------------------------------------------


def test_boundary_band_thickness_against_sampling(seed):
    rng = np.random.default_rng([seed, 5])
    lo = rng.uniform(0.0, 1.0, 50)
    z = lo + rng.uniform(0.0, 0.6, 50)
    hi = z + rng.uniform(0.0, 0.6, 50)
    got = boundary_band_thickness_m(lo, z, hi, 0.25)
    grid = np.linspace(-1.0, 3.0, 400_001)
    step = grid[1] - grid[0]
    for i in range(50):
        inside = (grid > lo[i]) & (grid <= hi[i]) & (np.abs(grid - z[i]) <= 0.25)
        assert got[i] == pytest.approx(inside.sum() * step, abs=2 * step)


def _grade_draws(rng, tonnes, grades, group, sd_by_group, band, diff_lo_hi, draws=DRAWS):
    """Mixture grades recomputed from perturbed pieces: each group's error, each boundary's
    true position uniform in the band (tonnes moved between its two band pieces)."""
    k, n_a = sd_by_group.shape
    out = np.empty((draws, n_a))
    for d in range(draws):
        g = grades + rng.standard_normal((k, n_a))[group] * sd_by_group[group]
        t = tonnes.copy()
        for (i_lo, i_hi), t_band in band:
            moved = rng.uniform(-0.5, 0.5) * t_band      # to the lower lot when > 0
            t[i_lo] += moved
            t[i_hi] -= moved
        out[d] = t @ g / t.sum()
    return out


def test_grade_sd_matches_monte_carlo(seed):
    rng = np.random.default_rng([seed, 6])
    n, n_a = 12, 2
    tonnes = rng.uniform(20.0, 80.0, n)
    tonnes[10:12] = tonnes[8:10]     # each boundary's band: as much below as above
    grades = rng.uniform(50.0, 64.0, (n, n_a))
    group = np.array([0, 0, 1, 2, 2, 3, 4, 4, 5, 5, 6, 6])
    assayed = group < 4
    lab, planned = np.array([0.15, 0.08]), np.array([0.5, 0.3])
    # two boundaries: pieces (8, 9) are lot 5's lower band and (10, 11) lot 6's upper one
    band = [((8, 10), tonnes[8] + tonnes[10]), ((9, 11), tonnes[9] + tonnes[11])]
    diff = np.array([grades[10] - grades[8], grades[11] - grades[9]])
    got = grade_sd(tonnes, group, assayed, lab, planned, [b for _, b in band], diff)
    sd_by_group = np.where((np.arange(7) < 4)[:, None], lab, planned)
    base = tonnes @ grades / tonnes.sum()
    draws = _grade_draws(rng, tonnes, grades, group, sd_by_group, band, diff, draws=DRAWS)
    assert np.allclose(draws.mean(axis=0), base, atol=0.05)
    # the draws also hold the second-order product the kernel leaves out (first order):
    # a band's moved tonnes (variance t_b^2 / 12) times its two pieces' grade errors
    # (independent groups), over the mixture's tonnes squared
    product_var = sum(t_b ** 2 / 12.0 * (sd_by_group[group[lo]] ** 2 + sd_by_group[group[hi]] ** 2)
                      for (lo, hi), t_b in band) / tonnes.sum() ** 2
    _close(draws.std(axis=0), np.sqrt(np.asarray(got) ** 2 + product_var))


def test_grade_sd_limits():
    tonnes = np.full(9, 10.0)
    lab, planned = np.array([0.2]), np.array([1.0])
    one = grade_sd(tonnes, np.zeros(9, np.int64), np.ones(9, bool), lab, planned)
    many = grade_sd(tonnes, np.arange(9), np.ones(9, bool), lab, planned)
    assert one[0] == pytest.approx(0.2) and many[0] == pytest.approx(0.2 / 3)
    planned_only = grade_sd(tonnes, np.zeros(9, np.int64), np.zeros(9, bool), lab, planned)
    assert planned_only[0] == pytest.approx(1.0)
    zero = grade_sd(tonnes, np.arange(9), np.ones(9, bool), [0.0], [0.0], [20.0], [[0.0]])
    assert zero[0] == 0.0
    # the whole mixture in one band: sd = |diff| / (2 sqrt 3)
    band = grade_sd(tonnes, np.arange(9), np.ones(9, bool), [0.0], [0.0], [90.0], [[3.0]])
    assert band[0] == pytest.approx(3.0 / (2 * math.sqrt(3)))


def test_grade_sd_unknown_lab_sd_is_nan_only_where_needed():
    tonnes = np.array([10.0, 10.0])
    got = grade_sd(tonnes, [0, 1], [False, False], [np.nan, 0.1], [0.5, 0.2])
    assert got[0] == pytest.approx(0.5 / math.sqrt(2))
    assert got[1] == pytest.approx(0.2 / math.sqrt(2))
    assert math.isnan(grade_sd(tonnes, [0, 1], [True, False], [np.nan, 0.1], [0.5, 0.2])[0])


# -- the figure ------------------------------------------------------------------------------


def test_figure_sd_matches_monte_carlo(seed):
    rng = np.random.default_rng([seed, 7])
    config = UncertaintyConfig(corr_cells=4, corr_share=0.5, unseen_sd_m=0.2,
                               residual_sd_share=0.5)
    var = rng.uniform(0.001, 0.004, (12, 10))
    var[:2, :3] = np.nan
    mask = np.ones(var.shape, bool)
    area, volume = 1.0, 300.0
    tonnes = rng.uniform(50.0, 100.0, 6)
    group = np.array([0, 1, 2, 3, 4, 4])
    assayed = np.array([True, True, True, False, False, False])
    reported = np.array([True, False, True, False, False, False])
    vv = volume_variance(var, mask, area, corr_cells=4, corr_share=0.5, unseen_sd_m=0.2)
    got = figure_sd(config, ("Fe", "Xx"), volume=vv, volume_m3=volume, tonnes=tonnes,
                    group=group, assayed=assayed, density_reported=reported, residual_m3=-8.0)
    assert math.isnan(got["grade_sd"]["Xx"])   # an analyte with no configured sd
    dv = _volume_draws(rng, var, mask, area, 4, 4, 0.5, 0.2) + 4.0 * rng.standard_normal(DRAWS)
    density = tonnes.sum() / volume
    own = rng.standard_normal((DRAWS, 5)) * config.density_repeat_rel
    shared = rng.standard_normal(DRAWS) * config.density_default_rel
    rel = np.where(reported, own[:, group], shared[:, None])
    rho = density * (1.0 + (rel * tonnes).sum(axis=1) / tonnes.sum())
    _close(((volume + dv) * rho).std(), got["tonnes_sd"])
    sd = np.where(assayed, config.lab_sd_pp["Fe"], config.planned_sd_pp["Fe"])
    per_group = rng.standard_normal((DRAWS, 5))[:, group] * sd
    _close(((per_group * tonnes).sum(axis=1) / tonnes.sum()).std(), got["grade_sd"]["Fe"])


def test_config_is_frozen_and_read_only():
    given = {"Fe": 0.2, "Mn": 0.05}
    config = UncertaintyConfig(lab_sd_pp=given)
    given["Fe"] = 9.0                          # the config keeps its own copy
    assert dict(config.lab_sd_pp) == {"Fe": 0.2, "Mn": 0.05}
    with pytest.raises(dataclasses.FrozenInstanceError):
        config.corr_share = 0.1
    with pytest.raises(TypeError):
        config.lab_sd_pp["Fe"] = 1.0


# -- bad input -------------------------------------------------------------------------------

_V = np.full((3, 3), 0.01)
_M = np.ones((3, 3), bool)


@pytest.mark.parametrize("call", [
    lambda: volume_variance(np.zeros(9), np.ones(9, bool), 1.0),
    lambda: volume_variance(_V, np.ones((3, 4), bool), 1.0),
    lambda: volume_variance(_V, np.ones((3, 3)), 1.0),
    lambda: volume_variance(-_V, _M, 1.0),
    lambda: volume_variance(np.full((3, 3), np.inf), _M, 1.0),
    lambda: volume_variance(_V, _M, 0.0),
    lambda: volume_variance(_V, _M, 1.0, corr_cells=0),
    lambda: volume_variance(_V, _M, 1.0, corr_cells=(2, 1.5)),
    lambda: volume_variance(_V, _M, 1.0, corr_share=1.5),
    lambda: volume_variance(_V, _M, 1.0, unseen_sd_m=-1.0),
    lambda: tonnes_sd(-1.0, 1.0, 2.4, 0.01),
    lambda: tonnes_sd(1.0, math.nan, 2.4, 0.01),
    lambda: weighted_mean_sd([1.0, 2.0], [0], [0.1]),
    lambda: weighted_mean_sd([1.0, -2.0], [0, 0], [0.1]),
    lambda: weighted_mean_sd([1.0, 2.0], [0.0, 1.0], [0.1, 0.1]),
    lambda: weighted_mean_sd([1.0, 2.0], [0, 2], [0.1, 0.1]),
    lambda: weighted_mean_sd([1.0, 2.0], [0, 1], [0.1, -0.1]),
    lambda: density_rel_sd([1.0], [0], [1], 0.01, 0.05),
    lambda: boundary_band_thickness_m([0.0], [1.0, 2.0], [3.0], 0.2),
    lambda: boundary_band_thickness_m([0.0], [1.0], [3.0], -0.2),
    lambda: grade_sd([1.0, 1.0], [0, 0], [True, False], [0.1], [1.0]),
    lambda: grade_sd([1.0], [0], [True], [0.1, 0.2], [1.0]),
    lambda: grade_sd([1.0], [0], [True], [0.1], [1.0], [5.0], [[1.0, 2.0]]),
    lambda: grade_sd([1.0], [0], [True], [0.1], [1.0], [-5.0], [[1.0]]),
    lambda: UncertaintyConfig(corr_cells=0),
    lambda: UncertaintyConfig(corr_share=2.0),
    lambda: UncertaintyConfig(lab_sd_pp={"Fe": -0.1}),
])
def test_bad_input_raises_value_error(call):
    with pytest.raises(ValueError):
        call()
