"""The PostgreSQL ledger against a real server started by the tests (tests/pg_fixtures.py):
the whole backend contract, one writer, append-only in the database, roles, snapshots,
the README's SQL, and how backend errors read."""

from __future__ import annotations

import dataclasses
import json
import os
import pwd
import socket
import stat
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import duckdb
import psycopg
import pytest

from ledger import EventClock, is_postgres_url, open_ledger, postgres_store
from ledger.clock import ManualClock
from ledger.errors import (IntegrityError, InterfaceError, LedgerDiskFull, LedgerLocked,
                           OperationalError, ProgrammingError)
from ledger.importing import import_lines
from ledger.postgres_sql import quoted
from ledger.pg_local import LocalPostgres, PostgresFailed, PostgresNotFound, find_bindir
from ledger.postgres_store import PostgresStore, install, postgres_errors
from ledger.records import RecordedEvent
from ledger.testing import LedgerStoreContract, joint_event, tampered_rows
from schemas import pb
from schemas.analytes import AnalyteOptions
from schemas.events import make_event, set_timestamp_ns
from stockpile.sample import generate_sample

#: how long a test waits for the writer thread to reach a point, seconds
WAIT_S = 30.0


def _rewrite(admin_url: str, store: PostgresStore, change) -> PostgresStore:
    """Close ``store``, run ``change(con, schema)`` as the superuser with the triggers off
    (``session_replication_role = replica``: an attacker with superuser rights), and
    open the ledger again read-only."""
    url, schema = store.url, quoted(store.schema)
    store.close()
    with psycopg.connect(admin_url) as con:
        con.execute("SET LOCAL session_replication_role = replica")
        change(con, schema)
    return PostgresStore(url, ManualClock(0), read_only=True)


def _stored_rows(con, schema: str) -> tuple[list[RecordedEvent], dict]:
    rows = con.execute(
        f"SELECT global_seq, type, source, epoch, seq, valid_time_ns, recorded_time_ns, "
        f"payload, payload_sha256, chain_sha256, flags, signer, signature, body "
        f"FROM {schema}.event_log ORDER BY global_seq").fetchall()
    records = [RecordedEvent(*r[:10], tuple(r[10].split(",")) if r[10] else (), r[11], r[12])
               for r in rows]
    bodies = {(r[2], r[3], r[4]): r[13] for r in rows}
    return records, bodies


def _insert_rows(con, schema: str, rows: list[RecordedEvent], bodies: dict) -> None:
    with con.cursor() as cur:
        cur.executemany(
            f"INSERT INTO {schema}.event_log (global_seq, type, source, epoch, seq, "
            "valid_time_ns, recorded_time_ns, payload, payload_sha256, chain_sha256, flags, "
            "signer, signature, body) VALUES (%s, %s, %s, %s, %s, %s, %s, %s, %s, %s, %s, "
            "%s, %s, %s)",
            [list(r[:10]) + [",".join(r.flags) or None, r.signer, r.signature,
                             psycopg.types.json.Jsonb(bodies.get(r.key))
                             if bodies.get(r.key) is not None else None] for r in rows])


class TestPostgresStore(LedgerStoreContract):
    persistent = True

    @pytest.fixture(autouse=True)
    def _schemas(self, pg_schemas):
        self.pg = pg_schemas

    def create_store(self, clock, directory, signing=None):
        return PostgresStore(self.pg.new_url(), clock, signing=signing)

    def reopen(self, store, clock):
        store.close()
        return PostgresStore(store.url, clock, signing=store.signing)

    def tamper(self, store, global_seq, field):
        def change(con, schema):
            rows, bodies = _stored_rows(con, schema)
            changed = tampered_rows(rows, global_seq, field)
            # the attacker drops the keys that would refuse the forged rows
            con.execute(f"ALTER TABLE {schema}.event_log DROP CONSTRAINT event_log_pkey, "
                        "DROP CONSTRAINT event_log_identity")
            start = next((i for i, (a, b) in enumerate(zip(rows, changed)) if a != b),
                         min(len(rows), len(changed)))
            con.execute(f"DELETE FROM {schema}.event_log WHERE global_seq >= %s", [start])
            _insert_rows(con, schema, changed[start:], bodies)
        return _rewrite(self.pg.admin_url, store, change)

    def replace_rows(self, store, rows):
        def change(con, schema):
            _, bodies = _stored_rows(con, schema)
            con.execute(f"DELETE FROM {schema}.event_log")
            _insert_rows(con, schema, rows, bodies)
        return _rewrite(self.pg.admin_url, store, change)

    def replace_side_tables(self, store, quarantine, gaps):
        def change(con, schema):
            con.execute(f"DELETE FROM {schema}.quarantine")
            con.execute(f"DELETE FROM {schema}.gaps")
            with con.cursor() as cur:
                if quarantine:
                    cur.executemany(f"INSERT INTO {schema}.quarantine VALUES "
                                    "(%s, %s, %s, %s, %s, %s, %s, %s, %s, %s, %s, %s, %s)",
                                    [dataclasses.astuple(q) for q in quarantine])
                if gaps:
                    cur.executemany(f"INSERT INTO {schema}.gaps VALUES "
                                    "(%s, %s, %s, %s, %s, %s, %s)",
                                    [dataclasses.astuple(g) for g in gaps])
        return _rewrite(self.pg.admin_url, store, change)


# -- one writer -------------------------------------------------------------------------------

def test_a_second_writer_is_refused_in_one_line_naming_the_holder(pg_url, pg_server):
    first = PostgresStore(pg_url, ManualClock(1_000))
    holder_pid = first._con.info.backend_pid
    with pytest.raises(LedgerLocked) as refused:
        PostgresStore(pg_url, ManualClock(1_000))
    message = str(refused.value)
    assert "\n" not in message
    assert refused.value.holder_pid == holder_pid
    assert f"pid {holder_pid}" in message and f"pid {os.getpid()}" in message
    assert socket.gethostname()[:20] in message and "127.0.0.1" in message
    assert pg_server.password not in message
    # a reader is never refused, and the ledger is free again once the writer closes
    PostgresStore(pg_url, read_only=True).close()
    first.close()
    PostgresStore(pg_url, ManualClock(1_000)).close()


def test_several_schemas_in_one_database_are_separate_ledgers(pg_schemas):
    a_url, b_url = pg_schemas.new_url("site_a"), pg_schemas.new_url("site_b")
    with PostgresStore(a_url, ManualClock(10)) as a, PostgresStore(b_url, ManualClock(10)) as b:
        a.append([joint_event("a.src", i, i) for i in range(3)])
        b.append([joint_event("b.src", 0, 5)])
    with open_ledger(a_url, read_only=True) as a, open_ledger(b_url, read_only=True) as b:
        assert [r.source for r in a.read()] == ["a.src"] * 3
        assert [r.source for r in b.read()] == ["b.src"]
        assert a.verify().ok and b.verify().ok


# -- append-only in the database ------------------------------------------------------------------

def _ledger_with_a_gap(url: str) -> None:
    with PostgresStore(url, ManualClock(100)) as store:
        store.append([joint_event("a.src", 0, 1), joint_event("a.src", 3, 2),
                      joint_event("b.src", 0, 3), joint_event("b.src", 2, 4)])
        store.append([joint_event("b.src", 1, 5)])  # closes b's gap


@pytest.mark.parametrize("statement", [
    "UPDATE {s}.event_log SET valid_time_ns = valid_time_ns + 1",
    "DELETE FROM {s}.event_log WHERE global_seq = 0",
    "TRUNCATE {s}.event_log",
    "UPDATE {s}.quarantine SET detail = 'x'",
    "DELETE FROM {s}.quarantine",
    "TRUNCATE {s}.quarantine",
    "UPDATE {s}.gaps SET last_seq = last_seq + 1",
    "UPDATE {s}.gaps SET closed_recorded_ns = NULL WHERE closed_recorded_ns IS NOT NULL",
    "UPDATE {s}.gaps SET closed_recorded_ns = 7 WHERE closed_recorded_ns IS NOT NULL",
    "UPDATE {s}.gaps SET closed_recorded_ns = 7, first_seq = 2 WHERE closed_recorded_ns IS NULL",
    "DELETE FROM {s}.gaps",
    "TRUNCATE {s}.gaps",
])
def test_the_trigger_refuses_changes_even_for_the_owner(pg_schemas, statement):
    url = pg_schemas.new_url()
    _ledger_with_a_gap(url)
    schema = quoted(url.rsplit("=", 1)[1])
    with psycopg.connect(pg_schemas.admin_url, autocommit=True) as con:
        owner = con.execute("SELECT tableowner FROM pg_tables WHERE schemaname = %s "
                            "AND tablename = 'event_log'", [schema.strip('"')]).fetchone()[0]
        assert owner == con.execute("SELECT current_user").fetchone()[0]  # the superuser owns it
        with pytest.raises(psycopg.errors.RestrictViolation, match="append-only|only close"):
            con.execute(statement.replace("{s}", schema))
        # closing an open gap, and nothing else, is allowed
        with con.transaction(force_rollback=True):
            closed = con.execute(f"UPDATE {schema}.gaps SET closed_recorded_ns = 9 "
                                 "WHERE closed_recorded_ns IS NULL")
            assert closed.rowcount == 1


def test_the_unique_constraint_refuses_a_direct_duplicate(pg_url):
    with PostgresStore(pg_url, ManualClock(100)) as store:
        store.append([joint_event("a.src", 0, 1)])
    schema = quoted(pg_url.rsplit("=", 1)[1])
    with psycopg.connect(pg_url.split("?")[0], autocommit=True) as con:
        with pytest.raises(psycopg.errors.UniqueViolation, match="event_log_identity"):
            con.execute(f"INSERT INTO {schema}.event_log SELECT global_seq + 1, type, source, "
                        f"epoch, seq, valid_time_ns, recorded_time_ns, payload, payload_sha256, "
                        f"chain_sha256, flags, body, signer, signature FROM {schema}.event_log")
        with pytest.raises(IntegrityError, match="event_log_pkey"), postgres_errors():
            con.execute(f"INSERT INTO {schema}.event_log SELECT global_seq, type, source, "
                        f"epoch + 1, seq, valid_time_ns, recorded_time_ns, payload, "
                        f"payload_sha256, chain_sha256, flags, body, signer, signature "
                        f"FROM {schema}.event_log")


# -- roles ----------------------------------------------------------------------------------------

@pytest.fixture
def login_roles(pg_schemas):
    """``make(name, group)``: a login role in ``group`` with a password; dropped after."""
    made = []

    def make(name: str, group: str) -> str:
        password = f"pw-{name}"
        with psycopg.connect(pg_schemas.admin_url, autocommit=True) as con:
            con.execute(f"CREATE ROLE {quoted(name)} LOGIN PASSWORD '{password}' IN ROLE {group}")
        made.append(name)
        return password

    yield make
    pg_schemas.drop_all()
    with psycopg.connect(pg_schemas.admin_url, autocommit=True) as con:
        for name in made:
            con.execute(f"DROP ROLE IF EXISTS {quoted(name)}")


def test_the_roles_read_and_append_but_never_change_the_log(pg_schemas, login_roles):
    schema = pg_schemas.new_schema()
    with PostgresStore(pg_schemas.url_of(schema), ManualClock(100)) as store:  # installs
        store.append([joint_event("a.src", 0, 1)])
    tag = schema.replace("_", "")
    writer_pw = login_roles(f"w{tag}", "stockpile_writer")
    reader_pw = login_roles(f"r{tag}", "stockpile_reader")
    writer_url = pg_schemas.url_of(schema, f"w{tag}", writer_pw)
    reader_url = pg_schemas.url_of(schema, f"r{tag}", reader_pw)
    # the writer role appends (binary COPY, gaps, quarantine) and re-creates assays
    with PostgresStore(writer_url, ManualClock(200),
                       analytes=AnalyteOptions(("Fe", "Zn"))) as store:
        assert store.append([joint_event("a.src", 3, 2)]).appended == 1  # opens gap 1-2
        result = store.append([joint_event("a.src", 1, 3),  # closes it (an UPDATE), opens 2-2
                               joint_event("a.src", 0, 1, travel_m=5.0)])
        assert [o.status for o in result.outcomes] == ["appended", "conflict"]
    with PostgresStore(reader_url, read_only=True) as reader:
        assert [r.seq for r in reader.read()] == [0, 3, 1] and reader.verify().ok
        assert len(reader.quarantine()) == 1
        assert [(g.first_seq, g.last_seq, g.is_open) for g in reader.gaps()] == [
            (1, 2, False), (2, 2, True)]
    s = quoted(schema)
    with psycopg.connect(writer_url.split("?")[0], autocommit=True) as con:
        for statement in (f"UPDATE {s}.event_log SET seq = 9", f"DELETE FROM {s}.event_log",
                          f"TRUNCATE {s}.event_log", f"DELETE FROM {s}.quarantine",
                          f"UPDATE {s}.gaps SET last_seq = 9", f"DELETE FROM {s}.gaps"):
            with pytest.raises(psycopg.errors.InsufficientPrivilege):
                con.execute(statement)
    with psycopg.connect(reader_url.split("?")[0], autocommit=True) as con:
        columns = [c.name for c in con.execute(f"SELECT * FROM {s}.assays").description]
        assert "Zn" in columns and columns[-1] == "unrecognised_analytes"
        assert con.execute(f"SELECT count(*) FROM {s}.events").fetchone()[0] == 3
        for statement in (f"INSERT INTO {s}.event_log SELECT * FROM {s}.event_log",
                          f"INSERT INTO {s}.gaps SELECT * FROM {s}.gaps",
                          f"UPDATE {s}.ledger_meta SET value = 'x'"):
            with pytest.raises(psycopg.errors.InsufficientPrivilege):
                con.execute(statement)


def test_a_user_who_may_not_install_is_told_how(pg_schemas, login_roles):
    install(pg_schemas.admin_url, pg_schemas.new_schema())  # the roles exist from then on
    role = pg_schemas.new_schema("u").replace("_", "")
    password = login_roles(role, "stockpile_reader")
    url = pg_schemas.url_of(pg_schemas.new_schema(), role, password)
    with pytest.raises(OperationalError) as refused:
        PostgresStore(url, ManualClock(1))
    message = str(refused.value)
    assert "install(" in message and "\n" not in message and password not in message
    with pytest.raises(OperationalError, match="no ledger schema"):
        PostgresStore(url, read_only=True)
    # what the message says to do: an administrator installs it (twice: idempotent)
    schema = pg_schemas.names[-1]
    install(pg_schemas.admin_url, schema)
    install(pg_schemas.url_of(schema))
    with PostgresStore(url, read_only=True) as reader:
        assert reader.head().global_seq == -1 and reader.verify().ok
    with pytest.raises(ProgrammingError, match="permission denied"):  # a reader never writes
        PostgresStore(url, ManualClock(1))


# -- readers: one snapshot, never half a batch, never blocking the writer ---------------------------

def test_a_reader_sees_one_committed_prefix_while_the_writer_appends(pg_url):
    batch = 40
    writer = PostgresStore(pg_url, ManualClock(1_000))
    progress = {"batches": 0}
    changed = threading.Condition()
    stop = threading.Event()
    errors: list[BaseException] = []

    def write() -> None:
        n = 0
        try:
            while not stop.is_set() and n < 1_000:
                writer.append([joint_event("w.src", n * batch + i, n * batch + i)
                               for i in range(batch)])
                n += 1
                with changed:
                    progress["batches"] = n
                    changed.notify_all()
        except BaseException as exc:  # pragma: no cover - reported below
            errors.append(exc)
            with changed:
                changed.notify_all()

    def wait_for(batches: int) -> None:
        with changed:
            assert changed.wait_for(lambda: progress["batches"] >= batches or errors, WAIT_S)
        assert errors == []

    thread = threading.Thread(target=write)
    thread.start()
    try:
        wait_for(3)
        reader = PostgresStore(pg_url, read_only=True)
        head = reader.head()
        n_rows = head.global_seq + 1
        # the writer commits more batches while the reader's snapshot stays open
        wait_for(n_rows // batch + 3)
        rows = list(reader.read())
        assert n_rows % batch == 0 and len(rows) == n_rows
        assert [r.global_seq for r in rows] == list(range(n_rows))
        assert rows[-1].chain_sha256 == head.chain_sha256
        assert len(list(reader.as_of(10**18, 10**18))) == n_rows
        assert reader.stats().events == n_rows and reader.verify().ok
        assert [s.max_seq for s in reader.streams()] == [n_rows - 1]
        reader.close()
    finally:
        stop.set()
        thread.join(WAIT_S)
    assert errors == [] and writer.head().global_seq + 1 > n_rows
    assert writer.verify().ok
    writer.close()


# -- the README's SQL ---------------------------------------------------------------------------

def _readme_statements() -> list[str]:
    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    blocks = [b.split("```")[0] for b in readme.split("```sql")[1:]]
    return [s.strip() for block in blocks for s in block.split(";") if s.strip()]


def _comparable(rows) -> list:
    """Rows as comparable values: floats to 9 significant digits, lists sorted, rows
    sorted (the statements' own ORDER BY is checked by DuckDB's tests)."""
    def value(v):
        if isinstance(v, float):
            return float(f"{v:.9g}")
        if isinstance(v, list):
            return sorted(value(x) for x in v)
        return v
    return sorted((tuple(value(v) for v in row) for row in rows), key=repr)


def test_the_readme_sql_gives_duckdbs_answers(tmp_path, pg_url):
    lines = generate_sample(seed=5).lines
    with open_ledger(tmp_path / "l.duckdb", EventClock()) as store:
        import_lines(store, lines)
    with open_ledger(pg_url, EventClock()) as store:
        import_lines(store, lines)
    statements = _readme_statements()
    assert len(statements) >= 10
    duck = duckdb.connect(str(tmp_path / "l.duckdb"), read_only=True)
    with psycopg.connect(pg_url.split("?")[0], autocommit=True) as con:
        con.execute(f"SET search_path TO {quoted(pg_url.rsplit('=', 1)[1])}")
        for statement in statements:
            want = _comparable(duck.execute(statement).fetchall())
            got = _comparable(con.execute(statement).fetchall())
            assert want and got == want, statement
    duck.close()


def _spelled_assays() -> list:
    """Assays naming analytes in other spellings (``FE``, `` sio2``) and unknown ones."""
    events = []
    for seq, analytes in enumerate([{"FE": 61.5, " sio2": 4.25, "Zn": 0.1},
                                    {"fe": 58.0, "cu": 0.2, "ZN": 0.3, "SiO2": 6.0},
                                    {"Fe": 60.0, "SiO2": 5.0}]):
        message = pb.Assay(assay_id=f"A{seq}", lot_id="L1", lab_id="lab1",
                           analytes=analytes, status=pb.FINAL)
        set_timestamp_ns(message.window_start, 1_000 * seq)
        set_timestamp_ns(message.window_end, 1_000 * seq + 500)
        events.append(make_event(message, source="lab1", epoch=1, seq=seq))
    return events


def test_the_assays_view_reads_spellings_and_lists_unknown_names_as_duckdb(tmp_path, pg_url):
    events = _spelled_assays()
    query = ('SELECT assay_id, "Fe", "SiO2", unrecognised_analytes FROM assays '
             "ORDER BY global_seq")
    with open_ledger(tmp_path / "l.duckdb", ManualClock(10**6)) as store:
        outcomes = [o.status for o in store.append(events).outcomes]
    duck = duckdb.connect(str(tmp_path / "l.duckdb"), read_only=True)
    want = [(a, fe, si, sorted(json.loads(u))) for a, fe, si, u in duck.execute(query).fetchall()]
    duck.close()
    with open_ledger(pg_url, ManualClock(10**6)) as store:
        assert [o.status for o in store.append(events).outcomes] == outcomes
    with psycopg.connect(pg_url.split("?")[0], autocommit=True) as con:
        con.execute(f"SET search_path TO {quoted(pg_url.rsplit('=', 1)[1])}")
        got = [(a, fe, si, sorted(u)) for a, fe, si, u in con.execute(query).fetchall()]
    assert outcomes == ["appended"] * 3 and got == want and len(want) == 3
    assert any(row[3] for row in want) and any(row[1] is not None for row in want)


def test_a_writer_growing_the_analytes_while_a_reader_holds_assays_says_why(pg_url,
                                                                             monkeypatch):
    PostgresStore(pg_url, ManualClock(1)).close()
    monkeypatch.setattr(postgres_store, "VIEW_LOCK_TIMEOUT_MS", 100)
    schema = quoted(pg_url.rsplit("=", 1)[1])
    with psycopg.connect(pg_url.split("?")[0]) as reader:  # a transaction left open
        reader.execute(f"SELECT count(*) FROM {schema}.assays").fetchone()
        with pytest.raises(OperationalError, match="in use by a reader") as refused:
            PostgresStore(pg_url, ManualClock(2), analytes=AnalyteOptions(("Fe", "Zn")))
        assert "\n" not in str(refused.value)
    with PostgresStore(pg_url, ManualClock(3), analytes=AnalyteOptions(("Fe", "Zn"))):
        pass  # once the reader is done
    with psycopg.connect(pg_url.split("?")[0]) as con:
        columns = [c.name for c in con.execute(f"SELECT * FROM {schema}.assays").description]
    assert "Zn" in columns


# -- errors -------------------------------------------------------------------------------------

def test_a_lost_connection_is_a_one_line_operational_error(pg_url):
    store = PostgresStore(pg_url, ManualClock(100))
    store.append([joint_event("a.src", 0, 1)])
    with psycopg.connect(pg_url.split("?")[0], autocommit=True) as admin:
        assert admin.execute("SELECT pg_terminate_backend(%s)",
                             [store._con.info.backend_pid]).fetchone()[0]
    with pytest.raises(OperationalError) as lost:
        store.append([joint_event("a.src", 1, 2)])
    assert "connection to the PostgreSQL ledger was lost" in str(lost.value)
    assert "\n" not in str(lost.value)
    store.close()
    with PostgresStore(pg_url, read_only=True) as reader:  # nothing of the batch was kept
        assert reader.head().global_seq == 0


def test_a_server_disk_full_error_is_ledger_disk_full_with_the_servers_message(pg_url):
    with psycopg.connect(pg_url.split("?")[0], autocommit=True) as con:
        with pytest.raises(LedgerDiskFull) as full, postgres_errors():
            con.execute("DO $$ BEGIN RAISE EXCEPTION 'could not extend file \"base/1/2\": "
                        "No space left on device' USING ERRCODE = 'disk_full'; END $$")
    assert "No space left on device" in str(full.value) and "\n" not in str(full.value)
    assert full.value.os_error == "No space left on device"


def test_open_ledger_takes_postgres_urls_and_refuses_duckdb_only_options(pg_url, pg_server):
    assert is_postgres_url(pg_url) and is_postgres_url("postgres://h/db")
    assert not is_postgres_url("ledger.duckdb") and not is_postgres_url(Path("x"))
    other = pg_url.replace("postgresql://", "postgres://", 1)
    with open_ledger(other, ManualClock(5), memory_limit_mb=64) as store:
        assert store.backend == "postgresql" and store.append([joint_event("a", 0, 1)]).appended
        assert pg_server.password not in repr(store) and pg_server.password not in store.name
    with pytest.raises(InterfaceError, match="accept_loss"):
        open_ledger(pg_url, accept_loss=True)
    with pytest.raises(InterfaceError, match="not a plain SQL identifier"):
        open_ledger(pg_url.split("?")[0] + "?schema=Robert'); DROP")


# -- the local server -------------------------------------------------------------------------------

def test_the_local_server_keeps_its_password_private_and_runs_unprivileged(pg_server):
    assert stat.S_IMODE(os.stat(pg_server.password_file).st_mode) == 0o600
    assert pg_server.password not in pg_server.log.read_text(errors="replace")
    expected_uid = pwd.getpwnam("nobody").pw_uid if os.geteuid() == 0 else os.geteuid()
    assert os.stat(f"/proc/{pg_server._process.pid}").st_uid == expected_uid
    assert os.stat(pg_server.data).st_uid == expected_uid
    with psycopg.connect(pg_server.url(), autocommit=True) as con:
        assert con.execute("SHOW listen_addresses").fetchone()[0] == "127.0.0.1"
        assert con.execute("SHOW wal_level").fetchone()[0] == "replica"
    with pytest.raises(psycopg.OperationalError, match="password authentication failed"):
        psycopg.connect(pg_server.url(password="wrong"))


def _wait_until(predicate, timeout_s: float = WAIT_S, poll_s: float = 0.02) -> bool:
    """Poll ``predicate`` until it holds (True) or ``timeout_s`` passes (False)."""
    end = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > end:
            return False
        time.sleep(poll_s)
    return True


def test_a_standby_made_from_the_server_replays_what_the_primary_commits(pg_url, pg_server):
    standby = pg_server.make_standby()
    try:
        with PostgresStore(pg_url, ManualClock(100)) as store:
            store.append([joint_event("a.src", i, i) for i in range(5)])
        with psycopg.connect(pg_server.url(), autocommit=True) as primary:
            lsn = primary.execute("SELECT pg_current_wal_insert_lsn()").fetchone()[0]
        with psycopg.connect(standby.url(), autocommit=True) as con:
            assert con.execute("SELECT pg_is_in_recovery()").fetchone()[0]
            assert _wait_until(lambda: con.execute(
                "SELECT pg_last_wal_replay_lsn() >= %s::pg_lsn", [lsn]).fetchone()[0])
        standby_url = pg_url.replace(f":{pg_server.port}/", f":{standby.port}/")
        with PostgresStore(standby_url, read_only=True) as replica:
            assert [r.seq for r in replica.read()] == list(range(5)) and replica.verify().ok
    finally:
        standby.stop()


def test_without_psycopg_a_postgres_url_is_a_one_line_error_naming_the_extra():
    code = textwrap.dedent("""
        import sys

        class NotInstalled:
            def find_spec(self, name, path=None, target=None):
                if name.split(".")[0] == "psycopg":
                    raise ModuleNotFoundError(f"No module named {name!r}", name=name)

        sys.meta_path.insert(0, NotInstalled())
        from ledger import open_ledger
        try:
            open_ledger("postgresql://u@127.0.0.1:1/db")
        except Exception as exc:
            print(type(exc).__name__, exc)
    """)
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120)
    assert run.returncode == 0, run.stderr
    assert run.stdout.startswith("InterfaceError a PostgreSQL ledger needs psycopg")
    assert "stockpile-ledger[ledger]" in run.stdout and run.stdout.count("\n") == 1


def test_binaries_that_are_missing_or_private_are_a_clear_error(tmp_path, monkeypatch):
    monkeypatch.setenv("STOCKPILE_PG_BINDIR", str(tmp_path))
    with pytest.raises(PostgresNotFound, match="holds no PostgreSQL server binaries"):
        find_bindir()
    monkeypatch.delenv("STOCKPILE_PG_BINDIR")
    try:
        real = find_bindir()
    except PostgresNotFound:
        pytest.skip("no PostgreSQL server binaries on this machine")
    if os.geteuid() != 0:
        pytest.skip("only root runs the server as another user")
    private = tmp_path / "private"  # pytest's temporary folders are private (0700)
    private.mkdir()
    for name in ("initdb", "postgres", "pg_isready"):
        (private / name).symlink_to(real / name)
    with pytest.raises(PostgresNotFound, match="not executable by user nobody|do not run"):
        LocalPostgres(bindir=private)
    with pytest.raises(PostgresFailed, match="cannot be entered by user nobody"):
        LocalPostgres(tmp_path / "data", bindir=real)
