"""Structured log lines in logfmt, the one format every service writes on stderr.

:func:`log` writes ``ts=... level=... service=... msg=... key=value ...`` lines
(thread-safe), :func:`format_log` builds one, and :func:`parse_logfmt` reads one back
(the demo and the tests compare what services logged with the ledger).
"""

from __future__ import annotations

import json
import sys
import threading
import time
from typing import Any, TextIO

from schemas.times import NS_PER_S

__all__ = ["format_log", "log", "parse_logfmt"]

_log_lock = threading.Lock()


def _logfmt_value(value: Any) -> str:
    if isinstance(value, float):
        text = f"{value:.6g}"
    else:
        text = str(value)
    if text == "" or any(c in text for c in ' ="\\\n\t'):
        return json.dumps(text)
    return text


def format_log(service: str, level: str, msg: str, fields: dict[str, Any],
               now_ns: int | None = None) -> str:
    """One logfmt line: ``ts=... level=... service=... msg=... key=value ...``."""
    now_ns = time.time_ns() if now_ns is None else now_ns
    secs, ns = divmod(now_ns, NS_PER_S)
    ts = time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(secs)) + f".{ns // 1_000_000:03d}Z"
    parts = [f"ts={ts}", f"level={level}", f"service={_logfmt_value(service)}",
             f"msg={_logfmt_value(msg)}"]
    parts += [f"{k}={_logfmt_value(v)}" for k, v in fields.items()]
    return " ".join(parts)


def log(service: str, msg: str, *, level: str = "info", stream: TextIO | None = None,
        **fields: Any) -> None:
    """Write one structured log line on stderr (thread-safe)."""
    line = format_log(service, level, msg, fields)
    with _log_lock:
        out = stream or sys.stderr
        out.write(line + "\n")
        out.flush()


def parse_logfmt(line: str) -> dict[str, str]:
    """Inverse of :func:`format_log` for one line (tests and the demo read logs back)."""
    out: dict[str, str] = {}
    i, n = 0, len(line)
    while i < n:
        while i < n and line[i] == " ":
            i += 1
        eq = line.find("=", i)
        if eq < 0:
            break
        key = line[i:eq]
        j = eq + 1
        if j < n and line[j] == '"':
            decoder = json.JSONDecoder()
            value, end = decoder.raw_decode(line, j)
            out[key] = value
            i = end
        else:
            end = line.find(" ", j)
            end = n if end < 0 else end
            out[key] = line[j:end]
            i = end
    return out
