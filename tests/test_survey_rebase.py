"""The model rebased on a survey (projector/rebase.py), under the pile's policy.

The audit tests' yard is imported twice into real DuckDB ledgers: as it is, and with its
``pile_declared`` asking for rebases (``survey_rebase``). A survey planted 10 cm above
the model over a box that also covers bare ground is imported into both with the real
command. The expectations come from the survey's own cells and the model just before it:

- without the policy the fold ignores the survey: every surface is bit for bit the same
  as without it;
- with it, on every surveyed cell with material, the top is the survey's height and each
  deposit keeps its share of the column; every other cell is untouched; the volume and
  the tonnes change by the survey's excess (the density held); the audit trail says so.
"""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from ledger import open_ledger
from projector import fold as F
from projector.material_fit import close_face
from projector.query import project
from projector.surveys import survey_heights
from schemas.events import decode_payload
from schemas.times import parse_time_ns
from stockpile import cli
from test_audit import PILE, audit_ledger

pytest.importorskip("laspy")

from geo.site_crs import SiteCrs  # noqa: E402
from sim.survey import write_laz  # noqa: E402

SITE = SiteCrs(-20.659739, 117.078497, 5.0, 7850)
TIME = "2026-11-01T05:00:00Z"
V = parse_time_ns(TIME)
#: the survey's excess over the model (m); its stated accuracy (m)
EXCESS_M, ACCURACY_M = 0.10, 0.03


def _with_policy(lines: str) -> str:
    out = []
    for line in lines.splitlines(keepends=True):
        if '"pile_declared"' in line:
            event = json.loads(line)
            event["body"]["survey_rebase"] = True
            line = json.dumps(event, separators=(",", ":"), sort_keys=True) + "\n"
        out.append(line)
    return "".join(out)


@pytest.fixture(scope="module")
def ledgers(small_yard_sim, tmp_path_factory, seed):
    """{"plain": without the survey, "off": the survey without the policy, "on": with
    it}; and the box surveyed (nx, ny) bool."""
    base = tmp_path_factory.mktemp("survey-rebase")
    source, _info = audit_ledger(small_yard_sim, tmp_path_factory.getbasetemp())
    jsonl = tmp_path_factory.getbasetemp() / "audit-ledger.jsonl"
    paths = {"plain": base / "plain.duckdb", "off": base / "off.duckdb",
             "on": base / "on.duckdb"}
    shutil.copy(source, paths["plain"])
    shutil.copy(source, paths["off"])
    policy = base / "policy.jsonl"
    policy.write_text(_with_policy(jsonl.read_text()))
    assert cli.main(["ledger", "import", str(policy), "--ledger", str(paths["on"]),
                     "--clock", "events"]) == 0
    with open_ledger(paths["plain"], read_only=True) as store:
        model = project(store, PILE, V)
    g, top = model.geometry, model.state.stack.surface()
    box = np.zeros(g.shape, bool)
    box[10:g.nx - 60, 30:g.ny - 30] = True        # reaches bare ground on the west
    rng = np.random.default_rng(seed)
    print(f"survey points seed {seed}")
    ix, iy = np.nonzero(box)
    ix, iy = np.repeat(ix, 2), np.repeat(iy, 2)
    x = g.origin_x_m + (ix + rng.uniform(0.05, 0.95, ix.size)) * g.cell_m
    y = g.origin_y_m + (iy + rng.uniform(0.05, 0.95, iy.size)) * g.cell_m
    laz = base / "flight.laz"
    write_laz(laz, [(x, y, top[ix, iy] + EXCESS_M)], SITE)
    for name in ("off", "on"):
        assert cli.main(["survey", "import", str(laz), "--ledger", str(paths[name]),
                         "--pile", PILE, "--time", TIME, "--accuracy-m", str(ACCURACY_M),
                         "--no-progress"]) == 0
    return paths, box


def _project(path, valid_ns):
    with open_ledger(path, read_only=True) as store:
        return project(store, PILE, valid_ns)


def test_without_the_policy_the_fold_ignores_the_survey(ledgers):
    paths, _box = ledgers
    plain, off = _project(paths["plain"], V + 1), _project(paths["off"], V + 1)
    assert np.array_equal(off.state.stack.surfaces(), plain.state.stack.surfaces())
    assert off.state.rebases == [] and off.state.counters["surveys_not_rebased"] == 1
    assert off.tonnes == plain.tonnes


def _fold_around_the_survey(path):
    """The fold's state just before the survey event (its open face slid, as the rebase
    does first) and just after it (no flush between: what the rebase itself did), and the
    survey's (heights, counts) on the grid."""
    with open_ledger(path, read_only=True) as store:
        events = list(store.as_of(V, 2**62, types=list(F.GEOMETRY_TYPES)))
    assert events[-1].type == "survey"
    state = F.initial_state(PILE)
    for event in events[:-1]:
        F.apply(state, event)
    before = state.copy()
    if before.open_face is not None:       # the rebase slides the open face first
        close_face(before)
    F.apply(state, events[-1])
    msg = decode_payload(events[-1].type, events[-1].payload)
    return before, state, survey_heights(msg, before.pile.geometry)


def test_with_the_policy_the_model_follows_the_survey(ledgers):
    paths, box = ledgers
    before, after, (heights, counts) = _fold_around_the_survey(paths["on"])
    surveyed = counts > 0
    assert np.array_equal(surveyed, box)
    s0, s1 = before.stack.surfaces(), after.stack.surfaces()
    ground = s0[0]
    column0 = s0[-1] - ground
    scaled = surveyed & (column0 > 1e-3)
    bare = surveyed & ~scaled
    assert scaled.sum() > 1000 and bare.sum() > 100
    np.testing.assert_allclose(s1[-1][scaled], heights[scaled], atol=1e-9)
    # each deposit's share of the column, unchanged
    share0 = np.diff(s0, axis=0)[:, scaled] / column0[scaled]
    share1 = np.diff(s1, axis=0)[:, scaled] / (s1[-1] - ground)[scaled]
    np.testing.assert_allclose(share1, share0, atol=1e-9)
    # every other cell untouched, bit for bit
    assert np.array_equal(s1[:, ~scaled], s0[:, ~scaled])
    # the height map takes the survey, with its accuracy (at least the scans' noise)
    sd = max(ACCURACY_M, after.point_sd_m)
    np.testing.assert_allclose(after.height.elevation[scaled], heights[scaled], atol=1e-9)
    assert np.all(after.height.variance[scaled] == sd ** 2)
    assert np.array_equal(after.height.elevation[~scaled], before.height.elevation[~scaled],
                          equal_nan=True)
    # the audit trail: the volume the survey added
    (rebase,) = after.rebases
    area = before.pile.geometry.cell_area_m2
    excess = float((heights - s0[-1])[scaled].sum() * area)
    assert rebase.cells_scaled == scaled.sum()
    assert rebase.cells_bare_above == int((bare & (heights - ground > sd)).sum()) > 0
    assert rebase.volume_change_m3 == pytest.approx(excess, rel=1e-9)
    assert sum(dv for _l, _p, dv in rebase.deposits_m3) == pytest.approx(excess, rel=1e-9)
    assert {lot for lot, _p, _dv in rebase.deposits_m3} == {"LOT-A"}


def test_the_projection_after_the_survey_keeps_it_and_the_density(ledgers):
    paths, box = ledgers
    _before, _after, (heights, counts) = _fold_around_the_survey(paths["on"])
    ahead, after = _project(paths["on"], V - 1), _project(paths["on"], V)
    top0, top1 = ahead.state.stack.surface(), after.state.stack.surface()
    scaled = (counts > 0) & (top0 - ahead.state.stack.ground() > 1e-3)
    # the query's settling (repose completion, the stack following the height map) may
    # still move a few cells at the toes; the rest keep the survey exactly
    kept = np.abs(top1 - heights)[scaled] < 1e-9
    print(f"{kept.mean():.4f} of {scaled.sum():,} rebased cells keep the survey exactly")
    assert kept.mean() > 0.99
    # a deposit's tonnes follow its volume: the density is held
    assert after.volume_m3 > ahead.volume_m3
    added_t, added_m3 = after.tonnes - ahead.tonnes, after.volume_m3 - ahead.volume_m3
    assert added_t / added_m3 == pytest.approx(ahead.tonnes / ahead.volume_m3, rel=0.01)


def test_the_report_compares_before_the_rebase_and_prints_it(ledgers, capsys):
    paths, box = ledgers
    capsys.readouterr()
    assert cli.main(["audit", "survey", "--ledger", str(paths["on"]), "--pile", PILE,
                     "--json"]) == 0
    (row,) = json.loads(capsys.readouterr().out)["surveys"]
    after = _project(paths["on"], V)
    (rebase,) = after.state.rebases
    # the model just before the survey: 10 cm short over every surveyed cell
    assert row["diff_now_m3"] == pytest.approx(EXCESS_M * row["area_m2"], rel=0.01)
    assert row["rebase"]["cells_scaled"] == rebase.cells_scaled
    assert row["rebase"]["volume_change_m3"] == pytest.approx(rebase.volume_change_m3)
    assert cli.main(["audit", "survey", "--ledger", str(paths["on"]), "--pile", PILE]) == 0
    text = capsys.readouterr().out
    assert "rebased on it (the pile's policy)" in text
    assert cli.main(["audit", "survey", "--ledger", str(paths["off"]), "--pile", PILE,
                     "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["surveys"][0]["rebase"] is None
