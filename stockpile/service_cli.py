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
import importlib
import signal
from dataclasses import dataclass

from common.options import plain_text
from stockpile import MissingExtra, add_missing_extra, import_for


@dataclass(frozen=True)
class Service:
    """One entry of the registry: where a service lives and what it needs."""

    #: the module that runs it (``add_arguments``, ``config_from_args``, ``main``)
    module: str
    #: the extra that installs its third-party packages
    extra: str
    #: one line for ``stockpile service --help``
    summary: str


#: ``stockpile service NAME`` -> the service
SERVICE_MODULES: dict[str, Service] = {
    "scanner": Service("services.scanner", "edge",
                       "read LMS200 telegrams from a serial port, publish scans"),
    "gnss": Service("services.gnss", "edge",
                    "read NMEA GGA from a serial port, publish location fixes"),
    "localizer": Service("services.localizer", "edge",
                         "fuse joint readings and GNSS fixes (UKF), publish joint estimates "
                         "and poses"),
    "ledger": Service("services.ledger_service", "ledger",
                      "the single writer of the ledger: subscribe, append in batches, serve "
                      "reads"),
    "projector": Service("services.projector_service", "projector",
                         "follow the ledger service and keep a live projection of one pile"),
    "dashboard": Service("services.dashboard", "dashboard",
                         "follow the ledger service and log one pile to Rerun (web viewer, "
                         ".rrd)"),
    "recorder": Service("replay.record", "ledger",
                        "record the site's events to MCAP files, rotating by size or time"),
}


def _run(args: argparse.Namespace) -> int:
    if hasattr(signal, "SIGUSR1"):
        faulthandler.register(signal.SIGUSR1, all_threads=True)
    module = importlib.import_module(SERVICE_MODULES[args.service].module)
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
            module = import_for(service.module, command, (service.extra,))
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
