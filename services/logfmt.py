"""Structured log lines, the one format every service writes on stderr.

:func:`log` logs ``ts=... level=... service=... msg=... key=value ...`` through the
standard :mod:`logging` module and structlog (:mod:`common.logs`: logfmt by default,
JSON lines with ``--log-format json``, filtered by ``--log-level``), on the stdlib
logger ``stockpile.<service>``.  :func:`format_log` builds one logfmt line and
:func:`parse_logfmt` reads one back (the demo and the tests compare what services
logged with the ledger); :func:`parse_log_line` reads a line of either format.
"""

from __future__ import annotations

import time
from typing import Any

from common.logs import emit, format_logfmt, format_timestamp, parse_log_line, parse_logfmt
from schemas.times import NS_PER_S

__all__ = ["format_log", "log", "parse_log_line", "parse_logfmt"]


def format_log(service: str, level: str, msg: str, fields: dict[str, Any],
               now_ns: int | None = None) -> str:
    """One logfmt line: ``ts=... level=... service=... msg=... key=value ...``."""
    now_ns = time.time_ns() if now_ns is None else now_ns
    return format_logfmt({"ts": format_timestamp(now_ns / NS_PER_S), "level": level,
                          "service": service, "msg": msg, **fields})

def log(service: str, msg: str, *, level: str = "info", **fields: Any) -> None:
    """Log one structured line for ``service`` at ``level`` (``debug``, ``info``,
    ``status``, ``warning``/``warn``, ``error``) with ``fields`` in the order given
    (thread-safe; on stderr unless :func:`common.logs.configure_logging` said otherwise)."""
    emit(f"stockpile.{service}", level, msg, service=service, **fields)
