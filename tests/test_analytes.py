"""Analytes have one spelling (issue 43, item 2).

Regression tests run the real CLI as child processes (``stockpile ledger import`` into a
real DuckDB file, then ``stockpile sql`` on it); the rest check the pure canonical names
and the readers (projector grades, the yard config) that must count ``FE`` as ``Fe``.
"""

from __future__ import annotations

import json
import random
import subprocess
import sys
from pathlib import Path

import duckdb
import pytest

from schemas import pb
from schemas.analytes import (DEFAULT_ANALYTES, AnalyteOptions, AnalytePolicy, canonical_grades,
                              canonical_name, formula_case, parse_list)
from schemas.events import make_event, set_timestamp_ns
from schemas.jsonl import event_line
from schemas.times import NS_PER_H
from projector.grades import AssayRecord, grade_from_map
from stockpile.run_config import ConfigError, load_config

ROOT = Path(__file__).resolve().parents[1]
V0 = 1_700_000_000_000_000_000  # valid time of the first event, UTC ns


def stockpile(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "stockpile.cli", *args], capture_output=True,
                          text=True, timeout=300, cwd=ROOT)


def _lot(lot_id: str = "L1") -> pb.LotDeclared:
    m = pb.LotDeclared(lot_id=lot_id, origin="pit A", planned_tonnes=50_000.0)
    m.planned_grade.update({"Fe": 62.0, "SiO2": 4.5})
    set_timestamp_ns(m.time, V0)
    return m


def _assay(i: int, analytes: dict[str, float], lot_id: str = "L1") -> pb.Assay:
    m = pb.Assay(assay_id=f"A{i}", lot_id=lot_id, lab_id="lab1", moisture_pct=6.0,
                 bulk_density_t_m3=2.3, status=pb.FINAL)
    m.analytes.update(analytes)
    end_ns = V0 + (i + 1) * NS_PER_H
    set_timestamp_ns(m.window_start, end_ns - NS_PER_H)
    set_timestamp_ns(m.window_end, end_ns)
    set_timestamp_ns(m.reported_time, end_ns + 4 * NS_PER_H)
    return m


def _write_lines(path: Path, assays: list[dict[str, float]], *, first: int = 0,
                 lot: bool = True) -> Path:
    events = [make_event(_lot(), source="lims", epoch=1, seq=0)] if lot else []
    events += [make_event(_assay(first + i, a), source="lab1", epoch=1, seq=first + i)
               for i, a in enumerate(assays)]
    path.write_text("".join(event_line(e) + "\n" for e in events))
    return path


def _import(lines: Path, ledger: Path, *options: str) -> subprocess.CompletedProcess:
    return stockpile("ledger", "import", str(lines), "--ledger", str(ledger), "--json",
                     *options)


def _sql(ledger: Path, query: str) -> list[dict]:
    done = stockpile("sql", "--ledger", str(ledger), query, "--format", "json")
    assert done.returncode == 0, done.stderr
    return [json.loads(line) for line in done.stdout.splitlines()]


def _columns(ledger: Path) -> list[str]:
    with duckdb.connect(str(ledger), read_only=True) as con:
        return [r[0] for r in con.execute("DESCRIBE assays").fetchall()]


# --- regressions: the view's columns come from the declared list, never from data -----------


def test_fe_spelled_in_capitals_counts_as_fe_in_the_readme_query(tmp_path, seed):
    """One assay spelling Fe as ``FE`` made the view name the columns ``FE`` and ``Fe_1``,
    and the README's ``avg("Fe")`` the mean of that one assay."""
    rng = random.Random(seed)
    fe = [round(rng.uniform(55.0, 66.0), 3) for _ in range(4)]
    spelled = [{"Fe": fe[0]}, {"Fe": fe[1]}, {"FE": fe[2]}, {" fe ": fe[3]}]
    for a in spelled:
        a["SiO2"] = round(rng.uniform(2.0, 8.0), 3)
    ledger = tmp_path / "l.duckdb"
    done = _import(_write_lines(tmp_path / "in.jsonl", spelled), ledger)
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)["appended"] == 5
    rows = _sql(ledger, 'SELECT avg("Fe") AS fe, count("Fe") AS n FROM assays')
    assert rows[0]["n"] == 4
    assert rows[0]["fe"] == pytest.approx(sum(fe) / 4, abs=1e-9)
    columns = _columns(ledger)
    assert [c for c in columns if c.lower() in ("fe", "fe_1")] == ["Fe"]
    assert list(columns).count("Fe") == 1


def test_an_analyte_named_like_a_fixed_column_cannot_shadow_or_retype_it(tmp_path, seed):
    """Analytes named ``lot_id``, ``status``, ``global_seq`` added columns ``lot_id_1`` ...
    to the view: its columns came from data."""
    rng = random.Random(seed)
    fe = round(rng.uniform(55.0, 66.0), 3)
    ledger = tmp_path / "l.duckdb"
    done = _import(_write_lines(tmp_path / "a.jsonl", [{"Fe": fe}]), ledger)
    assert done.returncode == 0, done.stderr
    before = _columns(ledger)
    odd = {"Fe": fe, "lot_id": 1.5, "status": 2.5, "global_seq": 3.5, "LATENESS_H": 0.5}
    done = _import(_write_lines(tmp_path / "b.jsonl", [odd], first=1, lot=False), ledger)
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)["appended"] == 1
    assert _columns(ledger) == before     # no input adds, renames or retypes a column
    rows = _sql(ledger, "SELECT global_seq, lot_id, status, lateness_h, valid_time_ns, "
                        "recorded_time_ns, typeof(lot_id) AS t_lot, typeof(global_seq) AS t_seq, "
                        "\"Fe\" FROM assays ORDER BY global_seq")
    assert [r["global_seq"] for r in rows] == [1, 2]
    assert all(r["lot_id"] == "L1" and r["t_lot"] == "VARCHAR" for r in rows)
    assert all(r["status"] == "FINAL" and r["t_seq"] == "BIGINT" for r in rows)
    assert all(r["lateness_h"] == pytest.approx(
        (r["recorded_time_ns"] - r["valid_time_ns"]) / 3.6e12) for r in rows)
    assert all(r["Fe"] == pytest.approx(fe) for r in rows)
    flagged = _sql(ledger, "SELECT unrecognised_analytes AS u FROM assays ORDER BY global_seq")
    assert json.loads(flagged[0]["u"]) == []
    assert sorted(json.loads(flagged[1]["u"])) == sorted(
        ["lot_id", "status", "global_seq", "LATENESS_H"])


# --- the site's policy ----------------------------------------------------------------------


def test_unknown_analyte_is_quarantined_when_the_site_says_so(tmp_path):
    ledger = tmp_path / "l.duckdb"
    lines = _write_lines(tmp_path / "in.jsonl",
                         [{"Fe": 62.0}, {"Fe": 61.0, "Zn": 0.2}, {"Fe": 30.0, "fe": 30.5},
                          {"Fe": 63.0}])
    done = _import(lines, ledger, "--unknown-analyte", "quarantine")
    assert done.returncode == 0, done.stderr
    counts = json.loads(done.stdout)
    assert counts["appended"] == 3 and counts["rejected"] == 2
    quarantined = _sql(ledger, "SELECT code, detail FROM quarantine ORDER BY quarantine_id")
    assert [q["code"] for q in quarantined] == ["unknown_analyte", "unknown_analyte"]
    assert "'Zn'" in quarantined[0]["detail"] and "name one analyte" in quarantined[1]["detail"]
    assert _sql(ledger, 'SELECT avg("Fe") AS fe FROM assays')[0]["fe"] == pytest.approx(62.5)
    # the policy is recorded: a later import without options quarantines Zn again
    more = _write_lines(tmp_path / "more.jsonl", [{"Fe": 62.0, "Zn": 0.1}], first=10, lot=False)
    done = _import(more, ledger)
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)["rejected"] == 1


def test_unknown_analyte_is_kept_flagged_and_never_a_column(tmp_path):
    ledger = tmp_path / "l.duckdb"
    lines = _write_lines(tmp_path / "in.jsonl", [{"Fe": 62.0, "ZN": 0.2}, {"Fe": 61.0}])
    done = _import(lines, ledger, "--unknown-analyte", "flag")
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)["appended"] == 3
    rows = _sql(ledger, "SELECT assay_id, unrecognised_analytes FROM assays "
                        "WHERE json_array_length(unrecognised_analytes) > 0")
    assert [(r["assay_id"], json.loads(r["unrecognised_analytes"])) for r in rows] == [
        ("A0", ["ZN"])]
    assert not {"zn"} & {c.lower() for c in _columns(ledger)}


def test_a_declared_name_that_collides_with_a_fixed_column_is_refused(tmp_path):
    ledger = tmp_path / "l.duckdb"
    lines = _write_lines(tmp_path / "in.jsonl", [{"Fe": 62.0}])
    done = _import(lines, ledger, "--analytes", "Fe,SiO2,Lot_ID")
    assert done.returncode == 2
    assert len(done.stderr.strip().splitlines()) == 1
    assert "collides" in done.stderr and "lot_id" in done.stderr
    assert not ledger.exists()   # refused before anything was created


def test_the_declared_list_is_recorded_and_only_grows(tmp_path):
    ledger = tmp_path / "l.duckdb"
    first = _write_lines(tmp_path / "a.jsonl", [{"Fe": 62.0, "cr2o3": 0.3}])
    done = _import(first, ledger, "--analytes", "fe, sio2,Cr2O3")
    assert done.returncode == 0, done.stderr
    assert [c for c in _columns(ledger) if c in ("Fe", "SiO2", "Cr2O3", "Al2O3")] == [
        "Fe", "SiO2", "Cr2O3"]
    assert _sql(ledger, 'SELECT "Cr2O3" AS cr FROM assays')[0]["cr"] == pytest.approx(0.3)
    # a writer told nothing keeps the recorded list; one told more adds to it
    second = _write_lines(tmp_path / "b.jsonl", [{"Fe": 61.0, "Mn": 0.4}], first=5, lot=False)
    assert _import(second, ledger).returncode == 0
    assert "Mn" not in _columns(ledger)
    third = _write_lines(tmp_path / "c.jsonl", [{"Fe": 60.0}], first=6, lot=False)
    assert _import(third, ledger, "--analytes", "MN").returncode == 0
    cols = _columns(ledger)
    assert [c for c in cols if c in ("Fe", "SiO2", "Cr2O3", "Mn")] == ["Fe", "SiO2", "Cr2O3", "Mn"]
    assert _sql(ledger, 'SELECT "Mn" FROM assays WHERE assay_id = \'A5\'')[0]["Mn"] == \
        pytest.approx(0.4)


# --- pure canonical names ---------------------------------------------------------------


def test_every_spelling_of_a_declared_analyte_is_that_analyte(seed):
    rng = random.Random(seed)
    for name in DEFAULT_ANALYTES:
        for _ in range(20):
            spelled = "".join(c.upper() if rng.random() < 0.5 else c.lower() for c in name)
            spelled = " " * rng.randrange(3) + spelled + "\t" * rng.randrange(2)
            assert canonical_name(spelled) == name
            assert AnalytePolicy().canonical(spelled) == name
    assert canonical_name("FE") == canonical_name("fe") == canonical_name("Fe ") == "Fe"
    assert formula_case("ZN") == "Zn" and formula_case("cr2o3") == "Cr2O3"
    assert formula_case("Moisture") == "Moisture"   # mixed case is kept as written
    assert parse_list(" fe,SIO2, fe ,LOI") == ("Fe", "SiO2", "LOI")
    for bad in ("", " , ", "Fe,\x00x", "Fe," + "x" * 40):
        with pytest.raises(ValueError):
            parse_list(bad)
    with pytest.raises(ValueError):
        AnalytePolicy(unknown="drop")


def test_options_resolve_against_the_recorded_policy():
    recorded = AnalytePolicy(("Fe", "SiO2"), "quarantine")
    assert AnalyteOptions().resolve(recorded) == recorded
    assert AnalyteOptions(("Mn", "fe")).resolve(recorded) == AnalytePolicy(
        ("Fe", "SiO2", "Mn"), "quarantine")
    assert AnalyteOptions(unknown="flag").resolve(recorded).unknown == "flag"
    assert AnalyteOptions().resolve(None) == AnalytePolicy()


# --- readers count a non-canonical spelling as its analyte ----------------------------------


def test_projector_grades_count_fe_spelled_in_capitals_as_fe():
    assert grade_from_map({"FE": 62.5, "sio2": 4.0}) == {"Fe": 62.5, "SiO2": 4.0}
    assert canonical_grades({"FE": 1.0, "Fe": 62.5}) == {"Fe": 62.5}
    record = AssayRecord(assay_id="A1", lot_id="L1", window_start_ns=V0, window_end_ns=V0 + 1,
                         analytes={"FE": 61.0, " Al2O3 ": 2.0}, bulk_density_t_m3=0.0,
                         status="FINAL", supersedes="", recorded_ns=V0 + 2)
    assert record.analytes == {"Al2O3": 2.0, "Fe": 61.0}


def test_yard_config_analytes_reach_the_ledger_service(tmp_path):
    good = tmp_path / "yard.toml"
    good.write_text('site = "s"\n[analytes]\ndeclared = ["fe", "SIO2", "P"]\n'
                    'unknown = "quarantine"\n[services.ledger]\nledger = "x.duckdb"\n')
    entry = load_config(good).services[0]
    argv = entry.argv("s", [])
    assert argv[argv.index("--analytes") + 1] == "Fe,SiO2,P"
    assert argv[argv.index("--unknown-analyte") + 1] == "quarantine"
    done = stockpile("run", "--config", str(good), "--check")
    assert done.returncode == 0, done.stderr
    for text, reason in [('declared = ["Fe", "status"]', "collides"),
                         ('unknown = "drop"', "analytes.unknown"),
                         ('declared = ["Fe", ""]', "empty")]:
        bad = tmp_path / "bad.toml"
        bad.write_text(f'site = "s"\n[analytes]\n{text}\n[services.ledger]\nledger = "x"\n')
        with pytest.raises(ConfigError, match=reason):
            load_config(bad)
        done = stockpile("run", "--config", str(bad), "--check")
        assert done.returncode == 2 and len(done.stderr.strip().splitlines()) == 1


def test_ledger_service_options_become_its_config():
    import argparse

    from services import ledger_service
    from stockpile import service_cli

    root = argparse.ArgumentParser(prog="stockpile")
    service_cli.register(root.add_subparsers(dest="command", required=True))

    def parse(*options: str) -> argparse.Namespace:
        return root.parse_args(["service", "ledger", "--site", "s", "--ledger", "x", *options])

    args = parse("--analytes", "fe,SIO2", "--unknown-analyte", "quarantine")
    config = ledger_service.config_from_args(args)
    assert config.analytes == AnalyteOptions(("Fe", "SiO2"), "quarantine")
    assert ledger_service.config_from_args(parse()).analytes is None
    with pytest.raises(ValueError, match="collides"):
        ledger_service.config_from_args(parse("--analytes", "Fe,Superseded"))


def test_the_in_memory_ledger_applies_the_same_policy():
    from ledger import open_ledger

    events = [make_event(_assay(i, a), source="lab1", epoch=1, seq=i) for i, a in
              enumerate([{"Fe": 62.0}, {"FE": 61.0}, {"Fe": 60.0, "Zn": 0.1}])]
    for unknown, statuses in (("flag", ["appended"] * 3),
                              ("quarantine", ["appended", "appended", "rejected"])):
        with open_ledger(":memory:", analytes=AnalytePolicy(("Fe",), unknown)) as store:
            outcomes = store.append(events).outcomes
        assert [o.status for o in outcomes] == statuses
        assert outcomes[2].code == (None if unknown == "flag" else "unknown_analyte")


def test_planner_bounds_name_the_canonical_analyte():
    """``--bound FE>=61`` bounded an analyte no prediction has, so no cut was ever outside."""
    from planner.cli import parse_bounds
    from planner.grades import CutPrediction, check_bounds

    bounds = parse_bounds(["FE>=61", " sio2 <=5"])
    assert bounds == {"Fe": (61.0, None), "SiO2": (None, 5.0)}
    low_fe = CutPrediction(volume_m3=100.0, tonnes=250.0, grade={"Fe": 58.0, "SiO2": 4.0},
                           assayed_fraction=1.0, deposits=[])
    report = check_bounds([low_fe], bounds)
    assert [(o["analyte"], o["bound"]) for o in report.outside] == [("Fe", "min")]
