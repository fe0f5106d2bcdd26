"""Both ledger backends pass the same contract (ledger.testing.LedgerStoreContract)."""

from __future__ import annotations

import duckdb

from ledger.clock import ManualClock
from ledger.duckdb_store import DuckDBStore
from ledger.memory import MemoryStore
from ledger.testing import LedgerStoreContract


class TestMemoryStore(LedgerStoreContract):
    persistent = False

    def create_store(self, clock, directory):
        return MemoryStore(clock)

    def tamper(self, store, global_seq, field):
        row = store._rows[global_seq]
        if field == "payload":
            changed = row._replace(payload=row.payload + b"\x00")
        else:
            changed = row._replace(recorded_time_ns=row.recorded_time_ns + 1)
        store._rows[global_seq] = changed
        return store


class TestDuckDBStore(LedgerStoreContract):
    persistent = True

    def create_store(self, clock, directory):
        return DuckDBStore(directory / "ledger.duckdb", clock)

    def reopen(self, store, clock):
        store.close()
        return DuckDBStore(store.path, clock)

    def tamper(self, store, global_seq, field):
        path = store.path
        store.close()
        con = duckdb.connect(str(path))
        if field == "payload":
            con.execute("UPDATE event_log SET payload = payload || '\\x00'::BLOB "
                        "WHERE global_seq = ?", [global_seq])
        else:
            con.execute("UPDATE event_log SET recorded_time_ns = recorded_time_ns + 1 "
                        "WHERE global_seq = ?", [global_seq])
        con.close()
        return DuckDBStore(path, ManualClock(0), read_only=True)
