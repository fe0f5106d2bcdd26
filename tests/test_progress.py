"""Progress on stderr (common/progress.py): plain lines when stderr is not a terminal, a bar
redrawn with ``\\r`` on a real pseudo-terminal, nothing when progress is off.

The commands run as real processes on a generated sample, with stderr a pipe or the
slave side of a pty.
"""

from __future__ import annotations

import fcntl
import json
import os
import pty
import struct
import termios
import re
import subprocess
import sys
from argparse import Namespace
from pathlib import Path

import pytest

from common.progress import Progress, enabled_from_args, progress
from stockpile.sample import generate_sample

STOCKPILE = str(Path(sys.executable).with_name("stockpile"))


@pytest.fixture(scope="module")
def sample_file(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("sample") / "sample.jsonl"
    path.write_text("\n".join(generate_sample(seed=5, hours=1.0).lines) + "\n")
    return path


@pytest.fixture(scope="module")
def ledger(tmp_path_factory, sample_file) -> Path:
    path = tmp_path_factory.mktemp("ledger") / "sample.duckdb"
    done = subprocess.run([STOCKPILE, "ledger", "import", str(sample_file), "--ledger", str(path),
                           "--clock", "events"], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    return path


def run_on_pty(args: list[str]) -> tuple[int, str, str]:
    """Run ``stockpile ARGS`` with stderr on a new 120-column pseudo-terminal: (exit code,
    stdout, everything written to the terminal)."""
    master, slave = pty.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 40, 120, 0, 0))  # rows, columns
    proc = subprocess.Popen([STOCKPILE, *args], stdout=subprocess.PIPE, stderr=slave,
                            stdin=subprocess.DEVNULL)
    os.close(slave)
    chunks = []
    while True:
        try:
            chunk = os.read(master, 65536)
        except OSError:  # EIO: the child closed the terminal's last slave side
            break
        if not chunk:
            break
        chunks.append(chunk)
    os.close(master)
    out = proc.stdout.read().decode()
    proc.stdout.close()
    return proc.wait(timeout=300), out, b"".join(chunks).decode(errors="replace")


# -- not a terminal -------------------------------------------------------------------------


def test_piped_ledger_import_writes_plain_lines_with_the_final_counts(tmp_path, sample_file):
    done = subprocess.run([STOCKPILE, "ledger", "import", str(sample_file), "--ledger",
                           str(tmp_path / "l.duckdb"), "--clock", "events", "--json"],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    counts = json.loads(done.stdout)  # the command's own summary is unchanged
    assert counts["lines"] == sum(1 for line in sample_file.read_text().splitlines() if line)
    assert "\r" not in done.stderr and "\x1b" not in done.stderr
    lines = done.stderr.splitlines()
    assert lines and all(line.startswith(f"importing {sample_file.name}: ") for line in lines)
    final = re.fullmatch(rf"importing {re.escape(sample_file.name)}: ([\d,]+) lines in "
                         r"[\d.]+ s \([\d,]+ lines/s\), ([\d,]+) appended", lines[-1])
    assert final, lines[-1]
    assert int(final[1].replace(",", "")) == counts["lines"]
    assert int(final[2].replace(",", "")) == counts["appended"]


def test_piped_export_mcap_ends_with_the_exported_count(tmp_path, ledger):
    done = subprocess.run([STOCKPILE, "export-mcap", "--ledger", str(ledger),
                           "--out", str(tmp_path / "out.mcap")], capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr
    exported = int(re.match(r"exported ([\d,]+) events", done.stdout)[1].replace(",", ""))
    assert "\r" not in done.stderr
    assert re.fullmatch(rf"export: {exported:,} events in [\d.]+ s \([\d,]+ events/s\)",
                        done.stderr.splitlines()[-1]), done.stderr


def test_plain_lines_come_at_most_every_every_s_and_count_up(tmp_path):
    log = tmp_path / "progress.log"
    with open(log, "w") as stream:
        with progress(total=300, unit="events", desc="job", enabled=True, stream=stream,
                      every_s=0.0) as bar:
            for _ in range(3):
                bar.update(100)
        with progress(desc="rare", enabled=True, stream=stream, every_s=3600.0) as bar:
            for _ in range(3):
                bar.update(100)
    lines = log.read_text().splitlines()
    assert lines[:3] == ["job: 100/300 events (33 %)" + lines[0].split("(33 %)")[1],
                         "job: 200/300 events (67 %)" + lines[1].split("(67 %)")[1],
                         "job: 300/300 events (100 %)" + lines[2].split("(100 %)")[1]]
    assert "ETA" in lines[0] and "events/s" in lines[0]
    assert re.fullmatch(r"job: 300 events in [\d.]+ s \([\d,]+ events/s\)", lines[3])
    # an hour between lines: only the final one
    assert len(lines) == 5 and lines[4].startswith("rare: 300 events in ")


def test_a_fraction_estimates_the_total():
    bar = Progress(enabled=False)
    bar.update_to(250, fraction=0.25)
    assert bar.total == 1000
    bar.total = 600  # a known total wins over the estimate
    assert bar.total == 600


def test_after_an_error_there_is_no_final_line(tmp_path):
    log = tmp_path / "progress.log"
    with open(log, "w") as stream, pytest.raises(ValueError):
        with progress(desc="job", enabled=True, stream=stream) as bar:
            bar.update(10)
            raise ValueError("bad input")
    assert log.read_text() == ""


# -- a terminal ---------------------------------------------------------------------------


def test_ledger_import_on_a_terminal_redraws_a_bar(tmp_path, sample_file):
    code, out, tty = run_on_pty(["ledger", "import", str(sample_file), "--ledger",
                                 str(tmp_path / "l.duckdb"), "--clock", "events", "--json"])
    assert code == 0, tty
    n = json.loads(out)["lines"]
    assert tty.count("\r") >= 2  # drawn, then redrawn in place
    assert f"importing {sample_file.name}:" in tty and " lines/s" in tty
    assert f"{n}/{n}" in tty  # the bar ends at the true count
    assert "100%" in tty


def test_replay_on_a_terminal_redraws_a_bar(tmp_path, ledger):
    mcap = tmp_path / "out.mcap"
    code, out, tty = run_on_pty(["export-mcap", "--ledger", str(ledger), "--out", str(mcap)])
    assert code == 0, tty
    assert "\r" in tty and "export:" in tty and "100%" in tty
    code, out, tty = run_on_pty(["replay", str(mcap), "--ledger", str(tmp_path / "c.duckdb")])
    assert code == 0, tty
    events = int(re.search(r": ([\d,]+) events ->", out)[1].replace(",", ""))
    assert "\r" in tty and f"{events}/{events}" in tty


# -- off ----------------------------------------------------------------------------------


def test_no_progress_writes_nothing_even_on_a_terminal(tmp_path, ledger):
    mcap = tmp_path / "out.mcap"
    code, out, tty = run_on_pty(["export-mcap", "--ledger", str(ledger), "--out", str(mcap),
                                 "--no-progress"])
    assert code == 0 and out.startswith("exported ")
    assert tty == ""
    done = subprocess.run([STOCKPILE, "replay", str(mcap), "--ledger", str(tmp_path / "c.duckdb"),
                           "--no-progress"], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0 and done.stderr == "", done.stderr


def test_disabled_and_automatic_at_the_api_level(tmp_path):
    master, slave = pty.openpty()
    try:
        with open(slave, "w", closefd=False) as terminal, open(tmp_path / "log", "w") as log:
            for stream in (terminal, log):
                with progress(total=10, desc="off", enabled=False, stream=stream) as bar:
                    bar.update(10)
            # automatic: nothing on a file, a bar on a terminal
            with progress(total=10, desc="auto", stream=log) as bar:
                bar.update(10)
            with progress(total=10, desc="auto", stream=terminal) as bar:
                bar.update(10)
        written = os.read(master, 65536).decode()
    finally:
        os.close(master)
        os.close(slave)
    assert (tmp_path / "log").read_text() == ""
    assert "off" not in written and "auto" in written and "\r" in written


def test_enabled_from_args_reads_either_spelling():
    assert enabled_from_args(Namespace(no_progress=True)) is False
    assert enabled_from_args(Namespace(no_progress=False, progress=False)) is True
    assert enabled_from_args(Namespace(progress=False)) is False
    assert enabled_from_args(Namespace(progress=None)) is True
    assert enabled_from_args(Namespace()) is True
