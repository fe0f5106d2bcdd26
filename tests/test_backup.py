"""``stockpile ledger backup`` and ``restore``: a consistent, verified copy, taken through
a running ledger service while a publisher publishes, and a damaged backup refused.

Ground truth: the ledger the service goes on writing after the backup; the backup must
be exactly its prefix up to the head the manifest names.
"""

from __future__ import annotations

import json
import random
import subprocess
from pathlib import Path

import pytest

from ledger import open_ledger
from ledger.backup import MANIFEST
from ledger.clock import ManualClock
from ledger.duckdb_store import DuckDBStore
from ledger.head_file import head_path
from ledger.holder import read_holder
from ledger.testing import joint_event
from services.ledger_client import LedgerClient
from zenoh_helpers import (PYTHON, client_args, open_router, stockpile, stop, wait_liveliness,
                           wait_until)

SITE = "backup"
RATE_HZ = 400
DURATION_S = 8


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([PYTHON, "-m", "stockpile.cli", *args], capture_output=True,
                          text=True, timeout=300)


def _one_line_error(result: subprocess.CompletedProcess) -> str:
    assert result.returncode == 2, (result.returncode, result.stdout, result.stderr)
    errors = [line for line in result.stderr.splitlines() if "error" in line]
    assert len(errors) == 1 and "Traceback" not in result.stderr, result.stderr
    return errors[0]


def _chain_at(path: Path, global_seq: int) -> bytes:
    with open_ledger(path, read_only=True) as store:
        return next(iter(store.read(global_seq, global_seq + 1))).chain_sha256


def test_backup_through_a_running_service_while_a_publisher_publishes(tmp_path):
    path = tmp_path / "yard.duckdb"
    router, endpoint = open_router()
    service = stockpile("service", "ledger", "--ledger", str(path), "--site", SITE,
                        "--status-period", "1", *client_args(endpoint),
                        stderr_path=tmp_path / "ledger.log")
    publisher = None
    report = tmp_path / "load0.json"
    try:
        wait_liveliness(router, f"stockpile/{SITE}/@live/ledger/**", 30)
        publisher = subprocess.Popen(
            [PYTHON, "-m", "services.loadgen", "--site", SITE, "--source", "load0",
             "--rate", str(RATE_HZ), "--duration", str(DURATION_S), "--linger", "300",
             "--wait-subscriber", "60", "--report", str(report), *client_args(endpoint)],
            stderr=open(tmp_path / "load0.log", "w"), stdout=subprocess.DEVNULL)
        client = LedgerClient(router, SITE, timeout_s=10)
        wait_until(lambda: client.head()["global_seq"] >= 300, 60, "300 events in the ledger")
        assert read_holder(path) is not None and publisher.poll() is None

        taken = _run("ledger", "backup", "--ledger", str(path), "--to",
                     str(tmp_path / "bk"), "--no-progress")
        assert taken.returncode == 0, taken.stderr
        assert "asking the ledger service" in taken.stderr
        manifest = json.loads((tmp_path / "bk" / MANIFEST).read_text())
        assert manifest["global_seq"] >= 300 and manifest["source"] == str(path.resolve())
        assert f"head global_seq {manifest['global_seq']} " in taken.stdout
        assert publisher.poll() is None, "the publisher stopped before the backup was taken"

        # restoring over a ledger a service holds is refused, and changes nothing
        held = _run("ledger", "restore", str(tmp_path / "bk"), "--ledger", str(path),
                    "--force")
        assert f"pid {service.pid}" in _one_line_error(held)

        wait_until(report.exists, 60, "the publisher's report")
        published = json.loads(report.read_text())["count"]
        assert published == RATE_HZ * DURATION_S
        wait_until(lambda: client.head()["global_seq"] == published - 1, 60,
                   "every published event in the ledger")
    finally:
        if publisher is not None:
            stop(publisher)
        code = stop(service)
        router.close()
    assert code == 0
    head = manifest["global_seq"]
    assert head < published - 1, "the service appended nothing after the backup"

    # the backup is the live ledger's prefix up to its head, and verifies
    backup_db = tmp_path / "bk" / "yard.duckdb"
    with DuckDBStore(backup_db, read_only=True) as copy:
        assert copy.verify().ok
        assert copy.head().global_seq == head
        assert [r.seq for r in copy.read()] == list(range(head + 1))
    assert _chain_at(path, head).hex() == manifest["chain_sha256"]
    assert json.loads(head_path(backup_db).read_text())["global_seq"] == head

    restored = tmp_path / "restored" / "yard.duckdb"
    done = _run("ledger", "restore", str(tmp_path / "bk"), "--ledger", str(restored),
                "--no-progress")
    assert done.returncode == 0, done.stderr
    verified = _run("ledger", "verify", "--ledger", str(restored))
    assert verified.returncode == 0, verified.stdout + verified.stderr
    assert f"head global_seq {head}," in verified.stdout
    assert "FAILED" not in verified.stdout

    # over the stopped ledger: refused without --force, then replaces it (its WAL too)
    refused = _run("ledger", "restore", str(tmp_path / "bk"), "--ledger", str(path))
    assert "--force" in _one_line_error(refused)
    with open_ledger(path, read_only=True) as store:
        assert store.head().global_seq == published - 1
    forced = _run("ledger", "restore", str(tmp_path / "bk"), "--ledger", str(path), "--force")
    assert forced.returncode == 0, forced.stderr
    with open_ledger(path, ManualClock(0)) as store:     # opens for writing: sidecar agrees
        assert store.head().global_seq == head
        assert store.verify().ok


def _small_ledger(path: Path, batches: int = 4) -> None:
    with open_ledger(path, ManualClock(1_000)) as store:
        for b in range(batches):
            store.append([joint_event("bk.src", b * 50 + i, b * 50 + i) for i in range(50)])


@pytest.fixture
def backup_dir(tmp_path) -> Path:
    """A backup taken directly (no service holds the ledger)."""
    _small_ledger(tmp_path / "small.duckdb")
    taken = _run("ledger", "backup", "--ledger", str(tmp_path / "small.duckdb"), "--to",
                 str(tmp_path / "bk"), "--no-progress")
    assert taken.returncode == 0, taken.stderr
    assert "asking the ledger service" not in taken.stderr
    assert "200 rows verified" in taken.stdout
    return tmp_path / "bk"


def test_a_backup_directory_is_refused_as_a_target(backup_dir, tmp_path):
    again = _run("ledger", "backup", "--ledger", str(tmp_path / "small.duckdb"), "--to",
                 str(backup_dir))
    assert "already holds a backup" in _one_line_error(again)
    missing = _run("ledger", "backup", "--ledger", str(tmp_path / "none.duckdb"), "--to",
                   str(tmp_path / "bk2"))
    assert "no ledger" in _one_line_error(missing)
    assert not (tmp_path / "none.duckdb").exists()


def test_a_damaged_backup_is_refused_and_nothing_is_installed(backup_dir, tmp_path, seed):
    rng = random.Random(seed)
    database = backup_dir / "small.duckdb"
    good = database.read_bytes()
    manifest = json.loads((backup_dir / MANIFEST).read_text())
    target = tmp_path / "restored.duckdb"

    flipped = bytearray(good)
    at = rng.randrange(len(good))
    flipped[at] ^= 1 + rng.randrange(255)
    database.write_bytes(bytes(flipped))
    line = _one_line_error(_run("ledger", "restore", str(backup_dir), "--ledger", str(target)))
    assert "sha256" in line and "damaged" in line, (at, line)

    database.write_bytes(good[:len(good) // 2])
    line = _one_line_error(_run("ledger", "restore", str(backup_dir), "--ledger", str(target)))
    assert "bytes where the manifest records" in line

    # the file changed and the manifest's sha256 and size rewritten to match: the chain
    # or the head check catches it (an older ledger passed off as this backup)
    older = tmp_path / "older.duckdb"
    _small_ledger(older, batches=2)
    database.write_bytes(older.read_bytes())
    from ledger.backup import file_sha256
    (backup_dir / MANIFEST).write_text(json.dumps(
        {**manifest, "sha256": file_sha256(database), "size_bytes": database.stat().st_size}))
    line = _one_line_error(_run("ledger", "restore", str(backup_dir), "--ledger", str(target)))
    assert f"where global_seq {manifest['global_seq']}" in line, line

    (backup_dir / MANIFEST).unlink()
    line = _one_line_error(_run("ledger", "restore", str(backup_dir), "--ledger", str(target)))
    assert "is not a backup" in line
    assert not target.exists() and not head_path(target).exists()
    assert not list(tmp_path.glob("restored*"))
