"""Typed SQL views over the raw ``event_log`` table, for auditors (DuckDB backend).

Times appear twice: ``*_ns`` (UTC nanoseconds, exact) and as ``TIMESTAMP_NS``
(UTC, no zone) for reading.  Domain events keep their protobuf JSON body in
``event_log.body``; the views unpack it.

==================  =====================================================================
view                one row per
==================  =====================================================================
``events``          stored event (identity, times, payload size and hash, flags, body)
``assays``          assay, one DOUBLE column per declared analyte (``"Fe"``, ``"SiO2"``
                    ...), the undeclared names it gives (``unrecognised_analytes``, JSON),
                    lateness in hours, whether it was superseded
``reclaim_cuts``    reclaim cut (travel, luff, slew range, belt-scale tonnes, PLC samples
                    with bad or uncertain status during it)
``stack_passes``    stacking pass (start joined with its end, when it has one; the end's
                    bad-status sample count)
``lots``            declared lot (planned tonnes, planned grade as JSON)
==================  =====================================================================

The analyte columns of ``assays`` are the ledger's declared analyte list
(:mod:`schemas.analytes`, recorded in ``ledger_meta``), never names from data: each is
the value under the declared spelling or any other stored spelling of it (``FE`` counts
as ``Fe``).  A name on no list is only listed in ``unrecognised_analytes``.  A declared
name that would collide with a fixed column is refused.  The writer recreates the views
when a new spelling first appears, and when the declared list grows.
"""

from __future__ import annotations

import json
from typing import TYPE_CHECKING, Iterable

from schemas.analytes import AnalytePolicy, key as analyte_key

if TYPE_CHECKING:  # only for annotations: importing the views' rules stays light
    import duckdb

#: The ``assays`` view's columns that are not analytes (no declared analyte may be named so).
ASSAY_FIXED_COLUMNS: tuple[str, ...] = (
    "global_seq", "source", "assay_id", "lot_id", "lab_id", "status", "supersedes",
    "window_start", "window_end", "reported_time", "recorded_time", "valid_time_ns",
    "recorded_time_ns", "lateness_h", "moisture_pct", "bulk_density_t_m3", "superseded",
    "unknown_lot_when_recorded", "unrecognised_analytes",
)

_META_ANALYTES = "analytes"
_META_UNKNOWN = "unknown_analyte"


def _ts(expr: str) -> str:
    """A protobuf-JSON timestamp string (RFC 3339, 'Z') as TIMESTAMP_NS."""
    return f"TRY_CAST(rtrim({expr}, 'Z') AS TIMESTAMP_NS)"


def _quote(name: str) -> str:
    return '"' + name.replace('"', '""') + '"'


def _literal(text: str) -> str:
    return "'" + text.replace("'", "''") + "'"


def stored_analytes(con: duckdb.DuckDBPyConnection) -> set[str]:
    """Every analyte name that appears in a stored assay."""
    rows = con.execute(
        "SELECT DISTINCT unnest(json_keys(body->'analytes')) FROM event_log "
        "WHERE type = 'assay' AND body IS NOT NULL").fetchall()
    return {r[0] for r in rows if r[0]}


def check_declared(declared: Iterable[str]) -> None:
    """Raise ValueError (one line) when a declared analyte would collide with a fixed
    column of the ``assays`` view (SQL names ignore case)."""
    fixed = {c.casefold() for c in ASSAY_FIXED_COLUMNS}
    for name in declared:
        if name.casefold() in fixed or analyte_key(name) in fixed:
            raise ValueError(f"declared analyte {name!r} collides with the assays view's "
                             f"column {name.strip().lower()!r}; rename it")


def recorded_policy(con: duckdb.DuckDBPyConnection) -> AnalytePolicy | None:
    """The analyte list and unknown-analyte policy the ledger recorded (None: none yet)."""
    rows = dict(con.execute("SELECT key, value FROM ledger_meta WHERE key IN (?, ?)",
                            [_META_ANALYTES, _META_UNKNOWN]).fetchall())
    if _META_ANALYTES not in rows:
        return None
    try:
        names = json.loads(rows[_META_ANALYTES])
        if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
            raise ValueError("not a JSON list of names")
        return AnalytePolicy(tuple(names), rows.get(_META_UNKNOWN, "flag"))
    except ValueError as exc:
        raise ValueError(f"the ledger's recorded analyte list (ledger_meta) is damaged: "
                         f"{exc}") from None


def record_policy(con: duckdb.DuckDBPyConnection, policy: AnalytePolicy) -> None:
    """Store ``policy`` in ``ledger_meta`` (inside the caller's transaction)."""
    con.execute("DELETE FROM ledger_meta WHERE key IN (?, ?)", [_META_ANALYTES, _META_UNKNOWN])
    con.execute("INSERT INTO ledger_meta VALUES (?, ?), (?, ?)",
                [_META_ANALYTES, json.dumps(list(policy.declared)), _META_UNKNOWN, policy.unknown])


def _analyte_columns(declared: Iterable[str], stored: Iterable[str]) -> str:
    """The ``assays`` columns of the declared analytes and ``unrecognised_analytes``."""
    by_key: dict[str, list[str]] = {}
    for name in sorted(stored):
        by_key.setdefault(analyte_key(name), []).append(name)
    columns = []
    known: list[str] = []
    for name in declared:
        spellings = [name] + [s for s in by_key.get(analyte_key(name), []) if s != name]
        known += spellings
        values = ", ".join(f"body->'analytes'->>{_literal(s)}" for s in spellings)
        value = f"coalesce({values})" if len(spellings) > 1 else values
        columns.append(f",\n        TRY_CAST({value} AS DOUBLE) AS {_quote(name)}")
    known_list = "[" + ", ".join(_literal(s) for s in known) + "]::VARCHAR[]"
    columns.append(
        ",\n        coalesce(to_json(list_filter(json_keys(body->'analytes'), "
        f"lambda k: NOT list_contains({known_list}, k))), '[]')::JSON AS unrecognised_analytes")
    return "".join(columns)


def view_statements(declared: Iterable[str], stored: Iterable[str] = ()) -> list[str]:
    """``CREATE OR REPLACE VIEW`` statements for every auditor view: ``assays`` with a
    column per ``declared`` analyte, read from any of the ``stored`` spellings of it."""
    declared = tuple(declared)
    check_declared(declared)
    analyte_columns = _analyte_columns(declared, stored)
    return [
        """CREATE OR REPLACE VIEW events AS
    SELECT global_seq, type, source, epoch, seq,
        make_timestamp_ns(valid_time_ns) AS valid_time, valid_time_ns,
        make_timestamp_ns(recorded_time_ns) AS recorded_time, recorded_time_ns,
        octet_length(payload) AS payload_bytes, lower(hex(payload_sha256)) AS payload_sha256,
        lower(hex(chain_sha256)) AS chain_sha256, flags, body
    FROM event_log""",
        f"""CREATE OR REPLACE VIEW assays AS
    SELECT a.global_seq, a.source,
        body->>'assay_id' AS assay_id,
        body->>'lot_id' AS lot_id,
        body->>'lab_id' AS lab_id,
        coalesce(body->>'status', 'ASSAY_STATUS_UNSPECIFIED') AS status,
        nullif(body->>'supersedes', '') AS supersedes,
        {_ts("body->>'window_start'")} AS window_start,
        make_timestamp_ns(valid_time_ns) AS window_end,
        {_ts("body->>'reported_time'")} AS reported_time,
        make_timestamp_ns(recorded_time_ns) AS recorded_time,
        valid_time_ns, recorded_time_ns,
        (recorded_time_ns - valid_time_ns) / 3.6e12 AS lateness_h,
        coalesce(TRY_CAST(body->>'moisture_pct' AS DOUBLE), 0) AS moisture_pct,
        coalesce(TRY_CAST(body->>'bulk_density_t_m3' AS DOUBLE), 0) AS bulk_density_t_m3,
        EXISTS (SELECT 1 FROM event_log s WHERE s.type = 'assay'
                AND s.body->>'supersedes' = a.body->>'assay_id') AS superseded,
        coalesce(flags LIKE '%unknown_lot%', false) AS unknown_lot_when_recorded{analyte_columns}
    FROM event_log a WHERE type = 'assay'""",
        """CREATE OR REPLACE VIEW reclaim_cuts AS
    SELECT global_seq, source,
        body->>'pile_id' AS pile_id, body->>'cut_id' AS cut_id,
        body->>'bench_id' AS bench_id, body->>'machine_id' AS machine_id,
        """ + _ts("body->>'start_time'") + """ AS start_time,
        make_timestamp_ns(valid_time_ns) AS end_time,
        make_timestamp_ns(recorded_time_ns) AS recorded_time,
        coalesce(TRY_CAST(body->>'travel_m' AS DOUBLE), 0) AS travel_m,
        coalesce(TRY_CAST(body->>'luff_rad' AS DOUBLE), 0) AS luff_rad,
        coalesce(TRY_CAST(body->>'slew_start_rad' AS DOUBLE), 0) AS slew_start_rad,
        coalesce(TRY_CAST(body->>'slew_end_rad' AS DOUBLE), 0) AS slew_end_rad,
        coalesce(TRY_CAST(body->>'tonnes' AS DOUBLE), 0) AS belt_tonnes,
        coalesce(TRY_CAST(body->>'bad_samples' AS BIGINT), 0) AS bad_samples
    FROM event_log WHERE type = 'reclaim_cut'""",
        """CREATE OR REPLACE VIEW stack_passes AS
    WITH s AS (SELECT * FROM event_log WHERE type = 'stack_started'),
         e AS (SELECT * FROM event_log WHERE type = 'stack_ended')
    SELECT s.body->>'pile_id' AS pile_id, s.body->>'pass_id' AS pass_id,
        s.body->>'lot_id' AS lot_id, s.body->>'machine_id' AS machine_id,
        s.body->>'pattern' AS pattern,
        coalesce(TRY_CAST(s.body->>'start_y_m' AS DOUBLE), 0) AS start_y_m,
        coalesce(TRY_CAST(s.body->>'end_y_m' AS DOUBLE), 0) AS end_y_m,
        make_timestamp_ns(s.valid_time_ns) AS started,
        make_timestamp_ns(e.valid_time_ns) AS ended,
        coalesce(TRY_CAST(e.body->>'tonnes' AS DOUBLE), 0) AS belt_tonnes,
        s.global_seq AS started_global_seq, e.global_seq AS ended_global_seq,
        coalesce(TRY_CAST(e.body->>'bad_samples' AS BIGINT), 0) AS bad_samples
    FROM s LEFT JOIN e ON s.body->>'pile_id' = e.body->>'pile_id'
                      AND s.body->>'pass_id' = e.body->>'pass_id'""",
        """CREATE OR REPLACE VIEW lots AS
    SELECT global_seq, body->>'lot_id' AS lot_id, body->>'origin' AS origin,
        make_timestamp_ns(valid_time_ns) AS declared,
        coalesce(TRY_CAST(body->>'planned_tonnes' AS DOUBLE), 0) AS planned_tonnes,
        body->'planned_grade' AS planned_grade
    FROM event_log WHERE type = 'lot_declared'""",
    ]


def create_views(con: duckdb.DuckDBPyConnection, declared: Iterable[str],
                 stored: Iterable[str] = ()) -> None:
    """(Re)create every view; call inside the writer's transaction."""
    for statement in view_statements(declared, stored):
        con.execute(statement)
