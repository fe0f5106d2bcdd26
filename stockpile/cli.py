"""The ``stockpile`` command line: one entry point, one subcommand per job.

Every subcommand reports errors as one line on stderr (no traceback) and exits
0 when all is well, 1 when a verification failed, 2 on bad usage or an error.
"""

from __future__ import annotations

import argparse
import sys
from typing import Sequence

from audit import cli as audit_cli
from ledger import cli as ledger_cli
from ledger.errors import LedgerError
from planner import cli as plan_cli
from projector import cli as project_cli
from replay import cli as replay_cli
from services import dashboard
from sim import cli as sim_cli
from stockpile import demo, run_config, service_cli

EXIT_USAGE = 2


class _Parser(argparse.ArgumentParser):
    """argparse, but a usage error is one line: ``stockpile ledger: error: ...``."""

    def error(self, message: str) -> None:  # type: ignore[override]
        self.exit(EXIT_USAGE, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="stockpile",
        description="stockpile-ledger: the system of record for the grade of iron-ore "
        "stockpiles.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True,
                                parser_class=_Parser)
    demo.register(sub)
    ledger_cli.register(sub)
    project_cli.register(sub)
    sim_cli.register(sub)
    service_cli.register(sub)
    run_config.register(sub)
    plan_cli.register(sub)
    replay_cli.register(sub)
    audit_cli.register(sub)
    dashboard.register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print("stockpile: interrupted", file=sys.stderr)
        return 130
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
