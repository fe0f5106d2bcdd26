"""A writer killed with SIGKILL loses no acknowledged batch and leaves no partial one."""

from __future__ import annotations

import random
import sys
import textwrap

from ledger.clock import ManualClock
from ledger.duckdb_store import DuckDBStore
from kill_helpers import run_until_killed

BATCH = 2_000

# The child appends batch after batch of BATCH joint readings; batch b holds seqs
# b*BATCH .. b*BATCH+BATCH-1 of source "kill.src"; after each commit it prints "ack b".
CHILD = textwrap.dedent(f"""
    import sys
    from ledger.clock import ManualClock
    from ledger.duckdb_store import DuckDBStore
    from ledger.testing import joint_event

    path, first = sys.argv[1], int(sys.argv[2])
    store = DuckDBStore(path, ManualClock(1_000))
    b = first
    while True:
        store.append([joint_event("kill.src", b * {BATCH} + i, b * {BATCH} + i, travel_m=b)
                      for i in range({BATCH})])
        print(f"ack {{b}}", flush=True)
        b += 1
""")


def _run_until_killed(path, first_batch: int, acks_before_kill: int) -> list[int]:
    """Start the child, SIGKILL it after ``acks_before_kill`` acks; return every ack it wrote."""
    return run_until_killed([sys.executable, "-c", CHILD, str(path), str(first_batch)],
                            acks_before_kill)


def test_sigkill_keeps_exactly_the_acknowledged_batches(tmp_path, seed):
    """The acks before each kill are drawn from the run's seed (``--seed``); where the kill
    lands inside a batch is the machine's timing."""
    rng = random.Random(seed)
    path = tmp_path / "ledger.duckdb"
    acked: list[int] = []
    next_batch = 0
    for round_ in range(3):
        acked += _run_until_killed(path, next_batch, rng.randrange(2, 8))
        store = DuckDBStore(path, ManualClock(0))
        rows = list(store.read())
        seqs = [r.seq for r in rows]
        present = sorted({s // BATCH for s in seqs})
        # no partial batch: every present batch is complete, and nothing else is there
        assert len(seqs) == len(present) * BATCH, (seed, round_)
        assert seqs == list(range(len(seqs))), (seed, round_)
        # every acknowledged batch survived; at most the one in flight when the kill landed
        # (committed, ack not yet written) is there beyond them
        assert set(acked) <= set(present), (seed, round_)
        assert len(present) - len(acked) in (0, 1), (seed, round_, acked, present)
        assert [r.global_seq for r in rows] == list(range(len(rows)))
        report = store.verify()
        assert report.ok, (seed, report)
        assert store.gaps() == []
        next_batch = len(present)
        acked = present
        store.close()
