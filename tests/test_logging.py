"""Logging through the standard logging module and structlog (common/logs.py): logfmt and
JSON lines, levels, Python warnings in the same stream, and a real service process whose
stderr holds nothing but log lines."""

from __future__ import annotations

import argparse
import io
import json
import logging
import os
import subprocess
import sys

import pytest

from common.logs import (
    ENV_FORMAT,
    add_logging_options,
    configure_from_args,
    configure_logging,
    get_logger,
    parse_log_line,
    parse_logfmt,
)
from services.logfmt import format_log, log
from stockpile.orchestrate import Child
from zenoh_helpers import open_router, stockpile, stop, wait_liveliness, wait_until


@pytest.fixture(autouse=True)
def default_logging(monkeypatch):
    """Each test starts and ends with the default configuration (and no format in the
    environment: configure_from_args exports it)."""
    for name in (ENV_FORMAT, "STOCKPILE_LOG_LEVEL"):
        monkeypatch.setenv(name, "")      # so that teardown restores what was there
        monkeypatch.delenv(name)
    yield
    configure_logging()


def _lines(stream: io.StringIO) -> list[str]:
    return stream.getvalue().splitlines()


def test_logfmt_lines_keep_the_prefix_and_the_field_order():
    out = io.StringIO()
    configure_logging("info", "logfmt", stream=out)
    log("scanner", "published", source="bwr1.scanner", epoch=17, count=1200)
    log("ledger", "gap opened", level="warning", source="s 1", first_seq=3, ratio=0.25)
    log("run", "started", name="ledger", msg_count=2)   # fields named like emit's arguments
    log("scanner", "status", level="status", published_per_s=12.5, errors=0)
    lines = _lines(out)
    assert len(lines) == 4, lines
    assert lines[0].startswith("ts=") and " level=info service=scanner msg=published " \
        "source=bwr1.scanner epoch=17 count=1200" in lines[0]
    records = [parse_logfmt(line) for line in lines]
    assert list(records[1]) == ["ts", "level", "service", "msg", "source", "first_seq", "ratio"]
    assert records[1]["level"] == "warning" and records[1]["msg"] == "gap opened"
    assert records[1]["source"] == "s 1" and records[1]["ratio"] == "0.25"
    assert records[2]["name"] == "ledger" and records[2]["service"] == "run"
    assert records[3]["level"] == "status" and records[3]["published_per_s"] == "12.5"
    # the same line format_log builds (apart from the time)
    expected = parse_logfmt(format_log("scanner", "info", "published",
                                       {"source": "bwr1.scanner", "epoch": 17, "count": 1200}))
    assert {k: v for k, v in records[0].items() if k != "ts"} == \
        {k: v for k, v in expected.items() if k != "ts"}


def test_json_lines_are_one_object_each_with_the_same_keys():
    out = io.StringIO()
    configure_logging("info", "json", stream=out)
    log("scanner", "published", source="bwr1.scanner", epoch=17, count=1200)
    log("ledger", "quarantined", level="warn", reason='bad "payload"\nsecond line')
    lines = _lines(out)
    assert len(lines) == 2, lines
    first, second = (json.loads(line) for line in lines)
    assert list(first) == ["ts", "level", "service", "msg", "source", "epoch", "count"]
    assert first["count"] == 1200 and first["service"] == "scanner"
    assert second["level"] == "warning" and second["reason"] == 'bad "payload"\nsecond line'
    assert parse_log_line(lines[0]) == first


def test_warning_level_suppresses_info_and_status_but_not_warnings():
    out = io.StringIO()
    configure_logging("warning", "logfmt", stream=out)
    log("ledger", "committed", head=3)
    log("ledger", "status", level="status", errors=0)
    log("ledger", "debugging", level="debug")
    log("ledger", "gap opened", level="warning", source="s")
    log("ledger", "writer failed", level="error", error="disk full")
    assert [parse_logfmt(line)["msg"] for line in _lines(out)] == ["gap opened", "writer failed"]


def test_structlog_loggers_write_the_same_lines():
    out = io.StringIO()
    configure_logging("info", "logfmt", stream=out)
    get_logger("stockpile.demo").info("hello", n=1, level_m=2.5)
    get_logger("stockpile.demo").debug("hidden")
    lines = _lines(out)
    assert len(lines) == 1, lines
    record = parse_logfmt(lines[0])
    assert list(record) == ["ts", "level", "service", "msg", "n", "level_m"]
    assert (record["level"], record["service"], record["msg"]) == ("info", "stockpile.demo",
                                                                  "hello")


def test_debug_level_shows_debug_lines():
    out = io.StringIO()
    configure_logging("debug", "logfmt", stream=out)
    log("ledger", "details", level="debug", n=1)
    assert [parse_logfmt(line)["level"] for line in _lines(out)] == ["debug"]


WARNING_SCRIPT = """
import logging, warnings
from common.logs import configure_logging
configure_logging("info", "json")
warnings.warn("this option is deprecated", DeprecationWarning)   # shown in __main__
warnings.warn("this option is going away", FutureWarning)
logging.getLogger("duckdb").warning("checkpoint took %d ms", 12)
import threading
def fail():
    raise RuntimeError("reader died")
worker = threading.Thread(target=fail, name="reader")
worker.start()
worker.join()
"""


def test_warnings_other_libraries_and_thread_crashes_go_to_the_same_stream():
    # a fresh interpreter: pytest records warnings itself in this one
    done = subprocess.run([sys.executable, "-c", WARNING_SCRIPT], capture_output=True,
                          text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert done.stdout == ""
    records = [json.loads(line) for line in done.stderr.splitlines()]
    assert len(records) == 4, records
    assert all(r["service"] == "py.warnings" and r["level"] == "warning" for r in records[:2])
    assert "DeprecationWarning: this option is deprecated" in records[0]["msg"]
    assert "FutureWarning: this option is going away" in records[1]["msg"]
    assert not records[1]["msg"].endswith("\n")
    assert records[2] == {"ts": records[2]["ts"], "level": "warning", "service": "duckdb",
                          "msg": "checkpoint took 12 ms"}
    # a thread's uncaught exception: one error line, the traceback inside it
    assert records[3]["level"] == "error" and records[3]["thread"] == "reader"
    assert records[3]["exception"].endswith("RuntimeError: reader died")


def test_an_exception_is_one_line_with_its_traceback():
    out = io.StringIO()
    configure_logging("info", "logfmt", stream=out)
    try:
        1 / 0
    except ZeroDivisionError:
        logging.getLogger("stockpile").exception("failed")
    lines = _lines(out)
    assert len(lines) == 1
    record = parse_logfmt(lines[0])
    assert record["level"] == "error" and "ZeroDivisionError" in record["exception"]


def test_bad_level_or_format_is_refused():
    with pytest.raises(ValueError, match="log level"):
        configure_logging("loud")
    with pytest.raises(ValueError, match="log format"):
        configure_logging("info", "xml")


def test_command_line_options(capsys):
    parser = argparse.ArgumentParser()
    add_logging_options(parser)
    args = parser.parse_args(["--quiet"])
    configure_from_args(args)
    log("demo", "started")
    log("demo", "something odd", level="warning")
    err = capsys.readouterr().err.splitlines()
    assert [parse_logfmt(line)["msg"] for line in err] == ["something odd"]

    configure_from_args(parser.parse_args(["--log-level", "debug", "--log-format", "json"]))
    log("demo", "details", level="debug")
    assert json.loads(capsys.readouterr().err)["msg"] == "details"
    assert os.environ[ENV_FORMAT] == "json"       # child processes write the same format

    with pytest.raises(SystemExit):
        parser.parse_args(["--log-level", "verbose"])


def test_the_environment_gives_the_defaults_and_a_bad_value_is_ignored(monkeypatch, capsys):
    parser = argparse.ArgumentParser()
    add_logging_options(parser)
    monkeypatch.setenv(ENV_FORMAT, "json")
    monkeypatch.setenv("STOCKPILE_LOG_LEVEL", "error")
    configure_from_args(parser.parse_args([]))
    log("demo", "gap", level="warning")
    log("demo", "failed", level="error")
    assert [json.loads(line)["msg"] for line in capsys.readouterr().err.splitlines()] == \
        ["failed"]
    monkeypatch.setenv(ENV_FORMAT, "xml")
    monkeypatch.setenv("STOCKPILE_LOG_LEVEL", "loud")
    configure_from_args(parser.parse_args([]))
    log("demo", "started")
    assert parse_logfmt(capsys.readouterr().err.strip())["msg"] == "started"


@pytest.mark.parametrize("fmt", ["logfmt", "json"])
def test_a_service_process_writes_only_log_lines_on_stderr(tmp_path, monkeypatch, fmt):
    monkeypatch.setenv(ENV_FORMAT, fmt)          # what configure_from_args exports
    router, endpoint = open_router()
    err, out = tmp_path / "ledger.log", tmp_path / "ledger.out"
    process = stockpile("service", "ledger", "--ledger", str(tmp_path / "ledger.duckdb"),
                        "--site", "logs", "--status-period", "0.2", "--mode", "client",
                        "--connect", endpoint, stderr_path=err, stdout_path=out)
    try:
        wait_liveliness(router, "stockpile/logs/@live/ledger/**", 30)
        wait_until(lambda: "status" in err.read_text(), 30, "a status line")
        assert stop(process) == 0, err.read_text()[-3000:]
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
        router.close()
    lines = err.read_text().splitlines()
    if fmt == "json":
        records = [json.loads(line) for line in lines]
    else:
        assert all(line.startswith("ts=") for line in lines), lines
        records = [parse_logfmt(line) for line in lines]
    assert all(list(r)[:4] == ["ts", "level", "service", "msg"] for r in records), records
    msgs = [r["msg"] for r in records]
    assert msgs[0] == "started" and msgs[-1] == "stopped", msgs
    assert {"ready", "status", "committed"} <= set(msgs), msgs
    assert {r["level"] for r in records if r["msg"] == "status"} == {"status"}
    assert out.read_text() == ""


def test_the_supervisor_reads_its_childrens_lines_in_either_format(tmp_path):
    path = tmp_path / "child.log"
    path.write_text(
        format_log("scanner", "info", "published", {"source": "a.scanner", "epoch": 7,
                                                    "count": 12}) + "\n"
        + json.dumps({"ts": "2026-11-22T10:00:00.000Z", "level": "info", "service": "gnss",
                      "msg": "published", "source": "a.gnss", "epoch": 8, "count": 3}) + "\n"
        + "not a log line\n" + '{"ts": "2026-11-22T10:00:0')      # a line being written
    child = Child("x", [], None, path, tmp_path / "child.out")
    assert child.published() == {"a.scanner": (7, 12), "a.gnss": (8, 3)}
