"""The distribution: one version, the extras, and a base install (no extras) that works.

The slow test installs the project into a fresh venv with no extras (pip, with the tested
versions of constraints.txt) and runs the command line there.
"""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
import tomllib
import venv
from importlib import metadata
from pathlib import Path

import pytest

import stockpile
from stockpile.cli import COMMAND_MODULES
from stockpile.sample import generate_sample
from stockpile.service_cli import SERVICE_MODULES

ROOT = Path(__file__).resolve().parents[1]
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())
TOP_COMMANDS = [name for entry in COMMAND_MODULES for name in entry.commands]


def run_blocked(blocked: list[str], *argv: str) -> subprocess.CompletedProcess:
    """``stockpile ARGV`` in a process where the modules ``blocked`` cannot be imported
    (as if their extra were not installed)."""
    code = textwrap.dedent(f"""
        import sys

        class NotInstalled:
            def find_spec(self, name, path=None, target=None):
                if name.split(".")[0] in {blocked!r}:
                    raise ModuleNotFoundError(f"No module named {{name!r}}", name=name)

        sys.meta_path.insert(0, NotInstalled())
        from stockpile.cli import main
        sys.exit(main({list(argv)!r}))
    """)
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=120)


def test_the_version_is_pyprojects():
    assert stockpile.version() == PYPROJECT["project"]["version"] == metadata.version(
        "stockpile-ledger")


def test_every_extra_of_the_code_is_an_extra_of_the_distribution():
    extras = PYPROJECT["project"]["optional-dependencies"]
    used = {e for entry in COMMAND_MODULES for e in entry.extras}
    used |= {service.extra for service in SERVICE_MODULES.values()}
    assert used <= set(stockpile.EXTRA_IMPORTS) <= set(extras)
    assert {"edge", "ledger", "projector", "dashboard", "sim", "all", "dev"} <= set(extras)
    # each extra installs the packages whose import names EXTRA_IMPORTS gives it
    # (read from this venv: which distribution provides each top-level module)
    providers = metadata.packages_distributions()
    for extra, names in stockpile.EXTRA_IMPORTS.items():
        declared = " ".join(extras[extra]).lower()
        for name in names:
            for dist in providers[name]:
                assert dist.lower() in declared or (
                    "stockpile-ledger[projector]" in declared
                    and dist.lower() in " ".join(extras["projector"]).lower()), (extra, name)


def test_without_zenoh_every_command_is_listed_and_names_its_extra():
    listed = run_blocked(["zenoh", "rerun", "scipy"], "--help")
    assert listed.returncode == 0, listed.stderr
    for name in TOP_COMMANDS:
        assert f"    {name}" in listed.stdout, name
    services = run_blocked(["zenoh"], "service", "--help")
    assert services.returncode == 0, services.stderr
    for name in SERVICE_MODULES:
        assert f"    {name}" in services.stdout, name
    ledger = run_blocked(["zenoh", "rerun", "scipy"], "ledger", "--help")
    assert ledger.returncode == 0 and "import" in ledger.stdout


@pytest.mark.parametrize(("blocked", "argv", "extra"), [
    (["serial"], ["service", "scanner", "--help"], "edge"),
    (["filterpy"], ["service", "localizer", "--port", "1"], "edge"),
    (["zenoh"], ["service", "ledger", "--help"], "ledger"),
    (["rerun"], ["service", "dashboard", "--help"], "dashboard"),
    (["scipy"], ["project", "--help"], "projector"),
    (["scipy"], ["sim"], "sim"),
    (["zenoh"], ["export-mcap", "--help"], "ledger"),
])
def test_a_missing_extra_is_one_line_naming_it(blocked, argv, extra):
    out = run_blocked(blocked, *argv)
    assert out.returncode == 2, out
    command = "stockpile " + " ".join(a for a in argv if not a.startswith("-") and a != "1")
    assert out.stderr.splitlines() == [
        f"stockpile: error: '{command}' needs the [{extra}] extra: "
        f"pip install 'stockpile-ledger[{extra}]'"]
    assert out.stdout == ""


def test_a_package_imported_only_when_the_command_runs_is_checked_up_front(tmp_path):
    """The dashboard imports rerun only when it renders; without it, the command still
    stops before doing anything, with the one line."""
    out = run_blocked(["rerun"], "dashboard", "--ledger", str(tmp_path / "nope.duckdb"),
                      "--rrd", str(tmp_path / "x.rrd"))
    assert out.returncode == 2
    assert out.stderr.splitlines() == [
        "stockpile: error: 'stockpile dashboard' needs the [dashboard] extra: "
        "pip install 'stockpile-ledger[dashboard]'"]
    assert not (tmp_path / "x.rrd").exists()


@pytest.mark.slow
def test_a_base_install_runs_the_ledger_and_names_the_extras(tmp_path):
    env_dir = tmp_path / "venv"
    venv.create(env_dir, with_pip=True)
    bin_dir = env_dir / "bin"
    install = subprocess.run(
        [str(bin_dir / "python"), "-m", "pip", "install", "--quiet", "-c",
         str(ROOT / "constraints.txt"), str(ROOT)],
        capture_output=True, text=True, timeout=900)
    assert install.returncode == 0, install.stderr[-3000:]
    installed = subprocess.run([str(bin_dir / "python"), "-m", "pip", "list"],
                               capture_output=True, text=True, timeout=120).stdout.lower()
    for heavy in ("eclipse-zenoh", "scipy", "rerun-sdk", "pyserial", "hypothesis"):
        assert heavy not in installed, heavy

    def stockpile_cmd(*argv: str) -> subprocess.CompletedProcess:
        return subprocess.run([str(bin_dir / "stockpile"), *argv], capture_output=True,
                              text=True, timeout=300, cwd=tmp_path)

    version = stockpile_cmd("--version")
    assert version.returncode == 0
    assert version.stdout.strip() == f"stockpile-ledger {PYPROJECT['project']['version']}"

    listed = stockpile_cmd("--help")
    assert listed.returncode == 0, listed.stderr
    for name in TOP_COMMANDS:
        assert f"    {name}" in listed.stdout, name

    sample = tmp_path / "sample.jsonl"
    lines = generate_sample(seed=3, hours=0.2).lines
    sample.write_text("\n".join(lines) + "\n")
    ledger = tmp_path / "ledger.duckdb"
    imported = stockpile_cmd("ledger", "import", str(sample), "--ledger", str(ledger),
                             "--clock", "events", "--json")
    assert imported.returncode == 0, imported.stderr
    appended = json.loads(imported.stdout)["appended"]
    assert appended > 100
    stats = stockpile_cmd("ledger", "stats", "--ledger", str(ledger), "--json")
    assert stats.returncode == 0, stats.stderr
    assert json.loads(stats.stdout)["events"] == appended
    verify = stockpile_cmd("ledger", "verify", "--ledger", str(ledger))
    assert verify.returncode == 0, verify.stderr
    info = stockpile_cmd("info", str(ledger), "--json")
    assert info.returncode == 0, info.stderr
    assert json.loads(info.stdout)["events"] == appended
    import_ledger = subprocess.run([str(bin_dir / "python"), "-c", "import ledger.testing"],
                                   capture_output=True, text=True, timeout=120)
    assert import_ledger.returncode == 0, import_ledger.stderr

    scanner = stockpile_cmd("service", "scanner", "--help")
    assert scanner.returncode == 2
    assert scanner.stderr.splitlines() == [
        "stockpile: error: 'stockpile service scanner' needs the [edge] extra: "
        "pip install 'stockpile-ledger[edge]'"]


def _third_party_imports(graph, module: str, ours: set[str]) -> set[str]:
    """Top-level names of the non-stdlib packages ``module`` imports, directly or through
    the project's modules (imports inside functions included)."""
    seen, todo = {module}, [module]
    while todo:
        for imported in graph.find_modules_directly_imported_by(todo.pop()):
            if imported not in seen:
                seen.add(imported)
                if imported.split(".")[0] in ours:
                    todo.append(imported)
    roots = {name.split(".")[0] for name in seen}
    return roots - ours - set(sys.stdlib_module_names)


def test_each_command_needs_only_the_base_and_its_extras():
    grimp = pytest.importorskip("grimp")
    ours = set(PYPROJECT["tool"]["importlinter"]["root_packages"])
    graph = grimp.build_graph(*sorted(ours), include_external_packages=True)
    # lz4: an optional codec, imported when a recording needs it; psycopg: imported when a
    # command is given a postgresql:// ledger (the ledger extra; open_ledger names it if missing)
    optional = {"lz4", "psycopg"}
    modules = [(e.load().__name__, e.extras) for e in COMMAND_MODULES]
    modules += [(s.load().__name__, (s.extra,)) for s in SERVICE_MODULES.values()]
    for module, extras in modules:
        allowed = set(stockpile.BASE_IMPORTS) | optional
        for extra in extras:
            allowed |= stockpile.EXTRA_IMPORTS[extra]
        if module in ("stockpile.service_cli", "stockpile.run_config"):
            # the service registry's deferred loaders import every service (each checked
            # on its own); `stockpile run` checks its services' options with the registry
            for service in SERVICE_MODULES.values():
                allowed |= stockpile.EXTRA_IMPORTS[service.extra]
        assert _third_party_imports(graph, module, ours) <= allowed, module


def test_the_layering_contract_sees_every_command_and_service():
    # A module loaded by its name as a string is an import the contract cannot see: the
    # registries import with statements, and no product module loads one by name.
    grimp = pytest.importorskip("grimp")
    ours = sorted(PYPROJECT["tool"]["importlinter"]["root_packages"])
    graph = grimp.build_graph(*ours)
    for importer, loaders in (("stockpile.cli", [e.load for e in COMMAND_MODULES]),
                              ("stockpile.service_cli",
                               [s.load for s in SERVICE_MODULES.values()])):
        for load in loaders:
            module = load().__name__
            assert graph.direct_import_exists(importer=importer, imported=module), module
    root = Path(__file__).resolve().parents[1]
    by_name = [f"{path.relative_to(root)}:{n}"
               for package in ours for path in sorted((root / package).rglob("*.py"))
               for n, line in enumerate(path.read_text().splitlines(), 1)
               if "import_module(" in line or "__import__(" in line]
    assert by_name == []
