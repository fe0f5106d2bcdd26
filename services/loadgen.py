"""A load generator: one ledger-bound source publishing synthetic events at a fixed rate.

Used by the loss test and ``bench/ingest.py``::

    python -m services.loadgen --source load1 --type joint_reading --rate 2000 \\
        --duration 20 --connect tcp/127.0.0.1:7447 --report load1.json

It publishes through :class:`services.service.EventPublisher` (AdvancedPublisher,
cache, BLOCK), paced in 10 ms ticks against the monotonic clock, and writes a JSON
report: source, epoch, count (sequences ``0..count-1``), achieved rate, and the
monotonic publish time of every ``--stamp-every``-th event (for latency).  With
``--wait-subscriber S`` it starts only once a subscriber matches.
"""

from __future__ import annotations

import argparse
import array
import json
import math
import os
import sys
import time

import numpy as np
import zenoh
from foxglove_schemas_protobuf.LaserScan_pb2 import LaserScan

from schemas.events import set_timestamp_ns
from schemas.stockpile.v1 import events_pb2 as pb
from schemas.times import NS_PER_S
from services.service import EventPublisher, Stopper, ZenohOptions, log
from services.zenoh_config import add_zenoh_arguments

TICK_S = 0.01
BASE_TIME_NS = 1_790_000_000 * NS_PER_S  # 2026-09-21, a fixed valid-time origin


def make_message(type_name: str, index: int, rng: np.random.Generator, beams: int):
    """The ``index``-th synthetic message of ``type_name`` (valid time 1 ms apart)."""
    t = BASE_TIME_NS + index * 1_000_000
    if type_name == "joint_reading":
        msg = pb.JointReading(machine_id="load", travel_m=float(index % 1000) * 0.01,
                              slew_rad=0.1, luff_rad=0.05)
        set_timestamp_ns(msg.time, t)
        return msg
    if type_name == "scan":
        msg = LaserScan(frame_id="load/scanner", start_angle=-0.8726646259971648,
                        end_angle=0.8726646259971648)
        msg.ranges.extend((10.0 + rng.random(beams)).tolist())
        set_timestamp_ns(msg.timestamp, t)
        return msg
    raise ValueError(f"loadgen publishes joint_reading or scan, not {type_name!r}")


def run(session, *, site: str, source: str, type_name: str, rate_hz: float, duration_s: float,
        cache_samples: int, beams: int, stamp_every: int, stopper: Stopper,
        wait_subscriber_s: float = 0.0, seed: int = 0) -> tuple[dict, EventPublisher]:
    """Publish; return the report and the (still open) publisher."""
    publisher = EventPublisher(session, site, source, cache_samples=cache_samples)
    publisher.declare(type_name)
    if wait_subscriber_s > 0:
        publisher.wait_matched(type_name, wait_subscriber_s)
    rng = np.random.default_rng(seed)
    # pre-build a pool of messages so building them does not limit the rate
    pool = [make_message(type_name, i, rng, beams) for i in range(min(1000, max(1, int(rate_hz))))]
    # monotonic s of events 0, stamp_every, 2 * stamp_every, ...: 8 bytes each, so that a
    # long run's instrument does not grow the process by much
    stamps = array.array("d")
    total = math.inf if duration_s <= 0 else int(round(rate_hz * duration_s))
    t0 = time.monotonic()
    n = 0
    while n < total and not stopper.is_set():
        due = min(total, int((time.monotonic() - t0 + TICK_S) * rate_hz))
        while n < due:
            msg = pool[n % len(pool)]
            stamp = msg.timestamp if type_name == "scan" else msg.time
            set_timestamp_ns(stamp, BASE_TIME_NS + n * 1_000_000)
            publisher.publish(msg)
            if stamp_every and n % stamp_every == 0:
                stamps.append(time.monotonic())
            n += 1
        sleep = t0 + (n / rate_hz) - time.monotonic() if rate_hz > 0 else 0
        if sleep > 0:
            stopper.wait(min(sleep, TICK_S))
    elapsed = time.monotonic() - t0
    report = {"source": source, "epoch": publisher.epoch, "type": type_name, "count": n,
              "elapsed_s": elapsed, "rate_hz": n / elapsed if elapsed > 0 else 0.0,
              "stamps": [(i * stamp_every, t) for i, t in enumerate(stamps)]}
    return report, publisher


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m services.loadgen", description=__doc__.splitlines()[0])
    p.add_argument("--site", default="load")
    p.add_argument("--source", required=True)
    p.add_argument("--type", dest="type_name", default="joint_reading",
                   choices=("joint_reading", "scan"))
    p.add_argument("--rate", type=float, default=1000.0, help="events per second")
    p.add_argument("--duration", type=float, default=10.0, help="seconds (0 = until stopped)")
    p.add_argument("--cache", type=int, default=50_000, help="samples cached per key")
    p.add_argument("--beams", type=int, default=401, help="ranges per scan")
    p.add_argument("--stamp-every", type=int, default=0,
                   help="record the publish moment of every N-th event (latency)")
    p.add_argument("--wait-subscriber", type=float, default=0.0, metavar="S")
    p.add_argument("--report", help="write the JSON report here (default stdout)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--linger", type=float, default=0.0, metavar="S",
                   help="after the report, keep the publishers (and their caches) up for S "
                   "seconds or until SIGTERM, so a subscriber can still recover from them")
    add_zenoh_arguments(p)
    args = p.parse_args(argv)
    stopper = Stopper()
    with zenoh.open(ZenohOptions.from_args(args).to_config()) as session:
        report, publisher = run(session, site=args.site, source=args.source, type_name=args.type_name,
                     rate_hz=args.rate, duration_s=args.duration, cache_samples=args.cache,
                     beams=args.beams, stamp_every=args.stamp_every, stopper=stopper,
                     wait_subscriber_s=args.wait_subscriber, seed=args.seed)
        text = json.dumps(report)
        if args.report:
            tmp = f"{args.report}.tmp"
            with open(tmp, "w", encoding="utf-8") as f:
                f.write(text)
            os.replace(tmp, args.report)  # appears whole: readers may poll for it
        else:
            print(text)
        log("loadgen", "published", source=report["source"], epoch=report["epoch"],
            count=report["count"], rate_hz=report["rate_hz"])
        if args.linger > 0:
            stopper.wait(args.linger)
        publisher.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
