"""A blending yard live at 1x real time: what the whole stack costs a small edge box.

    .venv/bin/python bench/live.py                       # 10 site minutes, into bench/out/live
    .venv/bin/python bench/live.py --minutes 2 --keep /tmp/live   # a shorter look

The yard has two beds, both the thesis' full-scale pile (220 m x 70 m, about 30 m
high): bed A is being stacked (pile ``A``, stacker ``stk1``, its reclaimer ``bwr1``
trailing the stacker with its scanner) while bed B, stacked the day before, is being
reclaimed (pile ``B``, reclaimer ``bwr2``, 300 m further along the rail).  Each bed is a
simulator process (``stockpile sim --scenario two-bed-stack`` / ``two-bed-reclaim``); in
the live window each scanner runs at 75 Hz, each GNSS at 10 Hz and each machine's
encoders at 50 Hz, with the PLCs' stacking and reclaim events and the lab's assays.

1. **History.**  Each bed's day before the live moment (``--after-reclaim-min`` after
   bed B's reclaim starts, so that the window sees its first cuts) is simulated as fast as it goes (scans at 2 Hz, true poses) and both are
   imported into one DuckDB ledger, each line's recorded time the site time it was
   emitted at (kept in ``--keep`` and reused when the seed and moment are the same).
2. **The stack**, every service its own process on a loopback Zenoh router (this
   process; mutual TLS and access by role unless ``--insecure``): ``ledger``,
   ``recorder`` (MCAP), per machine ``scanner`` (the simulator's LMS200 pseudo-terminal),
   ``gnss`` (its NMEA pseudo-terminal) and ``localizer``, one ``projector`` per pile and
   one ``dashboard --out live.rrd`` showing both piles.  The projectors and the
   dashboard fold the history first (their catch-up, timed, not in the window).
3. **Live.**  Both simulators skip silently to the live moment and then run paced at
   1x, in step on the wall clock (``stockpile sim --live-at --live-wall``).  After
   ``--settle-s``, the window of ``--minutes`` site minutes is measured: each process's
   CPU seconds (``/proc/<pid>/stat``) per site second, its RSS sampled every 5 s (the
   window's first and last minute) and its peak RSS (``VmHWM``).

Targets (issue 41): the whole stack (every service and the router; not the simulators,
which are the world) within 50 % of one core, and no process growing in memory over the
window (its last minute's mean RSS within 5 % or 20 MiB of its first minute's).
"""

from __future__ import annotations

import argparse
import heapq
import json
import os
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from stockpile.orchestrate import Supervisor

SITE = "capelambert"
BEDS = {"A": "two-bed-stack", "B": "two-bed-reclaim"}
MACHINES = {"A": "bwr1", "B": "bwr2"}
TARGET_CORE_FRACTION = 0.5
#: a process "grows" when its last minute's mean RSS exceeds its first minute's by more
#: than both of these
GROWTH_FRACTION, GROWTH_MIB = 0.05, 20.0
SAMPLE_S = 5.0
CLK_TCK = os.sysconf("SC_CLK_TCK")
PAGE_MIB = os.sysconf("SC_PAGE_SIZE") / 2**20


def _stockpile(*args: str, capture: bool = True) -> str:
    proc = subprocess.run([sys.executable, "-m", "stockpile.cli", *args], check=False,
                          stdout=subprocess.PIPE if capture else None, text=True)
    if proc.returncode != 0:
        raise SystemExit(f"live: stockpile {' '.join(args[:3])} ... failed (exit "
                         f"{proc.returncode})")
    return proc.stdout or ""


def milestones(scenario: str, seed: int) -> dict:
    return json.loads(_stockpile("sim", "--scenario", scenario, "--seed", str(seed),
                                 "--milestones").strip().splitlines()[-1])


# -- 1. the history -----------------------------------------------------------------------


def _emitted(path: Path):
    """``(recorded_ns, line)`` of a run's events.jsonl: each line recorded at the site
    time it was emitted (the running maximum of the valid times: a late assay is
    emitted when the lab reports it, after the windows it covers)."""
    latest = -1
    with path.open(encoding="utf-8") as fh:
        for line in fh:
            record = json.loads(line)
            latest = max(latest, int(record["valid_time_ns"]))
            record["recorded_time_ns"] = latest
            yield latest, json.dumps(record, separators=(",", ":"), sort_keys=True)


def history(keep: Path, seed: int, live_ns: int) -> tuple[Path, int]:
    """The ledger holding both beds' history up to ``live_ns`` (built once); its events."""
    ledger = keep / f"history-seed{seed}-{live_ns}.duckdb"
    merged = keep / f"history-seed{seed}-{live_ns}.jsonl"
    if ledger.exists():
        return ledger, sum(1 for _ in merged.open("rb"))
    runs = []
    for bed, scenario in BEDS.items():
        start = milestones(scenario, seed)["start_ns"]
        out = keep / f"history-{bed}-seed{seed}-{live_ns}"
        if not (out / "truth.json").exists():
            print(f"  simulating bed {bed}'s history ({(live_ns - start) / 3.6e12:.1f} site h, "
                  "scans at 2 Hz)", flush=True)
            _stockpile("sim", "--scenario", scenario, "--seed", str(seed), "--speed", "0",
                       "--scan-events", "truth", "--duration", f"{(live_ns - start) / 1e9:.3f}s",
                       "--out", str(out), capture=False)
        runs.append(out / "events.jsonl")
    n = 0
    partial = merged.with_name(merged.name + ".partial")
    with partial.open("w", encoding="utf-8") as dst:
        for _t, line in heapq.merge(*(_emitted(p) for p in runs), key=lambda x: x[0]):
            dst.write(line + "\n")
            n += 1
    partial.replace(merged)
    print(f"  importing {n:,} history events into {ledger.name}", flush=True)
    _stockpile("ledger", "import", str(merged), "--ledger", str(ledger), "--clock", "events",
               capture=False)
    return ledger, n


# -- 3. measuring processes ---------------------------------------------------------------


def cpu_s(pid: int) -> float:
    """User + system CPU seconds of a live process (its threads included)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / CLK_TCK


def rss_mib(pid: int) -> float:
    return int(Path(f"/proc/{pid}/statm").read_text().split()[1]) * PAGE_MIB


def peak_rss_mib(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return float("nan")


@dataclass
class Watched:
    name: str
    pid: int
    world: bool = False                       # a simulator: not part of the stack
    cpu0: float = 0.0
    cpu1: float = 0.0
    rss: list[tuple[float, float]] = field(default_factory=list)   # (s into window, MiB)
    peak_mib: float = 0.0

    def growth(self, minutes: float) -> tuple[float, float, bool]:
        """First and last minute's mean RSS (MiB), and whether it grew."""
        first = [m for t, m in self.rss if t <= 60.0]
        last = [m for t, m in self.rss if t >= minutes * 60.0 - 60.0]
        a, b = sum(first) / len(first), sum(last) / len(last)
        return a, b, (b - a) > max(GROWTH_FRACTION * a, GROWTH_MIB)


def measure(procs: list[Watched], seconds: float) -> None:
    """CPU over ``seconds`` and RSS every SAMPLE_S, for every process."""
    t0 = time.monotonic()
    for p in procs:
        p.cpu0 = cpu_s(p.pid)
    next_sample = t0
    while True:
        now = time.monotonic()
        if now >= next_sample:
            for p in procs:
                p.rss.append((now - t0, rss_mib(p.pid)))
            next_sample += SAMPLE_S
            done = now - t0
            if int(done) % 60 < SAMPLE_S:
                print(f"  window: {done / 60:.1f} of {seconds / 60:g} site min", flush=True)
        if now - t0 >= seconds:
            break
        time.sleep(max(0.0, min(next_sample, t0 + seconds) - time.monotonic()))
    for p in procs:
        p.cpu1 = cpu_s(p.pid)
        p.peak_mib = peak_rss_mib(p.pid)


# -- 2. the stack -------------------------------------------------------------------------


def members() -> dict[str, str]:
    out = {"ledger": "ledger", "recorder": "recorder", "dashboard": "dashboard",
           "simA": "replay", "simB": "replay"}
    for bed, machine in MACHINES.items():
        out.update({f"{machine}.scanner": "scanner", f"{machine}.gnss": "gnss",
                    f"{machine}.localizer": "localizer", f"projector-{bed}": "projector"})
    return out


def _common(yard: Supervisor, name: str) -> list[str]:
    return ["--site", SITE, "--status-period", "30", *yard.client_args_for(name)]


def _wait_log(yard: Supervisor, name: str, message: str, timeout_s: float) -> float:
    """Block until child ``name`` logs ``message``; the monotonic time it was seen."""
    deadline = time.monotonic() + timeout_s
    child = yard.children[name]
    while time.monotonic() < deadline:
        if any(r.get("msg") == message for r in child.log_records()):
            return time.monotonic()
        if child.process.poll() is not None:
            raise SystemExit(f"live: {name} exited ({child.process.returncode}); see "
                             f"{child.log_path}")
        time.sleep(0.5)
    raise SystemExit(f"live: {name} did not log {message!r} in {timeout_s:g} s; see "
                     f"{child.log_path}")


def start_followers(yard: Supervisor, ledger: Path, out: Path) -> dict[str, float]:
    """Ledger, recorder, projectors and the dashboard; their catch-up seconds."""
    yard.start("ledger", ["service", "ledger", "--ledger", str(ledger), "--clock", "events",
                          *_common(yard, "ledger")])
    yard.wait_live("ledger")
    yard.start("recorder", ["service", "recorder", "--out", str(out / "live.mcap"),
                            "--clock", "events", *_common(yard, "recorder")])
    t0 = time.monotonic()
    for bed in BEDS:
        yard.start(f"projector-{bed}", ["service", "projector", "--pile", bed,
                                        *_common(yard, f"projector-{bed}")])
    yard.start("dashboard", ["service", "dashboard", *[a for bed in BEDS for a in ("--pile", bed)],
                             "--out", str(out / "live.rrd"), *_common(yard, "dashboard")])
    caught = {}
    for name in [f"projector-{bed}" for bed in BEDS] + ["dashboard"]:
        caught[name] = _wait_log(yard, name, "caught up", 3600.0) - t0
        print(f"  {name} caught up with the history in {caught[name]:.0f} s", flush=True)
    return caught


def start_yard(yard: Supervisor, out: Path, seed: int, live_ns: int, live_wall: float,
               end_ns: int) -> None:
    """Both simulators and, on their devices, each machine's scanner, GNSS and localizer."""
    for bed, scenario in BEDS.items():
        machine = MACHINES[bed]
        start = milestones(scenario, seed)["start_ns"]
        yard.start(f"localizer-{bed}", ["service", "localizer", "--machine", machine,
                                        *_common(yard, f"{machine}.localizer")])
        sim = yard.start(f"sim{bed}", [
            "sim", "--scenario", scenario, "--seed", str(seed), "--out", str(out / f"sim-{bed}"),
            "--pty", "--zenoh", "--speed", "1", "--live-at", str(live_ns),
            "--live-wall", f"{live_wall:.3f}", "--duration", f"{(end_ns - start) / 1e9:.3f}s",
            "--linger", "30", *yard.client_args_for(f"sim{bed}")])
        scanner = sim.wait_stdout(lambda line: line.startswith("LMS200 scanner on"), 120)
        gnss = sim.wait_stdout(lambda line: line.startswith("GNSS receiver"), 120)
        yard.start(f"scanner-{bed}", ["service", "scanner", "--device", scanner.split()[-1],
                                      "--clock", "events", "--source", f"{machine}.scanner",
                                      *_common(yard, f"{machine}.scanner")])
        yard.start(f"gnss-{bed}", ["service", "gnss", "--device", gnss.split()[-1],
                                   "--clock", "events", "--source", f"{machine}.gnss",
                                   "--frame-id", f"{machine}/gnss",
                                   *_common(yard, f"{machine}.gnss")])


# -- the report ---------------------------------------------------------------------------


def report(procs: list[Watched], window_s: float, minutes: float, caught: dict) -> bool:
    print(f"\n{'process':<14} {'CPU s':>8} {'CPU s / site s':>15} {'RSS first min':>14} "
          f"{'RSS last min':>13} {'peak RSS':>10}  grows")
    stack_cpu, ok = 0.0, True
    for p in sorted(procs, key=lambda p: (p.world, p.name)):
        used = p.cpu1 - p.cpu0
        a, b, grows = p.growth(minutes)
        if not p.world:
            stack_cpu += used
            ok &= not grows
        label = p.name + (" (world)" if p.world else "")
        print(f"{label:<14} {used:>8.1f} {used / window_s:>15.3f} {a:>10,.0f} MiB "
              f"{b:>9,.0f} MiB {p.peak_mib:>6,.0f} MiB  {'YES' if grows else 'no'}")
    share = stack_cpu / window_s
    ok &= share <= TARGET_CORE_FRACTION
    print(f"the stack (every service and the router): {stack_cpu:.1f} CPU s over "
          f"{window_s:.0f} site s = {share:.1%} of one core; target <= "
          f"{TARGET_CORE_FRACTION:.0%} {'PASS' if share <= TARGET_CORE_FRACTION else 'MISS'}")
    print("catch-up of the history before the window: " + ", ".join(
        f"{name} {s:.0f} s" for name, s in caught.items()))
    print(f"no process grows (last minute's mean RSS within {GROWTH_FRACTION:.0%} or "
          f"{GROWTH_MIB:g} MiB of the first's): "
          f"{'PASS' if all(not p.growth(minutes)[2] for p in procs if not p.world) else 'MISS'}")
    return ok


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--keep", default=str(ROOT / "bench" / "out" / "live"),
                    help="folder of the history, logs and recordings (default %(default)s)")
    ap.add_argument("--seed", type=int, default=1, help="the simulators' seed (default 1)")
    ap.add_argument("--minutes", type=float, default=10.0,
                    help="site minutes measured at 1x (default %(default)s)")
    ap.add_argument("--settle-s", type=float, default=30.0,
                    help="site seconds after the live moment before the window opens")
    ap.add_argument("--lead-s", type=float, default=240.0,
                    help="wall seconds the simulators get to skip to the live moment")
    ap.add_argument("--after-reclaim-min", type=float, default=10.0,
                    help="site minutes after bed B's reclaim starts that the yard goes live "
                    "(default %(default)s: its reclaimer has travelled to the first cut, "
                    "which the window sees)")
    ap.add_argument("--insecure", action="store_true", help="plain TCP instead of mutual TLS")
    args = ap.parse_args(argv)
    if args.minutes < 2:
        ap.error("--minutes must be at least 2 (a first and a last minute are compared)")
    keep = Path(args.keep)
    keep.mkdir(parents=True, exist_ok=True)
    live_ns = (milestones(BEDS["B"], args.seed)["reclaim_start_ns"]
               + int(args.after_reclaim_min * 60e9))
    print(f"live yard: two full-scale beds, seed {args.seed}, live from "
          f"{args.after_reclaim_min:g} min after bed B's reclaim start ({live_ns} ns), "
          f"{args.minutes:g} site min at 1x (CPUs {os.cpu_count()}, load average "
          f"{os.getloadavg()[0]:.2f})", flush=True)
    ledger_src, n_history = history(keep, args.seed, live_ns)
    run = keep / f"run-{time.strftime('%Y%m%dT%H%M%S')}"
    run.mkdir()
    ledger = run / "ledger.duckdb"
    for part in ledger_src.parent.glob(ledger_src.name + "*"):   # the file and its sidecars
        if part.is_file():
            shutil.copy2(part, run / ("ledger.duckdb" + part.name[len(ledger_src.name):]))
    window_s = args.minutes * 60.0
    end_ns = live_ns + int((args.settle_s + window_s + 30.0) * 1e9)
    with Supervisor(run, site=SITE, quiet=True,
                    members=None if args.insecure else members()) as yard:
        caught = start_followers(yard, ledger, run)
        live_wall = time.time() + args.lead_s
        start_yard(yard, run, args.seed, live_ns, live_wall, end_ns)
        wait = live_wall + args.settle_s - time.time()
        print(f"  history {n_history:,} events; the yard goes live in "
              f"{live_wall - time.time():.0f} s; the window opens {args.settle_s:g} s later",
              flush=True)
        time.sleep(max(0.0, wait))
        dead = [f"{name} (exit {child.process.returncode}, {child.log_path})"
                for name, child in yard.children.items() if child.process.poll() is not None]
        if dead:
            raise SystemExit("live: a process of the yard stopped before the window: "
                             + "; ".join(dead))
        procs = [Watched(name, child.process.pid, world=name.startswith("sim"))
                 for name, child in yard.children.items()]
        procs.append(Watched("router", os.getpid()))
        measure(procs, window_s)
        late = [r for name in ("simA", "simB") for r in yard.children[name].log_records()
                if "late" in str(r.get("msg", ""))]
    ok = report(procs, window_s, args.minutes, caught)
    for r in late:
        print(f"  a simulator reached the live moment late: {r}")
    print(f"logs, live.mcap and live.rrd in {run}")
    return 0 if ok and not late else 1


if __name__ == "__main__":
    sys.exit(main())
