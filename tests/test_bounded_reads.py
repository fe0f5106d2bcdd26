"""Bounded work on reads: times outside the representable range and ranges too long to list.

Every command that takes a time refuses one outside int64 UTC ns with one line on stderr
and exit 2 (schemas.times); :func:`schemas.times.format_time_ns` never raises on an int;
``stockpile audit history`` counts its rows before listing them and refuses a range of
more than ``--max-rows`` (common.options.DEFAULT_MAX_ROWS) naming the count and the limit,
with the refused command's peak RSS (``os.wait4`` of the real ``stockpile`` process)
staying near that of a command that does nothing.  The ledger is the one-hour sample
(``stockpile.sample``) imported by the real command.
"""

from __future__ import annotations

import os
import resource
import subprocess
import sys
from pathlib import Path

import pytest
from hypothesis import given, strategies as st

from audit.marks import history_count, history_marks
from cli_in_process import run
from common.options import DEFAULT_MAX_ROWS, check_range_rows, parse_duration_s
from schemas.times import MAX_TIME_NS, MIN_TIME_NS, NS_PER_S, format_time_ns, parse_time_ns
from stockpile.sample import generate_sample

STOCKPILE = str(Path(sys.executable).with_name("stockpile"))
HUGE = "99999999999999999999999"
#: address space a refused command may have (bytes): a guard that turns a regression into
#: a MemoryError instead of the machine's out-of-memory killer
ADDRESS_SPACE_CAP_BYTES = 3 * 1024**3
#: how much more a refused range may take at peak than a command refused at once (kB)
REFUSAL_RSS_MARGIN_KB = 40 * 1024


@pytest.fixture(scope="module")
def ledger(tmp_path_factory) -> Path:
    base = tmp_path_factory.mktemp("bounded")
    sample = base / "sample.jsonl"
    sample.write_text("\n".join(generate_sample(seed=3, hours=1.0).lines) + "\n")
    path = base / "ledger.duckdb"
    done = subprocess.run([STOCKPILE, "ledger", "import", str(sample), "--ledger", str(path)],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    return path


def run_measured(*args: str) -> tuple[int, str, str, int]:
    """``stockpile ARGS`` as its own process: (exit code, stdout, stderr, peak RSS in kB)."""
    def cap() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (ADDRESS_SPACE_CAP_BYTES, ADDRESS_SPACE_CAP_BYTES))

    with open(os.devnull, "rb") as stdin, \
            subprocess.Popen([STOCKPILE, *args], stdin=stdin, stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, preexec_fn=cap) as proc:
        out, err = proc.stdout.read(), proc.stderr.read()
        _, status, usage = os.wait4(proc.pid, 0)
        proc.returncode = os.waitstatus_to_exitcode(status)
    return proc.returncode, out.decode(), err.decode(), usage.ru_maxrss


def assert_one_line_error(code: int, err: str, *needles: str) -> None:
    assert code == 2, err
    assert "Traceback" not in err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("stockpile"), err
    for needle in needles:
        assert needle in lines[0], err


# -- times -----------------------------------------------------------------------------------


def test_parse_time_ns_accepts_exactly_the_int64_range():
    assert parse_time_ns(str(MAX_TIME_NS)) == MAX_TIME_NS
    assert parse_time_ns(str(MIN_TIME_NS)) == MIN_TIME_NS
    assert parse_time_ns("2262-04-11T23:47:16.854775807Z") == MAX_TIME_NS
    assert parse_time_ns("1677-09-21T00:12:43.145224192Z") == MIN_TIME_NS
    for text in (str(MAX_TIME_NS + 1), str(MIN_TIME_NS - 1), HUGE, "9" * 5000,
                 "2262-04-11T23:47:16.854775808Z", "1677-09-21T00:12:43.145224191Z",
                 "9999-12-31T23:59:59Z", "0001-01-01", "2262-04-11T23:59:59-00:30"):
        with pytest.raises(ValueError, match="outside the representable range"):
            parse_time_ns(text)


def test_parse_time_ns_takes_ascii_digits_only():
    for text in ("١٧٦٣٧٨٠٤٠٠٠٠٠٠٠٠٠٠٠٠", "٢٠٢٦-01-01", "2026-01-01T00:00:00.٣Z", "1_000"):
        with pytest.raises(ValueError, match="not an ISO-8601 time"):
            parse_time_ns(text)


@given(st.integers())
def test_format_time_ns_never_raises_on_an_int(ns):
    text = format_time_ns(ns)
    assert isinstance(text, str) and text
    if MIN_TIME_NS <= ns <= MAX_TIME_NS:
        assert parse_time_ns(text) == ns
    else:
        with pytest.raises(ValueError, match="outside the representable range"):
            parse_time_ns(text)


@pytest.mark.parametrize("args", [
    ("ledger", "export", "--valid-time", HUGE),
    ("ledger", "export", "--known-time", HUGE),
    ("ledger", "export", "--valid-time", "9999-12-31T23:59:59Z"),
    ("project", "--pile", "P1", "--valid-time", HUGE),
    ("project", "--pile", "P1", "--known-time", "-" + HUGE),
    ("plan", "reclaim", "--pile", "P1", "--machine", "bwr1", "--valid-time", HUGE),
    ("audit", "cuts", "--pile", "P1", "--known-time", HUGE),
    ("audit", "assays", "--known-time", HUGE),
    ("audit", "history", "--pile", "P1", "--every", "1h", "--to", "9999-12-31T23:59:59Z"),
    ("audit", "history", "--pile", "P1", "--every", "1h", "--from", "-" + HUGE),
], ids=lambda a: " ".join(a[:2]) + " " + " ".join(a[-2:]))
def test_a_time_outside_the_range_is_one_line_and_exit_2(ledger, args):
    at = args.index(args[1]) + 1 if args[0] in ("ledger", "plan", "audit") else 1
    code, out, err, _ = run_measured(*args[:at], "--ledger", str(ledger), *args[at:])
    assert_one_line_error(code, err, "outside the representable range")
    assert out == ""


def test_keys_revoke_from_outside_the_range_is_one_line(tmp_path, capsys):
    code, _, err = run(capsys, "keys", "revoke", "--admin", str(tmp_path / "no.key"),
                       "--out", str(tmp_path / "out.jsonl"), "--key-id", "k", "--from", HUGE)
    assert_one_line_error(code, err, "outside the representable range")
    assert not (tmp_path / "out.jsonl").exists()


# -- ranges ----------------------------------------------------------------------------------


@given(st.integers(-10**6, 10**6), st.integers(-10**6, 10**6), st.integers(1, 5000))
def test_history_count_is_the_length_of_the_marks(first, last, every):
    assert history_count(first, last, every) == len(history_marks(first, last, every))


def test_history_count_of_the_whole_time_range_takes_no_list():
    assert history_count(MIN_TIME_NS, MAX_TIME_NS, 1) == 2**64 - 1 + 1
    with pytest.raises(ValueError, match=r"18,446,744,073,709,551,616 rows, more than the "
                                         r"limit of 100,000"):
        check_range_rows(history_count(MIN_TIME_NS, MAX_TIME_NS, 1), DEFAULT_MAX_ROWS)


def test_a_duration_too_long_for_a_float_is_refused(ledger, capsys):
    with pytest.raises(ValueError, match="too long"):
        parse_duration_s("9" * 400 + "d")
    code, _, err = run(capsys, "audit", "history", "--ledger", str(ledger), "--pile", "P1",
                       "--every", "9" * 400 + "d")
    assert_one_line_error(code, err, "--every", "too long")


@pytest.fixture(scope="module")
def idle_rss_kb(ledger) -> int:
    """Peak RSS (kB) of ``stockpile audit history`` refused for an unknown pile: the
    interpreter, the command's imports and the open ledger, no range."""
    code, _, err, rss_kb = run_measured("audit", "history", "--ledger", str(ledger), "--pile",
                                        "NO-SUCH-PILE", "--every", "1h", "--no-progress")
    assert_one_line_error(code, err, "NO-SUCH-PILE")
    return rss_kb


@pytest.mark.parametrize("every, start, end", [
    # every millisecond of two hours: 7.2 million rows (main: about 300 MB listed, refused)
    ("1ms", "2026-01-01T00:00:00Z", "2026-01-01T02:00:00Z"),
    # every second of nearly the representable range: 18 billion rows (main: MemoryError)
    ("1s", "1677-09-22T00:00:00Z", "2262-04-11T00:00:00Z"),
])
def test_a_range_too_long_is_refused_before_it_is_listed(ledger, idle_rss_kb, every, start,
                                                         end):
    rows = (parse_time_ns(end) - parse_time_ns(start)) // round(
        parse_duration_s(every) * NS_PER_S) + 1
    code, out, err, rss_kb = run_measured(
        "audit", "history", "--ledger", str(ledger), "--pile", "P1", "--every", every,
        "--from", start, "--to", end, "--no-progress")
    assert_one_line_error(code, err, f"{rows:,} rows", f"limit of {DEFAULT_MAX_ROWS:,}",
                          "--max-rows")
    assert out == ""
    print(f"refused {rows:,} rows at a peak RSS of {rss_kb / 1024:.0f} MB (refused for an "
          f"unknown pile: {idle_rss_kb / 1024:.0f} MB)")
    assert rss_kb < idle_rss_kb + REFUSAL_RSS_MARGIN_KB


def test_max_rows_lowers_and_raises_the_limit(ledger, capsys):
    base = ("audit", "history", "--ledger", str(ledger), "--pile", "P1", "--json",
            "--no-progress", "--every", "10min")
    code, _, err = run(capsys, *base, "--max-rows", "3")
    assert_one_line_error(code, err, "more than the limit of 3", "--max-rows")
    code, out, err = run(capsys, *base)
    assert code == 0, err
    assert '"points"' in out
    code, _, err = run(capsys, *base, "--max-rows", "0")
    assert_one_line_error(code, err, "--max-rows")


def test_history_marks_are_the_ends_and_the_aligned_steps_between():
    every = NS_PER_S
    assert history_marks(0, 3 * every, every) == [0, every, 2 * every, 3 * every]
    assert history_marks(500, 2 * every + 1, every) == [500, every, 2 * every, 2 * every + 1]
    assert history_marks(7, 7, every) == [7] and history_count(7, 7, every) == 1
    assert history_marks(9, 7, every) == [9] and history_count(9, 7, every) == 1
