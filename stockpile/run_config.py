"""``stockpile run --config yard.toml``: start the services a site's config names.

The config (TOML; a documented example ships as ``docs/yard.example.toml``)::

    site = "capelambert"

    [zenoh]                      # shared by every service (the --mode/--connect/... options)
    mode = "client"
    connect = ["tcp/127.0.0.1:7447"]

    [tls]                        # mutual TLS on every link, access control by role
    dir = "/srv/stockpile/pki"   # the site PKI (stockpile pki): ca.pem, index.json, NAME.pem/key

    [router]                     # optional: run a Zenoh router here, on these endpoints
    listen = ["tls/127.0.0.1:7447"]
    uplink = "tls/hq.example.com:7447"   # optional: link to the head office's router,
    uplink_tls = "/srv/stockpile/hq-link" # with its CA and this site's uplink certificate

    [analytes]                   # optional: the site's declared analytes (schemas.analytes)
    declared = ["Fe", "SiO2", "Al2O3", "P", "LOI"]
    unknown = "quarantine"       # or "flag" (the default)

    [services.ledger]            # table name = service name, or set service = "..."
    ledger = "/var/lib/stockpile/ledger.duckdb"

    [services.scanner-east]
    service = "scanner"
    device = "/dev/ttyUSB0"

With ``[tls]``, each service connects with the certificate named by its table's
``tls_name`` (default: the table's name), and the router (``[router] tls_name``, default
``router``) enforces the access control generated from the PKI's index
(:mod:`services.acl`); with ``uplink`` it links to the head office's router
(:class:`services.router.Uplink`: ``uplink_tls``, ``uplink_name`` default
``<site>.router``, ``head_office_name`` default ``hq.router``; ``docs/deployment.md``).
Every other key of a service table becomes that service's
command-line option
(``batch_size = 500`` -> ``--batch-size 500``; ``true`` -> a bare flag; a list
repeats the option).  Services start in the order ledger, localizer, the rest;
a service that exits unexpectedly is restarted after ``restart_delay_s`` (default 2 s,
doubling up to 60 s while it keeps exiting, and back to ``restart_delay_s`` once it ran
for :data:`STABLE_RUN_S` before exiting); SIGINT/SIGTERM stops them in reverse order, the ledger last.
``[analytes]`` becomes every ledger service's ``--analytes`` and ``--unknown-analyte``.
"""

from __future__ import annotations

import argparse
import signal
import subprocess
import sys
import threading
import time
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from common.options import plain_text
from ledger.views import check_declared
from schemas.analytes import UNKNOWN_POLICIES, declared_list
from services.router import DEFAULT_HEAD_OFFICE, Uplink, load_members, site_router_config
from services.service import Stopper, ZenohOptions, log, open_session
from stockpile import service_cli
from stockpile.service_cli import SERVICE_MODULES

START_ORDER = ("ledger", "localizer")


#: a service that ran this long before exiting restarts after ``restart_delay_s`` again,
#: not after its doubled delay, seconds
STABLE_RUN_S = 60.0


class ConfigError(ValueError):
    """The yard config is unreadable or names something unknown."""


@dataclass(frozen=True)
class ServiceEntry:
    """One service instance of the config."""

    name: str
    service: str
    options: dict[str, Any] = field(default_factory=dict)
    tls_name: str = ""   # its certificate's name (with [tls])

    def argv(self, site: str, zenoh_argv: list[str], tls_dir: str | None = None) -> list[str]:
        args = ["service", self.service, "--site", site]
        if tls_dir:
            args += ["--tls-dir", tls_dir, "--tls-name", self.tls_name or self.name]
        for key, value in self.options.items():
            flag = "--" + key.replace("_", "-")
            if isinstance(value, bool):
                if value:
                    args.append(flag)
            elif isinstance(value, list):
                for item in value:
                    args += [flag, str(item)]
            else:
                args += [flag, str(value)]
        return args + zenoh_argv


@dataclass(frozen=True)
class YardConfig:
    site: str
    zenoh_argv: list[str]
    router_listen: list[str]
    services: list[ServiceEntry]
    restart_delay_s: float = 2.0
    tls_dir: str | None = None
    router_tls_name: str = "router"
    router_uplink: Uplink | None = None


def load_config(path: str | Path) -> YardConfig:
    """Parse and check a yard config; raises :class:`ConfigError` with the reason."""
    try:
        data = tomllib.loads(Path(path).read_text())
    except OSError as exc:
        raise ConfigError(f"cannot read {path}: {exc.strerror}") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path} is not valid TOML: {exc}") from None
    site = data.get("site")
    if not isinstance(site, str) or not site:
        raise ConfigError(f"{path}: 'site' (a string) is required")
    zenoh = data.get("zenoh", {})
    zenoh_argv: list[str] = []
    for key in ("mode", "config"):
        if key in zenoh:
            zenoh_argv += [f"--{key}", str(zenoh[key])]
    for key in ("connect", "listen"):
        for endpoint in _as_list(zenoh.get(key, []), f"zenoh.{key}"):
            zenoh_argv += [f"--{key}", endpoint]
    router = data.get("router", {})
    router_listen = _as_list(router.get("listen", []), "router.listen")
    tls = data.get("tls", {})
    if not isinstance(tls, dict) or (tls and not isinstance(tls.get("dir"), str)):
        raise ConfigError(f"{path}: [tls] needs dir = \"PKI directory\"")
    tls_dir = tls.get("dir")
    services_table = data.get("services")
    if not isinstance(services_table, dict) or not services_table:
        raise ConfigError(f"{path}: no [services.NAME] tables")
    entries = []
    for name, options in services_table.items():
        if not isinstance(options, dict):
            raise ConfigError(f"{path}: services.{name} must be a table")
        options = dict(options)
        service = options.pop("service", name)
        tls_name = str(options.pop("tls_name", name))
        if service not in SERVICE_MODULES:
            raise ConfigError(f"{path}: services.{name}: unknown service {service!r} "
                              f"(known: {', '.join(SERVICE_MODULES)})")
        entries.append(ServiceEntry(name, service, options, tls_name))
    _add_analytes(entries, data.get("analytes"), path)
    entries.sort(key=lambda e: START_ORDER.index(e.service) if e.service in START_ORDER
                 else len(START_ORDER))
    return YardConfig(site, zenoh_argv, router_listen, entries,
                      float(data.get("restart_delay_s", 2.0)), tls_dir,
                      str(router.get("tls_name", "router")), _uplink(site, router, tls_dir, path))


def _uplink(site: str, router: Any, tls_dir: str | None, path: str | Path) -> Uplink | None:
    """``[router] uplink`` (with ``uplink_tls``, ``uplink_name``, ``head_office_name``) as
    an :class:`Uplink`; None without it; :class:`ConfigError` when it is incomplete."""
    if not isinstance(router, dict) or "uplink" not in router:
        return None
    if not isinstance(router.get("uplink_tls"), str) or not tls_dir:
        raise ConfigError(f"{path}: [router] uplink needs uplink_tls = \"DIR\" and [tls]")
    try:
        return Uplink(str(router["uplink"]), router["uplink_tls"],
                      str(router.get("uplink_name", f"{site}.router")),
                      str(router.get("head_office_name", DEFAULT_HEAD_OFFICE)))
    except ValueError as exc:
        raise ConfigError(f"{path}: [router] {exc}") from None


def _add_analytes(entries: list[ServiceEntry], table: Any, path: str | Path) -> None:
    """``[analytes]`` (``declared``, ``unknown``) checked and given to every ledger service
    as ``--analytes``/``--unknown-analyte``; raises :class:`ConfigError`."""
    if table is None:
        return
    if not isinstance(table, dict) or set(table) - {"declared", "unknown"}:
        raise ConfigError(f"{path}: [analytes] takes declared = [\"Fe\", ...] and "
                          f"unknown = \"{'|'.join(UNKNOWN_POLICIES)}\"")
    options: dict[str, Any] = {}
    if "declared" in table:
        try:
            declared = declared_list(_as_list(table["declared"], "analytes.declared"))
            check_declared(declared)
        except ValueError as exc:
            raise ConfigError(f"{path}: analytes.declared: {exc}") from None
        options["analytes"] = ",".join(declared)
    if "unknown" in table:
        if table["unknown"] not in UNKNOWN_POLICIES:
            raise ConfigError(f"{path}: analytes.unknown must be one of "
                              f"{', '.join(UNKNOWN_POLICIES)}, not {table['unknown']!r}")
        options["unknown_analyte"] = table["unknown"]
    for entry in entries:
        if entry.service != "ledger":
            continue
        both = set(options) & set(entry.options)
        if both:
            raise ConfigError(f"{path}: services.{entry.name} sets {', '.join(sorted(both))}; "
                              "the site's analytes belong in [analytes]")
        entry.options.update(options)


def _as_list(value: Any, where: str) -> list[str]:
    if isinstance(value, str):
        return [value]
    if isinstance(value, list) and all(isinstance(v, str) for v in value):
        return list(value)
    raise ConfigError(f"{where} must be a string or a list of strings")


class _Refused(Exception):
    """argparse's complaint about a service's options (instead of usage and exit)."""


class _QuietParser(argparse.ArgumentParser):
    """A parser (and, through add_subparsers, its subparsers) that raises instead of
    printing its usage and exiting."""

    def error(self, message: str):  # type: ignore[override]
        raise _Refused(message)


def check_arguments(config: YardConfig) -> None:
    """Parse every service's command line now, so a typo fails before anything starts.

    Raises :class:`ConfigError` naming the service and argparse's reason, one line
    (``--batch-interval`` is the TOML key ``batch_interval``).
    """
    parser = _QuietParser(prog="stockpile", add_help=False)
    service_cli.register(parser.add_subparsers(dest="command", required=True))
    for entry in config.services:
        argv = entry.argv(config.site, config.zenoh_argv, config.tls_dir)
        try:
            parser.parse_args(argv)
        except _Refused as exc:
            raise ConfigError(f"services.{entry.name}: {exc} (options {entry.options})") from None
        except SystemExit:
            raise ConfigError(f"services.{entry.name}: bad options {entry.options}") from None


def router_options(config: YardConfig) -> tuple[ZenohOptions, Any]:
    """The supervisor's router: its options, and with ``[tls]`` its config with the access
    control generated from the PKI's index (else None: the options alone)."""
    if not config.tls_dir:
        return ZenohOptions(mode="router", listen=tuple(config.router_listen)), None
    options = ZenohOptions(mode="router", listen=tuple(config.router_listen),
                           tls_dir=config.tls_dir, tls_name=config.router_tls_name)
    return options, site_router_config(config.site, options, load_members(config.tls_dir),
                                       config.router_uplink)


def run(config: YardConfig, *, stopper: Stopper | None = None) -> int:
    stopper = stopper or Stopper()
    router = None
    if config.router_listen:
        router = open_session(*router_options(config))
        log("run", "router", listen=",".join(config.router_listen),
            tls=bool(config.tls_dir))
    children: dict[str, subprocess.Popen] = {}
    delays = {e.name: config.restart_delay_s for e in config.services}
    next_start = {e.name: 0.0 for e in config.services}
    started_at = {e.name: 0.0 for e in config.services}
    lock = threading.Lock()

    def start(entry: ServiceEntry) -> None:
        argv = [sys.executable, "-m", "stockpile.cli",
                *entry.argv(config.site, config.zenoh_argv, config.tls_dir)]
        children[entry.name] = subprocess.Popen(argv)
        started_at[entry.name] = time.monotonic()
        log("run", "started", name=entry.name, kind=entry.service,
            pid=children[entry.name].pid)

    try:
        for entry in config.services:
            start(entry)
        while not stopper.wait(0.5):
            now = time.monotonic()
            with lock:
                for entry in config.services:
                    proc = children[entry.name]
                    code = proc.poll()
                    if code is None:
                        continue
                    if next_start[entry.name] == 0.0:
                        if now - started_at[entry.name] >= STABLE_RUN_S:
                            delays[entry.name] = config.restart_delay_s
                        log("run", "exited", level="error", name=entry.name, code=code,
                            restart_in_s=delays[entry.name])
                        next_start[entry.name] = now + delays[entry.name]
                        delays[entry.name] = min(60.0, delays[entry.name] * 2)
                    elif now >= next_start[entry.name]:
                        next_start[entry.name] = 0.0
                        start(entry)
    finally:
        for entry in reversed(config.services):
            proc = children.get(entry.name)
            if proc is not None and proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
                try:
                    proc.wait(30)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
            if proc is not None:
                log("run", "stopped", name=entry.name, code=proc.returncode)
        if router is not None:
            router.close()
    return 0


def cmd_run(args: argparse.Namespace) -> int:
    try:
        config = load_config(args.config)
        check_arguments(config)
    except ConfigError as exc:
        raise ValueError(str(exc)) from None
    if args.check:
        for entry in config.services:
            print(" ".join(["stockpile", *entry.argv(config.site, config.zenoh_argv,
                                                     config.tls_dir)]))
        return 0
    return run(config)


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("run", help="start the services a yard config names (a real site)",
                              description=plain_text(__doc__.split("\n\n")[0]))
    p.add_argument("--config", required=True, metavar="TOML",
                   help="the yard config (see docs/yard.example.toml)")
    p.add_argument("--check", action="store_true",
                   help="only check the config and print the command of every service")
    p.set_defaults(func=cmd_run)
