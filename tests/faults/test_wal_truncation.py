"""The ledger is SIGKILLed while its WAL is being written, and its leftover WAL is then
truncated: every case is detected (the open refuses, naming both heads) or loses
nothing; none is silent.

A real writer process appends batches and prints an ack after each; it is SIGKILLed
right after its n-th ack, while it writes the next batch into the WAL.  Its leftover
``.wal`` is then cut at seeded points, each case in a copy of the ledger (database file,
head sidecar, the cut WAL), and the copy is opened for writing.
"""

from __future__ import annotations

import json
import os
import random
import shutil
import sys
import textwrap
from pathlib import Path

import pytest

from ledger import errors, open_ledger
from ledger.clock import ManualClock
from kill_helpers import run_until_killed

BATCH = 100
CASES = 24

# batch b holds seqs b*BATCH .. b*BATCH+BATCH-1 of source "wal.src"; "ack b" after each commit
CHILD = textwrap.dedent(f"""
    import sys
    from ledger import open_ledger
    from ledger.clock import ManualClock
    from ledger.testing import joint_event

    store = open_ledger(sys.argv[1], ManualClock(1_000))
    b = 0
    while True:
        store.append([joint_event("wal.src", b * {BATCH} + i, b * {BATCH} + i)
                      for i in range({BATCH})])
        print(f"ack {{b}}", flush=True)
        b += 1
""")


def _write_until_killed(path: Path, acks_before_kill: int) -> list[int]:
    """Run the writer, SIGKILL it right after ``acks_before_kill`` acks; every ack it wrote."""
    return run_until_killed([sys.executable, "-c", CHILD, str(path)], acks_before_kill)


def _case(source: Path, wal: bytes, cut: int, directory: Path) -> Path:
    """A copy of the killed ledger with its WAL cut to ``cut`` bytes."""
    directory.mkdir()
    for name in os.listdir(source):
        if not name.endswith(".wal"):
            shutil.copy(source / name, directory / name)
    path = directory / "ledger.duckdb"
    Path(str(path) + ".wal").write_bytes(wal[:cut])
    return path


def test_truncated_wal_is_detected_or_loses_nothing(tmp_path, seed):
    rng = random.Random(seed)
    killed = tmp_path / "killed"
    killed.mkdir()
    acked = _write_until_killed(killed / "ledger.duckdb", rng.randrange(4, 9))
    wal = (killed / "ledger.duckdb.wal").read_bytes()
    assert wal, "the killed writer left no WAL: nothing to truncate"
    acked_seqs = set(range((max(acked) + 1) * BATCH))
    last_acked_seq = (max(acked) + 1) * BATCH - 1
    sidecar = Path(str(killed / "ledger.duckdb") + ".head")
    # the head the writer recorded: its last acked batch's, or the one in flight after it
    sidecar_seq = json.loads(sidecar.read_text())["global_seq"] if sidecar.exists() else None
    cuts = [0, len(wal)] + [rng.randrange(len(wal)) for _ in range(CASES - 2)]
    detected = intact = 0
    silent: list[tuple[int, int]] = []
    for i, cut in enumerate(cuts):
        path = _case(killed, wal, cut, tmp_path / f"case{i}")
        try:
            store = open_ledger(path, ManualClock(0))
        except errors.HeadWentBackwards as exc:
            message = str(exc)
            assert "\n" not in message
            assert sidecar_seq in (last_acked_seq, last_acked_seq + BATCH), sidecar_seq
            assert f"records global_seq {sidecar_seq} " in message, message
            assert "the database holds global_seq " in message, message
            assert "--accept-loss" in message and "restore" in message, message
            detected += 1
            continue
        with store:
            seqs = {row.seq for row in store.read()}
            if acked_seqs <= seqs and store.verify().ok:
                intact += 1
            else:
                silent.append((cut, len(acked_seqs - seqs)))
    print(f"wal truncation: {len(cuts)} cases, {detected} detected, {intact} intact, "
          f"{len(silent)} silent (WAL {len(wal):,} bytes, {len(acked)} batches acked, "
          f"seed {seed})")
    assert not silent, f"committed events lost silently (cut, events lost): {silent}"
    assert detected + intact == len(cuts) >= 18
    # the whole WAL loses nothing, and cutting it all off loses every acked batch: detected
    assert detected >= 1 and intact >= 1


def test_accept_loss_opens_it_and_rewrites_the_sidecar(tmp_path):
    killed = tmp_path / "killed"
    killed.mkdir()
    acked = _write_until_killed(killed / "ledger.duckdb", 3)
    wal = (killed / "ledger.duckdb.wal").read_bytes()
    path = _case(killed, wal, 0, tmp_path / "case")
    with pytest.raises(errors.HeadWentBackwards):
        open_ledger(path, ManualClock(0)).close()
    with open_ledger(path, ManualClock(0), accept_loss=True) as store:
        head = store.head().global_seq
    assert head < max(acked) * BATCH
    assert json.loads(Path(str(path) + ".head").read_text())["global_seq"] == head
    with open_ledger(path, ManualClock(0)) as store:   # accepted: opens as it is now
        assert store.head().global_seq == head
