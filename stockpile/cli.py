"""The ``stockpile`` command line: one entry point, one subcommand per job.

Every subcommand reports errors as one line on stderr (no traceback) and exits
0 when all is well, 1 when a verification failed, 2 on bad usage or an error.
A command whose extra is not installed (:data:`COMMAND_MODULES`) is still listed, and
using it is one line naming the extra to install.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from types import ModuleType
from typing import Callable, Sequence

from pathlib import Path

from common.logs import add_logging_options, configure_from_args
from ledger.errors import LedgerError, LedgerLocked
from ledger.holder import LedgerHolder, set_remote_reader
from ledger.store import LedgerStore
from stockpile import DISTRIBUTION, MissingExtra, add_missing_extra, import_for, is_missing_extra, version

EXIT_USAGE = 2


@dataclass(frozen=True)
class CommandModule:
    """A module whose ``register(subparsers)`` adds top-level commands."""

    #: imports the module (a deferred import statement: its extras may be missing)
    load: Callable[[], ModuleType]
    #: the extras whose packages its imports need (empty: the base install)
    extras: tuple[str, ...]
    #: the commands it registers -> their one-line summary (shown when an extra is missing)
    commands: dict[str, str]


# Each loader imports one command module.  The imports are real statements, deferred
# into functions so that a missing extra leaves the other commands working, and visible
# to the layering contract (a module named by a string would not be).

def _stockpile_demo() -> ModuleType:
    from stockpile import demo  # deferred: see COMMAND_MODULES
    return demo


def _surveys_cli() -> ModuleType:
    from surveys import cli  # deferred: see COMMAND_MODULES
    return cli


def _exports_cli() -> ModuleType:
    from exports import cli  # deferred: see COMMAND_MODULES
    return cli


def _ledger_cli() -> ModuleType:
    from ledger import cli  # deferred: see COMMAND_MODULES
    return cli


def _projector_cli() -> ModuleType:
    from projector import cli  # deferred: see COMMAND_MODULES
    return cli


def _sim_cli() -> ModuleType:
    from sim import cli  # deferred: see COMMAND_MODULES
    return cli


def _stockpile_service_cli() -> ModuleType:
    from stockpile import service_cli  # deferred: see COMMAND_MODULES
    return service_cli


def _stockpile_run_config() -> ModuleType:
    from stockpile import run_config  # deferred: see COMMAND_MODULES
    return run_config


def _planner_cli() -> ModuleType:
    from planner import cli  # deferred: see COMMAND_MODULES
    return cli


def _replay_cli() -> ModuleType:
    from replay import cli  # deferred: see COMMAND_MODULES
    return cli


def _audit_cli() -> ModuleType:
    from audit import cli  # deferred: see COMMAND_MODULES
    return cli


def _services_dashboard() -> ModuleType:
    from services import dashboard  # deferred: see COMMAND_MODULES
    return dashboard


def _stockpile_info() -> ModuleType:
    from stockpile import info  # deferred: see COMMAND_MODULES
    return info


def _ledger_sql() -> ModuleType:
    from ledger import sql  # deferred: see COMMAND_MODULES
    return sql


def _security_cli() -> ModuleType:
    from security import cli  # deferred: see COMMAND_MODULES
    return cli


def _keys_cli() -> ModuleType:
    from ledger import keys_cli  # deferred: see COMMAND_MODULES
    return keys_cli


#: every top-level command, in ``stockpile --help`` order.  A module is imported only
#: when the parser is built, so the base install (no extras) runs the commands it can
#: and names the extra for the others.
COMMAND_MODULES: tuple[CommandModule, ...] = (
    CommandModule(_stockpile_demo, ("edge", "ledger", "projector", "sim"),
                  {"demo": "simulate the demo yard and ledger it (the main job)"}),
    CommandModule(_ledger_cli, (),
                  {"ledger": "import, export, verify and summarise an event ledger"}),
    CommandModule(_projector_cli, ("projector",),
                  {"project": "the pile as of a valid time, as known at a known time"}),
    CommandModule(_sim_cli, ("sim",),
                  {"sim": "run the yard simulator (ground truth + emulated hardware)"}),
    CommandModule(_stockpile_service_cli, (),
                  {"service": "start one service of the yard"}),
    CommandModule(_stockpile_run_config, ("ledger",),
                  {"run": "start the services a yard config names (a real site)"}),
    CommandModule(_planner_cli, ("projector",),
                  {"plan": "plan reclaim work before the wheel touches the pile"}),
    CommandModule(_replay_cli, ("ledger",),
                  {"record": "record the site's events to MCAP",
                   "replay": "replay an MCAP file onto Zenoh or into a ledger",
                   "export-mcap": "write a ledger's events as an MCAP file"}),
    CommandModule(_audit_cli, ("projector",),
                  {"audit": "audit and reconciliation reports (cuts, history, assays)"}),
    CommandModule(_exports_cli, ("geo",),
                  {"export": "surfaces, meshes, block models and cuts for mine planning and GIS"}),
    CommandModule(_surveys_cli, ("geo",),
                  {"survey": "surveys of the piles: import LAS/LAZ"}),
    CommandModule(_services_dashboard, ("dashboard",),
                  {"dashboard": "render a ledger to a Rerun dashboard"}),
    CommandModule(_stockpile_info, (),
                  {"info": "what an MCAP session or a ledger holds: span, counts, gaps"}),
    CommandModule(_ledger_sql, (),
                  {"sql": "SQL on a ledger's views, read-only"}),
    CommandModule(_security_cli, (),
                  {"pki": "the site PKI: a site CA, a certificate per service, revocation"}),
    CommandModule(_keys_cli, (),
                  {"keys": "producers' signing keys and the admin's declarations of them"}),
)


class _Parser(argparse.ArgumentParser):
    """argparse, but a usage error is one line: ``stockpile ledger: error: ...``."""

    def error(self, message: str) -> None:  # type: ignore[override]
        self.exit(EXIT_USAGE, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


#: the top-level options that take a value (the logging options)
_OPTIONS_WITH_VALUE = frozenset({"--log-level", "--log-format"})


def command_of(argv: Sequence[str]) -> str | None:
    """The top-level command ``argv`` names (its first word after the top-level
    options), or None when it names none that :data:`COMMAND_MODULES` knows."""
    commands = {name for entry in COMMAND_MODULES for name in entry.commands}
    tokens = iter(argv)
    for token in tokens:
        if token in commands:
            return token
        if not token.startswith("-"):
            return None
        if token in _OPTIONS_WITH_VALUE:
            next(tokens, None)
    return None


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The ``stockpile`` parser: every command, or only ``command`` (then only its
    module is imported, so one command starts without importing the others)."""
    parser = _Parser(
        prog="stockpile",
        description="stockpile-ledger: the system of record for the grade of iron-ore "
        "stockpiles.",
    )
    parser.add_argument("--version", action="version", version=f"stockpile-ledger {version()}",
                        help="print the version and exit")
    add_logging_options(parser)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True,
                                parser_class=_Parser)
    for entry in COMMAND_MODULES:
        if command is not None and command not in entry.commands:
            continue
        # deferred: each command's module is imported here, not at the top, so that a
        # missing extra (an optional dependency) leaves the other commands working
        try:
            module = import_for(entry.load, f"stockpile {next(iter(entry.commands))}",
                                entry.extras)
        except MissingExtra:
            for name, summary in entry.commands.items():
                add_missing_extra(sub, name, summary, MissingExtra(f"stockpile {name}",
                                                                   entry.extras))
            continue
        module.register(sub)
        for name in entry.commands:
            # a deferred import of the extra inside the command is reported the same way
            sub.choices[name].set_defaults(_needs=(f"stockpile {name}", entry.extras))
    return parser


def read_through_service(path: Path, holder: LedgerHolder) -> LedgerStore:
    """Read a ledger file that a running ledger service holds through that service's
    queryables (:mod:`ledger.holder`); says so in one line on stderr."""
    try:
        from services.ledger_client import open_remote_ledger
    except ModuleNotFoundError as exc:
        if is_missing_extra(exc, ("ledger",)):
            raise LedgerLocked(f"{path} is held by {holder.describe()}; reading through it "
                               f"needs the [ledger] extra: pip install '{DISTRIBUTION}[ledger]'",
                               holder.pid) from None
        raise
    print(f"stockpile: {path} is held by {holder.describe()}; reading through its "
          f"queryables at {', '.join(holder.endpoints) or '(no endpoint)'}", file=sys.stderr)
    return open_remote_ledger(holder)


def main(argv: Sequence[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser(command_of(argv))
    args = parser.parse_args(argv)
    configure_from_args(args)
    set_remote_reader(read_through_service)
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print("stockpile: interrupted", file=sys.stderr)
        return 130
    except ModuleNotFoundError as exc:
        command, extras = getattr(args, "_needs", ("stockpile", ()))
        if not is_missing_extra(exc, extras):
            raise
        print(f"stockpile: error: {MissingExtra(command, extras)}", file=sys.stderr)
        return EXIT_USAGE
    except BrokenPipeError:
        # the reader went away (e.g. `| head`): not an error
        sys.stderr.close()
        return 0
    except (LedgerError, ValueError, OSError) as exc:
        message = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        print(f"stockpile: error: {message}", file=sys.stderr)
        return EXIT_USAGE


if __name__ == "__main__":
    sys.exit(main())
