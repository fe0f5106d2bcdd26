"""Audit and reconciliation reports (``audit.report``, ``stockpile audit``) on a real ledger.

The ledger is the short simulated yard of ``small_yard_sim`` (seed 2, one stacking pass
and the start of a second) imported as the ledger service would store it, followed by
what happens hours later: a reclaim cut through the pile, the simulator's own lab
results for the lot (``truth.json``: the lab's figures and the times it reported them)
arriving 2-6 h after their sampling windows, a PROVISIONAL result that the FINAL
supersedes, an assay for a lot nobody declared and a lot that never gets an assay.  The
cut's true grade is the simulator's true belt grade of the passes it took (truth.json).
"""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from ledger import open_ledger
from audit.report import audit_assays, audit_cuts, audit_history
from projector.query import project
from schemas.times import format_time_ns
from stockpile import cli

SEED = 2          # the seed of the small_yard_sim fixture (tests/conftest.py)
PILE = "P1"
CUT = "T-C01"
from schemas.times import NS_PER_S as S  # noqa: E402
H = 3600 * S


def _line(kind: str, source: str, seq: int, valid_ns: int, recorded_ns: int, body: dict) -> str:
    return json.dumps({"type": kind, "source": source, "epoch": 1, "seq": seq,
                       "valid_time_ns": valid_ns, "recorded_time_ns": recorded_ns,
                       "body": body}) + "\n"


def late_events(sim_dir: Path) -> tuple[list[str], dict]:
    """The events appended after the simulated yard (JSON lines) and what they are."""
    truth = json.loads((sim_dir / "truth.json").read_text())
    last_valid = max(json.loads(line)["valid_time_ns"] for line in (sim_dir / "events.jsonl").open())
    m = truth["machine"]
    end = (last_valid // S + 60) * S
    # a cut whose envelope floor is 0.5 m above the ground at the pile's centre line
    luff = math.asin((0.5 + m["cutting_radius_m"] - m["rail_z_m"] - m["l2_m"] - m["l3_m"])
                     / m["l5_m"])
    rho = m["l4_m"] + m["l5_m"] * math.cos(luff)
    slew = math.asin((29.5 - m["rail_x_m"]) / rho)
    lines = [_line("reclaim_cut", "bwr1.plc", 0, end, end, {
        "pile_id": PILE, "cut_id": CUT, "bench_id": "T", "machine_id": "bwr1",
        "start_time": format_time_ns(end - 120 * S), "end_time": format_time_ns(end),
        "travel_m": 20.0, "luff_rad": luff, "slew_start_rad": slew - 0.12,
        "slew_end_rad": slew + 0.12, "tonnes": 140.0})]
    lab = sorted((a for a in truth["assays"] if a["lot_id"] == "LOT-A"),
                 key=lambda a: a["reported_ns"])
    first = lab[0]["reported_ns"]
    p1 = next(a for a in lab if a["assay_id"] == "AS-00001")
    provisional = {"assay_id": "AS-P01", "lot_id": "LOT-A", "lab_id": "lab1",
                   "status": "PROVISIONAL",
                   "analytes": {k: v * (0.97 if k == "Fe" else 1.0)
                                for k, v in p1["analytes_pct"].items()},
                   "bulk_density_t_m3": p1["bulk_density_t_m3"],
                   "window_start": format_time_ns(p1["window_start_ns"]),
                   "window_end": format_time_ns(p1["window_end_ns"]),
                   "reported_time": format_time_ns(first - H)}
    timeline = [(first - H, "assay", "lab1", provisional, p1["window_end_ns"])]
    for a in lab:
        body = {"assay_id": a["assay_id"], "lot_id": a["lot_id"], "lab_id": a["lab_id"],
                "status": a["status"], "analytes": a["analytes_pct"],
                "bulk_density_t_m3": a["bulk_density_t_m3"],
                "window_start": format_time_ns(a["window_start_ns"]),
                "window_end": format_time_ns(a["window_end_ns"]),
                "reported_time": format_time_ns(a["reported_ns"])}
        if a["assay_id"] == "AS-00001":
            body["supersedes"] = "AS-P01"
        timeline.append((a["reported_ns"], "assay", "lab1", body, a["window_end_ns"]))
    stray = {"assay_id": "AS-Z01", "lot_id": "LOT-Z", "lab_id": "lab2", "status": "FINAL",
             "analytes": {"Fe": 60.0, "SiO2": 4.0},
             "window_start": format_time_ns(end - 600 * S), "window_end": format_time_ns(end),
             "reported_time": format_time_ns(end + 2 * H)}
    timeline.append((end + 2 * H, "assay", "lab2", stray, end))
    lot_y = {"lot_id": "LOT-Y", "origin": "pit-9", "planned_tonnes": 500.0,
             "planned_grade": {"Fe": 58.0, "SiO2": 5.0}, "time": format_time_ns(end + 10 * S)}
    timeline.append((end + 10 * S, "lot_declared", "lims.test", lot_y, end + 10 * S))
    timeline.sort(key=lambda item: item[0])
    seqs: dict[str, int] = {}
    for recorded, kind, source, body, valid in timeline:
        seq = seqs.get(source, 0)
        seqs[source] = seq + 1
        lines.append(_line(kind, source, seq, valid, recorded, body))
    passes = {p["pass_id"]: p for p in truth["passes"]}
    truth_windows = [(a["lot_id"], a["window_start_ns"], a["window_end_ns"], a["true_grade_pct"])
                     for a in truth["assays"]]
    return lines, {"cut_end_ns": end, "provisional_ns": first - H, "lab": lab,
                   "passes": passes, "truth_windows": truth_windows,
                   "final_p1": p1, "stray_ns": end + 2 * H}


def audit_ledger(sim_dir: Path, base: Path) -> tuple[Path, dict]:
    """The small yard plus the late events, imported once per session (cached in ``base``)."""
    lines, info = late_events(sim_dir)
    path = base / "audit-ledger.duckdb"
    if not path.exists():
        work = base / "audit-ledger.tmp.duckdb"
        if work.exists():
            work.unlink()
        jsonl = base / "audit-ledger.jsonl"
        with jsonl.open("w") as out:
            out.write((sim_dir / "events.jsonl").read_text())
            out.writelines(lines)
        # the real `stockpile ledger import`, in this process (no interpreter start-up)
        assert cli.main(["ledger", "import", str(jsonl), "--ledger", str(work), "--clock",
                         "events"]) == 0
        shutil.move(work, path)
    return path, info


@pytest.fixture(scope="module")
def ledger_and_info(small_yard_sim, tmp_path_factory):
    print(f"simulated yard seed {SEED}")
    return audit_ledger(small_yard_sim, tmp_path_factory.getbasetemp())


@pytest.fixture(scope="module")
def cuts_report(ledger_and_info):
    path, _info = ledger_and_info
    with open_ledger(path, read_only=True) as store:
        return audit_cuts(store, PILE)


def cut_truth(cut, info) -> dict[str, float]:
    """The simulator's true grade of the material a cut took: per pass it drew from, the true
    belt grade of the lab window that pass was stacked in, weighted by the cut's tonnes."""
    total, sums = 0.0, {}
    for d in cut.deposits:
        p = info["passes"][d["pass_id"]]
        grade = next(g for lot, t0, t1, g in info["truth_windows"]
                     if lot == p["lot_id"] and t0 <= p["t0_ns"] < t1)
        total += d["tonnes"]
        for a, v in grade.items():
            sums[a] = sums.get(a, 0.0) + d["tonnes"] * v
    return {a: v / total for a, v in sums.items()}


def test_a_late_assay_moves_the_final_grade_towards_the_truth(ledger_and_info, cuts_report):
    path, info = ledger_and_info
    assert [c.cut_id for c in cuts_report.cuts] == [CUT]
    row = cuts_report.cuts[0]
    # when the cut ended no assay was known: the estimate is the lot's planned grade
    assert row.estimated_known_ns == info["cut_end_ns"]
    assert row.assayed_fraction_at_end == 0.0
    assert row.grade_at_end_pct["Fe"] == pytest.approx(56.23, abs=1e-9)   # LOT-A planned
    assert row.assayed_fraction > 0.99
    assert row.tonnes_t > 50.0, "the cut must take material from the pile"
    with open_ledger(path, read_only=True) as store:
        final = project(store, PILE)
    cut = next(c for c in final.cuts if c.cut_id == CUT)
    truth = cut_truth(cut, info)
    err_then = abs(row.grade_at_end_pct["Fe"] - truth["Fe"])
    err_now = abs(row.grade_pct["Fe"] - truth["Fe"])
    print(f"seed {SEED}: cut {CUT} Fe at its end {row.grade_at_end_pct['Fe']:.3f} %, final "
          f"{row.grade_pct['Fe']:.3f} %, simulator truth {truth['Fe']:.3f} %")
    assert err_now < err_then
    assert row.changed(0.1)
    # the final figure is the projector's at K, and the delta is final minus estimate
    assert row.grade_pct["Fe"] == pytest.approx(cut.grade["Fe"], rel=1e-12)
    assert row.tonnes_t == pytest.approx(cut.tonnes, rel=1e-12)
    assert row.delta_pp["Fe"] == pytest.approx(row.grade_pct["Fe"] - row.grade_at_end_pct["Fe"])
    assert row.lots_t and set(row.lots_t) == {"LOT-A"}
    assert cuts_report.pile_tonnes_t == pytest.approx(final.tonnes, rel=1e-12)


def test_the_figure_as_known_at_k_follows_k_and_the_estimate_does_not(ledger_and_info,
                                                                      cuts_report):
    path, info = ledger_and_info
    # after the PROVISIONAL arrived, before the FINAL superseded it: the provisional grade
    k = info["provisional_ns"] + 60 * S
    with open_ledger(path, read_only=True) as store:
        report = audit_cuts(store, PILE, known_time_ns=k)
    row, final = report.cuts[0], cuts_report.cuts[0]
    assert report.known_time_ns == k
    assert row.grade_at_end_pct == final.grade_at_end_pct   # the estimate never moves
    assert row.assayed_fraction > 0.99
    # the provisional reported 97 % of the FINAL's Fe for pass 1, which most of the cut is
    assert final.grade_pct["Fe"] - row.grade_pct["Fe"] > 1.0
    assert final.grade_at_end_pct["Fe"] < row.grade_pct["Fe"] < final.grade_pct["Fe"]


def test_history_as_known_then_and_now(ledger_and_info, cuts_report):
    path, info = ledger_and_info
    with open_ledger(path, read_only=True) as store:
        report = audit_history(store, PILE, 120 * S)
        early = next(p for p in report.points if 0 < p.tonnes_t)
        exact_then = project(store, PILE, early.valid_time_ns, early.valid_time_ns)
    times = [p.valid_time_ns for p in report.points]
    assert times == sorted(times) and len(times) == len(set(times))
    assert all(t % (120 * S) == 0 for t in times[1:-1])   # aligned on the 2-minute grid
    last = report.points[-1]
    # the last row is everything the ledger knows: the pile as project() sees it
    assert last.tonnes_t == pytest.approx(cuts_report.pile_tonnes_t, rel=1e-12)
    # ... and as known at its own valid time no lab had answered yet
    assert last.assayed_fraction_then == 0.0 and last.assayed_fraction > 0.9
    # a row after the cut and before any assay: then = planned, now = the lab's figures
    row = next(p for p in report.points
               if info["cut_end_ns"] <= p.valid_time_ns < info["provisional_ns"])
    assert row.assayed_fraction_then == 0.0 and row.assayed_fraction > 0.9
    assert row.grade_then_pct["Fe"] == pytest.approx(56.23, abs=1e-9)
    assert abs(row.delta_pp["Fe"]) > 1.0
    assert row.tonnes_then_t != pytest.approx(row.tonnes_t, rel=1e-6)   # densities differ
    # "then" is exactly the projection as of that time as known at that time
    assert early.tonnes_then_t == pytest.approx(exact_then.tonnes, rel=1e-12)
    assert early.volume_then_m3 == pytest.approx(exact_then.volume_m3, rel=1e-12)


def test_assay_report(ledger_and_info):
    path, info = ledger_and_info
    with open_ledger(path, read_only=True) as store:
        report = audit_assays(store)
    lab1 = next(lab for lab in report.labs if lab.lab_id == "lab1")
    late_h = sorted([(a["reported_ns"] - a["window_end_ns"]) / H for a in info["lab"]]
                    + [(info["provisional_ns"] - info["final_p1"]["window_end_ns"]) / H])
    assert lab1.assays == len(late_h)
    # recorded = reported here, so lateness is reported time minus window end
    assert lab1.min_h == pytest.approx(late_h[0], abs=1e-9)
    assert lab1.max_h == pytest.approx(late_h[-1], abs=1e-9)
    assert lab1.mean_h == pytest.approx(sum(late_h) / len(late_h), abs=1e-9)
    assert sum(lab1.histogram.values()) == len(late_h)
    assert [s["assay_id"] for s in report.superseded] == ["AS-P01"]
    assert report.superseded[0]["superseded_by"] == "AS-00001"
    assert report.superseded[0]["delta_pp"]["Fe"] == pytest.approx(
        0.03 * info["final_p1"]["analytes_pct"]["Fe"], rel=1e-6)
    assert [(p["assay_id"], p["replaced_by"], p["open"]) for p in report.provisional] == [
        ("AS-P01", "AS-00001", False)]
    assert [(u["assay_id"], u["lot_id"], u["declared_by_k"]) for u in report.unknown_lots] == [
        ("AS-Z01", "LOT-Z", False)]
    assert [lot["lot_id"] for lot in report.lots_without_assays] == ["LOT-Y"]
    # before the superseding FINAL arrived, the provisional was still open
    with open_ledger(path, read_only=True) as store:
        before = audit_assays(store, info["provisional_ns"])
    assert before.superseded == []
    assert [(p["assay_id"], p["open"]) for p in before.provisional] == [("AS-P01", True)]


def test_cli_tables_and_json(ledger_and_info, cuts_report, small_yard_sim, capsys):
    path, _info = ledger_and_info
    truth = small_yard_sim / "truth.json"
    assert cli.main(["audit", "cuts", "--ledger", str(path), "--pile", PILE, "--json",
                     "--no-progress", "--truth", str(truth)]) == 0
    out = json.loads(capsys.readouterr().out)
    (row,) = out["cuts"]
    expected = cuts_report.cuts[0]
    assert row["cut_id"] == CUT and row["changed"] is True
    assert row["grade_pct"]["Fe"] == pytest.approx(expected.grade_pct["Fe"], rel=1e-12)
    assert row["grade_at_end_pct"]["Fe"] == pytest.approx(expected.grade_at_end_pct["Fe"])
    assert row["truth_grade_pct"] is None   # the simulator made no cut of that name
    assert cli.main(["audit", "assays", "--ledger", str(path)]) == 0
    text = capsys.readouterr().out
    assert "lateness per lab" in text and "AS-P01" in text and "LOT-Y" in text
    assert "AS-Z01" in text
    assert cli.main(["audit", "history", "--ledger", str(path), "--pile", PILE, "--every",
                     "1min", "--to", "2026-11-01T00:06:00Z", "--no-progress"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("pile P1: tonnes and grade every 1min")
    assert any(line.strip().startswith("2026-11-01 00:06:00") for line in lines)


def test_bad_input_is_one_line_and_exit_2(ledger_and_info, tmp_path, capsys):
    path, _info = ledger_and_info
    missing = tmp_path / "nope.duckdb"
    proc = subprocess.run([sys.executable, "-m", "stockpile.cli", "audit", "cuts", "--ledger",
                           str(missing), "--pile", PILE], capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [f"stockpile: error: no ledger at {missing}"]
    assert "Traceback" not in proc.stderr and not missing.exists()
    for argv, needle in (
            (["audit", "cuts", "--ledger", str(path), "--pile", "NOPE"], "pile 'NOPE'"),
            (["audit", "cuts", "--ledger", str(path), "--pile", PILE, "--truth",
              str(tmp_path / "none.json")], "no truth file")):
        assert cli.main(argv) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("stockpile: error:") and needle in err[0]
    # a bad duration is a usage error of the subcommand (common.options.DurationAction)
    for every, needle in (("0s", "must be positive"), ("soon", "is not a duration"),
                          ("3600", "needs a unit")):
        with pytest.raises(SystemExit) as exited:
            cli.main(["audit", "history", "--ledger", str(path), "--pile", PILE, "--every", every])
        assert exited.value.code == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("stockpile audit history: error: --every ")
        assert needle in err[0]
