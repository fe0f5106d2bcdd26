"""Helpers the Zenoh process tests share: free ports, a loopback router, child processes."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Callable

import zenoh
import zenoh.ext as zext

from schemas import pb
from schemas.events import (
    encode_attachment,
    event_from_sample,
    key_expr,
    make_event,
    set_timestamp_ns,
)
from security.pki import init_ca, issue
from services.acl import access_control
from services.ledger_service import query_key
from services.router import load_members
from services.service import ZenohOptions, parse_logfmt

PYTHON = sys.executable


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def site_pki(directory: Path, site: str, members: dict[str, str]) -> Path:
    """A real site PKI in ``directory`` (``security.pki``): a CA, the router's certificate
    and one per member (``{name: role}``); returns the directory."""
    init_ca(site, directory)
    for name, role in {"router": "router", **members}.items():
        issue(directory, role, name)
    return Path(directory)


def open_router(pki: Path | None = None, site: str | None = None) -> tuple[zenoh.Session, str]:
    """A router-mode session on a free loopback port (scouting off); returns (session, endpoint).

    With ``pki`` (:func:`site_pki`): mutual TLS, and the access control generated for
    the PKI's certificates on ``site`` (the router's own session is not subject to it).
    """
    if pki is None:
        endpoint = f"tcp/127.0.0.1:{free_port()}"
        return zenoh.open(ZenohOptions(mode="router", listen=(endpoint,)).to_config()), endpoint
    endpoint = f"tls/127.0.0.1:{free_port()}"
    config = ZenohOptions(mode="router", listen=(endpoint,), tls_dir=str(pki),
                          tls_name="router").to_config()
    config.insert_json5("access_control", json.dumps(access_control(site, load_members(pki))))
    return zenoh.open(config), endpoint


def client_args(endpoint: str, pki: Path | None = None, name: str | None = None) -> list[str]:
    """A child's Zenoh options: a client of ``endpoint``, with certificate ``name`` of
    ``pki`` when given."""
    tls = ["--tls-dir", str(pki), "--tls-name", name] if pki is not None else []
    return ["--mode", "client", "--connect", endpoint, *tls]


def stockpile(*args: str, stderr_path: Path | None = None, stdout_path: Path | None = None,
              ) -> subprocess.Popen:
    """Start ``stockpile ARGS`` as a child process (its stderr to a file, for its log lines)."""
    stderr = open(stderr_path, "w") if stderr_path else subprocess.DEVNULL
    stdout = open(stdout_path, "w") if stdout_path else subprocess.DEVNULL
    process = subprocess.Popen([PYTHON, "-m", "stockpile.cli", *args], stderr=stderr,
                               stdout=stdout, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    process.stderr_path = stderr_path     # for stop()'s report on a process that hangs
    return process


def stop(process: subprocess.Popen, timeout_s: float = 30.0) -> int:
    """SIGTERM and wait; SIGKILL if it does not stop in time (and fail loudly)."""
    if process.poll() is None:
        process.send_signal(signal.SIGTERM)
    try:
        return process.wait(timeout_s)
    except subprocess.TimeoutExpired:
        stacks = _stacks_of(process)
        process.kill()
        process.wait()
        raise AssertionError(f"process {process.args} ignored SIGTERM for {timeout_s} s"
                             f"{stacks}") from None


def stop_all(*processes: subprocess.Popen | None, timeout_s: float = 30.0) -> list[int]:
    """:func:`stop` every process given (None skipped), each even when one before it hung;
    their exit codes, or the first hang's AssertionError once all are stopped (a hung
    dashboard must not leave its ledger service running after the test)."""
    codes, failure = [], None
    for process in processes:
        if process is None:
            continue
        try:
            codes.append(stop(process, timeout_s))
        except AssertionError as exc:
            failure = failure or exc
    if failure is not None:
        raise failure
    return codes


def _stacks_of(process: subprocess.Popen) -> str:
    """Ask a hung service for its threads' stacks (SIGUSR1, see stockpile.service_cli) and
    return the tail of its log, where they are written; "" without a log file."""
    path = getattr(process, "stderr_path", None)
    if path is None or not hasattr(signal, "SIGUSR1"):
        return ""
    size = Path(path).stat().st_size
    process.send_signal(signal.SIGUSR1)
    try:                       # the dump is written at once; give it a moment to land
        wait_until(lambda: Path(path).stat().st_size > size, 5, "the stack dump")
    except AssertionError:
        pass
    return (_signal_state(process.pid) + "; its log ends:\n"
            + Path(path).read_text(errors="replace")[-6000:])


def _signal_state(pid: int) -> str:
    """Where SIGTERM stands in a hung process (Linux /proc): pending, caught, ignored, and
    in how many threads blocked; "" elsewhere."""
    bit = 1 << (signal.SIGTERM - 1)

    def sigterm_in(status: Path, keys: tuple[str, ...]) -> dict[str, bool]:
        """For each signal mask ``key`` of a /proc status file (read once): SIGTERM's bit."""
        masks = dict(line.partition(":")[::2] for line in status.read_text().splitlines())
        return {key: bool(int(masks.get(key, "0").strip(), 16) & bit) for key in keys}

    try:
        process = sigterm_in(Path(f"/proc/{pid}/status"), ("ShdPnd", "SigCgt", "SigIgn"))
        flags = ", ".join(f"{key} {'yes' if on else 'no'}" for key, on in process.items())
        tasks = list(Path(f"/proc/{pid}/task").iterdir())
        blocked = sorted(t.name for t in tasks
                         if sigterm_in(t / "status", ("SigBlk",))["SigBlk"])
    except OSError:
        return ""
    return (f"; SIGTERM: {flags}, blocked in {len(blocked)} of {len(tasks)} threads"
            f" (by tid: {', '.join(blocked) or '-'})")


@contextlib.contextmanager
def service_on_a_stuck_ledger(service: str, log: Path, *args: str):
    """Start ``stockpile service SERVICE --site stuck ARGS`` (its stderr to ``log``)
    against a router whose ledger queryable takes every query and never answers; yield
    the process once its first query is held.  On the way out the process is killed if
    it still runs, and the queryable and the router are closed."""
    router, endpoint = open_router()
    held: list = []
    queryable = router.declare_queryable(query_key("stuck", "**"), held.append)
    process = stockpile("service", service, "--site", "stuck", *args, *client_args(endpoint),
                        stderr_path=log)
    try:
        wait_until(lambda: held or process.poll() is not None, 60,
                   f"the {service} service's first query")
        assert process.poll() is None, log.read_text()[-2000:]
        yield process
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
        held.clear()
        queryable.undeclare()
        router.close()


def log_lines(path: Path) -> list[dict[str, str]]:
    """The logfmt lines of a service's stderr file."""
    out = []
    for line in Path(path).read_text().splitlines():
        if line.startswith("ts="):
            out.append(parse_logfmt(line))
    return out


def wait_until(predicate: Callable[[], bool], timeout_s: float, what: str,
               interval_s: float = 0.05) -> None:
    """Poll ``predicate`` until true; AssertionError naming ``what`` after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")
        time.sleep(interval_s)



def wait_token(session: zenoh.Session, key: str, process, timeout_s: float) -> None:
    """Until a liveliness token matching ``key`` exists; fails at once if ``process`` exits."""
    seen = threading.Event()
    sub = session.liveliness().declare_subscriber(key, lambda s: seen.set(), history=True)
    try:
        wait_until(lambda: seen.is_set() or process.poll() is not None, timeout_s, key)
    finally:
        sub.undeclare()
    assert seen.is_set(), f"{process.args} exited with {process.returncode}"


def last_status(path: Path) -> dict[str, str]:
    """The last ``status`` log line a service wrote to ``path`` ({} before the first)."""
    lines = [line for line in log_lines(path) if line.get("msg") == "status"]
    return lines[-1] if lines else {}

def wait_liveliness(session: zenoh.Session, key: str, timeout_s: float) -> None:
    """Block until a liveliness token matching ``key`` exists (a service is up)."""
    seen = threading.Event()
    sub = session.liveliness().declare_subscriber(key, lambda s: seen.set(), history=True)
    try:
        if not seen.wait(timeout_s):
            raise AssertionError(f"no liveliness token {key} within {timeout_s} s")
    finally:
        sub.undeclare()


class EventSink:
    """A real subscriber on one type and source of a site's events: decoded, in arrival order."""

    def __init__(self, session: zenoh.Session, site: str, type_name: str, source: str,
                 timeout_s: float = 20.0) -> None:
        self.type_name, self.timeout_s = type_name, timeout_s
        self.events: list = []
        self._cond = threading.Condition()
        self._subscriber = zext.declare_advanced_subscriber(
            session, key_expr(site, type_name, source), self._on_sample,
            history=zext.HistoryConfig(detect_late_publishers=True),
            recovery=zext.RecoveryConfig(heartbeat=True))

    def _on_sample(self, sample) -> None:
        attachment = sample.attachment.to_bytes() if sample.attachment is not None else None
        event = event_from_sample(str(sample.key_expr), sample.payload.to_bytes(), attachment)
        with self._cond:
            self.events.append(event)
            self._cond.notify_all()

    def wait_for(self, n: int, process: subprocess.Popen, timeout_s: float | None = None) -> list:
        """Block until ``n`` events arrived (fail early if the service died)."""
        timeout_s = self.timeout_s if timeout_s is None else timeout_s
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while len(self.events) < n:
                remaining = deadline - time.monotonic()
                assert process.poll() is None, f"service exited with {process.returncode}"
                assert remaining > 0, (f"got {len(self.events)} of {n} {self.type_name} events in "
                                         f"{timeout_s} s")
                self._cond.wait(min(remaining, 0.5))
            return list(self.events)

    def close(self) -> None:
        self._subscriber.undeclare()


class SiteClock:
    """A site clock source, like the simulator's: ``clock`` events every ``period_s``,
    running in real time from ``start_ns`` (site UTC ns); ``site_ns(monotonic_ns)`` is its
    time at a local monotonic reading."""

    def __init__(self, session: zenoh.Session, site: str, start_ns: int,
                 period_s: float = 0.1) -> None:
        self.session, self.site = session, site
        self.start_ns, self.period_s = start_ns, period_s
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._origin_ns = 0

    def site_ns(self, monotonic_ns: int) -> int:
        return self.start_ns + (monotonic_ns - self._origin_ns)

    def _run(self) -> None:
        seq = 0
        while True:
            msg = pb.Clock()
            set_timestamp_ns(msg.time, self.site_ns(time.monotonic_ns()))
            event = make_event(msg, source="sim.clock", epoch=1, seq=seq)
            self.session.put(key_expr(self.site, "clock", "sim.clock"), event.payload,
                             attachment=encode_attachment(1, seq, event.valid_time_ns))
            seq += 1
            if self._stop.wait(self.period_s):  # the clock's period, not a synchronisation
                return

    def __enter__(self) -> "SiteClock":
        self._origin_ns = time.monotonic_ns()
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()


class LiveDashboard:
    """A running :func:`live_dashboard`: its router session, the dashboard's ``caught up``
    log line, its log file, and (after the block) both processes' exit codes."""

    def __init__(self, router: zenoh.Session, log: Path) -> None:
        self.router, self.log = router, log
        self.caught: dict = {}
        self.codes: list[int] | None = None


@contextlib.contextmanager
def live_dashboard(ledger_path: Path, site: str, piles: tuple[str, ...], out: Path,
                   logs: Path):
    """A real ledger service on ``ledger_path`` and ``stockpile service dashboard`` of
    ``piles`` following it, writing ``out``, on a fresh loopback router (their logs in
    ``logs``); yields a :class:`LiveDashboard` once the dashboard has caught up, and stops
    both (the ledger last) and the router when the block ends."""
    router, endpoint = open_router()
    run = LiveDashboard(router, logs / "dashboard.log")
    service = stockpile("service", "ledger", "--ledger", str(ledger_path), "--site", site,
                        "--status-period", "1", *client_args(endpoint),
                        stderr_path=logs / "ledger.log")
    dashboard = None
    try:
        wait_token(router, f"stockpile/{site}/@live/ledger/**", service, 30)
        dashboard = stockpile("service", "dashboard",
                              *[arg for pile in piles for arg in ("--pile", pile)],
                              "--site", site, "--out", str(out), "--every", "10min",
                              "--update-period-s", "0", "--status-period", "0.2",
                              *client_args(endpoint), stderr_path=run.log)
        token = "+".join(piles) if len(piles) > 1 else "**"
        wait_token(router, f"stockpile/{site}/@live/dashboard/{token}", dashboard, 90)
        run.caught = next(line for line in log_lines(run.log) if line["msg"] == "caught up")
        yield run
    finally:
        try:
            run.codes = stop_all(dashboard, service)
        finally:
            router.close()
