"""``stockpile info`` and ``stockpile sql`` on real files, run as real processes.

The ledger comes from ``stockpile demo --sample`` (it has gaps and quarantine), the
MCAP file from ``stockpile export-mcap`` of that ledger.  The two commands run in a
child process through a parser built from their own ``register`` functions.
"""

from __future__ import annotations

import csv
import io
import json
import shutil
import subprocess
import sys

import duckdb
import pytest

from ledger.sql import created_by_version, statements, version_warning

# the `stockpile` parser for just these two commands, run in a child process
RUNNER = """
import argparse, sys
from ledger import sql
from stockpile import info
parser = argparse.ArgumentParser(prog="stockpile")
sub = parser.add_subparsers(dest="command", required=True)
info.register(sub)
sql.register(sub)
args = parser.parse_args(sys.argv[1:])
sys.exit(args.func(args))
"""

# a README query ("grade per lot from the final (or latest) assays")
README_QUERY = ('SELECT lot_id, round(avg("Fe"), 2) AS fe_pct, round(avg("SiO2"), 2) AS sio2_pct '
                'FROM assays WHERE NOT superseded GROUP BY lot_id ORDER BY lot_id')


def stockpile(*args: str, stdin: str | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "stockpile.cli", *args], capture_output=True,
                          text=True, timeout=300, input=stdin)


def command(*args: str, stdin: str | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", RUNNER, *args], capture_output=True, text=True,
                          timeout=300, input=stdin)


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    out = tmp_path_factory.mktemp("info")
    run = stockpile("demo", "--sample", "--out", str(out))
    assert run.returncode == 0, run.stderr
    ledger = out / "ledger.duckdb"
    mcap = out / "session.mcap"
    run = stockpile("export-mcap", "--ledger", str(ledger), "--out", str(mcap), "--no-progress")
    assert run.returncode == 0, run.stderr
    stats = stockpile("ledger", "stats", "--ledger", str(ledger), "--json")
    assert stats.returncode == 0, stats.stderr
    return {"dir": out, "ledger": ledger, "mcap": mcap, "stats": json.loads(stats.stdout)}


def info_json(path) -> dict:
    run = command("info", str(path), "--json")
    assert run.returncode == 0, run.stderr
    return json.loads(run.stdout)


def test_info_ledger_matches_ledger_stats(files):
    stats = files["stats"]
    info = info_json(files["ledger"])
    assert info["kind"] == "ledger"
    assert info["per_type"] == stats["per_type"] and info["per_source"] == stats["per_source"]
    assert info["events"] == stats["events"] == sum(stats["per_type"].values())
    assert [info["valid_time"]["first_ns"], info["valid_time"]["last_ns"]] == \
        stats["valid_time_range_ns"]
    assert [info["recorded_time"]["first_ns"], info["recorded_time"]["last_ns"]] == \
        stats["recorded_time_range_ns"]
    # the sample plants a dropped sequence number and bad lines
    assert info["gaps"]["open"] == stats["open_gaps"] >= 1
    assert len(info["gaps"]["listed"]) == stats["open_gaps"]
    assert info["quarantine"]["count"] == stats["quarantined"] >= 1
    assert info["quarantine"]["by_code"] == stats["quarantine_by_code"]
    assert info["size_bytes"] == files["ledger"].stat().st_size
    assert info["duckdb_created_by"] == f"v{duckdb.__version__}"

    text = command("info", str(files["ledger"]))
    assert text.returncode == 0, text.stderr
    assert f"quarantine:   {stats['quarantined']}" in text.stdout
    for name, n in stats["per_type"].items():
        assert f"  {name:<20} {n:>10,}" in text.stdout


def test_info_mcap_matches_the_ledger(files):
    stats = files["stats"]
    info = info_json(files["mcap"])
    assert info["kind"] == "mcap"
    assert info["per_type"] == stats["per_type"] and info["per_source"] == stats["per_source"]
    assert info["events"] == info["messages"] == stats["events"]
    # publish_time = valid time, log_time = recorded time in an export
    assert [info["valid_time"]["first_ns"], info["valid_time"]["last_ns"]] == \
        stats["valid_time_range_ns"]
    assert [info["log_time"]["first_ns"], info["log_time"]["last_ns"]] == \
        stats["recorded_time_range_ns"]
    # the ledger's open gaps are holes in the exported sequences too
    assert info["gaps"]["count"] == stats["open_gaps"]
    assert info["gaps"]["missing_events"] == stats["missing_events"]
    assert sum(c["messages"] for c in info["channels"]) == stats["events"]
    assert {c["topic"].split("/")[3] for c in info["channels"]} == set(stats["per_type"])
    assert {"stockpile.v1.Assay", "foxglove.LaserScan"} <= {s[0] for s in info["schemas"]}
    assert info["metadata"] == {"stockpile.export": 1}
    damage = info["damage"]
    assert damage["complete"] and not damage["damaged"] and damage["lost"] == 0
    assert damage["summary_total"] == stats["events"]

    text = command("info", str(files["mcap"]))
    assert text.returncode == 0, text.stderr
    assert "integrity:    complete: nothing lost" in text.stdout
    assert "stockpile/demo/@v1/assay/lab1" in text.stdout


def test_info_truncated_mcap_reports_the_loss(files):
    cut = files["dir"] / "cut.mcap"
    data = files["mcap"].read_bytes()
    cut.write_bytes(data[:len(data) * 6 // 10])
    info = info_json(cut)
    damage = info["damage"]
    assert not damage["complete"] and damage["damaged"] and damage["lost_unknown"]
    assert any("cut short" in p for p in damage["problems"])
    assert 0 < info["events"] < files["stats"]["events"]
    assert info["events"] == sum(info["per_type"].values())
    text = command("info", str(cut))
    assert text.returncode == 0, text.stderr
    assert "integrity:    DAMAGED:" in text.stdout and "cut short" in text.stdout


@pytest.mark.parametrize("make, message", [
    (lambda d: d / "missing.mcap", "no such file"),
    (lambda d: d / "sample.jsonl", "neither an MCAP file nor a ledger"),
    (lambda d: d, "is not a file"),
])
def test_info_errors_are_one_line(files, make, message):
    run = command("info", str(make(files["dir"])))
    assert run.returncode == 2 and run.stdout == ""
    assert run.stderr.count("\n") == 1 and message in run.stderr
    assert run.stderr.startswith("stockpile info: error: ")


def test_info_on_a_duckdb_file_that_is_not_a_ledger(tmp_path):
    path = tmp_path / "other.duckdb"
    con = duckdb.connect(str(path))
    con.execute("CREATE TABLE t (a INTEGER)")
    con.close()
    run = command("info", str(path))
    assert run.returncode == 2 and run.stderr.count("\n") == 1
    assert "not a readable ledger" in run.stderr


def test_info_imports_no_heavy_optional_packages(files):
    """info needs neither zenoh, scipy nor rerun (the base install lacks them)."""
    code = ("import sys\nfrom stockpile import info\n"
            f"info.describe({str(files['mcap'])!r}); info.describe({str(files['ledger'])!r})\n"
            "print(sorted(m for m in ('zenoh', 'scipy', 'rerun') if m in sys.modules))")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    assert run.stdout.strip() == "[]"


def expected_grades(ledger) -> list[tuple]:
    con = duckdb.connect(str(ledger), read_only=True)
    try:
        return con.execute(README_QUERY).fetchall()
    finally:
        con.close()


def test_sql_answers_a_readme_query_in_every_format(files):
    expected = expected_grades(files["ledger"])
    assert len(expected) == 3  # the sample's three lots
    ledger = str(files["ledger"])

    table = command("sql", "--ledger", ledger, README_QUERY)
    assert table.returncode == 0, table.stderr
    lines = table.stdout.splitlines()
    assert lines[0].split() == ["lot_id", "fe_pct", "sio2_pct"]
    assert [line.split() for line in lines[2:5]] == [[lot, f"{fe:.10g}", f"{si:.10g}"]
                                                     for lot, fe, si in expected]
    assert lines[5] == "(3 rows)"
    # numbers are right-aligned: the column ends where its header ends
    assert lines[2].rstrip().endswith(f"{expected[0][2]:.10g}")

    as_csv = command("sql", "--ledger", ledger, README_QUERY, "--format", "csv")
    assert as_csv.returncode == 0, as_csv.stderr
    rows = list(csv.reader(io.StringIO(as_csv.stdout)))
    assert rows[0] == ["lot_id", "fe_pct", "sio2_pct"]
    assert [(r[0], float(r[1]), float(r[2])) for r in rows[1:]] == expected

    as_json = command("sql", "--ledger", ledger, README_QUERY, "--format", "json")
    assert as_json.returncode == 0, as_json.stderr
    objects = [json.loads(line) for line in as_json.stdout.splitlines()]
    assert [(o["lot_id"], o["fe_pct"], o["sio2_pct"]) for o in objects] == expected


def test_sql_refuses_writes_and_keeps_the_file(files):
    ledger = files["ledger"]
    before = ledger.read_bytes()
    for statement in ("DELETE FROM event_log", "CREATE TABLE x (a INTEGER)",
                      "UPDATE quarantine SET code = 'x'"):
        run = command("sql", "--ledger", str(ledger), statement)
        assert run.returncode == 2 and run.stdout == ""
        assert run.stderr.count("\n") == 1 and "read-only" in run.stderr
    assert ledger.read_bytes() == before
    assert stockpile("ledger", "verify", "--ledger", str(ledger)).returncode == 0


def test_sql_errors_are_one_line(files):
    bad = command("sql", "--ledger", str(files["ledger"]), "SELEC 1")
    assert bad.returncode == 2 and bad.stderr.count("\n") == 1 and "syntax error" in bad.stderr
    for path, message in ((files["mcap"], "is an MCAP file, not a ledger"),
                          (files["dir"] / "missing.duckdb", "no such file"),
                          (files["dir"] / "sample.jsonl", "not a ledger")):
        run = command("sql", "--ledger", str(path), "SELECT 1")
        assert run.returncode == 2 and run.stderr.count("\n") == 1, run.stderr
        assert message in run.stderr


def test_sql_prompt_reads_statements_until_end_of_input(files):
    expected = expected_grades(files["ledger"])
    script = (README_QUERY.replace(" FROM", "\n  FROM") + ";\n"
              "SELECT count(*) AS n FROM quarantine;\n"
              "DROP VIEW assays;\n"
              "SELECT count(*) AS n FROM events;\n")
    run = command("sql", "--ledger", str(files["ledger"]), "--format", "json", stdin=script)
    # the refused DROP is reported on one line; the statements after it still run
    assert run.returncode == 2
    assert run.stderr.count("\n") == 1 and "read-only" in run.stderr
    objects = [json.loads(line) for line in run.stdout.splitlines()]
    assert [(o["lot_id"], o["fe_pct"], o["sio2_pct"]) for o in objects[:3]] == expected
    assert objects[3:] == [{"n": files["stats"]["quarantined"]}, {"n": files["stats"]["events"]}]

    clean = command("sql", "--ledger", str(files["ledger"]), stdin="SELECT 1 AS one;\n")
    assert clean.returncode == 0 and clean.stdout.splitlines()[0] == "one"


def test_statements_split_on_semicolons_at_line_ends():
    assert list(statements(["SELECT 1\n", "  , 2;\n", "\n", ";\n", "SELECT 3"])) == \
        ["SELECT 1\n  , 2;", "SELECT 3"]


def test_version_warning_names_the_writing_duckdb(files, tmp_path):
    assert created_by_version(files["ledger"]) == f"v{duckdb.__version__}"
    assert version_warning(files["ledger"]) is None
    other = tmp_path / "other.duckdb"
    shutil.copy(files["ledger"], other)
    with open(other, "r+b") as handle:  # the header's library version field (offset 52)
        handle.seek(52)
        handle.write(b"v0.9.9".ljust(32, b"\0"))
    assert created_by_version(other) == "v0.9.9"
    warning = version_warning(other)
    assert warning is not None and "v0.9.9" in warning and duckdb.__version__ in warning
    assert "\n" not in warning
