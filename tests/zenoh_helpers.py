"""Helpers the Zenoh process tests share: free ports, a loopback router, child processes."""

from __future__ import annotations

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

from services.service import ZenohOptions, parse_logfmt

PYTHON = sys.executable


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def open_router() -> tuple[zenoh.Session, str]:
    """A router-mode session on a free loopback port (scouting off); returns (session, endpoint)."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    session = zenoh.open(ZenohOptions(mode="router", listen=(endpoint,)).to_config())
    return session, endpoint


def client_args(endpoint: str) -> list[str]:
    return ["--mode", "client", "--connect", endpoint]


def stockpile(*args: str, stderr_path: Path | None = None, stdout_path: Path | None = None,
              ) -> subprocess.Popen:
    """Start ``stockpile ARGS`` as a child process (its stderr to a file, for its log lines)."""
    stderr = open(stderr_path, "w") if stderr_path else subprocess.DEVNULL
    stdout = open(stdout_path, "w") if stdout_path else subprocess.DEVNULL
    return subprocess.Popen([PYTHON, "-m", "services.cli", *args], stderr=stderr, stdout=stdout,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})


def stop(process: subprocess.Popen, timeout_s: float = 30.0) -> int:
    """SIGTERM and wait; SIGKILL if it does not stop in time (and fail loudly)."""
    if process.poll() is None:
        process.send_signal(signal.SIGTERM)
    try:
        return process.wait(timeout_s)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait()
        raise AssertionError(f"process {process.args} ignored SIGTERM for {timeout_s} s")


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


def wait_liveliness(session: zenoh.Session, key: str, timeout_s: float) -> None:
    """Block until a liveliness token matching ``key`` exists (a service is up)."""
    seen = threading.Event()
    sub = session.liveliness().declare_subscriber(key, lambda s: seen.set(), history=True)
    try:
        if not seen.wait(timeout_s):
            raise AssertionError(f"no liveliness token {key} within {timeout_s} s")
    finally:
        sub.undeclare()
