"""The standard deviations wired through the query, the commands and the dashboard.

On a short real fold: the ledger of ``test_audit`` (the small simulated yard of
``small_yard_sim``, seed 2, with a reclaim cut and the lab's late assays).  Checked: the
pile's and every cut's ``tonnes_sd`` and ``grade_sd`` are in the API and the JSON,
finite and positive where there is material; they grow when cells are never seen and
when no assay covers the material (the same fold re-summarised with those inputs
changed); the fold keeps each cut's footprint variances; ``stockpile project``, ``plan
reclaim`` and ``audit cuts/history`` print ``+/-`` and give the keys in JSON; the
dashboard's recording holds the one-sd bands.  The kernels themselves:
``tests/test_uncertainty.py``.
"""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest

from cli_in_process import run
from ledger import open_ledger
from projector.query import grade_inputs, project, summarise
from projector.uncertainty import UncertaintyConfig
from services.dashboard import Config, render_ledger
from test_audit import CUT, PILE, SEED, audit_ledger
from test_dashboard import Rrd

ANALYTES_WITH_SD = ("Fe", "SiO2", "Al2O3", "P", "LOI")


@pytest.fixture(scope="module")
def ledger(small_yard_sim, tmp_path_factory):
    print(f"simulated yard seed {SEED}")
    return audit_ledger(small_yard_sim, tmp_path_factory.getbasetemp())[0]


@pytest.fixture(scope="module")
def folded(ledger):
    """``(PileState, lots, assays)`` with everything known."""
    with open_ledger(ledger, read_only=True) as store:
        p = project(store, PILE)
        lots, assays = grade_inputs(store, p.valid_time_ns, p.known_time_ns)
    return p, lots, assays


def _again(p, lots, assays, state=None, config=None):
    """The same fold summarised again (another state, assays or config)."""
    return summarise(state or p.state, lots, assays, valid_time_ns=p.valid_time_ns,
                     known_time_ns=p.known_time_ns, uncertainty=config)


def _finite_positive(figure, analytes) -> None:
    assert math.isfinite(figure.tonnes_sd) and figure.tonnes_sd > 0
    for a in analytes:
        if a in ANALYTES_WITH_SD and math.isfinite(figure.grade.get(a, math.nan)):
            assert math.isfinite(figure.grade_sd[a]) and figure.grade_sd[a] > 0, a


def test_the_pile_and_every_cut_carry_finite_positive_sds(folded):
    p, _lots, _assays = folded
    assert p.tonnes > 0 and p.cuts and any(c.cut_id == CUT for c in p.cuts)
    _finite_positive(p, p.analytes)
    for c in p.cuts:
        assert c.tonnes > 0
        _finite_positive(c, p.analytes)
        # an sd is a fraction of the figure, not a multiple of it
        assert c.tonnes_sd < c.tonnes
    assert p.tonnes_sd < p.tonnes
    out = p.to_json()
    assert out["tonnes_sd"] == p.tonnes_sd and out["grade_sd"] == p.grade_sd
    for c in out["cuts"]:
        assert math.isfinite(c["tonnes_sd"]) and set(c["grade_sd"]) == set(p.analytes)


def test_the_fold_keeps_each_cut_footprint_variances(folded):
    p, _lots, _assays = folded
    for cut in p.state.cuts:
        cells = cut.removals[0].flat_cells(p.geometry.shape)
        assert cut.footprint_var_m2 is not None and cut.footprint_var_m2.shape == cells.shape
        kept = cut.footprint_var_m2
        assert (kept[np.isfinite(kept)] > 0).all()
        # the bank the cut took was seen before it (most of it)
        assert np.isfinite(kept).mean() > 0.5


def test_tonnes_sd_grows_when_cells_are_never_seen(folded):
    p, lots, assays = folded
    state = p.state.copy()
    grid = state.height.grid
    material = np.flatnonzero((state.stack.surface() > state.stack.ground()).ravel())
    grid["variance"].ravel()[material[::2]] = np.nan        # half the pile never seen
    state.cuts = [dataclasses.replace(c, footprint_var_m2=np.full_like(c.footprint_var_m2,
                                                                       np.nan))
                  for c in state.cuts]
    blind = _again(p, lots, assays, state)
    assert blind.tonnes == p.tonnes
    assert blind.tonnes_sd > 1.5 * p.tonnes_sd
    for seen, unseen in zip(p.cuts, blind.cuts):
        assert unseen.tonnes == seen.tonnes and unseen.tonnes_sd > 1.5 * seen.tonnes_sd
    # the never-seen cells' prior drives it
    small = _again(p, lots, assays, state, UncertaintyConfig(unseen_sd_m=0.05))
    assert small.tonnes_sd < blind.tonnes_sd


def test_grade_sd_grows_when_no_assay_covers_the_material(folded):
    p, lots, assays = folded
    assert assays and p.assayed_fraction > 0.5
    unassayed = _again(p, lots, [])
    assert unassayed.assayed_fraction == 0
    assert unassayed.grade_sd["Fe"] > 3 * p.grade_sd["Fe"]
    cut = next(c for c in p.cuts if c.cut_id == CUT)
    cut_plan = next(c for c in unassayed.cuts if c.cut_id == CUT)
    assert cut.assayed_fraction > 0.5
    assert cut_plan.grade_sd["Fe"] > 3 * cut.grade_sd["Fe"]
    # the lab's repeatability is what an assayed grade's sd scales with
    worse_lab = _again(p, lots, assays, config=UncertaintyConfig(
        lab_sd_pp={**UncertaintyConfig().lab_sd_pp, "Fe": 1.5}))
    assert worse_lab.grade_sd["Fe"] > p.grade_sd["Fe"]
    assert worse_lab.grade_sd["SiO2"] == pytest.approx(p.grade_sd["SiO2"], rel=1e-12)


def test_the_window_drift_widens_a_cut_more_than_the_pile(folded):
    """A cut holds a few seconds of each window, the pile whole windows: the drift inside
    a window adds to the cut's grade sd more than to the pile's, and nothing once off."""
    p, lots, assays = folded
    off = _again(p, lots, assays, config=UncertaintyConfig(window_drift=False))
    cut, cut_off = (next(c for c in f.cuts if c.cut_id == CUT) for f in (p, off))
    assert cut.grade_sd["Fe"] > cut_off.grade_sd["Fe"]
    assert cut.grade_sd["Fe"] / cut_off.grade_sd["Fe"] > p.grade_sd["Fe"] / off.grade_sd["Fe"]
    assert cut.tonnes_sd == pytest.approx(cut_off.tonnes_sd, rel=1e-12)


def test_a_lab_stated_repeatability_overrules_the_configured_one(folded):
    """An assay's stated repeatability takes the place of the configured one for its
    analytes: stating the configured value changes nothing, a worse Fe one widens Fe's
    sd alone, and where every assay states its own the configured one no longer
    matters."""
    p, lots, assays = folded
    assert assays and not any(a.repeatability_pp for a in assays)

    def stating(fe_pp: float) -> list:
        return [dataclasses.replace(a, repeatability_pp={"Fe": fe_pp}) for a in assays]
    configured = UncertaintyConfig().lab_sd_pp["Fe"]
    same = _again(p, lots, stating(configured))
    assert same.grade_sd["Fe"] == pytest.approx(p.grade_sd["Fe"], rel=1e-12)
    worse = _again(p, lots, stating(1.5))
    assert worse.grade_sd["Fe"] > 2 * p.grade_sd["Fe"]
    assert worse.grade_sd["SiO2"] == pytest.approx(p.grade_sd["SiO2"], rel=1e-12)
    cut, cut_worse = (next(c for c in f.cuts if c.cut_id == CUT) for f in (p, worse))
    assert cut_worse.grade_sd["Fe"] > cut.grade_sd["Fe"]
    other = UncertaintyConfig(lab_sd_pp={**UncertaintyConfig().lab_sd_pp, "Fe": 9.0})
    assert _again(p, lots, stating(1.5), config=other).grade_sd["Fe"] == \
        pytest.approx(worse.grade_sd["Fe"], rel=1e-12)
    assert _again(p, lots, assays, config=other).grade_sd["Fe"] > worse.grade_sd["Fe"]


def test_stockpile_project_text_and_json(ledger, folded, capsys):
    p, _lots, _assays = folded
    code, out, err = run(capsys, "project", "--ledger", str(ledger), "--pile", PILE)
    assert code == 0, err
    pile_line = next(line for line in out.splitlines() if line.strip().startswith("volume"))
    assert f"{p.tonnes:,.1f} +/- {p.tonnes_sd:,.1f} t" in pile_line
    assert f"Fe {p.grade['Fe']:.2f} +/- {p.grade_sd['Fe']:.2f} %" in pile_line
    cut_line = next(line for line in out.splitlines() if line.strip().startswith(CUT))
    assert cut_line.count("+/-") >= 2
    code, out, err = run(capsys, "project", "--ledger", str(ledger), "--pile", PILE, "--json")
    assert code == 0, err
    data = json.loads(out)
    assert data["tonnes_sd"] == pytest.approx(p.tonnes_sd, rel=1e-12)
    assert data["grade_sd"]["Fe"] == pytest.approx(p.grade_sd["Fe"], rel=1e-12)
    assert all(c["tonnes_sd"] > 0 and c["grade_sd"]["Fe"] > 0 for c in data["cuts"])
    # the pile's material as its scans show it (projector.material_fit), fitted per cut face
    material = data["material"]
    assert material["cuts_fitted"] + material["face_cells_predicted"] > 0
    assert material["repose_deg"] is not None and 20 < material["repose_deg"] < 60


def test_stockpile_plan_gives_each_planned_cut_an_sd(ledger, capsys):
    args = ["plan", "reclaim", "--ledger", str(ledger), "--pile", PILE, "--machine", "bwr1",
            "--cuts", "3"]
    code, out, err = run(capsys, *args, "--json")
    assert code == 0, err
    cuts = [c for c in json.loads(out)["cuts"] if c["tonnes"] > 0]
    assert cuts
    for c in cuts:
        assert 0 < c["tonnes_sd"] < c["tonnes"] and c["grade_sd"]["Fe"] > 0
    code, out, err = run(capsys, *args)
    assert code == 0, err
    assert any("+/-" in line and "Fe" in line for line in out.splitlines())


def test_stockpile_audit_cuts_and_history(ledger, folded, capsys):
    p, _lots, _assays = folded
    code, out, err = run(capsys, "audit", "cuts", "--ledger", str(ledger), "--pile", PILE,
                         "--json")
    assert code == 0, err
    (row,) = [r for r in json.loads(out)["cuts"] if r["cut_id"] == CUT]
    cut = next(c for c in p.cuts if c.cut_id == CUT)
    assert row["tonnes_sd"] == pytest.approx(cut.tonnes_sd, rel=1e-12)
    assert row["grade_sd"]["Fe"] == pytest.approx(cut.grade_sd["Fe"], rel=1e-12)
    code, out, err = run(capsys, "audit", "cuts", "--ledger", str(ledger), "--pile", PILE)
    assert code == 0, err
    assert f"{cut.grade['Fe']:.2f} +/- {cut.grade_sd['Fe']:.2f}" in out
    code, out, err = run(capsys, "audit", "history", "--ledger", str(ledger), "--pile", PILE,
                         "--every", "30min", "--json")
    assert code == 0, err
    points = [q for q in json.loads(out)["points"] if q["tonnes_t"] > 0]
    assert points and all(q["tonnes_sd"] > 0 and q["grade_sd"]["Fe"] > 0 for q in points)


def test_the_dashboard_draws_one_sd_bands(ledger, folded, tmp_path):
    p, _lots, _assays = folded
    out = tmp_path / "bands.rrd"
    render_ledger(str(ledger), None, Config(rrd=str(out), every_s=1800.0))
    rrd = Rrd(out)
    for base in ("/series/pile/tonnes_t/known_then", "/series/pile/grade_pct/Fe/known_then",
                 "/series/cuts/tonnes_t/geometry", "/series/cuts/grade_pct/Fe/at_end"):
        mid, hi, lo = (rrd.scalars(base + s) for s in ("", "_hi", "_lo"))
        assert hi and len(hi) == len(lo), base
        at = {(v, s): x for v, s, x in mid}
        for (v, s, h), (v2, s2, low) in zip(hi, lo):
            assert (v, s) == (v2, s2) and low <= at[(v, s)] <= h, base
            assert at[(v, s)] <= 0 or low < at[(v, s)] < h, base   # material: a band
            assert h - at[(v, s)] == pytest.approx(at[(v, s)] - low, rel=1e-9), base
        # its rows are on the data's timelines (a static chunk, the series' style, has none)
        assert ("ledger_seq", "valid_time") in rrd.timelines[base + "_hi"], base
    # the last update is the pile as of everything: its band is the projector's sd
    (v, s, hi), (_v, _s, mid) = rrd.scalars("/series/pile/tonnes_t/known_then_hi")[-1], \
        rrd.scalars("/series/pile/tonnes_t/known_then")[-1]
    assert hi - mid == pytest.approx(p.tonnes_sd, rel=1e-9)


def _two_lot_cut(lower_m, upper_m):
    """A cut of 4 cells that took ``lower_m`` of lot A's deposit and ``upper_m`` of lot B's
    above it in each, and the join that grades both lots from their plans."""
    from types import SimpleNamespace

    from projector.deposits import DepositInfo, DepositRemoval, Removal
    from projector.grid import GridGeometry
    from projector.query import GradeJoin
    from projector.summary_sd import cut_sd

    geometry = GridGeometry(0.0, 0.0, 1.0, 2, 2)
    ix, iy = np.array([0, 0, 1, 1]), np.array([0, 1, 0, 1])
    parts = tuple(DepositRemoval(k, DepositInfo(k, f"p{k}", lot, 0), 4 * m, ix, iy,
                                 np.full(4, m), np.zeros(4, np.int64))
                  for k, lot, m in ((1, "A", lower_m), (2, "B", upper_m)))
    cut = SimpleNamespace(removals=(Removal(parts),), footprint_var_m2=np.full(4, 1e-4),
                          residual_m3=0.0)
    state = SimpleNamespace(pile=SimpleNamespace(geometry=geometry), height=None)
    join = GradeJoin({"A": {"Fe": 58.0}, "B": {"Fe": 64.0}}, [], 0, 2.4)
    return lambda config: cut_sd(cut, state, join, config)["grade_sd"]["Fe"]


def test_a_boundary_between_slivers_carries_no_band():
    """Slid material lies in thin slivers of every deposit: a boundary counts only where
    one side is at least ``boundary_sliver_m`` thick."""
    config = UncertaintyConfig()
    for lower, upper, counted in ((0.05, 0.05, False), (0.01, 0.5, True), (0.5, 0.01, True)):
        sd = _two_lot_cut(lower, upper)
        without = sd(dataclasses.replace(config, boundary_band_m=0.0))
        assert (sd(config) > without + 1e-6) is counted, (lower, upper)
