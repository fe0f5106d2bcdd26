"""``stockpile run --config yard.toml``: config checks, and a real supervised yard.

The supervised run starts a Zenoh router on a free loopback port, the ledger service
and the localizer as child processes; the test kills the localizer with SIGKILL and
checks that it is restarted, then stops the whole yard with SIGTERM.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import zenoh

from ledger import open_ledger
from stockpile.run_config import ConfigError, load_config
from services.service import ZenohOptions
from tests.zenoh_helpers import free_port, log_lines, stockpile, stop, wait_liveliness, wait_until

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "docs" / "yard.example.toml"


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "stockpile.cli", *args], capture_output=True,
                          text=True, timeout=120, cwd=ROOT)


def test_the_example_config_checks_and_names_every_service_ledger_first():
    done = _run("run", "--config", str(EXAMPLE), "--check")
    assert done.returncode == 0, done.stderr
    commands = done.stdout.splitlines()
    assert [c.split()[2] for c in commands] == ["ledger", "localizer", "scanner", "gnss"]
    assert all("--site capelambert" in c and "--connect tls/127.0.0.1:7447" in c
               and "--tls-dir /srv/stockpile/pki" in c for c in commands)
    names = {c.split()[2]: c.split()[c.split().index("--tls-name") + 1] for c in commands}
    assert names == {"ledger": "ledger", "localizer": "bwr1.localizer",
                     "scanner": "bwr1.scanner", "gnss": "bwr1.gnss"}
    scanner = next(c for c in commands if c.split()[2] == "scanner")
    assert "--device /dev/ttyUSB0" in scanner and "--baud 500000" in scanner
    assert "--send-start" in scanner.split()


def test_bad_configs_fail_with_one_line_before_anything_starts(tmp_path):
    cases = {
        "unknown_service.toml": ('site = "s"\n[services.crusher]\n', "unknown service 'crusher'"),
        "typo.toml": ('site = "s"\n[services.ledger]\nledger = "x.duckdb"\nbatch_sise = 5\n',
                      "services.ledger: unrecognized arguments: --batch-sise 5"),
        "bad_value.toml": ('site = "s"\n[services.ledger]\nledger = "x.duckdb"\n'
                           'batch_interval = "soon"\n',
                           "services.ledger: argument --batch-interval: invalid float value"),
        "no_site.toml": ('[services.ledger]\nledger = "x.duckdb"\n', "'site'"),
        "not_toml.toml": ('site = "s\n', "not valid TOML"),
        "no_services.toml": ('site = "s"\n', "no [services.NAME] tables"),
    }
    for name, (text, reason) in cases.items():
        path = tmp_path / name
        path.write_text(text)
        done = _run("run", "--config", str(path), "--check")
        assert done.returncode == 2, (name, done.stdout, done.stderr)
        assert reason in done.stderr, (name, done.stderr)
        assert len(done.stderr.splitlines()) == 1, (name, done.stderr)   # no usage text
    missing = _run("run", "--config", str(tmp_path / "absent.toml"))
    assert missing.returncode == 2 and "cannot read" in missing.stderr


def test_load_config_keeps_instance_names_and_orders_the_ledger_first(tmp_path):
    path = tmp_path / "yard.toml"
    path.write_text('site = "s"\n[services.scanner-east]\nservice = "scanner"\ndevice = "/dev/a"\n'
                    '[services.ledger]\nledger = "l.duckdb"\n')
    config = load_config(path)
    assert [(e.name, e.service) for e in config.services] == [("ledger", "ledger"),
                                                             ("scanner-east", "scanner")]
    path.write_text('site = "s"\n[zenoh]\nconnect = 7\n[services.ledger]\nledger = "l"\n')
    try:
        load_config(path)
    except ConfigError as exc:
        assert "zenoh.connect" in str(exc)
    else:
        raise AssertionError("a non-string endpoint was accepted")


def _pki(*args: str) -> None:
    done = _run("pki", *args)
    assert done.returncode == 0, done.stderr


def test_a_supervised_yard_restarts_a_killed_service_and_stops_cleanly(tmp_path):
    """Over mutual TLS with the access control generated from the site PKI."""
    pki = tmp_path / "pki"
    _pki("init", "--site", "testyard", "--out", str(pki))
    for role, name in (("router", "router"), ("ledger", "ledger"),
                       ("localizer", "bwr1.localizer"), ("auditor", "watch1")):
        _pki("issue", "--ca", str(pki), "--role", role, "--name", name)
    endpoint = f"tls/127.0.0.1:{free_port()}"
    ledger_path = tmp_path / "ledger.duckdb"
    config = tmp_path / "yard.toml"
    config.write_text(f"""
site = "testyard"
restart_delay_s = 0.2
[zenoh]
mode = "client"
connect = ["{endpoint}"]
[tls]
dir = "{pki}"
[router]
listen = ["{endpoint}"]
[services.ledger]
ledger = "{ledger_path}"
clock = "wall"
[services.localizer]
machine = "bwr1"
tls_name = "bwr1.localizer"
""")
    log = tmp_path / "run.log"
    process = stockpile("run", "--config", str(config), stderr_path=log)
    try:
        wait_until(lambda: any(r.get("msg") == "router" for r in log_lines(log)), 60,
                   "the supervisor's router")
        session = zenoh.open(ZenohOptions(mode="client", connect=(endpoint,), tls_dir=str(pki),
                                          tls_name="watch1").to_config())
        try:
            wait_liveliness(session, "stockpile/testyard/@live/ledger/**", 60)
            wait_liveliness(session, "stockpile/testyard/@live/localizer/**", 60)
        finally:
            session.close()

        def started(name: str) -> list[int]:
            return [int(r["pid"]) for r in log_lines(log)
                    if r.get("service") == "run" and r.get("msg") == "started"
                    and r.get("name") == name]

        [first_pid] = started("localizer")
        os.kill(first_pid, signal.SIGKILL)
        wait_until(lambda: len(started("localizer")) == 2, 60, "the localizer's restart")
        exited = [r for r in log_lines(log) if r.get("msg") == "exited"]
        assert exited and exited[0]["name"] == "localizer"
        assert int(exited[0]["code"]) == -signal.SIGKILL
        assert started("localizer")[1] != first_pid
        wait_until(lambda: sum(1 for r in log_lines(log) if r.get("service") == "localizer"
                               and r.get("msg") == "ready") == 2, 60,
                   "the restarted localizer's token")
        assert len(started("ledger")) == 1  # the ledger was never touched
    finally:
        code = stop(process, 60)
    assert code == 0
    records = log_lines(log)
    stopped = [r["name"] for r in records if r.get("service") == "run" and r.get("msg") == "stopped"]
    assert stopped == ["localizer", "ledger"]  # reverse order: the ledger last
    assert "Traceback" not in log.read_text()
    with open_ledger(ledger_path, read_only=True) as store:  # the writer let go of the file
        assert store.verify().ok
