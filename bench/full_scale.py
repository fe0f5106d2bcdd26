"""Full scale end to end: the thesis' 24-hour pile simulated, ledgered, projected, judged.

    .venv/bin/python bench/full_scale.py                        # into bench/out/full-scale
    .venv/bin/python bench/full_scale.py --keep /work/fs --reuse  # reuse the stages done

The simulator's ``full-scale`` scenario (a 220 m x 70 m chevron pile, about 30 m high, 12
lots x 3 passes of 22,000 t stacked over about 21 h, then a reclaim of three benches) for
24 site hours, through the product's own commands.  Each stage is a child process; the
table gives its wall seconds, its CPU seconds and its peak RSS (``os.wait4``):

1. ``simulate``: ``stockpile sim --scenario full-scale --duration 24h --scan-events
   truth`` (scans and the scanner's true poses as events, the LMS200 and GNSS streams, the
   truth);
2. ``localize`` (``--poses localizer``, the default: a yard's path): the product's
   localizer (its UKF over the run's encoders and GNSS) replaces the true poses
   (:func:`services.localizer_offline.write_ledger_input`); ``--poses truth`` skips it;
3. ``import``: ``stockpile ledger import --clock events`` into a DuckDB ledger (the
   backfill path);
4. ``fold``: one fold of the whole ledger that saves a snapshot every
   ``--snapshot-every-min`` site minutes and after every cut
   (:func:`projector.query.build_snapshots`), then the pile as of the end, everything
   known, from the last snapshot; it prints the pile and every cut against the
   simulator's truth in :mod:`bench.projector_truth`'s form (its tables and verdicts:
   the thesis-scale fidelity row);
5. ``query``: three as-of queries ``project(V, K)`` from the snapshots, each in a fresh
   process (the seconds of the query alone, and the process's peak RSS).

Targets (issue 41): stages 1-4 within 20 minutes of wall time; each as-of query within
1 s, in a process whose peak RSS stays within 1 GiB.  ``--reuse`` keeps a stage's output
from an earlier run (its row says ``reused``, and the wall total then counts only the
stages run).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

SCENARIO = "full-scale"
PILE = "P1"
TARGET_WALL_S = 20 * 60.0
TARGET_QUERY_S = 1.0
TARGET_QUERY_RSS_MIB = 1024.0


@dataclass
class Stage:
    """One child process's measurements (seconds, MiB); ``reused``: not run this time."""

    name: str
    wall_s: float = 0.0
    cpu_s: float = 0.0
    peak_rss_mib: float = 0.0
    reused: bool = False
    detail: str = ""


def run_child(name: str, argv: list[str], *, capture: bool = False) -> tuple[Stage, str]:
    """Run ``argv``; its wall and CPU seconds and peak RSS, and its stdout when
    ``capture`` (else passed through).  A failed child raises SystemExit with one line."""
    print(f"[{name}] {' '.join(Path(a).name if a == sys.executable else a for a in argv)}",
          file=sys.stderr, flush=True)
    t0 = time.perf_counter()
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE if capture else None, text=True)
    out = proc.stdout.read() if capture and proc.stdout else ""
    _pid, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        raise SystemExit(f"full_scale: stage {name!r} failed (exit {proc.returncode})")
    return Stage(name, wall, usage.ru_utime + usage.ru_stime, usage.ru_maxrss / 1024), out


def _stockpile(*args: str) -> list[str]:
    return [sys.executable, "-m", "stockpile.cli", *args]


def _self(*args: str) -> list[str]:
    return [sys.executable, str(Path(__file__).resolve()), *args]


# -- the stages run in child processes ----------------------------------------------------


def stage_localize(sim_dir: Path, out: Path) -> None:
    from services.localizer_offline import write_ledger_input
    truth = json.loads((sim_dir / "truth.json").read_text())
    write_ledger_input(sim_dir / "events.jsonl", sim_dir / "gnss.nmea", out,
                       machine_id=truth["scenario"]["machine_id"])


def stage_fold(sim_dir: Path, ledger: Path, snaps_path: Path, every_min: float,
               poses: str, seed: int) -> None:
    """Snapshots over one fold, the end state from the last, the truth tables."""
    from projector_truth import _exact_lab, report

    from ledger import open_ledger
    from projector.query import SnapshotStore, build_snapshots, grade_inputs, project
    from schemas.times import NS_PER_S

    truth = json.loads((sim_dir / "truth.json").read_text())
    t0 = time.perf_counter()
    with open_ledger(ledger, read_only=True) as store, SnapshotStore(snaps_path) as snaps:
        first = None

        def progress(n: int, valid_ns: int) -> None:
            nonlocal first
            first = valid_ns if first is None else first
            if n % 12 == 0:
                print(f"  snapshot {n} at site hour {(valid_ns - first) / 3.6e12:.1f} "
                      f"({time.perf_counter() - t0:.0f} s)", file=sys.stderr, flush=True)

        saved = build_snapshots(store, snaps, PILE, every_ns=int(every_min * 60 * NS_PER_S),
                                progress=progress)
        fold_s = time.perf_counter() - t0
        t1 = time.perf_counter()
        state = project(store, PILE, snapshots=snaps)
        project_s = time.perf_counter() - t1
        lots, assays = grade_inputs(store, state.valid_time_ns, state.known_time_ns)
        result = {"scenario": SCENARIO, "seed": seed, "poses": poses, "noise_seed": seed,
                  "state": state, "truth": truth, "prepare_s": fold_s,
                  "project_s": project_s, "sim_dir": sim_dir, "ledger": ledger,
                  "exact_lab": _exact_lab(state, lots, assays, truth)}
        print(f"\nfold: {saved} snapshots in {fold_s:.0f} s; the end from the last: "
              f"{project_s:.2f} s ('projected in'; 'to simulate and import' below is the "
              "fold's)")
        figures = report(result)
    print("FIGURES " + json.dumps({
        "ok": figures["ok"], "pile_pct": figures["pile_pct"],
        "volume_pct": figures["volume_pct"], "cuts": figures["cuts"],
        "within": figures["within"], "worst_pct": figures["worst_pct"],
        "worst_exact_pp": figures["worst_exact_pp"], "snapshots": saved,
        "fold_s": fold_s}))


def stage_query(ledger: Path, snaps_path: Path, which: str) -> None:
    """One as-of query from the snapshots, timed alone; prints its JSON line."""
    from ledger import open_ledger
    from projector.query import SnapshotStore, project
    from schemas.times import NS_PER_H

    with open_ledger(ledger, read_only=True) as store, SnapshotStore(snaps_path) as snaps:
        head = store.head()
        first = next(iter(store.read(0, 1))).valid_time_ns
        last = max(e.valid_time_ns for e in store.read(max(0, head.global_seq - 2000)))
        v, k = {"end": (None, None),
                "hour-before": (last - NS_PER_H, head.recorded_time_ns - NS_PER_H),
                "half-way": (first + (last - first) // 2, None)}[which]
        t0 = time.perf_counter()
        state = project(store, PILE, v, k, snapshots=snaps)
        seconds = time.perf_counter() - t0
    print(json.dumps({"seconds": seconds, "tonnes": state.tonnes, "cuts": len(state.cuts)}))


QUERIES = {"end": "the end, everything known",
           "hour-before": "1 h before the end, known then",
           "half-way": "half way, known now"}


# -- the parent ---------------------------------------------------------------------------


def _remove(*paths: Path) -> None:
    """Delete files, and folders of files, that a stage writes afresh."""
    for path in paths:
        if path.is_dir():
            shutil.rmtree(path)
        elif path.exists():
            path.unlink()


def _table(stages: list[Stage]) -> None:
    print(f"\n{'stage':<10} {'wall s':>8} {'CPU s':>8} {'peak RSS':>10}  detail")
    for s in stages:
        if s.reused:
            print(f"{s.name:<10} {'reused':>8} {'':>8} {'':>10}  {s.detail}")
        else:
            print(f"{s.name:<10} {s.wall_s:>8.0f} {s.cpu_s:>8.0f} "
                  f"{s.peak_rss_mib:>7,.0f} MiB  {s.detail}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--keep", default=str(ROOT / "bench" / "out" / "full-scale"),
                    help="folder of the run's files (default %(default)s)")
    ap.add_argument("--seed", type=int, default=1, help="the simulator's seed (default 1)")
    ap.add_argument("--poses", choices=("localizer", "truth"), default="localizer",
                    help="the scanner poses that place the scans (default %(default)s)")
    ap.add_argument("--duration", default="24h", help="site time simulated (default 24h)")
    ap.add_argument("--snapshot-every-min", type=float, default=10.0,
                    help="site minutes between snapshots (default %(default)s)")
    ap.add_argument("--reuse", action="store_true",
                    help="keep the stages an earlier run left in --keep")
    ap.add_argument("--stage", help=argparse.SUPPRESS)
    ap.add_argument("--query", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    out = Path(args.keep)
    sim_dir = out / f"{SCENARIO}-seed{args.seed}"
    ledger_in = sim_dir / ("events-localizer.jsonl" if args.poses == "localizer"
                           else "events.jsonl")
    ledger = out / f"{sim_dir.name}-{args.poses}.duckdb"
    snaps = out / f"{ledger.stem}-snapshots.duckdb"
    if args.stage == "localize":
        stage_localize(sim_dir, ledger_in)
        return 0
    if args.stage == "fold":
        stage_fold(sim_dir, ledger, snaps, args.snapshot_every_min, args.poses, args.seed)
        return 0
    if args.stage == "query":
        stage_query(ledger, snaps, args.query)
        return 0

    out.mkdir(parents=True, exist_ok=True)
    common = ["--keep", str(out), "--seed", str(args.seed), "--poses", args.poses,
              "--snapshot-every-min", str(args.snapshot_every_min)]
    print(f"full scale end to end: {SCENARIO}, seed {args.seed}, {args.duration}, "
          f"{args.poses} poses, into {out} (CPUs: {os.cpu_count()}, load average "
          f"{os.getloadavg()[0]:.2f})", flush=True)
    stages: list[Stage] = []

    def step(name: str, done: bool, argv: list[str], clear: list[Path]) -> Stage:
        if args.reuse and done:
            stage = Stage(name, reused=True)
        else:
            _remove(*clear)
            stage, _ = run_child(name, argv)
        stages.append(stage)
        return stage

    step("simulate", (sim_dir / "truth.json").exists(),
         _stockpile("sim", "--scenario", SCENARIO, "--seed", str(args.seed), "--speed", "0",
                    "--scan-events", "truth", "--duration", args.duration,
                    "--out", str(sim_dir)), [])
    if args.poses == "localizer":
        step("localize", ledger_in.exists(), _self("--stage", "localize", *common), [])
    step("import", ledger.exists(),
         _stockpile("ledger", "import", str(ledger_in), "--ledger", str(ledger), "--clock",
                    "events"), [ledger, snaps, Path(str(snaps) + ".d")])
    events = sum(1 for _ in ledger_in.open("rb"))
    stages[-1].detail = f"{events:,} events"
    _remove(snaps, Path(str(snaps) + ".d"))    # one fold builds them afresh
    fold, text = run_child("fold", _self("--stage", "fold", *common), capture=True)
    stages.append(fold)
    report_lines = [line for line in text.splitlines() if not line.startswith("FIGURES ")]
    figures = json.loads(next(line for line in text.splitlines()
                              if line.startswith("FIGURES "))[len("FIGURES "):])
    fold.detail = f"{figures['snapshots']} snapshots, fold {figures['fold_s']:.0f} s"
    wall = sum(s.wall_s for s in stages if not s.reused)
    print("\n".join(report_lines))
    queries = []
    for key, label in QUERIES.items():
        stage, text = run_child("query", _self("--stage", "query", "--query", key, *common),
                                capture=True)
        answer = json.loads(text.strip().splitlines()[-1])
        queries.append((label, answer, stage))

    _table(stages)
    all_run = not any(s.reused for s in stages)
    wall_ok = wall <= TARGET_WALL_S
    print(f"simulate + ingest + project: {wall:,.0f} s wall "
          f"({'every stage' if all_run else 'the stages run this time'}); target "
          f"<= {TARGET_WALL_S:,.0f} s {'PASS' if wall_ok and all_run else 'MISS' if all_run else '-'}")
    print(f"\n{'as-of query':<32} {'tonnes':>12} {'cuts':>5} {'query s':>8} {'peak RSS':>10}  verdict")
    query_ok = True
    for label, answer, stage in queries:
        good = answer["seconds"] <= TARGET_QUERY_S and stage.peak_rss_mib <= TARGET_QUERY_RSS_MIB
        query_ok &= good
        print(f"{label:<32} {answer['tonnes']:>12,.0f} {answer['cuts']:>5} "
              f"{answer['seconds']:>8.2f} {stage.peak_rss_mib:>7,.0f} MiB  "
              f"{'PASS' if good else 'MISS'}")
    print(f"targets: each query <= {TARGET_QUERY_S:g} s with peak RSS <= "
          f"{TARGET_QUERY_RSS_MIB:,.0f} MiB (the whole process, imports included); "
          f"fidelity: {'PASS' if figures['ok'] else 'MISS'} ({figures['within']} of "
          f"{figures['cuts']} cuts within 3 % and 0.3 pp; pile {figures['pile_pct']:+.2f} %)")
    return 0 if (figures["ok"] and query_ok and wall_ok and all_run) else 1


if __name__ == "__main__":
    sys.exit(main())
