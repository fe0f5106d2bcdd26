"""The PostgreSQL ledger's schema: tables, indexes, the append-only triggers, roles and
grants, and the auditors' views in PostgreSQL's dialect; :func:`install_on` puts them in.
Also the ledger URL's own ``schema`` parameter (:func:`split_url`, :func:`describe_url`).

One ledger is one PostgreSQL schema (default ``stockpile``) holding the tables of the
DuckDB ledger (``event_log``, ``gaps``, ``quarantine``, ``ledger_meta``) and the same
views (``events``, ``assays``, ``reclaim_cuts``, ``stack_passes``, ``lots``; see
:mod:`ledger.views`).  Several ledgers (one per site) may share a database.

Append-only in the database itself: a trigger refuses UPDATE, DELETE and TRUNCATE on
``event_log`` and ``quarantine``, even for their owner; on ``gaps`` it allows exactly
one change, closing an open gap (``closed_recorded_ns`` from NULL to a time).  Two
cluster-wide roles are created (NOLOGIN; grant them to login roles):

``stockpile_writer``
    SELECT, INSERT on the log and the quarantine; SELECT, INSERT and
    UPDATE(closed_recorded_ns) on gaps; SELECT, INSERT, UPDATE on ``ledger_meta``; it owns
    the views (a writer re-creates ``assays`` when the declared analytes grow).
``stockpile_reader``
    SELECT on every table and view.

No role of the product has UPDATE or DELETE on the log.

The views read like DuckDB's, so the README's SQL runs unchanged: times as ``*_ns``
BIGINT (exact) and as ``timestamp`` (UTC, microseconds, truncated), bodies as ``jsonb``,
``assays.unrecognised_analytes`` as a ``text[]``; the schema also defines the DuckDB
functions those queries use (``round(double precision, int)``, ``median``,
``quantile_cont``, ``list``, ``list_distinct``, ``flatten``, ``json_array_length`` of
a ``text[]``), so a client with the ledger's schema on its ``search_path`` can run them.
An analyte column holds the value under the declared spelling, else under another
spelling of it (white space trimmed, case ignored: ``lower``).
"""

from __future__ import annotations

import contextlib
import json
import re
from typing import Iterable
from urllib.parse import parse_qsl, urlencode, urlsplit, urlunsplit

import psycopg

from schemas.analytes import AnalytePolicy, key as analyte_key

from ledger import views

SCHEMA_VERSION = "pg1"
DEFAULT_SCHEMA = "stockpile"
WRITER_ROLE = "stockpile_writer"
READER_ROLE = "stockpile_reader"
#: the high 32 bits of the writer's advisory lock key (the low 32 are the schema's oid)
LOCK_CLASS = 0x53544B4C
#: the install lock's key (transaction-scoped): installs never run at once
INSTALL_LOCK = (LOCK_CLASS << 32) - 1

META_VIEWS_ANALYTES = "views_analytes"
TABLES = ("event_log", "gaps", "quarantine", "ledger_meta")
VIEWS = ("events", "assays", "reclaim_cuts", "stack_passes", "lots")

_SCHEMA_NAME = re.compile(r"[a-z_][a-z0-9_]{0,62}")


def check_schema_name(name: str) -> str:
    """``name`` when it is a plain lower-case SQL identifier (not ``pg_*``), else
    ValueError with a one-line reason."""
    if not _SCHEMA_NAME.fullmatch(name or "") or name.startswith("pg_"):
        raise ValueError(f"schema name {name!r} is not a plain SQL identifier: lower-case "
                         "letters, digits and _, not starting with a digit or pg_, at most 63")
    return name


def split_url(url: str) -> tuple[str, str]:
    """``(libpq URL, schema)``: ``url`` without this product's ``schema`` parameter, and
    that schema (default ``stockpile``); ValueError (one line) for a bad schema name."""
    parts = urlsplit(url)
    query = parse_qsl(parts.query, keep_blank_values=True)
    schemas = [v for k, v in query if k == "schema"]
    schema = check_schema_name(schemas[-1] if schemas else DEFAULT_SCHEMA)
    rest = urlencode([(k, v) for k, v in query if k != "schema"])
    return urlunsplit(parts._replace(query=rest)), schema


def describe_url(url: str) -> str:
    """``url`` without its password (and without other query parameters than schema)."""
    parts = urlsplit(url)
    host = parts.hostname or ""
    netloc = (f"{parts.username}@" if parts.username else "") + host
    with contextlib.suppress(ValueError):
        netloc += f":{parts.port}" if parts.port else ""
    schema = dict(parse_qsl(parts.query)).get("schema", DEFAULT_SCHEMA)
    return f"{parts.scheme}://{netloc}{parts.path}?schema={schema}"


def quoted(name: str) -> str:
    """``name`` as a quoted SQL identifier."""
    return '"' + name.replace('"', '""') + '"'


def _literal(text: str) -> str:
    return "'" + text.replace("'", "''") + "'"


def _in(schema: str, statements: Iterable[str]) -> list[str]:
    s = quoted(check_schema_name(schema))
    return [statement.replace("{s}", s) for statement in statements]


_ROLES = [f"""DO $$ BEGIN
    IF NOT EXISTS (SELECT FROM pg_roles WHERE rolname = '{role}') THEN
        CREATE ROLE {role} NOLOGIN;
    END IF;
EXCEPTION WHEN duplicate_object OR unique_violation THEN NULL;
END $$""" for role in (WRITER_ROLE, READER_ROLE)]

_TABLES = [
    "CREATE SCHEMA IF NOT EXISTS {s}",
    """CREATE TABLE IF NOT EXISTS {s}.ledger_meta (key text PRIMARY KEY, value text NOT NULL)""",
    """CREATE TABLE IF NOT EXISTS {s}.event_log (
        global_seq bigint NOT NULL,
        type text NOT NULL,
        source text NOT NULL,
        epoch bigint NOT NULL,
        seq bigint NOT NULL,
        valid_time_ns bigint NOT NULL,
        recorded_time_ns bigint NOT NULL,
        payload bytea NOT NULL,
        payload_sha256 bytea NOT NULL,
        chain_sha256 bytea NOT NULL,
        flags text,
        body jsonb,
        signer text,
        signature bytea,
        CONSTRAINT event_log_pkey PRIMARY KEY (global_seq),
        CONSTRAINT event_log_identity UNIQUE (source, epoch, seq)
    )""",
    # payloads and hashes are random-looking bytes: never worth compressing
    "ALTER TABLE {s}.event_log ALTER COLUMN payload SET STORAGE EXTERNAL",
    # as_of: ordered by (valid time, global seq), filtered by recorded time in the index
    """CREATE INDEX IF NOT EXISTS event_log_valid ON {s}.event_log
        (valid_time_ns, global_seq) INCLUDE (recorded_time_ns)""",
    "CREATE INDEX IF NOT EXISTS event_log_recorded ON {s}.event_log (recorded_time_ns)",
    "CREATE INDEX IF NOT EXISTS event_log_type ON {s}.event_log (type, global_seq)",
    """CREATE INDEX IF NOT EXISTS event_log_flagged ON {s}.event_log (global_seq)
        WHERE flags IS NOT NULL""",
    """CREATE TABLE IF NOT EXISTS {s}.gaps (
        gap_id bigint PRIMARY KEY,
        source text NOT NULL,
        epoch bigint NOT NULL,
        first_seq bigint NOT NULL,
        last_seq bigint NOT NULL,
        opened_recorded_ns bigint NOT NULL,
        closed_recorded_ns bigint
    )""",
    """CREATE TABLE IF NOT EXISTS {s}.quarantine (
        quarantine_id bigint PRIMARY KEY,
        recorded_time_ns bigint NOT NULL,
        type text NOT NULL,
        source text NOT NULL,
        epoch bigint,
        seq bigint,
        valid_time_ns bigint,
        code text NOT NULL,
        detail text NOT NULL,
        raw bytea NOT NULL,
        existing_global_seq bigint,
        after_global_seq bigint NOT NULL,
        chain_sha256 bytea NOT NULL
    )""",
]

_TRIGGERS = [
    """CREATE OR REPLACE FUNCTION {s}.refuse_change() RETURNS trigger LANGUAGE plpgsql AS $$
BEGIN
    RAISE EXCEPTION 'the ledger''s % is append-only: % refused', TG_TABLE_NAME, TG_OP
        USING ERRCODE = 'restrict_violation';
END $$""",
    """CREATE OR REPLACE FUNCTION {s}.only_close_gap() RETURNS trigger LANGUAGE plpgsql AS $$
BEGIN
    IF OLD.closed_recorded_ns IS NULL AND NEW.closed_recorded_ns IS NOT NULL
       AND (NEW.gap_id, NEW.source, NEW.epoch, NEW.first_seq, NEW.last_seq,
            NEW.opened_recorded_ns)
           IS NOT DISTINCT FROM (OLD.gap_id, OLD.source, OLD.epoch, OLD.first_seq,
                                 OLD.last_seq, OLD.opened_recorded_ns) THEN
        RETURN NEW;
    END IF;
    RAISE EXCEPTION 'the ledger''s gaps only close (closed_recorded_ns set once): UPDATE refused'
        USING ERRCODE = 'restrict_violation';
END $$""",
    """CREATE OR REPLACE TRIGGER append_only BEFORE UPDATE OR DELETE OR TRUNCATE
        ON {s}.event_log FOR EACH STATEMENT EXECUTE FUNCTION {s}.refuse_change()""",
    """CREATE OR REPLACE TRIGGER append_only BEFORE UPDATE OR DELETE OR TRUNCATE
        ON {s}.quarantine FOR EACH STATEMENT EXECUTE FUNCTION {s}.refuse_change()""",
    """CREATE OR REPLACE TRIGGER append_only BEFORE DELETE OR TRUNCATE
        ON {s}.gaps FOR EACH STATEMENT EXECUTE FUNCTION {s}.refuse_change()""",
    """CREATE OR REPLACE TRIGGER only_close BEFORE UPDATE
        ON {s}.gaps FOR EACH ROW EXECUTE FUNCTION {s}.only_close_gap()""",
]

# What the views use, and the DuckDB functions the README's SQL calls.
_FUNCTIONS = [
    # nanoseconds -> timestamp, exact to the microsecond (truncated), over the int64 range
    """CREATE OR REPLACE FUNCTION {s}.ns_timestamp(ns bigint) RETURNS timestamp
    LANGUAGE sql IMMUTABLE STRICT PARALLEL SAFE AS
    $$ SELECT TIMESTAMP '1970-01-01' + make_interval(days => (ns / 86400000000000)::int)
              + ((ns % 86400000000000) / 1000) * INTERVAL '1 microsecond' $$""",
    """CREATE OR REPLACE FUNCTION {s}.try_float8(t text) RETURNS double precision
    LANGUAGE plpgsql IMMUTABLE PARALLEL SAFE AS $$
BEGIN
    RETURN t::double precision;
EXCEPTION WHEN invalid_text_representation OR numeric_value_out_of_range THEN
    RETURN NULL;
END $$""",
    # a protobuf-JSON timestamp (RFC 3339, 'Z', up to 9 decimals) as timestamp, truncated
    """CREATE OR REPLACE FUNCTION {s}.try_timestamp(t text) RETURNS timestamp
    LANGUAGE plpgsql IMMUTABLE PARALLEL SAFE AS $$
BEGIN
    RETURN regexp_replace(rtrim(t, 'Z'), '(\\.[0-9]{6})[0-9]+$', '\\1')::timestamp;
EXCEPTION WHEN invalid_datetime_format OR datetime_field_overflow
          OR invalid_text_representation THEN
    RETURN NULL;
END $$""",
    # an analyte under its declared spelling, else under another spelling of it
    """CREATE OR REPLACE FUNCTION {s}.analyte_value(analytes jsonb, name text)
    RETURNS double precision LANGUAGE sql IMMUTABLE PARALLEL SAFE AS
    $$ SELECT {s}.try_float8(coalesce(analytes->>name,
           (SELECT e.value FROM jsonb_each_text(analytes) e
            WHERE lower(btrim(e.key)) = lower(btrim(name)) AND e.value IS NOT NULL
            ORDER BY e.key COLLATE "C" LIMIT 1))) $$""",
    """CREATE OR REPLACE FUNCTION {s}.unrecognised(analytes jsonb, declared_keys text[])
    RETURNS text[] LANGUAGE sql IMMUTABLE PARALLEL SAFE AS
    $$ SELECT coalesce(array_agg(k ORDER BY k COLLATE "C"), '{}')
       FROM jsonb_object_keys(CASE WHEN jsonb_typeof(analytes) = 'object' THEN analytes END) k
       WHERE NOT lower(btrim(k)) = ANY (declared_keys) $$""",
    # DuckDB's round(DOUBLE, INTEGER): in doubles, halves away from zero
    """CREATE OR REPLACE FUNCTION {s}.round(v double precision, digits integer)
    RETURNS double precision LANGUAGE sql IMMUTABLE STRICT PARALLEL SAFE AS
    $$ SELECT CASE WHEN v * m >= 0 THEN floor(v * m + 0.5) ELSE ceil(v * m - 0.5) END / m
       FROM (SELECT 10::double precision ^ digits AS m) AS p $$""",
    """CREATE OR REPLACE FUNCTION {s}.json_array_length(a text[]) RETURNS integer
    LANGUAGE sql IMMUTABLE STRICT PARALLEL SAFE AS $$ SELECT cardinality(a) $$""",
    """CREATE OR REPLACE FUNCTION {s}.flatten(a anyarray) RETURNS anyarray
    LANGUAGE sql IMMUTABLE STRICT PARALLEL SAFE AS $$ SELECT a $$""",
    """CREATE OR REPLACE FUNCTION {s}.list_distinct(a anyarray) RETURNS anyarray
    LANGUAGE sql IMMUTABLE STRICT PARALLEL SAFE AS
    $$ SELECT ARRAY(SELECT DISTINCT x FROM unnest(a) x WHERE x IS NOT NULL) $$""",
    """CREATE OR REPLACE FUNCTION {s}.list_append(state anyarray, value anynonarray)
    RETURNS anyarray LANGUAGE sql IMMUTABLE PARALLEL SAFE AS
    $$ SELECT array_append(state, value) $$""",
    """CREATE OR REPLACE FUNCTION {s}.list_concat(state anyarray, value anyarray)
    RETURNS anyarray LANGUAGE sql IMMUTABLE PARALLEL SAFE AS
    $$ SELECT array_cat(state, value) $$""",
    """CREATE OR REPLACE AGGREGATE {s}.list(anynonarray) (
        SFUNC = {s}.list_append, STYPE = anyarray)""",
    # a list of lists is kept flat (PostgreSQL arrays are not ragged); flatten() is then
    # the identity
    """CREATE OR REPLACE AGGREGATE {s}.list(anyarray) (
        SFUNC = {s}.list_concat, STYPE = anyarray)""",
    # quantiles: the state is [fraction, value, value, ...]
    """CREATE OR REPLACE FUNCTION {s}.quantile_add(state double precision[],
        v double precision, q double precision) RETURNS double precision[]
    LANGUAGE sql IMMUTABLE PARALLEL SAFE AS
    $$ SELECT CASE WHEN v IS NULL THEN state WHEN state IS NULL THEN ARRAY[q, v]
                   ELSE state || v END $$""",
    """CREATE OR REPLACE FUNCTION {s}.median_add(state double precision[],
        v double precision) RETURNS double precision[]
    LANGUAGE sql IMMUTABLE PARALLEL SAFE AS
    $$ SELECT {s}.quantile_add(state, v, 0.5) $$""",
    """CREATE OR REPLACE FUNCTION {s}.quantile_final(state double precision[])
    RETURNS double precision LANGUAGE sql IMMUTABLE PARALLEL SAFE AS
    $$ SELECT percentile_cont(state[1]) WITHIN GROUP (ORDER BY v)
       FROM unnest(state[2:]) v $$""",
    """CREATE OR REPLACE AGGREGATE {s}.median(double precision) (
        SFUNC = {s}.median_add, STYPE = double precision[],
        FINALFUNC = {s}.quantile_final)""",
    """CREATE OR REPLACE AGGREGATE {s}.quantile_cont(double precision, double precision) (
        SFUNC = {s}.quantile_add, STYPE = double precision[],
        FINALFUNC = {s}.quantile_final)""",
]


def _float(expr: str) -> str:
    return f"coalesce({{s}}.try_float8({expr}), 0)"


_FIXED_VIEWS = {
    "events": """CREATE OR REPLACE VIEW {s}.events AS
    SELECT global_seq, type, source, epoch, seq,
        {s}.ns_timestamp(valid_time_ns) AS valid_time, valid_time_ns,
        {s}.ns_timestamp(recorded_time_ns) AS recorded_time, recorded_time_ns,
        octet_length(payload) AS payload_bytes, encode(payload_sha256, 'hex') AS payload_sha256,
        encode(chain_sha256, 'hex') AS chain_sha256, flags, body
    FROM {s}.event_log""",
    "reclaim_cuts": f"""CREATE OR REPLACE VIEW {{s}}.reclaim_cuts AS
    SELECT global_seq, source,
        body->>'pile_id' AS pile_id, body->>'cut_id' AS cut_id,
        body->>'bench_id' AS bench_id, body->>'machine_id' AS machine_id,
        {{s}}.try_timestamp(body->>'start_time') AS start_time,
        {{s}}.ns_timestamp(valid_time_ns) AS end_time,
        {{s}}.ns_timestamp(recorded_time_ns) AS recorded_time,
        {_float("body->>'travel_m'")} AS travel_m,
        {_float("body->>'luff_rad'")} AS luff_rad,
        {_float("body->>'slew_start_rad'")} AS slew_start_rad,
        {_float("body->>'slew_end_rad'")} AS slew_end_rad,
        {_float("body->>'tonnes'")} AS belt_tonnes,
        {_float("body->>'bad_samples'")}::bigint AS bad_samples
    FROM {{s}}.event_log WHERE type = 'reclaim_cut'""",
    "stack_passes": f"""CREATE OR REPLACE VIEW {{s}}.stack_passes AS
    WITH s AS (SELECT * FROM {{s}}.event_log WHERE type = 'stack_started'),
         e AS (SELECT * FROM {{s}}.event_log WHERE type = 'stack_ended')
    SELECT s.body->>'pile_id' AS pile_id, s.body->>'pass_id' AS pass_id,
        s.body->>'lot_id' AS lot_id, s.body->>'machine_id' AS machine_id,
        s.body->>'pattern' AS pattern,
        {_float("s.body->>'start_y_m'")} AS start_y_m,
        {_float("s.body->>'end_y_m'")} AS end_y_m,
        {{s}}.ns_timestamp(s.valid_time_ns) AS started,
        {{s}}.ns_timestamp(e.valid_time_ns) AS ended,
        {_float("e.body->>'tonnes'")} AS belt_tonnes,
        s.global_seq AS started_global_seq, e.global_seq AS ended_global_seq,
        {_float("e.body->>'bad_samples'")}::bigint AS bad_samples
    FROM s LEFT JOIN e ON s.body->>'pile_id' = e.body->>'pile_id'
                      AND s.body->>'pass_id' = e.body->>'pass_id'""",
    "lots": f"""CREATE OR REPLACE VIEW {{s}}.lots AS
    SELECT global_seq, body->>'lot_id' AS lot_id, body->>'origin' AS origin,
        {{s}}.ns_timestamp(valid_time_ns) AS declared,
        {_float("body->>'planned_tonnes'")} AS planned_tonnes,
        body->'planned_grade' AS planned_grade
    FROM {{s}}.event_log WHERE type = 'lot_declared'""",
}


def _assays_view(declared: tuple[str, ...]) -> str:
    """The ``assays`` view with a column per declared analyte (the column names of
    :data:`ledger.views.ASSAY_FIXED_COLUMNS` first)."""
    views.check_declared(declared)
    analyte_columns = "".join(
        f",\n        {{s}}.analyte_value(body->'analytes', {_literal(name)}) AS {quoted(name)}"
        for name in declared)
    keys = "ARRAY[" + ", ".join(_literal(analyte_key(n)) for n in declared) + "]::text[]"
    return f"""CREATE VIEW {{s}}.assays AS
    SELECT a.global_seq, a.source,
        body->>'assay_id' AS assay_id,
        body->>'lot_id' AS lot_id,
        body->>'lab_id' AS lab_id,
        coalesce(body->>'status', 'ASSAY_STATUS_UNSPECIFIED') AS status,
        nullif(body->>'supersedes', '') AS supersedes,
        {{s}}.try_timestamp(body->>'window_start') AS window_start,
        {{s}}.ns_timestamp(valid_time_ns) AS window_end,
        {{s}}.try_timestamp(body->>'reported_time') AS reported_time,
        {{s}}.ns_timestamp(recorded_time_ns) AS recorded_time,
        valid_time_ns, recorded_time_ns,
        (recorded_time_ns - valid_time_ns)::double precision / 3.6e12 AS lateness_h,
        {_float("body->>'moisture_pct'")} AS moisture_pct,
        {_float("body->>'bulk_density_t_m3'")} AS bulk_density_t_m3,
        EXISTS (SELECT 1 FROM {{s}}.event_log s WHERE s.type = 'assay'
                AND s.body->>'supersedes' = a.body->>'assay_id') AS superseded,
        coalesce(flags LIKE '%unknown_lot%', false) AS unknown_lot_when_recorded{analyte_columns},
        {{s}}.unrecognised(body->'analytes', {keys}) AS unrecognised_analytes
    FROM {{s}}.event_log a WHERE type = 'assay'"""


def assays_statements(schema: str, declared: tuple[str, ...]) -> list[str]:
    """(Re)create ``assays`` for ``declared`` (inside a transaction): dropped and made
    again, owned by the writer role, readable by the reader role."""
    return _in(schema, [
        "DROP VIEW IF EXISTS {s}.assays",
        _assays_view(declared),
        f"ALTER VIEW {{s}}.assays OWNER TO {WRITER_ROLE}",
        f"GRANT SELECT ON {{s}}.assays TO {READER_ROLE}",
    ])


def _grants() -> list[str]:
    w, r = WRITER_ROLE, READER_ROLE
    statements = [
        f"GRANT USAGE ON SCHEMA {{s}} TO {w}, {r}",
        f"GRANT CREATE ON SCHEMA {{s}} TO {w}",  # it re-creates the assays view
        f"GRANT SELECT, INSERT ON {{s}}.event_log, {{s}}.quarantine TO {w}",
        f"GRANT SELECT, INSERT ON {{s}}.gaps TO {w}",
        f"GRANT UPDATE (closed_recorded_ns) ON {{s}}.gaps TO {w}",
        f"GRANT SELECT, INSERT, UPDATE ON {{s}}.ledger_meta TO {w}",
        f"GRANT SELECT ON {', '.join('{s}.' + t for t in TABLES)} TO {r}",
    ]
    for view in _FIXED_VIEWS:
        statements += [f"ALTER VIEW {{s}}.{view} OWNER TO {w}",
                       f"GRANT SELECT ON {{s}}.{view} TO {r}"]
    return statements


def schema_oid(con: psycopg.Connection, schema: str) -> int | None:
    """The oid of ``schema`` in the connected database, or None when it is missing."""
    row = con.execute("SELECT oid::bigint FROM pg_namespace WHERE nspname = %s",
                      [schema]).fetchone()
    return None if row is None else row[0]


def views_analytes(con: psycopg.Connection, schema: str) -> tuple[str, ...] | None:
    """The declared list the ``assays`` view was made for (None: not recorded)."""
    row = con.execute(f"SELECT value FROM {quoted(schema)}.ledger_meta WHERE key = %s",
                      [META_VIEWS_ANALYTES]).fetchone()
    return None if row is None else tuple(json.loads(row[0]))


def install_statements(schema: str) -> list[str]:
    """Every statement of an install but the ``assays`` view (idempotent)."""
    return _ROLES + _in(schema, _TABLES + _TRIGGERS + _FUNCTIONS
                        + list(_FIXED_VIEWS.values()) + _grants())


def install_on(con: psycopg.Connection, schema: str = DEFAULT_SCHEMA) -> None:
    """Install (or bring up to date) the ledger ``schema`` over ``con`` in one
    transaction: roles, tables, triggers, functions, views, grants.  Idempotent; the
    ``assays`` view keeps the analytes it was made for (the default list at first)."""
    check_schema_name(schema)
    with con.transaction():
        con.execute("SELECT pg_advisory_xact_lock(%s)", [INSTALL_LOCK])
        for statement in install_statements(schema):
            con.execute(statement)
        declared = views_analytes(con, schema) or AnalytePolicy().declared
        for statement in assays_statements(schema, declared):
            con.execute(statement)
        meta = f"{quoted(schema)}.ledger_meta"
        con.execute(f"INSERT INTO {meta} VALUES ('schema_version', %s) ON CONFLICT DO NOTHING",
                    [SCHEMA_VERSION])
        con.execute(f"INSERT INTO {meta} VALUES (%s, %s) ON CONFLICT DO NOTHING",
                    [META_VIEWS_ANALYTES, json.dumps(list(declared))])


def may_install(con: psycopg.Connection) -> bool:
    """Whether the connected user may install a ledger: a superuser, or a role that may
    create roles and schemas in this database."""
    row = con.execute(
        "SELECT rolsuper OR (rolcreaterole AND has_database_privilege(current_database(), "
        "'CREATE')) FROM pg_roles WHERE rolname = current_user").fetchone()
    return bool(row and row[0])
