"""MCAP sessions benchmark: record, replay into a ledger, replay onto Zenoh.

    .venv/bin/python bench/replay.py [--ledger DEMO.duckdb] [--work DIR] [--repeats N]

The session is the demo yard: by default the simulator's full ``demo`` scenario
(seed 1, about 6 site hours, scans and scanner poses included) ledgered with the
site clock, built once in ``--work`` and reused; ``--ledger`` takes an existing demo
ledger instead (``make demo`` leaves one in ``demo-out/ledger.duckdb``).  Prints one
table:

1. export-mcap: the ledger to an MCAP file (msgs/s).
2. Record: the recorder's pipeline (the Zenoh callback's ``offer`` -> queue -> writer
   thread -> identity, duplicates, gaps, site-clock log time -> zstd MCAP) against the
   bare ``mcap`` writer writing the same messages to the same channels, best of N,
   interleaved.  Target: ratio >= 0.8.
3. replay --ledger into an empty ledger, recorded times preserved: site time covered
   by the session over wall time.  Target: >= 50x real time.
4. replay --publish --max onto Zenoh (the real command, its own process, a loopback
   router here) with a subscriber here counting every sample: msgs/s.
"""

from __future__ import annotations

import argparse
import gc
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import zenoh  # noqa: E402
from mcap.writer import CompressionType, Writer  # noqa: E402

from ledger import EventClock, open_ledger  # noqa: E402
from ledger.cli import import_lines  # noqa: E402
from replay.export import export_ledger  # noqa: E402
from replay.mcap_writer import channel_metadata, schema_of  # noqa: E402
from replay.record import Config, Recorder  # noqa: E402
from replay.replay import iter_events, replay_to_ledger  # noqa: E402
from schemas.events import encode_attachment  # noqa: E402
from services.service import SiteTime, ZenohOptions  # noqa: E402
from stockpile.orchestrate import free_loopback_port  # noqa: E402

SITE = "capelambert"


def demo_ledger(work: Path) -> Path:
    """The demo session's ledger, simulated and ledgered once (then reused)."""
    ledger = work / "demo.duckdb"
    if ledger.exists():
        return ledger
    sim = work / "sim"
    print("building the demo session (simulator, demo scenario, seed 1; takes a few minutes) ...",
          flush=True)
    subprocess.run([sys.executable, "-m", "stockpile.cli", "sim", "--scenario", "demo", "--seed",
                    "1", "--speed", "0", "--scan-events", "truth", "--out", str(sim)], check=True,
                   stdout=subprocess.DEVNULL)
    partial = work / "demo.partial.duckdb"
    with open_ledger(partial, EventClock()) as store, (sim / "events.jsonl").open("rb") as f:
        import_lines(store, f, batch_size=10_000)
    partial.rename(ledger)
    return ledger


# -- record ------------------------------------------------------------------------------


def bare_writer(samples: list, path: Path) -> float:
    """Seconds for the bare mcap writer to write ``samples`` (channels made on first use)."""
    started = time.perf_counter()
    with open(path, "wb") as f:
        writer = Writer(f, compression=CompressionType.ZSTD)
        writer.start()
        schemas: dict[str, int] = {}
        channels: dict[tuple[str, int], int] = {}
        for key, payload, _attachment, e in samples:
            channel = channels.get((key, e.epoch))
            if channel is None:
                if e.type not in schemas:
                    name, data = schema_of(e.type)
                    schemas[e.type] = writer.register_schema(name, "protobuf", data)
                channel = channels[(key, e.epoch)] = writer.register_channel(
                    key, "protobuf", schemas[e.type], channel_metadata(e.type, e.source, e.epoch))
            writer.add_message(channel, time.time_ns(), payload, e.valid_time_ns, e.seq)
        writer.finish()
    return time.perf_counter() - started


def recorder_pipeline(samples: list, path: Path) -> float:
    """Seconds from the first ``offer`` (a producer thread, as Zenoh's) to the closed file."""
    path.unlink(missing_ok=True)
    recorder = Recorder(Config(site=SITE, zenoh=ZenohOptions(), out=str(path)), SiteTime("wall"),
                        logger=lambda *a, **k: None)
    writer = threading.Thread(target=recorder.run)
    started = time.perf_counter()
    writer.start()
    offer = recorder.offer
    for key, payload, attachment, _e in samples:
        offer(key, payload, attachment)
    recorder.close()
    writer.join()
    elapsed = time.perf_counter() - started
    assert recorder.failed is None, recorder.failed
    assert recorder.status.get("recorded") == len(samples), recorder.status.counters
    return elapsed


def bench_record(session: Path, work: Path, repeats: int) -> dict:
    samples = [(e.topic, e.payload, encode_attachment(e.epoch, e.seq, e.valid_time_ns), e)
               for e in iter_events(session)]
    # the message list is long-lived for both sides: keep the cyclic GC from re-walking
    # it (the recorder service freezes what it holds at start-up the same way)
    gc.collect()
    gc.freeze()
    bare, ours = [], []
    for _ in range(repeats):  # interleaved, so both see the same machine
        bare.append(bare_writer(samples, work / "bare.mcap"))
        ours.append(recorder_pipeline(samples, work / "recorded.mcap"))
    gc.unfreeze()
    n = len(samples)
    paired = [b / o for b, o in zip(bare, ours)]
    return {"n": n, "bare_best": n / min(bare), "ours_best": n / min(ours),
            "bare_median": n / statistics.median(bare), "ours_median": n / statistics.median(ours),
            "paired_median": statistics.median(paired),
            "bytes": (work / "recorded.mcap").stat().st_size,
            "mean_payload": sum(len(s[1]) for s in samples) / n}


# -- replay --------------------------------------------------------------------------------


def bench_replay_ledger(session: Path, work: Path) -> dict:
    target = work / "replayed.duckdb"
    for suffix in ("", ".wal", ".head"):
        Path(str(target) + suffix).unlink(missing_ok=True)
    with open_ledger(target) as store:
        result = replay_to_ledger(session, store)
    return {"events": result.events, "appended": result.counts["appended"],
            "wall_s": result.wall_s, "site_h": result.site_span_s / 3600,
            "speed_up": result.speed_up}


def bench_replay_zenoh(session: Path, expected: int) -> dict:
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    router = zenoh.open(ZenohOptions(mode="router", listen=(endpoint,)).to_config())
    received = [0]
    done = threading.Event()

    def on_sample(_sample) -> None:
        received[0] += 1
        if received[0] >= expected:
            done.set()

    subscriber = router.declare_subscriber(f"stockpile/{SITE}/@v1/**", on_sample)
    try:
        run = subprocess.run([sys.executable, "-m", "stockpile.cli", "replay", str(session),
                              "--publish", "--max", "--no-progress", "--linger", "2",
                              *ZenohOptions(mode="client", connect=(endpoint,)).to_argv()],
                             capture_output=True, text=True, timeout=600)
        done.wait(30)
    finally:
        subscriber.undeclare()
        router.close()
    if run.returncode != 0:
        raise RuntimeError(run.stderr[-2000:])
    line = next(line for line in run.stdout.splitlines() if line.startswith("published"))
    rate = float(line.rsplit("=", 1)[1].split()[0].replace(",", ""))
    return {"line": line, "rate": rate, "received": received[0]}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ledger", type=Path, help="an existing demo ledger (default: build one)")
    parser.add_argument("--work", type=Path, default=Path("/tmp/stockpile-bench-replay"),
                        help="working folder (the built session is kept here)")
    parser.add_argument("--repeats", type=int, default=7, help="record runs per side (best of)")
    args = parser.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    ledger = args.ledger or demo_ledger(args.work)
    session = args.work / "session.mcap"

    with open_ledger(ledger, read_only=True) as store:
        exported = export_ledger(store, session, site=SITE)
    rec = bench_record(session, args.work, args.repeats)
    led = bench_replay_ledger(session, args.work)
    zen = bench_replay_zenoh(session, exported.events)

    print(f"\n# MCAP sessions benchmark: {ledger} ({exported.events:,} events, "
          f"{session.stat().st_size / 1e6:.1f} MB MCAP); 2-core VM, shared")
    print("\n| what | result | target |")
    print("|---|---|---|")
    print(f"| export-mcap | {exported.events:,} events in {exported.wall_s:.2f} s = "
          f"{exported.events / exported.wall_s:,.0f} msgs/s | - |")
    ratio_best = rec["ours_best"] / rec["bare_best"]
    ratio_median = rec["ours_median"] / rec["bare_median"]
    print(f"| record pipeline vs bare mcap writer ({rec['n']:,} msgs, mean payload "
          f"{rec['mean_payload']:,.0f} B, best of {args.repeats}) | ours {rec['ours_best']:,.0f} "
          f"msgs/s, bare {rec['bare_best']:,.0f} msgs/s = **{ratio_best:.2f}** (medians "
          f"{rec['ours_median']:,.0f} / {rec['bare_median']:,.0f} = {ratio_median:.2f}; median "
          f"of paired runs {rec['paired_median']:.2f}) | >= 0.8 "
          f"{'PASS' if ratio_best >= 0.8 else 'MISS'} |")
    print(f"| replay --ledger (recorded times preserved) | {led['appended']:,} events, "
          f"{led['site_h']:.2f} site h in {led['wall_s']:.2f} s = **{led['speed_up']:,.0f}x** "
          f"real time ({led['events'] / led['wall_s']:,.0f} msgs/s) | >= 50x "
          f"{'PASS' if led['speed_up'] >= 50 else 'MISS'} |")
    print(f"| replay --publish --max onto Zenoh | **{zen['rate']:,.0f} msgs/s**; the subscriber "
          f"received {zen['received']:,} of {exported.events:,} | - |")
    return 0 if ratio_best >= 0.8 and led["speed_up"] >= 50 and \
        zen["received"] == exported.events else 1


if __name__ == "__main__":
    sys.exit(main())
