"""A producer that dates its events by its own wall clock (``time.time_ns()``), as a PLC does.

Run as ``python tests/faults/wall_producer.py --source S --rate HZ --duration S --report
FILE [zenoh options]``.  It publishes through :class:`services.publishing.EventPublisher`
(epoch: the wall clock at start, as in production) one ``clock`` event then nine
``joint_reading`` events, and so on, each with valid time ``time.time_ns()`` at
publishing, paced against the monotonic clock; then it writes the report the fault
harness reads: ``{"streams": [{source, epoch, count, stamps}]}`` (stamps: ``[seq,
monotonic s]`` of every ``--stamp-every``-th event).  The clock-step case runs it with a
``sitecustomize`` that steps ``time.time``/``time.time_ns``/``datetime`` back.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import zenoh

from schemas.events import set_timestamp_ns
from schemas.stockpile.v1 import events_pb2 as pb
from services.publishing import EventPublisher
from services.service import Stopper, ZenohOptions
from services.zenoh_config import add_zenoh_arguments

#: every CLOCK_EVERY-th event is a ``clock`` event
CLOCK_EVERY = 10


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--site", default="faults")
    p.add_argument("--source", required=True)
    p.add_argument("--rate", type=float, default=200.0, help="events per second")
    p.add_argument("--duration", type=float, default=5.0, help="seconds")
    p.add_argument("--stamp-every", type=int, default=20)
    p.add_argument("--wait-subscriber", type=float, default=60.0, metavar="S")
    p.add_argument("--report", required=True)
    add_zenoh_arguments(p)
    args = p.parse_args(argv)
    stopper = Stopper()
    with zenoh.open(ZenohOptions.from_args(args).to_config()) as session:
        publisher = EventPublisher(session, args.site, args.source)
        publisher.declare("clock", "joint_reading")
        publisher.wait_matched("joint_reading", args.wait_subscriber)
        total = int(round(args.rate * args.duration))
        stamps, t0, n = [], time.monotonic(), 0
        while n < total and not stopper.is_set():
            due = min(total, int((time.monotonic() - t0 + 0.01) * args.rate))
            while n < due:
                if n % CLOCK_EVERY == 0:
                    msg = pb.Clock()
                    set_timestamp_ns(msg.time, time.time_ns())
                else:
                    msg = pb.JointReading(machine_id="plc", travel_m=n * 0.01, slew_rad=0.1,
                                          luff_rad=0.05)
                    set_timestamp_ns(msg.time, time.time_ns())
                publisher.publish(msg)
                if n % args.stamp_every == 0:
                    stamps.append((n, time.monotonic()))
                n += 1
            stopper.wait(0.01)   # the pacing tick
        report = {"streams": [{"source": args.source, "epoch": publisher.epoch, "count": n,
                               "stamps": stamps}]}
        with open(args.report + ".tmp", "w", encoding="utf-8") as f:
            f.write(json.dumps(report))
        os.replace(args.report + ".tmp", args.report)
        stopper.wait()   # keep the cache up for the ledger until stopped
        publisher.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
