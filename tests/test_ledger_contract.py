"""Both ledger backends pass the same contract (ledger.testing.LedgerStoreContract)."""

from __future__ import annotations

import dataclasses

import duckdb

from ledger.clock import ManualClock
from ledger.duckdb_store import DuckDBStore
from ledger.memory import MemoryStore
from ledger.records import RecordedEvent
from ledger.testing import LedgerStoreContract, tampered_rows


class TestMemoryStore(LedgerStoreContract):
    persistent = False

    def create_store(self, clock, directory, signing=None):
        return MemoryStore(clock, signing=signing)

    def tamper(self, store, global_seq, field):
        # the rows as the store keeps them, changed in place (its index and writer state
        # are left as they were: only verify looks)
        store._rows[:] = tampered_rows(store._rows, global_seq, field)
        store._recorded[:] = [r.recorded_time_ns for r in store._rows]
        return store

    def replace_rows(self, store, rows):
        store._rows[:] = rows
        store._recorded[:] = [r.recorded_time_ns for r in rows]
        return store

    def replace_side_tables(self, store, quarantine, gaps):
        store._quarantine[:] = quarantine
        store._gaps = {g.gap_id: g for g in gaps}
        return store


class TestDuckDBStore(LedgerStoreContract):
    persistent = True

    def create_store(self, clock, directory, signing=None):
        return DuckDBStore(directory / "ledger.duckdb", clock, signing=signing)

    def reopen(self, store, clock):
        store.close()
        return DuckDBStore(store.path, clock, signing=store.signing)

    def tamper(self, store, global_seq, field):
        # event_log rewritten with SQL in another connection, the file reopened read-only
        path = store.path
        store.close()
        con = duckdb.connect(str(path))
        columns = "global_seq, type, source, epoch, seq, valid_time_ns, recorded_time_ns, " \
                  "payload, payload_sha256, chain_sha256, flags"
        rows = [RecordedEvent(*r[:7], bytes(r[7]), bytes(r[8]), bytes(r[9]),
                              tuple(r[10].split(",")) if r[10] else ())
                for r in con.execute(f"SELECT {columns} FROM event_log ORDER BY global_seq"
                                     ).fetchall()]
        changed = tampered_rows(rows, global_seq, field)
        con.execute("BEGIN TRANSACTION")
        # the rows from the first changed one on are deleted and written again
        start = next((i for i, (a, b) in enumerate(zip(rows, changed)) if a != b),
                     min(len(rows), len(changed)))
        con.execute("DELETE FROM event_log WHERE global_seq >= ?", [start])
        con.executemany(f"INSERT INTO event_log ({columns}) VALUES "
                        "(?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                        [list(r[:10]) + [",".join(r.flags) or None] for r in changed[start:]])
        con.execute("COMMIT")
        con.close()
        return DuckDBStore(path, ManualClock(0), read_only=True)

    def replace_side_tables(self, store, quarantine, gaps):
        path = store.path
        store.close()
        con = duckdb.connect(str(path))
        con.execute("BEGIN TRANSACTION")
        con.execute("DELETE FROM quarantine")
        con.execute("DELETE FROM gaps")
        if quarantine:
            con.executemany("INSERT INTO quarantine VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                            [list(dataclasses.astuple(q)) for q in quarantine])
        if gaps:
            con.executemany("INSERT INTO gaps VALUES (?, ?, ?, ?, ?, ?, ?)",
                            [list(dataclasses.astuple(g)) for g in gaps])
        con.execute("COMMIT")
        con.close()
        return DuckDBStore(path, ManualClock(0), read_only=True)

    def replace_rows(self, store, rows):
        path = store.path
        store.close()
        con = duckdb.connect(str(path))
        con.execute("BEGIN TRANSACTION")
        con.execute("DELETE FROM event_log")
        con.executemany(
            "INSERT INTO event_log (global_seq, type, source, epoch, seq, valid_time_ns, "
            "recorded_time_ns, payload, payload_sha256, chain_sha256, flags, signer, signature) "
            "VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
            [list(r[:10]) + [",".join(r.flags) or None, r.signer, r.signature] for r in rows])
        con.execute("COMMIT")
        con.close()
        return DuckDBStore(path, ManualClock(0), read_only=True)
