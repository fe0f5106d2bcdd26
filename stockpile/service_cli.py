"""``stockpile service NAME``: start one service of the yard.

Each service module (:data:`SERVICE_MODULES`) provides
``add_arguments(parser)`` (its own options; the shared ones are added here),
``config_from_args(args) -> Config`` and ``main(config, *, stopper=None) -> int``.
A service module is imported only when the parser is built; one whose extra is not
installed is still listed, and using it says which extra to install.

A running service dumps the stack of every thread to its log (stderr) on SIGUSR1
(``kill -USR1 PID``): the way to see where a service that does not stop is waiting.
"""

from __future__ import annotations

import argparse
import faulthandler
import signal
from dataclasses import dataclass
from types import ModuleType
from typing import Callable

from common.options import plain_text
from stockpile import MissingExtra, add_missing_extra, import_for


@dataclass(frozen=True)
class Service:
    """One entry of the registry: where a service lives and what it needs."""

    #: imports the module that runs it (``add_arguments``, ``config_from_args``, ``main``)
    #: with a deferred import statement: its extra may be missing
    load: Callable[[], ModuleType]
    #: the extra that installs its third-party packages
    extra: str
    #: one line for ``stockpile service --help``
    summary: str


def _services_scanner() -> ModuleType:
    from services import scanner  # deferred: its extra may be missing
    return scanner


def _services_gnss() -> ModuleType:
    from services import gnss  # deferred: its extra may be missing
    return gnss


def _services_plc() -> ModuleType:
    from services import plc  # deferred: its extra may be missing
    return plc


def _services_lab() -> ModuleType:
    from services import lab  # deferred: its extra may be missing
    return lab


def _services_localizer() -> ModuleType:
    from services import localizer  # deferred: its extra may be missing
    return localizer


def _services_ledger_service() -> ModuleType:
    from services import ledger_service  # deferred: its extra may be missing
    return ledger_service


def _services_projector_service() -> ModuleType:
    from services import projector_service  # deferred: its extra may be missing
    return projector_service


def _services_dashboard() -> ModuleType:
    from services import dashboard  # deferred: its extra may be missing
    return dashboard


def _services_router() -> ModuleType:
    from services import router  # deferred: its extra may be missing
    return router


def _services_hq_service() -> ModuleType:
    from services import hq_service  # deferred: its extra may be missing
    return hq_service


def _replay_record() -> ModuleType:
    from replay import record  # deferred: its extra may be missing
    return record


#: ``stockpile service NAME`` -> the service
SERVICE_MODULES: dict[str, Service] = {
    "router": Service(_services_router, "ledger",
                      "the site's Zenoh router: mutual TLS only, access control by role"),
    "scanner": Service(_services_scanner, "edge",
                       "read LMS200 telegrams from a serial port or LMS1xx/5xx/TiM over TCP, publish scans"),
    "gnss": Service(_services_gnss, "edge",
                    "read NMEA GGA from a serial port, publish location fixes"),
    "plc": Service(_services_plc, "edge",
                   "subscribe to the machines' PLC tags over OPC UA, publish joint readings, "
                   "passes and cuts"),
    "lab": Service(_services_lab, "edge",
                   "watch a LIMS drop folder, publish each result row as an assay, exactly once"),
    "localizer": Service(_services_localizer, "edge",
                         "fuse joint readings and GNSS fixes (UKF), publish joint estimates "
                         "and poses"),
    "ledger": Service(_services_ledger_service, "ledger",
                      "the single writer of the ledger: subscribe, append in batches, serve "
                      "reads"),
    "projector": Service(_services_projector_service, "projector",
                         "follow the ledger service and keep a live projection of one pile"),
    "dashboard": Service(_services_dashboard, "dashboard",
                         "follow the ledger service and log one or more piles to Rerun "
                         "(web viewer, .rrd)"),
    "hq": Service(_services_hq_service, "ledger",
                  "the head office: mirror every site's ledger from its queryables"),
    "recorder": Service(_replay_record, "ledger",
                        "record the site's events to MCAP files, rotating by size or time"),
}


def _run(args: argparse.Namespace) -> int:
    if hasattr(signal, "SIGUSR1"):
        faulthandler.register(signal.SIGUSR1, all_threads=True)
    module = SERVICE_MODULES[args.service].load()
    return int(module.main(module.config_from_args(args)) or 0)


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("service", help="start one service of the yard ("
                              + ", ".join(SERVICE_MODULES) + ")",
                              description=plain_text(__doc__.splitlines()[0]))
    sub = p.add_subparsers(dest="service", metavar="NAME", required=True,
                           parser_class=type(p))
    for name, service in SERVICE_MODULES.items():
        command = f"stockpile service {name}"
        try:
            module = import_for(service.load, command, (service.extra,))
        except MissingExtra as missing:
            add_missing_extra(sub, name, service.summary, missing)
            continue
        # deferred: services.service imports zenoh, which only the extras install (every
        # service module imports it too, so it is there once one of them imported)
        from services.service import add_service_arguments

        sp = sub.add_parser(name, help=service.summary, description=service.summary)
        module.add_arguments(sp)
        add_service_arguments(sp)
        sp.set_defaults(func=_run, _needs=(command, (service.extra,)))
