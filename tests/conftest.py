"""Shared test configuration."""

import os

# keep hypothesis' example database out of the work tree
os.environ.setdefault("HYPOTHESIS_STORAGE_DIRECTORY", "/tmp/stockpile-hypothesis")

import random  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402

import pytest  # noqa: E402

pytest_plugins = ["pg_fixtures"]  # the PostgreSQL server and schemas (tests/pg_fixtures.py)

# the checks in the shared bad-input helpers are plain asserts: give them pytest's messages
pytest.register_assert_rewrite("bad_input_helpers")

from bad_input_helpers import Backend  # noqa: E402
import seeding  # noqa: E402


# -- the run's random seed (tests/seeding.py) ----------------------------------------------

def pytest_addoption(parser):
    parser.addoption("--seed", type=int, default=None, metavar="N",
                     help=f"the seed of every random test (default: ${seeding.ENV}, else a "
                     "fresh one per run, printed)")
    parser.addoption("--long-faults", action="store_true", default=False,
                     help="also run the long fault-injection cases (tests/faults, marked "
                     "long_fault; `make faults`)")


def pytest_configure(config):
    seeding.resolve(config.getoption("--seed"))
    config.addinivalue_line(
        "markers", "seeded: draws from the run's random seed (tests/seeding.py); a failure "
        "says how to re-run it")


def pytest_report_header(config):
    return seeding.rerun_hint()


def _is_seeded(item) -> bool:
    """The test draws from the run's seed: marked, using the ``seed`` fixture (not a
    parametrized literal ``seed``), or a Hypothesis test."""
    if item.get_closest_marker("seeded") is not None:
        return True
    if getattr(getattr(item, "obj", None), "is_hypothesis_test", False):
        return True
    params = getattr(getattr(item, "callspec", None), "params", {})
    return "seed" in getattr(item, "fixturenames", ()) and "seed" not in params


def pytest_collection_modifyitems(config, items):
    """Hypothesis tests draw their examples from the run's seed (and skip the example
    database, as ``hypothesis.seed`` does), so ``--seed N`` replays them.  The long
    fault-injection cases run only with ``--long-faults`` (``make faults``)."""
    from hypothesis import seed as hypothesis_seed

    long_faults = config.getoption("--long-faults")
    for item in items:
        if item.get_closest_marker("long_fault") is not None and not long_faults:
            item.add_marker(pytest.mark.skip(reason="a long fault case: make faults runs it"))
        obj = getattr(item, "obj", None)
        if getattr(obj, "is_hypothesis_test", False):
            hypothesis_seed(seeding.session_seed())(obj)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    outcome = yield
    report = outcome.get_result()
    if report.failed and _is_seeded(item):
        if hasattr(report.longrepr, "addsection"):
            report.longrepr.addsection("random seed", seeding.rerun_hint())
        else:
            report.sections.append(("random seed", seeding.rerun_hint()))


def pytest_terminal_summary(terminalreporter):
    terminalreporter.write_line(seeding.rerun_hint())


@pytest.fixture(autouse=True)
def _python_random_from_the_run_seed(request):
    """Python's global ``random`` starts each test from the run's seed and the test's id,
    so a test that draws from it (the ledger contract's randomised batches) replays under
    ``--seed``."""
    random.seed(f"{seeding.session_seed()}:{request.node.nodeid}")


@pytest.fixture(scope="session")
def seed() -> int:
    """The run's seed (``--seed`` / ``$STOCKPILE_TEST_SEED`` / fresh), printed."""
    value = seeding.session_seed()
    print(f"seed={value}")
    return value


@pytest.fixture(scope="session")
def small_yard_sim(tmp_path_factory):
    """A short simulated yard shared by the projector tests (one stacking pass, seed 2).

    ``stockpile sim --scenario demo --duration 0.19 --scan-events truth --assay-window
    1200``: real scans and scanner poses as events, the lab's windows as long as a pass (one
    assay per pass, which the audit tests supersede and delay); returns the output
    directory (``events.jsonl``, truth).
    """
    out = tmp_path_factory.mktemp("small-yard") / "sim"
    subprocess.run([sys.executable, "-m", "stockpile.cli", "sim", "--scenario", "demo",
                    "--seed", "2", "--duration", "0.19", "--speed", "0", "--scan-events",
                    "truth", "--assay-window", "1200", "--out", str(out)],
                   check=True, capture_output=True, timeout=300)
    return out


@pytest.fixture(scope="session")
def process_demo(tmp_path_factory):
    """One short process demo shared by the end-to-end and the recording tests.

    ``stockpile demo --duration 0.2h --speed 30 --seed 3 --record live.mcap``: every service
    a separate process, the recorder beside the ledger.  Returns ``(out_dir, completed)``.
    """
    out = tmp_path_factory.mktemp("process-demo") / "demo"
    run = subprocess.run(
        [sys.executable, "-m", "stockpile.cli", "demo", "--out", str(out), "--seed", "3",
         "--duration", "0.2h", "--speed", "30", "--record", str(out / "live.mcap")],
        capture_output=True, text=True, timeout=600)
    return out, run


@pytest.fixture(params=["memory", "duckdb"])
def backend(request, tmp_path):
    """A fresh ledger for the bad-input tests: once in memory, once on a DuckDB file."""
    b = Backend(request.param, tmp_path)
    try:
        yield b
    finally:
        b.close()
