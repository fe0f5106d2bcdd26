"""The DuckDB ledger's schema and the text of its SQL statements (:mod:`ledger.duckdb_store`
runs them): the tables, the Arrow schemas batches go in by, and each query's SQL.

Kept as module constants: mutmut does not mutate module-level constants, so the upper- or
lower-cased SQL that DuckDB reads the same does not count as (equivalent) mutants.
"""

from __future__ import annotations

import pyarrow as pa

SCHEMA_VERSION = "2"

_DDL = [
    """CREATE TABLE IF NOT EXISTS ledger_meta (key VARCHAR NOT NULL, value VARCHAR NOT NULL)""",
    """CREATE TABLE IF NOT EXISTS event_log (
        global_seq BIGINT NOT NULL,
        type VARCHAR NOT NULL,
        source VARCHAR NOT NULL,
        epoch BIGINT NOT NULL,
        seq BIGINT NOT NULL,
        valid_time_ns BIGINT NOT NULL,
        recorded_time_ns BIGINT NOT NULL,
        payload BLOB USING COMPRESSION uncompressed NOT NULL,
        payload_sha256 BLOB USING COMPRESSION uncompressed NOT NULL,
        chain_sha256 BLOB USING COMPRESSION uncompressed NOT NULL,
        flags VARCHAR,
        body JSON,
        signer VARCHAR,
        signature BLOB
    )""",
    """CREATE TABLE IF NOT EXISTS gaps (
        gap_id BIGINT NOT NULL,
        source VARCHAR NOT NULL,
        epoch BIGINT NOT NULL,
        first_seq BIGINT NOT NULL,
        last_seq BIGINT NOT NULL,
        opened_recorded_ns BIGINT NOT NULL,
        closed_recorded_ns BIGINT
    )""",
    """CREATE TABLE IF NOT EXISTS quarantine (
        quarantine_id BIGINT NOT NULL,
        recorded_time_ns BIGINT NOT NULL,
        type VARCHAR NOT NULL,
        source VARCHAR NOT NULL,
        epoch BIGINT,
        seq BIGINT,
        valid_time_ns BIGINT,
        code VARCHAR NOT NULL,
        detail VARCHAR NOT NULL,
        raw BLOB NOT NULL,
        existing_global_seq BIGINT,
        after_global_seq BIGINT NOT NULL,
        chain_sha256 BLOB NOT NULL
    )""",
]

_ROW_COLUMNS = ("global_seq, type, source, epoch, seq, valid_time_ns, recorded_time_ns, "
                "payload, payload_sha256, chain_sha256, flags, signer, signature")

_EVENT_SCHEMA = pa.schema([
    ("global_seq", pa.int64()), ("type", pa.string()), ("source", pa.string()),
    ("epoch", pa.int64()), ("seq", pa.int64()), ("valid_time_ns", pa.int64()),
    ("recorded_time_ns", pa.int64()), ("payload", pa.binary()),
    ("payload_sha256", pa.binary()), ("chain_sha256", pa.binary()),
    ("flags", pa.string()), ("body", pa.string()),
    ("signer", pa.string()), ("signature", pa.binary()),
])

_FETCH_ROWS = 65_536

_BEGIN = "BEGIN TRANSACTION"
_COMMIT = "COMMIT"
_ROLLBACK = "ROLLBACK"
_SELECT_HEAD = ("SELECT global_seq, recorded_time_ns, chain_sha256 FROM event_log "
                "ORDER BY global_seq DESC LIMIT 1")
_SELECT_STREAMS = "SELECT source, epoch, max(seq) FROM event_log GROUP BY source, epoch"
_GAP_COLUMNS = ("gap_id, source, epoch, first_seq, last_seq, opened_recorded_ns, "
                "closed_recorded_ns")
_SELECT_OPEN_GAPS_BY_FIRST_SEQ = (f"SELECT {_GAP_COLUMNS} FROM gaps "
                                  "WHERE closed_recorded_ns IS NULL ORDER BY first_seq")
_SELECT_LATEST_CLOCK = "SELECT max(valid_time_ns) FROM event_log WHERE type = 'clock'"
_SELECT_KEY_ROWS = ("SELECT type, payload FROM event_log WHERE type IN "
                    "('source_key_declared', 'source_key_revoked') ORDER BY global_seq")
_SELECT_KNOWN_LOTS = ("SELECT DISTINCT body->>'lot_id' FROM event_log "
                      "WHERE type = 'lot_declared'")
_SELECT_NEXT_GAP_ID = "SELECT coalesce(max(gap_id) + 1, 0) FROM gaps"
_SELECT_NEXT_QUARANTINE_ID = "SELECT coalesce(max(quarantine_id) + 1, 0) FROM quarantine"
_WANTED_KEYS = "wanted_keys"
_KEYS_SCHEMA = pa.schema([("source", pa.string()), ("epoch", pa.int64()), ("seq", pa.int64())])
_SELECT_WANTED_KEYS = ("SELECT e.source, e.epoch, e.seq, e.global_seq, e.payload_sha256, "
                       "e.type, e.valid_time_ns "
                       f"FROM event_log e JOIN {_WANTED_KEYS} w USING (source, epoch, seq) "
                       "WHERE e.seq BETWEEN ? AND ?")
_AND_VALID_IN = " AND e.valid_time_ns BETWEEN ? AND ?"
_NEW_EVENTS = "new_events"
_INSERT_NEW_EVENTS = f"INSERT INTO event_log SELECT * FROM {_NEW_EVENTS}"
_FLAG_SEPARATOR = ","
_INSERT_QUARANTINE = "INSERT INTO quarantine VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)"
_GAP_SCHEMA = pa.schema([
    ("gap_id", pa.int64()), ("source", pa.string()), ("epoch", pa.int64()),
    ("first_seq", pa.int64()), ("last_seq", pa.int64()),
    ("opened_recorded_ns", pa.int64()), ("closed_recorded_ns", pa.int64()),
])
_GAP_CHANGES = "gap_changes"
_INSERT_GAPS = f"INSERT INTO gaps SELECT * FROM {_GAP_CHANGES}"
_CLOSE_GAPS = (f"UPDATE gaps SET closed_recorded_ns = c.closed_recorded_ns "
               f"FROM {_GAP_CHANGES} c WHERE gaps.gap_id = c.gap_id")
_WHERE_TYPE_IN = "list_contains(?, type)"
_WHERE_SOURCE_IN = "list_contains(?, source)"
_WHERE_SEQ_FROM = "global_seq >= ?"
_WHERE_SEQ_BEFORE = "global_seq < ?"
_WHERE_VALID_BY = "valid_time_ns <= ?"
_WHERE_KNOWN_BY = "recorded_time_ns <= ?"
_WHERE_AFTER = "(valid_time_ns > ? OR (valid_time_ns = ? AND global_seq > ?))"
_AND = " AND "
_SELECT_ROWS_WHERE = f"SELECT {_ROW_COLUMNS} FROM event_log WHERE "
_ORDER_BY_SEQ = " ORDER BY global_seq"
_ORDER_BY_TIME = " ORDER BY valid_time_ns, global_seq"
_SELECT_GAPS = f"SELECT {_GAP_COLUMNS} FROM gaps ORDER BY gap_id"
_SELECT_OPEN_GAPS = (f"SELECT {_GAP_COLUMNS} FROM gaps WHERE closed_recorded_ns IS NULL "
                     "ORDER BY gap_id")
_SELECT_QUARANTINE = ("SELECT quarantine_id, recorded_time_ns, type, source, epoch, seq, "
                      "valid_time_ns, code, detail, raw, existing_global_seq, after_global_seq, "
                      "chain_sha256 FROM quarantine ORDER BY quarantine_id")
_SELECT_LAST_QUARANTINE_LINK = ("SELECT after_global_seq, chain_sha256 FROM quarantine "
                                "ORDER BY quarantine_id DESC LIMIT 1")
