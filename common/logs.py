"""Logging for every command and service: the standard :mod:`logging` module with structlog.

One handler on the root logger writes one line per record on stderr, either logfmt
(default)::

    ts=2026-11-22T10:00:00.000Z level=info service=scanner msg=published source=bwr1.scanner count=1200

or, with ``fmt="json"``, one JSON object per line with the same keys in the same order
(for log collectors).  Records of other libraries' loggers and Python warnings
(:func:`logging.captureWarnings`, e.g. duckdb's) go through the same handler, with
``service`` set to the logger's name (``py.warnings`` for warnings), and so does a
thread's uncaught exception (one error line with its traceback in ``exception``).

- :func:`configure_logging` sets the level, the format and the stream (idempotent: a
  second call replaces the first one's handler);
- :func:`ensure_configured` configures with the defaults, unless something already did
  (what :func:`get_logger` calls, so a service logs correctly without any setup);
- :func:`add_logging_options` / :func:`configure_from_args`: ``--log-level``,
  ``--log-format``, ``--quiet`` on a command line;
- :func:`format_logfmt` / :func:`parse_logfmt`: one logfmt line and back.

Levels are the standard ones plus ``status`` (:data:`STATUS`, between info and
warning: a service's periodic status line).  The environment variables
``STOCKPILE_LOG_LEVEL`` and ``STOCKPILE_LOG_FORMAT`` give the defaults;
:func:`configure_from_args` sets the format one, so child processes started by a
command (``stockpile demo``/``run``) write the same format (:func:`parse_log_line`
reads either).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import threading
import time
from typing import Any, Mapping, TextIO

import structlog

__all__ = [
    "FORMATS", "LEVELS", "STATUS", "add_logging_options", "configure_from_args",
    "configure_logging", "emit", "ensure_configured", "format_logfmt", "format_timestamp", "get_logger",
    "level_number", "parse_log_line", "parse_logfmt",
]

#: the ``status`` level (numeric, between INFO 20 and WARNING 30): a service's status line
STATUS = 25
logging.addLevelName(STATUS, "STATUS")

#: the level names ``--log-level`` accepts
LEVELS = ("debug", "info", "warning", "error")
#: the line formats ``--log-format`` accepts
FORMATS = ("logfmt", "json")

#: environment variables holding the default level and format (set by configure_from_args)
ENV_LEVEL, ENV_FORMAT = "STOCKPILE_LOG_LEVEL", "STOCKPILE_LOG_FORMAT"

_LEVEL_NUMBERS = {"debug": logging.DEBUG, "info": logging.INFO, "status": STATUS,
                  "warn": logging.WARNING, "warning": logging.WARNING,
                  "error": logging.ERROR, "critical": logging.CRITICAL}

_lock = threading.Lock()
_handler: logging.Handler | None = None


def level_number(level: str | int) -> int:
    """The :mod:`logging` number of a level name (``warn`` = ``warning``); ValueError if unknown."""
    if isinstance(level, int):
        return level
    try:
        return _LEVEL_NUMBERS[level.lower()]
    except KeyError:
        raise ValueError(f"unknown log level {level!r} (one of {', '.join(LEVELS)})") from None


def _logfmt_value(value: Any) -> str:
    text = f"{value:.6g}" if isinstance(value, float) else str(value)
    if text == "" or any(c in text for c in ' ="\\\n\t'):
        return json.dumps(text)
    return text


def format_timestamp(seconds: float) -> str:
    """``2026-11-22T10:00:00.000Z`` (UTC, milliseconds) for a time in seconds since the epoch."""
    ms = int(seconds * 1000)
    secs, ms = divmod(ms, 1000)
    return time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(secs)) + f".{ms:03d}Z"


def format_logfmt(record: Mapping[str, Any]) -> str:
    """One logfmt line of ``key=value`` pairs in the mapping's order (values quoted as JSON
    strings when they hold a space, ``=``, a quote, a backslash or a control character)."""
    return " ".join(f"{k}={_logfmt_value(v)}" for k, v in record.items())


def parse_logfmt(line: str) -> dict[str, str]:
    """Inverse of :func:`format_logfmt` for one line (tests and the demo read logs back)."""
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
            value, end = json.JSONDecoder().raw_decode(line, j)
            out[key] = value
            i = end
        else:
            end = line.find(" ", j)
            end = n if end < 0 else end
            out[key] = line[j:end]
            i = end
    return out


#: keys of an event dict that are not fields of the line
_INTERNAL = ("_record", "_from_structlog", "event", "service", "exc_info", "stack_info")


def _ordered(event_dict: dict[str, Any]) -> dict[str, Any]:
    """``ts, level, service, msg`` then the record's own fields in the order given."""
    record: logging.LogRecord | None = event_dict.get("_record")
    created = record.created if record is not None else time.time()
    levelname = record.levelname if record is not None else str(event_dict.get("level", "info"))
    service = event_dict.get("service") or (record.name if record is not None else "")
    out: dict[str, Any] = {"ts": format_timestamp(created), "level": levelname.lower(),
                           "service": service, "msg": event_dict.get("event", "")}
    if not event_dict.get("_from_structlog") and isinstance(out["msg"], str):
        out["msg"] = out["msg"].rstrip()      # a warning's text ends with a newline
    out.update((k, v) for k, v in event_dict.items() if k not in _INTERNAL)
    exc_info = event_dict.get("exc_info")
    if isinstance(exc_info, BaseException):
        exc_info = (type(exc_info), exc_info, exc_info.__traceback__)
    elif exc_info is True:
        exc_info = sys.exc_info()
    if isinstance(exc_info, tuple) and exc_info[0] is not None:
        out["exception"] = logging.Formatter().formatException(exc_info)
    return out


def _render_logfmt(_logger: Any, _name: str, event_dict: dict[str, Any]) -> str:
    return format_logfmt(_ordered(event_dict))


def _render_json(_logger: Any, _name: str, event_dict: dict[str, Any]) -> str:
    return json.dumps(_ordered(event_dict), default=str, ensure_ascii=False)


class _Stderr(logging.StreamHandler):
    """A handler on whatever ``sys.stderr`` is when it writes (so redirections apply)."""

    def __init__(self) -> None:
        super().__init__(sys.stderr)

    @property  # type: ignore[override]
    def stream(self) -> TextIO:
        return sys.stderr

    @stream.setter
    def stream(self, _value: TextIO) -> None:
        pass


def configure_logging(level: str = "info", fmt: str = "logfmt",
                      stream: TextIO | None = None) -> None:
    """Log records of ``level`` and above on ``stream`` (stderr by default) as ``fmt``
    (``logfmt`` or ``json``) lines, through the root logger; route Python warnings
    there too.  ValueError for an unknown level or format."""
    global _handler
    number = level_number(level)
    if fmt not in FORMATS:
        raise ValueError(f"unknown log format {fmt!r} (one of {', '.join(FORMATS)})")
    renderer = _render_json if fmt == "json" else _render_logfmt
    handler: logging.Handler = _Stderr() if stream is None else logging.StreamHandler(stream)
    handler.setFormatter(structlog.stdlib.ProcessorFormatter(
        processors=[renderer]))
    root = logging.getLogger()
    with _lock:
        if _handler is not None:
            root.removeHandler(_handler)
        root.addHandler(handler)
        root.setLevel(number)
        _handler = handler
        structlog.configure(
            processors=[structlog.stdlib.filter_by_level,
                        structlog.stdlib.ProcessorFormatter.wrap_for_formatter],
            logger_factory=structlog.stdlib.LoggerFactory(),
            wrapper_class=structlog.stdlib.BoundLogger,
            cache_logger_on_first_use=False)
    logging.captureWarnings(True)
    if threading.excepthook is threading.__excepthook__:     # not replaced by a test runner
        threading.excepthook = _log_thread_exception


def _log_thread_exception(args: threading.ExceptHookArgs) -> None:
    """A thread's uncaught exception as one error line (not a bare traceback on stderr)."""
    if args.exc_type is SystemExit:
        return
    name = args.thread.name if args.thread is not None else "?"
    emit("stockpile.thread", "error", "uncaught exception in a thread", thread=name,
         exc_info=(args.exc_type, args.exc_value, args.exc_traceback))


def ensure_configured() -> None:
    """Configure with the defaults (``STOCKPILE_LOG_LEVEL``/``_FORMAT`` or info, logfmt)
    unless :func:`configure_logging` already ran."""
    if _handler is None:
        configure_logging(_from_env(ENV_LEVEL, LEVELS) or "info",
                          _from_env(ENV_FORMAT, FORMATS) or "logfmt")


def _from_env(name: str, allowed: tuple[str, ...]) -> str | None:
    """The environment variable ``name`` if it holds one of ``allowed`` (else None)."""
    value = os.environ.get(name, "").strip().lower()
    return value if value in allowed else None


def get_logger(name: str = "stockpile") -> Any:
    """A structlog logger on the stdlib logger ``name`` (configuring the defaults first)."""
    ensure_configured()
    return structlog.get_logger(name)


def emit(name: str, level: str | int, msg: str, /, **fields: Any) -> None:
    """Log ``msg`` with ``fields`` (kept in order) at ``level`` on the stdlib logger
    ``name`` through structlog's formatter (configuring the defaults first).  Unlike
    :func:`get_logger`'s methods it takes any level, :data:`STATUS` included."""
    ensure_configured()
    number = level_number(level)
    logger = logging.getLogger(name)
    if logger.isEnabledFor(number):
        # the event dict as structlog's wrap_for_formatter hands it to the stdlib logger
        logger.log(number, {"event": msg, **fields},
                   extra={"_logger": logger, "_name": logging.getLevelName(number).lower()})


def parse_log_line(line: str) -> dict[str, Any] | None:
    """One log line of either format as a dict (``None`` for a line that is neither:
    not ``ts=...`` logfmt, not a JSON object)."""
    if line.startswith("ts="):
        return parse_logfmt(line)
    if line.startswith("{"):
        try:
            record = json.loads(line)
        except ValueError:
            return None
        return record if isinstance(record, dict) else None
    return None


def add_logging_options(parser: argparse.ArgumentParser) -> None:
    """Add ``--log-level``, ``--log-format`` and ``--quiet`` (= ``--log-level warning``)."""
    group = parser.add_argument_group("logging")
    group.add_argument("--log-level", choices=LEVELS, default=None,
                       help="lowest level logged on stderr (default info)")
    group.add_argument("--log-format", choices=FORMATS, default=None,
                       help="log line format on stderr: logfmt, or json for collectors "
                            "(default logfmt)")
    group.add_argument("--quiet", action="store_true",
                       help="log warnings and errors only (= --log-level warning)")


def configure_from_args(args: argparse.Namespace) -> None:
    """Configure from :func:`add_logging_options`' options (``--log-level`` wins over
    ``--quiet``; unset ones from the environment, else info and logfmt).  A format given
    on the command line is exported in the environment so child processes (whose logs
    go to files) write the same format; the level is not: ``stockpile demo`` reads its
    children's info lines."""
    level = getattr(args, "log_level", None)
    if getattr(args, "quiet", False) and level is None:
        level = "warning"
    level = level or _from_env(ENV_LEVEL, LEVELS) or "info"
    given_fmt = getattr(args, "log_format", None)
    fmt = given_fmt or _from_env(ENV_FORMAT, FORMATS) or "logfmt"
    configure_logging(level, fmt)
    if given_fmt:
        os.environ[ENV_FORMAT] = given_fmt
