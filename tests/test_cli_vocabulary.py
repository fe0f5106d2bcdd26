"""One vocabulary for the command line (common.options), checked on every subcommand.

The parser walk reads ``stockpile.cli.build_parser()`` recursively; the behaviour tests run
the real command as a subprocess (``python -m stockpile.cli``) on a small ledger imported
from the generated sample.
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
from pathlib import Path

import pytest

from common import options
from common.options import (DEFAULT_BATCH_SIZE, KNOWN_TIME_HELP, VALID_TIME_HELP, DurationAction,
                            parse_duration_s)
from stockpile.cli import build_parser
from stockpile.sample import generate_sample

#: spellings replaced by the shared vocabulary: never shown in --help
OLD_SPELLINGS = {"--as-of-valid", "--as-of-known", "-o", "--output", "--rrd"}

#: reST that must not leak into help texts
REST = re.compile(r"``|:(mod|func|class|meth|data|attr|obj|ref):`")

#: descriptions that come from files outside this change (stockpile/service_cli.py builds
#: `stockpile service`'s from its module docstring); remove when that file uses
#: common.options.plain_text
REST_ELSEWHERE: set[tuple[str, ...]] = set()

#: option names that take a time quantity (their help, metavar or name must carry a unit)
TIMEISH = re.compile(r"duration|every|period|interval|timeout|linger|wait-subscriber|window|"
                     r"reorder|hold|lag")
TIME_UNIT = re.compile(r"\b(s|seconds?|ms|min|minutes?|h|hours?|d|days?|ns|DURATION|S|SECONDS)\b"
                       r"|-s$|90s|1h")


def walk(parser: argparse.ArgumentParser, path: tuple[str, ...] = ()):
    """Every (path, parser) below ``parser``, sub-subcommands included."""
    yield path, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from walk(sub, path + (name,))


PARSERS = list(walk(build_parser()))
SUBCOMMANDS = [(p, sp) for p, sp in PARSERS if p]


def visible(parser: argparse.ArgumentParser):
    return [a for a in parser._actions if a.help is not argparse.SUPPRESS]


def run(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "stockpile.cli", *args], capture_output=True,
                          text=True, timeout=300, cwd=cwd)


@pytest.fixture(scope="module")
def ledger(tmp_path_factory) -> Path:
    """A small real ledger: one hour of the generated sample, imported by the command."""
    work = tmp_path_factory.mktemp("vocab")
    sample = work / "sample.jsonl"
    sample.write_text("\n".join(generate_sample(seed=3, hours=1.0).lines) + "\n")
    path = work / "ledger.duckdb"
    out = run("ledger", "import", str(sample), "--ledger", str(path), "--clock", "events")
    assert out.returncode == 0, out.stderr
    return path


# -- the parser walk ------------------------------------------------------------------------


def test_the_walk_reaches_the_sub_subcommands():
    paths = {p for p, _ in PARSERS}
    for path in (("ledger", "export"), ("audit", "history"), ("plan", "reclaim"),
                 ("service", "recorder"), ("demo",), ("record",), ("export-mcap",)):
        assert path in paths


@pytest.mark.parametrize("path,parser", SUBCOMMANDS, ids=[" ".join(p) for p, _ in SUBCOMMANDS])
def test_every_subcommand_has_a_description_without_rest(path, parser):
    assert parser.description and parser.description.strip(), f"{' '.join(path)}: no description"
    texts = [parser.description] + [a.help or "" for a in visible(parser)]
    leaks = [t for t in texts if REST.search(t)]
    if path in REST_ELSEWHERE:
        return
    assert not leaks, f"{' '.join(path)}: reST in help: {leaks}"


@pytest.mark.parametrize("path,parser", PARSERS, ids=[" ".join(p) or "stockpile" for p, _ in PARSERS])
def test_shared_options_have_one_spelling_and_one_default(path, parser):
    where = " ".join(("stockpile",) + path)
    for action in visible(parser):
        shown = set(action.option_strings)
        assert not shown & OLD_SPELLINGS, f"{where} shows {shown & OLD_SPELLINGS}"
        if "--valid-time" in shown:
            assert action.help == VALID_TIME_HELP, where
        if "--known-time" in shown:
            assert action.help == KNOWN_TIME_HELP, where
        if "--batch-size" in shown:
            assert action.default == DEFAULT_BATCH_SIZE and f"{DEFAULT_BATCH_SIZE:,}" in action.help
        if "--clock" in shown:
            assert action.metavar == "{wall,events}" and action.default == "wall", where
            assert "(default wall)" in action.help, where
        if "--types" in shown:
            assert action.nargs == "+" and action.metavar == "TYPE", where
        if "--progress" in shown:
            assert isinstance(action, argparse.BooleanOptionalAction), where
            assert "--no-progress" in shown and action.default is None, where
        if "--no-progress" in shown:
            assert "--progress" in shown, f"{where}: --no-progress without --progress"
        if "--out" in shown:
            assert action.metavar in ("PATH", "DIR", "OUT.mcap"), where
        if isinstance(action, DurationAction):
            assert action.metavar == "DURATION" and "unit" in action.help, where
            assert re.search(r"\b(site|wall|valid)\b", action.help), f"{where}: site or wall?"
        for flag in action.option_strings:
            if flag.startswith("--") and TIMEISH.search(flag):
                text = f"{action.help} {action.metavar or ''} {flag}"
                assert TIME_UNIT.search(text), f"{where} {flag}: no unit in {text!r}"


def test_durations_need_a_unit():
    assert parse_duration_s("90s") == 90.0
    assert parse_duration_s("15min") == 900.0
    assert parse_duration_s("1h") == 3600.0
    assert parse_duration_s("2d") == 172_800.0
    assert parse_duration_s("1h30min") == 5400.0
    for seconds, text in ((60, "1min"), (5400, "1h30min"), (90, "1min30s"), (0.25, "0.25s"),
                          (172_800, "2d")):
        assert options.format_duration_s(seconds) == text
        assert parse_duration_s(text) == seconds
    for bad, needle in (("3600", "needs a unit, e.g. 1h or 90s"), ("0.1", "needs a unit"),
                        ("0s", "must be positive"), ("soon", "is not a duration")):
        with pytest.raises(ValueError, match=needle):
            parse_duration_s(bad)


# -- the real command -------------------------------------------------------------------------


@pytest.mark.parametrize("argv,line", [
    (["audit", "history", "--ledger", "x.duckdb", "--pile", "P1", "--every", "3600"],
     "stockpile audit history: error: --every needs a unit, e.g. 1h or 90s, got '3600'"),
    (["demo", "--duration", "0.1"],
     "stockpile demo: error: --duration needs a unit, e.g. 1h or 90s, got '0.1'"),
    (["record", "--out", "x.mcap", "--duration", "60"],
     "stockpile record: error: --duration needs a unit, e.g. 1h or 90s, got '60'"),
    (["dashboard", "--ledger", "x.duckdb", "--out", "x.rrd", "--every", "300"],
     "stockpile dashboard: error: --every needs a unit, e.g. 1h or 90s, got '300'"),
])
def test_a_bare_number_is_a_one_line_error(argv, line, tmp_path):
    out = run(*argv, cwd=tmp_path)
    assert out.returncode == 2
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(line), out.stderr
    assert not list(tmp_path.iterdir()), "nothing may be written on a usage error"


@pytest.mark.parametrize("argv,needle", [
    (["demo", "--in-process", "--duration", "1h"], "--duration does not apply to demo --in-process"),
    (["demo", "--in-process", "--speed", "10"], "--speed does not apply to demo --in-process"),
    (["demo", "--sample", "--idle-speed", "10"], "--idle-speed does not apply to demo --sample"),
    (["demo", "--sample", "--record", "x.mcap"], "--record does not apply to demo --sample"),
    (["demo", "--sample", "--in-process"], "choose one"),
    (["demo", "--sample", "--speed", "-3"], "--speed: must be positive"),
    (["demo", "--speed", "0"], "--speed: must be positive"),
    (["sim", "--speed", "-1"], "--speed: must not be negative"),
])
def test_options_that_do_not_apply_are_errors(argv, needle, tmp_path):
    out = run(*argv, "--out", str(tmp_path / "o"), cwd=tmp_path)
    assert out.returncode == 2, out.stdout + out.stderr
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and needle in lines[0], out.stderr
    assert not (tmp_path / "o").exists()


def test_old_time_and_output_spellings_still_work_and_warn(ledger, tmp_path):
    new = run("ledger", "export", "--ledger", str(ledger), "--valid-time", "2026-11-01T00:20:00Z",
              "--known-time", "2026-11-01T00:30:00Z", "--out", str(tmp_path / "new.jsonl"))
    assert new.returncode == 0 and "warning" not in new.stderr, new.stderr
    lines = (tmp_path / "new.jsonl").read_text().splitlines()
    everything = run("ledger", "export", "--ledger", str(ledger)).stdout.splitlines()
    assert 0 < len(lines) < len(everything)
    for valid, known, out, warned in (
            ("--as-of-valid", "--as-of-known", "-o",
             [("--as-of-valid", "--valid-time"), ("--as-of-known", "--known-time"), ("-o", "--out")]),
            ("--valid-time", "--as-of-known", "--output",
             [("--as-of-known", "--known-time"), ("--output", "--out")])):
        target = tmp_path / f"old{out}.jsonl"
        old = run("ledger", "export", "--ledger", str(ledger), valid, "2026-11-01T00:20:00Z",
                  known, "2026-11-01T00:30:00Z", out, str(target))
        assert old.returncode == 0, old.stderr
        assert target.read_text().splitlines() == lines
        warnings = [l for l in old.stderr.splitlines() if "deprecated" in l]
        assert warnings == [f"stockpile: warning: {o} is deprecated, use {n}" for o, n in warned]


def test_clock_site_is_a_deprecated_alias_of_events(ledger, tmp_path):
    sample = tmp_path / "sample.jsonl"
    sample.write_text("\n".join(generate_sample(seed=3, hours=1.0).lines) + "\n")
    by_events = run("ledger", "import", str(sample), "--ledger", str(tmp_path / "a.duckdb"),
                    "--clock", "events", "--json")
    by_site = run("ledger", "import", str(sample), "--ledger", str(tmp_path / "b.duckdb"),
                  "--clock", "site", "--json")
    assert by_events.returncode == by_site.returncode == 0, by_site.stderr
    assert by_site.stdout == by_events.stdout
    assert "stockpile: warning: --clock site is deprecated, use --clock events" in by_site.stderr
    assert "warning" not in by_events.stderr
    a = run("ledger", "export", "--ledger", str(tmp_path / "a.duckdb"), "--known-time",
            "2026-11-01T00:10:00Z").stdout
    b = run("ledger", "export", "--ledger", str(tmp_path / "b.duckdb"), "--known-time",
            "2026-11-01T00:10:00Z").stdout
    assert a == b and a, "the site alias must record the same times as the events clock"
    bad = run("ledger", "import", str(sample), "--ledger", str(tmp_path / "c.duckdb"),
              "--clock", "moon")
    assert bad.returncode == 2 and "choose from wall, events" in bad.stderr


def test_export_mcap_positional_output_still_works_and_warns(ledger, tmp_path):
    target = tmp_path / "old.mcap"
    old = run("export-mcap", "--ledger", str(ledger), str(target), "--types", "assay",
              "--no-progress")
    assert old.returncode == 0 and target.stat().st_size > 0, old.stderr
    assert (f"stockpile: warning: the output file as a positional argument ({target}) is "
            f"deprecated, use --out {target}") in old.stderr
    new = run("export-mcap", "--ledger", str(ledger), "--out", str(tmp_path / "new.mcap"),
              "--types", "assay", "--no-progress")
    assert new.returncode == 0 and "warning" not in new.stderr, new.stderr
    both = run("export-mcap", "--ledger", str(ledger), str(target), "--out", str(target))
    assert both.returncode == 2 and "once" in both.stderr


def test_audit_history_with_units_runs(ledger):
    out = run("audit", "history", "--ledger", str(ledger), "--pile", "P1", "--every", "15min",
              "--json", "--no-progress")
    assert out.returncode == 0, out.stderr
    assert '"every_ns": 900000000000' in out.stdout


def test_the_vocabulary_module_imports_nothing_of_the_project():
    source = Path(options.__file__).read_text()
    imports = re.findall(r"^(?:from|import) (\w+)", source, re.M)
    assert set(imports) <= {"__future__", "argparse", "re", "sys", "typing"}, imports


def test_dashboard_rrd_is_a_deprecated_spelling_of_out(tmp_path):
    missing = tmp_path / "none.duckdb"
    old = run("dashboard", "--ledger", str(missing), "--rrd", str(tmp_path / "x.rrd"))
    assert old.returncode == 2
    assert old.stderr.splitlines() == ["stockpile: warning: --rrd is deprecated, use --out",
                                       f"stockpile: error: no ledger at {missing}"]
