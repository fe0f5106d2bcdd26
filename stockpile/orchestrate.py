"""Start, watch and stop the yard's processes (``stockpile demo``, ``stockpile run``).

A :class:`Supervisor` owns a loopback Zenoh router (a router-mode session in this
process, scouting off) and the child processes wired to it as Zenoh clients.  Given
``members`` (``{certificate name: role}``), the links are mutual TLS: the supervisor
makes a throw-away site PKI in ``<out>/pki`` (a CA and one certificate per member, valid
for two days), and its router enforces the access control generated for those roles
(:mod:`services.acl`); each child then connects with its own certificate
(:meth:`Supervisor.client_args_for`).  Without ``members``, plain TCP on loopback.  Each
child's stderr (its log lines) goes to ``<logs>/<name>.log`` and stdout to
``<logs>/<name>.out``.  Stopping is orderly: producers first, the ledger last,
SIGTERM with a deadline, then SIGKILL (reported).
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import zenoh

from security.pki import init_ca, issue
from services.acl import access_control
from services.logfmt import parse_log_line
from services.service import ZenohOptions, log

#: validity of the throw-away PKI a supervised yard makes for itself, days
THROWAWAY_PKI_DAYS = 2


def free_loopback_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@dataclass
class Child:
    """One supervised process."""

    name: str
    argv: list[str]
    process: subprocess.Popen
    log_path: Path
    out_path: Path
    stdout_lines: list[str] = field(default_factory=list)
    _reader: threading.Thread | None = None

    def log_records(self) -> list[dict]:
        """The child's log lines so far (logfmt or JSON lines), as dicts."""
        if not self.log_path.exists():
            return []
        lines = self.log_path.read_text(errors="replace").splitlines()
        return [record for record in map(parse_log_line, lines) if record is not None]

    def published(self) -> dict[str, tuple[int, int]]:
        """``source -> (epoch, count)`` from the child's ``published`` lines."""
        out = {}
        for record in self.log_records():
            if record.get("msg") == "published" and "source" in record:
                out[record["source"]] = (int(record["epoch"]), int(record["count"]))
        return out

    def wait_stdout(self, predicate: Callable[[str], bool], timeout_s: float) -> str:
        """Block until a stdout line satisfies ``predicate``; return it."""
        deadline = time.monotonic() + timeout_s
        seen = 0
        while time.monotonic() < deadline:
            lines = list(self.stdout_lines)
            for line in lines[seen:]:
                if predicate(line):
                    return line
            seen = len(lines)
            if self.process.poll() is not None and self._reader is not None \
                    and not self._reader.is_alive():
                lines = list(self.stdout_lines)
                for line in lines[seen:]:
                    if predicate(line):
                        return line
                raise RuntimeError(f"{self.name} exited ({self.process.returncode}) before "
                                   f"printing the expected line; see {self.log_path}")
            time.sleep(0.02)
        raise TimeoutError(f"{self.name} did not print the expected line in {timeout_s:g} s")


class Supervisor:
    """A loopback router plus child processes; a context manager that always cleans up."""

    def __init__(self, out_dir: Path, *, site: str, quiet: bool = False,
                 members: dict[str, str] | None = None) -> None:
        self.out_dir = Path(out_dir)
        self.logs = self.out_dir / "logs"
        self.logs.mkdir(parents=True, exist_ok=True)
        self.site = site
        self.quiet = quiet
        self.members = dict(members or {})
        self.pki: Path | None = None
        port = free_loopback_port()
        if self.members:
            self.pki = self._make_pki()
            self.endpoint = f"tls/127.0.0.1:{port}"
            router = ZenohOptions(mode="router", listen=(self.endpoint,), tls_dir=str(self.pki),
                                  tls_name="router")
            config = router.to_config()
            config.insert_json5("access_control",
                                json.dumps(access_control(site, self.members)))
        else:
            self.endpoint = f"tcp/127.0.0.1:{port}"
            config = ZenohOptions(mode="router", listen=(self.endpoint,)).to_config()
        self.session = zenoh.open(config)
        self.children: dict[str, Child] = {}

    def _make_pki(self) -> Path:
        """A fresh throw-away site PKI in ``<out>/pki``: a CA, the router and every member."""
        pki = self.out_dir / "pki"
        # the CA a day longer than its certificates, issued moments after it
        init_ca(self.site, pki, valid_days=THROWAWAY_PKI_DAYS + 1, force=True)
        for name, role in {"router": "router", **self.members}.items():
            issue(pki, role, name, valid_days=THROWAWAY_PKI_DAYS, force=True)
        if not self.quiet:
            log("demo", "throw-away PKI", dir=str(pki), certificates=len(self.members) + 1)
        return pki

    @property
    def client_args(self) -> list[str]:
        """Zenoh options of a child without a certificate (plain TCP yards only)."""
        if self.pki is not None:
            raise ValueError("a TLS yard's children connect with their own certificate: "
                             "use client_args_for(name)")
        return ZenohOptions(mode="client", connect=(self.endpoint,)).to_argv()

    def client_args_for(self, name: str) -> list[str]:
        """Zenoh options of the child holding certificate ``name`` (plain TCP yards: the
        same for every child)."""
        if self.pki is None:
            return ZenohOptions(mode="client", connect=(self.endpoint,)).to_argv()
        if name not in self.members:
            raise ValueError(f"no certificate {name!r} in this yard (members: "
                             f"{', '.join(sorted(self.members))})")
        return ZenohOptions(mode="client", connect=(self.endpoint,), tls_dir=str(self.pki),
                            tls_name=name).to_argv()

    def start(self, name: str, args: list[str]) -> Child:
        """Start ``stockpile ARGS`` (this interpreter) as child ``name``."""
        argv = [sys.executable, "-m", "stockpile.cli", *args]
        log_path, out_path = self.logs / f"{name}.log", self.logs / f"{name}.out"
        process = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=open(log_path, "w"),
                                   text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"})
        child = Child(name, argv, process, log_path, out_path)

        def pump() -> None:
            with open(out_path, "w") as out:
                assert process.stdout is not None
                for line in process.stdout:
                    out.write(line)
                    out.flush()
                    child.stdout_lines.append(line.rstrip("\n"))

        child._reader = threading.Thread(target=pump, name=f"{name}-stdout", daemon=True)
        child._reader.start()
        self.children[name] = child
        if not self.quiet:
            log("demo", "started", child=name, pid=process.pid, log=str(log_path))
        return child

    def wait_live(self, service: str, timeout_s: float = 60.0) -> None:
        """Block until ``stockpile/<site>/@live/<service>/**`` exists."""
        seen = threading.Event()
        key = f"stockpile/{self.site}/@live/{service}/**"
        sub = self.session.liveliness().declare_subscriber(key, lambda _s: seen.set(),
                                                            history=True)
        try:
            deadline = time.monotonic() + timeout_s
            while not seen.wait(0.2):
                for child in self.children.values():
                    if child.process.poll() is not None and child.process.returncode != 0:
                        raise RuntimeError(f"{child.name} exited with {child.process.returncode}; "
                                           f"see {child.log_path}")
                if time.monotonic() > deadline:
                    raise TimeoutError(f"{key} did not appear in {timeout_s:g} s")
        finally:
            sub.undeclare()

    def wait_exit(self, name: str, timeout_s: float) -> int | None:
        try:
            return self.children[name].process.wait(timeout_s)
        except subprocess.TimeoutExpired:
            return None

    def stop(self, name: str, timeout_s: float = 30.0) -> int:
        """SIGTERM ``name`` and wait; SIGKILL after ``timeout_s`` (logged)."""
        child = self.children[name]
        if child.process.poll() is None:
            child.process.send_signal(signal.SIGTERM)
            try:
                child.process.wait(timeout_s)
            except subprocess.TimeoutExpired:
                log("demo", "killing a child that ignored SIGTERM", level="error", child=name)
                child.process.kill()
                child.process.wait()
        if child._reader is not None:
            child._reader.join(timeout=5.0)
        return child.process.returncode

    def close(self) -> None:
        for name in reversed(list(self.children)):
            if self.children[name].process.poll() is None:
                self.stop(name, timeout_s=15.0)
        self.session.close()

    def __enter__(self) -> Supervisor:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def fresh_ledger_path(path: Path) -> Path:
    """``path`` with any ledger file (and its ``.wal`` and head sidecar) already there removed."""
    for suffix in ("", ".wal", ".head"):
        candidate = Path(str(path) + suffix)
        if candidate.exists():
            candidate.unlink()
    return path
