"""``stockpile service NAME``: start one service of the yard.

Each service module (:data:`SERVICE_MODULES`) provides
``add_arguments(parser)`` (its own options; the shared ones are added here),
``config_from_args(args) -> Config`` and ``main(config, *, stopper=None) -> int``.

A running service dumps the stack of every thread to its log (stderr) on SIGUSR1
(``kill -USR1 PID``): the way to see where a service that does not stop is waiting.
"""

from __future__ import annotations

import argparse
import faulthandler
import signal
from types import ModuleType

from replay import record
from services import dashboard, gnss, ledger_service, localizer, projector_service, scanner
from services.service import add_service_arguments

#: ``stockpile service NAME`` -> the module that runs it
SERVICE_MODULES: dict[str, ModuleType] = {
    "scanner": scanner,
    "gnss": gnss,
    "localizer": localizer,
    "ledger": ledger_service,
    "projector": projector_service,
    "dashboard": dashboard,
    "recorder": record,
}

SUMMARIES = {
    "scanner": "read LMS200 telegrams from a serial port, publish scans",
    "gnss": "read NMEA GGA from a serial port, publish location fixes",
    "localizer": "fuse joint readings and GNSS fixes (UKF), publish joint estimates and poses",
    "ledger": "the single writer of the ledger: subscribe, append in batches, serve reads",
    "projector": "follow the ledger service and keep a live projection of one pile",
    "dashboard": "follow the ledger service and log one pile to Rerun (web viewer, .rrd)",
    "recorder": "record the site's events to MCAP files, rotating by size or time",
}


def _run(args: argparse.Namespace) -> int:
    if hasattr(signal, "SIGUSR1"):
        faulthandler.register(signal.SIGUSR1, all_threads=True)
    module = SERVICE_MODULES[args.service]
    return int(module.main(module.config_from_args(args)) or 0)


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("service", help="start one service of the yard (scanner, gnss, "
                              "localizer, ledger, projector, recorder)",
                              description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="service", metavar="NAME", required=True,
                           parser_class=type(p))
    for name, module in SERVICE_MODULES.items():
        sp = sub.add_parser(name, help=SUMMARIES.get(name, ""), description=SUMMARIES.get(name))
        module.add_arguments(sp)
        add_service_arguments(sp)
        sp.set_defaults(func=_run)

