"""`make mutate`: mutation testing of the core modules with mutmut, one table per module.

Runs ``mutmut run`` on a copy of ``ledger/``, ``projector/``, ``tests/`` and
``pyproject.toml`` (whose ``[tool.mutmut]`` names the files and the tests) in
``build/mutate/``, for the functions listed in :data:`MODULES`, then prints per module the
mutants, how many the tests killed (a timeout counts as killed: the mutant hung the code),
how many survived and the score ``killed / mutants``.  Every survivor is printed with its
reason from ``tools/mutation_survivors.toml`` (the accepted survivors, each with why it
cannot matter), or as UNEXPLAINED with its diff.  Exits 1 if a module scores below
:data:`TARGET` or a survivor is unexplained.  docs/mutation.md says how to read it.

    python tools/mutate.py [--keep] [--jobs N] [--module NAME ...]

``--keep`` reuses ``build/mutate/`` (mutmut's cache) instead of starting afresh.
"""

from __future__ import annotations

import argparse
import fnmatch
import json
import os
import shutil
import subprocess
import sys
import time
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
WORK = ROOT / "build" / "mutate"
SURVIVORS = ROOT / "tools" / "mutation_survivors.toml"
TARGET = 0.90

# module -> (file, mutmut mutant-name patterns that count for it)
MODULES: dict[str, tuple[str, list[str]]] = {
    "chain": ("ledger/chain.py", ["ledger.chain.*"]),
    "append planner + state": ("ledger/store.py", [
        "ledger.writer_state.xǁStreamStateǁ*", "ledger.store.x__int64_or_none__mutmut_*",
        "ledger.store.x__split_reason__mutmut_*", "ledger.store.xǁ_BatchPlannerǁ*",
        "ledger.store.x_keys_to_look_up__mutmut_*"] + [
        f"ledger.store.xǁLedgerStoreǁ{name}__mutmut_*"
        for name in ("append", "head", "verify", "streams")]),
    "duckdb commit/read/as-of": ("ledger/duckdb_store.py", [
        f"ledger.duckdb_store.xǁDuckDBStoreǁ{name}__mutmut_*" for name in (
            "_load_state", "_lookup", "_commit", "_insert_rows", "_write_rest", "_with_gaps",
            "_new_analytes", "_query", "_filters", "read", "as_of", "gaps", "quarantine")]),
    "memory commit/read/as-of": ("ledger/memory.py", ["ledger.memory.*"]),
    "verify checks": ("ledger/verifying.py", ["ledger.verifying.*"]),
    "signed events": ("ledger/signing.py", [
        "ledger.signing.xǁKeyRegistryǁ*", "ledger.signing.x_sign_event__mutmut_*",
        "ledger.signing.x_signature_block__mutmut_*", "ledger.signing.x_registry_from_rows__mutmut_*",
        "ledger.signing.x__record__mutmut_*"]),
    "snapshot reuse": ("projector/query.py", [
        "projector.query.xǁSnapshotStoreǁfind__mutmut_*",
        "projector.query.x__unchanged_since__mutmut_*",
        "projector.query.x__config_key__mutmut_*"]),
    "grade join": ("projector/query.py + grades.py", [
        "projector.query.xǁGradeJoinǁ*", "projector.query.x_analytes_of__mutmut_*",
        "projector.grades.*"]),
}

# The review's two mutants of ledger/chain.py (issue 44), applied by hand to a copy of the
# package: which tests kill each is printed (mutmut's own mutants of chain_hash are smaller).
_CHAIN_JOIN = """        previous,
        _INTS.pack(global_seq, epoch, seq, valid_time_ns, recorded_time_ns),
        _names(type_name, source),
        payload_sha256,
"""
NAMED_MUTANTS: dict[str, tuple[str, str, str]] = {
    "chain hash without type, source, epoch and seq": ("ledger/chain.py", _CHAIN_JOIN, """\
        previous,
        struct.pack("<qqq", global_seq, valid_time_ns, recorded_time_ns),
        payload_sha256,
"""),
    "chain hash without the payload hash": ("ledger/chain.py", _CHAIN_JOIN, """\
        previous,
        _INTS.pack(global_seq, epoch, seq, valid_time_ns, recorded_time_ns),
        _names(type_name, source),
"""),
}
NAMED_TESTS = ["tests/test_chain.py", "tests/test_ledger_contract.py", "tests/test_mutation_store.py"]

# exit codes of a mutant's test run (mutmut.stats.status_by_exit_code)
KILLED = {1, 3, 36, -24, 24, 152, 255}
SURVIVED = {0}
NO_TESTS = {5, 33}


def _copy_tree() -> None:
    if WORK.exists():
        shutil.rmtree(WORK)
    WORK.mkdir(parents=True)
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc")
    for name in ("ledger", "projector", "tests"):
        shutil.copytree(ROOT / name, WORK / name, ignore=ignore)
    shutil.copy2(ROOT / "pyproject.toml", WORK / "pyproject.toml")


def _results() -> dict[str, int | None]:
    out: dict[str, int | None] = {}
    for meta in (WORK / "mutants").rglob("*.py.meta"):
        out.update(json.loads(meta.read_text())["exit_code_by_key"])
    return out


def _mutmut(*args: str) -> subprocess.CompletedProcess:
    exe = Path(sys.executable).with_name("mutmut")
    env = dict(os.environ, PYTHONDONTWRITEBYTECODE="1")
    return subprocess.run([str(exe), *args], cwd=WORK, env=env, text=True, capture_output=True)


def named_mutants() -> list[str]:
    """Run :data:`NAMED_MUTANTS`; lines naming the tests that fail under each."""
    lines = []
    for name, (path, old, new) in NAMED_MUTANTS.items():
        work = WORK.parent / "mutate-named" / name.replace(" ", "-").replace(",", "")
        if work.exists():
            shutil.rmtree(work)
        shutil.copytree(ROOT / "ledger", work / "ledger",
                        ignore=shutil.ignore_patterns("__pycache__"))
        source = (work / path).read_text()
        assert source.count(old) == 1, f"{path} changed: update NAMED_MUTANTS"
        (work / path).write_text(source.replace(old, new))
        env = dict(os.environ, PYTHONPATH=str(work), PYTHONDONTWRITEBYTECODE="1")
        out = subprocess.run([str(Path(sys.executable).with_name("pytest")), "-q", "-p", "no:cacheprovider",
                              "-rf", "--tb=no", *NAMED_TESTS], cwd=ROOT, env=env,
                             text=True, capture_output=True)
        failed = sorted(line.split()[1] for line in out.stdout.splitlines()
                        if line.startswith("FAILED "))
        status = f"killed by {len(failed)} tests" if failed else "SURVIVED"
        lines.append(f"  {name}: {status}")
        lines += [f"      {t}" for t in failed]
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--keep", action="store_true", help="reuse build/mutate (mutmut's cache)")
    parser.add_argument("--jobs", type=int, default=os.cpu_count() or 2)
    parser.add_argument("--module", action="append", choices=sorted(MODULES),
                        help="only this module (repeatable)")
    parser.add_argument("--named-only", action="store_true",
                        help="only the review's named mutants of the chain")
    args = parser.parse_args(argv)
    modules = {k: v for k, v in MODULES.items() if not args.module or k in args.module}
    patterns = [p for _, pats in modules.values() for p in pats]

    if args.named_only:
        named = named_mutants()
        print("\n".join(named))
        return 1 if any("SURVIVED" in line for line in named) else 0

    start = time.monotonic()
    if not args.keep or not WORK.exists():
        _copy_tree()
    run = _mutmut("run", "--max-children", str(args.jobs), *patterns)
    elapsed = time.monotonic() - start
    if run.returncode != 0:
        print(run.stdout[-4000:], run.stderr[-4000:], sep="\n", file=sys.stderr)
        print(f"mutmut run failed (exit {run.returncode})", file=sys.stderr)
        return 2

    accepted: dict[str, str] = tomllib.loads(SURVIVORS.read_text()).get("survivors", {})
    results = _results()
    failed = False
    rows, lines = [], []
    used: set[str] = set()
    for module, (path, pats) in modules.items():
        keys = sorted(k for k in results if any(fnmatch.fnmatchcase(k, p) for p in pats))
        codes = [results[k] for k in keys]
        killed = sum(c in KILLED for c in codes)
        survivors = [k for k in keys if results[k] not in KILLED]
        score = killed / len(keys) if keys else 0.0
        ok = bool(keys) and score >= TARGET
        failed |= not ok
        rows.append((module, path, len(keys), killed, len(survivors), score, ok))
        for k in survivors:
            what = {0: "survived", 5: "no tests", 33: "no tests", None: "not checked"}.get(
                results[k], f"exit {results[k]}")
            if k in accepted:
                used.add(k)
                lines.append(f"  {module}: {k} ({what}): accepted: {accepted[k]}")
            else:
                failed = True
                diff = _mutmut("show", k).stdout.strip()
                lines.append(f"  {module}: {k} ({what}): UNEXPLAINED\n"
                             + "\n".join("      " + d for d in diff.splitlines()[3:]))

    print(f"mutation testing (mutmut), {elapsed:.0f} s, {args.jobs} jobs; "
          f"score = killed / mutants, target {TARGET:.0%} per module\n")
    print(f"{'module':28} {'file':32} {'mutants':>7} {'killed':>7} {'survived':>8} {'score':>7}")
    for module, path, n, killed, survived, score, ok in rows:
        print(f"{module:28} {path:32} {n:7d} {killed:7d} {survived:8d} {score:7.1%}"
              + ("" if ok else "  BELOW TARGET"))
    total = sum(r[2] for r in rows)
    total_killed = sum(r[3] for r in rows)
    print(f"{'all':28} {'':32} {total:7d} {total_killed:7d} {total - total_killed:8d} "
          f"{total_killed / max(total, 1):7.1%}")
    print("\nsurvivors:" if lines else "\nsurvivors: none")
    print("\n".join(lines))
    named = named_mutants()
    print("\nthe review's named mutants (ledger/chain.py, applied by hand):")
    print("\n".join(named))
    failed |= any("SURVIVED" in line for line in named)
    stale = sorted(k for k in accepted if k not in used
                   and any(fnmatch.fnmatchcase(k, p) for _, pats in modules.values() for p in pats))
    if stale:
        print("\naccepted survivors that are now killed or gone (remove them from "
              f"{SURVIVORS.relative_to(ROOT)}):")
        print("\n".join(f"  {k}" for k in stale))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
