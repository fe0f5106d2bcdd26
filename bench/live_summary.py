"""What a live projector's summaries cost: a live yard's ledger replayed through its fold.

The projector service (and the dashboard) fold a pile live (``LiveProjection``): events
older than the reorder window are folded for good, and every summary folds the waiting
tail (about two site minutes of events) again on a copy.  This bench replays the live part
of a ledger written by ``bench/live.py`` (``--keep``: the run's ``ledger.duckdb``) in
global order, as the service receives it, and asks for a summary every P site seconds,
for several P, each from the same caught-up state.  It prints CPU seconds per site second
of the fold and of the summaries, and the same with the scan pass taken on every scan
(``--every-scan-pass``: the fold before the settled-scans check), for comparison.

    .venv/bin/python bench/live_summary.py /work/live/run-.../ledger.duckdb --pile A
"""

from __future__ import annotations

import argparse
import copy
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from ledger import open_ledger  # noqa: E402
from projector import fold as F  # noqa: E402
from schemas.times import NS_PER_S  # noqa: E402
from services.projector_service import LiveProjection  # noqa: E402
from services.service import LIVE_REORDER_S  # noqa: E402


def replay(base: LiveProjection, records, period_s: float, every_scan_pass: bool) -> dict:
    """Add ``records`` to a copy of ``base``, a summary every ``period_s`` site seconds."""
    projection = copy.deepcopy(base)
    saved = F.note_pending, F.note_pose
    if every_scan_pass:      # unsettled at every scan and pose: a pass over every waiting scan
        F.note_pending = lambda state, scan: (state.pending.append(scan),
                                              setattr(state, "pending_settled", False))
        F.note_pose = lambda state, frame, t_ns, new: setattr(state, "pending_settled", False)
    try:
        fold_s = summary_s = 0.0
        summaries = 0
        next_ns = records[0].recorded_time_ns + int(period_s * NS_PER_S)
        for record in records:
            t0 = time.process_time()
            projection.add(record)
            projection.advance()
            fold_s += time.process_time() - t0
            if record.recorded_time_ns >= next_ns:
                t0 = time.process_time()
                projection.summary()
                summary_s += time.process_time() - t0
                summaries += 1
                next_ns += int(period_s * NS_PER_S)
    finally:
        F.note_pending, F.note_pose = saved
    site_s = (records[-1].recorded_time_ns - records[0].recorded_time_ns) / NS_PER_S
    return {"fold": fold_s / site_s, "summary": summary_s / site_s, "n": summaries,
            "per_summary_s": summary_s / max(summaries, 1), "site_s": site_s}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("ledger", help="a live run's ledger.duckdb (bench/live.py --keep)")
    p.add_argument("--pile", default="A")
    p.add_argument("--live-from", type=int, required=True, metavar="SEQ",
                   help="the first live record's global seq (bench/live.py prints the "
                   "history's size: that number)")
    p.add_argument("--periods-s", type=float, nargs="+", default=[30.0])
    args = p.parse_args(argv)
    base = LiveProjection(args.pile, int(LIVE_REORDER_S * NS_PER_S))
    with open_ledger(args.ledger, read_only=True) as store:
        t0 = time.process_time()
        for record in store.read(0, args.live_from):
            base.add(record)
        base.advance()
        history_s = time.process_time() - t0
        live = list(store.read(args.live_from))
    print(f"{args.ledger}: {args.live_from:,} history records (caught up in {history_s:.0f} "
          f"CPU s), {len(live):,} live; pile {args.pile}; CPUs {os.cpu_count()}, load "
          f"{os.getloadavg()[0]:.2f}", flush=True)
    print(f"\n{'scan pass':<16} {'period s':>8} {'summaries':>9} {'fold':>7} {'summary':>8} "
          f"{'total':>7} {'s/summary':>9}   (CPU s per site s)")
    for every_scan_pass in (False, True):
        for period in args.periods_s:
            r = replay(base, live, period, every_scan_pass)
            label = "on every scan" if every_scan_pass else "when settled"
            print(f"{label:<16} {period:>8g} {r['n']:>9} {r['fold']:>7.3f} {r['summary']:>8.3f} "
                  f"{r['fold'] + r['summary']:>7.3f} {r['per_summary_s']:>9.3f}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
