"""The ``stockpile`` command and the jobs that span the whole yard (the top layer).

- :mod:`stockpile.cli`: the entry point; one subcommand per job, each registered by
  the package that does it
- :mod:`stockpile.demo`: ``stockpile demo``: the yard as processes (the default), the
  simulator imported in-process (``--in-process``), or the generated sample (``--sample``)
- :mod:`stockpile.yard_demo`: the end-to-end demo: every service and the simulator as
  separate processes, drained and checked (exactly once, the localizer, the projector
  against the simulator's truth)
- :mod:`stockpile.sample`: a generated sample session with bad input planted in it
- :mod:`stockpile.orchestrate`: start, watch and stop the yard's processes around a
  loopback Zenoh router (:class:`~stockpile.orchestrate.Supervisor`)
- :mod:`stockpile.service_cli`: ``stockpile service NAME``: the registry of services
- :mod:`stockpile.run_config`: ``stockpile run --config yard.toml``: a real site's
  services, started and restarted from its config

The package also knows its own version (:func:`version`, from the installed metadata:
``pyproject.toml`` is the one source) and which optional dependencies each extra of the
distribution installs (:data:`EXTRA_IMPORTS`), so that a command whose extra is missing
says which one to install (:func:`import_for`, :func:`add_missing_extra`).
"""

from __future__ import annotations

import argparse
import importlib.util
from importlib import metadata
from types import ModuleType
from typing import Callable, NoReturn, Sequence

#: the distribution's name on PyPI (``pip install stockpile-ledger``)
DISTRIBUTION = "stockpile-ledger"

#: the top-level import names of the base install's third-party packages
BASE_IMPORTS = frozenset({"google", "foxglove_schemas_protobuf", "numpy", "duckdb", "pyarrow",
                          "mcap", "mcap_protobuf", "zstandard", "tqdm", "structlog",
                          "cryptography"})

#: extra -> the top-level import names of the third-party packages it adds to the base
#: install (pyproject.toml's optional-dependencies install them)
EXTRA_IMPORTS: dict[str, frozenset[str]] = {
    "edge": frozenset({"zenoh", "serial", "filterpy", "scipy", "pymap3d", "asyncua"}),
    "ledger": frozenset({"zenoh"}),
    "projector": frozenset({"zenoh", "scipy"}),
    "dashboard": frozenset({"zenoh", "scipy", "rerun", "rerun_cli"}),
    # sim.runner emulates the scanner with services.scanner, which imports serial;
    # sim.opcua_server serves the machine PLCs with asyncua; sim.survey writes LAZ
    "sim": frozenset({"zenoh", "scipy", "pymap3d", "serial", "asyncua", "pyproj", "laspy",
                      "lazrs"}),
    # the mine grid, GeoTIFF, DXF and its contours, LAS/LAZ
    "geo": frozenset({"zenoh", "scipy", "pyproj", "rasterio", "affine", "ezdxf", "contourpy",
                      "laspy", "lazrs"}),
}


def version() -> str:
    """The installed distribution's version (``pyproject.toml``'s ``version``)."""
    try:
        return metadata.version(DISTRIBUTION)
    except metadata.PackageNotFoundError:
        return "0+unknown (not installed: pip install -e .)"


class MissingExtra(Exception):
    """A command needs third-party packages that only an extra installs."""

    def __init__(self, command: str, extras: Sequence[str]):
        self.command = command
        self.extras = tuple(extras)
        names = ",".join(self.extras)
        plural = "s" if len(self.extras) > 1 else ""
        super().__init__(f"'{command}' needs the [{names}] extra{plural}: "
                         f"pip install '{DISTRIBUTION}[{names}]'")


def is_missing_extra(exc: ModuleNotFoundError, extras: Sequence[str]) -> bool:
    """Whether ``exc`` is about a third-party package one of ``extras`` installs."""
    root = (exc.name or "").split(".")[0]
    return any(root in EXTRA_IMPORTS[extra] for extra in extras)


def _installed(name: str) -> bool:
    """Whether the top-level module ``name`` can be imported (found, not imported)."""
    try:
        return importlib.util.find_spec(name) is not None
    except (ImportError, ValueError):
        return False


def import_for(load: Callable[[], ModuleType], command: str,
               extras: Sequence[str]) -> ModuleType:
    """Import the module that implements ``command``: ``load()`` runs the import statement
    (a real one, so that the layering contract sees it).

    Raises :class:`MissingExtra` when a package of ``extras`` is not installed (even one
    the command imports only when it runs); any other missing module is a bug and
    propagates.
    """
    if not all(_installed(name) for extra in extras for name in EXTRA_IMPORTS[extra]):
        raise MissingExtra(command, extras)
    try:
        return load()
    except ModuleNotFoundError as exc:
        if is_missing_extra(exc, extras):
            raise MissingExtra(command, extras) from exc
        raise


def add_missing_extra(subparsers: argparse._SubParsersAction, name: str, summary: str,
                      missing: MissingExtra) -> argparse.ArgumentParser:
    """Register ``name`` as a placeholder: listed in the parent's ``--help``, and any use
    of it (``--help`` too) prints the one-line :class:`MissingExtra` error and exits 2."""
    parser = subparsers.add_parser(name, help=f"{summary} [{','.join(missing.extras)}]",
                                   add_help=False)

    def refuse(args: object = None, namespace: object = None) -> NoReturn:
        parser.exit(2, f"stockpile: error: {missing}\n")

    parser.parse_known_args = refuse  # type: ignore[method-assign, assignment]
    return parser
