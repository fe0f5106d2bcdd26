"""Belt grades (AR(1) drift) and the laboratory model of the simulator."""

from __future__ import annotations

import numpy as np

from schemas.times import NS_PER_H, NS_PER_S
from sim.grades import ANALYTES, BeltGrade, LabModel, table_5_4_lots


def test_table_5_4_magnitudes():
    lots = table_5_4_lots()
    assert [round(l.mean_pct[0], 2) for l in lots] == [56.23, 60.77, 51.43, 62.05]
    assert abs(lots[0].sd_pct[0] ** 2 - 6.56) < 1e-9  # the table gives variances


def test_belt_grade_is_autocorrelated_around_the_plan(seed):
    lot = table_5_4_lots()[1]
    belt = BeltGrade(lot, 0, 200 * NS_PER_H, np.random.default_rng(seed), tau_s=1200, step_s=10)
    x = belt.samples_pct[:, 0]
    # stationary mean and sd of the AR(1) process match the lot (long run: 72,000 samples);
    # the mean of an AR(1) over T has standard error sd * sqrt(2 tau / T): 5 of them
    se = lot.sd_pct[0] * np.sqrt(2 * 1200 / (200 * 3600))
    assert abs(x.mean() - lot.mean_pct[0]) < 5 * se, seed
    assert abs(x.std() - lot.sd_pct[0]) / lot.sd_pct[0] < 0.15, seed
    # lag-1 autocorrelation = exp(-step/tau)
    r1 = np.corrcoef(x[:-1], x[1:])[0, 1]
    assert abs(r1 - np.exp(-10 / 1200)) < 0.01, seed
    assert (belt.samples_pct >= 0).all() and (belt.samples_pct.sum(axis=1) <= 99.5 + 1e-9).all()


def test_grade_interpolates_between_samples():
    belt = BeltGrade(table_5_4_lots()[0], 0, NS_PER_H, np.random.default_rng(1), step_s=10)
    a, b = belt.samples_pct[3], belt.samples_pct[4]
    mid = belt.at(35 * NS_PER_S)
    assert np.allclose(mid, (a + b) / 2)
    assert belt.at(np.array([0, 10 * NS_PER_S])).shape == (2, len(ANALYTES))


def test_lab_reports_late_with_small_error_and_supersedes_provisionals(seed):
    rng = np.random.default_rng(seed)
    lot = table_5_4_lots()[2]
    belt = BeltGrade(lot, 0, 24 * NS_PER_H, rng)
    lab = LabModel(window_s=1200, delay_h=(2.0, 6.0), provisional_fraction=0.3)
    results = lab.assays(belt, 0, 20 * NS_PER_H, rng, [0])
    finals = [r for r in results if r.status == "FINAL"]
    provisionals = [r for r in results if r.status == "PROVISIONAL"]
    assert len(finals) == 60 and provisionals  # one FINAL per 20-minute window
    for r in results:
        late_h = (r.reported_ns - r.window_end_ns) / NS_PER_H
        assert 2.0 <= late_h <= 9.0
        assert sum(r.analytes_pct.values()) <= 100.0
    ids = {r.assay_id for r in results}
    for r in finals:
        if r.supersedes:
            assert r.supersedes in ids
            first = next(p for p in provisionals if p.assay_id == r.supersedes)
            assert r.reported_ns > first.reported_ns
    # lab error: FINAL Fe within a few lab sd of the true window mean
    errors = np.array([r.analytes_pct["Fe"] - r.true_grade_pct["Fe"] for r in finals])
    assert np.abs(errors).max() < 5 * lab.error_sd_pct[0], seed
    assert abs(errors.std() - lab.error_sd_pct[0]) < 0.08, seed
